"""Identification of the convective heat transfer coefficients H1..H7 from a window of measured temperatures.

The reduced model (``model.rom``) is fitted to the 32 sensor series of a ``Window``; the objective is the
paper's f = mean squared error [°C²] over the usable sensors and samples, fit = 1/(1+f). Methods:

- ``"empirical"``: the paper's correlations (``model.empirical.empirical_h``), no fitting;
- ``"ga"``, ``"woa"``, ``"gwo"``, ``"igwo"``: population optimizers (``model.optim``) with the paper's Table 3
  settings by default (population 7, 100 iterations, a 2.0 → 0.001);
- ``"hybrid"`` (default): a short IGWO on the reduced model, then a bounded trust-region least-squares polish
  (scipy TRF) with a finite-difference Jacobian evaluated as one batch.

Options: joint estimation of the front/rear bearing heat scale factors with H (``estimate_loads``); sensor
offsets subtracted (``offsets_c``, see ``baseline_offsets``); initial field ``window.t0``; warm start from a
previous solution; channel mask. Every result carries 95 % confidence intervals from the Jacobian at the
optimum (σ² = SSR/(m − p), cov = σ²(JᵀJ)⁻¹), the correlation matrix, and per-sensor and test-point errors.
With ``start_cov`` (the start field's error covariance, reduced coordinates) the covariance also carries the
start field's error (``model.carry``) and the result has the window-end state's covariance for the next one;
with ``options.start_modes`` k > 0 the start's k leading uncertain directions are fitted too (a Gaussian
prior from ``start_cov``, ``StartFitProblem``) and only the rest is carried.

With ``prior`` (``model.identify_prior.HPrior``, a Gaussian on ln H: the served modes) the fit is a MAP fit:
the prior's whitened rows are appended to the residuals (σ = ``options.prior_noise_c`` in the search, then the
fit's own σ), the covariance is the posterior's, (JᵀJ/σ² + P)⁻¹, and an H the data did not see
(``HPrior.dominated``) keeps the prior's value and band, flagged ``prior_dominated``, never ``identified``.
Without it (the paper's protocol) nothing changes.

Errors::

    IdentificationError(ValueError)        bad window, method, warm start or option (the field is named)
    └── InsufficientDataError              too few usable sensors or samples for a fit
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import least_squares

from model import optim, rom_modal
from model.carry import CarryError, carry, check_cov
from model.defaults import BOUND_REL_TOL, CI_REL_THRESHOLD
from model.errors import ModelError
from model.identify_prior import HPrior
from model.identify_problem import (
    N_H,
    Array,
    Layout,
    Problem,
    SensorModel,
    baseline_offsets,
    channel_bias_cov,
    confidence,
    per_sensor_rmse,
    point_errors,
    usable_entries,
    with_cov,
)
from model.optim._common import as_rng

__all__ = [
    "METHODS",
    "IdentificationError",
    "IdentificationResult",
    "IdentifyOptions",
    "InsufficientDataError",
    "Window",
    "baseline_offsets",
    "identify",
]

METHODS = ("empirical", "ga", "woa", "gwo", "igwo", "hybrid")
N_CHANNELS = 32


class IdentificationError(ModelError, ValueError):
    """The identification cannot run as asked; the message names the field."""


class InsufficientDataError(IdentificationError):
    """Too little usable data (sensors or samples) for a meaningful fit."""


@dataclass(frozen=True)
class Window:
    """Measured data for one identification.

    inputs: ``model.inputs.InputSeries`` over n_steps; measured_c: (n_steps + 1, 32) [°C], NaN for a missing
    sample; mask: (32,) bool, True = usable channel; t0: initial field, a uniform temperature [°C] or an (N,)
    field of the fitted model's mesh. ``speed_rpm`` (the condition's speed) is only needed by ``"empirical"``.
    """

    inputs: Any
    measured_c: NDArray[np.float64]
    mask: NDArray[np.bool_]
    t0: float | NDArray[np.float64]
    speed_rpm: float | None = None


@dataclass(frozen=True)
class IdentifyOptions:
    """Tuning of ``identify``; defaults are the paper's Table 3 for the metaheuristics."""

    popsize: int = 7
    maxiter: int = 100
    a_start: float = 2.0
    a_end: float = 0.001
    fun_target: float | None = None  # paper: stop at fit > 0.5, i.e. f < 1 °C²
    time_budget_s: float | None = None
    hybrid_popsize: int = 7
    hybrid_maxiter: int = 12
    warm_a_start: float = 0.3  # a warm start must not be scattered by a = 2 exploration
    warm_hybrid_maxiter: int = 3
    load_box: tuple[float, float] = (0.5, 2.0)
    ci_threshold: float = CI_REL_THRESHOLD  # 95 % half-width in log H above which an H is poorly identified
    bound_rel_tol: float = BOUND_REL_TOL  # H this close to a bound (fraction of box width): at the bound
    t0_shift_box: tuple[float, float] = (-2.0, 2.0)  # °C, the fitted uniform shift of the start field
    min_sensors: int = 4
    min_samples: int = 30
    lsq_max_nfev: int = 60
    lsq_tol: float = 1e-10
    # °C, 1σ of a constant per-channel model error carried in the CIs (``channel_bias_cov``): what is left of
    # the reduced model's and the plant's differences at the sensors, at its measured peak (projection
    # ≤ 0.011 °C, mesh ≤ 0.02 °C at 7000 rpm); 0.01 (the mesh's RMS) left H6/H7 at 0.86-0.89 coverage
    # (docs/design/identification.md, "Model error and sensor offsets", "Hidden-truth bench")
    model_error_c: float = 0.02
    # with ``start_cov``: also fit the start state along its k leading uncertain directions (eigenvectors of
    # start_cov scaled by √eigenvalue, each with a N(0, 1) prior), profiled out per candidate H by a ridge
    # least squares whose weight is ``start_noise_c`` [°C] (the measurement noise 1σ); the remaining
    # directions are only carried in the CIs. 0: no fit (the carry alone)
    start_modes: int = 0
    start_noise_c: float = 0.15
    # °C, the measurement noise 1σ that weighs a prior's rows against the residuals in the search (the
    # plant's and the DAQ's 0.15 °C); the hybrid's polish then re-weighs them with the fit's own σ
    prior_noise_c: float = 0.15


