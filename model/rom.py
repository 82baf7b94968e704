"""Parametric reduced-order model (POD-Galerkin) of the spindle's transient heat conduction.

The full FE model E·dT/dt + K(H)·T = Z is affine in H: K(H) = K0 + Σ H_i·K_i and
Z = T_amb·Σ H_i·z_i + s_f·Q_f·q_f + s_r·Q_r·q_r. With an E-orthonormal basis V (N, r) of full-FE snapshots
(``model.rom_train``), T ≈ V·a and the Galerkin projection keeps the structure exactly:
K_r(H) = VᵀK0V + Σ H_i·VᵀK_iV, so one projection serves the whole H box. A whole population of candidates is
evaluated in closed form per piecewise-constant input segment (``model.rom_modal``), reproducing the reduced
θ-method trajectory to round-off. The model is built offline and cached on disk (``model.rom_cache``).

Errors::

    RomError(ValueError)          bad argument (the field is named)
    └── RomCacheError             unreadable / mismatching cache file (load_or_build_rom rebuilds)
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from functools import cached_property
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from model import rom_cache, rom_modal, rom_split, rom_stream, rom_train
from model.errors import ModelError
from model.rom_check import error_report as _error_report
from model.rom_train import AffineSystem

Array = NDArray[np.float64]

# 56 with TRAIN_SUBSTEPS 4: the served model (exact over each held step) within 0.012 °C of a full FE
# converged in time over 8 x 6 random H x 2 histories, where rank 46 (10-s BE training) reached 0.040 °C and
# 52 0.022 °C (target 0.02); ~1.2x the cost per candidate of 46 (docs/design/rom.md, "Choices")
DEFAULT_RANK = 56
# θ-steps per 10-s step of the training trajectories' fast part: the snapshots follow the exact time response
# the served model reproduces (1, 10-s BE snapshots: rank 56 still 0.019 °C off a converged reference)
DEFAULT_TRAIN_SUBSTEPS = 4
DEFAULT_THETA = 1.0  # as model.fem.simulate (backward Euler); checked by the tests
# 0: the reduced ODE is integrated exactly over each 10-s input step (zero-order hold), so the model has no
# time-step error; backward Euler at 10 s was 0.07-0.14 °C off a converged reference at the sensors (issue 15)
DEFAULT_SUBSTEPS = 0
# spectral split (model.rom_split; docs/design/rom.md, "Spectral split"): -1 at the first gap of the spectrum
# (33 slow modes for the default model), k > 0: k slow modes, 0: all modes exact
DEFAULT_N_SLOW = rom_split.AUTO
DEFAULT_BOX = (5.0, 200.0)
DEFAULT_Q_MAX_W = (300.0, 150.0)  # W: above the packaged spindle's bearing heats at 7000 rpm, 20 N·m


class RomError(ModelError, ValueError):
    """A bad argument to the reduced model; the message names the field."""


class RomCacheError(RomError):
    """A cache file that cannot be read or does not match the requested model."""


class InputLike(Protocol):
    """Piecewise-constant inputs (``model.inputs.InputSeries``): entry k applies on step k -> k+1."""

    @property
    def dt_s(self) -> float: ...

    @property
    def ambient_c(self) -> Any: ...

    @property
    def q_front_w(self) -> Any: ...

    @property
    def q_rear_w(self) -> Any: ...


@dataclass(frozen=True)
class ReducedModel:
    """The reduced model: basis, projected affine operators and its measured error vs the full FE.

    Shapes: basis (N, r); k0 (r, r) [W/K]; k_zone (7, r, r) and z_zone (7, r) [m², times H]; q_front,
    q_rear (r,) per W; sensors (32, r); basis_t_mass (r, N) = Vᵀ·E.
    """

    basis: Array
    basis_t_mass: Array
    k0: Array
    k_zone: Array
    z_zone: Array
    q_front: Array
    q_rear: Array
    sensors: Array
    theta: float
    h_box: tuple[float, float]
    key: str
    substeps: int = 1  # time steps per input step in the closed form; 0: exact (rom_modal.step_factors)
    error_report: dict[str, Any] = field(default_factory=dict)
    build_s: float = 0.0
    from_cache: bool = False
    # slow modes of the spectral split (model.rom_split) in the served evaluation (substeps 0); 0: all exact
    n_slow: int = DEFAULT_N_SLOW

    @property
    def rank(self) -> int:
        """Number of basis vectors r."""
        return int(self.basis.shape[1])

    @property
    def n_nodes(self) -> int:
        """Number of FE nodes N of the full model."""
        return int(self.basis.shape[0])

    def lift(self, a: Array) -> Array:
        """Full field V·a [°C]: (r,) -> (N,), or (..., r) -> (..., N)."""
        return np.asarray(np.asarray(a) @ self.basis.T)

    def project(self, t: Array) -> Array:
        """E-orthogonal projection a = Vᵀ·E·T of a field (N,) [°C] -> (r,); exact for fields in the span."""
        t = np.asarray(t, dtype=np.float64)
        if t.shape[-1] != self.n_nodes:
            raise RomError(f"t: expected a field with {self.n_nodes} nodes, got shape {t.shape}")
        return np.asarray(t @ self.basis_t_mass.T)

    def initial_state(self, t0: float | Array) -> Array:
        """Reduced start state (r,) from a uniform temperature [°C] or an (N,) field [°C]."""
        t0_arr = np.asarray(t0, dtype=np.float64)
        if t0_arr.ndim == 0:
            return np.asarray(float(t0_arr) * self._uniform_state)
        if t0_arr.shape != (self.n_nodes,):
            raise RomError(f"t0: expected a scalar or shape ({self.n_nodes},), got {t0_arr.shape}")
        return self.project(t0_arr)

    @cached_property
    def _uniform_state(self) -> Array:
        return self.project(np.ones(self.n_nodes))

    @property
    def split_active(self) -> bool:
        """Whether ``simulate_sensors`` uses the spectral split (``model.rom_split``) for 10-s steps: exact
        per-step solution (substeps 0), n_slow auto (a gap found) or 0 < n_slow < rank, and its guards."""
        ops = self._split_operators
        return ops is not None and ops.usable(10.0)

    @cached_property
    def _split_operators(self) -> rom_split.SplitOperators | None:
        if self.substeps != 0 or self.n_slow == 0 or self.n_slow >= self.rank:
            return None
        lo, hi = self.h_box
        return rom_split.split_operators(
            self.k0,
            self.k_zone,
            self.z_zone,
            self.q_front,
            self.q_rear,
            self.sensors,
            h_centre=np.full(7, np.sqrt(lo * hi)),
            n_slow=self.n_slow,
        )

    def simulate_sensors(
        self,
        h: Array,
        inputs: InputLike,
        t0: float | Array,
        *,
        load_scale: Array | None = None,
        t0_shift: Array | None = None,
    ) -> Array:
        """Sensor temperatures (P, n_steps+1, 32) [°C] for P candidates H (P, 7) [W/(m²·K)].

        ``t0``: uniform start [°C] or (N,) field (projected). ``load_scale`` (P, 2) multiplies the front/rear
        bearing heat per candidate (default 1). ``t0_shift`` (P,) [°C] adds a uniform temperature to the
        start field per candidate (exact: the uniform field is in the basis).
        """
        h2, scale = self._check_population(h, load_scale)
        a0 = self._start_states(t0, t0_shift, h2.shape[0])
        ops = self._split_operators
        if ops is not None and ops.usable(float(inputs.dt_s)):
            seg = _segments(inputs)
            sr = rom_split.split_run(ops, h2, seg, a0, scale, float(inputs.dt_s))
            return rom_split.window_outputs(sr, seg)
        md = rom_modal.modes(self.k0, self.k_zone, h2)
        gain = np.matmul(self.sensors[None, :, :], md.phi)  # (P, 32, r)
        return rom_stream.window_outputs(self._modal_run(md, h2, inputs, a0, scale), gain)

    def simulate_state(
        self, h: Array, inputs: InputLike, t0: float | Array, *, load_scale: Array | None = None
    ) -> Array:
        """Reduced state trajectory (n_steps+1, r) for one H (7,); ``lift`` gives the fields [°C]."""
        h_arr = np.asarray(h, dtype=np.float64)
        if h_arr.shape != (7,):
            raise RomError(f"h: expected shape (7,), got {h_arr.shape}")
        scale = None if load_scale is None else np.asarray(load_scale, dtype=np.float64).reshape(1, 2)
        h2, scale2 = self._check_population(h_arr[None, :], scale)
        md = rom_modal.modes(self.k0, self.k_zone, h2)
        b = rom_modal.modal_trajectory(self._modal_run(md, h2, inputs, self.initial_state(t0), scale2))
        return np.asarray(b[:, 0, :] @ md.phi[0].T)

    def end_states(self, h: Array, inputs: InputLike, a0: Array, *, load_scale: Array | None = None) -> Array:
        """The reduced states (P, r) at the window's end for P candidates H (P, 7) from reduced starts
        ``a0`` (P, r): ``simulate_state``'s last row for each, in one batched run."""
        h2, scale = self._check_population(h, load_scale)
        starts = np.asarray(a0, dtype=np.float64)
        if starts.shape != (h2.shape[0], self.rank):
            raise RomError(f"a0: expected shape ({h2.shape[0]}, {self.rank}), got {starts.shape}")
        md = rom_modal.modes(self.k0, self.k_zone, h2)
        b = rom_modal.modal_trajectory(self._modal_run(md, h2, inputs, starts, scale))
        return np.asarray(np.einsum("prs,ps->pr", md.phi, b[-1]))

    def steady_state(
        self,
        h: Array,
        *,
        ambient_c: float,
        q_front_w: float,
        q_rear_w: float,
        load_scale: tuple[float, float] = (1.0, 1.0),
    ) -> Array:
        """Reduced steady state (r,) solving K_r(H)·a = Z_r; ``lift`` gives the field [°C]."""
        h_arr = np.asarray(h, dtype=np.float64).reshape(1, 7)
        kr = rom_modal.conductance(self.k0, self.k_zone, h_arr)[0]
        load = (
            ambient_c * (h_arr[0] @ self.z_zone)
            + q_front_w * load_scale[0] * self.q_front
            + q_rear_w * load_scale[1] * self.q_rear
        )
        return np.asarray(np.linalg.solve(kr, load))

    def _start_states(self, t0: float | Array, shift: Array | None, p: int) -> Array:
        """Reduced start state (r,), or (P, r) with a uniform ``shift`` [°C] per candidate."""
        a0 = self.initial_state(t0)
        if shift is None:
            return a0
        d = np.asarray(shift, dtype=np.float64)
        if d.shape != (p,) or not np.all(np.isfinite(d)):
            raise RomError(f"t0_shift: expected {p} finite values, got shape {d.shape}")
        return np.asarray(a0[None, :] + d[:, None] * self._uniform_state[None, :])

    def _check_population(self, h: Array, load_scale: Array | None) -> tuple[Array, Array]:
        h2 = np.asarray(h, dtype=np.float64)
        if h2.ndim != 2 or h2.shape[1] != 7:
            raise RomError(f"h: expected shape (P, 7), got {h2.shape}")
        if not np.all(np.isfinite(h2)) or np.any(h2 <= 0.0):
            raise RomError("h: every coefficient must be finite and > 0 W/(m²·K)")
        if load_scale is None:
            return h2, np.ones((h2.shape[0], 2))
        scale = np.asarray(load_scale, dtype=np.float64)
        if scale.shape != (h2.shape[0], 2):
            raise RomError(f"load_scale: expected shape ({h2.shape[0]}, 2), got {scale.shape}")
        return h2, scale

    def _modal_run(
        self, md: rom_modal.Modes, h: Array, inputs: InputLike, a0: Array, scale: Array
    ) -> rom_modal.ModalRun:
        """The window in the candidates' modal coordinates (start, μ, modal loads per unit input); the
        reduced start ``a0`` is (r,), shared, or (P, r), per candidate."""
        seg = _segments(inputs)  # validates the inputs (dt first) before anything uses them
        # γ·c = (1-μ)·c/λ
        mu, _ = rom_modal.step_factors(md.lam, float(inputs.dt_s), self.theta, self.substeps)
        phi_t = np.swapaxes(md.phi, 1, 2)
        forcing = (
            np.einsum("prs,ps->pr", phi_t, rom_modal.ambient_load(self.z_zone, h)),
            phi_t @ self.q_front,
            phi_t @ self.q_rear,
        )
        b0 = phi_t @ a0 if a0.ndim == 1 else np.einsum("prs,ps->pr", phi_t, a0)  # shared or per candidate
        return rom_modal.ModalRun(b0, md.lam, mu, forcing, seg, scale)


