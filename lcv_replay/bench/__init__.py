"""Benchmarks behind ``lcv-replay bench ...``: pure functions that measure, score and report."""
