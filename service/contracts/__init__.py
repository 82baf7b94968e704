"""The types the service's packages hand each other, below all of them.

- ``records``: the plain, immutable records the core emits, the writer stores and the views serve
  (``IdentificationData``, ``ConditionStart``, ``SampleData``, ...);
- ``outcome``: what became of an identification (``Outcome``, the stored values);
- ``errors``: the error a record that breaks its contract raises (``RecordError``).

A contract depends on nothing above it: these modules import the standard library, numpy, ``service.errors``
and each other (the model only for type checking), never another service package or ``api``
(``tests/test_layers.py``).
"""
