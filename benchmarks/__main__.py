"""``python -m benchmarks NAME [options]`` (``benchmarks.cli``)."""

from benchmarks.cli import main

raise SystemExit(main())
