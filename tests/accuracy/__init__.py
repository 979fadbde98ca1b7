"""Accuracy against ground truth: estimators scored on synthetic scenes, and the figures the README quotes."""
