"""The product as ``/compensation`` serves it, on a scenario's samples (issue 40 part 1).

The service's shell, core, inline identification and growth server on a manual clock
(``compensation_run.Session``, wired as ``chtc run`` wires it), the commissioned mechanics set before the
first sample (a stored calibration restored), read every minute as ``/compensation`` serves it
(``Session.read``: the served axial growth, its 95 % CI, the policy's verdict and typed reason). Optional:

- a restart before sample ``restart.k``: ``stored`` with what the database holds then
  (``compensation_run.stored_state``: identification, offset calibration, map, zero, live checkpoint; the
  commissioning and the accepted probe readings replayed, as ``bench commission`` restarts); ``no_state``
  with an empty database (the commissioning's mechanics and the configured zero kept: they are the
  configuration, ``[compensation] reference_c`` and the commissioning file re-applied);
- tool-setter readings (``ProbePlan``): every ``every_min`` after ``after_min`` the truth + N(0, sd²) posted
  as ``POST /compensation/measurements`` does (``SoftSensorService.add_measurement``), each minute's row read
  before that minute's reading.

Nothing here bypasses the served verdict: a minute counts as usable only when ``/compensation`` says so.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

__all__ = ["ProbePlan", "Restart", "Served", "serve"]


@dataclass(frozen=True, kw_only=True)
class Restart:
    """A restart before sample ``k``: ``mode`` ``stored`` or ``no_state``."""

    k: int
    mode: str


@dataclass(frozen=True, kw_only=True)
class ProbePlan:
    """A tool-setter reading (truth + N(0, ``sd_um``²)) every ``every_min`` after ``after_min``."""

    every_min: float
    after_min: float
    sd_um: float
    rng: np.random.Generator


@dataclass(kw_only=True)
class Served:
    """Per plant minute the served row (``compensation_run.Minute``); the readings posted, accepted and
    refused; the (minute, reading) pairs posted; with ``watch`` channels, per channel the first minute
    ``/compensation`` named it among its ``sensor_faults`` (the product's fault detection, issue 40 part 4;
    none while the product has none)."""

    minutes: list[Any] = field(default_factory=list)
    detected: dict[int, int] = field(default_factory=dict)
    readings: list[tuple[int, float]] = field(default_factory=list)
    accepted: int = 0
    refused: int = 0


def serve(
    model: Any,
    settings: Any,
    samples: list[Any],
    run: Any,
    truth: np.ndarray,
    *,
    mechanics: Any,
    restart: Restart | None = None,
    probe: ProbePlan | None = None,
    watch: tuple[int, ...] = (),
) -> Served:
    """The scenario's samples through the service (module docstring); ``truth`` [µm] per plant minute."""
    from benchmarks.compensation_run import PER_MIN, Session, stored_state
    from service.contracts.probe import ProbeError

    session = Session(model, settings, start=samples[0].t)
    session.svc.set_mechanics(mechanics)
    out = Served()
    every_k = round(probe.every_min * PER_MIN) if probe is not None else 0
    for k, sample in enumerate(samples):
        if restart is not None and k == restart.k:
            svc = session.svc
            if restart.mode == "stored":
                held = stored_state(svc.view, svc.growth.reference, session.stored.checkpoint())
                probes = tuple(m for m in reversed(svc.compensation_measurements()) if m.accepted)
                session = Session(
                    model,
                    settings,
                    start=sample.t,
                    restored=replace(held, mechanics=mechanics, probes=probes),
                )
            elif restart.mode == "no_state":
                session = Session(model, settings, start=sample.t)
                session.svc.set_mechanics(mechanics)
            else:
                raise ValueError(f"restart.mode: must be stored or no_state, got {restart.mode!r}")
        session.clock.at_least(sample.t)
        session.svc.on_sample(sample)
        if k % PER_MIN:
            continue
        i = k // PER_MIN
        truth_um = float(truth[i])
        out.minutes.append(session.read(float(run.times_s[k]), truth_um, np.asarray(run.h_true[k])))
        if watch:
            comp = session.svc.compensation()
            for f in getattr(comp, "sensor_faults", ()) if comp is not None else ():
                if f.channel in watch and f.channel not in out.detected:
                    out.detected[f.channel] = i
        since = k - round(probe.after_min * PER_MIN) if probe is not None else 0
        if probe is not None and since > 0 and since % every_k == 0:
            reading = truth_um + float(probe.rng.normal(0.0, probe.sd_um))
            out.readings.append((i, reading))
            try:
                m = session.svc.add_measurement(
                    at=sample.t, axial_um=reading, sd_um=probe.sd_um, set_by="bench", source="probe"
                )
            except ProbeError:
                out.refused += 1  # no zero or no live field yet: refused (422), not absorbed
                continue
            out.accepted += int(m.accepted)
    return out
