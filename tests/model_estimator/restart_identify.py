"""Measurement, not a test: identification windows after a restart, started from the filter's state.

For each window (3000 rpm 35–65 min, 4000 rpm 75–110 min of ``conftest.PROFILE``) and each filter lead time
L (the service restarted L min before the window; the filter ran from a wide prior with the stale H of the
restart time, off by a 20 % draw), over ``--seeds`` noise seeds: median |H error| %, CI coverage, share of
seeds covering all seven and the median CI half-width, for windows started from (a) the plant's true field
(interpolated onto the service mesh: the best possible start) and (b) the filter's mean with its covariance
as ``start_cov``. Run: ``OPENBLAS_NUM_THREADS=1 python -m tests.model_estimator.restart_identify --seeds 10``
(~1 min per lead time and window). Superseded by ``python -m benchmarks restart --mode filter`` (the whole
restart profile through ``service.estimate.state.FilteredState``; docs/design/estimator.md, "Identification
after a restart"); this script's 2026-11-23 figures (rank-30 θ-step model) are in that page's git history.
"""

from __future__ import annotations

import argparse
from typing import Any

import numpy as np
from scipy.interpolate import LinearNDInterpolator

from model.estimator import StateEstimator, wide_prior
from model.identify import Window, identify
from model.plant import Segment, VirtualPlant
from tests.model_estimator import conftest

SPM = 6  # samples per minute


def _true_field(model: Any, minute: int) -> np.ndarray:
    """The plant's field at ``minute`` of the profile, interpolated onto the service mesh."""
    plant = VirtualPlant(model.spec, noise_c=0.15, seed=11, steady_tol_c=0.0)
    segments, left = [], minute * 60.0
    for seg in conftest.PROFILE:
        duration = min(seg.duration_s, left)
        if duration > 0:
            segments.append(Segment(duration, seg.speed_rpm, seg.torque_nm, seg.ambient_c))
            left -= duration
    run = plant.run(segments, dt_s=10.0)
    return np.asarray(LinearNDInterpolator(plant.fe.nodes_rz, run.final_field_c)(model.fe.nodes_rz))


def _filtered_start(model: Any, data: Any, meas: np.ndarray, restart: int, start: int, h: np.ndarray) -> Any:
    est = StateEstimator(model.rom, wide_prior(model.rom, ambient_c=float(data.run.ambient_c[restart])))
    est.update(meas[restart])
    for k in range(restart, start):
        est.step(data.step_input(k, h / data.run.h_true[k]), meas[k + 1])
    return est.estimate


def _summary(name: str, rows: list[tuple[np.ndarray, np.ndarray, np.ndarray]]) -> str:
    err = np.array([r[0] for r in rows])
    cov = np.array([r[1] for r in rows])
    half = np.array([r[2] for r in rows])
    med_err = np.round(np.median(np.abs(err), 0), 1)
    med_half = np.round(np.median(half, 0), 0)
    coverage = f"coverage {cov.mean(0).round(2)} all7 {cov.all(1).mean():.2f}"
    return f"  {name:12s} median |err| % {med_err} {coverage} CI half-width % {med_half}"


def measure(model: Any, data: Any, window: tuple[int, int], lead_min: int, seeds: int) -> list[str]:
    """Print-ready lines for one window (start, end minute) and one filter lead time."""
    a, b = window[0] * SPM, window[1] * SPM
    restart = a - lead_min * SPM
    true_start = _true_field(model, window[0])
    inputs = data.inputs.slice(a, b)
    truth = data.run.h_true[a]
    rows: dict[str, list[Any]] = {"true start": [], "filter+cov": []}
    field_err = []
    for seed in range(seeds):
        rng = np.random.default_rng(100 + seed)
        meas = np.round((data.run.truth_c + 0.15 * rng.standard_normal(data.run.truth_c.shape)) / 0.01) * 0.01
        stale = data.run.h_true[restart] * np.exp(0.2 * np.random.default_rng(50 + seed).standard_normal(7))
        est = _filtered_start(model, data, meas, restart, a, stale)
        start = model.rom.lift(est.mean)
        field_err.append(np.sqrt(np.mean((start - true_start) ** 2)))
        mask = np.ones(32, dtype=bool)
        for name, t0, kw in (("true start", true_start, {}), ("filter+cov", start, {"start_cov": est.cov})):
            res = identify(
                model.rom, Window(inputs, meas[a : b + 1], mask, t0), rng=seed, spec=model.spec, **kw
            )
            inside = (res.h_ci95[:, 0] <= truth) & (truth <= res.h_ci95[:, 1])
            half = 100.0 * (res.h_ci95[:, 1] - res.h_ci95[:, 0]) / 2.0 / truth
            rows[name].append((100.0 * (res.h / truth - 1.0), inside, half))
    head = (
        f"window {window[0]}-{window[1]} min ({data.run.speed_rpm[a]:.0f} rpm), filter lead {lead_min} min, "
        f"{seeds} seeds: start field RMS error {np.median(field_err):.3f} °C"
    )
    return [head] + [_summary(name, r) for name, r in rows.items()]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--leads", type=int, nargs="+", default=[5, 15, 25])
    args = parser.parse_args()
    model = conftest.model.__wrapped__()  # type: ignore[attr-defined]
    data = conftest.plant_data.__wrapped__(model)  # type: ignore[attr-defined]
    for window in ((35, 65), (75, 110)):
        for lead in args.leads:
            print("\n".join(measure(model, data, window, lead, args.seeds)), flush=True)


if __name__ == "__main__":
    main()