@dataclass
class IdentificationResult:
    """Identified H and its quality. Units: H [W/(m²·K)], f [°C²], temperatures and errors [°C], wall_s [s].

    ``nfev`` counts reduced-model evaluations of the search (the CI Jacobian is extra); ``rmse_per_sensor`` is
    over the entries the fit used (NaN for a masked-out channel); ``test_points`` maps test point -> {me (max
    |error|), mae, rmse} against the window's (offset-corrected) usable measurements (a masked-out test point
    is absent); ``at_bound`` marks an H on a bound of the search box (not identified: the optimum may lie
    outside the box);
    ``fe_check`` (when a full FE model was given) the RMSE over the usable entries with the reduced model and
    with the full FE at the same H.
    """

    h: Array
    h_ci95: Array  # (7, 2), from the covariance of log H: lo = H·e^(−zσ), hi = H·e^(zσ), always > 0
    identified: NDArray[np.bool_]  # (7,): CI narrow enough (``ci_threshold``) and not at a bound
    correlation: Array  # (7, 7)
    load_scale: Array | None
    f: float
    fit: float
    rmse_per_sensor: Array  # (32,)
    test_points: dict[int, dict[str, float]]
    nfev: int
    wall_s: float
    method: str
    message: str
    load_scale_ci95: Array | None = None
    sigma_c: float = float("nan")
    t0_shift_c: float | None = None  # fitted uniform shift of the start field [°C] (estimate_t0_shift)
    t0_shift_ci95: Array | None = None  # (2,) [°C]
    end_ensemble: Any = field(default=None, repr=False)  # model.carry.Ensemble of the window end (start_cov)
    fe_check: dict[str, float] | None = None
    theta: Array = field(default_factory=lambda: np.zeros(0), repr=False)
    population: Array | None = field(default=None, repr=False)
    at_bound: NDArray[np.bool_] = field(default_factory=lambda: np.zeros(N_H, dtype=bool))  # (7,)
    # (7,) with a prior: the data cut var(ln H) by less than half of the cold prior's (then not identified)
    prior_dominated: NDArray[np.bool_] = field(default_factory=lambda: np.zeros(N_H, dtype=bool))
    prior_source: str | None = None  # where the prior came from (None: unregularised)


