"""The one validated settings object of the service.

``Settings`` is built once at the edge (``chtc run --config FILE`` → ``load_settings(path)``, or
``create_app(settings)``) and handed down as typed sections: ``settings.modbus``, ``settings.can``,
``settings.acquisition``, ``settings.model``, ``settings.identification`` (with the identification mode),
``settings.detector``, ``settings.api``, ``settings.database``, ``settings.compensation``, and
``settings.experimental``: the research switches (optimizer, the speed map's inner workings, mesh and rank)
an operator leaves at their measured defaults (issue 25; docs/configuration.md). Each value is declared once,
here: the engine's configuration objects have no defaults of their own and are built from these sections
(``service.core.config.core_config``).
Nothing here opens a file, a socket or a database at import time.

Precedence, highest first: keyword arguments to ``Settings(...)``, environment variables, the TOML file,
the defaults below. Environment variables use the prefix ``CHTC_`` and ``__`` between section and key,
e.g. ``CHTC_DATABASE__URL``, ``CHTC_API__TOKEN``, ``CHTC_MODBUS__PORT``. List and tuple values in the
environment are JSON (``CHTC_IDENTIFICATION__SCHEDULE_MIN='[7, 20, 40, 60]'``). ``Settings()`` with no file
works for the demo. Relative paths in a TOML file are relative to that file's directory.

Directories: ``CHTC_DATA_DIR`` (default ``$XDG_DATA_HOME/spindle-chtc`` or ``~/.local/share/spindle-chtc``)
holds the default SQLite database; ``CHTC_CACHE_DIR`` (default ``$XDG_CACHE_HOME/spindle-chtc`` or
``~/.cache/spindle-chtc``) is the default reduced-model cache. Both are read when ``Settings`` is built.

Errors::

    SettingsError(ValueError)   # bad value, unknown key, unreadable or malformed TOML; the message names
                                # the key ("modbus.port: ...") and the file (and line for TOML syntax errors);
                                # a key moved to another section or removed says so (MOVED_KEYS,
                                # REMOVED_KEYS)
"""

from __future__ import annotations

import os
import tomllib
from collections.abc import Callable
from contextvars import ContextVar
from pathlib import Path
from typing import Any, Literal, NamedTuple, TypeVar

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    SecretStr,
    ValidationError,
    field_validator,
    model_validator,
)
from pydantic_settings import (
    BaseSettings,
    InitSettingsSource,
    PydanticBaseSettingsSource,
    SettingsConfigDict,
)

from service.contracts.mode import IdentificationMode
from service.defaults import CARRY_START_ERROR, CI_REL_THRESHOLD, H_FORM_SD_LN, START_MODES
from service.errors import ServiceError
from service.mqttsettings import MqttSettings

APP_DIR_NAME = "spindle-chtc"
IDENTIFICATION_METHODS = ("hybrid", "igwo", "gwo", "woa", "ga", "empirical")  # == model.identify.METHODS


class SettingsError(ServiceError, ValueError):
    """A configuration value is invalid; the message names the key (``section.key``) and the source."""


def default_data_dir() -> Path:
    """``$CHTC_DATA_DIR``, else ``$XDG_DATA_HOME/spindle-chtc``, else ``~/.local/share/spindle-chtc``."""
    if env := os.environ.get("CHTC_DATA_DIR"):
        return Path(env).expanduser()
    base = os.environ.get("XDG_DATA_HOME") or str(Path.home() / ".local" / "share")
    return Path(base).expanduser() / APP_DIR_NAME


def default_cache_dir() -> Path:
    """``$CHTC_CACHE_DIR``, else ``$XDG_CACHE_HOME/spindle-chtc``, else ``~/.cache/spindle-chtc``."""
    if env := os.environ.get("CHTC_CACHE_DIR"):
        return Path(env).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base).expanduser() / APP_DIR_NAME


def default_database_url() -> str:
    """SQLite file ``chtc.db`` in the data directory (created by the engine factory on first use)."""
    return f"sqlite:///{default_data_dir() / 'chtc.db'}"


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


SPINDLE_ID_PATTERN = r"^[A-Za-z][A-Za-z0-9_-]{0,62}$"
# the [mqtt] keys a hosted spindle may set of its own ([[spindles]] mqtt = {...}): its Sparkplug device id and
# JSON topic level; the rest (broker, group, edge node) is the host's one connection
SPINDLE_MQTT_KEYS = frozenset({"device_id"})


class SpindleSettings(_Section):
    """Which spindle this instance serves: a stable name stored in every database row (``spindle_id``), so
    many spindles can share one database (docs/design/persistence.md, "Many spindles in one database")."""

    id: str = Field(default="spindle1", pattern=SPINDLE_ID_PATTERN)  # never rename a spindle in service
    description: str = Field(default="", max_length=200)  # stored in the ``spindles`` table


class SpindleEntry(_Section):
    """One spindle of an instance that hosts several (``[[spindles]]``; docs/design/fleet.md).

    ``modbus`` and ``can`` hold only the keys that differ from the top-level ``[modbus]``/``[can]`` (its DAQ
    address, its CAN channel), merged over them; ``mqtt`` likewise over ``[mqtt]``, with only the keys a
    spindle may have of its own (``SPINDLE_MQTT_KEYS``: its Sparkplug device id, the level of its JSON
    topics); ``geometry`` is its ``model.spindle`` file (default: the top-level one). Spindles with the same
    geometry share one reduced model."""

    id: str = Field(pattern=SPINDLE_ID_PATTERN)
    description: str = Field(default="", max_length=200)
    modbus: dict[str, Any] = Field(default_factory=dict)  # raw keys, validated merged over [modbus]
    can: dict[str, Any] = Field(default_factory=dict)  # raw keys, validated merged over [can]
    mqtt: dict[str, Any] = Field(default_factory=dict)  # raw keys (SPINDLE_MQTT_KEYS), merged over [mqtt]
    geometry: Path | None = None


