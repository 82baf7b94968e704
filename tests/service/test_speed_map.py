"""Speed-map mode (``identification.mode = "speed_map"``, issue 17) through the real core and shell: a short
duty cycle from the virtual plant (its own mesh and truth), /chtc served from the map at the current speed
right after a change, the status rules, the map persisted and restored as stale, the settings."""

from __future__ import annotations

from dataclasses import replace
from datetime import UTC, datetime, timedelta

import numpy as np
import pytest

from model.geometry import load_spindle
from model.hmap import Z95
from model.plant import VirtualPlant, h_true
from service.contracts.mode import IdentificationMode
from service.contracts.verdict import ChtcStatus, DataCode, DataProblem
from service.core.config import core_config, map_config
from service.core.machine import ServiceCore
from service.host.persistence import open_persistence
from service.identify.prior import ServedMapPrior
from service.identify.speedmap import MapConfig, SpeedMap, SpeedMapError
from service.serve.policy import map_verdict
from service.settings import ExperimentalSettings, Settings, SettingsError
from service.shell.service import MAP_H_BOX, SoftSensorService
from simulator.duty import condition_at, duty_profile
from tests.modes import per_condition

from .conftest import inline_service, samples_of

DURATION_S = 2700.0  # 5 min idle + 40 min of speed changes


def map_settings(**kw: object) -> Settings:
    """Speed-map mode with ``kw`` in whichever section holds each key."""
    exp = {k: v for k, v in kw.items() if k in ExperimentalSettings.model_fields}
    ident = {k: v for k, v in kw.items() if k not in exp}
    return Settings(identification={"mode": "speed_map", **ident}, experimental=exp)  # type: ignore[arg-type]


# The tests on the duty cycle below are ``slow``: the plant run and the service over it take ~12 s.
@pytest.fixture(scope="module")
def duty():
    profile = duty_profile(7, duration_s=DURATION_S)
    run = VirtualPlant(load_spindle(), seed=7).run(profile, dt_s=10.0)  # the plant's own (finer) mesh
    return profile, run, samples_of(run)


_service = inline_service


@pytest.fixture(scope="module")
def served(duty, loaded_model):
    """The duty cycle through the service in map mode; per sample: (speed, snapshot) after it."""
    samples = duty[2]
    svc, clock = _service(loaded_model, map_settings(), samples)
    seen = []
    for s in samples:
        clock.at_least(s.t)
        svc.on_sample(s)
        seen.append((s.speed_rpm, s.ambient_c, svc.chtc(), svc.view.speed_map))
    return svc, seen


def test_settings_choose_the_mode_and_validate_the_map_keys() -> None:
    assert Settings().identification.mode is IdentificationMode.COMBINED  # docs/design/hmap.md "Default"
    for mode in IdentificationMode:  # the settings' spelling is the enum's value
        assert core_config(Settings(identification={"mode": mode.value})).mode is mode
    cfg = map_config(map_settings(map_window_min=30, map_debounce_s=10, map_fresh_min=12))
    assert isinstance(cfg, MapConfig)
    assert (cfg.window_s, cfg.debounce_s, cfg.fresh_s, cfg.family) == (1800.0, 10.0, 720.0, "nodes")
    with pytest.raises(SettingsError, match=r"identification\.mode"):
        Settings.from_toml(None, identification={"mode": "speedmap"})
    with pytest.raises(SettingsError, match="map_min_window_min"):
        Settings.from_toml(
            None, identification={"mode": "speed_map"}, experimental={"map_min_window_min": 90}
        )
    with pytest.raises(SettingsError, match="map_margin_rpm"):
        Settings.from_toml(None, experimental={"map_margin_rpm": -1})
    with pytest.raises(SpeedMapError, match="window_s"):
        replace(cfg, window_s=0.0)


