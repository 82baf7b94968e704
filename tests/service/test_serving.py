"""One serving strategy per identification mode (``service.core.serving``, issue 25): which identification
serves, whether the map's H does, and which H the live state takes, driven as pure objects (no core, no
model). The same rules through the real core and shell: tests/service/test_combined_mode.py and
test_speed_map.py."""

from __future__ import annotations

from dataclasses import replace
from datetime import UTC, datetime, timedelta

import pytest

from service.contracts.mode import IdentificationMode
from service.contracts.records import IdentificationData
from service.contracts.snapshots import ConditionSnapshot, ConditionState, IdentificationRecord
from service.core.config import Restored
from service.core.serving import CombinedServing, PerConditionServing, SpeedMapServing, serving_for
from service.serve.views import data_to_record
from service.settings import Settings, SettingsError

T = datetime(2026, 3, 1, 8, 0, tzinfo=UTC)
H = [88.2, 46.3, 68.5, 46.7, 52.1, 70.2, 16.5]


def _cond(cid: int, state: ConditionState = ConditionState.STABLE) -> ConditionSnapshot:
    return ConditionSnapshot(
        id=cid, speed_rpm=1000.0 * cid, torque_nm=5.0, ambient_c=22.0, since=T, state=state
    )


def _rec(rid: int, cond: ConditionSnapshot, method: str = "hybrid") -> IdentificationRecord:
    data = IdentificationData(
        id=rid,
        condition_id=cond.id,
        started_at=T,
        finished_at=T,
        window_start=T - timedelta(minutes=10),
        window_end=T,
        reason="scheduled",
        outcome="ok",
        method=method,
        model_version="m",
        h=[x + rid for x in H],
        ci95_lo=[0.9 * x for x in H],
        ci95_hi=[1.1 * x for x in H],
        identified=[True] * 7,
        f=0.0225,
        fit=1 / 1.0225,
        rmse_c=0.15,
        diagnostics={"at_bound": [False] * 7},
    )
    return data_to_record(data, cond)


@pytest.mark.parametrize(
    ("value", "strategy"),
    [("per_condition", PerConditionServing), ("speed_map", SpeedMapServing), ("combined", CombinedServing)],
)
def test_each_mode_has_its_strategy_and_keeps_the_settings_spelling(value: str, strategy: type) -> None:
    mode = Settings(identification={"mode": value}).identification.mode
    assert mode is IdentificationMode(value) and mode == value and f"{mode}" == value
    serving = serving_for(mode, Restored())
    assert type(serving) is strategy and serving.mode is mode
    with pytest.raises(SettingsError, match=r"identification\.mode"):
        Settings.from_toml(None, identification={"mode": "perCondition"})


def test_per_condition_serves_its_newest_identification_and_never_the_map() -> None:
    last = _rec(4, _cond(1))
    serving = serving_for(IdentificationMode.PER_CONDITION, Restored(last=last))
    assert serving.current is last and serving.from_restore and not serving.map_serves
    new = _rec(5, _cond(2))
    assert serving.identified(new, (1.1, 0.9), _cond(2)) == (new, (1.1, 0.9))  # the live state takes its H
    assert serving.current is new and not serving.from_restore and not serving.map_serves
    assert serving.follow(_cond(2, ConditionState.CHANGING)) is None


def test_speed_map_serves_each_fit_and_leaves_the_live_h_to_the_map() -> None:
    serving = serving_for(IdentificationMode.SPEED_MAP, Restored())
    assert serving.current is None and serving.map_serves
    fit = _rec(1, _cond(1), method="speed-map")
    assert serving.mapped(fit, _cond(1)) is None  # the live state's H comes from the map at each sample
    assert serving.current is fit and serving.map_serves


def test_combined_serves_the_held_conditions_own_identification_and_the_map_elsewhere() -> None:
    serving = serving_for(IdentificationMode.COMBINED, Restored())
    held = _cond(1)
    fit = _rec(1, held, method="speed-map")
    assert serving.mapped(fit, held) is None
    assert serving.current is fit and serving.map_serves
    generation = serving.generation
    own = _rec(2, held)
    assert serving.identified(own, None, held) == (own, None)  # the held condition's H goes to the live state
    assert serving.current is own and not serving.map_serves and serving.generation > generation
    # a newer map fit does not displace it while the condition holds
    assert serving.mapped(_rec(3, held, method="speed-map"), held) is None
    assert serving.current is own and not serving.map_serves
    # a pending change (CHANGING) or a new condition: the map serves again, its H at the next sample
    generation = serving.generation
    assert serving.follow(replace(held, state=ConditionState.CHANGING)) is None
    assert serving.current.id == 3 and serving.map_serves and serving.generation > generation
    assert serving.follow(_cond(2)) is None and serving.current.id == 3
    # back at the stable held condition its own identification serves again
    assert serving.follow(held) == (own, None) and serving.current is own


def test_combined_serves_a_per_condition_identification_before_the_first_map_fit() -> None:
    serving = serving_for(IdentificationMode.COMBINED, Restored())
    other = _rec(1, _cond(1))
    assert serving.identified(other, None, _cond(2)) is None  # not at the held condition: not its H
    assert serving.current is other and not serving.map_serves


def test_combined_waits_for_the_re_identification_of_a_restored_condition() -> None:
    held = _cond(1)
    last = _rec(4, held)
    serving = serving_for(IdentificationMode.COMBINED, Restored(last=last, conditions=(held,)))
    assert serving.follow(held) is None  # restored: served (there is no map), but its H is not re-applied
    assert serving.current is last and serving.from_restore and not serving.map_serves
    fit = _rec(5, held, method="speed-map")
    assert serving.mapped(fit, held) is None  # the stored one does not count as held: the map serves
    assert serving.current is fit and serving.map_serves and not serving.from_restore
