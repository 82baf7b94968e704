"""One seed of ``python -m benchmarks compensation`` (``benchmarks.compensation``): the plant runs and the
service runs of its five scenarios, read every minute as ``/compensation`` and ``/chtc`` serve.

Per seed and variant (``clean``; ``offsets``: per-channel offsets uniform in ±0.2 °C) the virtual plant
(``model.plant.VirtualPlant``: its finer mesh, 2.5-s internal steps, σ = 0.15 °C) runs the seed's duty cycle
(``simulator.duty``: ``rest_min`` at rest, then the speed changing every 1–6 min over 0–7000 rpm) with the
seed's random truth (``simulator.randomtruth``, never ``model.plant.h_true``) and keeps its whole field
every minute; the true axial growth is that field's through a growth model built on the plant's mesh with the
plant's own mechanics (``--plant-mechanics drawn``, the default: the seed's mount restraint and α factors,
``model.plantmech``, which the service does not know; ``nominal``: the description's), over the plant's
uniform start (the controller zeroed cold). The service (``SoftSensorService``: shell, core, the
identification inline, its own ``GrowthServer`` as ``chtc run`` builds it) sees the samples on a manual clock:

- ``normal``: every sample (both variants);
- ``restart_stored`` (offsets): the service stops at ``plan.restart_min`` and a new one starts on the next
  sample with what the database holds then (``stored_state``: the served identification, the per-condition
  history, the conditions, the offset calibration, the speed map, the compensation zero, and the live
  state's newest checkpoint, stored once a minute: up to a minute old at the restart);
- ``restart_no_state`` (offsets): the same restart with an empty database (no identification, history,
  calibration, map, live state nor stored zero). "No stored state" is the database's: the commissioned zero
  also lives in the configuration, so this run is given ``compensation.reference_c`` = the plant's uniform
  start temperature, the zero its true growth is measured against (``Plant.start_c``). Without it the warm
  spindle never rests in equilibrium, the growth would stay ``no_reference`` for the whole run and its
  coverage would measure a provisional zero nobody applies;
- ``outages`` (offsets): one run with a DAQ outage while CAN keeps coming (the acquisition's stale DAQ
  sample: the last temperatures with quality ``stale``, ambient NaN, ``daq_ok`` False, speed and torque
  live) and later both devices down (the acquisition's sample with neither: the last values, ``daq_ok`` and
  ``can_ok`` False), ``plan.outage_min`` each.

The controller is zeroed at the cold start: ``compensation.reference_on_first_start`` (the service's zero from
the first sample at rest in equilibrium, as the demo and a commissioning take it).

Every minute (and every 10 s while both devices are down) a :class:`Minute` row holds what is served.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import UTC, datetime
from typing import Any

import numpy as np

from drivers.quality import Quality
from drivers.ringbuffer import Sample
from service.contracts.checkpoint import LiveCheckpoint
from service.contracts.records import Record
from service.contracts.snapshots import ConditionState
from service.host.persistence import GateSink

DT_S = 10.0
PER_MIN = 6  # samples per minute
T0 = datetime(2026, 4, 6, 6, 0, 0, tzinfo=UTC).timestamp()
VARIANTS = ("clean", "offsets")
OFFSET_C = 0.2


@dataclass(frozen=True, kw_only=True)
class Plan:
    """The seed's timeline [min from the plant's start]: rest, restart, the two outages, the end."""

    rest_min: int
    total_min: int
    restart_min: int
    daq_out: tuple[int, int]  # DAQ down, CAN alive: [start, end)
    both_out: tuple[int, int]  # both down: [start, end)


def plan_for(hours: float, *, rest_min: int = 30, outage_min: int = 10) -> Plan:
    """Restart half-way through the machining, the DAQ outage at a quarter, both down at three quarters;
    ``ValueError`` when the machining is too short for them (< 4 outages long)."""
    total = round(60.0 * hours)
    machining = total - rest_min
    if rest_min < 5 or machining < 4 * outage_min:
        raise ValueError(
            f"--hours: the machining after the {rest_min}-min rest must be >= {4 * outage_min} min, "
            f"got {machining} (and the rest >= 5 min)"
        )
    daq = rest_min + machining // 4
    both = rest_min + (3 * machining) // 4
    return Plan(
        rest_min=rest_min,
        total_min=total,
        restart_min=rest_min + machining // 2,
        daq_out=(daq, daq + outage_min),
        both_out=(both, both + outage_min),
    )


@dataclass(frozen=True, kw_only=True)
class Minute:
    """What was served at plant time ``t_s`` and the plant's truth then (µm, W/(m²·K))."""

    t_s: float
    served: bool  # /compensation answered (not None)
    usable: bool
    status: str  # /compensation's (else /chtc's, else "none")
    reason: str | None  # the typed code (``reason_code``) when not usable
    um: float = math.nan  # served axial growth and its 95 % CI
    lo: float = math.nan
    hi: float = math.nan
    t_ref_c: float = math.nan
    truth_um: float = math.nan
    converged: bool = False  # the live state
    nis_ratio: float = math.nan  # the live state's NIS window: Σ NIS / Σ dof (1 when consistent)
    h: np.ndarray | None = None  # /chtc (7,) and CI, flags; None: nothing served
    h_lo: np.ndarray | None = None
    h_hi: np.ndarray | None = None
    identified: np.ndarray | None = None
    h_fresh: bool = False  # /chtc's status is fresh
    h_truth: np.ndarray = field(default_factory=lambda: np.full(7, np.nan))


