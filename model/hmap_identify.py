"""Identification of the H map θ (``model.hmap``) from a window in which the speed changes any number of
times.

MAP estimate: minimise

    Σ_usable (T_model(θ) − T_measured)² / σ²  +  (θ − μ₀)ᵀ Σ₀⁻¹ (θ − μ₀)

with the reduced model evaluated segment by segment (``model.rom_segments``: H_s = F(n_s, Ti_s; θ) for each
constant-speed segment), started at the prior mean, by bounded Levenberg–Marquardt on the normal equations
(default; ``method="trf"`` runs scipy's bounded TRF, as ``model.identify``'s hybrid polish: same optimum,
but its SVD of the whole m×p Jacobian per iteration costs as much as a model run). The Jacobian is exact:
the tangent-linear model of the reduced θ-method times dH/dθ of the family (``Family.log_h_jacobian``).
The prior is a regularisation term, so directions that the window does not determine stay at the prior.
Posterior covariance (Laplace / Gauss–Newton at the optimum): Σ = (JᵀJ/σ̂² + Σ₀⁻¹)⁻¹ with
σ̂ = max(σ, RMS residual), so a fit worse than the noise widens the bands.

Chaining: the posterior of one window, passed through ``forget`` for the time elapsed, is the next window's
prior. ``forget`` decays the information exponentially toward the cold-start prior's information::

    Λ' = e^(−Δt/τ)·Λ + (1 − e^(−Δt/τ))·Λ₀,    Λ = Σ⁻¹,  mean kept

so a direction no window determines relaxes back to the cold-start uncertainty (never wider), and a direction
that was determined loses half its information in τ·ln 2 (τ = 4 h by default: a change of the machine, e.g. a
new lubricant state, is followed within a shift).

Errors::

    HMapIdentifyError(ValueError)   bad window, prior or option (the field is named)
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from types import SimpleNamespace
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

from model import rom_segments
from model.errors import ModelError
from model.hmap import DEFAULT_FAMILY, T_REF_C, Family, Gaussian

Array = NDArray[np.float64]
N_CHANNELS = 32
DEFAULT_TAU_H = 4.0
RELINEARISE = 0.05  # ln H: re-linearise the start modes' response when θ moved more than this


class HMapIdentifyError(ModelError, ValueError):
    """The map identification cannot run as asked; the message names the field."""


@dataclass(frozen=True)
class SpeedWindow:
    """Data of one map identification.

    inputs: ``model.inputs.InputSeries`` (n_steps; entry k applies on step k → k+1); speed_rpm: (n_steps,)
    the speed on each step [rpm] (sets the segments); measured_c: (n_steps+1, 32) [°C], NaN = missing;
    mask: (32,) bool usable channels; t0: uniform start [°C] or (N,) start field of the fitted model's mesh.
    """

    inputs: Any
    speed_rpm: Array
    measured_c: Array
    mask: NDArray[np.bool_]
    t0: float | Array


@dataclass(frozen=True)
class MapOptions:
    """Tuning: ``sigma_c`` the assumed measurement noise [°C] that weighs the data against the prior;
    ``max_nfev`` iterations (LM) or evaluations (TRF); ``tol`` TRF's ftol/xtol/gtol; ``method`` "lm" or
    "trf"; LM: start damping, stop when an accepted step lowers χ² by less than ``chi2_tol`` or moves θ by
    less than ``step_tol``; ``level_first`` (physics family only): first fit the levels with the crossovers
    held, ``level_nfev`` iterations."""

    sigma_c: float = 0.15
    max_nfev: int = 60
    tol: float = 1e-6
    level_first: bool = True
    level_nfev: int = 8
    method: str = "lm"
    lm_damping: float = 1e-2
    chi2_tol: float = 0.1
    step_tol: float = 1e-4


@dataclass(frozen=True)
class MapFit:
    """Result: ``posterior`` (θ mean and covariance), the ``prior`` it used, ``sigma_c`` the noise level used
    for the covariance [°C], ``rmse_c`` the fit's RMS residual [°C], the visited speeds [rpm] and seconds
    spent at each, the window-end field (N,) [°C] of the fitted model (the next window's start), counts and
    wall time [s]."""

    posterior: Gaussian
    prior: Gaussian
    family: Family
    sigma_c: float
    rmse_c: float
    visited_rpm: Array
    visited_s: Array
    end_field_c: Array = field(repr=False)
    nfev: int = 0
    wall_s: float = 0.0
    message: str = ""

    def h_at(self, speed_rpm: Any, ambient_c: Any = T_REF_C) -> tuple[Array, Array, Array]:
        """H and its 95 % band (each (S, 7) [W/(m²·K)]) at speeds [rpm] and ambient [°C]."""
        return self.family.h_ci95_at(self.posterior.mean, self.posterior.cov, speed_rpm, ambient_c)


def _check(window: SpeedWindow, rom: Any) -> tuple[Array, NDArray[np.bool_]]:
    n = int(np.asarray(window.inputs.ambient_c).shape[0])
    meas = np.asarray(window.measured_c, dtype=np.float64)
    if meas.shape != (n + 1, N_CHANNELS):
        raise HMapIdentifyError(
            f"window.measured_c: expected shape ({n + 1}, {N_CHANNELS}), got {meas.shape}"
        )
    if np.asarray(window.speed_rpm).shape != (n,):
        raise HMapIdentifyError(f"window.speed_rpm: expected shape ({n},), got {np.shape(window.speed_rpm)}")
    mask = np.asarray(window.mask)
    if mask.shape != (N_CHANNELS,) or mask.dtype != bool:
        raise HMapIdentifyError(f"window.mask: expected ({N_CHANNELS},) bool, got {mask.shape} {mask.dtype}")
    usable = np.isfinite(meas) & mask[None, :]
    usable[0] = False
    if usable.sum() < 30:
        raise HMapIdentifyError(f"window.measured_c: {int(usable.sum())} usable entries, at least 30 needed")
    return meas, usable


class _Objective:
    """Whitened MAP residuals and their exact Jacobian; one model run per distinct θ, its tangents when the
    Jacobian is asked for."""

    def __init__(
        self,
        rom: Any,
        window: SpeedWindow,
        prior: Gaussian,
        family: Family,
        data: tuple[Array, NDArray[np.bool_]],
        sigma: float,
        bias_sd: Array | None = None,
        start_modes: Array | None = None,
        x0: Array | None = None,
    ) -> None:
        meas, usable = data
        self.rom, self.window, self.sigma, self.family = rom, window, sigma, family
        self.plan = rom_segments.plan_from_speed(window.speed_rpm)
        self.speeds = np.abs(np.asarray(window.speed_rpm, dtype=np.float64)[self.plan.start])
        self.ambients = rom_segments.segment_means(self.plan, window.inputs.ambient_c)
        self.flat = np.flatnonzero(usable.ravel())
        self.target = meas.ravel()[self.flat]
        chol = np.linalg.cholesky(prior.cov)
        self.whiten = np.linalg.solve(chol, np.eye(chol.shape[0]))  # C⁻¹ with Σ₀ = C·Cᵀ
        self.mu0 = prior.mean
        self.p = prior.mean.size
        # nuisance parameters, linear with Gaussian priors N(0, sd²): constant per-channel biases of the
        # channels with data, then the start state's coefficients along ``start_modes``
        channel = self.flat % N_CHANNELS
        sd = np.zeros(N_CHANNELS) if bias_sd is None else bias_sd
        self.bias_ch = np.flatnonzero((sd > 0) & np.isin(np.arange(N_CHANNELS), channel))
        col = {c: i for i, c in enumerate(self.bias_ch)}
        bias_jac = np.zeros((self.flat.size, self.bias_ch.size))
        rows = np.flatnonzero(np.isin(channel, self.bias_ch))
        bias_jac[rows, [col[c] for c in channel[rows]]] = 1.0
        self._bias_jac, self._bias_sd = bias_jac, sd[self.bias_ch]
        self.modes = np.zeros((0, 0)) if start_modes is None else np.atleast_2d(start_modes)
        self.mode_end = np.zeros((self.modes.shape[0], rom.k0.shape[0]))
        self.bias_jac, self.bias_sd = bias_jac, self._bias_sd
        self._key: bytes = b""
        self._val: tuple[Array, Array, NDArray[np.intp], rom_segments.Tangents] | None = None
        # θ, H, the states and operators, the residuals of the last run
        self._run: tuple[bytes, Array, tuple[Array, rom_segments.Operators], Array] | None = None
        self._nuis: tuple[tuple[float, int], Array, Array] | None = None
        self.runs = 0
        self.runs_start = 0  # start-mode responses computed (the nuisance Jacobian's version)
        if self.modes.shape[0]:
            self.set_start_response(np.clip(prior.mean if x0 is None else x0, *family.bounds()))

    def set_start_response(self, theta: Array) -> None:
        """The sensors' response to each start mode (linear, H held at ``theta``): one batched run with
        zero loads and ambient; appended to the nuisance Jacobian (each coefficient's prior N(0, 1))."""
        k = self.modes.shape[0]
        h = self.family.h_at(theta, self.speeds, self.ambients)
        n = self.plan.n_steps
        zero = SimpleNamespace(
            dt_s=self.window.inputs.dt_s, ambient_c=np.zeros(n), q_front_w=np.zeros(n), q_rear_w=np.zeros(n)
        )
        states = rom_segments.simulate_states(
            self.rom, np.broadcast_to(h, (k, *h.shape)), self.plan, zero, self.modes
        )
        resp = (states @ self.rom.sensors.T).reshape(k, -1)[:, self.flat].T  # (m, K)
        self.mode_end = states[:, -1, :]  # (K, r)
        self.bias_jac = np.hstack([self._bias_jac, resp])
        self.bias_sd = np.concatenate([self._bias_sd, np.ones(k)])
        self.runs += 1
        self.runs_start += 1

    @property
    def n_x(self) -> int:
        """θ and the fitted channel biases."""
        return self.p + self.bias_sd.size

    def normal(self, th: Array, sigma: float | None = None) -> tuple[Array, Array, float]:
        """Gauss–Newton normal equations of θ (p, p), (p,) and the χ² at ``th`` (data weighted by
        ``sigma``, default the objective's), with the linear nuisances (biases, start modes) profiled out:
        the Schur complement, i.e. θ's marginal precision at the end."""
        a, g, cost, _ = self.profiled(th, sigma)
        return a, g, cost

    def cost(self, th: Array) -> float:
        """``normal``'s χ² alone: one model run without the tangents (an LM trial that may be rejected)."""
        r_base = self._residual(th[: self.p])
        return self._profile(r_base, th, self.sigma)[3]

    def _nuisance(self, sig: float) -> tuple[Array, Array]:
        """The nuisances' whitened Jacobian (m, q) and normal matrix (q, q) at ``sig`` (kept until the
        start modes' response changes)."""
        key = (sig, self.runs_start)
        if self._nuis is None or self._nuis[0] != key:
            ns = self.bias_jac / sig
            self._nuis = (key, ns, ns.T @ ns + np.diag(1.0 / self.bias_sd**2))
        return self._nuis[1], self._nuis[2]

    def _profile(self, r_base: Array, th: Array, sig: float) -> tuple[Array, Array, Array, float]:
        """(whitened data residuals with the nuisances at their optimum, whitened prior residual, c*(θ),
        χ²)."""
        rs = r_base / sig
        pr = self.whiten @ (th[: self.p] - self.mu0)
        c: Array = np.zeros(self.bias_sd.size)
        if c.size:
            ns, ann = self._nuisance(sig)
            c = np.asarray(-np.linalg.solve(ann, ns.T @ rs), dtype=np.float64)
            rs = rs + ns @ c
        cost = float(rs @ rs + pr @ pr + np.sum((c / self.bias_sd) ** 2))
        return rs, pr, c, cost

    def profiled(self, th: Array, sigma: float | None = None) -> tuple[Array, Array, float, Array]:
        """``normal``'s (A, g, χ²) and the nuisances' optimum c*(θ) (q,). The Jacobian's columns of the
        directions that move no segment's H are zero: the products run over the others only."""
        sig = self.sigma if sigma is None else sigma
        r_base, j_act, act, _ = self._eval_tangents(th[: self.p])
        rs, pr, c, cost = self._profile(r_base, th, sig)
        js = j_act / sig
        blk = np.ix_(act, act)
        a = self.whiten.T @ self.whiten
        a[blk] += js.T @ js
        if c.size:
            ns, ann = self._nuisance(sig)
            a_tn = js.T @ ns
            a[blk] -= a_tn @ np.linalg.solve(ann, a_tn.T)
        g = self.whiten.T @ pr
        g[act] += js.T @ rs
        return a, g, cost, c

    def _residual(self, th: Array) -> Array:
        """Model minus measured at the usable entries (m,) (the run's states kept for its tangents)."""
        key = th.tobytes()
        if self._run is None or self._run[0] != key:
            h = self.family.h_at(th, self.speeds, self.ambients)  # (S, 7)
            run = rom_segments.simulate_run(self.rom, h[None], self.plan, self.window.inputs, self.window.t0)
            r = (run[0][0] @ self.rom.sensors.T).ravel()[self.flat] - self.target
            self._run, self.runs = (key, h, run, r), self.runs + 1
        return self._run[3]

    def _eval_tangents(self, th: Array) -> tuple[Array, Array, NDArray[np.intp], rom_segments.Tangents]:
        """(residuals (m,), the Jacobian's columns (m, J) of the directions ``act`` (J,) that move some
        segment's H, the run); the other columns are zero."""
        key = th.tobytes()
        if self._val is None or self._key != key:
            r = self._residual(th)
            assert self._run is not None
            h, run = self._run[1], self._run[2]
            dh = np.moveaxis(self.family.h_jacobian(th, self.speeds, self.ambients), 2, 0)  # (p, S, 7)
            act = np.flatnonzero(np.any(dh != 0.0, axis=(1, 2)))
            tg = rom_segments.simulate_tangents(
                self.rom, h, dh[act], self.plan, self.window.inputs, self.window.t0, run=run
            )
            j = tg.d_sensors.reshape(act.size, -1)[:, self.flat].T
            self._key, self._val = key, (r, j, act, tg)
        assert self._val is not None
        return self._val

    def _eval_base(self, th: Array) -> tuple[Array, Array, rom_segments.Tangents]:
        """Residuals (m,), the full Jacobian (m, p) and the run at θ ``th``."""
        r, j_act, act, tg = self._eval_tangents(th)
        j = np.zeros((r.size, self.p))
        j[:, act] = j_act
        return r, j, tg

    def _eval(self, x: Array) -> tuple[Array, Array, rom_segments.Tangents]:
        r, j, tg = self._eval_base(x[: self.p])
        if self.bias_sd.size:
            r = r + self.bias_jac @ x[self.p :]
            j = np.hstack([j, self.bias_jac])
        return r, j, tg

    def fun(self, x: Array) -> Array:
        r, _, _ = self._eval(x)
        prior = self.whiten @ (x[: self.p] - self.mu0)
        return np.concatenate([r / self.sigma, prior, x[self.p :] / self.bias_sd])

    def prior_jac(self) -> Array:
        """d(whitened prior residuals)/dx: block-diagonal (θ's prior, the biases' 1/σ)."""
        out = np.zeros((self.n_x, self.n_x))
        out[: self.p, : self.p] = self.whiten
        out[self.p :, self.p :] = np.diag(1.0 / self.bias_sd)
        return out

    def jac(self, x: Array) -> Array:
        _, j, _ = self._eval(x)
        return np.vstack([j / self.sigma, self.prior_jac()])


def identify_map(
    rom: Any,
    window: SpeedWindow,
    prior: Gaussian,
    *,
    family: Family = DEFAULT_FAMILY,
    options: MapOptions | None = None,
    bias_sd_c: Any = None,
    start_modes: Any = None,
    x0: Any = None,
) -> MapFit:
    """MAP fit of θ (``family.n_theta``,) to ``window`` with the reduced model ``rom`` and prior ``prior``
    (a cold start: ``family.prior(spec)``; later: ``forget(previous.posterior, cold, ...)``).

    ``bias_sd_c`` (scalar or (32,) °C, None: none): 1σ of a constant per-channel bias (the sensor offsets
    still unknown after a baseline, the reduced model's error at the sensor); each used channel's bias is
    fitted jointly with θ under that Gaussian prior and marginalised out of the posterior, so a bias is not
    read as H (a 0.03 °C offset error, a 30-sample baseline's, moved H5 by 40 % without; docs/design/hmap.md).
    ``start_modes`` (K, r) reduced directions of the start state's error (e.g. a filtered state's leading
    eigenvectors scaled by √eigenvalue): their coefficients (prior N(0, 1)) are fitted too, the response
    linearised at the start and again at the optimum if θ moved more than ``RELINEARISE``, then
    marginalised out of the posterior. ``x0``: where the iteration starts (default the prior mean; a
    chained service fit starts from the newest posterior's mean, minutes old, while its prior is an
    older one: fewer model runs, the same optimum).

    Raises HMapIdentifyError for a bad window (shapes, mask, too few usable entries), prior or option.
    """
    started = time.perf_counter()
    opts = options or MapOptions()
    if not (np.isfinite(opts.sigma_c) and opts.sigma_c > 0):
        raise HMapIdentifyError(f"options.sigma_c: must be > 0 °C, got {opts.sigma_c}")
    if opts.method not in ("lm", "trf"):
        raise HMapIdentifyError(f"options.method: expected 'lm' or 'trf', got {opts.method!r}")
    meas, usable = _check(window, rom)
    if prior.mean.shape != (family.n_theta,):
        raise HMapIdentifyError(
            f"prior.mean: expected {family.n_theta} values for {family.kind!r}, got {prior.mean.shape}"
        )
    bias = None
    if bias_sd_c is not None:
        bias = np.broadcast_to(np.asarray(bias_sd_c, dtype=np.float64), (N_CHANNELS,)).copy()
        if not np.all(np.isfinite(bias)) or np.any(bias < 0):
            raise HMapIdentifyError("bias_sd_c: expected finite values >= 0 °C (a scalar or 32)")
    modes = None
    if start_modes is not None:
        modes = np.atleast_2d(np.asarray(start_modes, dtype=np.float64))
        if modes.shape[1] != rom.k0.shape[0] or not np.all(np.isfinite(modes)):
            raise HMapIdentifyError(f"start_modes: expected (K, {rom.k0.shape[0]}) finite, got {modes.shape}")
    lo, hi = family.bounds()
    start = prior.mean if x0 is None else family.check_theta(x0, "x0")
    if start.shape != prior.mean.shape:
        raise HMapIdentifyError(f"x0: expected shape {prior.mean.shape}, got {start.shape}")
    x0 = np.clip(start, lo + 1e-9, hi - 1e-9)
    obj = _Objective(rom, window, prior, family, (meas, usable), opts.sigma_c, bias, modes, x0)
    nb = obj.bias_sd.size
    if nb and (opts.method == "trf" or family.kind == "physics"):
        raise HMapIdentifyError("bias_sd_c, start_modes: only with method 'lm' and the 'nodes' family")
    if opts.level_first and family.kind == "physics":
        x0 = _levels_first(obj, x0, lo, hi, opts)
    if opts.method == "trf":
        sol = least_squares(
            obj.fun, x0, jac=obj.jac, bounds=(lo, hi), method="trf", x_scale="jac",
            ftol=opts.tol, xtol=opts.tol, gtol=opts.tol, max_nfev=opts.max_nfev,
        )  # fmt: skip
        x, message = np.asarray(sol.x), f"TRF: {sol.message}"
    else:
        x, message = _levenberg_marquardt(obj, x0, lo, hi, opts)
        if obj.modes.shape[0] and np.max(np.abs(x - x0)) > RELINEARISE:
            obj.set_start_response(x)  # the start modes' response at the optimum's H, and polish
            x, message = _levenberg_marquardt(obj, x, lo, hi, opts)
    r_base, _, _, tg = obj._eval_tangents(x)
    c = obj.profiled(x)[3]
    r = r_base + (obj.bias_jac @ c if nb else 0.0)
    rmse = float(np.sqrt(np.mean(r**2)))
    sigma = max(opts.sigma_c, rmse)
    info, _, _ = obj.normal(x, sigma)
    cov = np.linalg.inv(info)  # θ's marginal precision's inverse: the nuisances integrated out
    visited, seconds = _visited(window)
    return MapFit(
        posterior=Gaussian(x, 0.5 * (cov + cov.T)),
        prior=prior,
        family=family,
        sigma_c=sigma,
        rmse_c=rmse,
        visited_rpm=visited,
        visited_s=seconds,
        end_field_c=np.asarray(rom.lift(tg.states[-1] + c[obj._bias_sd.size :] @ obj.mode_end)),
        nfev=obj.runs,
        wall_s=time.perf_counter() - started,
        message=f"{message} ({obj.runs} model runs)",
    )


def _levenberg_marquardt(
    obj: _Objective,
    x0: Array,
    lo: Array,
    hi: Array,
    opts: MapOptions,
    *,
    free: NDArray[np.intp] | None = None,
    max_iter: int | None = None,
) -> tuple[Array, str]:
    """Bounded Levenberg–Marquardt on the normal equations over the parameters ``free`` (default all):
    Marquardt's diagonal scaling, steps projected on the bounds, stop when an accepted step lowers χ² by
    less than ``chi2_tol`` (the residuals are whitened, so that is a change far inside the posterior) or
    moves θ by less than ``step_tol``. One model run per trial gives its χ²; the exact Jacobian (the
    tangents) is run only for a step taken (a rejected trial needs none); the normal equations are p×p,
    where scipy's TRF takes an SVD of the whole m×p Jacobian per iteration (as costly as a model run
    here)."""
    idx = np.arange(x0.size) if free is None else free
    x = x0.copy()
    a_full, g_full, cost = obj.normal(x)
    damping = opts.lm_damping
    n_iter = opts.max_nfev if max_iter is None else max_iter
    for it in range(n_iter):
        a, g = a_full[np.ix_(idx, idx)], g_full[idx]
        step = np.linalg.solve(a + damping * np.diag(np.maximum(np.diag(a), 1e-12)), -g)
        trial = x.copy()
        trial[idx] = np.clip(x[idx] + step, lo[idx], hi[idx])
        cost_t = obj.cost(trial)  # the tangents only for a step taken
        if cost_t >= cost:
            damping *= 4.0
            if damping > 1e8:
                return x, f"LM: no further decrease after {it + 1} iterations"
            continue
        a_t, g_t, cost_t = obj.normal(trial)
        gain = cost - cost_t  # decrease of χ²
        x, a_full, g_full, cost = trial, a_t, g_t, cost_t
        damping = max(damping / 3.0, 1e-7)
        if gain < opts.chi2_tol or np.max(np.abs(step)) < opts.step_tol:
            return x, f"LM: converged in {it + 1} iterations"
    return x, f"LM: stopped after {n_iter} iterations"


def _levels_first(obj: _Objective, x0: Array, lo: Array, hi: Array, opts: MapOptions) -> Array:
    """A start for the full fit: only the levels l0, l1 fitted with the crossovers held (a better
    conditioned 14-parameter problem; the crossovers are the weakly determined, nonlinear part)."""
    idx = np.flatnonzero(np.arange(x0.size) % 3 != 2)
    x, _ = _levenberg_marquardt(
        obj, x0, lo, hi, replace(opts, chi2_tol=1.0), free=idx, max_iter=opts.level_nfev
    )
    return x


def predict(rom: Any, window: SpeedWindow, thetas: Any, *, family: Family = DEFAULT_FAMILY) -> Array:
    """Sensors (P, n_steps+1, 32) [°C] of the reduced model over ``window`` for a population θ (P, p): H per
    segment from the family at the segment's speed and mean ambient (no fit)."""
    plan = rom_segments.plan_from_speed(window.speed_rpm)
    speeds = np.abs(np.asarray(window.speed_rpm, dtype=np.float64)[plan.start])
    ambients = rom_segments.segment_means(plan, window.inputs.ambient_c)
    theta = family.check_theta(np.atleast_2d(thetas))
    return rom_segments.simulate_sensors(
        rom, family.h_at(theta, speeds, ambients), plan, window.inputs, window.t0
    )


def _visited(window: SpeedWindow) -> tuple[Array, Array]:
    speeds = np.abs(np.asarray(window.speed_rpm, dtype=np.float64))
    uniq, inv = np.unique(speeds, return_inverse=True)
    return uniq, np.bincount(inv).astype(np.float64) * float(window.inputs.dt_s)


def forget(
    posterior: Gaussian, cold: Gaussian, *, elapsed_h: float, tau_h: float = DEFAULT_TAU_H
) -> Gaussian:
    """The next window's prior: information decayed toward the cold-start prior's over ``elapsed_h`` hours,
    Λ' = λΛ + (1−λ)Λ₀ with λ = e^(−elapsed/τ); the mean is kept. Never wider than the cold start."""
    if not (np.isfinite(elapsed_h) and elapsed_h >= 0):
        raise HMapIdentifyError(f"elapsed_h: must be >= 0 h, got {elapsed_h}")
    if not (np.isfinite(tau_h) and tau_h > 0):
        raise HMapIdentifyError(f"tau_h: must be > 0 h, got {tau_h}")
    lam = float(np.exp(-elapsed_h / tau_h))
    info = lam * np.linalg.inv(posterior.cov) + (1.0 - lam) * np.linalg.inv(cold.cov)
    cov = np.linalg.inv(info)
    return Gaussian(posterior.mean.copy(), 0.5 * (cov + cov.T))
