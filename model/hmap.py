"""H as a function of the operating condition, H_i = F_i(n, Ti; θ): two families over speed, a physics prior.

**Physics family** (``PHYSICS``, three parameters per zone θ_i = (l0_i, l1_i, c_i), 21 in all)::

    ln H_i(n, Ti) = l0_i + (l1_i − l0_i)·s(n; c_i) + ln A_i(Ti),
    s(n; c) = ln(1 + (n/n_c)²) / ln(1 + (N_REF/n_c)²),  n_c = e^c [rpm],  N_REF = 3500 rpm

i.e. H = H(0)·(1 + (n/n_c)²)^(m/2)·A(Ti): a natural-convection level at standstill (Churchill–Chu),
the forced-convection power law H ∝ n^m for n ≫ n_c (rotating surfaces Nu = C·Re^m, Bejan, *Convection Heat
Transfer*, 4th ed., ch. 7: laminar m = 1/2, turbulent 4/5; the annular air gap Nu ∝ Ta^(m/2), Ta ∝ n²,
Becker & Kaye 1962: Nu = 0.409·Ta^0.241, m ≈ 0.48), joined by a Churchill–Usagi blend (AIChE J. 18, 1972)
with crossover speed n_c. Parametrised by the levels at 0 and N_REF (ln H) and ln n_c: the levels are what a
window determines, which made the fit converge in ~40 instead of ~120 model runs with (ln H0, m, ln n_c).
The sign of the exponent is free: the identified H are *effective* coefficients referred to the single
ambient Ti (docs/design/model.md), and an air gap that warms with speed makes the effective H fall with speed.

**Tabulated family** (``NODES``, the default): ln H_i at the speed nodes 0, 1000, ..., 7000 rpm (8 per zone,
56 in all), linear in between (constant outside), plus the same ln A_i(Ti). Its prior carries the physics:
mean from the physics curves, smoothness from a second-difference penalty. Linear in θ, so the fit converges
in ~15 model runs; its interpolation error is ~1 %. Measured on the virtual plant (docs/design/hmap.md), it
gives smaller H errors and honest bands, where the 3-parameter family's model-form error (up to 16 % for H7)
is compensated by the other zones in the sensor fit (errors 10-20 % at visited speeds with bands of 5-10 %).

Ambient (both families, no parameter): H ∝ λ·ν^(−m) through the air properties at the film temperature
(``model.empirical.air_properties``): A = (λ(Ti)/λ(T_ref))·(ν(T_ref)/ν(Ti))^m_i with the physics m_i
(1/2; 0 for the stationary H7): −0.03 %/K, i.e. physics says a ±1 °C drift hardly matters.

Cold-start prior (``Family.prior``): the physics curve of each zone at T_ref, ``model.empirical.empirical_h``
for H1–H5 and H7 and, for H6 (which ``model.empirical`` treats as still air), Becker–Kaye of the central
annulus with the natural-convection floor; wide (σ 1.5 in ln H: a factor 4.5 at 1σ).

Neither family contains the virtual plant's ``h_true`` (a tanh in n): ``Family.form_error`` measures the
best fit over 0..7000 rpm (docs/design/hmap.md).

Errors::

    HMapError(ValueError)   bad θ, covariance, speed or ambient shape (the argument is named)
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import least_squares

from model.empirical import air_properties, empirical_h
from model.errors import ModelError

Array = NDArray[np.float64]

N_ZONES = 7
T_REF_C = 20.0  # reference ambient of the families [°C]
FILM_RISE_K = 10.0  # assumed surface rise for the film temperature (as model.empirical)
SPEED_MAX_RPM = 7000.0
Z95 = 1.959963984540054
N_REF_RPM = 3500.0  # physics family: the speed of the second level parameter
PHYSICS_SD = (1.5, 1.5, 2.0)  # physics family prior σ: l0, l1 [ln W/(m²K)], c [ln rpm]
PHYSICS_BOUNDS = ((np.log(0.5), np.log(500.0)), (np.log(0.5), np.log(500.0)), (np.log(30.0), np.log(1e5)))
LEVEL_SD = 1.5  # tabulated family prior σ of ln H at a node (around the smoothed physics curve)
CURVATURE_SD = 0.3  # tabulated family prior σ of the second difference of ln H between nodes
# tabulated family: σ of a rotating zone's linear trend of ln H over speed (± TREND_SD at 0 and 7000 rpm, 0 at
# the middle node), added to the smoothed node prior. Without it the physics curve's trend was known to ±0.8
# (the per-node σ averaged over 8 nodes) and H1, which the data barely determine, kept the physics curve's
# rising trend where the plant's falls (docs/design/hmap.md, "H1 at 4000 rpm on the chain"). 2.0 ≈ the physics
# family's own prior on the rise from 0 to 3500 rpm (two independent levels of σ 1.5: σ 2.1): the sign of a
# rotating surface's effective exponent is free. Stationary zones (H6, H7) keep the node prior alone.
TREND_SD = 2.0
LEVEL_BOUNDS = (np.log(0.5), np.log(500.0))  # ln H [ln W/(m²K)]
AMBIENT_EXPONENT = (0.5, 0.5, 0.5, 0.5, 0.5, 0.5, 0.0)  # m in the air-property factor ν^(-m)
DEFAULT_NODES_RPM = tuple(float(n) for n in range(0, 7001, 1000))


class HMapError(ModelError, ValueError):
    """A bad argument to the H map; the message names it."""


@dataclass(frozen=True)
class Gaussian:
    """A Gaussian over θ: ``mean`` (p,), ``cov`` (p, p) symmetric positive semi-definite."""

    mean: Array
    cov: Array

    def __post_init__(self) -> None:
        m = np.asarray(self.mean, dtype=np.float64)
        if m.ndim != 1 or not np.all(np.isfinite(m)):
            raise HMapError(f"mean: expected a finite 1-D array, got shape {m.shape}")
        check_cov(self.cov, m.size)


def check_cov(cov: ArrayLike, p: int) -> Array:
    """A symmetric positive semi-definite (p, p) covariance, or HMapError naming ``cov``."""
    c = np.asarray(cov, dtype=np.float64)
    if c.shape != (p, p) or not np.all(np.isfinite(c)):
        raise HMapError(f"cov: expected ({p}, {p}) finite values, got shape {c.shape}")
    if not np.allclose(c, c.T, rtol=1e-8, atol=1e-12) or np.linalg.eigvalsh(0.5 * (c + c.T))[0] < -1e-9:
        raise HMapError("cov: must be symmetric positive semi-definite")
    return c


def _conditions(speed_rpm: ArrayLike, ambient_c: ArrayLike) -> tuple[Array, Array]:
    n = np.abs(np.atleast_1d(np.asarray(speed_rpm, dtype=np.float64)))
    if n.ndim != 1 or not np.all(np.isfinite(n)):
        raise HMapError(f"speed_rpm: expected a scalar or 1-D finite array, got shape {n.shape}")
    try:
        ti = np.broadcast_to(np.asarray(ambient_c, dtype=np.float64), n.shape)
    except ValueError as err:
        raise HMapError(
            f"ambient_c: expected a scalar or shape {n.shape}, got {np.shape(ambient_c)}"
        ) from err
    if not np.all(np.isfinite(ti)):
        raise HMapError("ambient_c: contains non-finite values")
    return n, np.asarray(ti)


def _ambient_log(ambient_c: Array) -> Array:
    """ln A_i(Ti) (S, 7): λ(Ti)/λ(T_ref)·(ν(T_ref)/ν(Ti))^m_i at the film temperatures, physics m_i."""
    ref = air_properties(T_REF_C + 0.5 * FILM_RISE_K)
    uniq, inv = np.unique(ambient_c, return_inverse=True)
    props = [air_properties(float(t) + 0.5 * FILM_RISE_K) for t in uniq]
    lk = np.array([np.log(p.k_w_mk / ref.k_w_mk) for p in props])[inv.ravel()]
    lnu = np.array([np.log(ref.nu_m2_s / p.nu_m2_s) for p in props])[inv.ravel()]
    return np.asarray(lk[:, None] + np.asarray(AMBIENT_EXPONENT)[None, :] * lnu[:, None])


# ---- physics family: (l0, l1, c) per zone ----


def _g(n: Array, c: Array) -> Array:
    """ln(1 + (n/n_c)²)."""
    return np.asarray(np.log1p((n / np.exp(c)) ** 2))


def _dg_dc(n: Array, c: Array) -> Array:
    u2 = (n / np.exp(c)) ** 2
    return np.asarray(-2.0 * u2 / (1.0 + u2))


def shape(speed_rpm: ArrayLike, c: ArrayLike) -> Array:
    """The physics family's normalised speed shape s(n; c): 0 at rest, 1 at N_REF_RPM."""
    n, cc = np.asarray(speed_rpm, dtype=np.float64), np.asarray(c, dtype=np.float64)
    return _g(n, cc) / _g(np.asarray(N_REF_RPM), cc)


