"""The asyncua server of the OPC UA outlet, in its own thread with its own event loop.

asyncua's ``init()`` blocks its loop for about 0.6 s and every read, subscription and secure-channel
operation runs Python on it; on a thread of its own none of that runs on the loop that serves REST.
Values cross over through a latest-value slot (:meth:`OpcUaServer.offer`: the newest ``ViewReader``, and a
wake-up by ``call_soon_threadsafe``); the server's loop renders it (``service.serve.opcua.nodes.render``) at
most every ``update_interval_s`` and at least every ``refresh_s`` (so ages and statuses move on while no view
arrives: the acquisition stopped), and writes only the values that changed. In a cell, an update renders
only the spindles with a new reader or not rendered for ``refresh_s`` (``_due``): N spindles' views wake it
up to 1/``update_interval_s`` times a second, and rendering all N each time cost N times the work.

Address space (namespace ``[opcua] namespace_uri``, index 2 on this server): the object type
``SpindleThermalModelType`` (below BaseObjectType) with one object per group (``Status``, ``H``,
``Condition``, ``Temperatures``, ``Growth``, ``Controller``, ``Devices``) and their variables; the instance
``<spindle>`` (``opcua.spindle``, unset: ``spindle.id``) below Objects, whose NodeIds are the browse paths
(``ns=2;s=<spindle>.Growth.Axial``). Analog values are ``AnalogUnitRangeType`` variables with
``EngineeringUnits`` (UNECE) and ``EURange``; every variable is read-only (AccessLevel CurrentRead).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import tempfile
import threading
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any

from asyncua import Server, ua
from asyncua.common.callback import CallbackType, ServerItemCallback
from asyncua.server.internal_session import InternalSession
from asyncua.server.users import UserRole

from service.logctx import in_current_context
from service.serve.errors import OutletError
from service.serve.opcua.nodes import (
    EPOCH,
    GROUPS,
    MODEL_PUBLISHED,
    MODEL_VERSION,
    UNECE,
    UNITS_NAMESPACE,
    Reading,
    Var,
    render,
    unit_id,
)
from service.serve.opcua.nodeset import Model, conform
from service.serve.opcua.refusals import UAPROCESSOR, Refusals, install_fault_filter
from service.serve.opcua.security import (
    HashedUserManager,
    ReadOnlyRules,
    load_trust_list,
    load_users,
)

if TYPE_CHECKING:
    from service.serve.reader import ViewReader
    from service.settings import OpcUaSettings

__all__ = [
    "METHODS",
    "TYPE_NAME",
    "Methods",
    "OpcUaServer",
    "add_methods",
    "build_address_space",
    "export_nodeset",
]

log = logging.getLogger(__name__)
TYPE_NAME = "SpindleThermalModelType"
POLICIES = {
    "None": ua.SecurityPolicyType.NoSecurity,
    "Basic256Sha256_SignAndEncrypt": ua.SecurityPolicyType.Basic256Sha256_SignAndEncrypt,
}
_VT = {
    "Double": (ua.VariantType.Double, ua.ObjectIds.Double),
    "Boolean": (ua.VariantType.Boolean, ua.ObjectIds.Boolean),
    "String": (ua.VariantType.String, ua.ObjectIds.String),
    "UInt32": (ua.VariantType.UInt32, ua.ObjectIds.UInt32),
    "Int32": (ua.VariantType.Int32, ua.ObjectIds.Int32),
    "Int64": (ua.VariantType.Int64, ua.ObjectIds.Int64),
    "DateTime": (ua.VariantType.DateTime, ua.ObjectIds.DateTime),
}
_ZERO: dict[str, object] = {
    "Double": float("nan"),
    "Boolean": False,
    "String": "",
    "UInt32": 0,
    "Int32": 0,
    "Int64": 0,
    "DateTime": EPOCH,
}


@dataclass(frozen=True)
class Methods:
    """The optional methods' actions (blocking; called in a worker thread): each returns a message."""

    start_identification: Callable[[str], str]
    take_sensor_baseline: Callable[[], str]


def _variant(var: Var, value: object) -> ua.Variant:
    vt = _VT[var.vtype][0]
    if var.length:
        return ua.Variant(list(value), vt, is_array=True)  # type: ignore[call-overload]
    return ua.Variant(value, vt)


def _initial(var: Var) -> ua.Variant:
    zero = _ZERO[var.vtype]
    return _variant(var, [zero] * max(var.length, 0) if var.length else zero)


