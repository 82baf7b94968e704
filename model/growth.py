"""Growth uncertainty, sensor sensitivity and forecast, on top of ``model.thermoelastic`` (pure).

All growth values in µm, temperatures in °C, H in W/(m² K), times in s. ``operators`` is a
``GrowthModel.operators`` array (n_out, N) [µm/K] or one row (N,).

- Uncertainty: the growth is linear in the field, y = g·ΔT, so a field covariance Σ gives var y = g Σ gᵀ
  exactly (nodal Σ, or reduced: field = Φ a with Cov a = P, var y = (gΦ) P (gΦ)ᵀ; or a factor Σ = U Uᵀ).
  H's covariance enters through the field's Jacobian ∂T/∂H (``steady_jacobian_h``).
- Sensor sensitivity: a linear field estimate T̂ = M y from the 32 sensors gives ∂growth/∂y_j = g·M[:, j]
  [µm/°C]; ``reconstruction_h_fit`` is M for a least-squares H fit at steady state (linearised, the product's
  own path: sensors -> H -> field), ``reconstruction_basis`` for a least-squares fit of basis coordinates.
- Forecast: the condition (ambient, bearing heats) and H held: steady growth (``model.fem.steady_state``),
  growth at the horizons (``model.fem.simulate``, backward Euler), and the thermal modes K v = λ E v that set
  the time constants (the dominant one: the mode carrying most of the remaining growth).

Errors::

    GrowthError(ValueError)   a covariance, field or horizon of the wrong shape or value (argument named)
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla
import scipy.sparse.linalg as spla
from numpy.typing import ArrayLike, NDArray

from model.banded import BandedCholesky, SolverError, band_order
from model.errors import ModelError
from model.fem import FEModel, make_stepper, steady_state, stiffness
from model.inputs import InputSeries
from model.thermoelastic import GrowthModel

Array = NDArray[np.float64]
Z95 = 1.959963984540054  # two-sided 95 % normal quantile


class GrowthError(ModelError, ValueError):
    """Bad input to a growth function; the message names the argument."""


# ---------------------------------------------------------------- uncertainty


def _ops(operators: ArrayLike, phi: ArrayLike | None) -> Array:
    g = np.atleast_2d(np.asarray(operators, dtype=float))
    if phi is None:
        return g
    ph = np.asarray(phi, dtype=float)
    if ph.ndim != 2 or ph.shape[0] != g.shape[1]:
        raise GrowthError(f"phi: expected shape ({g.shape[1]}, r), got {ph.shape}")
    return g @ ph


def growth_std_um(
    operators: ArrayLike,
    *,
    cov: ArrayLike | None = None,
    factor: ArrayLike | None = None,
    phi: ArrayLike | None = None,
) -> Array:
    """Standard deviation [µm] of each output from the field's uncertainty, (n_out,).

    Give ``cov`` (n, n) [°C²] or ``factor`` U (n, k) with Σ = U Uᵀ; n = N (nodal) or, with ``phi`` (N, r),
    n = r (reduced coordinates, field = Φ a). Exact for a linear model: no sampling, no linearisation.
    """
    g = _ops(operators, phi)
    if (cov is None) == (factor is None):
        raise GrowthError("cov: give exactly one of cov or factor")
    if cov is not None:
        c = np.asarray(cov, dtype=float)
        if c.shape != (g.shape[1], g.shape[1]) or not np.all(np.isfinite(c)):
            raise GrowthError(f"cov: expected a finite ({g.shape[1]}, {g.shape[1]}) matrix, got {c.shape}")
        var = np.einsum("ij,jk,ik->i", g, c, g)
    else:
        u = np.asarray(factor, dtype=float)
        if u.ndim != 2 or u.shape[0] != g.shape[1] or not np.all(np.isfinite(u)):
            raise GrowthError(f"factor: expected a finite ({g.shape[1]}, k) matrix, got {u.shape}")
        var = np.sum((g @ u) ** 2, axis=1)
    if np.any(var < -1e-12 * np.max(np.abs(var), initial=1.0)):
        raise GrowthError("cov: not positive semi-definite along the growth operator")
    return np.asarray(np.sqrt(np.maximum(var, 0.0)))


def ci95(value_um: ArrayLike, std_um: ArrayLike) -> Array:
    """Two-sided 95 % interval [µm], (..., 2) as (low, high), for a Gaussian error of ``std_um``."""
    v, s = np.asarray(value_um, dtype=float), np.asarray(std_um, dtype=float)
    return np.stack([v - Z95 * s, v + Z95 * s], axis=-1)


def steady_jacobian_h(
    fe: FEModel,
    h: ArrayLike,
    *,
    ambient_c: float,
    q_front_w: float,
    q_rear_w: float,
    load_scale: tuple[float, float] = (1.0, 1.0),
    t_ss: ArrayLike | None = None,
) -> Array:
    """∂T_ss/∂H_i (N, 7) [°C per W/(m² K)] of the steady field: K ∂T/∂H_i = z_i Ti − K_i T (exact).

    ``t_ss`` (N,) [°C]: the steady field for the same H and condition when the caller has it (else solved
    here); the 7 right-hand sides share one banded Cholesky factorisation of K(H)."""
    if t_ss is None:
        t_ss = steady_state(
            fe, h, ambient_c=ambient_c, q_front_w=q_front_w, q_rear_w=q_rear_w, load_scale=load_scale
        )
    t = np.asarray(t_ss, dtype=float)
    rhs = np.column_stack([z * ambient_c - k @ t for z, k in zip(fe.z_zone, fe.K_zone, strict=True)])
    try:
        chol = BandedCholesky(stiffness(fe, h), band_order(fe.nodes_rz))
    except SolverError as err:
        raise GrowthError(f"h: stiffness not positive definite ({err})") from err
    return np.asarray(chol.solve(rhs))


def h_growth_std_um(operators: ArrayLike, jacobian_h: ArrayLike, cov_h: ArrayLike) -> Array:
    """Standard deviation [µm] of each output from H's covariance (7, 7) through the field Jacobian (N, 7)."""
    j = np.asarray(jacobian_h, dtype=float)
    return growth_std_um(np.atleast_2d(np.asarray(operators, dtype=float)) @ j, cov=cov_h)