def _check_window(window: Window, n_nodes: int | None) -> Array:
    meas = np.asarray(window.measured_c, dtype=float)
    n = int(window.inputs.n_steps) if hasattr(window.inputs, "n_steps") else len(window.inputs.ambient_c)
    if meas.shape != (n + 1, N_CHANNELS):
        raise IdentificationError(
            f"window.measured_c: expected shape ({n + 1}, {N_CHANNELS}), got {meas.shape}"
        )
    mask = np.asarray(window.mask)
    if mask.shape != (N_CHANNELS,) or mask.dtype != bool:
        raise IdentificationError(
            f"window.mask: expected ({N_CHANNELS},) bool, got {mask.shape} {mask.dtype}"
        )
    t0 = np.asarray(window.t0, dtype=float)
    if t0.ndim > 0 and n_nodes is not None and t0.shape != (n_nodes,):
        raise IdentificationError(f"window.t0: expected a scalar or ({n_nodes},) field, got {t0.shape}")
    return meas


def _bounds(box: tuple[float, float], layout: Layout, opts: IdentifyOptions) -> Array:
    lo, hi = float(box[0]), float(box[1])
    if not (0.0 < lo < hi):
        raise IdentificationError(f"box: expected 0 < low < high, got {box}")
    rows = [[lo, hi]] * N_H
    if layout.loads:
        rows += [list(opts.load_box)] * 2
    if layout.t0_shift:
        rows += [list(opts.t0_shift_box)]
    return np.array(rows, dtype=float)


def _warm_vector(warm_start: Any, layout: Layout, bounds: Array) -> Array | None:
    """θ to start from: H (and load scales, if both fit them) of a previous solution; missing load scales
    start at 1, the start-field shift at 0 (it belongs to one window, not to the condition)."""
    if warm_start is None:
        return None
    if isinstance(warm_start, IdentificationResult):
        ls = warm_start.load_scale
        theta = warm_start.h if ls is None else np.concatenate([warm_start.h, ls])
    else:
        theta = np.asarray(warm_start, dtype=float).reshape(-1)
    accepted = {N_H, layout.p} | ({N_H + 2} if layout.loads else set())
    if theta.size not in accepted or not np.all(np.isfinite(theta)):
        sizes = " or ".join(str(n) for n in sorted(accepted))
        raise IdentificationError(f"warm_start: expected {sizes} finite values, got {theta.size}")
    rest = theta[N_H:]
    loads = (rest[:2] if rest.size >= 2 else np.ones(2)) if layout.loads else np.zeros(0)
    shift = rest[-1:] if layout.t0_shift and theta.size == layout.p else np.zeros(int(layout.t0_shift))
    return np.clip(np.concatenate([theta[:N_H], loads, shift]), bounds[:, 0], bounds[:, 1])


def _objective(problem: Problem, prior: HPrior | None, noise_c: float) -> Any:
    """f(θ) (P,) [°C²] the optimizers minimise: mean(r²), plus σ²·(prior penalty)/m with a prior."""
    if prior is None:
        return problem.objective
    weight = float(noise_c) ** 2 / max(problem.usable.m, 1)

    def objective(theta: Array) -> Array:
        return np.asarray(problem.objective(theta) + weight * prior.penalty(theta))

    return objective


