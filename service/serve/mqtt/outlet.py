"""The MQTT outlet: the asyncio shell around ``service.serve.mqtt.points`` / ``sparkplug`` / ``plainjson``.

Three tasks, none of which the service waits for::

    on_view(reader)  (event loop, after each published view: remember it, wake the sampler; never blocks)
    sampler          reader -> points (in a thread: compensation() may compute) -> changes beyond the
                     deadbands -> bounded buffer (oldest dropped, counted); also every ``tick_s`` (ages)
    connection       a new aiomqtt client per try, exponential backoff; on connect: births (Sparkplug,
                     a new bdSeq) or "online" (JSON), then the buffer in order, and NCMD rebirths

During a broker outage the sampler keeps buffering up to ``buffer_messages``; on reconnect Sparkplug sends a
new NBIRTH/DBIRTH with the current values and then the buffered DDATA flagged ``is_historical`` (a host keeps
them out of its current values), JSON sends "online", the buffered values and the current ones (retained).

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
from collections.abc import Callable
from dataclasses import dataclass, replace
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING

import aiomqtt

from service.contracts.metrics import OutletMetrics
from service.errors import ServiceError
from service.mqttsettings import MqttSettings
from service.serve.mqtt.bdseq import BdSeqStore
from service.serve.mqtt.buffer import OutBuffer, OutletCounters
from service.serve.mqtt.plainjson import OFFLINE, ONLINE, JsonTopics, payload
from service.serve.mqtt.points import CATALOGUE, Point, ServedReader, changed, read_points
from service.serve.mqtt.sparkplug import PayloadError, SparkplugSession, SparkplugTopics, is_rebirth_request
from service.settings import default_data_dir

if TYPE_CHECKING:
    from service.serve.outlet import OutletContext

__all__ = ["MqttOutlet", "MqttOutletError", "mqtt_outlet"]

log = logging.getLogger(__name__)
Clock = Callable[[], datetime]


class MqttOutletError(ServiceError):
    """The MQTT outlet cannot start as configured."""


@dataclass(frozen=True)
class _Item:
    """One buffered message: Sparkplug DDATA (``points``) or one JSON topic (a single point)."""

    serial: int
    points: dict[str, Point]


def _utc_now() -> datetime:
    return datetime.now(UTC)


class MqttOutlet:
    """See the module docstring. ``start()`` on the loop, ``on_view`` after each publish, ``close()``."""

    name = "mqtt"

    def __init__(
        self,
        settings: MqttSettings,
        *,
        state_dir: Path,
        clock: Clock = _utc_now,
        on_event: Callable[[str], None] | None = None,
    ) -> None:
        self.settings = settings
        self.clock = clock
        self.on_event = on_event or (lambda msg: log.info("%s", msg))
        self.sparkplug = settings.mode == "sparkplug"
        s = settings
        self.session = SparkplugSession(SparkplugTopics(s.group_id, s.edge_node_id, s.device))
        self.json_topics = JsonTopics(s.topic_prefix, s.device)
        self.bdseq = BdSeqStore(Path(state_dir) / f"mqtt-bdseq-{s.group_id}-{s.edge_node_id}")
        self.bd_seq: int | None = None  # this connection's
        self.buffer: OutBuffer[_Item] = OutBuffer(s.buffer_messages)
        self.counters = OutletCounters()
        self._deadbands = s.deadbands.model_dump()
        self._reader: ServedReader | None = None
        self._views = 0
        self._current: dict[str, Point] = {}  # the newest points read
        self._queued: dict[str, Point] = {}  # the last point queued (or born) per metric: the deadband base
        self._serial = 0
        self._birth_mark = 0  # Sparkplug: items with serial <= this were queued before the current birth
        self._wake = asyncio.Event()  # the sampler: a new view
        self._have_points = asyncio.Event()  # the first values are read: births carry them
        self._send = asyncio.Event()  # the sender: a buffered message or a rebirth
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
            asyncio.create_task(self._sampler(), name="mqtt-sampler"),
            asyncio.create_task(self._connection(), name="mqtt-connection"),
        ]

    def on_view(self, reader: ServedReader) -> None:
        """A new view was published: remember its reader and wake the sampler (cheap; never blocks)."""
        self._reader = reader
        self._views += 1
        self._wake.set()

    async def close(self) -> None:
        """Say goodbye (NDEATH / "offline": a clean disconnect sends no Will) and stop."""
        self._closing = True
        client = self._client
        if client is not None and self.counters.connected:
            with contextlib.suppress(aiomqtt.MqttError, asyncio.TimeoutError):
                await asyncio.wait_for(self._goodbye(client), timeout=2.0)
        for task in self._tasks:
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        self.counters.connected = False

    def stats(self) -> OutletCounters:
        """The counters now (a copy), with the buffer's drops."""
        return replace(self.counters, dropped=self.buffer.dropped)

    def outlet_metrics(self) -> OutletMetrics:
        """For ``/metrics`` (``service.serve.interface.CountedOutlet``)."""
        c = self.counters
        return OutletMetrics(
            sent=c.sent,
            dropped=self.buffer.dropped,
            buffered=len(self.buffer),
            reconnects=c.reconnects,
            connect_failures=c.connect_failures,
            connected=c.connected,
        )

    @property
    def buffered(self) -> int:
        return len(self.buffer)

    # --- sampler -----------------------------------------------------------------------------------------
    async def _sampler(self) -> None:
        while True:
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._wake.wait(), timeout=self.settings.tick_s)
            self._wake.clear()
            reader = self._reader
            if reader is None:
                continue
            try:
                points = await asyncio.to_thread(read_points, reader, now=self.clock(), heartbeat=self._views)
            except Exception as err:  # a reader failure must not end the outlet; the next view retries
                log.warning("mqtt: reading the served values failed: %s: %s", type(err).__name__, err)
                continue
            self._enqueue(points)

    def _enqueue(self, points: dict[str, Point]) -> None:
        self._current = points
        self._have_points.set()
        names = changed(CATALOGUE, points, self._queued, self._deadbands)
        if not names:
            return
        for n in names:
            self._queued[n] = points[n]
        groups = [names] if self.sparkplug else [[n] for n in names]
        for group in groups:
            self._serial += 1
            self.buffer.put(_Item(self._serial, {n: points[n] for n in group}))
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
            await asyncio.wait_for(self._have_points.wait(), timeout=s.tick_s)
        while not self._closing:
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
        tasks = [asyncio.create_task(self._drain(client))]
        if self.sparkplug:
            tasks.append(asyncio.create_task(self._commands(client)))
        try:  # both end only by an error (the connection lost): raise the first
            done, _ = await asyncio.wait(tasks, return_when=asyncio.FIRST_EXCEPTION)
            for task in done:
                task.result()
        finally:
            for task in tasks:
                task.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)

    async def _births(self, client: aiomqtt.Client) -> None:
        assert self.bd_seq is not None
        self._birth_mark = self._serial
        self._queued = dict(self._current)
        for topic, body in self.session.births(self.bd_seq, self._current, self.clock()):
            await client.publish(topic, body, qos=0)
            self.counters.sent += 1
        self.counters.births += 1

    async def _drain(self, client: aiomqtt.Client) -> None:
        """Send the buffered messages in order (the only sender while connected: seq stays in order)."""
        if not self.sparkplug:  # after a (re)connect the retained topics get the current values last
            self._requeue_current()
        while True:
            if self._rebirth_due:
                self._rebirth_due = False
                await self._births(client)
                self.counters.rebirths += 1
            item = self.buffer.take()
            if item is None:
                self._send.clear()
                await self._send.wait()
                continue
            try:
                await self._publish(client, item)
            except aiomqtt.MqttError:
                self.buffer.put_back(item)
                raise
            self.counters.sent += 1

    def _requeue_current(self) -> None:
        for n, p in self._current.items():
            self._serial += 1
            self.buffer.put(_Item(self._serial, {n: p}))
        self._queued = dict(self._current)

    async def _publish(self, client: aiomqtt.Client, item: _Item) -> None:
        if self.sparkplug:
            historical = item.serial <= self._birth_mark
            body = self.session.data(item.points, self.clock(), historical=historical)
            await client.publish(self.session.topics.ddata, body, qos=0)
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
