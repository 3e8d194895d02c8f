"""Models: the shared BEV encoder, the decoders of each family, losses and training."""
