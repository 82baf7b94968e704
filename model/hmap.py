"""H as a function of the operating condition: a parametric family per zone, H_i = F_i(n, Ti; θ_i).

Family (the same form for every zone, three parameters θ_i = (a_i, m_i, c_i))::

    H_i(n, Ti) = exp(a_i) · (1 + (n / n_c,i)²)^(m_i / 2) · A_i(Ti),    n_c,i = exp(c_i) [rpm]

- exp(a) [W/(m²·K)] is the standstill level: natural convection (Churchill–Chu) when the shaft is at rest;
- for n ≫ n_c the law is the forced-convection power law H ∝ n^m, i.e. Nu = C·Re^m (rotating surfaces,
  Bejan, *Convection Heat Transfer*, 4th ed., ch. 7: laminar m = 1/2, turbulent m = 4/5) or, for the
  annular air gap, Nu ∝ Ta^(m/2) with Ta ∝ n² (Becker & Kaye 1962: Nu = 0.409·Ta^0.241 above Ta ≈ 1e4,
  so m ≈ 0.48);
- the two regimes are joined by a Churchill–Usagi blend (Churchill & Usagi, AIChE J. 18, 1972) with
  exponent 2 in n; n_c is the crossover speed where the forced part equals the standstill level;
- A(Ti) carries the ambient through the air properties at the film temperature (no extra parameter):
  H ∝ λ·ν^(−m), so A = (λ(Ti)/λ(T_ref))·(ν(T_ref)/ν(Ti))^m with ``model.empirical.air_properties``
  (about −0.03 %/K for m = 1/2: physics says the ambient barely matters over a ±1 °C drift).

The sign of m is left free (bounded in [−2, 2]): the identified H are *effective* coefficients referred to
the single ambient Ti (docs/model.md), and an air gap that warms with speed makes the effective H fall with
speed even though the true film coefficient rises. Stationary surfaces (H7) get the prior m = 0.

Priors (cold start, ``prior_from_empirical``): the mean is the family's least-squares fit, in log H, to the
physics curve of the zone over 0..7000 rpm (``model.empirical.empirical_h`` for H1–H5 and H7; H6, which
``model.empirical`` treats as still air, gets Becker–Kaye of the central annulus with the natural floor),
with a weak pull to the physical exponent and crossover so that a flat curve still gives a unique fit;
the spread is wide (σ 1.5 in a, 0.75 in m, 2.5 in c: a factor 4.5 in H at 1σ).

The family does not contain the virtual plant's ``h_true`` (a tanh in n, saturating at both ends): the best
fit over 0..7000 rpm leaves a model-form error measured by ``model_form_error`` (docs/hmap.md).

Errors::

    HMapError(ValueError)   bad θ, covariance, speed or ambient shape (the argument is named)
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import least_squares

from model.empirical import air_properties, empirical_h

Array = NDArray[np.float64]

N_ZONES = 7
N_PER_ZONE = 3  # (a, m, c)
N_THETA = N_ZONES * N_PER_ZONE
T_REF_C = 20.0  # reference ambient of the family [°C]
FILM_RISE_K = 10.0  # assumed surface rise for the film temperature (as model.empirical)
SPEED_MAX_RPM = 7000.0
Z95 = 1.959963984540054
N_REF_RPM = 3500.0  # the reference speed of the second level parameter
PRIOR_SD = (1.5, 1.5, 2.0)  # σ of l0, l1 [ln W/(m²K)] and c [ln rpm] at a cold start
BOUNDS = ((np.log(0.5), np.log(500.0)), (np.log(0.5), np.log(500.0)), (np.log(30.0), np.log(1e5)))
STATIONARY = (False, False, False, False, False, False, True)  # H7: natural convection only
AMBIENT_EXPONENT = (0.5, 0.5, 0.5, 0.5, 0.5, 0.5, 0.0)  # m in the air-property factor ν^(-m)
BECKER_KAYE_TA_C = 1708.0


class HMapError(ValueError):
    """A bad argument to the H map; the message names it."""


@dataclass(frozen=True)
class Gaussian:
    """A Gaussian over θ (21,): ``mean`` (21,), ``cov`` (21, 21); θ = (a, m, c) of H1, then H2, ..."""

    mean: Array
    cov: Array

    def __post_init__(self) -> None:
        check_theta(self.mean, "mean")
        check_cov(self.cov)


def check_theta(theta: ArrayLike, name: str = "theta") -> Array:
    """θ as a float array (..., 21) or HMapError naming ``name``."""
    t = np.asarray(theta, dtype=np.float64)
    if t.ndim == 0 or t.shape[-1] != N_THETA or not np.all(np.isfinite(t)):
        raise HMapError(f"{name}: expected (..., {N_THETA}) finite values, got shape {t.shape}")
    return t


def check_cov(cov: ArrayLike) -> Array:
    """A symmetric positive semi-definite (21, 21) covariance, or HMapError."""
    c = np.asarray(cov, dtype=np.float64)
    if c.shape != (N_THETA, N_THETA) or not np.all(np.isfinite(c)):
        raise HMapError(f"cov: expected ({N_THETA}, {N_THETA}) finite values, got shape {c.shape}")
    if not np.allclose(c, c.T, rtol=1e-8, atol=1e-12) or np.linalg.eigvalsh(0.5 * (c + c.T))[0] < -1e-9:
        raise HMapError("cov: must be symmetric positive semi-definite")
    return c


def bounds() -> tuple[Array, Array]:
    """Lower and upper bounds of θ (21,) each: a in ln(0.5..500) W/(m²K), m in [-2, 2], n_c in 1..1e5 rpm."""
    lo = np.tile([b[0] for b in BOUNDS], N_ZONES)
    hi = np.tile([b[1] for b in BOUNDS], N_ZONES)
    return lo, hi


def _conditions(speed_rpm: ArrayLike, ambient_c: ArrayLike) -> tuple[Array, Array]:
    n = np.abs(np.atleast_1d(np.asarray(speed_rpm, dtype=np.float64)))
    if n.ndim != 1 or not np.all(np.isfinite(n)):
        raise HMapError(f"speed_rpm: expected a scalar or 1-D finite array, got shape {n.shape}")
    ti = np.broadcast_to(np.asarray(ambient_c, dtype=np.float64), n.shape) if np.ndim(ambient_c) else None
    if ti is None:
        ti = np.full(n.shape, float(np.asarray(ambient_c)))
    if not np.all(np.isfinite(ti)):
        raise HMapError("ambient_c: contains non-finite values")
    return n, np.asarray(ti)


def _air_logs(ambient_c: Array) -> tuple[Array, Array]:
    """ln(λ(Ti)/λ(T_ref)) and ln(ν(T_ref)/ν(Ti)) at the film temperatures, per condition."""
    ref = air_properties(T_REF_C + 0.5 * FILM_RISE_K)
    uniq, inv = np.unique(ambient_c, return_inverse=True)
    props = [air_properties(float(t) + 0.5 * FILM_RISE_K) for t in uniq]
    lk = np.array([np.log(p.k_w_mk / ref.k_w_mk) for p in props])[inv]
    lnu = np.array([np.log(ref.nu_m2_s / p.nu_m2_s) for p in props])[inv]
    return lk.reshape(ambient_c.shape), lnu.reshape(ambient_c.shape)


def _split(theta: Array) -> tuple[Array, Array, Array]:
    t = theta.reshape(*theta.shape[:-1], N_ZONES, N_PER_ZONE)
    return t[..., 0], t[..., 1], t[..., 2]


def _g(n: Array, c: Array) -> Array:
    """ln(1 + (n/n_c)²): twice the blend's log-ratio to the standstill level per unit exponent."""
    return np.asarray(np.log1p((n / np.exp(c)) ** 2))


