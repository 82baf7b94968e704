"""The robustness bench (issue 40 parts 1, 2, 6): the product against regression peers on scenarios the
thermal test never saw (``benchmarks.robustness.bench``)."""