def _physics_log_h(t: Array, n: Array) -> Array:
    z = t.reshape(*t.shape[:-1], N_ZONES, 3)
    l0, l1, c = (z[..., k][..., None, :] for k in range(3))  # (..., 1, 7)
    return np.asarray(l0 + (l1 - l0) * shape(n[:, None], c))


def _physics_jacobian(t: Array, n: Array) -> Array:
    z = t.reshape(N_ZONES, 3)
    l0, l1, c = z[:, 0], z[:, 1], z[:, 2]
    ref = np.asarray(N_REF_RPM)
    g, g_ref = _g(n[:, None], c[None, :]), _g(ref, c)[None, :]
    s = g / g_ref
    ds = (_dg_dc(n[:, None], c[None, :]) * g_ref - g * _dg_dc(ref, c)[None, :]) / g_ref**2
    jac = np.zeros((n.size, N_ZONES, 3 * N_ZONES))
    zones = np.arange(N_ZONES)
    jac[:, zones, 3 * zones] = 1.0 - s
    jac[:, zones, 3 * zones + 1] = s
    jac[:, zones, 3 * zones + 2] = (l1 - l0)[None, :] * ds
    return jac


def fit_physics(curve: Array, speed_rpm: Array, *, c0: float, ridge: float = 0.05) -> Array:
    """Least-squares fit of one zone's (l0, l1, c) to ln curve (S,) over ``speed_rpm`` (S,), with a weak
    pull (``ridge``) toward the crossover c0 = ln n_c [rpm] (a unique fit of a flat curve); multistart."""
    y = np.log(curve)
    lo, hi = (np.array([b[k] for b in PHYSICS_BOUNDS]) for k in (0, 1))

    def resid(x: Array) -> Array:
        return np.concatenate([x[0] + (x[1] - x[0]) * shape(speed_rpm, x[2]) - y, [ridge * (x[2] - c0)]])

    y_ref = float(np.interp(N_REF_RPM, speed_rpm, y))
    sols = [
        least_squares(resid, np.clip([y[0], y_ref, c1], lo + 1e-9, hi - 1e-9), bounds=(lo, hi))
        for c1 in (c0, np.log(300.0), np.log(3000.0), np.log(20000.0))
    ]
    return np.asarray(min(sols, key=lambda sol: sol.cost).x)


