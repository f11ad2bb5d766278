"""Evaluation on the test split, threshold diagnostics, and batched inference of student checkpoints."""
