"""The domain's words: the value types the service's packages hand each other, below all of them (as asyncua
keeps its types in ``ua/`` below client and server).

- ``snapshots``: what the service serves (``ChtcSnapshot``, ``IdentificationRecord``, ``ChtcMapSnapshot``,
  ``CompensationSnapshot``, ``FieldSnapshot``, ``SensorReading``, ``ConditionSnapshot``, ...); ``health``
  (``DeviceHealth``, ``HealthSnapshot``, ``Readiness``); ``metrics`` (``MetricsSnapshot`` and its parts);
  ``verdict``: the served-value policy's vocabulary (``Verdict``, ``Reason``, ``ChtcStatus``);
- ``records``: the plain, immutable records the core emits and the writer stores (``IdentificationData``,
  ``ConditionStart``, ``SampleData``, ...; ``Record``, every type the store writes); ``columns``: what a
  stored column holds and the conversions every record shares; ``outcome``: what became of an identification;
- the domain objects stored as they are (each with ``values()``, its row): ``calibration`` (the sensor-offset
  baseline), ``checkpoint`` (the live state's), ``reference`` (the compensation zero), ``mechanics`` (a
  commissioning), ``probe`` (a probe reading); ``growth``: the served growth and its controller values;
  ``mode``: the identification mode;
- ``errors``: ``RecordError`` and the service protocol's failures (``NotFoundError``, ``NotReadyError``, ...).

A contract depends on nothing above it: these modules import the standard library, numpy, the model,
``service.errors`` and each other, never another service package, a driver or ``api``; no I/O
(``tests/test_layers.py``).
"""
