"""Honest splits: which split each frame is prepared into (plan.py: the dataset's own, split files, or the
geographic scheme of geographic.py), and how close each non-training split lies to training (leakage.py)."""
