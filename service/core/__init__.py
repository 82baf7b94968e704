"""The service's pure core (STYLE rule 2): ``machine.ServiceCore``, a state machine ``handle(event) ->
instructions`` with its parts (detector and scheduler tracks, serving strategies, job book, sample book), its
events and instructions, its configuration, and ``offline.run_offline``, the same core driven over a recorded
sample sequence. No asyncio, no threads, no database, no I/O: it imports none of ``service.shell`` and
``service.host`` (tests/test_layers.py). docs/design/ARCHITECTURE.md, "service/".
"""
