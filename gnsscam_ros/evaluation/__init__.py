"""Evaluation: filter runs against ground truth, metrics, tables, plots, benchmarks."""