class ModbusSettings(_Section):
    """Temperature DAQ over Modbus TCP (input registers, read-only)."""

    host: str = "127.0.0.1"
    port: int = Field(default=5020, ge=1, le=65535)
    unit: int | None = Field(default=None, ge=0, le=247)  # None → the register map's unit_id (1 by default)
    timeout_s: float = Field(default=1.0, gt=0)
    poll_interval_s: float = Field(default=1.0, gt=0)
    register_map: Path | None = None  # TOML register map; None → drivers.registers.default_register_map()


_CAN_RESERVED_OPTIONS = frozenset(
    {"interface", "channel", "bitrate", "fd", "data_bitrate", "can_filters", "ignore_config"}
)


class CanFilter(_Section):
    """One python-can receive filter: a frame passes when ``id & can_mask == can_id & can_mask``."""

    can_id: int = Field(ge=0, le=0x1FFFFFFF)
    can_mask: int = Field(ge=0, le=0x1FFFFFFF)
    extended: bool | None = None  # None: both 11- and 29-bit IDs


class CanSettings(_Section):
    """Speed/torque sensor over CAN (python-can interface + DBC)."""

    interface: str = "virtual"  # any python-can interface (can.interfaces.VALID_INTERFACES)
    channel: str = "chtc"  # "can0" for socketcan, "ws://host:port/" for remote, any name for virtual
    dbc: Path | None = None  # None → packaged drivers/data/spindle.dbc
    bitrate: int | None = Field(default=None, gt=0)
    stale_after_s: float = Field(
        default=0.5, gt=0
    )  # no SpindleStatus frame for this long → speed/torque STALE
    # the reader thread wakes the event loop once per batch of frames (after the first frame waited this
    # long; 0: once per frame): at 100 frames/s, 0.05 s is 20 wake-ups/s instead of 100
    # (docs/design/threading.md)
    batch_s: float = Field(default=0.05, ge=0, le=0.25)
    fd: bool = False  # open the bus in CAN FD mode (SpindleStatus frames must still be CAN 2.0A)
    data_bitrate: int | None = Field(default=None, gt=0)  # CAN FD data-phase bit rate, bit/s
    filters: list[CanFilter] | None = None  # python-can can_filters, applied by the interface
    options: dict[str, object] = Field(default_factory=dict)  # further keyword arguments for the interface

    @field_validator("interface")
    @classmethod
    def _known_interface(cls, value: str) -> str:
        import can.interfaces  # only needed when a CAN section is validated

        if value not in can.interfaces.VALID_INTERFACES:
            known = ", ".join(sorted(can.interfaces.VALID_INTERFACES))
            raise ValueError(f"unknown python-can interface {value!r} (one of {known})")
        return value

    @field_validator("options")
    @classmethod
    def _no_reserved_options(cls, value: dict[str, object]) -> dict[str, object]:
        reserved = sorted(set(value) & _CAN_RESERVED_OPTIONS)
        if reserved:
            raise ValueError(
                f"{reserved} have their own keys (interface, channel, bitrate, fd, data_bitrate, filters)"
            )
        return value


class AcquisitionSettings(_Section):
    ring_capacity: int = Field(default=8640, ge=2)  # samples kept in memory (8640 × 10 s = 24 h)
    sample_period_s: float = Field(default=10.0, gt=0)  # one Sample per period (the paper samples every 10 s)


class ModelSettings(_Section):
    spindle: Path | None = None  # None → packaged model/data/spindle.toml
    rom_cache_dir: Path = Field(default_factory=default_cache_dir)
    h_box: tuple[float, float] = (5.0, 200.0)  # search box for H1..H7, W/(m²·K)

    @field_validator("h_box")
    @classmethod
    def _box_ordered(cls, value: tuple[float, float]) -> tuple[float, float]:
        lo, hi = value
        if not 0 < lo < hi:
            raise ValueError(f"need 0 < lo < hi, got [{lo}, {hi}]")
        return value


