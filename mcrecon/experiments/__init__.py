"""Experiments that produce figures and tables: convergence, error rates, stability, statistics."""