# ---- tabulated family: ln H at speed nodes per zone ----


def node_weights(speed_rpm: Array, nodes_rpm: Array) -> Array:
    """Linear-interpolation weights (S, K) of speeds (S,) on the nodes (K,) (constant outside)."""
    n = np.clip(np.abs(speed_rpm), nodes_rpm[0], nodes_rpm[-1])
    k = np.clip(np.searchsorted(nodes_rpm, n, side="right") - 1, 0, nodes_rpm.size - 2)
    frac = (n - nodes_rpm[k]) / (nodes_rpm[k + 1] - nodes_rpm[k])
    w = np.zeros((n.size, nodes_rpm.size))
    rows = np.arange(n.size)
    w[rows, k] = 1.0 - frac
    w[rows, k + 1] += frac
    return w


def second_differences(k: int) -> Array:
    """(K-2, K) second-difference operator."""
    return np.asarray(np.diff(np.eye(k), 2, axis=0))


# ---- the family object ----


@dataclass(frozen=True)
class Family:
    """A family of H maps: ``kind`` "nodes" (ln H at ``nodes_rpm`` per zone) or "physics" (l0, l1, c per
    zone). θ is zone-major: the parameters of H1, then of H2, ... ``n_theta`` in all."""

    kind: Literal["nodes", "physics"] = "nodes"
    nodes_rpm: tuple[float, ...] = DEFAULT_NODES_RPM
    _nodes: Array = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if self.kind not in ("nodes", "physics"):
            raise HMapError(f"kind: expected 'nodes' or 'physics', got {self.kind!r}")
        nodes = np.asarray(self.nodes_rpm, dtype=np.float64)
        if nodes.ndim != 1 or nodes.size < 3 or nodes[0] != 0.0 or np.any(np.diff(nodes) <= 0):
            raise HMapError(f"nodes_rpm: expected >= 3 increasing speeds from 0 rpm, got {self.nodes_rpm}")
        object.__setattr__(self, "_nodes", nodes)

    @property
    def per_zone(self) -> int:
        """Parameters per zone."""
        return int(self._nodes.size) if self.kind == "nodes" else 3

    @property
    def n_theta(self) -> int:
        """Number of parameters p."""
        return N_ZONES * self.per_zone

    def check_theta(self, theta: ArrayLike, name: str = "theta") -> Array:
        """θ as a float array (..., p), or HMapError naming ``name``."""
        t = np.asarray(theta, dtype=np.float64)
        if t.ndim == 0 or t.shape[-1] != self.n_theta or not np.all(np.isfinite(t)):
            raise HMapError(f"{name}: expected (..., {self.n_theta}) finite values, got shape {t.shape}")
        return t

    def bounds(self) -> tuple[Array, Array]:
        """Lower and upper bounds of θ (p,) each (ln H in ln(0.5..500) W/(m²K); n_c in 30..1e5 rpm)."""
        if self.kind == "nodes":
            return np.full(self.n_theta, LEVEL_BOUNDS[0]), np.full(self.n_theta, LEVEL_BOUNDS[1])
        lo = np.tile([b[0] for b in PHYSICS_BOUNDS], N_ZONES)
        return lo, np.tile([b[1] for b in PHYSICS_BOUNDS], N_ZONES)

    def log_h(self, theta: ArrayLike, speed_rpm: ArrayLike, ambient_c: ArrayLike = T_REF_C) -> Array:
        """ln H [ln W/(m²K)] for θ (..., p) at S conditions (speed [rpm], ambient [°C]): (..., S, 7)."""
        t = self.check_theta(theta)
        n, ti = _conditions(speed_rpm, ambient_c)
        if self.kind == "physics":
            core = _physics_log_h(t, n)
        else:
            z = t.reshape(*t.shape[:-1], N_ZONES, self.per_zone)
            core = np.swapaxes(z @ node_weights(n, self._nodes).T, -1, -2)
        return np.asarray(core + _ambient_log(ti))

    def h_at(self, theta: ArrayLike, speed_rpm: ArrayLike, ambient_c: ArrayLike = T_REF_C) -> Array:
        """H1..H7 [W/(m²·K)]: θ (p,) gives (S, 7), θ (P, p) gives (P, S, 7)."""
        return np.exp(self.log_h(theta, speed_rpm, ambient_c))

    def log_h_jacobian(self, theta: ArrayLike, speed_rpm: ArrayLike, ambient_c: ArrayLike = T_REF_C) -> Array:
        """d ln H_i / dθ (S, 7, p) for one θ (p,), block-diagonal per zone (analytic)."""
        t = self.check_theta(theta)
        if t.ndim != 1:
            raise HMapError(f"theta: expected shape ({self.n_theta},), got {t.shape}")
        n, _ = _conditions(speed_rpm, ambient_c)
        if self.kind == "physics":
            return _physics_jacobian(t, n)
        w, k = node_weights(n, self._nodes), self.per_zone
        jac = np.zeros((n.size, N_ZONES, self.n_theta))
        for i in range(N_ZONES):
            jac[:, i, i * k : (i + 1) * k] = w
        return jac

    def h_jacobian(self, theta: ArrayLike, speed_rpm: ArrayLike, ambient_c: ArrayLike = T_REF_C) -> Array:
        """dH_i/dθ (S, 7, p) [W/(m²·K) per unit θ] for one θ (p,): H·d ln H/dθ."""
        h = self.h_at(theta, speed_rpm, ambient_c)
        return np.asarray(h[:, :, None] * self.log_h_jacobian(theta, speed_rpm, ambient_c))

    def log_h_sd(
        self, theta: ArrayLike, cov: ArrayLike, speed_rpm: ArrayLike, ambient_c: ArrayLike = T_REF_C
    ) -> Array:
        """σ of ln H (S, 7) from cov (p, p) of θ (delta method): the relative 1σ uncertainty of H."""
        jac = self.log_h_jacobian(theta, speed_rpm, ambient_c)
        var = np.einsum("szi,ij,szj->sz", jac, check_cov(cov, self.n_theta), jac)
        return np.asarray(np.sqrt(np.maximum(var, 0.0)))

    def h_ci95_at(
        self, theta: ArrayLike, cov: ArrayLike, speed_rpm: ArrayLike, ambient_c: ArrayLike = T_REF_C
    ) -> tuple[Array, Array, Array]:
        """H (S, 7) and its 95 % band lo, hi (S, 7) [W/(m²·K)] from cov (p, p) propagated to ln H:
        lo = H·e^(−1.96σ), hi = H·e^(1.96σ), always > 0."""
        sd = self.log_h_sd(theta, cov, speed_rpm, ambient_c)
        h = self.h_at(theta, speed_rpm, ambient_c)
        return h, h * np.exp(-Z95 * sd), h * np.exp(Z95 * sd)

    def prior(self, spec: Any, *, trend_sd: float = TREND_SD, level_sd: float = 0.0) -> Gaussian:
        """Cold-start prior from the physics curves (``physics_curves``) of ``spec``'s zones.

        physics: mean = the family fitted to the curves over 0..7000 rpm, σ ``PHYSICS_SD`` per parameter;
        nodes: mean Λ⁻¹·μ/σ_l², the smoothed curve, with Λ = I/σ_l² + DᵀD/σ_c² per zone (σ_l = LEVEL_SD
        around the curve's ln H at the nodes, σ_c = CURVATURE_SD on its second differences D); covariance
        Λ⁻¹ + σ_t²·ttᵀ per rotating zone (``spec.zones[i].rotating``; Λ⁻¹ alone for the stationary ones):
        a linear trend over speed of unknown size (t from −1 at the first node to +1 at the last, σ_t =
        ``trend_sd``), so that the physics curve's speed dependence is uncertain as a whole, not only node
        by node (0: the smoothed-node prior alone); plus σ_0²·11ᵀ per zone (σ_0 = ``level_sd``): an overall
        factor of the physics curve of unknown size, every zone (0: none).
        """
        if self.kind == "physics":
            speeds = np.linspace(0.0, SPEED_MAX_RPM, 71)
            curves = physics_curves(spec, speeds)
            mean = np.concatenate(
                [fit_physics(curves[:, i], speeds, c0=np.log(100.0)) for i in range(N_ZONES)]
            )
            return Gaussian(mean, np.diag(np.tile(np.square(PHYSICS_SD), N_ZONES)))
        mu = np.log(physics_curves(spec, self._nodes)).T.ravel()  # zone-major
        d = second_differences(self.per_zone)
        block = np.eye(self.per_zone) / LEVEL_SD**2 + d.T @ d / CURVATURE_SD**2
        smooth = np.linalg.inv(np.kron(np.eye(N_ZONES), block))
        mid = 0.5 * (self._nodes[0] + self._nodes[-1])
        trend = (self._nodes - mid) / (self._nodes[-1] - mid)  # -1 at the first node, +1 at the last
        rotating = np.array([bool(z.rotating) for z in spec.zones], dtype=float)
        cov = smooth + np.kron(np.diag(rotating), trend_sd**2 * np.outer(trend, trend))
        cov += np.kron(np.eye(N_ZONES), level_sd**2 * np.ones((self.per_zone, self.per_zone)))
        return Gaussian(smooth @ mu / LEVEL_SD**2, 0.5 * (cov + cov.T))

    def form_error(
        self,
        h_of: Any,
        *,
        speed_max_rpm: float = SPEED_MAX_RPM,
        ambient_c: float = T_REF_C,
        n_grid: int = 141,
    ) -> tuple[Array, Array, Array]:
        """Best fit (least squares in ln H over a 0..speed_max grid) of the family to a law
        ``h_of(speed_rpm, ambient_c) -> (7,)``: θ (p,), max and RMS of |H_fit/H − 1| per zone (7,) each."""
        speeds = np.linspace(0.0, speed_max_rpm, n_grid)
        y = np.log(np.array([h_of(float(n), ambient_c) for n in speeds]))  # (S, 7)
        if self.kind == "physics":
            th = np.concatenate(
                [fit_physics(np.exp(y[:, i]), speeds, c0=np.log(1000.0), ridge=1e-6) for i in range(N_ZONES)]
            )
        else:
            w = node_weights(speeds, self._nodes)
            th = np.linalg.lstsq(w, y - _ambient_log(np.full(speeds.size, ambient_c)), rcond=None)[
                0
            ].T.ravel()
        rel = self.h_at(th, speeds, ambient_c) / np.exp(y) - 1.0
        return th, np.abs(rel).max(axis=0), np.sqrt(np.mean(rel**2, axis=0))


