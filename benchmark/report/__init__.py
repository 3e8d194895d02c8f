"""`cli report` and `cli viz`: the comparison tables and pictures of finished runs, with the paper's
published tables beside them."""
