"""What hosts the service in a process: ``runtime.Runtime`` (one spindle assembled from ``Settings``: devices,
acquisition, core, shell, worker, database, outlets), ``fleet.Host`` (several spindles in one process,
docs/design/fleet.md) and ``persistence`` (migrate, restore the last run, gate the writer;
docs/design/persistence.md). Nothing in ``service.core`` or ``service.shell`` imports it
(tests/test_layers.py).
"""