def _metaheuristic(
    problem: Problem,
    method: str,
    rng: np.random.Generator,
    x0: Array | None,
    opts: IdentifyOptions,
    prior: HPrior | None = None,
) -> tuple[Array, str, Array]:
    objective = _objective(problem, prior, opts.prior_noise_c)
    common: dict[str, Any] = {
        "rng": rng,
        "x0": x0,
        "popsize": opts.popsize,
        "maxiter": opts.maxiter,
        "fun_target": opts.fun_target,
        "time_budget_s": opts.time_budget_s,
    }
    if method in ("gwo", "igwo"):
        a0 = opts.warm_a_start if x0 is not None else opts.a_start
        res = optim.grey_wolf(
            objective,
            problem.bounds,
            variant="gwo" if method == "gwo" else "igwo",
            a_start=a0,
            a_end=opts.a_end,
            **common,
        )
    elif method == "woa":
        res = optim.whale(objective, problem.bounds, **common)
    else:
        res = optim.genetic(objective, problem.bounds, **common)
    return res.x, res.message, res.population


def _hybrid(
    problem: Problem,
    rng: np.random.Generator,
    x0: Array | None,
    opts: IdentifyOptions,
    prior: HPrior | None = None,
) -> tuple[Array, str, Array]:
    stage = replace(
        opts,
        popsize=opts.hybrid_popsize,
        maxiter=opts.warm_hybrid_maxiter if x0 is not None else opts.hybrid_maxiter,
        fun_target=None,
    )
    start, _, pop = _metaheuristic(problem, "igwo", rng, x0, stage, prior)
    sol = _polish(problem, start, opts, prior, opts.prior_noise_c)
    message = f"IGWO {stage.popsize}x{stage.maxiter} + TRF: {sol.message}"
    if prior is not None:  # re-weigh the prior with the fit's own noise σ (what the covariance uses)
        r = problem.residuals(np.asarray(sol.x)[None, :])[0]
        sigma = float(np.sqrt(r @ r / max(r.size - problem.p, 1)))
        if abs(sigma / opts.prior_noise_c - 1.0) > 0.1:
            sol = _polish(problem, np.asarray(sol.x), opts, prior, sigma)
        message += f"; MAP fit, prior: {prior.source}"
    return np.asarray(sol.x), message, pop


def _polish(
    problem: Problem, start: Array, opts: IdentifyOptions, prior: HPrior | None, noise_c: float
) -> Any:
    """Bounded TRF least squares from ``start``; with a prior its rows σ·W·(ln H − μ) are appended."""
    scale = 1.0 / np.sqrt(problem.usable.m)
    cache: dict[bytes, Array] = {}

    def fun(x: Array) -> Array:
        r = problem.residuals(x[None, :])[0]
        cache.clear()
        cache[x.tobytes()] = r
        if prior is not None:
            r = np.concatenate([r, noise_c * prior.rows(x)[0]])
        return np.asarray(r * scale)

    def jac(x: Array) -> Array:
        j, _ = problem.jacobian(x, cache.get(x.tobytes()))
        if prior is not None:
            j = np.vstack([j, noise_c * prior.rows_jacobian(x)])
        return np.asarray(j * scale)

    return least_squares(
        fun,
        start,
        jac=jac,
        bounds=(problem.bounds[:, 0], problem.bounds[:, 1]),
        method="trf",
        x_scale="jac",
        ftol=opts.lsq_tol,
        xtol=opts.lsq_tol,
        gtol=opts.lsq_tol,
        max_nfev=opts.lsq_max_nfev,
    )


def _empirical(window: Window, spec: Any, bounds: Array) -> tuple[Array, str]:
    p = len(bounds)
    if window.speed_rpm is None:
        raise IdentificationError("window.speed_rpm: required by method 'empirical'")
    from model.empirical import empirical_h

    ambient = float(np.mean(window.inputs.ambient_c))
    h = np.asarray(empirical_h(spec, speed_rpm=float(window.speed_rpm), ambient_c=ambient), dtype=float)
    h = np.clip(h, bounds[:N_H, 0], bounds[:N_H, 1])  # the reduced model is only valid inside the box
    theta = np.concatenate([h, np.ones(p - N_H)]) if p > N_H else h
    return theta, "empirical correlations (no fit)"


