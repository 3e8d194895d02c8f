"""Data side: dataset adapters, cropping to the ego frame, graph representations, Parquet I/O."""
