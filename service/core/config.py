"""The service core's configuration (``CoreConfig``, built from ``Settings`` by ``core_config``) and what
the database knew at start-up (``Restored``, read by ``service.host.persistence.restore``).

One declaration per setting: the configuration objects of the engine (``CoreConfig`` and its parts, the
policy's ``CompensationLimits``) have no defaults of their own. Every value comes from its settings section
(``service.settings``, where the defaults are declared) or, for a value with no settings key, from a named
constant of the module that uses it; the functions here are the one place that maps one onto the other
(``tests/settings/test_engine_config.py`` holds them to that).
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass
from typing import TYPE_CHECKING

from service.acquire import calibration as cal
from service.acquire.calibration import CalibrationConfig
from service.contracts.calibration import Calibration
from service.contracts.checkpoint import LiveCheckpoint
from service.contracts.mechanics import MechanicsCalibration
from service.contracts.mode import IdentificationMode
from service.contracts.probe import ProbeMeasurement
from service.contracts.reference import CompensationReference
from service.contracts.snapshots import ConditionSnapshot, IdentificationRecord
from service.defaults import H_NO_BASELINE_SD_LN
from service.estimate.state import FilterSettings
from service.identify.detector import DetectorConfig
from service.identify.scheduler import PastResult, SchedulerConfig
from service.identify.speedmap import MAP_BIN_RPM, MapConfig, SpeedMap
from service.identify.window import MAX_GAP_S, MIN_GOOD_FRACTION, WindowRules
from service.serve.cigate import CiGateLimits
from service.serve.command import profile_from
from service.serve.controlled import ControlLimits
from service.serve.policy import compensation_limits

if TYPE_CHECKING:
    from service.settings import IdentificationSettings, Settings

__all__ = [
    "CoreConfig",
    "Restored",
    "calibration_config",
    "checkpoint_phase",
    "compensation_limits",
    "control_limits",
    "core_config",
    "map_config",
]

# the core's values with no settings key
MIN_SPEED_RPM = 100.0  # below: spindle idle, no bearing heat, H not identifiable -> skipped
INITIAL_H = (50.0,) * 7  # live-state H before the first identification (no data yet), W/(m²·K)
STALE_AFTER_MIN_S = 60.0  # H is reported stale after this long without good data, or ...
STALE_AFTER_SAMPLES = 6  # ... this many sample periods, whichever is longer
FILTER = FilterSettings()  # the live state's filter tuning: its own defaults (frozen, shared)


@dataclass(frozen=True, kw_only=True)
class CoreConfig:
    """The core's configuration; no defaults (``core_config(settings)`` builds it)."""

    detector: DetectorConfig
    scheduler: SchedulerConfig
    rules: WindowRules
    method: str  # experimental.method
    seed: int  # experimental.seed
    estimate_loads: bool  # experimental.estimate_loads
    carry_start_error: bool  # CIs carry the start field's error (the filtered state's)
    start_modes: int  # the start's leading uncertain directions fitted (IdentifyOptions)
    filter: FilterSettings  # the live state's Kalman filter (no settings key: its own defaults)
    time_budget_s: float | None  # an identification's optimizer budget (None: none; no settings key)
    ci_threshold: float  # identification.ci_rel_threshold
    h_form_sd: float  # experimental.h_form_sd_ln: added to every served H band (ln H)
    # added to the live state's considered H error (ln H; CoreParts.h_rel_for): h_form_sd in the service, 0 in
    # the commissioning's field history, whose fit estimates its own residual noise and correlation
    live_h_form_sd: float
    # added to h_form_sd and to the live state's considered H error while calibration is on but has no
    # baseline yet (ln H; CoreParts.no_baseline_sd; service.defaults.H_NO_BASELINE_SD_LN)
    h_no_baseline_sd: float
    # sample time without good data (a sample, >= rules.min_good_channels usable channels and the ambient,
    # speed and torque from CAN) before H is reported stale
    stale_after_s: float
    sample_store_period_s: float  # database.sample_store_period_s
    # the live state is handed to the writer this often [s of sample time] (a restart resumes the filter
    # from it: service.estimate.checkpoint); 0: never (database.live_checkpoint_s)
    live_checkpoint_s: float
    # the first checkpoint this long after the first sample [s], the next every live_checkpoint_s: a host's
    # spindles, started together, would otherwise all hand theirs to the writers in the same second
    # (``checkpoint_phase``; docs/design/fleet.md)
    live_checkpoint_phase_s: float
    min_speed_rpm: float  # below: spindle idle, no bearing heat, H not identifiable -> skipped
    initial_h: tuple[float, ...]  # live-state H before the first identification (no data yet)
    # sensor offsets zeroed against a baseline at thermal equilibrium (service.acquire.calibration); None: the
    # measurements are taken as they come and no offset uncertainty is carried in the CIs
    calibration: CalibrationConfig | None
    # identification.mode: its serving strategy (service.core.serving) decides what runs and what serves:
    # the per-condition schedule (the paper's protocol, one H per held condition), the speed map (H = F(n, Ti)
    # over a rolling window, re-fitted on condition changes; docs/design/hmap.md) or both ("combined": the
    # held condition's per-condition identification serves instead of the map's H, docs/design/hmap.md
    # "Combined mode")
    mode: IdentificationMode
    speed_map: MapConfig  # the map's knobs (used when the mode fits one)