async def _add_variable(
    server: Server, parent: ua.NodeId, nodeid: ua.NodeId, var: Var, idx: int
) -> ua.NodeId:
    attrs = ua.VariableAttributes()
    attrs.DisplayName = ua.LocalizedText(var.name)
    attrs.Description = ua.LocalizedText(var.description)
    attrs.Value = _initial(var)
    attrs.DataType = ua.NodeId(_VT[var.vtype][1])
    attrs.ValueRank = 1 if var.length else -1
    attrs.ArrayDimensions = [max(var.length, 0)] if var.length else []
    attrs.AccessLevel = ua.AccessLevel.CurrentRead.mask
    attrs.UserAccessLevel = ua.AccessLevel.CurrentRead.mask
    attrs.Historizing = False  # no history is served (asyncua's default is True)
    item = ua.AddNodesItem()
    item.RequestedNewNodeId = nodeid
    item.BrowseName = ua.QualifiedName(var.name, idx)
    item.NodeClass = ua.NodeClass.Variable
    item.ParentNodeId = parent
    item.ReferenceTypeId = ua.NodeId(ua.ObjectIds.HasComponent)
    item.TypeDefinition = ua.NodeId(
        ua.ObjectIds.AnalogUnitRangeType if var.analog else ua.ObjectIds.BaseDataVariableType
    )
    item.NodeAttributes = attrs
    res = (await server.iserver.isession.add_nodes([item]))[0]
    res.StatusCode.check()
    node = server.get_node(res.AddedNodeId)
    await node.set_modelling_rule(True)
    if var.unit is not None:
        name, desc = UNECE[var.unit]
        eu = ua.EUInformation(
            NamespaceUri=UNITS_NAMESPACE,
            UnitId=unit_id(var.unit),
            DisplayName=ua.LocalizedText(name),
            Description=ua.LocalizedText(desc),
        )
        prop = await node.add_property(
            _child_id(nodeid, "EngineeringUnits"),
            ua.QualifiedName("EngineeringUnits", 0),
            ua.Variant(eu, ua.VariantType.ExtensionObject),
        )
        await prop.write_attribute(
            ua.AttributeIds.DataType, ua.DataValue(ua.Variant(ua.NodeId(ua.ObjectIds.EUInformation)))
        )
        await prop.set_modelling_rule(True)
    if var.range is not None:
        rng = ua.Range(Low=float(var.range[0]), High=float(var.range[1]))
        prop = await node.add_property(
            _child_id(nodeid, "EURange"),
            ua.QualifiedName("EURange", 0),
            ua.Variant(rng, ua.VariantType.ExtensionObject),
        )
        await prop.write_attribute(
            ua.AttributeIds.DataType, ua.DataValue(ua.Variant(ua.NodeId(ua.ObjectIds.Range)))
        )
        await prop.set_modelling_rule(True)
    return res.AddedNodeId


def user_attributes(event: ServerItemCallback, _dispatcher: object) -> None:
    """asyncua's PostRead callback: the UserExecutable of a method as the reading session may call it.

    asyncua answers the attribute as stored (True, the methods' own); an anonymous session's Call is refused
    (``ReadOnlyRules``), so it reads False. UserAccessLevel and UserWriteMask are the same for every
    session (CurrentRead, 0: nobody writes), as stored."""
    user = event.user
    if not event.is_external or (user is not None and user.role is UserRole.User):
        return
    params, results = event.request_params, event.response_params
    for i, rv in enumerate(params.NodesToRead):
        value = results[i].Value
        if rv.AttributeId == ua.AttributeIds.UserExecutable and value is not None and value.Value is True:
            results[i] = ua.DataValue(ua.Variant(False, ua.VariantType.Boolean))


def _child_id(parent: ua.NodeId, name: str) -> ua.NodeId:
    """A child's stable string NodeId: the parent's and the child's name (``<path>.EURange``)."""
    return ua.NodeId(f"{parent.Identifier}.{name}", parent.NamespaceIndex)


