"""The building blocks that the four models compose: the shared BEV encoder (camera, LiDAR, fusion) and its
ResNet, deformable attention, the query decoder, the raster head, and their matcher and dense targets."""
