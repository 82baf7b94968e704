"""One serving strategy per identification mode (``service.identify.mode.IdentificationMode``,
docs/design/hmap.md).

A strategy decides what runs (``tracks``: the per-condition schedule, the speed map, or both) and which
identification serves: ``current`` (what /chtc shows, the live state's H) and ``map_serves`` (H comes from
the speed map at the current speed). The core tells it when an identification finished (``identified``: a
per-condition one, ``mapped``: a map fit) and when the condition may have changed state (``follow``); each
returns the identification whose H the live state takes now (None: its H stays, or comes from the map).

    PerConditionServing   the per-condition schedule; its newest identification serves
    SpeedMapServing       the speed map; its newest fit serves, H from the map at the current speed
    CombinedServing       both; the held condition's own per-condition identification while that condition
                          is stable, the newest map fit elsewhere (docs/design/hmap.md "Combined mode")

Pure: no I/O, no clock.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, Protocol

from service.contracts.mode import IdentificationMode
from service.contracts.snapshots import ConditionSnapshot, ConditionState, IdentificationRecord
from service.core.config import CoreConfig, Restored
from service.core.maptrack import MapSide, MapTrack, NoMaps
from service.core.parts import CoreParts, Decides, Load, Served
from service.core.schedtrack import ManualTrack, ScheduleTrack, Unscheduled

__all__ = [
    "CombinedServing",
    "PerConditionServing",
    "Served",
    "Serving",
    "SpeedMapServing",
    "Tracks",
    "serving_for",
]


@dataclass(frozen=True)
class Tracks:
    """What runs in a mode: the speed map, the per-condition schedule, and which of them takes manual
    requests."""

    maps: MapSide
    schedule: ScheduleTrack
    manual: ManualTrack


class Serving(Decides, Protocol):
    """See the module docstring. ``generation`` changes whenever what serves changes (the map's H is then
    given to the live state again at the next sample when the map serves)."""

    mode: ClassVar[IdentificationMode]

    def longest_window_s(self, config: CoreConfig) -> float:
        """The longest window a job may start back in time [s] (the live state keeps its snapshots 3× this
        long)."""
        ...

    def tracks(self, parts: CoreParts, restored: Restored) -> Tracks: ...


class PerConditionServing:
    """The paper's protocol: one identification per held condition, the newest serves."""

    mode: ClassVar[IdentificationMode] = IdentificationMode.PER_CONDITION

    def __init__(self, restored: Restored) -> None:
        self.current = restored.last
        self.from_restore = restored.last is not None
        self.map_serves = False
        self.generation = 0

    def longest_window_s(self, config: CoreConfig) -> float:
        return config.scheduler.max_window_s

    def tracks(self, parts: CoreParts, restored: Restored) -> Tracks:
        schedule = ScheduleTrack(parts)
        return Tracks(maps=NoMaps(), schedule=schedule, manual=schedule)

    def identified(
        self, rec: IdentificationRecord, load: Load, condition: ConditionSnapshot | None
    ) -> Served | None:
        self.current, self.from_restore = rec, False
        return rec, load

    def mapped(self, rec: IdentificationRecord, condition: ConditionSnapshot | None) -> Served | None:
        self.current, self.from_restore = rec, False
        return None

    def follow(self, condition: ConditionSnapshot | None) -> Served | None:
        return None


class SpeedMapServing(PerConditionServing):
    """H = F(n, Ti): the newest map fit serves (a restored one, stale until re-fitted, whatever was last);
    the live state takes the map's H at each sample's speed (``MapTrack``)."""

    mode: ClassVar[IdentificationMode] = IdentificationMode.SPEED_MAP

    def __init__(self, restored: Restored) -> None:
        super().__init__(restored)
        self.map_serves = True
        self.map_last = None if restored.speed_map is None else (restored.map_last or restored.last)
        if self.map_last is not None:
            self.current = self.map_last

    def longest_window_s(self, config: CoreConfig) -> float:
        """The per-condition ``max_window_s`` or the map's rolling window if longer (a map window starting
        before the oldest kept snapshot could not start: found with a 90-s ``max_window_s`` and the map's
        10-min first window, tests/service/test_speed_map.py)."""
        return max(config.scheduler.max_window_s, config.speed_map.window_s)

    def tracks(self, parts: CoreParts, restored: Restored) -> Tracks:
        maps = MapTrack(parts, restored.speed_map)
        return Tracks(maps=maps, schedule=Unscheduled(parts), manual=maps)


class CombinedServing(SpeedMapServing):
    """Both tracks run. The held condition's per-condition identification serves (``current``, the live
    state's H) while that condition is stable (not a restored one: a stored one waits for its
    re-identification, as in per-condition mode); else the newest map fit (the per-condition one when there
    is no map yet). Measured better at a held condition on the chain and after restarts, the map on a duty
    cycle (docs/design/hmap.md "Combined mode")."""

    mode: ClassVar[IdentificationMode] = IdentificationMode.COMBINED

    def __init__(self, restored: Restored) -> None:
        super().__init__(restored)
        self._restored = tuple(r for r in (restored.last, self.map_last) if r is not None)
        self._map_rec: IdentificationRecord | None = self.map_last
        self._cond_rec = None if restored.last is self.map_last else restored.last
        self._cond_load: Load = None

    def tracks(self, parts: CoreParts, restored: Restored) -> Tracks:
        maps = MapTrack(parts, restored.speed_map)
        # the held condition's fits are MAP fits: the physics prior plus the map's information there
        return Tracks(maps=maps, schedule=ScheduleTrack(parts, prior=maps.h_prior), manual=maps)

    def identified(
        self, rec: IdentificationRecord, load: Load, condition: ConditionSnapshot | None
    ) -> Served | None:
        self._cond_rec, self._cond_load = rec, load
        return self.follow(condition)

    def mapped(self, rec: IdentificationRecord, condition: ConditionSnapshot | None) -> Served | None:
        self._map_rec = rec
        return self.follow(condition)

    def follow(self, condition: ConditionSnapshot | None) -> Served | None:
        pc = self._cond_rec
        held = (
            pc is not None
            and all(pc is not r for r in self._restored)
            and condition is not None
            and pc.condition.id == condition.id
            and condition.state is ConditionState.STABLE
        )
        target = pc if held else (self._map_rec if self._map_rec is not None else pc)
        serves = not held and self._map_rec is not None
        if target is None or (target is self.current and serves == self.map_serves):
            return None
        self.current = target
        self.from_restore = any(target is r for r in self._restored)
        self.map_serves = serves
        self.generation += 1
        return (pc, self._cond_load) if held and pc is not None else None


_STRATEGIES: dict[IdentificationMode, type[PerConditionServing]] = {
    s.mode: s for s in (PerConditionServing, SpeedMapServing, CombinedServing)
}


def serving_for(mode: IdentificationMode, restored: Restored) -> Serving:
    """The serving strategy of ``mode``, starting from what the database knew."""
    return _STRATEGIES[IdentificationMode(mode)](restored)
