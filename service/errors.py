"""The root of the service layer's typed error tree.

Every exception class defined in ``service/`` derives from :class:`ServiceError` (``tests/test_layers.py``
checks it); builtin bases (``ValueError``, ``LookupError``, ...) are kept beside it, so ``except ValueError``
still works where a caller relies on it. Each package keeps its errors in its own modules; the tree::

    ServiceError(Exception)                                  service.errors: root of every error in service/
    ├── NotFoundError(ServiceError, LookupError)             ┐ service.serve.interface: what the service
    ├── NoDataYetError(ServiceError)                         │ answers the API; api/errors.py maps these
    ├── BusyError(ServiceError)                              │ to HTTP codes (404, 503, 409, 503) in one
    ├── NotReadyError(ServiceError)                          ┘ place, any other ServiceError to a 500
    ├── RecordError(ServiceError, ValueError)                service.contracts.errors: a record breaks its
    │                                                        contract (names the record and the field)
    ├── DatabaseError(ServiceError)                          service.store.errors (its tree is drawn there):
    │   ├── DatabaseUnavailableError(DatabaseError, ConnectionError)   down, locked, not migrated: retry
    │   │   ├── DatabaseBusyError(DatabaseUnavailableError)            every API read slot is taken
    │   │   ├── DatabaseTimeoutError(DatabaseUnavailableError, TimeoutError)  a read did not answer
    │   │   └── SchemaError(DatabaseUnavailableError)                  schema missing or old: --migrate
    │   ├── RecordNotFoundError(DatabaseError, LookupError)            unknown id
    │   └── RecordRejectedError(DatabaseError, RecordError)            the database refuses a record
    │       └── StoredCalibrationError(RecordRejectedError)  service.store.calibrations: unusable stored row
    ├── LiveStateError(ServiceError, RuntimeError)           service.estimate.live: no state/snapshot yet
    │   └── StateConverging(LiveStateError)                  service.core.jobs: filter not converged
    ├── GrowthEstimateError(ServiceError, ValueError)        service.estimate.growth
    ├── DetectorError(ServiceError, ValueError)              service.identify.detector: bad configuration
    ├── SchedulerError(ServiceError, ValueError)             service.identify.scheduler: bad configuration
    ├── SpeedMapError(ServiceError, ValueError)              service.identify.speedmap
    ├── InsufficientWindowError(ServiceError, ValueError)    service.identify.window: too few usable data
    ├── WorkerError(ServiceError, RuntimeError)              service.identify.worker: the worker process
    ├── JobCancelled(ServiceError)                           service.identify.worker: a job stopped on request
    ├── CoreError(ServiceError, ValueError)                  service.core.machine: an event the core refuses
    ├── SettingsError(ServiceError, ValueError)              service.settings: names the key
    ├── CommandError(ServiceError, ValueError)               service.commands._common: a CLI user error
    ├── ProfileError(ServiceError, ValueError)               service.commands.simulate: a bad profile file
    ├── OutletError(ServiceError, RuntimeError)              service.serve.errors: an outlet (REST, OPC UA,
    │                                                        MQTT) cannot be loaded, configured or started
    └── ServedError(ServiceError, RuntimeError)              simulator.served: the test rig's service

The layers below (``model.errors.ModelError``, ``drivers.errors.DriverError``) keep their own roots: the
service translates them where it calls them (a job's failure becomes its stored outcome,
``service.identify.worker.job_outcome_of``), or lets them through unchanged where they name the bad input.
The store never raises an API error: ``service.shell.archive`` turns a database that cannot answer into
``NotReadyError`` (503) for the API.
"""

from __future__ import annotations

__all__ = ["ServiceError"]


class ServiceError(Exception):
    """Base of every error raised by ``service/``."""
