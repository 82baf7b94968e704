"""What the service serves (the values the API, OPC UA and MQTT render): the current H (``ChtcSnapshot``,
the identification ``IdentificationRecord``), the H map (``ChtcMapSnapshot``), the growth
(``CompensationSnapshot``, ``SectionSnapshot``), the field, the sensors, the condition, the identifications
and jobs, the spindle's layout. Built by ``service.serve.views`` and the engine; read through
``service.serve.interface.ChtcService``.

Units: temperatures °C, H in W/(m²·K), lengths m, speed rpm, torque N·m, durations s; every ``datetime`` is
timezone-aware UTC. Snapshots are frozen; arrays inside them must not be mutated after construction.
"""

from __future__ import annotations

import enum
from collections.abc import Sequence
from dataclasses import dataclass, field
from datetime import datetime
from typing import Literal

import numpy as np
import numpy.typing as npt

from model.locator import TriangleLocator, locator_for
from service.contracts.command import CommandSnapshot
from service.contracts.growth import GrowthEstimate, PlcCompensation
from service.contracts.mechanics import MechanicsCalibration
from service.contracts.probe import FixtureOffset
from service.contracts.records import IdentificationData
from service.contracts.reference import CompensationReference
from service.contracts.sensorfault import SensorFault
from service.contracts.verdict import ChtcStatus, Verdict

__all__ = [
    "H_UNIT",
    "ZONE_NAMES",
    "BoolArray",
    "ChtcMapSnapshot",
    "ChtcSnapshot",
    "CompensationSnapshot",
    "ConditionSnapshot",
    "ConditionState",
    "FieldAt",
    "FieldSnapshot",
    "FloatArray",
    "IdentificationJob",
    "IdentificationPage",
    "IdentificationRecord",
    "JobState",
    "Judged",
    "OffsetBaseline",
    "SectionPart",
    "SectionSnapshot",
    "SensorHistory",
    "SensorReading",
    "SpindleLayout",
    "ZoneInfo",
]

H_UNIT = "W/(m²·K)"


FloatArray = npt.NDArray[np.float64]


BoolArray = npt.NDArray[np.bool_]


ZONE_NAMES: tuple[str, ...] = ("H1", "H2", "H3", "H4", "H5", "H6", "H7")


class ConditionState(enum.StrEnum):
    STABLE = "stable"
    CHANGING = "changing"


@dataclass(frozen=True, kw_only=True)
class ConditionSnapshot:
    """One operating condition as seen by the change detector."""

    id: int
    speed_rpm: float
    torque_nm: float
    ambient_c: float
    since: datetime  # UTC start of this condition
    state: ConditionState


FieldAt = Literal["now", "steady"]


@dataclass(frozen=True, eq=False)
class FieldSnapshot:
    """A temperature field on the axisymmetric (r, z) section of the P1 mesh."""

    t: datetime  # UTC instant the field belongs to (for "steady": when it was computed)
    at: FieldAt
    nodes_rz: np.ndarray  # (N, 2) m
    triangles: np.ndarray  # (M, 3) node indices
    temps_c: np.ndarray  # (N,) °C
    identification_id: int | None = None
    # (N,) °C 1σ of temps_c: the filtered live state's uncertainty ("now"); None for "steady" (a model output)
    std_c: np.ndarray | None = None

    @property
    def bounds_rz(self) -> tuple[float, float, float, float]:
        """(r_min, r_max, z_min, z_max) of the mesh, m."""
        lo = self.nodes_rz.min(axis=0)
        hi = self.nodes_rz.max(axis=0)
        return float(lo[0]), float(hi[0]), float(lo[1]), float(hi[1])

    @property
    def locator(self) -> TriangleLocator:
        """The mesh's point locator, shared by every snapshot on the same mesh arrays (built once)."""
        return locator_for(self.nodes_rz, self.triangles)

    def evaluate(self, points_rz: np.ndarray) -> np.ndarray:
        """Temperatures (°C) at (P, 2) points (r, z) in m, by P1 interpolation; NaN outside the section."""
        pts = np.asarray(points_rz, dtype=float).reshape(-1, 2)
        return self.locator.interpolate(self.temps_c, self.locator.locate(pts))

    def evaluate_std(self, points_rz: np.ndarray) -> np.ndarray | None:
        """1σ (°C) at (P, 2) points by P1 interpolation of the nodal 1σ (an upper bound of the interpolated
        temperature's 1σ: σ of a convex combination ≤ the combination of the σ); None without ``std_c``."""
        if self.std_c is None:
            return None
        pts = np.asarray(points_rz, dtype=float).reshape(-1, 2)
        return self.locator.interpolate(self.std_c, self.locator.locate(pts))