async def build_address_space(
    server: Server, idx: int, variables: Sequence[Var], *, spindle: str
) -> tuple[Any, Any]:
    """Add ``SpindleThermalModelType`` (with the groups and ``variables``) and its instance ``spindle`` under
    Objects; (type node, instance node)."""
    base = server.get_node(ua.ObjectIds.BaseObjectType)
    otype = await base.add_object_type(ua.NodeId(TYPE_NAME, idx), ua.QualifiedName(TYPE_NAME, idx))
    await otype.write_attribute(
        ua.AttributeIds.Description,
        ua.DataValue(ua.Variant(ua.LocalizedText("Soft sensor of a spindle's thermal state (spindle-chtc)"))),
    )
    groups: dict[str, ua.NodeId] = {}
    for group, desc in GROUPS.items():
        gid = ua.NodeId(f"{TYPE_NAME}.{group}", idx)
        node = await otype.add_object(gid, ua.QualifiedName(group, idx))
        await node.write_attribute(
            ua.AttributeIds.Description, ua.DataValue(ua.Variant(ua.LocalizedText(desc)))
        )
        await node.set_modelling_rule(True)
        groups[group] = gid
    for var in variables:
        await _add_variable(server, groups[var.group], ua.NodeId(f"{TYPE_NAME}.{var.path}", idx), var, idx)
    return otype, await add_instance(server, otype, spindle)


async def add_instance(server: Server, otype: Any, spindle: str) -> Any:
    """An object ``spindle`` of the type ``otype`` below Objects (NodeIds ``ns=<ours>;s=<spindle>...``)."""
    idx = otype.nodeid.NamespaceIndex
    return await server.nodes.objects.add_object(
        ua.NodeId(spindle, idx), ua.QualifiedName(spindle, idx), objecttype=otype.nodeid
    )