class IdentificationSettings(_Section):
    """What an operator tunes for a machine: how H is identified and served (``mode``), when, on how much
    data, how sure it must be, the sensor offsets, and how long the speed map stays fresh. The research
    switches are in ``ExperimentalSettings`` (``[experimental]``)."""

    # "per_condition": one H per held condition (the paper's protocol: schedule_min, min/max_window_s);
    # "speed_map": H = F(n, Ti) fitted over a rolling window of map_window_min, re-fitted
    # experimental.map_debounce_s after each condition change (and every map_refit_min), served at the
    # current speed at once (docs/design/hmap.md); "combined": both, the per-condition H served at a condition
    # held longer than the first schedule entry, the map's elsewhere (docs/design/hmap.md "Combined mode").
    # In [experimental] until issue 39
    mode: IdentificationMode = IdentificationMode.COMBINED

    # re-identify this long after a condition change (or after the live state's convergence on a restart).
    # The first entry is 7 min, not 10: the window starts from the converged filtered state with its
    # covariance, so the first H is served within 13 min of a (re)start, also when the restart falls just
    # before a change (docs/design/estimator.md, "First served H after a start"); the later windows are
    # unchanged
    schedule_min: tuple[float, ...] = (7.0, 20.0, 40.0, 60.0)
    min_window_s: float = Field(default=420.0, gt=0)  # shorter windows are skipped ("too little data")
    max_window_s: float = Field(default=3600.0, gt=0)  # fit at most this much recent data
    min_good_channels: int = Field(default=24, ge=1, le=32)
    # 95 % half-width of log H (≈ relative half-width) above this → "not identified"
    # (docs/design/identification.md)
    ci_rel_threshold: float = Field(default=CI_REL_THRESHOLD, gt=0)
    timeout_s: float = Field(default=120.0, gt=0)
    # zero the sensor offsets against a baseline at thermal equilibrium (spindle idle, offset_rest_s, sensors
    # flat, at the ambient: service.acquire.calibration); without a baseline their 1σ offset_sd_c widens the
    # CIs
    offset_calibration: bool = True
    offset_rest_s: float = Field(default=300.0, gt=0)
    offset_sd_c: float = Field(default=0.173, ge=0)  # ±0.3 °C uniform, unknown until a baseline
    # the speed map (mode "speed_map" or "combined", docs/design/hmap.md): fitted over a rolling
    # window of map_window_min, again every map_refit_min without a change, not fresh after map_fresh_min
    map_window_min: float = Field(default=60.0, gt=0)
    map_refit_min: float = Field(default=10.0, gt=0)
    map_fresh_min: float = Field(default=15.0, gt=0)

    @field_validator("schedule_min")
    @classmethod
    def _schedule_increasing(cls, value: tuple[float, ...]) -> tuple[float, ...]:
        if not value or any(v <= 0 for v in value) or list(value) != sorted(set(value)):
            raise ValueError(
                f"need a non-empty, strictly increasing list of positive minutes, got {list(value)}"
            )
        return value

    @model_validator(mode="after")
    def _windows_consistent(self) -> IdentificationSettings:
        if self.max_window_s < self.min_window_s:
            raise ValueError(
                f"max_window_s ({self.max_window_s}) must be >= min_window_s ({self.min_window_s})"
            )
        if self.schedule_min[0] * 60.0 < self.min_window_s:
            raise ValueError(
                f"the first schedule entry ({self.schedule_min[0]} min) comes before min_window_s "
                f"({self.min_window_s} s) of data exists"
            )
        return self

    @property
    def schedule_s(self) -> tuple[float, ...]:
        """``schedule_min`` in s."""
        return tuple(60.0 * m for m in self.schedule_min)


class ExperimentalSettings(_Section):
    """Research switches (issue 25): their defaults are the measured choices (docs/design/hmap.md,
    docs/design/rom.md, docs/design/estimator.md); they are here to reproduce or extend a measurement (the
    benches' ``--set KEY=VALUE``, ``CHTC_EXPERIMENTAL__KEY``), not to tune a machine. One section for the
    identification's and the model's switches, so an operator's file needs none of them (the identification
    mode, the product's one choice among them, is ``identification.mode`` since issue 39)."""

    method: Literal["hybrid", "igwo", "gwo", "woa", "ga", "empirical"] = "hybrid"
    # 1σ in ln H added in quadrature to every band /chtc serves: the model-form error no statistical band
    # sees (docs/design/policy.md, "The served H band"); the ``identified`` flag is judged on the widened band
    h_form_sd_ln: float = Field(default=H_FORM_SD_LN, ge=0, le=2)
    seed: int = 0
    estimate_loads: bool = False  # also fit front/rear bearing heat scales
    # the filtered start state's leading uncertain directions fitted in each window (0: only carried)
    start_modes: int = Field(default=START_MODES, ge=0)
    # widen the CIs by the start field's error that earlier windows' H left in the live state (model.carry);
    # false: noise-only CIs, which undercover at chained conditions (docs/design/service.md)
    carry_start_error: bool = CARRY_START_ERROR
    distance_scales: tuple[float, float, float] = (1000.0, 5.0, 5.0)  # rpm, N·m, °C: warm-start "nearness"
    map_family: Literal["nodes", "physics"] = "nodes"  # model.hmap: tabulated over speed nodes, or physics
    # a cold start waits for this much data (7 served 3 min sooner a first map whose bands missed H6/H7 from a
    # cold start: docs/design/hmap.md "Measured: restart"); <= identification.map_window_min
    map_min_window_min: float = Field(default=10.0, gt=0)
    # after a confirmed change, wait this long (<= identification.map_fresh_min)
    map_debounce_s: float = Field(default=30.0, ge=0)
    # a speed this close to a visited one is covered (500: half the node spacing of the "nodes" family, so
    # it shares a node with the visited speed)
    map_margin_rpm: float = Field(default=500.0, ge=0)
    map_min_visit_s: float = Field(default=60.0, ge=0)  # seconds of data at a speed before it is visited
    map_forget_tau_h: float = Field(default=4.0, gt=0)  # forgetting time of the map's information
    # covariance intersection ω of a fit's chained prior and its start field, which share earlier data:
    # prior covariance / ω, start covariance / (1 − ω); 1: treated as independent (docs/design/hmap.md)
    map_prior_weight: float = Field(default=0.25, gt=0, le=1)
    # σ of the cold prior's overall ln H level per zone, around the physics curves (docs/design/hmap.md)
    map_prior_level_sd: float = Field(default=0.0, ge=0)
    # 30 biased H by 10-26 %, 46 0.04 °C off (issue 15, docs/design/rom.md)
    rom_rank: int = Field(default=56, ge=1)
    mesh_size_m: float | None = Field(default=None, gt=0)  # None → model.fem default service mesh

    @field_validator("distance_scales")
    @classmethod
    def _scales_positive(cls, value: tuple[float, float, float]) -> tuple[float, float, float]:
        if any(v <= 0 for v in value):
            raise ValueError(f"need 3 positive scales (rpm, N·m, °C), got {list(value)}")
        return value


class Moved(NamedTuple):
    """Where a key went (``section``) and when and why (``why``, for the error message)."""

    section: str
    why: str


