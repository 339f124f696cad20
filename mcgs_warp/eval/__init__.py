"""Evaluation: trajectory error (ATE, RPE), image metrics, plots."""