@dataclass(frozen=True, kw_only=True, slots=True)
class Tick:
    """What ``/compensation`` serves after one sample (every 10 s), for the CI gate and the command value
    (``service.serve.controlled``), beside the truth on the minute samples (NaN between them)."""

    t: float  # the sample's instant [POSIX s]
    t_s: float  # plant time [s]
    served: bool
    usable: bool  # the policy's plain verdict (before the CI gate: ``CompensationSnapshot.policy_verdict``)
    reason: str | None
    status: str
    um: float = math.nan
    lo: float = math.nan
    hi: float = math.nan
    truth_um: float = math.nan


def reason_code(snap: Any) -> str | None:
    """The typed reason of a ``/chtc`` or ``/compensation`` snapshot (its policy verdict's ``Reason``, what
    the API serves as ``reason_code``; None when usable). Never parsed from the human text."""
    code = snap.verdict.reason
    return None if code is None else str(code.value)


MECHANICS = ("drawn", "nominal")


def add_jobs_argument(parser: Any) -> None:
    """``--jobs N`` of the seed benches (``python -m benchmarks compensation``, ``commission``)."""
    parser.add_argument(
        "--jobs",
        type=int,
        default=1,
        help="seeds run in this many processes at once (default 1; each takes one core and ~1 GiB)",
    )


def add_plant_mechanics_argument(parser: Any) -> None:
    """``--plant-mechanics drawn|nominal`` of the growth benches (``python -m benchmarks compensation``,
    ``growth``)."""
    parser.add_argument(
        "--plant-mechanics",
        choices=("drawn", "nominal"),
        default="drawn",
        help="the plant's mechanics: drawn per seed (mount restraint, α ±5 %%; default) or nominal (the "
        "service's own, the figures before issue 27)",
    )


class Plant:
    """The plant's mesh, its growth model (nose axial) and the runs of a seed.

    ``mechanics`` "drawn" (default): each seed's plant has its own mechanics
    (``model.plantmech.mechanics_for_seed``: mount restraint, α factors), unknown to the service, and its
    true growth comes from them on the plant's mesh; "nominal": the description's own (the figures before
    issue 27)."""

    def __init__(self, spec: Any, *, mechanics: str = "drawn") -> None:
        from model.fem import build_fe_model

        if mechanics not in MECHANICS:
            raise ValueError(f"--plant-mechanics: must be one of {MECHANICS}, got {mechanics!r}")
        self.spec = spec
        self.mode = mechanics
        self.fe = build_fe_model(spec, mesh_size_m=spec.plant_mesh_size_m)
        self._growth: dict[int, Any] = {}

    def mechanics(self, seed: int) -> Any:
        """The seed's plant mechanics (``model.plantmech.PlantMechanics``)."""
        from model.plantmech import PlantMechanics, mechanics_for_seed

        return mechanics_for_seed(seed) if self.mode == "drawn" else PlantMechanics.nominal(self.spec)

    def growth(self, seed: int) -> Any:
        """The seed's plant growth model (built once per seed, shared by its variants)."""
        from model.plantmech import build_plant_growth

        if seed not in self._growth:
            self._growth = {seed: build_plant_growth(self.spec, self.fe, self.mechanics(seed))}
        return self._growth[seed]

    @staticmethod
    def start_c(run: Any) -> float:
        """The plant's uniform start temperature [°C] (the mean of its first kept field): the zero its true
        growth is measured against, the controller's commissioned zero."""
        return float(run.fields_c[0].mean())

    def run(self, seed: int, variant: str, profile: list[Any], truth: Any) -> tuple[Any, np.ndarray]:
        """The plant run (samples every 10 s, fields every minute) and the true axial growth [µm] per minute
        over the uniform start."""
        from model.plant import VirtualPlant

        rng = np.random.default_rng([seed, VARIANTS.index(variant)])
        offsets = rng.uniform(-OFFSET_C, OFFSET_C, 32) if variant == "offsets" else None
        plant = VirtualPlant(
            self.spec,
            fe=self.fe,
            offsets_c=offsets,
            h_law=truth,
            seed=int(rng.integers(2**31)),
            mechanics=self.mechanics(seed),
            growth=self.growth(seed),
        )
        run = plant.run(profile, dt_s=DT_S, keep_fields_every=PER_MIN)
        t_ref = self.start_c(run)
        row = plant.growth.names.index("nose_axial")
        growth = np.asarray(plant.growth_um(run.fields_c, t_ref))[:, row]
        return run, growth


