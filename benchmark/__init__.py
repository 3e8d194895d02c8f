"""Graph reconstruction (Path2Graph, Piece2Graph, Pixel2Graph), lane-graph metrics, speed and reports."""