def _segments(inputs: InputLike) -> rom_modal.Segments:
    dt = float(inputs.dt_s)
    if not np.isfinite(dt) or dt <= 0.0:
        raise RomError(f"inputs.dt_s: must be > 0 s, got {inputs.dt_s}")
    arrays = [
        np.asarray(getattr(inputs, name), dtype=np.float64) for name in ("ambient_c", "q_front_w", "q_rear_w")
    ]
    n = arrays[0].shape
    for name, arr in zip(("ambient_c", "q_front_w", "q_rear_w"), arrays, strict=True):
        if arr.ndim != 1 or arr.shape != n:
            raise RomError(
                f"inputs.{name}: expected a 1-D array of length {n[0] if n else '?'}, got {arr.shape}"
            )
        if not np.all(np.isfinite(arr)):
            raise RomError(f"inputs.{name}: contains non-finite values")
    return rom_modal.split_segments(*arrays)


@dataclass(frozen=True)
class BuildOptions:
    """Everything besides the FE matrices and the spec that determines a reduced model (in the cache key)."""

    rank: int = DEFAULT_RANK
    theta: float = DEFAULT_THETA
    substeps: int = DEFAULT_SUBSTEPS
    box: tuple[float, float] = DEFAULT_BOX
    n_train: int = 24
    keep_per_sample: int = 60
    sensor_weight: float = 3.0
    ambient_amp_c: float = 30.0  # 3x weight on the ambient-step response (first steps after a jump)
    n_check: int = 8
    check_dt_s: float = 10.0
    check_steps: int = 360
    q_max_w: tuple[float, float] = DEFAULT_Q_MAX_W
    seed: int = 0
    train_substeps: int = DEFAULT_TRAIN_SUBSTEPS  # θ-steps per 10-s snapshot step (training's fast part)