def stale_daq(last: Sample, now: Sample, *, can_ok: bool = True) -> Sample:
    """The acquisition's sample while the DAQ is silent (``drivers.acquisition.combine``): the last
    temperatures, quality ``stale``, no ambient, ``daq_ok`` False; speed and torque live (``can_ok``), or
    the last ones with ``can_ok`` False (CAN silent too)."""
    quality = np.full(len(last.temps_c), np.uint8(Quality.STALE))
    return Sample(
        now.t,
        np.asarray(last.temps_c, dtype=float).copy(),
        math.nan,
        now.speed_rpm if can_ok else last.speed_rpm,
        now.torque_nm if can_ok else last.torque_nm,
        quality,
        daq_ok=False,
        can_ok=can_ok,
    )


class NewestLiveState(GateSink):
    """The bench's database writer: keeps the newest live-state checkpoint the core stored (what the
    ``live_state`` table holds at a restart), drops every other record."""

    def __init__(self) -> None:
        super().__init__(max_held=0)
        self.record: LiveCheckpoint | None = None

    def submit(self, record: Record) -> bool:
        if isinstance(record, LiveCheckpoint):
            self.record = record
        return True

    def checkpoint(self) -> LiveCheckpoint | None:
        """The stored checkpoint as ``restore`` reads it back (None: none stored yet)."""
        if self.record is None:
            return None
        row = self.record.values()
        return LiveCheckpoint.from_parts(
            bytes(row["payload"]),  # type: ignore[arg-type]
            t=row["at"].timestamp(),  # type: ignore[union-attr]
            model_version=self.record.model_version,
            converged=self.record.converged,
            inputs=self.record.inputs,
        )


