"""Tools that run from a checkout, never installed: speed benchmarks of every layer (`make bench*`), the GPU
acceptance check (`make gpu-check`) and the decoder diagnosis; each is `python -m tools.NAME`."""
