"""Evaluation: success metrics aggregated into the paper's tables."""
