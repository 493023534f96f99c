"""Evaluation utilities: trajectory metrics (see :mod:`kpflow.eval.metrics`)."""