def reconstruction_basis(phi: ArrayLike, sensor_op: ArrayLike, *, ridge: float = 0.0) -> Array:
    """M (N, 32): T̂ = Φ a with a the (ridge-)least-squares fit of the sensors y ≈ S Φ a."""
    ph = np.asarray(phi, dtype=float)
    sp_ = np.asarray(sensor_op @ ph) if hasattr(sensor_op, "tocsr") else np.asarray(sensor_op) @ ph
    if ridge < 0:
        raise GrowthError(f"ridge: must be >= 0, got {ridge!r}")
    gram = sp_.T @ sp_ + ridge * np.eye(ph.shape[1])
    return np.asarray(ph @ np.linalg.pinv(gram) @ sp_.T)


def reconstruction_h_fit(
    fe: FEModel, jacobian_h: ArrayLike, *, noise_c: float | None = None, prior_cov_h: ArrayLike | None = None
) -> Array:
    """M (N, 32) of an H fit to the 32 sensors, linearised at steady state (J = ∂T/∂H, N x 7).

    Least squares: δT̂ = J (S J)⁺ δy. With ``noise_c`` σ [°C] and ``prior_cov_h`` (7, 7) the maximum a
    posteriori fit instead: δT̂ = J (JᵀSᵀSJ/σ² + P⁻¹)⁻¹ JᵀSᵀ/σ², which bounds H where the data say little.
    """
    j = np.asarray(jacobian_h, dtype=float)
    sj = np.asarray(fe.sensor_op @ j)
    if (noise_c is None) != (prior_cov_h is None):
        raise GrowthError("prior_cov_h: give both noise_c and prior_cov_h, or neither")
    if noise_c is None or prior_cov_h is None:
        return np.asarray(j @ np.linalg.pinv(sj))
    prior = np.asarray(prior_cov_h, dtype=float)
    if prior.shape != (j.shape[1], j.shape[1]) or not noise_c > 0:
        raise GrowthError(f"prior_cov_h: expected ({j.shape[1]}, {j.shape[1]}) and noise_c > 0")
    info = sj.T @ sj / noise_c**2 + np.linalg.inv(prior)
    return np.asarray(j @ np.linalg.solve(info, sj.T / noise_c**2))


def sensor_sensitivity(operators: ArrayLike, reconstruction: ArrayLike) -> Array:
    """∂growth/∂(sensor reading) (n_out, 32) [µm/°C] for a linear field estimate T̂ = M y."""
    return np.atleast_2d(np.asarray(operators, dtype=float)) @ np.asarray(reconstruction, dtype=float)


# ---------------------------------------------------------------- time constants


@dataclass(frozen=True)
class ThermalModes:
    """Slowest thermal modes K(H) v = λ E v: time constants tau_s = 1/λ (k,) [s], vectors (N, k), VᵀEV = I."""

    tau_s: Array
    vectors: Array


def thermal_modes(
    fe: FEModel, h: ArrayLike, *, n_modes: int = 8, basis: ArrayLike | None = None
) -> ThermalModes:
    """The ``n_modes`` slowest modes of the thermal model for H: shift-invert Lanczos on the full model (one
    factorisation), or with ``basis`` Φ (N, r), r > ``n_modes`` (the reduced model's), Rayleigh–Ritz in its
    span: ΦᵀKΦ y = λ ΦᵀEΦ y, v = Φy (dense r × r; ~50x cheaper on the service mesh, r = 56). The reduced
    basis holds the slow dynamics: on the service model the slowest 9 time constants agree with Lanczos to
    < 0.1 %, the 12th and 13th to 3 % (docs/design/threading.md)."""
    if not 1 <= n_modes < fe.n_nodes - 1:
        raise GrowthError(f"n_modes: must be in [1, {fe.n_nodes - 2}], got {n_modes!r}")
    k_mat = stiffness(fe, h)
    if basis is not None:
        phi = np.asarray(basis, dtype=float)
        if phi.ndim != 2 or phi.shape[0] != fe.n_nodes or phi.shape[1] <= n_modes:
            raise GrowthError(f"basis: expected ({fe.n_nodes}, r > {n_modes}), got {phi.shape}")
        kr, er = phi.T @ (k_mat @ phi), phi.T @ (fe.E @ phi)
        lam_r, y = sla.eigh(0.5 * (kr + kr.T), 0.5 * (er + er.T), subset_by_index=[0, n_modes - 1])
        return ThermalModes(tau_s=1.0 / lam_r, vectors=phi @ y)
    lam, vec = spla.eigsh(k_mat.tocsc(), k=n_modes, M=fe.E.tocsc(), sigma=0.0, which="LM")
    order = np.argsort(lam)
    return ThermalModes(tau_s=1.0 / lam[order], vectors=vec[:, order])


