"""Studies of the model (mesh, growth, estimator cost) and the literature's MLR peer: research code the
product does not run. Each with a command line runs as ``python -m benchmarks.studies.<name>``."""