@dataclass(frozen=True)
class SensorReading:
    """One channel at the newest sample, with the model's prediction for it."""

    channel: int  # 1..32
    name: str
    role: str  # "bearing" | "housing" | "shaft"
    r_m: float
    z_m: float
    measured_c: float | None  # None when the channel has no usable value (see quality)
    predicted_c: (
        float | None
    )  # the filtered live state at the sensor, offset-corrected; None before it started
    residual_c: float | None  # measured - offset - predicted
    quality: str  # drivers.quality.Quality value: "ok", "stale", "open_circuit", ...
    t: datetime  # UTC of the sample
    offset_c: float | None = None  # zeroed sensor offset (subtracted before the fit); None: no baseline
    offset_sd_c: float | None = None  # 1σ of the offset still unknown, carried in the CIs
    offset_calibrated_at: datetime | None = None  # UTC end of the baseline (service.acquire.calibration)
    offset_source: str | None = None  # the baseline's source (Calibration.source); None: no baseline
    predicted_sd_c: float | None = None  # 1σ of predicted_c (the filtered state's and the model's error)


@dataclass(frozen=True, kw_only=True)
class OffsetBaseline:
    """A sensor-offset baseline taken at thermal equilibrium (``service.acquire.calibration``): the window
    [t_from, t_to] (UTC), "auto" or "manual", and per channel the offset and its 1σ (°C; None: no data)."""

    t_from: datetime
    t_to: datetime
    source: str
    samples: int
    offsets_c: tuple[float | None, ...]
    sd_c: tuple[float, ...]


@dataclass(frozen=True, eq=False, kw_only=True)
class IdentificationRecord:
    """One finished (or failed, skipped, cancelled) identification as served: the stored ``data``, the
    condition it was taken at, and its per-zone values as read-only (7,) arrays.

    Built by ``service.serve.views.data_to_record`` only. Every other value is the stored record's, read
    through ``data`` (the properties below name the ones the service and the API use).
    """

    data: IdentificationData
    condition: ConditionSnapshot
    h: FloatArray  # (7,) W/(m²·K); NaN when not identified (failed, skipped)
    ci95_lo: FloatArray  # (7,) W/(m²·K), >= 0
    ci95_hi: FloatArray
    identified: BoolArray  # (7,) 95 % CI narrow enough and not at a bound
    at_bound: BoolArray  # (7,) H on a bound of the search box (then not identified)
    # (7,) H the data could not see: value and band are the prior's (a MAP fit; never identified)
    prior_dominated: BoolArray = field(default_factory=lambda: np.zeros(len(ZONE_NAMES), dtype=bool))

    @property
    def id(self) -> int:
        return self.data.id

    @property
    def started_at(self) -> datetime:
        return self.data.started_at

    @property
    def finished_at(self) -> datetime:
        return self.data.finished_at

    @property
    def reason(self) -> str:
        """Trigger: "condition-change" | "scheduled" | "manual" | ..."""
        return self.data.reason

    @property
    def outcome(self) -> str:
        """A ``service.contracts.outcome.Outcome`` value: "ok", "failed", "insufficient-data", ..."""
        return self.data.outcome

    @property
    def message(self) -> str:
        return self.data.message

    @property
    def window_from(self) -> datetime:
        return self.data.window_start

    @property
    def window_to(self) -> datetime:
        return self.data.window_end

    @property
    def f(self) -> float | None:
        """Objective: mean squared residual, °C²."""
        return self.data.f

    @property
    def fit(self) -> float | None:
        """1 / (1 + f)."""
        return self.data.fit

    @property
    def rmse_c(self) -> float | None:
        return self.data.rmse_c

    @property
    def method(self) -> str:
        return self.data.method

    @property
    def model_version(self) -> str:
        return self.data.model_version

    @property
    def nfev(self) -> int:
        return self.data.nfev

    @property
    def wall_s(self) -> float:
        return self.data.duration_s

    @property
    def n_sensors_used(self) -> int:
        """Channels the fit used (masked-out ones excluded)."""
        return self.data.n_sensors_used


class Judged:
    """A snapshot carrying the served-value policy's ``verdict`` (``service.serve.policy``), read through
    these properties: its status, the usable flag a consumer acts on, and the reason for humans."""

    verdict: Verdict

    @property
    def status(self) -> ChtcStatus:
        return self.verdict.status

    @property
    def usable_for_compensation(self) -> bool:
        """The flag a consumer acts on (the policy's verdict)."""
        return self.verdict.usable

    @property
    def reason(self) -> str | None:
        """Why not usable, for humans ("code: detail"; ``verdict.reason`` is the typed code)."""
        return self.verdict.text