@pytest.mark.slow
def test_map_served_at_the_current_speed_right_after_a_change(served, duty) -> None:
    svc, seen = served
    assert svc.view.h_form_sd == 0.15  # the default model-form error of the served bands
    served_prior = ServedMapPrior(svc.core.model.spec, svc.core.model.ref.h_box)
    profile, run, _ = duty
    fitted = [k for k, (_, _, _, m) in enumerate(seen) if m is not None]
    assert fitted, "no map fit in 45 min"
    assert fitted[0] * 10.0 <= 300.0 + 600.0 + 120.0  # the first fit after 10 min of data (plus a change)
    changes = [
        k
        for k in range(fitted[0] + 1, len(seen))
        if seen[k][0] != seen[k - 1][0] and seen[k][3] is not None and seen[k][3] is seen[k - 1][3]
    ]
    assert len(changes) >= 3
    for k in changes:  # the first sample at the new speed: no fit since, H from the map at the new speed
        speed, ambient, snap, m = seen[k]
        assert snap is not None
        # the map's information at the new speed on the cold physics prior (service.identify.prior)
        prior = served_prior.at(m, level_sd=0.0, speed_rpm=speed, ambient_c=ambient)
        np.testing.assert_allclose(snap.h, np.exp(prior.log_mean))
        # its band widened by the model-form error and truncated to the map's level bounds (views.widen_band)
        half = Z95 * np.sqrt(np.diag(prior.log_cov) + svc.view.h_form_sd**2)
        np.testing.assert_allclose(
            snap.ci95_hi, np.minimum(snap.h * np.exp(half), np.maximum(MAP_H_BOX[1], snap.h))
        )
        np.testing.assert_array_equal(snap.record.prior_dominated, prior.dominated(np.diag(prior.log_cov)))
        _, lo, hi = m.h_at([speed], ambient)
        assert np.all((lo[0] <= snap.h) & (snap.h <= hi[0]))  # inside the map's own band there
        assert np.all(snap.ci95_hi <= 10 * svc.core.model.ref.h_box[1])  # never beyond 10x the search box
        assert not np.allclose(snap.h, m.h_at([seen[k - 1][0]], ambient)[0])
        visited = m.covered(speed, margin_rpm=500.0, min_visit_s=60.0)
        assert (snap.status is ChtcStatus.FRESH) == visited, (speed, snap.status, snap.reason)
        if not visited:
            assert snap.reason is not None and snap.reason.startswith("speed_not_visited")
            assert not snap.usable_for_compensation
    # the served H against the plant's truth where the map is fresh: H6 and H7 within 25 %
    errs = []
    for k, (_, _, snap, _) in enumerate(seen):
        if snap is not None and snap.status is ChtcStatus.FRESH and k % 6 == 0:
            seg = condition_at(profile, float(run.times_s[k]))
            errs.append(np.asarray(snap.h) / h_true(seg.speed_rpm, seg.ambient_c) - 1.0)
    assert len(errs) >= 10
    med = np.median(np.abs(np.array(errs)), axis=0)
    assert med[5] < 0.25 and med[6] < 0.25, med


@pytest.mark.slow
def test_chtc_map_snapshot_and_per_condition_mode(served, loaded_model, duty) -> None:
    svc, _ = served
    snap = svc.chtc_map()
    assert snap is not None and snap.family == "nodes"
    assert snap.speeds_rpm[0] == 0.0 and snap.speeds_rpm[-1] == 7000.0
    k = snap.speeds_rpm.size
    assert snap.h_w_m2k.shape == snap.ci95_lo_w_m2k.shape == snap.ci95_hi_w_m2k.shape == (k, 7)
    assert np.all(snap.ci95_lo_w_m2k < snap.h_w_m2k) and np.all(snap.h_w_m2k < snap.ci95_hi_w_m2k)
    assert snap.visited_rpm.size == snap.visited_s.size > 3 and np.all(np.diff(snap.visited_rpm) > 0)
    assert snap.fitted_at.tzinfo is not None and snap.identification_id == svc.view.current.id
    assert not snap.h_w_m2k.flags.writeable
    _, _, samples = duty
    per_cond, clock = _service(loaded_model, per_condition(), samples[:40])
    for s in samples[:40]:
        clock.at_least(s.t)
        per_cond.on_sample(s)
    assert per_cond.chtc_map() is None