class OpcUaServer:
    """See the module docstring. ``start()`` (blocks until serving or raises ``OutletError``),
    ``offer(reader)`` from any thread, ``stop()``."""

    def __init__(
        self,
        cfg: OpcUaSettings,
        *,
        variables: Sequence[Var],
        clock: Callable[[], datetime],
        bad_after_s: float,
        n_sensors: int = 32,
        methods: Methods | Mapping[str, Methods] | None = None,
        spindles: Sequence[str] = (),
    ) -> None:
        """``spindles``: a cell's objects, one per spindle id (each fed by ``offer(reader, spindle)``, each
        with its own ``methods[spindle]``); empty: one object, ``cfg.node_prefix``."""
        self.cfg = cfg
        self.spindles = tuple(spindles) or (cfg.node_prefix,)
        self.variables = tuple(variables)
        self.clock = clock
        self.bad_after_s = float(bad_after_s)
        self.n_sensors = n_sensors
        self.methods = methods
        self.heartbeat = 0
        self.updates = 0
        self.update_errors = 0
        self._slots: dict[str, ViewReader] = {}
        self._rendered: dict[str, tuple[ViewReader, float]] = {}  # the reader rendered last, loop time
        self.renders: dict[str, int] = {}  # renders per spindle (tests, the bench)
        self._loop: asyncio.AbstractEventLoop | None = None
        self._wake: asyncio.Event | None = None
        self._stop: asyncio.Event | None = None
        self._thread: threading.Thread | None = None
        self._ready = threading.Event()
        self._failed: BaseException | None = None
        self._written: dict[tuple[str, str], tuple[object, int, datetime | None]] = {}
        self._nodeids: dict[tuple[str, str], ua.NodeId] = {}
        self.refusals = Refusals()  # counted for /metrics, logged once per client and reason
        self.server: Server | None = None
        self.on_update: Callable[[], None] | None = None  # after each update (tests, the bench)
        # the start's progress (``start``): one step for the server's set-up, one per object built, one per
        # object's initial values, one per object's methods, one for the server's own start
        self.start_total = 3 * len(self.spindles) + 2
        self.start_steps = 0

    @property
    def endpoint(self) -> str:
        return f"opc.tcp://{self.cfg.host}:{self.cfg.port}{self.cfg.path}"

    # --- lifecycle (caller's thread) ---------------------------------------------------------------------
    def start(self, stall_s: float = 60.0) -> None:
        """Start the server's thread and wait until it serves, however long its start takes while it makes
        progress (a cell's objects are built one by one: 50 spindles' took over 60 s beside the spindles'
        own start on 2 cores, and ended the host); ``OutletError`` once ``stall_s`` pass without a step."""
        self._thread = threading.Thread(target=in_current_context(self._run), name="chtc-opcua", daemon=True)
        self._thread.start()
        seen = -1
        while not self._ready.wait(stall_s):
            if self.start_steps == seen:
                raise OutletError(
                    f"the OPC UA server did not start: no progress for {stall_s:.0f} s "
                    f"({self.start_steps} of {self.start_total} start steps done)"
                )
            seen = self.start_steps
        if self._failed is not None:
            raise OutletError(f"the OPC UA server did not start: {self._failed}") from self._failed

    def offer(self, reader: ViewReader, spindle: str | None = None) -> None:
        """Hand over the newest reader of ``spindle`` (None: the only one; any thread; never blocks)."""
        self._slots[self.spindles[0] if spindle is None else spindle] = reader
        loop, wake = self._loop, self._wake
        if loop is not None and wake is not None and not loop.is_closed():
            with contextlib.suppress(RuntimeError):  # the loop just closed
                loop.call_soon_threadsafe(wake.set)

    def stop(self, timeout_s: float = 10.0) -> None:
        loop, stop = self._loop, self._stop
        if loop is not None and stop is not None and not loop.is_closed():
            with contextlib.suppress(RuntimeError):
                loop.call_soon_threadsafe(stop.set)
        if self._thread is not None:
            self._thread.join(timeout_s)

    # --- the server's thread -----------------------------------------------------------------------------
    def _run(self) -> None:
        try:
            asyncio.run(self._main())
        except BaseException as err:  # reported to start() if it has not returned yet
            self._failed = self._failed or err
            log.exception("OPC UA server stopped: %s", err)
        finally:
            self._ready.set()

    async def _main(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._wake, self._stop = asyncio.Event(), asyncio.Event()
        faults = install_fault_filter(self.refusals)
        try:
            try:
                server = await self._build()
                await server.start()
                self.start_steps += 1
            except BaseException as err:
                self._failed = err
                self._ready.set()
                raise
            self.server = server
            try:
                await self._update()
                self._ready.set()
                await self._serve()
            finally:
                await server.stop()
        finally:
            logging.getLogger(UAPROCESSOR).removeFilter(faults)

    async def _serve(self) -> None:
        assert self._wake is not None and self._stop is not None
        loop = asyncio.get_running_loop()
        last = loop.time()
        while not self._stop.is_set():
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._wake.wait(), timeout=self.cfg.refresh_s)
            self._wake.clear()
            if self._stop.is_set():
                break
            wait = self.cfg.update_interval_s - (loop.time() - last)
            if wait > 0:  # views coalesce: the newest one is rendered after the wait
                await asyncio.sleep(wait)
            last = loop.time()
            await self._update()

    async def _update(self) -> None:
        slots = dict(self._slots)
        if not slots or self.server is None:
            return
        self.heartbeat += 1
        now = self.clock()
        t = asyncio.get_running_loop().time()
        for spindle, reader in self._due(slots, t).items():
            self._rendered[spindle] = (reader, t)
            self.renders[spindle] = self.renders.get(spindle, 0) + 1
            try:
                readings = render(
                    reader,
                    now=now,
                    bad_after_s=self.bad_after_s,
                    heartbeat=self.heartbeat,
                    n_sensors=self.n_sensors,
                )
                await self._write(spindle, readings, now)
            except Exception as err:  # keep serving the last values; say why once per failure
                self.update_errors += 1
                log.warning("OPC UA update of %s failed: %s: %s", spindle, type(err).__name__, err)
        self.updates += 1
        if self.on_update is not None:
            self.on_update()

    def _due(self, slots: dict[str, ViewReader], t: float) -> dict[str, ViewReader]:
        """The spindles to render at loop time ``t``: a new reader, or none rendered for ``refresh_s``
        (50 ms early: the wait that times out after ``refresh_s`` may wake a clock tick before it)."""
        out = {}
        for spindle, reader in slots.items():
            last = self._rendered.get(spindle)
            if last is None or last[0] is not reader or t - last[1] >= self.cfg.refresh_s - 0.05:
                out[spindle] = reader
        return out

    async def _write(self, spindle: str, readings: dict[str, Reading], now: datetime) -> None:
        assert self.server is not None
        wall = datetime.now(UTC)
        for var in self.variables:
            r = readings.get(var.path)
            if r is None:
                continue
            key = (r.value, int(r.status), r.source_time)
            at = (spindle, var.path)
            if self._written.get(at) == key:
                continue
            dv = ua.DataValue(
                Value=_variant(var, r.value),
                StatusCode_=ua.StatusCode(int(r.status)),
                SourceTimestamp=_ua_time(r.source_time or now),  # the data's time (the service's clock)
                ServerTimestamp=wall,  # when this server took the value (its own clock)
            )
            await self.server.write_attribute_value(self._nodeids[at], dv)
            self._written[at] = key

    async def _build(self) -> Server:
        cfg = self.cfg
        sec_only = "None" not in cfg.security_policies
        trusted = load_trust_list(cfg.trust_dir) if cfg.trust_dir is not None else frozenset()
        users = load_users({k: v.get_secret_value() for k, v in cfg.users.items()}, cfg.users_file)
        manager = HashedUserManager(users, anonymous=cfg.anonymous, require_trusted=sec_only, trusted=trusted)
        server = Server(user_manager=manager)
        await server.init()
        server.iserver.allow_remote_admin = False
        InternalSession.max_connections = cfg.max_connections  # asyncua keeps the bound per process
        server.set_endpoint(self.endpoint)
        server.set_server_name("spindle-chtc OPC UA")
        await server.set_application_uri("urn:spindle-chtc:server")
        server.set_security_policy(
            [POLICIES[p] for p in cfg.security_policies], permission_ruleset=ReadOnlyRules(self.refusals)
        )
        server.subscribe_server_callback(CallbackType.PostRead, user_attributes)
        ids = (["Anonymous"] if cfg.anonymous else []) + (["Username"] if users else [])
        if not ids:
            raise OutletError("opcua: anonymous = false and no users: nobody could connect")
        server.set_security_IDs(ids)
        if cfg.certificate is not None and cfg.private_key is not None:
            await server.load_certificate(str(cfg.certificate))
            await server.load_private_key(str(cfg.private_key))
        idx = await server.register_namespace(cfg.namespace_uri)
        self.start_steps += 1
        otype, instance = await build_address_space(server, idx, self.variables, spindle=self.spindles[0])
        instances = {self.spindles[0]: instance}
        self.start_steps += 1
        for name in self.spindles[1:]:  # a cell: one object per spindle, of the same type
            instances[name] = await add_instance(server, otype, name)
            self.start_steps += 1
        self._nodeids = {
            (sp, v.path): ua.NodeId(f"{sp}.{v.path}", idx) for sp in self.spindles for v in self.variables
        }
        waiting = ua.StatusCode(ua.StatusCodes.BadWaitingForInitialData)
        for sp in self.spindles:  # nothing is known before the first view
            for var in self.variables:
                dv = ua.DataValue(Value=_initial(var), StatusCode_=waiting, ServerTimestamp=datetime.now(UTC))
                await server.write_attribute_value(self._nodeids[(sp, var.path)], dv)
            self.start_steps += 1
        for name, inst in instances.items():
            methods = self.methods.get(name) if isinstance(self.methods, Mapping) else self.methods
            if methods is not None:
                await self._add_methods(server, inst, idx, methods)
            self.start_steps += 1
        return server

    async def _add_methods(self, server: Server, instance: Any, idx: int, methods: Methods) -> None:
        async def run(fn: Callable[[], str]) -> list[ua.Variant]:
            try:
                msg = await asyncio.to_thread(fn)  # the service's handover blocks: off this loop
            except Exception as err:  # the service's refusal (busy, not ready) is the call's status
                log.info("OPC UA method refused: %s: %s", type(err).__name__, err)
                raise ua.UaStatusCodeError(ua.StatusCodes.BadInvalidState) from err
            return [ua.Variant(msg, ua.VariantType.String)]

        async def start_identification(_parent: ua.NodeId, reason: ua.Variant) -> list[ua.Variant]:
            text = str(reason.Value or "OPC UA StartIdentification")[:200]
            return await run(lambda: methods.start_identification(text))

        async def take_sensor_baseline(_parent: ua.NodeId) -> list[ua.Variant]:
            return await run(methods.take_sensor_baseline)

        await add_methods(
            server,
            instance,
            {"StartIdentification": start_identification, "TakeSensorBaseline": take_sensor_baseline},
        )


