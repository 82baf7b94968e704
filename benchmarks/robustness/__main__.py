"""``python -m benchmarks.robustness --seeds N --json`` (``benchmarks.robustness.bench``)."""

import sys

from benchmarks.robustness.bench import main

sys.exit(main())