_RESEARCH = "in issue 25 (a research switch; docs/configuration.md)"
_FROM_MODEL = ("rom_rank", "mesh_size_m")
# keys that left a section: an old file or CHTC_* variable setting one gets an error saying where the key
# went, or why it is gone, instead of a bare "unknown key"
MOVED_KEYS: dict[tuple[str, str], Moved] = {
    **{
        ("model" if k in _FROM_MODEL else "identification", k): Moved("experimental", _RESEARCH)
        for k in ExperimentalSettings.model_fields
    },
    ("experimental", "mode"): Moved(
        "identification", "in issue 39 (the product's identification mode, an operator's setting)"
    ),
    ("growth", "reference_c"): Moved("compensation", "in issue 39 ([growth] folded into [compensation])"),
}
REMOVED_KEYS: dict[tuple[str, str], str] = {
    ("identification", k): "removed in issue 25: measured without effect "
    '(docs/design/hmap.md "Making the bands honest")'
    for k in ("map_start_draws", "map_start_lead_min", "map_live_h_error")
}


def check_across_sections(settings: Settings) -> None:
    """The rules that tie an ``[experimental]`` key to an ``[identification]`` one; ``ValueError`` naming
    both keys (``Settings`` runs it when validated, ``service.commands._common.override`` after a change)."""
    ident, exp = settings.identification, settings.experimental
    if exp.map_min_window_min > ident.map_window_min:
        raise ValueError(
            f"experimental.map_min_window_min ({exp.map_min_window_min}) must be <= "
            f"identification.map_window_min ({ident.map_window_min})"
        )
    if ident.map_fresh_min * 60.0 < exp.map_debounce_s:
        raise ValueError(
            f"identification.map_fresh_min ({ident.map_fresh_min} min) must be >= "
            f"experimental.map_debounce_s ({exp.map_debounce_s} s)"
        )


class DetectorSettings(_Section):
    """A new operating condition: a quantity moves this far from the current one and stays there hold_s."""

    speed_threshold_rpm: float = Field(default=150.0, gt=0)
    torque_threshold_nm: float = Field(default=1.0, gt=0)
    ambient_threshold_c: float = Field(default=1.0, gt=0)
    hold_s: float = Field(default=60.0, gt=0)
    median_samples: int = Field(default=3, ge=1)  # median filter length against isolated outliers
    max_gap_s: float = Field(default=120.0, gt=0)  # a longer gap inside a hold period restarts it


MIN_TOKEN_CHARS = 16
PLACEHOLDER_TOKENS = ("change-me", "changeme", "replace-me", "your-token", "example")


class CompensationSettings(_Section):
    """The thermal growth at the tool (``/compensation``, docs/design/growth.md): its configured zero and when
    a controller may apply it (``usable_for_compensation``; the policy, ``service.serve.policy``;
    docs/design/policy.md says how the defaults were chosen)."""

    # the uniform temperature [°C] at which the growth is 0 (where the controller's compensation was zeroed),
    # used when no zero is stored (a stored one, POST /api/v1/compensation/reference, wins); None: none.
    # In [growth] until issue 39
    reference_c: float | None = Field(default=None, ge=-50.0, le=200.0, allow_inf_nan=False)
    # the growth's 95 % CI half-width the controller tolerates [µm]: wider is never usable
    max_ci95_um: float = Field(default=2.0, gt=0.0, le=1000.0, allow_inf_nan=False)
    # the H in use (the identification or map fit) may be at most this old [min]
    max_identification_age_min: float = Field(default=1440.0, gt=0.0, allow_inf_nan=False)
    # DAQ down while CAN speed/torque keep coming: the growth is predicted open loop (status "predicted")
    # and stays usable at most this long [min] (and only while its CI is within max_ci95_um); 0: never
    max_open_loop_min: float = Field(default=10.0, ge=0.0, le=1440.0, allow_inf_nan=False)
    # with no stored compensation zero (and no reference_c), take one from the first sample at rest in
    # equilibrium and store it (source "first_start"); false: /compensation stays not usable (no_reference)
    # until one is set (POST /api/v1/compensation/reference or chtc commission zero). Only right if the
    # spindle rests in equilibrium when the service first starts and the controller was zeroed then.
    reference_on_first_start: bool = False
    # /compensation is not usable (reason mechanics_uncalibrated) until the growth's mechanics are
    # commissioned
    # from a measured thermal test (chtc commission growth): with the mount restraint and α unknown the served
    # CI covered the truth 4 % of the time (docs/design/policy.md); false only for a machine whose mechanics
    # match the spindle description (the simulator's plant)
    require_mechanics_calibration: bool = True
    # /compensation is not usable (reason no_offset_baseline) while sensor calibration is on and has no
    # baseline yet: after a start on a warm spindle with no stored calibration the unknown offsets
    # (±0.2 °C) biased the growth by up to −2 µm with a CI that missed it (issue 40; docs/design/policy.md);
    # the baseline is taken at the next rest in equilibrium or on request (POST /api/v1/sensors/baseline);
    # until then the stored commissioning's (its thermal test's rest) counts, when it fits the sensors
    require_offset_baseline: bool = True
    # a probe reading (POST /api/v1/compensation/measurements) further than this many σ of its prediction (the
    # served growth's CI with the probe's own sd) is flagged and not absorbed (a crash or a tool change)
    probe_gate_sigma: float = Field(default=3.0, gt=0.0, le=100.0, allow_inf_nan=False)
    # probe readings also estimate a fixture or tool-holder offset b (service.estimate.probe; issue 40): its
    # prior 1σ at the commissioning and after a step (two consecutive gated readings that agree) [µm] ...
    probe_offset_sd_um: float = Field(default=5.0, gt=0.0, le=1000.0, allow_inf_nan=False)
    # ... a step of it is taken when two readings in a row lie beyond this many σ of their prediction, on the
    # same side and consistent (a single outlier beyond probe_gate_sigma is never a step) ...
    probe_step_sigma: float = Field(default=2.0, gt=0.0, le=100.0, allow_inf_nan=False)
    # ... and its random walk between readings [µm²/h] (a slow drift; a step is found by the gate)
    probe_offset_q_um2_per_h: float = Field(default=0.05, ge=0.0, le=1000.0, allow_inf_nan=False)
    # the CI part of the verdict has hysteresis (service.serve.cigate; docs/design/policy.md, "A steady
    # verdict"): usable again only when the 95 % CI half-width is at most this fraction of max_ci95_um ...
    ci_enter_fraction: float = Field(default=0.8, gt=0.0, le=1.0, allow_inf_nan=False)
    # ... and not usable once it has stayed above max_ci95_um this long [s] ...
    ci_exit_hold_s: float = Field(default=300.0, ge=0.0, le=86400.0, allow_inf_nan=False)
    # ... or at once above this multiple of max_ci95_um (or not a number)
    ci_hard_fraction: float = Field(default=1.5, ge=1.0, le=10.0, allow_inf_nan=False)


