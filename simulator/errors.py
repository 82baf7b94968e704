"""The simulator's error tree (the virtual spindle the demo, ``chtc simulate`` and the tests drive)::

    ServiceError (service.errors)
    └── SimulatorError
        ├── RigProcessError (+ RuntimeError)   simulator.rigproc: a rig's process failed to start or died
        └── ServedError (+ RuntimeError)       simulator.served: a served simulated service failed

It derives from the service's root, so a tool that catches ``ServiceError`` reports these the same way.
"""

from __future__ import annotations

from service.errors import ServiceError

__all__ = ["SimulatorError"]


class SimulatorError(ServiceError):
    """Every error the simulator raises."""
