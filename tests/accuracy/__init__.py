"""Accuracy against ground truth: estimators scored on synthetic scenes, and the figures docs/accuracy.md quotes."""