def _spec_or_default(spec: Any) -> Any:
    if spec is not None:
        return spec
    from model.geometry import load_spindle

    return load_spindle()


def identify(
    rom: SensorModel,
    window: Window,
    *,
    rng: np.random.Generator | int,
    method: str = "hybrid",
    box: tuple[float, float] | None = None,
    warm_start: ArrayLike | IdentificationResult | None = None,
    estimate_loads: bool = False,
    estimate_t0_shift: bool = False,
    offsets_c: ArrayLike | None = None,
    offset_sd_c: ArrayLike | None = None,
    start_cov: ArrayLike | None = None,
    fe: Any = None,
    spec: Any = None,
    options: IdentifyOptions | None = None,
    prior: HPrior | None = None,
) -> IdentificationResult:
    """Identify H1..H7 [W/(m²·K)] from ``window`` by fitting the reduced model ``rom``.

    Args:
        rom: ``model.rom.ReducedModel`` (anything with a batched ``simulate_sensors``).
        window: inputs, measurements, channel mask and initial field.
        rng: generator or seed of the stochastic methods (same seed, same answer).
        method: one of ``METHODS``; ``"hybrid"`` (IGWO then bounded TRF) by default.
        box: search box for H [W/(m²·K)]; None uses ``rom.h_box`` or (5, 200).
        warm_start: a previous solution (7 values, 9 with load scales, all p, or an ``IdentificationResult``):
            the population is seeded around it (plus random wolves) and starts with a smaller control
            parameter a.
        estimate_loads: also fit the front/rear bearing heat scale factors (box ``options.load_box``).
        estimate_t0_shift: also fit a uniform shift of ``window.t0`` [°C] (box ``options.t0_shift_box``):
            for a start field that is known only up to a common offset (a service's live state).
        offsets_c: (32,) constant sensor offsets [°C] subtracted from the measurements.
        offset_sd_c: 1σ [°C] (scalar or (32,)) of the offsets still unknown (no baseline: the sensors'
            offset tolerance; after a baseline: its own error): carried in the CIs, with
            ``options.model_error_c``, as a constant bias per channel (``channel_bias_cov``).
        start_cov: (r, r) covariance [°C²] of the error of the reduced start state (a ``ReducedModel``'s
            coordinates; zeros for an exact start): the CIs then also carry that error, and the result's
            ``end_ensemble`` is the window-end state's error (``model.carry``).
        fe: full FE model for an optional re-check of the answer (``fe_check``).
        spec: ``SpindleSpec`` for the test-point channels and the empirical method (None: packaged spindle).
        options: tuning (``IdentifyOptions``).
        prior: a Gaussian prior on ln H (``model.identify_prior``): a MAP fit with the posterior covariance
            and ``prior_dominated`` flags (not for ``"empirical"``); None: the unregularised fit.

    Raises:
        IdentificationError: bad method, window shape, mask, warm start or box.
        InsufficientDataError: fewer than ``min_sensors`` usable channels or ``min_samples`` usable samples.
    """
    started = time.perf_counter()
    opts = options or IdentifyOptions()
    if method not in METHODS:
        raise IdentificationError(f"method: expected one of {', '.join(METHODS)}, got {method!r}")
    basis = getattr(rom, "basis", None)
    meas = _check_window(window, None if basis is None else int(basis.shape[0]))
    if offsets_c is not None:
        off = np.asarray(offsets_c, dtype=float)
        if off.shape != (N_CHANNELS,) or not np.all(np.isfinite(off)):
            raise IdentificationError(
                f"offsets_c: expected {N_CHANNELS} finite values, got shape {off.shape}"
            )
        meas = meas - off[None, :]
    usable = usable_entries(meas, window.mask)
    _check_enough(usable, opts)
    p0 = None if start_cov is None else _start_cov(rom, start_cov)
    layout = Layout(loads=estimate_loads, t0_shift=estimate_t0_shift)
    bounds = _bounds(box or tuple(getattr(rom, "h_box", (5.0, 200.0))), layout, opts)
    kwargs: dict[str, Any] = {
        "inputs": window.inputs,
        "measured_c": meas,
        "usable": usable,
        "t0": window.t0,
        "bounds": bounds,
        "layout": layout,
    }
    if p0 is not None and opts.start_modes > 0:
        directions, p0 = split_start_cov(p0, opts.start_modes)
        problem: Problem = StartFitProblem(rom, directions=directions, noise_c=opts.start_noise_c, **kwargs)
    else:
        problem = Problem(rom, **kwargs)
    generator = as_rng(rng)
    x0 = _warm_vector(warm_start, layout, bounds)
    spec = _spec_or_default(spec)
    population = None
    if method == "empirical":
        theta, message = _empirical(window, spec, bounds)
    elif method == "hybrid":
        theta, message, population = _hybrid(problem, generator, x0, opts, prior)
    else:
        theta, message, population = _metaheuristic(problem, method, generator, x0, opts, prior)
    nfev = problem.nfev
    bias_sd = _bias_sd(offset_sd_c, opts.model_error_c)
    result = _assemble(
        problem,
        theta,
        meas,
        spec,
        method=method,
        message=message,
        nfev=nfev,
        opts=opts,
        start_cov=p0,
        bias_sd=bias_sd,
        prior=None if method == "empirical" else prior,
    )
    result.population = population
    if fe is not None:
        result.fe_check = _fe_check(fe, problem, theta, window)
    result.wall_s = time.perf_counter() - started
    return result