def build_rom(
    fe: AffineSystem,
    spec: Any = None,
    *,
    options: BuildOptions | None = None,
    key: str = "",
    progress: Callable[[str], None] | None = None,
    **overrides: Any,
) -> ReducedModel:
    """Build the reduced model from full-FE snapshots and measure its error (``error_report``).

    ``spec`` (a ``SpindleSpec``) supplies the H box when ``box`` is not given. Keyword ``overrides`` replace
    fields of ``BuildOptions`` (e.g. ``rank=20``). About 40 s for the 8.7k-node default mesh on two cores
    (~3/4 snapshots, ~1/4 the self-check); the time grows about linearly with N and n_train.
    """
    opts = resolve_options(spec, options, overrides)
    if opts.rank < 2:
        raise RomError(f"rank: must be >= 2, got {opts.rank}")
    started = time.perf_counter()
    rng = np.random.default_rng(opts.seed)
    basis, sing = _train_basis(fe, opts, rng, progress)
    proj = rom_train.project_system(fe, basis)
    rom = ReducedModel(
        basis=basis,
        basis_t_mass=proj.basis_t_mass,
        k0=proj.k0,
        k_zone=proj.k_zone,
        z_zone=proj.z_zone,
        q_front=proj.q_front,
        q_rear=proj.q_rear,
        sensors=proj.sensors,
        theta=opts.theta,
        h_box=opts.box,
        key=key,
        substeps=opts.substeps,
    )
    report = _error_report(
        # the projection error: both sides take the same θ-steps (docs/design/rom.md)
        replace(rom, substeps=1),
        fe,
        theta=opts.theta,
        box=opts.box,
        n_cases=opts.n_check,
        seed=opts.seed + 1_000_003,
        q_max_w=opts.q_max_w,
        n_steps=opts.check_steps,
        dt_s=opts.check_dt_s,
        progress=progress,
    )
    report["rank"] = opts.rank
    report["pod_sigma_ratio_at_rank"] = float(sing[min(opts.rank - 1, sing.size - 1)] / sing[0])
    report["train_samples"] = opts.n_train + 2
    build_s = time.perf_counter() - started
    report["build_s"] = build_s
    return replace(rom, error_report=report, build_s=build_s)


