"""The lane-graph metric (docs/METRICS.md): TOPO, Junction TOPO and mIoU of a predicted graph against the
ground truth, and bootstrap intervals over frames.

In the order of the definition's steps: params.py (thresholds, METRIC_VERSION), densify.py,
candidates.py, matching.py, reach.py (the per-pair kernels), totals.py (the sums and scores, where the
steps are assembled), iou.py (mIoU), bootstrap.py (intervals over the per-frame counts).
"""
