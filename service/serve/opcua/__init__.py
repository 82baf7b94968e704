"""The OPC UA outlet (issue 28 item 2): an asyncua server in its own thread, fed the published views.

- ``status``: the served-value policy's verdict -> OPC UA StatusCode (pure);
- ``nodes``: the address space as data (NodeIds, types, units, ranges) and the values of one reader (pure);
- ``security``: the user manager (hashed passwords), the trust list and the permission rules;
- ``server``: the asyncua server built from ``nodes`` in its own thread and event loop;
- ``outlet``: the ``service.serve.outlet.Outlet`` the runtime starts (``opcua_outlet``).
"""
