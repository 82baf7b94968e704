"""SQLAlchemy 2.0 typed declarative models (the schema of migrations ``0001_initial`` to ``0009``).

Since ``0007`` every table but ``spindles`` carries ``spindle_id`` (``SpindleScoped``): many spindles share
one database. Service-assigned ids (conditions, identifications) are unique per spindle (composite keys
``(spindle_id, id)``); database-assigned ids are BIGINT and unique over the database. Samples are keyed by
``(spindle_id, t)`` (a retried batch is ``ON CONFLICT DO NOTHING``), and on PostgreSQL the table is
partitioned by day on ``t`` (``service.store.partitions``). Sessions from
``service.store.engine.make_session_factory(engine, spindle_id=...)`` see one spindle's rows only.

Tables: ``conditions``, ``identifications``, ``device_events``, ``samples``, (migration ``0002``)
``offset_calibrations``, (``0003``) ``compensation_references``, (``0004``) ``live_state`` and (``0005``)
``mechanics_calibrations``. Every
timestamp is :class:`~service.store.types.UtcDateTime` (aware UTC in and out, on SQLite too).
Units: °C, rpm, N·m, W/(m²·K), s.

Ids of conditions and identifications are assigned by the service (it needs them before the row is stored,
because the writer may hold rows while the database is down); device events and samples get database ids.

Per-channel sample temperatures are one array per row rather than 32 columns: the number of channels is
configuration (the spindle file), so a different DAQ needs no migration, and the array is always read whole.
The cost is that one channel cannot be indexed in SQL; nobody needs that. Since ``0008`` the samples are
compact on PostgreSQL (``service.store.types``): temperatures ``smallint[]`` of centi-degrees, speed, torque
and ambient ``real``, the bad channels' qualities ``bytea``, columns ordered for alignment
(docs/design/persistence.md, "Storage per spindle-day").
H1–H7 of an identification are seven columns because they are what trend queries read.
"""

from __future__ import annotations

from datetime import datetime

from sqlalchemy import (
    JSON,
    BigInteger,
    Boolean,
    Double,
    ForeignKey,
    ForeignKeyConstraint,
    Index,
    Integer,
    LargeBinary,
    MetaData,
    PrimaryKeyConstraint,
    SmallInteger,
    String,
    Text,
    false,
)
from sqlalchemy.orm import DeclarativeBase, Mapped, declared_attr, mapped_column, relationship

from service.contracts.columns import JsonValue
from service.store.types import Float32, QualityMap, TemperatureArray, UtcDateTime

# BIGINT everywhere; on SQLite an INTEGER PRIMARY KEY (the 64-bit rowid) so database ids autoincrement there
BigId = BigInteger().with_variant(Integer(), "sqlite")
SmallInt = SmallInteger().with_variant(Integer(), "sqlite")  # SQLite: INTEGER as before 0008
SPINDLE_ID_LENGTH = 64

NAMING = {
    "ix": "ix_%(table_name)s_%(column_0_N_name)s",
    "uq": "uq_%(table_name)s_%(column_0_N_name)s",
    "ck": "ck_%(table_name)s_%(constraint_name)s",
    "fk": "fk_%(table_name)s_%(column_0_name)s_%(referred_table_name)s",
    "pk": "pk_%(table_name)s",
}


class Base(DeclarativeBase):
    metadata = MetaData(naming_convention=NAMING)
    type_annotation_map = {datetime: UtcDateTime, float: Double}  # noqa: RUF012


class Spindle(Base):
    """A spindle known to the database (``[spindle] id``); registered by the service at start-up."""

    __tablename__ = "spindles"

    id: Mapped[str] = mapped_column(String(SPINDLE_ID_LENGTH), primary_key=True)
    description: Mapped[str] = mapped_column(Text, default="")
    created_at: Mapped[datetime]


class SpindleScoped:
    """A table whose rows belong to one spindle: ``spindle_id`` (→ ``spindles``), filtered in every query."""

    @declared_attr
    def spindle_id(cls) -> Mapped[str]:
        return mapped_column(String(SPINDLE_ID_LENGTH), ForeignKey("spindles.id"))


