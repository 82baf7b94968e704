"""The MQTT outlet: the asyncio shell around ``service.serve.mqtt.points`` / ``devices`` / ``sparkplug`` /
``plainjson``.

One connection (one Sparkplug edge node, or one JSON device) with one device per spindle it carries: one for
a single spindle (``mqtt_outlet``), every running spindle of a host with Sparkplug
(``service.serve.mqtt.hosted``). Tasks, none of which the service waits for::

    on_view(reader)  (event loop, after each published view of a spindle: remember it, wake its sampler;
                     never blocks)
    sampler          one per device: reader -> points (in a thread: compensation() may compute) -> changes
                     beyond the deadbands -> the device's bounded buffer (oldest dropped, counted); also
                     every ``tick_s`` (ages)
    connection       a new aiomqtt client per try, exponential backoff; on connect: births (Sparkplug,
                     a new bdSeq: NBIRTH, then a DBIRTH per live device) or "online" (JSON), then the
                     buffers in the order queued, DDEATHs of devices whose spindle stopped, and NCMD rebirths

During a broker outage each device's sampler keeps buffering up to ``buffer_messages``; on reconnect
Sparkplug sends a new NBIRTH and the DBIRTHs with the current values and then the buffered DDATA flagged
``is_historical`` (a host keeps them out of its current values), JSON sends "online", the buffered values
and the current ones (retained).

Errors::

    ServiceError
    └── MqttOutletError      the outlet cannot start (a TLS file unreadable)
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import ssl
import time
from collections.abc import Callable, Sequence
from dataclasses import replace
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING

import aiomqtt

from service.contracts.metrics import OutletMetrics
from service.errors import ServiceError
from service.mqttsettings import MqttSettings
from service.serve.mqtt.bdseq import BdSeqStore
from service.serve.mqtt.buffer import OutletCounters
from service.serve.mqtt.devices import Devices, Item
from service.serve.mqtt.plainjson import OFFLINE, ONLINE, JsonTopics, payload
from service.serve.mqtt.points import Point, ServedReader, read_points
from service.serve.mqtt.sparkplug import PayloadError, SparkplugSession, SparkplugTopics, is_rebirth_request
from service.serve.tasks import raise_if_cancelled, stop_tasks
from service.settings import default_data_dir

if TYPE_CHECKING:
    from service.serve.outlet import OutletContext

__all__ = ["DeviceFeed", "MqttOutlet", "MqttOutletError", "mqtt_outlet"]

log = logging.getLogger(__name__)
Clock = Callable[[], datetime]


class MqttOutletError(ServiceError):
    """The MQTT outlet cannot start as configured."""


def _utc_now() -> datetime:
    return datetime.now(UTC)


class DeviceFeed:
    """One device's subscription to its spindle's views and its sampler task (module docstring). With a
    host, ``service.subscribe(feed)`` for each spindle; ``close()`` when that spindle stops (its DDEATH)."""

    name = "mqtt"

    def __init__(self, outlet: MqttOutlet, device: str) -> None:
        self.outlet = outlet
        self.device = device
        self.reader: ServedReader | None = None
        self.views = 0
        self.wake = asyncio.Event()

    async def start(self) -> None:
        return None  # the outlet runs the sampler (``run``)

    def on_view(self, reader: ServedReader) -> None:
        """A new view was published: remember its reader and wake the sampler (cheap; never blocks)."""
        self.reader = reader
        self.views += 1
        self.wake.set()

    async def close(self) -> None:
        """The spindle stopped: its DDEATH (Sparkplug), nothing more for it."""
        self.outlet.device_stopped(self.device)

    async def run(self) -> None:
        o = self.outlet
        while True:
            raise_if_cancelled()
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(o.settings.tick_s):
                    await self.wake.wait()
            self.wake.clear()
            reader = self.reader
            if reader is None:
                continue
            try:
                points = await asyncio.to_thread(read_points, reader, now=o.clock(), heartbeat=self.views)
            except Exception as err:  # a reader failure must not end the outlet; the next view retries
                log.warning(
                    "mqtt: reading %s's served values failed: %s: %s", self.device, type(err).__name__, err
                )
                continue
            o.offer(self.device, points)


class MqttOutlet:
    """See the module docstring. ``start()`` on the loop, ``on_view`` after each publish (a single spindle;
    a host feeds ``feeds[device]``), ``close()``."""

    name = "mqtt"

    def __init__(
        self,
        settings: MqttSettings,
        *,
        state_dir: Path,
        clock: Clock = _utc_now,
        on_event: Callable[[str], None] | None = None,
        devices: Sequence[str] | None = None,
    ) -> None:
        self.settings = settings
        self.clock = clock
        self.on_event = on_event or (lambda msg: log.info("%s", msg))
        self.sparkplug = settings.mode == "sparkplug"
        s = settings
        names = list(devices) if devices is not None else [s.device]
        if not self.sparkplug and len(names) != 1:
            raise ValueError("mqtt: a JSON connection carries one device")
        self.session = SparkplugSession(SparkplugTopics(s.group_id, s.edge_node_id, names[0]))
        self.json_topics = JsonTopics(s.topic_prefix, names[0])
        self.bdseq = BdSeqStore(Path(state_dir) / f"mqtt-bdseq-{s.group_id}-{s.edge_node_id}")
        self.bd_seq: int | None = None  # this connection's
        self.devices = Devices(
            names,
            buffer_messages=s.buffer_messages,
            deadbands=s.deadbands.model_dump(),
            per_point=not self.sparkplug,
        )
        self.feeds = {n: DeviceFeed(self, n) for n in names}
        self.counters = OutletCounters()
        self._born: set[str] = set()  # devices with a DBIRTH in this connection
        self._deaths: list[str] = []  # devices whose spindle stopped: DDEATH due
        self._have_points = asyncio.Event()  # every device's first values are read: births carry them
        self._send = asyncio.Event()  # the sender: a buffered message, a rebirth or a death
        self._rebirth_due = False
        self._last_rebirth = -float("inf")
        self._tasks: list[asyncio.Task[None]] = []
        self._client: aiomqtt.Client | None = None
        self._tls: ssl.SSLContext | None = None
        self._closing = False
        self._said_down = False

    # --- the outlet protocol ------------------------------------------------------------------------------
    async def start(self) -> None:
        self._tls = self._tls_context()
        self._tasks = [
            asyncio.create_task(feed.run(), name=f"mqtt-sampler-{name}") for name, feed in self.feeds.items()
        ]
        self._tasks.append(asyncio.create_task(self._connection(), name="mqtt-connection"))

    def on_view(self, reader: ServedReader) -> None:
        """A single spindle's new view (its only device's feed; cheap, never blocks)."""
        self.feeds[self.session.topics.device].on_view(reader)

    async def close(self) -> None:
        """Say goodbye (NDEATH / "offline": a clean disconnect sends no Will) and stop."""
        self._closing = True
        client = self._client
        if client is not None and self.counters.connected:
            with contextlib.suppress(aiomqtt.MqttError, TimeoutError):
                async with asyncio.timeout(2.0):
                    await self._goodbye(client)
        abandoned = await stop_tasks(self._tasks, timeout_s=15.0)
        if abandoned:
            names = sorted(t.get_name() for t in abandoned)
            log.warning("mqtt: %s did not stop within 15 s; abandoned", names)
        self.counters.connected = False

    def stats(self) -> OutletCounters:
        """The counters now (a copy), with the buffers' drops."""
        return replace(self.counters, dropped=self.devices.dropped)

    def outlet_metrics(self) -> OutletMetrics:
        """For ``/metrics`` (``service.serve.interface.CountedOutlet``)."""
        c = self.counters
        return OutletMetrics(
            sent=c.sent,
            dropped=self.devices.dropped,
            buffered=self.devices.buffered,
            reconnects=c.reconnects,
            connect_failures=c.connect_failures,
            connected=c.connected,
        )

    @property
    def buffered(self) -> int:
        return self.devices.buffered

    # --- the devices ---------------------------------------------------------------------------------------
    def offer(self, device: str, points: dict[str, Point]) -> None:
        """A device's sampler read ``points``: queue the changes, wake the sender."""
        if self.devices.offer(device, points):
            self._send.set()
        if all(q.have_points for q in self.devices.live):
            self._have_points.set()

    def device_stopped(self, device: str) -> None:
        """``device``'s spindle stopped: its sampler ends, its buffer goes, a DDEATH if it was born."""
        if not self.devices.stop(device):
            return
        task = next((t for t in self._tasks if t.get_name() == f"mqtt-sampler-{device}"), None)
        if task is not None:
            task.cancel()
        if self.sparkplug and device in self._born:
            self._deaths.append(device)
            self._send.set()

    # --- connection ----------------------------------------------------------------------------------------
    def _tls_context(self) -> ssl.SSLContext | None:
        tls = self.settings.tls
        if not tls.active:
            return None
        try:
            ctx = ssl.create_default_context(cafile=None if tls.ca is None else str(tls.ca))
            if tls.cert is not None and tls.key is not None:
                ctx.load_cert_chain(str(tls.cert), str(tls.key))
        except (OSError, ssl.SSLError) as err:
            raise MqttOutletError(f"mqtt.tls: {err}") from err
        if tls.insecure:
            ctx.check_hostname = False
        return ctx

    def _client_for_try(self) -> aiomqtt.Client:
        s = self.settings
        if self.sparkplug:
            self.bd_seq = self.bdseq.upcoming()
            will = aiomqtt.Will(self.session.topics.ndeath, self.session.death(self.bd_seq, self.clock()), 1)
        else:
            will = aiomqtt.Will(self.json_topics.availability, OFFLINE, qos=1, retain=True)
        return aiomqtt.Client(
            s.host,
            s.port,
            username=s.username,
            password=None if s.password is None else s.password.get_secret_value(),
            identifier=s.effective_client_id,
            will=will,
            clean_session=True,
            keepalive=s.keepalive_s,
            tls_context=self._tls,
            timeout=10.0,
        )

    async def _connection(self) -> None:
        s = self.settings
        backoff = s.backoff_initial_s
        ever = False
        with contextlib.suppress(TimeoutError):  # births with values rather than nulls, if they come soon
            async with asyncio.timeout(s.tick_s):
                await self._have_points.wait()
        while not self._closing:
            raise_if_cancelled()
            client = self._client_for_try()
            connected = False
            try:
                async with client:
                    connected = True
                    self._commit_bdseq()
                    self._client = client
                    self.counters.connected = True
                    if ever:
                        self.counters.reconnects += 1
                    ever = True
                    backoff = s.backoff_initial_s
                    self._said_down = False
                    self.on_event(f"mqtt: connected to {s.host}:{s.port} ({s.mode}, bdSeq {self.bd_seq})")
                    await self._serve(client)
            except aiomqtt.MqttError as err:
                if not connected:
                    self.counters.connect_failures += 1
                if connected or not self._said_down:  # once per outage, not every retry
                    self.on_event(f"mqtt: {'connection lost' if connected else 'cannot connect'}: {err}")
                self._said_down = True
                log.debug("mqtt: %s (retry in %.1f s)", err, backoff)
            except Exception as err:  # a bug must not end the outlet for good: say it, retry as for a loss
                log.exception("mqtt: unexpected %s: %s", type(err).__name__, err)
            finally:
                self.counters.connected = False
                self._client = None
            await asyncio.sleep(backoff)
            backoff = min(2.0 * backoff, s.backoff_max_s)

    def _commit_bdseq(self) -> None:
        if self.bd_seq is None:
            return
        try:
            self.bdseq.commit(self.bd_seq)
        except (
            OSError
        ) as err:  # publish anyway; the next start may repeat this number (hosts may be confused)
            self.on_event(f"mqtt: cannot store bdSeq in {self.bdseq.path}: {err}")

    async def _serve(self, client: aiomqtt.Client) -> None:
        if self.sparkplug:
            await client.subscribe(self.session.topics.ncmd, qos=1)
            await self._births(client)
        else:
            await client.publish(self.json_topics.availability, ONLINE, qos=1, retain=True)
            self.counters.sent += 1
        raise_if_cancelled()
        tasks = [asyncio.create_task(self._drain(client))]
        if self.sparkplug:
            tasks.append(asyncio.create_task(self._commands(client)))
        try:  # both end only by an error (the connection lost): raise the first
            done, _ = await asyncio.wait(tasks, return_when=asyncio.FIRST_EXCEPTION)
            for task in done:
                task.result()
        finally:
            await stop_tasks(tasks, timeout_s=10.0)

    async def _births(self, client: aiomqtt.Client) -> None:
        """NBIRTH, then a DBIRTH per live device with its current values (later deltas are against them)."""
        assert self.bd_seq is not None
        now = self.clock()
        s = self.session
        self._deaths.clear()  # the NBIRTH restarts the node: a stopped device is simply not born again
        await client.publish(s.topics.nbirth, s.nbirth(self.bd_seq, now), qos=0)
        self.counters.sent += 1
        self._born = set()
        for q in self.devices.live:
            self.devices.born(q.name)
            self._born.add(q.name)  # before the await: a stop meanwhile gets its DDEATH after this DBIRTH
            await client.publish(s.topics.of("DBIRTH", q.name), s.dbirth(q.current, now), qos=0)
            self.counters.sent += 1
        self.counters.births += 1

    async def _drain(self, client: aiomqtt.Client) -> None:
        """Send the buffered messages in order (the only sender while connected: seq stays in order)."""
        if not self.sparkplug:  # after a (re)connect the retained topics get the current values last
            for q in self.devices.live:
                self.devices.requeue_current(q.name)
        while True:
            raise_if_cancelled()  # a publish's acknowledgement may have swallowed the cancel (serve/tasks.py)
            if self._rebirth_due:
                self._rebirth_due = False
                await self._births(client)
                self.counters.rebirths += 1
            while self._deaths:
                device = self._deaths.pop(0)
                body = self.session.ddeath(self.clock())
                await client.publish(self.session.topics.of("DDEATH", device), body, qos=0)
                self._born.discard(device)
                self.counters.sent += 1
            item = self.devices.take()
            if item is None:
                self._send.clear()
                await self._send.wait()
                continue
            try:
                await self._publish(client, item)
            except aiomqtt.MqttError:
                self.devices.put_back(item)
                raise
            self.counters.sent += 1

    async def _publish(self, client: aiomqtt.Client, item: Item) -> None:
        if self.sparkplug:
            historical = self.devices.historical(item)
            body = self.session.ddata(item.points, self.clock(), historical=historical)
            await client.publish(self.session.topics.of("DDATA", item.device), body, qos=0)
            return
        ((name, point),) = item.points.items()
        await client.publish(self.json_topics.value(name), payload(point), qos=1, retain=True)

    async def _commands(self, client: aiomqtt.Client) -> None:
        async for message in client.messages:
            body = message.payload
            if not isinstance(body, bytes | bytearray):
                continue
            try:
                rebirth = is_rebirth_request(bytes(body))
            except PayloadError as err:
                log.warning("mqtt: %s", err)
                continue
            if rebirth:
                self._rebirth_requested()

    def _rebirth_requested(self) -> None:
        self.counters.rebirth_requests += 1
        mono = time.monotonic()
        if mono - self._last_rebirth < self.settings.rebirth_min_interval_s:
            log.info(
                "mqtt: rebirth request ignored (rate limit %.0f s)", self.settings.rebirth_min_interval_s
            )
            return
        self._last_rebirth = mono
        self._rebirth_due = True
        self._send.set()

    async def _goodbye(self, client: aiomqtt.Client) -> None:
        if self.sparkplug and self.bd_seq is not None:
            await client.publish(
                self.session.topics.ndeath, self.session.death(self.bd_seq, self.clock()), qos=1
            )
        elif not self.sparkplug:
            await client.publish(self.json_topics.availability, OFFLINE, qos=1, retain=True)


def mqtt_outlet(ctx: OutletContext) -> MqttOutlet:
    """The factory the runtime finds by name (``service.serve.outlet.OUTLETS["mqtt"]``): ``[mqtt]`` of the
    settings (the Sparkplug device named after the spindle unless ``mqtt.device_id`` is set), bdSeq kept in
    ``mqtt.state_dir`` (default: the data directory), the run's clock."""
    s = ctx.settings.mqtt.for_spindle(ctx.settings.spindle.id)
    state = s.state_dir if s.state_dir is not None else default_data_dir()
    return MqttOutlet(s, state_dir=state, clock=ctx.clock, on_event=ctx.on_event)