# name -> (description, input arguments); every method returns one String, "Result"
METHODS: dict[str, tuple[str, tuple[tuple[str, str], ...]]] = {
    "StartIdentification": (
        "Start an identification of H1-H7 now (as POST /identifications); Reason: free text, at most 200 "
        "characters. Authenticated users only.",
        (("Reason", "why (kept in the identification's record)"),),
    ),
    "TakeSensorBaseline": (
        "Take the sensor offset baseline now (as POST /sensors/baseline). Authenticated users only.",
        (),
    ),
}


def _argument(name: str, description: str) -> ua.Argument:
    return ua.Argument(
        Name=name,
        DataType=ua.NodeId(ua.ObjectIds.String),
        ValueRank=-1,
        Description=ua.LocalizedText(description),
    )


async def add_methods(server: Server, instance: Any, callbacks: dict[str, Callable[..., Any]] | None) -> None:
    """Add ``METHODS`` below ``instance`` with string NodeIds (``<spindle>.StartIdentification``, its
    ``<spindle>.StartIdentification.InputArguments``, ...); ``callbacks`` None: the model only (the NodeSet
    export)."""
    parent: ua.NodeId = instance.nodeid
    idx = parent.NamespaceIndex
    for name, (description, inputs) in METHODS.items():
        mid = _child_id(parent, name)
        attrs = ua.MethodAttributes()
        attrs.DisplayName = ua.LocalizedText(name)
        attrs.Description = ua.LocalizedText(description)
        attrs.WriteMask = attrs.UserWriteMask = 0
        attrs.Executable = attrs.UserExecutable = True  # UserExecutable per session: ``user_attributes``
        item = ua.AddNodesItem()
        item.RequestedNewNodeId = mid
        item.BrowseName = ua.QualifiedName(name, idx)
        item.NodeClass = ua.NodeClass.Method
        item.ParentNodeId = parent
        item.ReferenceTypeId = ua.NodeId(ua.ObjectIds.HasComponent)
        item.NodeAttributes = attrs
        (await server.iserver.isession.add_nodes([item]))[0].StatusCode.check()
        method = server.get_node(mid)
        args = {
            "InputArguments": [_argument(n, d) for n, d in inputs],
            "OutputArguments": [_argument("Result", "what the service did (or why not)")],
        }
        for prop_name, arguments in args.items():
            if not arguments:
                continue
            prop = await method.add_property(
                _child_id(mid, prop_name),
                ua.QualifiedName(prop_name, 0),
                ua.Variant(arguments, ua.VariantType.ExtensionObject, is_array=True),
                datatype=ua.NodeId(ua.ObjectIds.Argument),
            )
            await prop.write_attribute(
                ua.AttributeIds.ValueRank, ua.DataValue(ua.Variant(1, ua.VariantType.Int32))
            )
            await prop.write_attribute(
                ua.AttributeIds.ArrayDimensions,
                ua.DataValue(ua.Variant([len(arguments)], ua.VariantType.UInt32, is_array=True)),
            )
        if callbacks is not None:
            server.iserver.isession.add_method_callback(mid, callbacks[name])


