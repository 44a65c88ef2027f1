"""Benchmarks behind ``fgslam bench ...``: one module per benchmark, plain-data results."""