@dataclass(frozen=True, eq=False, kw_only=True)
class ChtcSnapshot(Judged):
    """The current H1-H7 (the identification ``record``) and whether a controller may use them now.

    Built by ``service.serve.views.chtc_snapshot`` only; the record's values are read through it.
    """

    record: IdentificationRecord  # the identification served: H, CIs, fit, provenance
    newest_sample_at: datetime | None  # UTC of the newest sample in the ring buffer
    identified: BoolArray  # (7,) the record's flag and not at a bound of the search box
    at_bound: BoolArray  # (7,) H on a bound of the search box (not identified)
    verdict: Verdict  # the policy's (service.serve.policy.chtc_verdict): status, usable, reason
    unit: str = H_UNIT
    zones: tuple[str, ...] = ZONE_NAMES
    box: tuple[float, float] | None = None  # the search box of H, W/(m²·K) (bounds beyond it print "> box")
    # channels the live state leaves out as stuck or drifting (service.estimate.sensorfaults), by channel
    sensor_faults: tuple[SensorFault, ...] = ()

    @property
    def h(self) -> FloatArray:
        """(7,) W/(m²·K)."""
        return self.record.h

    @property
    def prior_dominated(self) -> BoolArray:
        """(7,) H the data did not see: the prior's value and band (a MAP fit; never identified)."""
        return self.record.prior_dominated

    @property
    def ci95_lo(self) -> FloatArray:
        return self.record.ci95_lo

    @property
    def ci95_hi(self) -> FloatArray:
        return self.record.ci95_hi

    @property
    def identified_at(self) -> datetime:
        """UTC end of the identification."""
        return self.record.finished_at

    @property
    def condition(self) -> ConditionSnapshot:
        """The condition the window was taken at."""
        return self.record.condition

    @property
    def identification_id(self) -> int:
        return self.record.id

    @property
    def f(self) -> float | None:
        """Objective: mean squared residual, °C²."""
        return self.record.f

    @property
    def fit(self) -> float | None:
        return self.record.fit

    @property
    def rmse_c(self) -> float | None:
        return self.record.rmse_c

    @property
    def method(self) -> str:
        return self.record.method

    @property
    def model_version(self) -> str:
        return self.record.model_version


@dataclass(frozen=True, eq=False, kw_only=True)
class ChtcMapSnapshot(Judged):
    """The identified H map H = F(n, Ti) over the speed range (``identification.mode = "speed_map"``,
    docs/design/hmap.md): H1-H7 and their 95 % bands on a speed grid at the current ambient, the speeds the
    data have covered, and how current the map is.

    Built by ``service.serve.views.chtc_map_snapshot`` only. Arrays are read-only; speeds in rpm, H in
    W/(m²·K), durations in s, times UTC. Between and beyond the visited speeds the map is the prior's
    interpolation (its band says so: wide there).
    """

    fitted_at: datetime  # UTC end of the window of the fit the map comes from
    identification_id: int | None  # the stored identification of that fit (None: not stored)
    family: str  # "nodes" (ln H at speed nodes, the default) | "physics" (model.hmap)
    ambient_c: float  # the ambient the grid is evaluated at (the newest sample's; 20 °C before any)
    speeds_rpm: FloatArray  # (k,) grid, 0..7000 rpm
    h_w_m2k: FloatArray  # (k, 7)
    ci95_lo_w_m2k: FloatArray  # (k, 7), > 0
    ci95_hi_w_m2k: FloatArray  # (k, 7)
    identified: BoolArray  # (k, 7) 95 % band narrower than identification.ci_rel_threshold
    visited_rpm: FloatArray  # (m,) speeds the data covered (binned), ascending
    visited_s: FloatArray  # (m,) seconds of data at each visited speed (decayed like the map's information)
    verdict: Verdict  # how current the map is at the current speed (service.serve.policy.map_verdict)
    newest_sample_at: datetime | None  # UTC of the newest sample
    current_speed_rpm: float | None = None  # the newest sample's speed (None before any)
    visited_margin_rpm: float = 0.0  # a speed within this of a visited one counts as covered
    rmse_c: float | None = None  # the fit's RMS residual, °C
    restored: bool = False  # the stored map, not re-fitted since the restart
    unit: str = H_UNIT
    zones: tuple[str, ...] = ZONE_NAMES


@dataclass(frozen=True, kw_only=True)
class IdentificationPage:
    items: Sequence[IdentificationRecord]  # newest first
    total: int  # matching the filter, over all pages
    limit: int
    offset: int
    partial_reason: str | None = None  # set when the database could not be read: only records in memory


