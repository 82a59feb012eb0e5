"""Evaluation: pure functions from a verification result (and the log's truth) to metrics.

* :mod:`~lcv_replay.evaluation.truth`: which constraints are true (labels, else ground truth).
* :mod:`~lcv_replay.evaluation.metrics`: precision/recall, ATE with SE(2) alignment, latency,
  per-window metrics, and :func:`~lcv_replay.evaluation.metrics.evaluate` for a whole run.
"""