def split_start_cov(cov: Array, k: int) -> tuple[Array, Array]:
    """The k leading directions of ``cov`` (r, r) [°C²] as columns (r, k) scaled by √eigenvalue (a unit
    Gaussian prior on their coefficients) and the covariance that remains, ``cov`` − U·Uᵀ."""
    lam, vec = np.linalg.eigh(cov)
    top = np.argsort(lam)[::-1][: max(int(k), 0)]
    u = vec[:, top] * np.sqrt(np.maximum(lam[top], 0.0))[None, :]
    rest = cov - u @ u.T
    return np.asarray(u), np.asarray(0.5 * (rest + rest.T))


class StartFitProblem(Problem):
    """The window's problem with the start state also fitted along ``directions`` (r, k) (reduced
    coordinates, coefficients c with a N(0, I) prior).

    The reduced model is linear in its start state for fixed H, so the sensors are T(θ, a₀ + U·c) =
    T(θ, a₀) + Σ c_j·R_j(H) with R_j the free response to u_j (``model.carry.start_responses``), and for each
    candidate the best c is a ridge least squares, c = −(DᵀD + σ²I)⁻¹·Dᵀ·r₀ (D: the responses over the usable
    entries, r₀ the residual from a₀, σ the measurement noise): the coefficients are profiled out
    (variable projection), and the optimizers and the finite-difference Jacobian see H (and the other θ)
    only. ``last_coefficients`` holds c of the last evaluated population.
    """

    def __init__(self, model: Any, *, directions: Array, noise_c: float, **kwargs: Any) -> None:
        super().__init__(model, **kwargs)
        self.directions = np.asarray(directions, dtype=float)
        self.noise_var = float(noise_c) ** 2
        self.last_coefficients = np.zeros((0, self.directions.shape[1]))

    def responses(self, h: Array) -> Array:
        """Sensor responses (k, n_steps + 1, 32) [°C] to the start directions under H (7,): C·Φ·μⁿ·Φᵀ·u_j
        (as ``model.carry.start_responses``, in one matrix product)."""
        rom: Any = self.model  # a ReducedModel (checked by ``_start_cov``)
        md = rom_modal.modes(rom.k0, rom.k_zone, np.asarray(h, dtype=float).reshape(1, N_H))
        dt, n = float(self.inputs.dt_s), len(self.inputs.ambient_c)
        mu, _ = rom_modal.step_factors(md.lam, dt, float(rom.theta), int(getattr(rom, "substeps", 1)))
        phi = md.phi[0]
        powers = rom_modal.power_table(mu, n)[:, 0, :]  # (n+1, r)
        coeff = phi.T @ self.directions  # (r, k)
        gain_t = (np.asarray(rom.sensors) @ phi).T  # (r, 32)
        modal = powers[:, None, :] * coeff.T[None, :, :]  # (n+1, k, r)
        return np.ascontiguousarray(np.swapaxes(modal @ gain_t, 0, 1))  # (k, n+1, 32)

    def predict(self, theta: Array) -> Array:
        theta = np.atleast_2d(theta)
        base = super().predict(theta)
        out = base.copy()
        k = self.directions.shape[1]
        coeffs = np.zeros((len(theta), k))
        for i in range(len(theta)):
            resp = self.responses(theta[i, :N_H])  # (k, n+1, 32)
            d = self.select(resp)  # (k, m)
            r0 = self.select(base[i : i + 1])[0] - self._target
            c = -np.linalg.solve(d @ d.T + self.noise_var * np.eye(k), d @ r0)
            out[i] += np.tensordot(c, resp, axes=1)
            coeffs[i] = c
        self.last_coefficients = coeffs
        return out