class Condition(SpindleScoped, Base):
    """An operating condition (speed, torque, ambient) from its start until the next one starts."""

    __tablename__ = "conditions"
    __table_args__ = (PrimaryKeyConstraint("spindle_id", "id"), Index(None, "spindle_id", "started_at"))

    id: Mapped[int] = mapped_column(BigInteger, autoincrement=False)
    started_at: Mapped[datetime]
    ended_at: Mapped[datetime | None]
    speed_rpm: Mapped[float]
    torque_nm: Mapped[float]
    ambient_c: Mapped[float]

    identifications: Mapped[list[Identification]] = relationship(
        back_populates="condition", passive_deletes=True
    )


class Identification(SpindleScoped, Base):
    """One identification of H1–H7 (also the failed, skipped and cancelled ones, with their message)."""

    __tablename__ = "identifications"
    __table_args__ = (
        PrimaryKeyConstraint("spindle_id", "id"),
        ForeignKeyConstraint(
            ["spindle_id", "condition_id"], ["conditions.spindle_id", "conditions.id"], ondelete="CASCADE"
        ),
        Index(None, "spindle_id", "finished_at"),
        Index(None, "spindle_id", "condition_id"),
    )

    id: Mapped[int] = mapped_column(BigInteger, autoincrement=False)
    condition_id: Mapped[int] = mapped_column(BigInteger)
    started_at: Mapped[datetime]
    finished_at: Mapped[datetime]
    window_start: Mapped[datetime]
    window_end: Mapped[datetime]
    reason: Mapped[str] = mapped_column(String(32))  # trigger: "schedule", "manual", ...
    outcome: Mapped[str] = mapped_column(String(32))  # a service.contracts.outcome.Outcome value
    message: Mapped[str] = mapped_column(Text, default="")
    method: Mapped[str] = mapped_column(String(32))
    model_version: Mapped[str] = mapped_column(String(128))
    h1: Mapped[float | None]  # W/(m²·K); NULL when not identified (failed, skipped)
    h2: Mapped[float | None]
    h3: Mapped[float | None]
    h4: Mapped[float | None]
    h5: Mapped[float | None]
    h6: Mapped[float | None]
    h7: Mapped[float | None]
    ci95_lo: Mapped[list[float | None] | None] = mapped_column(JSON)  # 7, W/(m²·K)
    ci95_hi: Mapped[list[float | None] | None] = mapped_column(JSON)
    identified: Mapped[list[bool] | None] = mapped_column(JSON)  # 7; False: practically unidentifiable
    load_scale_front: Mapped[float | None]  # fitted bearing heat scales (estimate_loads), 1 = nominal
    load_scale_rear: Mapped[float | None]
    f: Mapped[float | None]  # objective, mean squared residual, °C²
    fit: Mapped[float | None]  # 1 / (1 + f)
    rmse_c: Mapped[float | None]  # °C
    nfev: Mapped[int] = mapped_column(Integer, default=0)
    duration_s: Mapped[float]  # wall time, s
    n_sensors_used: Mapped[int] = mapped_column(Integer, default=0)
    warm_start_source: Mapped[str | None] = mapped_column(
        String(64)
    )  # "this condition", "condition 7", "none"
    warm_start_id: Mapped[int | None] = mapped_column(BigInteger)  # soft reference: no FK, may be gone
    diagnostics: Mapped[dict[str, JsonValue] | None] = mapped_column(
        JSON
    )  # free-form: test-point errors, per-sensor RMSE, ...

    condition: Mapped[Condition] = relationship(back_populates="identifications")

    @property
    def h(self) -> tuple[float | None, ...]:
        """H1..H7, W/(m²·K) (None where not identified)."""
        return (self.h1, self.h2, self.h3, self.h4, self.h5, self.h6, self.h7)


class DeviceEvent(SpindleScoped, Base):
    """Something a device (or the database, or the worker) did: connected, lost, fault frame, restarted."""

    __tablename__ = "device_events"
    __table_args__ = (Index(None, "spindle_id", "t"),)

    id: Mapped[int] = mapped_column(BigId, primary_key=True)
    t: Mapped[datetime]
    device: Mapped[str] = mapped_column(String(16))  # "modbus" | "can" | "db" | "worker" | ...
    kind: Mapped[str] = mapped_column(String(64))  # "connected", "timeout", "fault-status", ...
    detail: Mapped[str] = mapped_column(Text, default="")


