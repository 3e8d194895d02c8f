"""Lane graphs scored: reconstruction from each representation (graphs/), the metric (metric/), `cli score`
(formats/ reads, score.py scores) and `cli report` (report/)."""