class ControllerSettings(_Section):
    """The command value served for the controller (``/compensation`` ``command``; service.serve.command;
    docs/design/policy.md, "The command value"): how far it may move per update and per second, its absolute
    limit (the profile's unless overridden), and how long it holds the last applied value when the verdict
    drops."""

    # sinumerik, fanuc, heidenhain or generic: the largest step, rate and magnitude the controller accepts
    profile: Literal["generic", "sinumerik", "fanuc", "heidenhain"] = "generic"
    max_step_um: float | None = Field(default=None, gt=0.0, le=10000.0, allow_inf_nan=False)  # per update
    max_rate_um_s: float | None = Field(default=None, gt=0.0, le=10000.0, allow_inf_nan=False)
    limit_um: float | None = Field(default=None, gt=0.0, le=100000.0, allow_inf_nan=False)  # |command|
    # after the verdict drops, the last applied value is held this long [s] before it moves towards the best
    # estimate the service still has
    hold_s: float = Field(default=300.0, ge=0.0, le=86400.0, allow_inf_nan=False)


def check_token(text: str) -> str:
    """A bearer token without surrounding whitespace (a secret file's trailing newline); refuses one that is
    short or a placeholder, naming why but never the token."""
    token = text.strip()
    if len(token) < MIN_TOKEN_CHARS:
        raise ValueError(
            f"too short ({len(token)} characters): use at least {MIN_TOKEN_CHARS} random characters, "
            "e.g. `openssl rand -hex 32`"
        )
    if any(p in token.lower() for p in PLACEHOLDER_TOKENS):
        raise ValueError(
            "still the placeholder from the example: set a random token, e.g. `openssl rand -hex 32`"
        )
    return token


class ApiSettings(_Section):
    host: str = "127.0.0.1"
    port: int = Field(default=8000, ge=1, le=65535)
    token: SecretStr | None = None  # bearer token for writes; None → every write is refused (403)
    read_token: SecretStr | None = None  # None → reads are open

    @field_validator("token", "read_token", mode="before")
    @classmethod
    def _empty_is_unset(cls, value: object) -> object:
        return None if isinstance(value, str) and not value.strip() else value

    @field_validator("token", "read_token")
    @classmethod
    def _strong_token(cls, value: SecretStr | None) -> SecretStr | None:
        return None if value is None else SecretStr(check_token(value.get_secret_value()))


OpcUaPolicy = Literal["None", "Basic256Sha256_SignAndEncrypt"]


class OpcUaSettings(_Section):
    """The OPC UA server, an outlet beside the REST API (``service.serve.opcua``; docs/integration.md): off by
    default; anonymous read-only on loopback unless configured otherwise."""

    enabled: bool = False
    host: str = "127.0.0.1"
    port: int = Field(default=4840, ge=1, le=65535)
    path: str = "/chtc"  # endpoint opc.tcp://host:port/path
    # the NodeId prefix (ns=<idx>;s=<spindle>.H.H1) and the object's name; None: the spindle's id (spindle.id)
    spindle: str | None = Field(default=None, pattern=SPINDLE_ID_PATTERN)
    namespace_uri: str = "urn:spindle-chtc:opcua"
    # the endpoints offered: "None" (no security) and/or "Basic256Sha256_SignAndEncrypt"
    security_policies: tuple[OpcUaPolicy, ...] = ("None",)
    certificate: Path | None = None  # the server's certificate (DER or PEM); needed for Sign&Encrypt
    private_key: Path | None = None  # its private key (PEM)
    trust_dir: Path | None = None  # trusted client certificates (*.der, *.pem); any other is refused
    anonymous: bool = True  # anonymous sessions (read-only); false: user/password only
    users: dict[str, SecretStr] = Field(default_factory=dict)  # name -> pbkdf2_sha256 hash (chtc opcua user)
    users_file: Path | None = None  # TOML [users] name = "hash", merged over ``users``
    max_connections: int = Field(default=10, ge=1, le=1000)
    methods: bool = False  # StartIdentification and TakeSensorBaseline (authenticated users only)
    update_interval_s: float = Field(default=0.2, gt=0, le=60)  # at most one address-space update per this
    refresh_s: float = Field(default=1.0, gt=0, le=60)  # re-evaluate ages and statuses without a new view
    bad_after_s: float | None = Field(default=None, gt=0)  # lost data: Bad past this; None: max_open_loop_min

    def for_spindle(self, spindle_id: str) -> OpcUaSettings:
        """This section with ``spindle`` set: as given, else ``spindle_id`` (this instance's spindle.id)."""
        return self if self.spindle is not None else self.model_copy(update={"spindle": spindle_id})

    @property
    def node_prefix(self) -> str:
        """The NodeId prefix; ``ValueError`` before :meth:`for_spindle` resolved a default one."""
        if self.spindle is None:
            raise ValueError("opcua.spindle: unset; resolve it with for_spindle(spindle.id)")
        return self.spindle

    @model_validator(mode="after")
    def _security_complete(self) -> OpcUaSettings:
        if not self.security_policies:
            raise ValueError("security_policies: at least one policy")
        if "Basic256Sha256_SignAndEncrypt" in self.security_policies:
            missing = [k for k in ("certificate", "private_key", "trust_dir") if getattr(self, k) is None]
            if missing:
                raise ValueError(f"Basic256Sha256_SignAndEncrypt needs {', '.join(missing)}")
        if not self.path.startswith("/"):
            raise ValueError(f"path: must start with '/', got {self.path!r}")
        return self