def modal_growth_gap(fe: FEModel, modes: ThermalModes, operator: ArrayLike, deviation_c: ArrayLike) -> Array:
    """Each mode's share (k,) [µm] of g·(T − T_ss): c_k = (g·v_k)(v_kᵀ E (T − T_ss)); decays as e^(−t/τ_k)."""
    d = np.asarray(deviation_c, dtype=float)
    return np.asarray((np.asarray(operator) @ modes.vectors) * (modes.vectors.T @ (fe.E @ d)))


def dominant_time_constant(
    fe: FEModel, modes: ThermalModes, operator: ArrayLike, deviation_c: ArrayLike
) -> float:
    """τ [s] of the mode that carries the largest part of the remaining growth g·(T − T_ss)."""
    return float(modes.tau_s[int(np.argmax(np.abs(modal_growth_gap(fe, modes, operator, deviation_c))))])


# ---------------------------------------------------------------- forecast


@dataclass(frozen=True)
class GrowthForecast:
    """Growth [µm] now, at the horizons (n_h, n_out) and at steady state, if condition and H hold.

    ``tau_s`` (n_out,): each output's dominant time constant [s]; ``slowest_tau_s``: the thermal model's.
    """

    names: tuple[str, ...]
    now_um: Array
    horizons_s: Array
    at_horizon_um: Array
    steady_um: Array
    tau_s: Array
    slowest_tau_s: float


def _steps(horizons_s: Sequence[float], dt_s: float) -> NDArray[np.int64]:
    hz = np.asarray(horizons_s, dtype=float)
    steps = np.rint(hz / dt_s).astype(np.int64)
    if hz.ndim != 1 or np.any(steps < 1) or np.any(np.abs(steps * dt_s - hz) > 1e-9 * np.maximum(hz, 1.0)):
        raise GrowthError(f"horizons_s: must be positive multiples of dt_s = {dt_s}, got {list(hz)}")
    return steps


def forecast_growth(
    fe: FEModel,
    growth: GrowthModel,
    h: ArrayLike,
    *,
    field_c: ArrayLike,
    t_ref_c: float | ArrayLike,
    ambient_c: float,
    q_front_w: float,
    q_rear_w: float,
    load_scale: tuple[float, float] = (1.0, 1.0),
    horizons_s: Sequence[float] = (300.0, 900.0, 1800.0),
    dt_s: float = 10.0,
    n_modes: int = 8,
) -> GrowthForecast:
    """Forecast the growth from the current field (N,) [°C] if the condition and H [W/(m² K)] hold.

    Steady state: ``model.fem.steady_state``; horizons: ``model.fem`` backward Euler at ``dt_s`` (the
    service's own discretisation); time constants: ``thermal_modes``. Cost at the default mesh: about
    0.1 s per 30 min of horizon plus 0.1 s for the modes.
    """
    t_now = np.asarray(field_c, dtype=float)
    if t_now.shape != (fe.n_nodes,):
        raise GrowthError(f"field_c: expected shape ({fe.n_nodes},), got {t_now.shape}")
    steps = _steps(horizons_s, dt_s)
    t_ss = steady_state(
        fe, h, ambient_c=ambient_c, q_front_w=q_front_w, q_rear_w=q_rear_w, load_scale=load_scale
    )
    n = int(steps.max())
    inputs = InputSeries(
        dt_s=dt_s,
        ambient_c=np.full(n, ambient_c),
        q_front_w=np.full(n, q_front_w),
        q_rear_w=np.full(n, q_rear_w),
    )
    fields, _ = make_stepper(fe, h, dt_s=dt_s).march(inputs, t_now, load_scale=load_scale)
    modes = thermal_modes(fe, h, n_modes=n_modes)
    taus = [dominant_time_constant(fe, modes, g, t_now - t_ss) for g in growth.operators]
    return GrowthForecast(
        names=growth.names,
        now_um=growth.growth_um(t_now, t_ref_c),
        horizons_s=np.asarray(steps * dt_s, dtype=np.float64),
        at_horizon_um=growth.growth_um(fields[steps], t_ref_c),
        steady_um=growth.growth_um(t_ss, t_ref_c),
        tau_s=np.array(taus),
        slowest_tau_s=float(modes.tau_s[0]),
    )
