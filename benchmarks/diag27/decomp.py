# ruff: noqa
"""Diagnostic (not part of the product): decompose the commissioned product's axial error on the duty cycle.

Per seed (the bench's own pieces: plant, thermal test, commissioning, duty, serve):
  a   the commissioned product as served (bench's calibrated arm, restart half-way)
  b   plant's true field interpolated (P1) onto the service mesh, through the served (fitted) operator,
      over the plant's true zero
  b2  same, the interpolated field E-projected onto the ROM basis (what the live state can represent)
  c   plant's true field on the service mesh through the service's operator with the plant's TRUE
      mechanics (s, a_s, a_h)
  c2  same on the ROM basis
  d   the service's live state with the TRUE H(speed) (and unit load scales), served with the fitted
      mechanics and the product's own zero
  dz  d over the true zero
  az  a over the true zero
  e   MLR
Saves per-seed npz in $CHTC_DIAG_OUT (default /tmp/chtc-diag27).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from contextlib import contextmanager, nullcontext
from dataclasses import replace
from pathlib import Path

import numpy as np

OUT = Path(os.environ.get("CHTC_DIAG_OUT", "/tmp/chtc-diag27"))  # npz outputs, ~140 MB for 26 seeds


def interp_matrix(src_fe, dst_fe):
    """Sparse P1 interpolation (N_dst, N_src) of src-mesh fields at dst nodes."""
    import scipy.sparse as sp

    from model.locator import TriangleLocator

    loc = TriangleLocator(src_fe.nodes_rz, src_fe.triangles)
    pts = np.asarray(dst_fe.nodes_rz)
    at = loc.locate(pts, tol=1e-7)
    miss = np.flatnonzero(at.tri < 0)
    rows, cols, vals = [], [], []
    tri = np.asarray(src_fe.triangles)
    ok = np.flatnonzero(at.tri >= 0)
    for k in range(3):
        rows.append(ok)
        cols.append(tri[at.tri[ok], k])
        vals.append(at.bary[ok, k])
    if miss.size:
        from scipy.spatial import cKDTree

        _, nn = cKDTree(src_fe.nodes_rz).query(pts[miss])
        rows.append(miss)
        cols.append(nn)
        vals.append(np.ones(miss.size))
        print(f"  {miss.size} service nodes outside the plant mesh: nearest node", file=sys.stderr)
    r, c, v = (np.concatenate(x) for x in (rows, cols, vals))
    return sp.csr_matrix((v, (r, c)), shape=(pts.shape[0], src_fe.n_nodes))


@contextmanager
def fixed_h(law):
    from model.estimator import StepInput
    from model.inputs import inputs_from_operation
    from service.estimate import state as st

    saved = st.FilteredState._step_input

    def step_input(self, inp):
        s = inputs_from_operation(
            self.spec,
            dt_s=1.0,
            speed_rpm=np.array([inp.speed_rpm]),
            torque_nm=np.array([inp.torque_nm]),
            ambient_c=np.array([inp.ambient_c]),
        )
        h = np.asarray(law(inp.speed_rpm, inp.ambient_c), dtype=float)
        return StepInput(h, inp.ambient_c, float(s.q_front_w[0]), float(s.q_rear_w[0]), self.dt_s)

    st.FilteredState._step_input = step_input
    try:
        yield
    finally:
        st.FilteredState._step_input = saved


def serve(model, settings, samples, run, truth, *, restart_k, mechanics, true_h=None):
    """The bench's serve_duty (no probe), recording the live mean and the zero each minute."""
    from benchmarks.compensation_run import PER_MIN, Session, stored_state

    patch = fixed_h(lambda n, _amb: true_h(n)) if true_h is not None else nullcontext()
    with patch:
        session = Session(model, settings, start=samples[0].t)
        session.svc.set_mechanics(mechanics)
        um, tref, means, hs, ok = [], [], [], [], []
        for k, sample in enumerate(samples):
            if k == restart_k:
                svc = session.svc
                held = stored_state(svc.view, svc.growth.reference, session.stored.checkpoint())
                restored = replace(held, mechanics=mechanics, probes=())
                session = Session(model, settings, start=sample.t, restored=restored)
            session.clock.at_least(sample.t)
            session.svc.on_sample(sample)
            if k % PER_MIN:
                continue
            row = session.read(float(run.times_s[k]), float(truth[k // PER_MIN]), np.asarray(run.h_true[k]))
            live = session.svc.view.live
            t_ref = session.svc.growth.t_ref_c(session.svc.view)
            um.append(row.um if row.served else np.nan)
            ok.append(row.served)
            tref.append(np.nan if t_ref is None else t_ref)
            means.append(np.full(model.rom.rank, np.nan) if live is None else np.asarray(live.mean))
            hs.append(np.full(7, np.nan) if row.h is None else row.h)
        ctx = session.svc.growth.prepare()
    return {
        "um": np.array(um),
        "tref": np.array(tref),
        "mean": np.array(means),
        "h": np.array(hs),
        "g": np.asarray(ctx.g[0]),
    }


def run_one(model, settings, plant, seed, args, P=None):
    from benchmarks.commission import prepare_seed
    from benchmarks.compensation_run import PER_MIN
    from service.estimate.mechanics import served_mechanics_basis
    from simulator.randomtruth import draw_truth

    t_start = time.perf_counter()
    basis = served_mechanics_basis(model.spec, model.fe)
    prep = prepare_seed(model, settings, plant, seed, args)
    mech, rep, peer, run, truth = prep.mech, prep.report, prep.peer, prep.run, prep.truth
    samples, restart_k = prep.samples, prep.restart_k
    truth_h = draw_truth(np.random.default_rng([seed, 7]))  # the duty's, as prepare_seed draws it
    print(f"seed {seed}: plant+commission {time.perf_counter() - t_start:.0f} s", file=sys.stderr)
    a = serve(model, settings, samples, run, truth, restart_k=restart_k, mechanics=rep.calibration)
    print(f"seed {seed}: served a {time.perf_counter() - t_start:.0f} s", file=sys.stderr)
    d = None
    if not args.no_d:
        d = serve(
            model,
            settings,
            samples,
            run,
            truth,
            restart_k=restart_k,
            mechanics=rep.calibration,
            true_h=truth_h,
        )
        print(f"seed {seed}: served d {time.perf_counter() - t_start:.0f} s", file=sys.stderr)
    if P is None:
        P = interp_matrix(plant.fe, model.fe)
    T_s = np.asarray((P @ run.fields_c.T).T)  # (m, N_service)
    rom = model.rom
    T_r = rom.lift(rom.project(T_s))
    t_ref_true = plant.start_c(run)
    g_fit = basis.operators_at(rep.calibration.x)[0]
    g_true = basis.operators_at((mech.restraint, mech.alpha_shaft, mech.alpha_housing))[0]
    assert np.allclose(g_fit, a["g"]), "served operator != basis at the fitted x"
    keep = np.array([i for i, tt in enumerate(run.field_times_s) if tt >= 60.0 * args.rest_min])
    mlr_pred = peer.predict(run.temps_c)
    phi = rom.basis
    tr = truth[keep]

    def grow(g, fields, tref):
        return fields @ g - g.sum() * tref

    def served_from(s, g, tref):
        return (s["mean"] @ phi.T) @ g - g.sum() * tref

    err = {
        "a": a["um"][keep] - tr,
        "a_recomputed": served_from(a, g_fit, a["tref"])[keep] - tr,
        "az": served_from(a, g_fit, t_ref_true)[keep] - tr,
        "ac": served_from(a, g_true, a["tref"])[keep] - tr,
        "b": grow(g_fit, T_s, t_ref_true)[keep] - tr,
        "b2": grow(g_fit, T_r, t_ref_true)[keep] - tr,
        "c": grow(g_true, T_s, t_ref_true)[keep] - tr,
        "c2": grow(g_true, T_r, t_ref_true)[keep] - tr,
        "e": np.array([mlr_pred[i * PER_MIN] - mlr_pred[0] for i in keep]) - tr,
    }
    if d is not None:
        err["d"] = d["um"][keep] - tr
        err["dz"] = served_from(d, g_fit, t_ref_true)[keep] - tr
        err["dc"] = served_from(d, g_true, t_ref_true)[keep] - tr
    OUT.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(
        OUT / f"seed{seed}{'_short' if args.short else ''}{args.tag}.npz",
        keep=keep,
        truth=truth,
        T_s=T_s.astype(np.float32),
        t_ref_true=t_ref_true,
        g_fit=g_fit,
        g_true=g_true,
        fitted=np.asarray(rep.calibration.x),
        mech=np.array([mech.restraint, mech.alpha_shaft, mech.alpha_housing]),
        a_um=a["um"],
        a_tref=a["tref"],
        a_mean=a["mean"],
        a_h=a["h"],
        d_um=np.full(1, np.nan) if d is None else d["um"],
        d_tref=np.full(1, np.nan) if d is None else d["tref"],
        d_mean=np.full((1, 1), np.nan) if d is None else d["mean"],
        h_true=np.array([run.h_true[i * PER_MIN] for i in range(len(truth))]),
        speed=np.array([run.speed_rpm[i * PER_MIN] for i in range(len(truth))]),
        mlr=np.array([mlr_pred[i * PER_MIN] - mlr_pred[0] for i in range(len(truth))]),
        **{f"err_{k}": v for k, v in err.items()},
    )
    rms = {k: float(np.sqrt(np.nanmean(v**2))) for k, v in err.items()}
    mean = {k: float(np.nanmean(v)) for k, v in err.items()}
    out = {
        "seed": seed,
        "rms": rms,
        "mean": mean,
        "tref_err_c": float(a["tref"][keep[0]] - t_ref_true),
        "fitted": [round(float(v), 3) for v in rep.calibration.x],
        "mech": [round(v, 3) for v in (mech.restraint, mech.alpha_shaft, mech.alpha_housing)],
        "wall_s": round(time.perf_counter() - t_start, 1),
    }
    return out, P


def main() -> int:
    from benchmarks.commission import _setup

    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, nargs="+", required=True)
    ap.add_argument("--short", action="store_true")
    ap.add_argument("--no-d", action="store_true")
    ap.add_argument("--hours", type=float, default=2.5)
    ap.add_argument("--rest-min", type=int, default=30)
    ap.add_argument("--sensors", type=int, default=5)
    ap.add_argument("--tag", default="")
    ap.add_argument("--set", action="append", default=[], help="section.key=value (JSON value)")
    args = ap.parse_args()
    model, settings, plant = _setup()
    from service.commands._common import override

    for item in args.set:
        key, value = item.split("=", 1)
        section, name = key.split(".")
        settings = override(settings, section, **{name: json.loads(value)})
    P = None
    for seed in args.seeds:
        out, P = run_one(model, settings, plant, seed, args, P)
        print(json.dumps(out), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