def checkpoint_phase(spindle_id: str, every_s: float) -> float:
    """How long after its live state starts a spindle's first checkpoint falls [s]: a fraction of
    ``every_s`` drawn from the spindle's id (CRC-32), so a host's spindles, started together, spread theirs
    over the period without knowing each other (the same fraction at every start)."""
    return every_s * (zlib.crc32(spindle_id.encode("utf-8")) % 1000) / 1000.0 if every_s > 0.0 else 0.0


def core_config(settings: Settings) -> CoreConfig:
    """The core's configuration from ``Settings`` (minutes -> s; the window grid is the sample period)."""
    ident, det, acq = settings.identification, settings.detector, settings.acquisition
    exp = settings.experimental
    return CoreConfig(
        detector=DetectorConfig(
            speed_threshold_rpm=det.speed_threshold_rpm,
            torque_threshold_nm=det.torque_threshold_nm,
            ambient_threshold_c=det.ambient_threshold_c,
            hold_s=det.hold_s,
            median_samples=det.median_samples,
            max_gap_s=det.max_gap_s,
        ),
        scheduler=SchedulerConfig(
            min_data_s=ident.min_window_s,
            schedule_s=ident.schedule_s,
            max_window_s=ident.max_window_s,
            distance_scales=exp.distance_scales,
            tolerance_s=0.5 * acq.sample_period_s,
        ),
        rules=WindowRules(
            dt_s=acq.sample_period_s,
            min_window_s=ident.min_window_s,
            min_good_channels=ident.min_good_channels,
            min_good_fraction=MIN_GOOD_FRACTION,
            max_gap_s=MAX_GAP_S,
        ),
        method=exp.method,
        seed=exp.seed,
        estimate_loads=exp.estimate_loads,
        carry_start_error=exp.carry_start_error,
        start_modes=exp.start_modes,
        filter=FILTER,
        time_budget_s=None,
        ci_threshold=ident.ci_rel_threshold,
        h_form_sd=exp.h_form_sd_ln,
        live_h_form_sd=exp.h_form_sd_ln,
        h_no_baseline_sd=H_NO_BASELINE_SD_LN,
        stale_after_s=max(STALE_AFTER_MIN_S, STALE_AFTER_SAMPLES * acq.sample_period_s),
        sample_store_period_s=settings.database.sample_store_period_s,
        live_checkpoint_s=settings.database.live_checkpoint_s,
        live_checkpoint_phase_s=checkpoint_phase(settings.spindle.id, settings.database.live_checkpoint_s),
        min_speed_rpm=MIN_SPEED_RPM,
        initial_h=INITIAL_H,
        calibration=calibration_config(ident) if ident.offset_calibration else None,
        mode=ident.mode,
        speed_map=map_config(settings),
    )