def _bias_sd(offset_sd_c: ArrayLike | None, model_error_c: float) -> Array | None:
    """Per-channel 1σ [°C] of the constant biases carried in the CIs, or None when there are none."""
    sd = (
        np.zeros(N_CHANNELS)
        if offset_sd_c is None
        else np.broadcast_to(np.asarray(offset_sd_c, float), (N_CHANNELS,))
    )
    if not np.all(np.isfinite(sd)) or np.any(sd < 0):
        raise IdentificationError("offset_sd_c: expected finite values >= 0 °C (a scalar or 32)")
    total = np.sqrt(sd**2 + float(model_error_c) ** 2)
    return total if np.any(total > 0) else None


def _start_cov(rom: Any, start_cov: ArrayLike) -> Array:
    k0 = getattr(rom, "k0", None)
    if k0 is None or not hasattr(rom, "simulate_state"):
        raise IdentificationError("start_cov: needs a reduced model (model.rom.ReducedModel)")
    try:
        return check_cov(start_cov, int(np.shape(k0)[0]))
    except CarryError as err:
        raise IdentificationError(str(err)) from err


def _check_enough(usable: Any, opts: IdentifyOptions) -> None:
    if usable.sensors < opts.min_sensors:
        raise InsufficientDataError(
            f"window.mask: {usable.sensors} usable channels, at least {opts.min_sensors} needed"
        )
    if usable.samples < opts.min_samples:
        raise InsufficientDataError(
            f"window.measured_c: {usable.samples} usable samples after t0, at least {opts.min_samples} needed"
        )