PHYSICS = Family("physics")
NODES = Family("nodes")
DEFAULT_FAMILY = NODES


def h_at(
    theta: ArrayLike, speed_rpm: ArrayLike, ambient_c: ArrayLike = T_REF_C, *, family: Family = DEFAULT_FAMILY
) -> Array:
    """H1..H7 [W/(m²·K)] of θ at speeds (S,) [rpm] and ambient(s) [°C]: (S, 7) (``Family.h_at``)."""
    return family.h_at(theta, speed_rpm, ambient_c)


def h_ci95_at(
    theta: ArrayLike,
    cov: ArrayLike,
    speed_rpm: ArrayLike,
    ambient_c: ArrayLike = T_REF_C,
    *,
    family: Family = DEFAULT_FAMILY,
) -> tuple[Array, Array, Array]:
    """H and its 95 % band, each (S, 7) [W/(m²·K)] (``Family.h_ci95_at``)."""
    return family.h_ci95_at(theta, cov, speed_rpm, ambient_c)


# ---- physics curves for the prior ----


def becker_kaye_h(speed_rpm: Array, *, r_in_m: float, r_out_m: float, ambient_c: float = T_REF_C) -> Array:
    """H [W/(m²K)] of an annular gap with a rotating inner cylinder (Becker & Kaye 1962, geometric factor 1):
    Ta = ω²·r_m·δ³/ν², Nu(2δ) = 2 (Ta < 1700), 0.128·Ta^0.367 (< 1e4), 0.409·Ta^0.241 (above; extrapolated
    beyond 1e7); H = Nu·λ/(2δ)."""
    air = air_properties(ambient_c + 0.5 * FILM_RISE_K)
    gap, r_m = r_out_m - r_in_m, 0.5 * (r_in_m + r_out_m)
    omega = 2.0 * np.pi * np.abs(np.asarray(speed_rpm, dtype=np.float64)) / 60.0
    ta = omega**2 * r_m * gap**3 / air.nu_m2_s**2
    nu = np.where(ta < 1700.0, 2.0, np.where(ta < 1e4, 0.128 * ta**0.367, 0.409 * ta**0.241))
    return np.asarray(np.maximum(nu, 2.0) * air.k_w_mk / (2.0 * gap))


def physics_curves(spec: Any, speed_rpm: Array) -> Array:
    """The physics prior curves H (S, 7) [W/(m²K)] at T_ref: ``model.empirical`` for every zone except H6,
    which gets Becker–Kaye of the annulus between the shaft (H3 radius) and the housing bore (H6 radius)
    with the empirical natural-convection value as a floor."""
    emp = np.array([empirical_h(spec, float(n), T_REF_C) for n in speed_rpm])
    bk = becker_kaye_h(speed_rpm, r_in_m=spec.zones[2].radius_m, r_out_m=spec.zones[5].radius_m)
    emp[:, 5] = np.maximum(emp[:, 5], bk)
    return emp
