"""The asyncio shell around the pure core: ``service.SoftSensorService`` (the facade the API and the outlets
read) over ``internal.InternalService`` (events in, the core's view published, instructions executed: database
writer, identification worker, outlets), where the core runs (``corethread``), the loop's lag, device health
and metrics, the growth terms' refresh, the commissioning of the mechanics. Imports none of ``service.host``
(tests/test_layers.py). docs/design/ARCHITECTURE.md, "service/"; docs/design/threading.md.
"""