def resolve_options(spec: Any, options: BuildOptions | None, overrides: dict[str, Any]) -> BuildOptions:
    """Options with the spec's H box as default box and keyword overrides applied."""
    base = options or BuildOptions()
    values = dict(base.__dict__)
    if options is None and "box" not in overrides and getattr(spec, "h_box", None) is not None:
        values["box"] = tuple(float(x) for x in spec.h_box)
    unknown = set(overrides) - set(values)
    if unknown:
        raise RomError(f"unknown build option(s): {', '.join(sorted(unknown))}")
    values.update(overrides)
    values["box"] = tuple(float(x) for x in values["box"])
    values["q_max_w"] = tuple(float(x) for x in values["q_max_w"])
    return BuildOptions(**values)


def _train_basis(
    fe: AffineSystem,
    opts: BuildOptions,
    rng: np.random.Generator,
    progress: Callable[[str], None] | None,
) -> tuple[Array, Array]:
    hs = rom_train.training_h(opts.n_train, opts.box, rng=rng)
    weighting = rom_train.Weighting.of(fe, opts.sensor_weight)
    n = fe.E.shape[0]
    starts = (np.zeros(n), np.zeros(n))
    amp = rom_train.Amplitudes(
        ambient_c=opts.ambient_amp_c, q_front_w=opts.q_max_w[0], q_rear_w=opts.q_max_w[1]
    )
    blocks = []
    for i, h in enumerate(hs):
        snap = rom_train.sample_snapshots(
            fe, h, theta=opts.theta, amp=amp, starts=starts, rng=rng, substeps=opts.train_substeps
        )
        blocks.append(rom_train.compress(snap, weighting, keep=opts.keep_per_sample))
        starts = (snap.steady, snap.transient)
        if progress is not None and (i + 1) % 5 == 0:
            progress(f"rom snapshots {i + 1}/{hs.shape[0]}")
    return rom_train.pod_basis(blocks, fe, weighting, opts.rank)