class SampleRow(SpindleScoped, Base):
    """One stored acquisition instant (the service stores one per ``database.sample_store_period_s``).

    Key ``(spindle_id, t)``: a retried batch is ``ON CONFLICT DO NOTHING``. On PostgreSQL the table is
    partitioned by day on ``t`` (``service.store.partitions``; the retention pass drops whole days)."""

    __tablename__ = "samples"
    __table_args__ = (PrimaryKeyConstraint("spindle_id", "t"), {"postgresql_partition_by": "RANGE (t)"})

    # Column order is the PostgreSQL row layout (revision 0008): fixed widths by alignment, then the varlenas
    t: Mapped[datetime]
    speed_rpm: Mapped[float | None] = mapped_column(Float32)  # PostgreSQL: real (float32)
    torque_nm: Mapped[float | None] = mapped_column(Float32)
    ambient_c: Mapped[float | None] = mapped_column(Float32)
    n_good: Mapped[int] = mapped_column(SmallInt)  # channels with quality "ok"
    can_ok: Mapped[bool] = mapped_column(Boolean)
    daq_ok: Mapped[bool] = mapped_column(Boolean)
    # per channel, °C to 0.01 °C; null = no usable value. PostgreSQL: smallint[] of centi-degrees
    temps_c: Mapped[list[float | None]] = mapped_column(TemperatureArray)
    # {"7": "open_circuit", ...} (1-based), the channels not ok. PostgreSQL: bytea, 2 bytes a bad channel
    bad_channels: Mapped[dict[str, str]] = mapped_column(QualityMap)


class SampleMinuteRow(SpindleScoped, Base):
    """The 1-minute means of the stored samples (``service.store.downsample``): kept ``database.minute_days``
    after the raw samples (``database.raw_days``) are dropped. Means over the samples of the minute
    ``[t, t + 60 s)``; a channel's mean over its non-null values (null: none)."""

    __tablename__ = "samples_1min"
    __table_args__ = (PrimaryKeyConstraint("spindle_id", "t"),)

    t: Mapped[datetime]  # the minute's start, UTC
    ambient_c: Mapped[float | None] = mapped_column(Float32)
    speed_rpm: Mapped[float | None] = mapped_column(Float32)
    torque_nm: Mapped[float | None] = mapped_column(Float32)
    speed_max_rpm: Mapped[float | None] = mapped_column(Float32)
    n: Mapped[int] = mapped_column(Integer)  # samples averaged
    n_good_min: Mapped[int] = mapped_column(SmallInt)  # the fewest good channels in a sample of the minute
    can_ok: Mapped[bool] = mapped_column(Boolean)  # every sample of the minute
    daq_ok: Mapped[bool] = mapped_column(Boolean)
    temps_c: Mapped[list[float | None]] = mapped_column(TemperatureArray)  # means to 0.01 °C


class SpeedMapStateRow(SpindleScoped, Base):
    """The speed map's newest state (``SpeedMap.to_json`` with its covariance): one row per spindle,
    upserted with every map fit. The identification history rows keep the map without the covariance."""

    __tablename__ = "speed_map_state"
    __table_args__ = (PrimaryKeyConstraint("spindle_id"),)

    identification_id: Mapped[int] = mapped_column(BigInteger)  # the map fit it came from
    fitted_at: Mapped[datetime]
    state: Mapped[dict[str, JsonValue]] = mapped_column(JSON)


class OffsetCalibrationRow(SpindleScoped, Base):
    """A sensor offset baseline (``service.contracts.calibration.Calibration``); the newest is restored."""

    __tablename__ = "offset_calibrations"
    __table_args__ = (Index(None, "spindle_id", "t_to"),)

    id: Mapped[int] = mapped_column(BigId, primary_key=True)
    t_from: Mapped[datetime]  # the rest window the offsets were averaged over
    t_to: Mapped[datetime]
    source: Mapped[str] = mapped_column(String(16))  # "auto" | "manual"
    samples: Mapped[int] = mapped_column(Integer)
    offsets_c: Mapped[list[float | None]] = mapped_column(JSON)  # per channel, °C; null = not corrected
    sd_c: Mapped[list[float | None]] = mapped_column(JSON)  # per channel 1σ of the offset, °C


