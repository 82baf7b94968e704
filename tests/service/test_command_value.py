"""The command value and the CI gate (service.serve.command, service.serve.cigate): pure, driven by time."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from service.serve.cigate import CiGateError, CiGateLimits, CiGateState, step_gate
from service.serve.command import (
    PROFILES,
    CommandError,
    CommandState,
    CommandStatus,
    advance,
    profile_from,
)
from service.serve.controlled import ControlLimits, ControlState, step_control

GENERIC = PROFILES["generic"]


def _run(
    steps: list[tuple[float, bool, float | None, float | None]], *, hold_s: float = 60.0
) -> list[CommandState]:
    state = CommandState.start(steps[0][0])
    out = []
    for t, usable, growth, best in steps:
        state = advance(
            state, t=t, usable=usable, growth_um=growth, best_um=best, profile=GENERIC, hold_s=hold_s
        )
        out.append(state)
    return out


def test_follows_a_usable_growth_after_a_bounded_ramp_from_zero() -> None:
    states = _run([(float(t), True, 3.0, 3.0) for t in range(0, 20)])
    values = [s.value_um for s in states]
    assert max(abs(np.diff(values))) <= GENERIC.max_step_um + 1e-12
    assert states[1].status is CommandStatus.RATE_LIMITED  # 0 -> 3 µm at 0.5 µm/s
    assert states[-1].value_um == pytest.approx(3.0)
    assert states[-1].status is CommandStatus.FOLLOWING


def test_holds_then_fades_to_the_best_estimate_and_returns_without_a_jump() -> None:
    steps: list[tuple[float, bool, float | None, float | None]] = []
    steps += [(float(t), True, 5.0, 5.0) for t in range(0, 30)]  # settled at 5 µm
    steps += [(float(t), False, None, 9.0) for t in range(30, 150)]  # CI wide: mean 9 µm
    steps += [(float(t), True, 2.0, 2.0) for t in range(150, 200)]  # usable again at 2 µm
    states = _run(steps, hold_s=60.0)
    by_t = {int(s.t): s for s in states}
    assert by_t[40].status is CommandStatus.HOLDING and by_t[40].value_um == pytest.approx(5.0)
    assert by_t[88].value_um == pytest.approx(5.0)  # held for 60 s after the last usable instant (29 s)
    assert by_t[95].status is CommandStatus.FADING and 5.0 < by_t[95].value_um < 9.0
    assert by_t[149].value_um == pytest.approx(9.0)
    assert by_t[151].status is CommandStatus.RATE_LIMITED  # back from 9 to 2 µm at the profile's rate
    assert by_t[199].value_um == pytest.approx(2.0) and by_t[199].status is CommandStatus.FOLLOWING
    steps_um = np.abs(np.diff([s.value_um for s in states]))
    assert steps_um.max() <= GENERIC.max_rate_um_s * 1.0 + 1e-12  # one update per second


def test_moves_to_zero_only_when_nothing_is_known() -> None:
    steps: list[tuple[float, bool, float | None, float | None]] = [
        (float(t), True, 4.0, 4.0) for t in range(12)
    ]
    steps += [(float(t), False, None, None) for t in range(12, 100)]
    states = _run(steps, hold_s=10.0)
    assert states[15].status is CommandStatus.HOLDING
    assert states[-1].status is CommandStatus.NONE and states[-1].value_um == pytest.approx(0.0)


def test_the_absolute_limit_clips_and_says_so() -> None:
    prof = profile_from("generic", limit_um=2.0, max_step_um=100.0, max_rate_um_s=100.0)
    state = advance(
        CommandState.start(0.0), t=1.0, usable=True, growth_um=5.0, best_um=5.0, profile=prof, hold_s=1
    )
    assert state.value_um == 2.0 and state.status is CommandStatus.AT_LIMIT
    state = advance(state, t=2.0, usable=True, growth_um=-7.0, best_um=-7.0, profile=prof, hold_s=1)
    assert state.value_um == -2.0 and state.status is CommandStatus.AT_LIMIT


def test_a_clock_stepping_back_moves_nothing() -> None:
    state = advance(
        CommandState.start(100.0), t=110.0, usable=True, growth_um=1.0, best_um=1.0, profile=GENERIC, hold_s=1
    )
    back = advance(state, t=50.0, usable=True, growth_um=-50.0, best_um=-50.0, profile=GENERIC, hold_s=1)
    assert back.value_um == state.value_um and back.t == state.t


@pytest.mark.parametrize("seed", range(5))
def test_random_verdicts_never_step_beyond_the_profile(seed: int) -> None:
    rng = np.random.default_rng(seed)
    for name, prof in PROFILES.items():
        state = CommandState.start(0.0)
        t, prev = 0.0, 0.0
        for _ in range(500):
            t += float(rng.uniform(0.1, 5.0))
            growth = float(rng.normal(0, 30))
            best = None if rng.random() < 0.2 else float(rng.normal(0, 30))
            state = advance(
                state,
                t=t,
                usable=bool(rng.random() < 0.6),
                growth_um=growth,
                best_um=best,
                profile=prof,
                hold_s=20,
            )
            assert abs(state.value_um - prev) <= prof.max_step_um + 1e-9, name
            assert abs(state.value_um) <= prof.limit_um
            prev = state.value_um


def test_bad_profiles_and_inputs_name_the_field() -> None:
    with pytest.raises(CommandError, match=r"controller\.profile"):
        profile_from("okuma")
    with pytest.raises(CommandError, match=r"controller\.max_rate_um_s"):
        profile_from("fanuc", max_rate_um_s=0.0)
    with pytest.raises(CommandError, match="growth_um"):
        advance(
            CommandState.start(0),
            t=1,
            usable=True,
            growth_um=float("nan"),
            best_um=0,
            profile=GENERIC,
            hold_s=1,
        )


LIMITS = CiGateLimits(max_ci95_um=2.0, enter_fraction=0.8, exit_hold_s=120.0, hard_fraction=1.5)


def _gate(halves: list[float], dt: float = 5.0) -> list[bool]:
    state, out = CiGateState(), []
    for k, half in enumerate(halves):
        state = step_gate(state, t=k * dt, half_um=half, limits=LIMITS)
        out.append(state.open)
    return out


def test_gate_opens_below_the_entry_fraction_only() -> None:
    assert _gate([1.9, 1.7, 1.61]) == [False, False, False]
    assert _gate([1.9, 1.6, 1.9]) == [False, True, True]


def test_gate_rides_out_a_half_width_that_hovers_at_the_tolerance() -> None:
    rng = np.random.default_rng(1)
    halves = [1.5, *(1.95 + 0.1 * rng.standard_normal(200))]  # median 1.95 µm, crossing 2.0 often
    opened = _gate([min(h, 2.9) for h in halves], dt=5.0)
    flips = sum(a != b for a, b in itertools.pairwise(opened))
    plain = [h <= 2.0 for h in halves]
    plain_flips = sum(a != b for a, b in itertools.pairwise(plain))
    assert plain_flips > 20 and flips <= 2


def test_gate_closes_after_the_hold_or_at_once_past_the_hard_limit() -> None:
    assert _gate([1.0] + [2.2] * 30)[-1] is False  # 145 s above 2.0 µm
    assert _gate([1.0] + [2.2] * 20)[-1] is True  # 100 s above: still open
    assert _gate([1.0, 3.1]) == [True, False]  # past 1.5 × the tolerance
    assert _gate([1.0, float("nan")]) == [True, False]


def test_gate_limits_name_the_setting() -> None:
    with pytest.raises(CiGateError, match="ci_enter_fraction"):
        CiGateLimits(max_ci95_um=2.0, enter_fraction=1.2, exit_hold_s=1, hard_fraction=1.5)
    with pytest.raises(CiGateError, match="ci_hard_fraction"):
        CiGateLimits(max_ci95_um=2.0, enter_fraction=0.8, exit_hold_s=1, hard_fraction=0.9)


# ----------------------------------------------------------- the gated verdict and the command together

CONTROL = ControlLimits(gate=LIMITS, profile=GENERIC, hold_s=60.0)


Step = tuple[float, bool, str | None, str, float | None, float]


def _control(steps: list[Step]) -> list[tuple[ControlState, bool]]:
    state, out = ControlState.start(steps[0][0]), []
    for t, usable, reason, status, growth, half in steps:
        state, ok = step_control(
            state,
            t=t,
            usable=usable,
            reason=reason,
            status=status,
            growth_um=growth,
            half_um=half,
            limits=CONTROL,
        )
        out.append((state, ok))
    return out


def test_a_safety_reason_acts_at_once_and_the_command_holds() -> None:
    steps: list[Step] = [(float(t), True, None, "fresh", 4.0, 1.0) for t in range(0, 30)]
    steps += [(float(t), False, "stale", "stale", 4.0, 1.0) for t in range(30, 40)]
    out = _control(steps)
    assert out[29][1] is True and out[30][1] is False  # the gate is open, the verdict drops at once
    assert out[35][0].command.status is CommandStatus.HOLDING
    assert out[35][0].command.value_um == pytest.approx(4.0)


def test_a_wide_ci_alone_keeps_the_verdict_and_then_fades_to_the_growth_mean() -> None:
    steps: list[Step] = [(float(t), True, None, "fresh", 4.0, 1.0) for t in range(0, 30)]
    steps += [(float(t), False, "ci_too_wide", "fresh", 6.0, 2.2) for t in range(30, 400, 5)]
    out = _control(steps)
    by_t = {int(s.command.t): (s, ok) for s, ok in out}
    assert by_t[100][1] is True  # 70 s above the tolerance: the gate (120 s) holds the verdict
    assert by_t[160][1] is False and by_t[160][0].command.status is CommandStatus.HOLDING
    assert by_t[395][0].command.value_um == pytest.approx(6.0)  # faded to the growth's mean
    assert by_t[395][0].command.status is CommandStatus.FADING


def test_the_daq_lost_fades_to_the_open_loop_prediction_and_nothing_known_to_zero() -> None:
    steps: list[Step] = [(float(t), True, None, "fresh", 4.0, 1.0) for t in range(0, 30)]
    steps += [(float(t), False, "open_loop_too_long", "predicted", 7.0, 1.0) for t in range(30, 200)]
    out = _control(steps)
    assert out[-1][0].command.value_um == pytest.approx(7.0)
    steps = [(float(t), True, None, "fresh", 4.0, 1.0) for t in range(0, 30)]
    steps += [(float(t), False, "state_converging", "stale", 7.0, 1.0) for t in range(30, 200)]
    out = _control(steps)
    assert out[-1][0].command.value_um == pytest.approx(0.0)
    assert out[-1][0].command.status is CommandStatus.NONE


def test_the_controller_rewrites_only_the_ci_part_of_the_verdict() -> None:
    from service.contracts.verdict import ChtcStatus, Reason, Verdict
    from service.serve.controlled import Controller

    ctl = Controller(CONTROL, tool_dir=-1)
    plain_ok = Verdict(ChtcStatus.FRESH, True)
    # within the tolerance but above the entry level (1.6 µm): the closed gate says ci_too_wide
    verdict, cmd = ctl.step(0.0, plain_ok, growth_um=3.0, half_um=1.8)
    assert not verdict.usable and verdict.reason is Reason.CI_TOO_WIDE and "1.60" in (verdict.detail or "")
    verdict, cmd = ctl.step(10.0, plain_ok, growth_um=3.0, half_um=1.2)
    assert verdict.usable and cmd.value_um == pytest.approx(1.0)  # ramping at 1 µm per update
    wide = Verdict(ChtcStatus.FRESH, False, Reason.CI_TOO_WIDE, "wide")
    verdict, cmd = ctl.step(20.0, wide, growth_um=3.0, half_um=2.3)
    assert verdict.usable and verdict.reason is None  # held open by the gate (120 s)
    stale = Verdict(ChtcStatus.STALE, False, Reason.STALE, "no samples")
    verdict, cmd = ctl.step(30.0, stale, growth_um=3.0, half_um=1.0)
    assert verdict is stale and cmd.status is CommandStatus.HOLDING
    assert cmd.plc.sd43900_mm == pytest.approx(cmd.value_um * 1e-3)  # tool to -Z: correction = +growth
    # a clock stepping back moves nothing
    _verdict, back = ctl.step(5.0, plain_ok, growth_um=-40.0, half_um=1.0)
    assert back.value_um == cmd.value_um and back.at == cmd.at


def test_the_control_state_survives_the_live_checkpoint() -> None:
    from service.contracts.checkpoint import LiveCheckpoint

    steps: list[Step] = [(float(t), True, None, "fresh", 4.0, 1.0) for t in range(0, 30)]
    steps += [(float(t), False, "ci_too_wide", "fresh", 6.0, 2.2) for t in range(30, 60)]
    state = _control(steps)[-1][0]
    r = 3
    cp = LiveCheckpoint(
        t=60.0,
        model_version="m",
        converged=True,
        inputs=(20.0, 0.0, 0.0),
        mean=np.zeros(r),
        cov=np.eye(r),
        cross=np.zeros((r, 9)),
        bias_s=np.zeros((r, 4)),
        bias_m=np.zeros((r, r)),
        control=state.to_array(),
    )
    back = LiveCheckpoint.from_parts(
        cp.to_bytes(), t=cp.t, model_version=cp.model_version, converged=True, inputs=cp.inputs
    )
    assert ControlState.from_array(back.control) == state
    assert state.gate.above_since is not None and state.command.status is not CommandStatus.NONE
    assert ControlState.from_array(None) is None and ControlState.from_array(np.zeros(3)) is None


def test_open_loop_the_gate_closes_as_soon_as_the_ci_passes_the_tolerance() -> None:
    steps: list[Step] = [(float(t), True, None, "fresh", 4.0, 1.0) for t in range(0, 30)]
    steps += [(30.0, False, "ci_too_wide", "predicted", 4.5, 2.2)]
    assert _control(steps)[-1][1] is False  # fresh data: the gate would hold it for 120 s