_ARRAYS = ("basis", "basis_t_mass", "k0", "k_zone", "z_zone", "q_front", "q_rear", "sensors")


def save_rom(rom: ReducedModel, path: Path) -> None:
    """Write the reduced model (arrays, θ, box, key, error report) to an npz file."""
    meta = {
        "key": rom.key,
        "theta": rom.theta,
        "substeps": rom.substeps,
        "h_box": list(rom.h_box),
        "error_report": rom.error_report,
        "build_s": rom.build_s,
    }
    rom_cache.save(path, {name: getattr(rom, name) for name in _ARRAYS}, meta)


def load_rom(path: Path, *, key: str | None = None) -> ReducedModel:
    """Read a reduced model written by ``save_rom``; ``RomCacheError`` if unreadable or of another key."""
    try:
        arrays, meta = rom_cache.load(path, _ARRAYS)
    except rom_cache.CacheReadError as err:
        raise RomCacheError(str(err)) from err
    if key is not None and meta.get("key") != key:
        raise RomCacheError(f"{path}: field key does not match the requested model")
    # typed Any: ReducedModel also has non-array fields (n_slow), which the arrays must not be checked against
    fields: dict[str, Any] = {n: np.asarray(arrays[n], dtype=np.float64) for n in _ARRAYS}
    try:
        return ReducedModel(
            **fields,
            theta=float(meta["theta"]),
            substeps=int(meta.get("substeps", 1)),
            h_box=(float(meta["h_box"][0]), float(meta["h_box"][1])),
            key=str(meta["key"]),
            error_report=dict(meta["error_report"]),
            build_s=float(meta["build_s"]),
            from_cache=True,
        )
    except (KeyError, TypeError, ValueError, IndexError) as err:
        raise RomCacheError(f"{path}: bad meta record ({err})") from err


def load_or_build_rom(
    fe: AffineSystem,
    spec: Any,
    cache_dir: Path,
    *,
    options: BuildOptions | None = None,
    rebuild: bool = False,
    progress: Callable[[str], None] | None = None,
    **overrides: Any,
) -> ReducedModel:
    """The cached reduced model for (FE matrices + mesh, spec, options), building and saving it if needed.

    The cache file is keyed by a hash of all of these, so a changed geometry, mesh, box, rank or θ rebuilds.
    An unreadable cache file is rebuilt and overwritten.
    """
    opts = resolve_options(spec, options, overrides)
    key = rom_cache.cache_key(fe, spec, asdict(opts))
    path = rom_cache.cache_path(Path(cache_dir), key)
    if path.exists() and not rebuild:
        try:
            return load_rom(path, key=key)
        except RomCacheError as err:
            if progress is not None:
                progress(f"rebuilding reduced model: {err}")
    rom = build_rom(fe, spec, options=opts, key=key, progress=progress)
    save_rom(rom, path)
    return rom