class EngineSettings(_Section):
    """Where the core's per-sample work runs and when the service says it falls behind
    (docs/design/threading.md)."""

    core_thread: bool = True  # the core in its own thread (False: on the event loop, as before issue 30)
    core_queue_samples: int = Field(default=1000, ge=1)  # samples waiting for the core (more: dropped)
    max_core_lag_s: float = Field(default=30.0, gt=0)  # a sample waiting longer: served values core_behind
    max_loop_lag_s: float = Field(default=0.25, gt=0)  # event-loop lag past this: /healthz degraded
    loop_lag_window_s: float = Field(default=30.0, gt=0)  # ... judged on the largest of this window
    # CPython's GIL switch interval in the service process (sys.setswitchinterval; Python's default 5 ms):
    # how long the event loop may wait for the GIL while the core or the growth terms compute
    gil_switch_interval_s: float = Field(default=0.001, gt=0, le=0.1)
    # identification processes shared by the spindles of an instance with [[spindles]] (None: one per core)
    identification_workers: int | None = Field(default=None, ge=1, le=256)


class DatabaseSettings(_Section):
    url: str = Field(default_factory=default_database_url)  # sqlite:///… or postgresql+psycopg://…
    sample_store_period_s: float = Field(default=10.0, gt=0)  # store at most one Sample per period
    # store the live state (one row, replaced; ~70 kB) this often [s of sample time]: a restart within the
    # filter's 300-s gap resumes from it instead of its prior (service.estimate.checkpoint); 0: never
    live_checkpoint_s: float = Field(default=60.0, ge=0)
    batch_size: int = Field(default=500, ge=1)
    retry_initial_s: float = Field(default=0.5, gt=0)
    retry_max_s: float = Field(default=30.0, gt=0)
    buffer_max: int = Field(
        default=100_000, ge=1
    )  # records held while the DB is down; beyond: dropped, counted
    echo: bool = False
    connect_timeout_s: float = Field(default=5.0, gt=0)  # PostgreSQL connect_timeout (whole seconds, >= 1)
    statement_timeout_s: float = Field(default=5.0, gt=0)  # server-side; the client aborts 1 s later
    heartbeat_s: float = Field(default=2.0, gt=0)  # an idle writer probes (SELECT 1) this often
    stall_s: float = Field(default=3.0, gt=0)  # a write/probe waiting longer: health says db "degraded"
    read_timeout_s: float = Field(default=2.0, gt=0)  # API reads of the database: 503 after this
    read_threads: int = Field(default=4, ge=1)  # at most this many API reads wait on the database
    # PostgreSQL connection pool of each engine (the writer's, the API reads'): its size and how many more
    # connections it may open at a peak (docs/deployment.md, "Connections")
    pool_size: int = Field(default=5, ge=1)
    max_overflow: int = Field(default=10, ge=0)
    # the server is reached through a pooler in transaction mode (PgBouncer pool_mode = transaction): no
    # prepared statements (psycopg prepare_threshold=None); the statement timeout is SET LOCAL either way
    transaction_pooling: bool = False
    # retention (service.store.retention): raw samples are kept this many days (by sample time), then only
    # their 1-minute means, kept ``minute_days``; then dropped. Identifications and calibrations are kept.
    # 0 days: keep for ever. The pass runs every ``retention_every_s`` (and ``chtc db retention``).
    raw_days: int = Field(default=30, ge=0)
    minute_days: int = Field(default=365, ge=0)
    retention_every_s: float = Field(default=86_400.0, gt=0)

    @field_validator("url")
    @classmethod
    def _url_parses(cls, value: str) -> str:
        from sqlalchemy.engine import make_url
        from sqlalchemy.exc import ArgumentError

        try:
            make_url(value)
        except ArgumentError as err:
            raise ValueError(f"not a database URL: {value!r}") from err
        return value

    @model_validator(mode="after")
    def _retry_order(self) -> DatabaseSettings:
        if self.retry_max_s < self.retry_initial_s:
            raise ValueError("retry_max_s must be >= retry_initial_s")
        return self

    @model_validator(mode="after")
    def _retention_order(self) -> DatabaseSettings:
        if self.raw_days > 0 and 0 < self.minute_days < self.raw_days:
            raise ValueError(
                "minute_days must be >= raw_days (or 0: for ever): the means outlive the samples"
            )
        return self


_TOML_DATA: ContextVar[dict[str, object] | None] = ContextVar("_chtc_toml_data", default=None)