def _dg_dc(n: Array, c: Array) -> Array:
    u2 = (n / np.exp(c)) ** 2
    return np.asarray(-2.0 * u2 / (1.0 + u2))


def shape(speed_rpm: ArrayLike, c: ArrayLike) -> Array:
    """The normalised speed shape s(n; c) = ln(1+(n/n_c)²)/ln(1+(N_REF/n_c)²): 0 at rest, 1 at N_REF."""
    n, cc = np.asarray(speed_rpm, dtype=np.float64), np.asarray(c, dtype=np.float64)
    return _g(n, cc) / _g(np.asarray(N_REF_RPM), cc)


def exponent(theta: ArrayLike, speed_rpm: float = SPEED_MAX_RPM) -> Array:
    """The local speed exponent m = d ln H / d ln n (..., 7) at ``speed_rpm`` (the Nu ∝ Re^m of the law)."""
    l0, l1, c = _split(check_theta(theta))
    u2 = (speed_rpm / np.exp(c)) ** 2
    return np.asarray((l1 - l0) / _g(np.asarray(N_REF_RPM), c) * 2.0 * u2 / (1.0 + u2))


def _ambient_log(ambient_c: Array) -> Array:
    """ln A_i(Ti) (S, 7): air-property factor λ(Ti)/λ(T_ref)·(ν(T_ref)/ν(Ti))^m_i with the physics m_i."""
    lk, lnu = _air_logs(ambient_c)
    return np.asarray(lk[:, None] + np.asarray(AMBIENT_EXPONENT)[None, :] * lnu[:, None])