def _ua_time(t: datetime) -> datetime:
    return t.astimezone(UTC) if t.tzinfo is not None else t.replace(tzinfo=UTC)


async def export_nodeset(
    cfg: OpcUaSettings, variables: Sequence[Var], path: Path, *, spindles: Sequence[str] = ()
) -> int:
    """Write the NodeSet2 XML of our namespace (the type, the instance ``cfg.node_prefix`` or, for a cell,
    one instance per name of ``spindles``, and with ``cfg.methods`` each instance's methods and their
    arguments) to ``path``, valid against the OPC Foundation's schemas (``service.serve.opcua.nodeset``);
    the number of data variables (the type's and the instances')."""
    names = list(spindles) or [cfg.node_prefix]
    server = Server()
    await server.init()
    idx = await server.register_namespace(cfg.namespace_uri)
    otype, instance = await build_address_space(server, idx, variables, spindle=names[0])
    instances = [instance] + [await add_instance(server, otype, name) for name in names[1:]]
    if cfg.methods:
        for inst in instances:
            await add_methods(server, inst, None)
    with tempfile.TemporaryDirectory(prefix="chtc-nodeset-") as tmp:
        raw = Path(tmp) / "raw.xml"
        with _quiet("asyncua.common.xmlexporter"):  # its warning that values may be invalid: mended below
            await server.export_xml_by_ns(str(raw), [idx], export_values=True)
        text = conform(
            raw.read_text(encoding="utf-8"),
            Model(uri=cfg.namespace_uri, version=MODEL_VERSION, published=MODEL_PUBLISHED),
        )
    path.write_text(text, encoding="utf-8")
    return (1 + len(names)) * len(variables)


@contextlib.contextmanager
def _quiet(logger: str) -> Iterator[None]:
    lg = logging.getLogger(logger)
    level = lg.level
    lg.setLevel(logging.ERROR)
    try:
        yield
    finally:
        lg.setLevel(level)
