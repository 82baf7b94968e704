"""Simulated devices for tests, ``chtc demo``, ``chtc simulate`` and replays (see docs/design/simulation.md).

- ``source``: ``Timeline`` (what a ``model.plant.PlantRun`` offers), ``ArrayTimeline``, ``TimelineSource``
  (simulated time = speed-up × injected wall clock);
- ``modbus_server``: ``SimulatedDaq``, the Modbus TCP temperature DAQ (pymodbus server, read-only);
- ``can_node``: ``SimulatedCanNode``, the ``SpindleStatus`` sender on any python-can bus;
- ``can_hub``: ``CanHub``, a python-can-remote server so other processes hear the node;
- ``faults``: ``Fault``, ``FaultKind``, ``FaultController``, ``parse_fault``;
- ``replay``: ``Replay`` (temperature CSV + CAN log through the simulators), ``CanReplayer``.

Nothing here opens a socket or a bus at import time.
"""
