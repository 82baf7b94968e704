"""The robustness bench (issue 40 parts 1, 2, 6): the product against regression peers on scenarios the
thermal test never saw (``benchmarks.robustness.bench``). ``python -m benchmarks robustness [options]`` or
``python -m benchmarks.robustness [options]``."""

from benchmarks.robustness.bench import add_arguments
from benchmarks.robustness.bench import run as main

__all__ = ["add_arguments", "main"]