class Session:
    """One service instance on a manual clock, wired as ``chtc run`` wires it (``core_config``,
    ``growth_server``: the settings' reference and compensation limits), with the identification inline;
    ``restored`` what the database held (its compensation zero included)."""

    def __init__(
        self,
        model: Any,
        settings: Any,
        *,
        start: datetime,
        restored: Any = None,
    ) -> None:
        from service.core.machine import ServiceCore
        from service.host.runtime import core_config, growth_server
        from service.identify.worker import run_job
        from service.shell.service import SoftSensorService
        from simulator.served import ManualClock

        core = ServiceCore(core_config(settings), model=model, restored=restored, history_capacity=100_000)
        self.clock = ManualClock(start)
        self.stored = NewestLiveState()
        self.svc = SoftSensorService(
            core,
            worker=None,
            writer=self.stored,
            clock=self.clock,
            on_event=lambda _m: None,
            run_job=lambda req: run_job(model, req),
            growth=growth_server(model, settings, restored),
        )

    def tick(self, t: float, t_s: float, truth_um: float) -> Tick:
        """What /compensation serves now (plain verdict, growth and CI), beside the truth."""
        comp = self.svc.compensation()
        if comp is None:
            return Tick(
                t=t, t_s=t_s, served=False, usable=False, reason=None, status="none", truth_um=truth_um
            )
        ax = comp.growth.axial
        plain = comp.policy_verdict or comp.verdict  # before the service's own CI gate
        return Tick(
            t=t,
            t_s=t_s,
            served=True,
            usable=bool(plain.usable),
            reason=None if plain.reason is None else str(plain.reason.value),
            status=plain.status.value,
            um=float(ax.um),
            lo=float(ax.ci95_um[0]),
            hi=float(ax.ci95_um[1]),
            truth_um=truth_um,
        )

    def read(self, t_s: float, truth_um: float, h_truth: np.ndarray) -> Minute:
        """What /compensation and /chtc serve now, beside the truth."""
        svc = self.svc
        chtc = svc.chtc()
        comp = svc.compensation()
        live = svc.view.live
        h: dict[str, Any] = {}
        if chtc is not None:
            h = {
                "h": np.asarray(chtc.h, dtype=float),
                "h_lo": np.asarray(chtc.ci95_lo, dtype=float),
                "h_hi": np.asarray(chtc.ci95_hi, dtype=float),
                "identified": np.asarray(chtc.identified, dtype=bool),
                "h_fresh": chtc.status.value == "fresh",
            }
        common: dict[str, Any] = {
            "t_s": t_s,
            "truth_um": truth_um,
            "h_truth": h_truth,
            "converged": bool(live is not None and live.converged),
            "nis_ratio": (live.nis_sum / live.nis_sum_dof)
            if live is not None and live.nis_sum_dof
            else math.nan,
        }
        if comp is None:
            status = "none" if chtc is None else chtc.status.value
            why = "nothing_served" if chtc is None else reason_code(chtc) or status
            return Minute(served=False, usable=False, status=status, reason=why, **common, **h)
        ax = comp.growth.axial
        return Minute(
            served=True,
            usable=bool(comp.usable_for_compensation),
            status=comp.status.value,
            reason=None if comp.usable_for_compensation else (reason_code(comp) or comp.status.value),
            um=float(ax.um),
            lo=float(ax.ci95_um[0]),
            hi=float(ax.ci95_um[1]),
            t_ref_c=float(comp.growth.t_ref_c),
            **common,
            **h,
        )


def stored_state(view: Any, reference: Any = None, live: LiveCheckpoint | None = None) -> Any:
    """What the database holds of a run at ``view`` (``service.host.persistence.restore`` builds the same
    ``Restored`` from its tables): the served identification, the newest complete H per condition, the
    conditions (stable), the offset calibration, the speed map and its newest fit, the compensation
    zero ``reference`` (the growth server's) and the live state's newest checkpoint ``live``."""
    from dataclasses import replace

    from service.core.config import Restored
    from service.core.jobbook import MAP_METHOD
    from service.identify.detector import OperatingPoint
    from service.identify.scheduler import PastResult

    latest: dict[int, Any] = {}
    for rec in view.records:  # newest first
        if rec.outcome == "ok" and rec.condition.id not in latest:
            latest[rec.condition.id] = rec
    history = tuple(
        PastResult(
            condition_id=cid,
            point=OperatingPoint(
                speed_rpm=r.condition.speed_rpm,
                torque_nm=r.condition.torque_nm,
                ambient_c=r.condition.ambient_c,
            ),
            h=tuple(float(x) for x in r.h),
        )
        for cid, r in reversed(latest.items())
        if np.all(np.isfinite(np.asarray(r.h, dtype=float)))
    )
    ids = [r.id for r in view.records] or [0]
    conds = [c.id for c in view.conditions] or [0]
    return Restored(
        last=view.current,
        history=history,
        conditions=tuple(replace(c, state=ConditionState.STABLE) for c in view.conditions),
        next_condition_id=max(conds) + 1,
        next_identification_id=max(ids) + 1,
        calibration=view.calibration,
        speed_map=view.speed_map,
        map_last=next((r for r in view.records if r.outcome == "ok" and r.method == MAP_METHOD), None),
        reference=reference,
        live=live,
    )


@dataclass(kw_only=True)
class SeedRows:
    """A seed's rows per scenario, the both-down ticks (s after the last sample, usable) and its wall time."""

    rows: dict[str, list[Minute]] = field(default_factory=dict)
    ticks: dict[str, list[Tick]] = field(default_factory=dict)  # every sample (normal runs, outages)
    both_ticks: list[tuple[float, bool]] = field(default_factory=list)
    ref_before_restart: float | None = None
    mechanics: dict[str, float] = field(default_factory=dict)  # the plant's (``PlantMechanics.as_dict``)
    wall_s: float = 0.0