def log_h(theta: ArrayLike, speed_rpm: ArrayLike, ambient_c: ArrayLike = T_REF_C) -> Array:
    """ln H [ln W/(m²K)] for θ (..., 21) at S conditions: shape (..., S, 7)."""
    t = check_theta(theta)
    n, ti = _conditions(speed_rpm, ambient_c)
    l0, l1, c = (x[..., None, :] for x in _split(t))  # (..., 1, 7)
    s = _g(n[:, None], c) / _g(np.asarray(N_REF_RPM), c)
    return np.asarray(l0 + (l1 - l0) * s + _ambient_log(ti))


def h_at(theta: ArrayLike, speed_rpm: ArrayLike, ambient_c: ArrayLike = T_REF_C) -> Array:
    """H1..H7 [W/(m²·K)] for θ (21,) at speeds (S,) [rpm] and ambient(s) [°C]: (S, 7); θ (P, 21) gives
    (P, S, 7)."""
    return np.exp(log_h(theta, speed_rpm, ambient_c))


def log_h_jacobian(theta: ArrayLike, speed_rpm: ArrayLike, ambient_c: ArrayLike = T_REF_C) -> Array:
    """d ln H_i / dθ at S conditions for one θ (21,): (S, 7, 21), block-diagonal per zone (analytic)."""
    t = check_theta(theta)
    if t.ndim != 1:
        raise HMapError(f"theta: expected shape ({N_THETA},), got {t.shape}")
    n, _ = _conditions(speed_rpm, ambient_c)
    l0, l1, c = _split(t)
    ref = np.asarray(N_REF_RPM)
    g, g_ref = _g(n[:, None], c[None, :]), _g(ref, c)[None, :]
    s = g / g_ref
    ds = (_dg_dc(n[:, None], c[None, :]) * g_ref - g * _dg_dc(ref, c)[None, :]) / g_ref**2
    jac = np.zeros((n.size, N_ZONES, N_THETA))
    zones = np.arange(N_ZONES)
    jac[:, zones, 3 * zones] = 1.0 - s
    jac[:, zones, 3 * zones + 1] = s
    jac[:, zones, 3 * zones + 2] = (l1 - l0)[None, :] * ds
    return jac


def h_ci95_at(
    theta: ArrayLike, cov: ArrayLike, speed_rpm: ArrayLike, ambient_c: ArrayLike = T_REF_C
) -> tuple[Array, Array, Array]:
    """H (S, 7) and its 95 % band (lo, hi), each (S, 7) [W/(m²·K)], from cov (21, 21) of θ propagated to
    ln H (delta method): lo = H·e^(−1.96σ), hi = H·e^(1.96σ), so the band is always > 0."""
    c = check_cov(cov)
    jac = log_h_jacobian(theta, speed_rpm, ambient_c)
    sd = np.sqrt(np.maximum(np.einsum("szi,ij,szj->sz", jac, c, jac), 0.0))
    h = h_at(theta, speed_rpm, ambient_c)
    return h, h * np.exp(-Z95 * sd), h * np.exp(Z95 * sd)


def log_h_sd(theta: ArrayLike, cov: ArrayLike, speed_rpm: ArrayLike, ambient_c: ArrayLike = T_REF_C) -> Array:
    """σ of ln H (S, 7) from cov (21, 21) (delta method): the relative 1σ uncertainty of H."""
    jac = log_h_jacobian(theta, speed_rpm, ambient_c)
    return np.asarray(np.sqrt(np.maximum(np.einsum("szi,ij,szj->sz", jac, check_cov(cov), jac), 0.0)))


# ---- cold-start prior from physics ----


