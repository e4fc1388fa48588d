"""Evaluation against ground truth: per-pair errors, drift, ATE (metrics are pure), and the
evaluation report with its plots."""