def calibration_config(ident: IdentificationSettings) -> CalibrationConfig:
    """The sensor offsets' equilibrium test from ``[identification]`` (``offset_*``, ``min_good_channels``)
    and ``service.acquire.calibration``'s constants (used when ``offset_calibration`` is on)."""
    return CalibrationConfig(
        rest_s=ident.offset_rest_s,
        max_rest_s=cal.MAX_REST_S,
        idle_speed_rpm=cal.IDLE_SPEED_RPM,
        flat_c=cal.FLAT_C,
        channel_flat_c=cal.CHANNEL_FLAT_C,
        max_offset_c=cal.MAX_OFFSET_C,
        mean_tol_c=cal.MEAN_TOL_C,
        min_channels=ident.min_good_channels,
        no_baseline_sd_c=ident.offset_sd_c,
        equilibrium_sd_c=cal.EQUILIBRIUM_SD_C,
    )


def map_config(settings: Settings) -> MapConfig:
    """The speed map's configuration (used in ``identification.mode`` ``"speed_map"`` and ``"combined"``)."""
    ident, exp = settings.identification, settings.experimental
    return MapConfig(
        window_s=60.0 * ident.map_window_min,
        min_window_s=60.0 * exp.map_min_window_min,
        debounce_s=exp.map_debounce_s,
        refit_s=60.0 * ident.map_refit_min,
        fresh_s=60.0 * ident.map_fresh_min,
        margin_rpm=exp.map_margin_rpm,
        min_visit_s=exp.map_min_visit_s,
        bin_rpm=MAP_BIN_RPM,
        tau_h=exp.map_forget_tau_h,
        family=exp.map_family,
        prior_weight=exp.map_prior_weight,
        prior_level_sd=exp.map_prior_level_sd,
    )


def control_limits(settings: Settings) -> ControlLimits:
    """The CI gate's limits (``[compensation]`` ``max_ci95_um``, ``ci_*``), the controller's profile and the
    command's hold (``[controller]``) for ``service.serve.controlled``."""
    comp, ctl = settings.compensation, settings.controller
    return ControlLimits(
        gate=CiGateLimits(
            max_ci95_um=comp.max_ci95_um,
            enter_fraction=comp.ci_enter_fraction,
            exit_hold_s=comp.ci_exit_hold_s,
            hard_fraction=comp.ci_hard_fraction,
        ),
        profile=profile_from(
            ctl.profile, max_step_um=ctl.max_step_um, max_rate_um_s=ctl.max_rate_um_s, limit_um=ctl.limit_um
        ),
        hold_s=ctl.hold_s,
    )


@dataclass(frozen=True, kw_only=True)
class Restored:
    """What the database knew at start-up (``service.host.persistence.restore``)."""

    last: IdentificationRecord | None = None
    history: tuple[PastResult, ...] = ()
    conditions: tuple[ConditionSnapshot, ...] = ()  # newest first
    next_condition_id: int = 1
    next_identification_id: int = 1
    calibration: Calibration | None = None  # the newest stored sensor offset baseline
    speed_map: SpeedMap | None = None  # the newest stored map fit (speed-map mode), restored as stale
    map_last: IdentificationRecord | None = None  # its identification (``last`` unless combined mode)
    reference: CompensationReference | None = None  # the newest stored compensation zero
    live: LiveCheckpoint | None = None  # the live state's stored checkpoint (the filter resumes from it)
    mechanics: MechanicsCalibration | None = None  # the newest stored commissioning of the mechanics
    probes: tuple[ProbeMeasurement, ...] = ()  # the newest stored probe readings, oldest first