@pytest.mark.slow
def test_status_rules(served) -> None:
    svc, _ = served
    m = svc.view.speed_map
    assert m is not None
    vis = float(m.visited_rpm[np.argmax(m.visited_s)])
    far = next(s for s in np.arange(0.0, 7001.0, 100.0) if not m.covered(s, margin_rpm=500, min_visit_s=60))
    now = m.fitted_at + timedelta(minutes=1)

    def status(**kw: object) -> str:
        base: dict[str, object] = {
            "newest_t": now,
            "speed_rpm": vis,
            "problems": (),
            "converging_since": None,
            "fresh_s": 900.0,
            "margin_rpm": 500.0,
            "min_visit_s": 60.0,
        }
        f = map_verdict(kw.pop("map", m), **(base | kw))  # type: ignore[arg-type]
        assert f.usable == (f.reason is None)
        return f"{f.status.value} {'' if f.reason is None else f.reason.value}".strip()

    assert status() == "fresh"
    assert status(speed_rpm=far) == "identifying speed_not_visited"
    assert status(newest_t=m.fitted_at + timedelta(minutes=16)) == "identifying map_old"
    assert status(problems=(DataProblem(DataCode.DAQ_NO_GOOD_DATA, ""),)) == "stale stale"
    assert status(converging_since=now) == "converging state_converging"
    restored = SpeedMap.from_json(m.to_json(), identification_id=m.identification_id)
    assert status(map=restored) == "stale restored"
    assert status(newest_t=None, speed_rpm=None) == "no-data no_data"
    assert status(speed_rpm=None) == "stale stale"  # a sample, but no speed known at all


@pytest.mark.slow
def test_one_missing_can_value_changes_no_status(duty, loaded_model) -> None:
    """Issue 26: a sample whose speed is missing (one lost CAN value) while samples keep flowing turned
    /chtc and /chtc/map to ``no-data`` ("no sample acquired yet"). The map is served at the condition's
    speed then, with the status the samples around it have."""
    _, _, samples = duty
    svc, clock = _service(loaded_model, map_settings(), samples)
    for s in samples:
        clock.at_least(s.t)
        svc.on_sample(s)
    before, map_before = svc.chtc(), svc.chtc_map()
    assert before is not None and map_before is not None
    assert before.status is not ChtcStatus.NO_DATA
    last = samples[-1]
    gap = replace(last, t=last.t + timedelta(seconds=10), speed_rpm=float("nan"))
    clock.at_least(gap.t)
    svc.on_sample(gap)
    after, map_after = svc.chtc(), svc.chtc_map()
    assert after is not None and map_after is not None
    assert after.status is before.status, (before.status, after.status, after.reason)
    assert map_after.status is map_before.status
    assert np.allclose(after.h, before.h)


@pytest.mark.slow
def test_restart_restores_the_map_as_stale(tmp_path, duty, loaded_model) -> None:
    _, _, samples = duty
    s = map_settings()
    db = s.database.model_copy(update={"url": f"sqlite:///{tmp_path / 'chtc.db'}"})
    first = open_persistence(db, migrate=True)
    svc, clock = _service(loaded_model, s, samples[:150], writer=first.sink)
    for smp in samples[:150]:
        clock.at_least(smp.t)
        svc.on_sample(smp)
    m = svc.view.speed_map
    assert m is not None and not m.restored
    first.close()

    second = open_persistence(db, migrate=True)
    r = second.restored.speed_map
    assert r is not None and r.restored and r.identification_id == m.identification_id
    np.testing.assert_allclose(r.mean, m.mean)
    np.testing.assert_allclose(r.cov, m.cov)
    np.testing.assert_allclose(r.visited_s, m.visited_s)
    assert r.fitted_at == m.fitted_at
    core = ServiceCore(core_config(s), model=loaded_model, restored=second.restored)
    now = datetime.now(UTC)
    svc2 = SoftSensorService(core, worker=None, clock=lambda: now)
    snap = svc2.chtc()
    assert snap is not None and snap.status is ChtcStatus.STALE
    mp = svc2.chtc_map()
    assert mp is not None and mp.restored and mp.status is ChtcStatus.STALE
    np.testing.assert_allclose(mp.h_w_m2k, svc.chtc_map().h_w_m2k, rtol=0.05)  # ambient may differ
    second.close()


# --- the fit's start covariance and prior (issue 17: honest bands on the steady chain) --------------------
def _book(loaded_model, **kw: object):
    from service.core.mapbook import MapBook

    return MapBook(core_config(map_settings(**kw)), loaded_model, None)


