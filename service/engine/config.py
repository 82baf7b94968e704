"""The service core's configuration (``CoreConfig``, built from ``Settings`` by ``runtime.core_config``) and
what the database knew at start-up (``Restored``, read by ``service.engine.persistence.restore``)."""

from __future__ import annotations

from dataclasses import dataclass, field

from service.acquire.calibration import CalibrationConfig
from service.contracts.calibration import Calibration
from service.contracts.checkpoint import LiveCheckpoint
from service.contracts.mechanics import MechanicsCalibration
from service.contracts.mode import IdentificationMode
from service.contracts.probe import ProbeMeasurement
from service.contracts.reference import CompensationReference
from service.contracts.snapshots import ConditionSnapshot, IdentificationRecord
from service.defaults import (
    CARRY_START_ERROR,
    CI_REL_THRESHOLD,
    H_FORM_SD_LN,
    H_NO_BASELINE_SD_LN,
    START_MODES,
)
from service.estimate.state import FilterSettings
from service.identify.detector import DetectorConfig
from service.identify.scheduler import PastResult, SchedulerConfig
from service.identify.speedmap import MapConfig, SpeedMap
from service.identify.window import WindowRules

__all__ = ["CoreConfig", "Restored"]


@dataclass(frozen=True, kw_only=True)
class CoreConfig:
    detector: DetectorConfig = field(default_factory=DetectorConfig)
    scheduler: SchedulerConfig = field(default_factory=SchedulerConfig)
    rules: WindowRules = field(default_factory=WindowRules)
    method: str = "hybrid"
    seed: int = 0
    estimate_loads: bool = False
    carry_start_error: bool = CARRY_START_ERROR  # CIs carry the start field's error (the filtered state's)
    start_modes: int = START_MODES  # the start's leading uncertain directions fitted (IdentifyOptions)
    filter: FilterSettings = field(default_factory=FilterSettings)  # the live state's Kalman filter
    time_budget_s: float | None = None
    ci_threshold: float = CI_REL_THRESHOLD
    h_form_sd: float = H_FORM_SD_LN  # experimental.h_form_sd_ln: added to every served H band (ln H)
    # added to h_form_sd and to the live state's considered H error while calibration is on but has no
    # baseline yet (ln H; CoreParts.no_baseline_sd)
    h_no_baseline_sd: float = H_NO_BASELINE_SD_LN
    # sample time without good data (a sample, >= rules.min_good_channels usable channels and the ambient,
    # speed and torque from CAN) before H is reported stale
    stale_after_s: float = 60.0
    sample_store_period_s: float = 10.0
    # the live state is handed to the writer this often [s of sample time] (a restart resumes the filter
    # from it: service.estimate.checkpoint); 0: never
    live_checkpoint_s: float = 60.0
    min_speed_rpm: float = 100.0  # below: spindle idle, no bearing heat, H not identifiable -> skipped
    initial_h: tuple[float, ...] = (50.0,) * 7  # live-state H before the first identification (no data yet)
    # sensor offsets zeroed against a baseline at thermal equilibrium (service.acquire.calibration); None: the
    # measurements are taken as they come and no offset uncertainty is carried in the CIs
    calibration: CalibrationConfig | None = field(default_factory=CalibrationConfig)
    # experimental.mode: its serving strategy (service.engine.serving) decides what runs and what serves: the
    # per-condition schedule (the paper's protocol, one H per held condition), the speed map (H = F(n, Ti)
    # over a rolling window, re-fitted on condition changes; docs/design/hmap.md) or both ("combined": the
    # held condition's per-condition identification serves instead of the map's H, docs/design/hmap.md
    # "Combined mode")
    mode: IdentificationMode = IdentificationMode.PER_CONDITION
    speed_map: MapConfig = field(default_factory=MapConfig)  # the map's knobs (used when the mode fits one)


@dataclass(frozen=True, kw_only=True)
class Restored:
    """What the database knew at start-up (``service.engine.persistence.restore``)."""

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