def run_seed(
    model: Any,
    settings: Any,
    plant: Plant,
    seed: int,
    plan: Plan,
    *,
    progress: Callable[[str], None] | None = None,
) -> SeedRows:
    """The five scenarios of one seed (module docstring)."""
    from service.commands._common import override
    from simulator.duty import duty_profile
    from simulator.plantsamples import samples_from_plant
    from simulator.randomtruth import draw_truth

    # a plant with the description's own mechanics needs no commissioning (issue 27's rule, off); a drawn
    # plant's are unknown to the service: the settings' rule applies (default: not usable, reason
    # mechanics_uncalibrated)
    known = {"require_mechanics_calibration": False} if plant.mode == "nominal" else {}
    settings = override(settings, "compensation", reference_on_first_start=True, **known)
    started = time.perf_counter()
    truth = draw_truth(np.random.default_rng([seed, 7]))
    profile = duty_profile(seed, duration_s=60.0 * plan.total_min, idle_s=60.0 * plan.rest_min)
    out = SeedRows(mechanics=plant.mechanics(seed).as_dict())
    for variant in VARIANTS:
        run, growth = plant.run(seed, variant, profile, truth)
        samples = samples_from_plant(run, t0_s=T0)
        restart_k = plan.restart_min * PER_MIN
        ticks: list[Tick] = []
        normal, stored = _serve(model, settings, samples, run, growth, capture_at=restart_k, ticks=ticks)
        out.rows[f"normal_{variant}"] = normal
        out.ticks[f"normal_{variant}"] = ticks
        if progress is not None:
            progress(f"  seed {seed} {variant}: normal run ({time.perf_counter() - started:.0f} s)")
        if variant != "offsets":
            continue
        assert stored is not None
        restored, t_ref = stored
        out.ref_before_restart = t_ref
        out.rows["restart_stored"], _ = _serve(
            model, settings, samples, run, growth, first=restart_k, restored=restored
        )
        zeroed = override(settings, "compensation", reference_c=plant.start_c(run))
        out.rows["restart_no_state"], _ = _serve(model, zeroed, samples, run, growth, first=restart_k)
        out.ticks["outages"] = []
        out.rows["outages"], _ = _serve(
            model,
            settings,
            samples,
            run,
            growth,
            plan=plan,
            both_ticks=out.both_ticks,
            ticks=out.ticks["outages"],
        )
    out.wall_s = time.perf_counter() - started
    return out


def _serve(
    model: Any,
    settings: Any,
    samples: list[Sample],
    run: Any,
    growth: np.ndarray,
    *,
    first: int = 0,
    restored: Any = None,
    capture_at: int | None = None,
    plan: Plan | None = None,
    both_ticks: list[tuple[float, bool]] | None = None,
    ticks: list[Tick] | None = None,
) -> tuple[list[Minute], tuple[Any, float | None] | None]:
    """The samples from ``first`` on through one service; with ``plan`` its two outages. Returns the minute
    rows and, with ``capture_at``, what is stored (``stored_state``, the reference) just before that
    sample; with ``ticks``, appends what is served after every sample."""
    session = Session(model, settings, start=samples[first].t, restored=restored)
    svc = session.svc
    rows: list[Minute] = []
    captured = None
    daq = both = (-1, -1)
    if plan is not None:
        daq = (plan.daq_out[0] * PER_MIN, plan.daq_out[1] * PER_MIN)
        both = (plan.both_out[0] * PER_MIN, plan.both_out[1] * PER_MIN)
    last_good = samples[first]
    for k in range(first, len(samples)):
        if k == capture_at:
            stored = stored_state(svc.view, svc.growth.reference, session.stored.checkpoint())
            captured = (stored, svc.growth.t_ref_c(svc.view))
        sample = samples[k]
        session.clock.at_least(sample.t)
        if daq[0] <= k < daq[1]:
            svc.on_sample(stale_daq(last_good, sample))
        elif both[0] <= k < both[1]:
            svc.on_sample(stale_daq(last_good, sample, can_ok=False))
        else:
            svc.on_sample(sample)
            last_good = sample
        t_s = float(run.times_s[k])
        minute = k % PER_MIN == 0
        if both[0] <= k < both[1] and both_ticks is not None:
            m = session.read(t_s, math.nan, run.h_true[k])
            both_ticks.append((t_s - float(run.times_s[both[0] - 1]), m.usable))
        if ticks is not None:
            truth = float(growth[k // PER_MIN]) if minute else math.nan
            ticks.append(session.tick(sample.t.timestamp(), t_s, truth))
        if minute:
            rows.append(
                session.read(t_s, float(growth[k // PER_MIN]), np.asarray(run.h_true[k], dtype=float))
            )
    return rows, captured
