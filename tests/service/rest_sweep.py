"""The at-rest sweep of issue 26 (not a test; run it): ``PYTHONPATH=. python3 tests/service/rest_sweep.py SEED
[off]`` prints one JSON line. The virtual plant rests uniformly at a random 16–30 °C (ambient the same, no
speed; ``off``: ±0.2 °C per-channel offsets) for 30 min through the service core (``run_offline``) and
``/compensation``'s own ``GrowthServer``: ``a`` with ``reference_on_first_start`` (the zero from the first
sample at rest), ``b`` with the exact rest temperature as a given zero (1σ 0: the live field's own CI).
``*_cov``: fraction of served minutes whose 95 % CI covers 0 (the truth at rest)."""

from __future__ import annotations

import json
import sys

import numpy as np

from benchmarks.chain import T0
from model.plant import Segment, VirtualPlant
from service.core.offline import run_offline
from service.host.runtime import core_config
from service.modelload import ModelRef, load_model
from service.serve.compensation import GrowthServer
from service.settings import Settings
from simulator.plantsamples import samples_from_plant


def main(seed: int, offsets: bool) -> dict[str, object]:
    rng = np.random.default_rng(500 + seed)
    temp = round(float(rng.uniform(16.0, 30.0)), 2)
    off = rng.uniform(-0.2, 0.2, 32) if offsets else None
    settings = Settings()
    model = load_model(ModelRef.from_settings(settings))
    run = VirtualPlant(model.spec, seed=seed, offsets_c=off).run([Segment(1800.0, 0.0, 0.0, temp)], dt_s=10.0)
    a = GrowthServer(model, reference_on_first_start=True)
    b = GrowthServer(model, t_ref_c=temp, context=a.prepare())
    rows: dict[str, list[tuple[float, float, float]]] = {"a": [], "b": []}

    def each(core, k, _last):  # type: ignore[no-untyped-def]
        view = core.view()
        a.observe(view)
        if k % 6 != 5 or view.current is None:
            return
        for name, server in (("a", a), ("b", b)):
            est = server.estimate(view)
            if est is not None and (name == "b" or a.reference is not None):
                rows[name].append((est.axial.um, *est.axial.ci95_um))

    run_offline(samples_from_plant(run, t0_s=T0), model=model, config=core_config(settings), on_sample=each)
    ref = a.reference
    out: dict[str, object] = {"seed": seed, "temp": temp, "offsets": offsets}
    out["zero"] = None if ref is None else [round(ref.temperature_c, 4), round(ref.sd_c, 4)]
    for name, r in rows.items():
        out[f"{name}_cov"] = round(float(np.mean([lo <= 0.0 <= hi for _, lo, hi in r])), 3) if r else None
        out[f"{name}_n"] = len(r)
        out[f"{name}_max_abs_um"] = round(max(abs(u) for u, _, _ in r), 4) if r else None
        out[f"{name}_last"] = [round(x, 4) for x in r[-1]] if r else None
    return out


if __name__ == "__main__":
    print(json.dumps(main(int(sys.argv[1]), len(sys.argv) > 2 and sys.argv[2] == "off")))
