"""Learners beyond the paper: the same algorithms with training-only signals or a position belief."""