def test_covariance_intersection_is_consistent_for_any_correlation(loaded_model) -> None:
    """Fusing the prior and the start field with ``MapBook.intersect``'s covariances never claims less than
    the fused estimate's actual error, whatever the correlation of their errors (Julier & Uhlmann 1997);
    treating them as independent (ω = 1) does when the errors are shared."""
    from model.hmap import Gaussian

    book = _book(loaded_model, map_prior_weight=0.3)
    a, b = np.diag([4.0, 1.0]), np.diag([1.0, 9.0])
    prior, start = book.intersect(Gaussian(np.zeros(2), a), b)
    np.testing.assert_allclose(prior.cov, a / 0.3)
    np.testing.assert_allclose(start, b / 0.7)
    same, unchanged = _book(loaded_model, map_prior_weight=1.0).intersect(Gaussian(np.zeros(2), a), b)
    assert same.cov is a and unchanged is b
    cold, start_cov = book.intersect(book.cold, np.eye(3))  # the spindle file's prior shares no data
    assert cold is book.cold and np.array_equal(start_cov, np.eye(3))
    for rho in (0.0, 0.5, 0.99):  # e_a, e_b with correlation rho per component
        cross = rho * np.sqrt(np.diag(a) * np.diag(b))
        for pa, pb, ok in ((prior.cov, start, True), (a, b, rho == 0.0)):
            ia, ib = np.linalg.inv(pa), np.linalg.inv(pb)
            fused = np.linalg.inv(ia + ib)
            ka, kb = fused @ ia, fused @ ib
            actual = ka @ a @ ka.T + kb @ b @ kb.T + ka @ np.diag(cross) @ kb.T + kb @ np.diag(cross) @ ka.T
            claims_enough = bool(np.all(np.linalg.eigvalsh(fused - actual) >= -1e-12))
            assert claims_enough or not ok, (rho, pa)
            if rho > 0.9 and pa is a:
                assert not claims_enough  # the naive fusion is overconfident with shared errors


@pytest.mark.slow
def test_a_map_window_longer_than_max_window_s_still_starts(duty, loaded_model) -> None:
    """The live state keeps its snapshots 3× the longest window a job may use: the per-condition
    ``max_window_s`` alone (90 s here, as the compose test's trial timing) dropped the snapshot at the
    convergence time before the map's first 10-min window needed it (every fit: insufficient data)."""
    from service.core.offline import run_offline

    settings = map_settings(min_window_s=90.0, max_window_s=90.0, schedule_min=[1.5])
    result = run_offline(duty[2][:90], model=loaded_model, config=core_config(settings))  # 15 min
    assert result.records, "no map fit launched"
    assert all(r.outcome == "ok" for r in result.records), [r.message for r in result.records]


@pytest.mark.slow
def test_stored_map_json_is_exact_compact_and_reads_the_earlier_form(served) -> None:
    """The covariance is stored as its packed upper triangle (float64, base64): exact, a quarter of the
    list-of-lists form, which is still read; a bad or short field is named."""
    import json

    svc, _ = served
    m = svc.view.speed_map
    assert m is not None
    stored = json.loads(json.dumps(m.to_json()))
    back = SpeedMap.from_json(stored, identification_id=m.identification_id)
    np.testing.assert_array_equal(back.cov, m.cov)
    np.testing.assert_array_equal(back.mean, m.mean)
    earlier = {k: v for k, v in stored.items() if k != "cov_upper_b64"} | {"cov": m.cov.tolist()}
    np.testing.assert_array_equal(SpeedMap.from_json(earlier, identification_id=None).cov, m.cov)
    assert len(json.dumps(stored)) < 0.4 * len(json.dumps(earlier))
    with pytest.raises(SpeedMapError, match=r"cov_upper_b64: not base64"):
        SpeedMap.from_json(stored | {"cov_upper_b64": "#"}, identification_id=None)
    with pytest.raises(SpeedMapError, match=r"cov_upper_b64: 8 bytes, expected"):
        SpeedMap.from_json(stored | {"cov_upper_b64": "AAAAAAAAAAA="}, identification_id=None)
    with pytest.raises(SpeedMapError, match=r"speed_map\.cov_upper_b64: missing"):
        SpeedMap.from_json({k: v for k, v in stored.items() if k != "cov_upper_b64"}, identification_id=None)