class JobState(enum.StrEnum):
    QUEUED = "queued"
    RUNNING = "running"
    DONE = "done"
    FAILED = "failed"


@dataclass(frozen=True, kw_only=True)
class IdentificationJob:
    job_id: str
    reason: str
    state: JobState
    requested_at: datetime
    finished_at: datetime | None = None
    identification_id: int | None = None  # set when state is DONE (or FAILED with a stored record)
    message: str = ""


@dataclass(frozen=True, eq=False, kw_only=True)
class CompensationSnapshot(Judged):
    """What ``/compensation`` serves (docs/design/growth.md): the thermal growth at the spindle nose from the
    live field (``growth``: µm, 0.1-µm integers, 95 % CIs, forecast, sensor sensitivity; frozen) with the
    policy's verdict on it at the same instant (``service.serve.policy.compensation_verdict``: judged on the
    growth itself, not on the H), and the controller values of the axial growth (``plc``, for a tool pointing
    along ``tool_dir`` of the machine axis)."""

    growth: GrowthEstimate
    verdict: Verdict  # the policy's (service.serve.policy.compensation_verdict): status, usable, reason
    newest_sample_at: datetime | None
    identification_id: int | None  # the identification whose H the growth uses (None: none yet, H guessed)
    plc: PlcCompensation
    tool_dir: int  # -1: the tool points to -Z
    channels: tuple[int, ...]  # sensor channel numbers of the sensitivity entries
    reference: CompensationReference | None = None  # the zero in use (None: none set, not usable)
    mechanics: MechanicsCalibration | None = None  # the commissioned mechanics (None: the description's)
    # the fixture offset the probe readings measured, included in the axial growth (None: none absorbed)
    fixture_offset: FixtureOffset | None = None
    # channels the live state leaves out as stuck or drifting (service.estimate.sensorfaults), by channel:
    # the growth's CI carries what they bent before they were found
    sensor_faults: tuple[SensorFault, ...] = ()
    # what the controller applies now (service.serve.controlled; None: no controller stepped it)
    command: CommandSnapshot | None = None
    # the policy's verdict before the CI gate (``verdict`` is the gated one; None: no gate, they are one)
    policy_verdict: Verdict | None = None

    @property
    def reference_at(self) -> datetime | None:
        """When the compensation reference was set; None: none set (the growth is provisional)."""
        return None if self.reference is None else self.reference.at


@dataclass(frozen=True, eq=False, kw_only=True)
class SectionSnapshot:
    """What ``/compensation/section`` serves (docs/design/growth.md, "The deformed section"): the outline of
    the spindle's axisymmetric section (``nodes_rz`` (M, 2) [m], ``edges`` (E, 2) node indices: every region's
    boundary) and its displacement ``u_um`` (2, M) [µm] (u_r, u_z) by the live field over the reference
    ``t_ref_c``, at ``at`` (UTC, the live field's instant), with the status of ``/compensation``."""

    at: datetime
    t_ref_c: float
    nodes_rz: FloatArray
    edges: npt.NDArray[np.int64]
    u_um: FloatArray
    status: ChtcStatus
    identification_id: int | None
    newest_sample_at: datetime | None


@dataclass(frozen=True, eq=False, kw_only=True)
class SensorHistory:
    """Per-sample measured and predicted temperatures, oldest first (measured vs predicted over time)."""

    t: tuple[datetime, ...]  # (n,) UTC sample times
    measured_c: np.ndarray  # (n, C) °C; NaN where the channel had no usable value (quality not "ok")
    predicted_c: np.ndarray  # (n, C) °C; NaN before the first identification
    channels: tuple[int, ...]  # (C,) channel numbers of the columns
    names: tuple[str, ...]  # (C,) sensor names (the spindle description's)
    roles: tuple[str, ...]  # (C,) "bearing" | "housing" | "shaft"
    capacity: int  # samples the buffer keeps; older ones are gone


@dataclass(frozen=True, kw_only=True)
class SectionPart:
    """A solid part of the (r, z) section: a rectangle in m (``[[regions]]`` of the spindle TOML)."""

    name: str  # e.g. "housing", "front_end_cap", "rear_bearing"
    material: str
    r0_m: float
    r1_m: float
    z0_m: float
    z1_m: float


@dataclass(frozen=True)
class ZoneInfo:
    name: str  # "H1" .. "H7"
    description: str  # e.g. "rear shaft pulley <-> ambient"


@dataclass(frozen=True, kw_only=True)
class SpindleLayout:
    name: str  # the spindle description's name
    parts: tuple[SectionPart, ...]
    zones: tuple[ZoneInfo, ...]