def becker_kaye_h(speed_rpm: Array, *, r_in_m: float, r_out_m: float, ambient_c: float = T_REF_C) -> Array:
    """H [W/(m²K)] of an annular gap with a rotating inner cylinder (Becker & Kaye 1962, geometric factor 1):
    Ta = ω²·r_m·δ³/ν², Nu(2δ) = 2 (Ta < 1700), 0.128·Ta^0.367 (< 1e4), 0.409·Ta^0.241 (above; extrapolated
    beyond 1e7); H = Nu·λ/(2δ)."""
    air = air_properties(ambient_c + 0.5 * FILM_RISE_K)
    gap, r_m = r_out_m - r_in_m, 0.5 * (r_in_m + r_out_m)
    omega = 2.0 * np.pi * np.abs(speed_rpm) / 60.0
    ta = omega**2 * r_m * gap**3 / air.nu_m2_s**2
    nu = np.where(ta < 1700.0, 2.0, np.where(ta < 1e4, 0.128 * ta**0.367, 0.409 * ta**0.241))
    return np.asarray(np.maximum(nu, 2.0) * air.k_w_mk / (2.0 * gap))


def physics_curves(spec: Any, speed_rpm: Array) -> Array:
    """The physics prior curves H (S, 7) [W/(m²K)] at T_ref: ``model.empirical`` for every zone except H6,
    which gets Becker–Kaye of the annulus between the shaft (H3 radius) and the housing bore (H6 radius)
    with the empirical natural-convection value as a floor."""
    emp = np.array([empirical_h(spec, float(n), T_REF_C) for n in speed_rpm])
    r_in, r_out = spec.zones[2].radius_m, spec.zones[5].radius_m
    bk = becker_kaye_h(speed_rpm, r_in_m=r_in, r_out_m=r_out)
    emp[:, 5] = np.maximum(emp[:, 5], bk)
    return emp


def fit_family(curve: Array, speed_rpm: Array, *, c0: float, ridge: float = 0.05) -> Array:
    """Least-squares fit of one zone's (l0, l1, c) to ln curve (S,) over ``speed_rpm`` (S,) at T_ref, with a
    weak pull (``ridge``) toward the crossover c0 = ln n_c [rpm] (a unique fit of a flat curve); multistart
    over the crossover."""
    y = np.log(curve)
    lo, hi = (np.array([b[k] for b in BOUNDS]) for k in (0, 1))

    def resid(x: Array) -> Array:
        model = x[0] + (x[1] - x[0]) * shape(speed_rpm, x[2])
        return np.concatenate([model - y, [ridge * (x[2] - c0)]])

    y_ref = float(np.interp(N_REF_RPM, speed_rpm, y))
    best = None
    for c_start in (c0, np.log(300.0), np.log(3000.0), np.log(20000.0)):
        x0 = np.clip([y[0], y_ref, c_start], lo + 1e-9, hi - 1e-9)
        sol = least_squares(resid, x0, bounds=(lo, hi))
        if best is None or sol.cost < best.cost:
            best = sol
    assert best is not None
    return np.asarray(best.x)


def prior_from_empirical(spec: Any, *, sd: tuple[float, float, float] = PRIOR_SD) -> Gaussian:
    """Cold-start prior over θ: mean = family fitted to ``physics_curves`` over 0..7000 rpm, independent
    σ ``sd`` = (a, m, c) per zone (wide: a factor e^1.5 = 4.5 in H at 1σ)."""
    speeds = np.linspace(0.0, SPEED_MAX_RPM, 71)
    curves = physics_curves(spec, speeds)
    mean = [fit_family(curves[:, i], speeds, c0=np.log(100.0)) for i in range(N_ZONES)]
    var = np.tile(np.square(sd), N_ZONES)
    return Gaussian(np.concatenate(mean), np.diag(var))


def model_form_error(
    h_of: Any, *, speed_max_rpm: float = SPEED_MAX_RPM, ambient_c: float = T_REF_C, n_grid: int = 141
) -> tuple[Array, Array, Array]:
    """Best fit of the family to a law ``h_of(speed_rpm, ambient_c) -> (7,)`` over 0..speed_max: returns the
    fitted θ (21,), max |H_fit/H − 1| (7,) and RMS of the same (7,) over the grid (in log-space LSQ)."""
    speeds = np.linspace(0.0, speed_max_rpm, n_grid)
    curves = np.array([h_of(float(n), ambient_c) for n in speeds])
    theta = [fit_family(curves[:, i], speeds, c0=np.log(1000.0), ridge=1e-6) for i in range(N_ZONES)]
    th = np.concatenate(theta)
    rel = h_at(th, speeds, ambient_c) / curves - 1.0
    return th, np.abs(rel).max(axis=0), np.sqrt(np.mean(rel**2, axis=0))
