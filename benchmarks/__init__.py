"""The laboratory: benchmarks, studies and diagnostics of spindle-chtc, outside the product's wheel.

Run a benchmark as ``python -m benchmarks NAME [options]`` (``python -m benchmarks --help`` lists them;
``benchmarks.cli``). A benchmark prints figures, it is not a test (``benchmarks.targets``).

- ``benchmarks/<name>.py``: one module per benchmark (``add_arguments(parser)``, ``main(args) -> int``) and
  its helpers;
- ``benchmarks/studies/``: the model's studies (mesh, growth, estimator cost) and the MLR peer of the
  commission bench, each ``python -m benchmarks.studies.<name>``;
- ``benchmarks/diag27/``: the issue-27 diagnostic scripts (their README).

Benchmarks may import anything (the product, the simulator, the plant); nothing in the product imports them
(``tests/test_layers.py``).
"""