class Settings(BaseSettings):
    """All settings; see the module docstring for sources and precedence."""

    model_config = SettingsConfigDict(
        env_prefix="CHTC_",
        env_nested_delimiter="__",
        extra="forbid",
        frozen=True,
        hide_input_in_errors=True,  # a raw ValidationError must not echo a token
    )

    spindle: SpindleSettings = Field(default_factory=SpindleSettings)
    modbus: ModbusSettings = Field(default_factory=ModbusSettings)
    can: CanSettings = Field(default_factory=CanSettings)
    acquisition: AcquisitionSettings = Field(default_factory=AcquisitionSettings)
    model: ModelSettings = Field(default_factory=ModelSettings)
    identification: IdentificationSettings = Field(default_factory=IdentificationSettings)
    detector: DetectorSettings = Field(default_factory=DetectorSettings)
    api: ApiSettings = Field(default_factory=ApiSettings)
    database: DatabaseSettings = Field(default_factory=DatabaseSettings)
    compensation: CompensationSettings = Field(default_factory=CompensationSettings)
    controller: ControllerSettings = Field(default_factory=ControllerSettings)
    experimental: ExperimentalSettings = Field(default_factory=ExperimentalSettings)
    engine: EngineSettings = Field(default_factory=EngineSettings)
    opcua: OpcUaSettings = Field(default_factory=OpcUaSettings)
    mqtt: MqttSettings = Field(default_factory=MqttSettings)  # the MQTT outlet (off by default)
    # several spindles in this one instance; empty: one, described by [spindle], [modbus] and [can]
    spindles: list[SpindleEntry] = Field(default_factory=list, max_length=1000)

    @model_validator(mode="after")
    def _across_sections(self) -> Settings:
        check_across_sections(self)
        self.per_spindle()  # every entry merged and validated here, so a bad one names its key at load
        return self

    def per_spindle(self) -> list[Settings]:
        """One ``Settings`` per hosted spindle: ``[[spindles]]`` merged over the top-level sections (and
        ``spindles`` emptied), or ``[self]`` without entries. ``ValueError`` names the entry's key."""
        if not self.spindles:
            return [self]
        out: list[Settings] = []
        seen: dict[str, str] = {}
        for i, entry in enumerate(self.spindles):
            where = f"spindles[{i}]"
            if entry.id in seen:
                raise ValueError(f"{where}.id: {entry.id!r} is also {seen[entry.id]}.id; ids must be unique")
            seen[entry.id] = where
            modbus = _merged(ModbusSettings, self.modbus, entry.modbus, f"{where}.modbus")
            can = _merged(CanSettings, self.can, entry.can, f"{where}.can")
            other = sorted(set(entry.mqtt) - SPINDLE_MQTT_KEYS)
            if other:
                raise ValueError(
                    f"{where}.mqtt.{other[0]}: not per spindle (the host's one MQTT connection has it; "
                    f"per spindle: {', '.join(sorted(SPINDLE_MQTT_KEYS))})"
                )
            mqtt = _merged(MqttSettings, self.mqtt, entry.mqtt, f"{where}.mqtt")
            model = (
                self.model
                if entry.geometry is None
                else self.model.model_copy(update={"spindle": entry.geometry})
            )
            spindle = SpindleSettings(id=entry.id, description=entry.description)
            out.append(
                self.model_copy(
                    update={
                        "spindle": spindle,
                        "modbus": modbus,
                        "can": can,
                        "mqtt": mqtt,
                        "model": model,
                        "spindles": [],
                    }
                )
            )
        _check_unique(out, lambda s: f"{s.modbus.host}:{s.modbus.port}/unit {s.modbus.unit}", "modbus")
        _check_unique(out, lambda s: f"{s.can.interface}:{s.can.channel}", "can")
        if self.mqtt.enabled:
            _check_unique(out, lambda s: s.mqtt.for_spindle(s.spindle.id).device, "mqtt", what="device id")
        return out

    @classmethod
    def settings_customise_sources(
        cls,
        settings_cls: type[BaseSettings],
        init_settings: PydanticBaseSettingsSource,
        env_settings: PydanticBaseSettingsSource,
        dotenv_settings: PydanticBaseSettingsSource,
        file_secret_settings: PydanticBaseSettingsSource,
    ) -> tuple[PydanticBaseSettingsSource, ...]:
        toml = InitSettingsSource(settings_cls, init_kwargs=dict(_TOML_DATA.get() or {}))
        return (init_settings, env_settings, _GoneSectionsEnv(settings_cls), toml)

    @classmethod
    def from_toml(cls, path: str | Path | None, **overrides: Any) -> Settings:  # raw input for pydantic
        """Settings from a TOML file (``None``: none) under the environment; raises ``SettingsError``."""
        data = _resolve_paths(read_toml(path), Path(path).parent) if path is not None else {}
        token = _TOML_DATA.set(data)
        try:
            return cls(**overrides)
        except ValidationError as err:
            raise SettingsError(format_validation_error(err, source=path)) from err
        finally:
            _TOML_DATA.reset(token)

    def redacted(self) -> dict[str, Any]:
        """Plain dict for logs and ``--print-config``: tokens masked, database password hidden."""
        from sqlalchemy.engine import make_url

        data = self.model_dump(mode="json")
        for key in ("token", "read_token"):
            if data["api"][key] is not None:
                data["api"][key] = "**********"
        data["opcua"]["users"] = {name: "**********" for name in data["opcua"]["users"]}
        data["database"]["url"] = make_url(self.database.url).render_as_string(hide_password=True)
        return data


class _GoneSectionsEnv(PydanticBaseSettingsSource):
    """``CHTC_<SECTION>__<KEY>`` of a section that no longer exists (``[growth]``): pydantic-settings reads
    only declared sections and would ignore it silently; handed on, it fails as the file's key would, with
    the "moved to" message."""

    def get_field_value(self, field: Any, field_name: str) -> tuple[Any, str, bool]:  # abstract in the base
        return None, field_name, False

    def __call__(self) -> dict[str, Any]:
        gone = {section for section, _ in MOVED_KEYS} - set(Settings.model_fields)
        out: dict[str, Any] = {}
        for name, value in os.environ.items():
            section, sep, key = name.upper().removeprefix("CHTC_").partition("__")
            if name.upper().startswith("CHTC_") and sep and section.lower() in gone:
                out.setdefault(section.lower(), {})[key.lower()] = value
        return out


