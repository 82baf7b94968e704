"""The devices of one MQTT connection and what each still has to send (pure: no I/O, no clock).

One Sparkplug edge node carries one device per spindle (one with a single spindle); a JSON connection
carries one. Per device: the newest points read (the births carry them), the last point queued per metric
(the deadband's base), a bounded buffer of messages (oldest dropped, counted; ``mqtt.buffer_messages`` per
device, as for a single spindle) and the birth mark (messages queued before the current birth are sent
flagged historical after it). Messages are numbered across the devices (``serial``), so the sender takes
them in the order they were queued whichever device they belong to::

    offer(device, points)   the sampler read new values: the changed ones queued (one message, or one per
                            point in JSON mode); True when something was queued
    born(device)            its DBIRTH is being sent with ``current``: later deltas are against it
    take() / put_back(m)    the sender: the oldest message of any live device / back to the front
    stop(device)            its spindle stopped: its buffer is dropped, it is sent nothing more (DDEATH)

Not thread-safe: the outlet uses it on the event loop only.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field

from service.serve.mqtt.buffer import OutBuffer
from service.serve.mqtt.points import CATALOGUE, Point, changed

__all__ = ["DeviceQueue", "Devices", "Item"]


@dataclass(frozen=True)
class Item:
    """One buffered message of ``device``: Sparkplug DDATA (``points``) or one JSON topic (one point)."""

    serial: int
    device: str
    points: dict[str, Point]


@dataclass
class DeviceQueue:
    name: str
    buffer: OutBuffer[Item]
    current: dict[str, Point] = field(default_factory=dict)  # the newest points read
    queued: dict[str, Point] = field(default_factory=dict)  # the last point queued (or born) per metric
    birth_mark: int = 0  # items with serial <= this were queued before the current birth
    live: bool = True  # False once its spindle stopped

    @property
    def have_points(self) -> bool:
        return bool(self.current)


class Devices:
    """See the module docstring. ``per_point``: JSON mode (one message per changed point)."""

    def __init__(
        self,
        names: Iterable[str],
        *,
        buffer_messages: int,
        deadbands: Mapping[str, float],
        per_point: bool = False,
    ) -> None:
        self.queues = {n: DeviceQueue(n, OutBuffer(buffer_messages)) for n in names}
        if not self.queues:
            raise ValueError("devices: at least one")
        self.deadbands = dict(deadbands)
        self.per_point = per_point
        self.serial = 0

    def __getitem__(self, name: str) -> DeviceQueue:
        return self.queues[name]

    @property
    def live(self) -> list[DeviceQueue]:
        return [q for q in self.queues.values() if q.live]

    @property
    def buffered(self) -> int:
        return sum(len(q.buffer) for q in self.queues.values())

    @property
    def dropped(self) -> int:
        return sum(q.buffer.dropped for q in self.queues.values())

    def _put(self, q: DeviceQueue, points: dict[str, Point]) -> None:
        self.serial += 1
        q.buffer.put(Item(self.serial, q.name, points))

    def offer(self, device: str, points: Mapping[str, Point]) -> bool:
        q = self.queues[device]
        if not q.live:
            return False
        q.current = dict(points)
        names = changed(CATALOGUE, points, q.queued, self.deadbands)
        if not names:
            return False
        for n in names:
            q.queued[n] = points[n]
        groups = [[n] for n in names] if self.per_point else [names]
        for group in groups:
            self._put(q, {n: points[n] for n in group})
        return True

    def born(self, device: str) -> None:
        q = self.queues[device]
        q.birth_mark = self.serial
        q.queued = dict(q.current)

    def historical(self, item: Item) -> bool:
        """Queued before its device's current birth: its values are older than the birth's."""
        return item.serial <= self.queues[item.device].birth_mark

    def requeue_current(self, device: str) -> None:
        """JSON mode after a (re)connect: the current values again, last, so the retained topics end with
        them."""
        q = self.queues[device]
        for n, p in q.current.items():
            self._put(q, {n: p})
        q.queued = dict(q.current)

    def take(self) -> Item | None:
        """The oldest message of any live device (None: none)."""
        best: DeviceQueue | None = None
        first = 0
        for q in self.queues.values():
            head = q.buffer.peek()
            if q.live and head is not None and (best is None or head.serial < first):
                best, first = q, head.serial
        return None if best is None else best.buffer.take()

    def put_back(self, item: Item) -> None:
        q = self.queues[item.device]
        if q.live:
            q.buffer.put_back(item)

    def stop(self, device: str) -> bool:
        """Its spindle stopped: nothing more is sent for it. True when it was live (a DDEATH is due)."""
        q = self.queues[device]
        was = q.live
        q.live = False
        while q.buffer.take() is not None:
            pass
        return was