class CompensationReferenceRow(SpindleScoped, Base):
    """A compensation zero (``service.contracts.reference.CompensationReference``); the newest is restored."""

    __tablename__ = "compensation_references"
    __table_args__ = (Index(None, "spindle_id", "at"),)

    id: Mapped[int] = mapped_column(BigId, primary_key=True)
    at: Mapped[datetime]  # when the controller was zeroed
    temperature_c: Mapped[float]  # the uniform temperature of growth 0, °C
    sd_c: Mapped[float]  # its 1σ, °C (0: given by an operator)
    source: Mapped[str] = mapped_column(String(16))  # "api" | "cli" | "first_start" | "config"
    set_by: Mapped[str] = mapped_column(String(64))


class MechanicsCalibrationRow(SpindleScoped, Base):
    """A commissioning of the growth's mechanics (``service.contracts.mechanics.MechanicsCalibration``); the
    newest is restored and serves ``/compensation``."""

    __tablename__ = "mechanics_calibrations"
    __table_args__ = (Index(None, "spindle_id", "at"),)

    id: Mapped[int] = mapped_column(BigId, primary_key=True)
    at: Mapped[datetime]  # when the calibration was made
    set_by: Mapped[str] = mapped_column(String(64))
    source: Mapped[str] = mapped_column(String(16))  # "cli" | "api"
    restraint: Mapped[float]  # mount radial restraint s in [0, 1]
    alpha_shaft: Mapped[float]  # α factor of the shaft's material
    alpha_housing: Mapped[float]  # α factor of the housing's material
    cov: Mapped[list[float | None]] = mapped_column(JSON)  # 3×3 posterior covariance of θ, row major
    residual_rms_um: Mapped[float | None]
    residual_max_um: Mapped[float | None]
    explained: Mapped[bool] = mapped_column(Boolean)  # the fit's verdict: the model explains the test
    temperatures_sha256: Mapped[str] = mapped_column(String(64))
    canlog_sha256: Mapped[str | None] = mapped_column(String(64))
    displacements_sha256: Mapped[str] = mapped_column(String(64))
    report: Mapped[dict[str, JsonValue]] = mapped_column(JSON)  # the whole report (JSON)


class ProbeMeasurementRow(SpindleScoped, Base):
    """A probe reading in service (``service.contracts.probe.ProbeMeasurement``); the accepted ones measured
    after the newest commissioning are replayed into the mechanical posterior at start-up."""

    __tablename__ = "probe_measurements"
    __table_args__ = (Index(None, "spindle_id", "at"),)

    id: Mapped[int] = mapped_column(BigId, primary_key=True)
    at: Mapped[datetime]  # the reading's instant
    recorded_at: Mapped[datetime]  # when the service took it
    axial_um: Mapped[float]  # the tool's axial position over the commissioned zero, µm
    sd_um: Mapped[float]  # its 1σ, µm
    features: Mapped[list[float | None]] = mapped_column(JSON)  # the field's feature row 2×3, µm, row major
    field_var_um2: Mapped[float]  # the served growth's variance from the field then, µm²
    predicted_um: Mapped[float]
    sigma_um: Mapped[float]  # 1σ of the predicted reading (√S), µm
    innovation_um: Mapped[float]
    accepted: Mapped[bool] = mapped_column(Boolean)  # absorbed into the posterior
    set_by: Mapped[str] = mapped_column(String(64))
    source: Mapped[str] = mapped_column(String(16))
    # absorbed as a step of the fixture offset (revision 0009; older rows: false)
    offset_step: Mapped[bool] = mapped_column(Boolean, server_default=false())


class LiveStateRow(SpindleScoped, Base):
    """The live state's newest checkpoint (``service.contracts.checkpoint.LiveCheckpoint``): one row, replaced
    on every write (``service.store.repository.write_records``); a restart resumes the filter from it."""

    __tablename__ = "live_state"
    __table_args__ = (Index(None, "spindle_id"),)

    id: Mapped[int] = mapped_column(BigId, primary_key=True)
    at: Mapped[datetime]  # the state's time (a sample's), UTC
    model_version: Mapped[str] = mapped_column(String(64))  # the reduced model it belongs to
    converged: Mapped[bool] = mapped_column(Boolean)
    ambient_c: Mapped[float]  # the inputs held at the checkpoint: °C, rpm, N·m
    speed_rpm: Mapped[float]
    torque_nm: Mapped[float]
    payload: Mapped[bytes] = mapped_column(LargeBinary)  # .npz: mean, cov, cross, bias_s, bias_m (float64)