_S = TypeVar("_S", bound=BaseModel)


def _merged(cls: type[_S], base: _S, changes: dict[str, Any], where: str) -> _S:  # raw input for pydantic
    """``base`` with ``changes`` merged over it, validated; ``ValueError`` names ``where.<key>``."""
    try:
        return cls.model_validate({**base.model_dump(), **changes})
    except ValidationError as err:
        first = err.errors()[0]
        key = ".".join(str(p) for p in first["loc"])
        raise ValueError(f"{where}.{key}: {first['msg']}") from None


def _check_unique(
    spindles: list[Settings], key: Callable[[Settings], str], section: str, *, what: str = "device"
) -> None:
    """Two hosted spindles on one device address would read each other's data (or publish as one MQTT
    device): refused, naming both."""
    seen: dict[str, str] = {}
    for s in spindles:
        k = key(s)
        if k in seen:
            raise ValueError(f"spindles: {seen[k]} and {s.spindle.id} share the {section} {what} {k}")
        seen[k] = s.spindle.id


def load_settings(path: str | Path | None = None, **overrides: Any) -> Settings:  # raw input
    """The edge entry point: ``Settings.from_toml(path)``; every failure is a ``SettingsError``."""
    return Settings.from_toml(path, **overrides)


def read_toml(path: str | Path) -> dict[str, object]:
    """Parse a TOML config file; ``SettingsError`` names the file (and line for syntax errors)."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as err:
        raise SettingsError(f"{path}: cannot read config file: {err.strerror or err}") from err
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise SettingsError(f"{path}: invalid TOML: {err}") from err


_PATH_KEYS: tuple[tuple[str, ...], ...] = (
    ("modbus", "register_map"),
    ("can", "dbc"),
    ("model", "spindle"),
    ("model", "rom_cache_dir"),
    ("opcua", "certificate"),
    ("opcua", "private_key"),
    ("opcua", "trust_dir"),
    ("opcua", "users_file"),
    ("mqtt", "state_dir"),
    ("mqtt", "tls", "ca"),
    ("mqtt", "tls", "cert"),
    ("mqtt", "tls", "key"),
)


_SPINDLE_PATH_KEYS: tuple[tuple[str, ...], ...] = (("geometry",), ("modbus", "register_map"), ("can", "dbc"))


def _resolve_paths(data: dict[str, object], base: Path) -> dict[str, object]:
    """Relative file paths in a config file are relative to that file's directory (``~`` is expanded)."""
    entries = data.get("spindles")
    for entry in entries if isinstance(entries, list) else ():
        if isinstance(entry, dict):
            _resolve_keys(entry, base, _SPINDLE_PATH_KEYS)
    return _resolve_keys(data, base, _PATH_KEYS)


def _resolve_keys(
    data: dict[str, object], base: Path, keys: tuple[tuple[str, ...], ...]
) -> dict[str, object]:
    for *sections, key in keys:
        block: object = data
        for section in sections:
            block = block.get(section) if isinstance(block, dict) else None
        if isinstance(block, dict) and isinstance(block.get(key), str):
            value = Path(block[key]).expanduser()
            block[key] = str(value if value.is_absolute() else base / value)
    return data


def format_validation_error(err: ValidationError, *, source: str | Path | None = None) -> str:
    """One line per problem, each starting with the dotted key, e.g. ``modbus.port: Input should be ...``."""
    lines = []
    for item in err.errors(include_url=False):
        key = ".".join(str(p) for p in item["loc"]) or "<root>"
        msg = item["msg"]
        if item["type"] == "extra_forbidden":
            msg = _gone(item["loc"], item.get("input"))
        if not item["loc"] and item["type"] == "value_error":
            msg = msg.removeprefix("Value error, ")  # a rule across sections: its message names the keys
        given = item.get("input")
        secret = any("token" in str(p) for p in item["loc"]) or item["type"] == "value_error"
        shown = "" if secret or isinstance(given, dict | SecretStr) or given is None else f" (got {given!r})"
        lines.append(msg if not item["loc"] else f"{key}: {msg}{shown}")
    where = f" in {source}" if source is not None else ""
    return f"invalid settings{where} (env CHTC_<SECTION>__<KEY> overrides the file):\n  " + "\n  ".join(lines)


def _gone(loc: tuple[int | str, ...], given: object = None) -> str:
    """Why ``loc`` is not a key: moved to another section, removed, or unknown. A section that is gone
    (``loc`` its name alone, ``given`` its keys) names where each of its keys went."""
    if len(loc) == 1 and isinstance(given, dict):
        section = str(loc[0])
        targets = sorted({to.section for (old, _), to in MOVED_KEYS.items() if old == section})
        if targets and section not in Settings.model_fields:
            keys = [
                f"{section}.{k} {_moved(section, str(k))}"
                if (section, str(k)) in MOVED_KEYS
                else f"{section}.{k}: unknown key"
                for k in given
            ]
            return (
                f"the section [{section}] is gone (its keys moved to [{'], ['.join(targets)}]): "
                + "; ".join(keys)
            )
    where = (str(loc[0]), str(loc[-1])) if len(loc) == 2 else None
    if where in MOVED_KEYS:
        return _moved(*where)
    if where in REMOVED_KEYS:
        return f"{REMOVED_KEYS[where]}; delete the line"
    return "unknown key"


def _moved(old_section: str, key: str) -> str:
    to = MOVED_KEYS[(old_section, key)]
    return (
        f"moved to [{to.section}] {to.why}: write it as {to.section}.{key} "
        f"(env CHTC_{to.section.upper()}__{key.upper()}), or delete the line to keep the default"
    )
