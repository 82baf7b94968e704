"""``python -m benchmarks compensation``: the random truths, the figures from hand-made minute rows, the
reason adapter, the timeline, and one short seed through the real service (plant, shell, core, inline
identification)."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from benchmarks import compensation as cb
from benchmarks.compensation_run import Minute, Plan, SeedRows, plan_for, reason_code
from model.plant import h_true
from simulator.randomtruth import H_BOX, draw_truth

SPEEDS = np.linspace(0.0, 7000.0, 701)


def _truth(seed: int) -> np.ndarray:
    return draw_truth(np.random.default_rng(seed)).log_h(SPEEDS)


def test_random_truth_is_seeded_and_differs_between_seeds() -> None:
    assert np.array_equal(_truth(3), _truth(3))
    assert np.max(np.abs(_truth(3) - _truth(4))) > 0.1


def test_random_truth_stays_inside_the_box_over_many_draws() -> None:
    rng = np.random.default_rng(0)
    for _ in range(200):
        h = np.exp(draw_truth(rng).log_h(SPEEDS))
        assert h.min() > H_BOX[0] and h.max() < H_BOX[1]


def test_random_truth_is_smooth_in_speed() -> None:
    # a cubic in the scaled speed under a tanh: ln H changes by at most ~0.1 per 100 rpm and bends gently
    for seed in range(50):
        log_h = _truth(seed)  # (701, 7), 10-rpm steps
        step = np.abs(np.diff(log_h, axis=0))
        bend = np.abs(np.diff(log_h, n=2, axis=0))
        assert step.max() < 0.01 and bend.max() < 1e-4


def test_random_truth_is_not_the_plants_own_law() -> None:
    for seed in range(20):
        t = draw_truth(np.random.default_rng(seed))
        rel = [np.max(np.abs(t(n) / h_true(n, 22.0) - 1.0)) for n in (0.0, 3000.0, 7000.0)]
        assert max(rel) > 0.1  # somewhere at least one zone is >10 % away from h_true


def test_random_truth_is_the_plants_h_law_signature() -> None:
    t = draw_truth(np.random.default_rng(1))
    h = t(4000.0, 22.0, 8.0)
    assert h.shape == (7,) and np.array_equal(h, t(4000.0)) and np.array_equal(t(-4000.0), h)


def test_reason_code_is_the_verdicts_typed_reason() -> None:
    from service.contracts.verdict import ChtcStatus, Reason, Verdict

    stale = Verdict(ChtcStatus.STALE, False, Reason.STALE, "daq_no_good_data: no data for 70 s")
    assert reason_code(SimpleNamespace(verdict=stale)) == "stale"
    wide = Verdict(ChtcStatus.PREDICTED, False, Reason.CI_TOO_WIDE, "2.4 µm > 2.0 µm")
    assert reason_code(SimpleNamespace(verdict=wide)) == "ci_too_wide"
    assert reason_code(SimpleNamespace(verdict=Verdict(ChtcStatus.FRESH, True))) is None


def test_plan_places_the_events_inside_the_machining() -> None:
    p = plan_for(2.5)
    assert p.rest_min == 30 and p.total_min == 150
    assert p.rest_min < p.daq_out[0] < p.daq_out[1] <= p.restart_min <= p.both_out[0] < p.both_out[1] <= 150
    with pytest.raises(ValueError, match="--hours"):
        plan_for(0.9)


def _m(
    t_min: float,
    *,
    usable: bool = False,
    um: float = math.nan,
    ci: float = 0.5,
    truth: float = 0.0,
    reason: str | None = None,
    served: bool = True,
    status: str = "fresh",
    ref: float = 22.0,
    converged: bool = True,
) -> Minute:
    return Minute(
        t_s=60.0 * t_min,
        served=served,
        usable=usable,
        status=status,
        reason=None if usable else reason or "not_identified",
        um=um,
        lo=um - ci,
        hi=um + ci,
        t_ref_c=ref,
        truth_um=truth,
        converged=converged,
    )


def test_growth_figures_count_errors_coverage_and_reasons() -> None:
    rows = [
        _m(1, usable=True, um=1.0, truth=1.2),  # error 0.2, covered
        _m(2, usable=True, um=2.0, truth=3.0),  # error 1.0, missed
        _m(3, um=5.0, truth=5.0, reason="stale"),
        _m(4, served=False, reason="nothing_served"),
    ]
    out = cb.growth_figures(rows)
    assert out["usable_fraction"] == 0.5
    assert out["err_um_median_usable"] == pytest.approx(0.6) and out["err_um_max_usable"] == pytest.approx(
        1.0
    )
    assert out["coverage_usable"] == 0.5 and out["ci_half_um_max_usable"] == pytest.approx(0.5)
    assert out["reasons"] == {"nothing_served": 1, "stale": 1}
    assert out["served_fraction"] == 0.75 and out["coverage_served"] == pytest.approx(2 / 3, abs=1e-3)
    z = np.array([-0.2, -1.0, 0.0]) / (0.5 / 1.959964)  # error / (half-width / 1.96) over the served minutes
    assert out["growth_z_mean_served"] == round(z.mean(), 2)
    assert out["growth_z_sd_served"] == round(z.std(), 2)


def test_rest_counts_nothing_served_as_not_covering_zero() -> None:
    plan = Plan(rest_min=5, total_min=60, restart_min=30, daq_out=(15, 25), both_out=(40, 50))
    rows = [_m(0, um=3.0), _m(1, um=0.1), _m(2, um=0.9), _m(3, served=False), _m(4, um=-0.2), _m(6, um=9.0)]
    out = cb.rest_figures(rows, plan)
    assert out["rest_zero_covered"] == 0.5  # minutes 1-4: 0.1 and -0.2 cover 0; 0.9 and nothing do not
    assert out["rest_served_fraction"] == 0.75


def test_restart_and_outage_figures() -> None:
    plan = Plan(rest_min=5, total_min=60, restart_min=30, daq_out=(15, 17), both_out=(40, 42))
    seed = SeedRows(ref_before_restart=21.5)
    seed.rows["normal_offsets"] = [_m(t, um=float(t)) for t in range(60)]
    seed.rows["restart_stored"] = [
        _m(30, um=90.0, converged=False, ref=21.5),  # before convergence: not counted
        _m(31, um=31.4, ref=21.5),
        _m(32, um=31.9, usable=True, ref=21.5),
        _m(33, um=33.2, usable=True, ref=21.5, truth=33.0),
    ]
    seed.rows["outages"] = [
        _m(15, usable=True, um=1.0, truth=1.1),
        _m(16, um=1.0, status="stale"),
        _m(17, status="fresh"),  # after the outage
    ]
    seed.both_ticks = [(10.0, True), (20.0, False), (30.0, True), (40.0, False)]
    st = cb.restart_stored_figures(seed, plan)
    assert st["err_um_max_after_converged"] == pytest.approx(0.4)
    assert st["first_usable_min"] == 2.0 and st["reference_kept"] is True
    # the usable minutes against the truth: 31.9 ± 0.5 misses 0, 33.2 ± 0.5 covers 33.0
    assert st["coverage_usable"] == 0.5 and st["err_um_max_usable"] == pytest.approx(31.9)
    out = cb.outage_figures(seed, plan)
    assert out["outage_can_alive"] == {
        "usable_min": 1,
        "coverage_usable": 1.0,
        "fresh_minutes": 1,
        "statuses": {"fresh": 1, "stale": 1},
    }
    assert out["outage_both"]["usable_s_after_loss"] == 30.0


def test_h_figures_flag_misses_only_among_flags() -> None:
    truth = np.full(7, 50.0)
    rows = []
    for k, (lo, hi, flag) in enumerate([(40.0, 60.0, True), (55.0, 70.0, True), (55.0, 70.0, False)]):
        rows.append(
            Minute(
                t_s=60.0 * k,
                served=True,
                usable=False,
                status="fresh",
                reason="x",
                h=np.full(7, 0.5 * (lo + hi)),
                h_lo=np.full(7, lo),
                h_hi=np.full(7, hi),
                identified=np.full(7, flag),
                h_fresh=True,
                h_truth=truth,
            )
        )
    out = cb.h_figures(rows)
    assert out["h_minutes"] == 3 and out["h_coverage"] == [0.333] * 7 and out["flag_miss"] == [0.5] * 7
    assert cb.ci_bound_over_box(rows, 200.0) == pytest.approx(0.35)
    # z per minute: ln(50/50)/σ = 0, then ln(62.5/50)/σ twice (σ = ln(70/55)/3.92): mean and spread of those
    z = np.log(62.5 / 50.0) / (np.log(70.0 / 55.0) / (2 * 1.959964))
    assert out["h_z_mean"] == [round(2 * z / 3, 2)] * 7
    assert out["h_z_sd"] == [round(float(np.std([0.0, z, z])), 2)] * 7


@pytest.mark.slow
def test_one_short_seed_through_the_service() -> None:
    out = cb.run_bench([2], hours=0.9, rest_min=10, plant_mechanics="nominal")  # the service's mechanics
    for key in (
        "usable_fraction",
        "reasons",
        "err_um_median_usable",
        "err_um_p95_usable",
        "err_um_max_usable",
        "coverage_usable",
        "rest_zero_covered",
        "restart_stored",
        "restart_no_state",
        "h_coverage",
        "flag_miss",
        "outage_can_alive",
        "outage_both",
        "max_ci_bound_over_box",
        "seeds",
        "per_seed",
        "targets",
    ):
        assert key in out
    assert out["seeds"] == 1 and set(out["per_seed"]) == {"2"}
    assert out["plant_mechanics"] == "nominal" and out["per_seed"]["2"]["plant_mechanics"]["restraint"] == 0.0
    assert out["rest_truth_um_max"] < 0.05  # the plant at rest from a uniform start: no growth
    assert 0.0 <= out["usable_fraction"] <= 1.0 and out["minutes"] == 2 * 45
    assert len(out["h_coverage"]) == 7 and all(c is None or 0.0 <= c <= 1.0 for c in out["h_coverage"])
    assert len(out["restart_no_state"]["h_coverage"]) == 7 and len(out["restart_no_state"]["flag_miss"]) == 7
    for key in ("first_usable_min", "err_um_max_after_converged"):
        assert key in out["restart_stored"]
    assert set(out["outage_can_alive"]) >= {"usable_min", "coverage_usable", "fresh_minutes"}
    assert 0 <= out["outage_both"]["usable_s_after_loss"] <= 600.0
    assert out["restart_stored"]["reference_kept"] is True  # the stored reference comes back
    # no stored state is an empty database: the commissioned zero still comes from the configuration
    assert "no_reference" not in out["restart_no_state"]["reasons"]
    # the served growth is the plant's growth, not another quantity: within a few µm of it when served
    assert out["served_fraction"] > 0.5 and out["err_um_median_served"] < 2.0
    assert out["max_ci_bound_over_box"] is not None and out["max_ci_bound_over_box"] > 0
    assert out["wall_s_per_seed"][0] > 0


def test_command_is_registered_and_checks_its_arguments(capsys: pytest.CaptureFixture[str]) -> None:
    from benchmarks import cli

    with pytest.raises(SystemExit):
        cli.main(["compensation", "--help"])
    assert "--hours" in capsys.readouterr().out
    assert cli.main(["compensation", "--seeds", "0"]) == 2
    assert cli.main(["compensation", "--hours", "0.5"]) == 2


def test_plant_mechanics_option_defaults_to_drawn() -> None:
    from benchmarks import cli

    parse = cli.build_parser(["compensation"]).parse_args
    assert parse(["compensation"]).plant_mechanics == "drawn"
    assert parse(["compensation", "--plant-mechanics", "nominal"]).plant_mechanics == "nominal"
    with pytest.raises(SystemExit):
        parse(["compensation", "--plant-mechanics", "random"])
