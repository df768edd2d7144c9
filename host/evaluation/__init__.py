"""Evaluation: trajectory metrics, report.json, plots, and running an estimator over a sequence."""