def _assemble(
    problem: Problem,
    theta: Array,
    meas: Array,
    spec: Any,
    *,
    method: str,
    message: str,
    nfev: int,
    opts: IdentifyOptions,
    start_cov: Array | None = None,
    bias_sd: Array | None = None,
    prior: HPrior | None = None,
) -> IdentificationResult:
    jac, r = problem.jacobian(theta)
    info = None if prior is None else prior.information(theta)
    conf, normal = confidence(jac, r, prior_information=info), None
    if info is not None:  # the MAP estimate's normal matrix: its gain is (JᵀJ + σ²P)⁻¹·Jᵀ
        normal = jac.T @ jac + conf.sigma_c**2 * info
    if bias_sd is not None:  # before the carry: the end ensemble must carry the biases' H error too
        bias = channel_bias_cov(jac, problem.channels, bias_sd, normal=normal)
        conf = with_cov(conf.sigma_c, conf.cov + bias)
    ensemble = None
    if start_cov is not None:
        carried = carry(problem, theta, jac, conf.cov, start_cov, normal=normal)
        conf, ensemble = with_cov(conf.sigma_c, carried.cov), carried.ensemble
    f = float(np.mean(r * r))
    pred = problem.predict(theta[None, :])[0]
    lo, hi = _interval(theta, conf.half_width, problem.layout)
    h = theta[:N_H]
    rel = conf.half_width[:N_H] / np.maximum(np.abs(h), 1e-12)  # z·σ(log H), delta method
    at_bound = _at_bound(h, problem.bounds[:N_H], opts.bound_rel_tol)
    dominated = np.zeros(N_H, dtype=bool)
    if prior is not None:
        dominated = prior.dominated(np.diag(conf.cov)[:N_H] / np.maximum(h, 1e-12) ** 2)
    used = np.where(problem.usable.entries, meas, np.nan)  # masked-out channels and NaNs excluded
    lay = problem.layout
    loads, shift = lay.load_scale(theta), lay.shift(theta)
    return IdentificationResult(
        h=h.copy(),
        h_ci95=np.column_stack([lo[:N_H], hi[:N_H]]),
        identified=np.asarray((rel <= opts.ci_threshold) & ~at_bound & ~dominated),
        correlation=conf.correlation[:N_H, :N_H].copy(),
        load_scale=None if loads is None else loads.copy(),
        f=f,
        fit=1.0 / (1.0 + f),
        rmse_per_sensor=per_sensor_rmse(pred, used),
        test_points=point_errors(pred, used, _test_channels(spec)),
        nfev=nfev,
        wall_s=0.0,
        method=method,
        message=message if shift is None else f"{message}; start field offset {float(shift):+.3f} °C",
        load_scale_ci95=None if loads is None else np.column_stack([lo[N_H : N_H + 2], hi[N_H : N_H + 2]]),
        sigma_c=conf.sigma_c,
        t0_shift_c=None if shift is None else float(shift),
        t0_shift_ci95=None if shift is None else np.array([lo[-1], hi[-1]]),
        end_ensemble=ensemble,
        theta=theta.copy(),
        at_bound=at_bound,
        prior_dominated=dominated,
        prior_source=None if prior is None else prior.source,
    )


def _interval(theta: Array, half_width: Array, layout: Layout) -> tuple[Array, Array]:
    """95 % bounds of θ: H and the load scales (positive) from the covariance of their logarithm (delta
    method, σ(log x) = σ(x)/x): x·e^(∓zσ(log x)), asymmetric and > 0; the start-field shift linear."""
    lo, hi = theta - half_width, theta + half_width
    n_pos = N_H + (2 if layout.loads else 0)
    x = theta[:n_pos]
    z_sd_log = half_width[:n_pos] / np.maximum(np.abs(x), 1e-12)
    with np.errstate(over="ignore", under="ignore"):  # a hopeless H: [0, inf), honestly unbounded
        lo[:n_pos], hi[:n_pos] = x * np.exp(-z_sd_log), x * np.exp(z_sd_log)
    return lo, hi


def _at_bound(h: Array, bounds: Array, rel_tol: float) -> NDArray[np.bool_]:
    """(7,) True where H lies within ``rel_tol`` × box width of its lower or upper bound."""
    tol = rel_tol * (bounds[:, 1] - bounds[:, 0])
    return np.asarray((h <= bounds[:, 0] + tol) | (h >= bounds[:, 1] - tol))


def _test_channels(spec: Any) -> Mapping[int, int]:
    channels = getattr(spec, "test_point_channels", None)
    return dict(channels) if channels else {}


def _fe_check(fe: Any, problem: Problem, theta: Array, window: Window) -> dict[str, float]:
    from model.fem import simulate_sensors

    loads = problem.layout.load_scale(theta)
    scale = (1.0, 1.0) if loads is None else (float(loads[0]), float(loads[1]))
    sens, _ = simulate_sensors(fe, theta[:N_H], window.inputs, problem.start(theta), load_scale=scale)
    rom_pred = problem.predict(theta[None, :])[0]
    e = problem.usable.entries
    rmse_fe = float(np.sqrt(np.mean((sens - problem.measured)[e] ** 2)))
    rmse_rom = float(np.sqrt(np.mean((rom_pred - problem.measured)[e] ** 2)))
    return {"rmse_rom_c": rmse_rom, "rmse_fe_c": rmse_fe, "rmse_diff_c": rmse_fe - rmse_rom}
