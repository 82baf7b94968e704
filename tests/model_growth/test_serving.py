"""The served growth (``service.estimate.growth``) against ``model.growth`` directly, and its CI's honesty."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta, timezone

import numpy as np
import pytest

from model.fem import FEModel, build_fe_model, steady_state
from model.geometry import SpindleSpec
from model.growth import (
    Z95,
    forecast_growth,
    growth_std_um,
    h_growth_std_um,
    reconstruction_h_fit,
    sensor_sensitivity,
    steady_jacobian_h,
)
from model.heat import bearing_heat_w
from model.thermoelastic import GrowthModel, build_growth_model
from service.estimate.growth import (
    ConditionTerms,
    FieldBelief,
    GrowthContext,
    GrowthEstimateError,
    build_context,
    condition_terms,
    estimate_growth,
    h_cov_from_ci,
    plc_compensation,
)
from tests.model_growth.conftest import H_TABLE4

AMB = 20.0
AT = datetime(2026, 3, 1, 12, 0, tzinfo=UTC)
H = np.array(H_TABLE4)
COV_H = np.diag((0.1 * H) ** 2)


def _heats(spec: SpindleSpec, speed: float) -> tuple[float, float]:
    return (
        float(bearing_heat_w(speed, 0.0, spec.bearings.front)),
        float(bearing_heat_w(speed, 0.0, spec.bearings.rear)),
    )


def _basis(fe: FEModel, spec: SpindleSpec) -> np.ndarray:
    """A small reduced basis (N, 4): uniform, and three steady shapes (orthonormalised)."""
    cols = [np.ones(fe.n_nodes)]
    for speed in (2000.0, 5000.0, 7000.0):
        qf, qr = _heats(spec, speed)
        cols.append(steady_state(fe, H, ambient_c=0.0, q_front_w=qf, q_rear_w=qr))
    q, _ = np.linalg.qr(np.column_stack(cols))
    return np.asarray(q)


@pytest.fixture(scope="module")
def ctx(spec: SpindleSpec, fe: FEModel, growth: GrowthModel) -> GrowthContext:
    return build_context(spec, fe, growth=growth, basis=_basis(fe, spec))


@pytest.fixture(scope="module")
def terms(spec: SpindleSpec, ctx: GrowthContext) -> ConditionTerms:
    qf, qr = _heats(spec, 5000.0)
    return condition_terms(ctx, h=H, cov_h=COV_H, ambient_c=AMB, q_front_w=qf, q_rear_w=qr)


def _rows(growth: GrowthModel) -> tuple[int, int]:
    return growth.names.index("nose_axial"), growth.names.index("nose_radial")


def test_now_is_the_growth_model_exactly(
    fe: FEModel, growth: GrowthModel, ctx: GrowthContext, terms: ConditionTerms
) -> None:
    field = AMB + 8.0 * np.random.default_rng(1).random(fe.n_nodes)
    est = estimate_growth(ctx, terms, FieldBelief(mean_c=field), t_ref_c=AMB, at=AT)
    ia, ir = _rows(growth)
    direct = growth.growth_um(field, AMB)
    assert est.axial.um == pytest.approx(direct[ia], rel=1e-12, abs=1e-12)
    assert est.radial.um == pytest.approx(direct[ir], rel=1e-12, abs=1e-12)
    assert est.axial.plc_0p1um == int(np.rint(10 * direct[ia]))
    assert est.axial.std_um == 0.0  # no uncertainty given and H's already in the (absent) field part


def test_reduced_state_and_covariance_match_model_growth(
    fe: FEModel, growth: GrowthModel, ctx: GrowthContext, terms: ConditionTerms
) -> None:
    assert ctx.phi is not None
    rng = np.random.default_rng(2)
    a = rng.normal(size=ctx.phi.shape[1]) * 30.0
    u = rng.normal(size=(ctx.phi.shape[1], ctx.phi.shape[1]))
    p = u @ u.T * 0.01
    by_state = estimate_growth(ctx, terms, FieldBelief(state=a, cov=p), t_ref_c=AMB, at=AT)
    by_field = estimate_growth(ctx, terms, FieldBelief(mean_c=ctx.phi @ a, cov=p), t_ref_c=AMB, at=AT)
    ia, ir = _rows(growth)
    expected = growth_std_um(growth.operators, cov=p, phi=ctx.phi)
    assert by_state.axial.std_field_um == pytest.approx(expected[ia], rel=1e-9)
    assert by_state.radial.std_field_um == pytest.approx(expected[ir], rel=1e-9)
    assert by_state.axial.um == pytest.approx(growth.growth_um(ctx.phi @ a, AMB)[ia], rel=1e-9)
    for x, y in zip(by_state.forecast.axial, by_field.forecast.axial, strict=True):
        assert x.um == pytest.approx(y.um, rel=1e-9)
    assert by_state.forecast.tau_s == by_field.forecast.tau_s
    # the same covariance as ensemble deviations (second moment) and as a nodal factor
    dev = rng.normal(size=(400, p.shape[0])) @ np.linalg.cholesky(p + 1e-12 * np.eye(p.shape[0])).T
    by_dev = estimate_growth(ctx, terms, FieldBelief(state=a, deviations=dev), t_ref_c=AMB, at=AT)
    moment = growth_std_um(growth.operators, cov=dev.T @ dev / len(dev), phi=ctx.phi)
    assert by_dev.axial.std_field_um == pytest.approx(moment[ia], rel=1e-9)
    by_factor = estimate_growth(
        ctx, terms, FieldBelief(state=a, factor=ctx.phi @ np.linalg.cholesky(p)), t_ref_c=AMB, at=AT
    )
    assert by_factor.axial.std_field_um == pytest.approx(expected[ia], rel=1e-9)


def test_compact_terms_serve_a_reduced_belief_alike_and_refuse_a_nodal_one(
    fe: FEModel, ctx: GrowthContext, terms: ConditionTerms
) -> None:
    """The service caches compact terms (issue 43 part 5): without the nodal functionals, a reduced belief's
    estimate is the same to the last bit, they are far smaller, and a nodal belief is refused by name."""
    assert ctx.phi is not None
    small = terms.compact()
    assert small.w is None and small.modes_e is None
    assert terms.w is not None and terms.modes_e is not None  # the full terms are left as they were

    def nbytes(t: ConditionTerms) -> int:
        return sum(v.nbytes for v in vars(t).values() if isinstance(v, np.ndarray))

    assert nbytes(small) < 0.5 * nbytes(terms)
    rng = np.random.default_rng(5)
    r = ctx.phi.shape[1]
    u = rng.normal(size=(r, r))
    for belief in (
        FieldBelief(state=30.0 * rng.standard_normal(r), cov=u @ u.T * 0.01),
        FieldBelief(state=30.0 * rng.standard_normal(r), deviations=0.1 * rng.standard_normal((50, r))),
        FieldBelief(state=30.0 * rng.standard_normal(r)),
    ):
        full = estimate_growth(ctx, terms, belief, t_ref_c=AMB, at=AT)
        assert estimate_growth(ctx, small, belief, t_ref_c=AMB, at=AT) == full
    nodal = (
        FieldBelief(mean_c=np.full(fe.n_nodes, AMB)),
        FieldBelief(state=np.zeros(r), std_c=np.full(fe.n_nodes, 0.1)),
        FieldBelief(state=np.zeros(r), factor=np.ones((fe.n_nodes, 1))),
    )
    for belief in nodal:
        with pytest.raises(GrowthEstimateError, match="compact"):
            estimate_growth(ctx, small, belief, t_ref_c=AMB, at=AT)


def test_per_node_std_is_bounded_by_full_correlation(
    fe: FEModel, growth: GrowthModel, ctx: GrowthContext, terms: ConditionTerms
) -> None:
    std = np.full(fe.n_nodes, 0.2)
    est = estimate_growth(
        ctx, terms, FieldBelief(mean_c=np.full(fe.n_nodes, AMB), std_c=std), t_ref_c=AMB, at=AT
    )
    ia, _ = _rows(growth)
    full = growth_std_um(growth.operators, factor=std[:, None])  # fully correlated: one common error
    assert est.axial.std_field_um >= full[ia] - 1e-12
    assert est.axial.std_field_um == pytest.approx(np.abs(growth.operators[ia]) @ std, rel=1e-12)


def test_forecast_matches_the_full_march(
    spec: SpindleSpec, fe: FEModel, growth: GrowthModel, ctx: GrowthContext, terms: ConditionTerms
) -> None:
    qf, qr = _heats(spec, 5000.0)
    ia, ir = _rows(growth)
    hot = steady_state(fe, H, ambient_c=AMB, q_front_w=2 * qf, q_rear_w=2 * qr)
    for field in (np.full(fe.n_nodes, AMB), hot):  # warm-up from cold, cool-down from hotter
        exact = forecast_growth(
            fe, growth, H, field_c=field, t_ref_c=AMB, ambient_c=AMB, q_front_w=qf, q_rear_w=qr
        )
        est = estimate_growth(ctx, terms, FieldBelief(mean_c=field), t_ref_c=AMB, at=AT)
        assert est.forecast.steady_axial.um == pytest.approx(exact.steady_um[ia], rel=1e-9)
        assert est.forecast.steady_radial.um == pytest.approx(exact.steady_um[ir], rel=1e-9)
        assert est.forecast.horizons_s == tuple(exact.horizons_s)
        for k, (ax, rad) in enumerate(zip(est.forecast.axial, est.forecast.radial, strict=True)):
            assert ax.um == pytest.approx(exact.at_horizon_um[k, ia], abs=0.01)  # 12 modes + the rest
            assert rad.um == pytest.approx(exact.at_horizon_um[k, ir], abs=0.01)
        assert est.forecast.tau_s == pytest.approx(exact.tau_s[ia], rel=1e-6)
        assert est.forecast.slowest_tau_s == pytest.approx(exact.slowest_tau_s, rel=1e-6)


def test_h_part_and_sensitivity_match_model_growth(
    spec: SpindleSpec, fe: FEModel, growth: GrowthModel, ctx: GrowthContext, terms: ConditionTerms
) -> None:
    qf, qr = _heats(spec, 5000.0)
    jac = steady_jacobian_h(fe, H, ambient_c=AMB, q_front_w=qf, q_rear_w=qr)
    ia, _ = _rows(growth)
    field = np.full(fe.n_nodes, AMB)
    est = estimate_growth(ctx, terms, FieldBelief(mean_c=field, includes_h=False), t_ref_c=AMB, at=AT)
    h_std = h_growth_std_um(growth.operators, jac, COV_H)[ia]
    assert est.forecast.steady_axial.std_h_um == pytest.approx(h_std, rel=1e-9)
    assert est.forecast.steady_axial.std_field_um == 0.0
    assert est.axial.std_h_um == pytest.approx(h_std, rel=1e-9)  # the steady Jacobian stands in
    lo, hi = est.forecast.steady_axial.ci95_um
    assert (hi - lo) / 2 == pytest.approx(Z95 * h_std, rel=1e-12)
    # 30 min ahead of a cold field: part of the way to the steady H sensitivity, not all of it
    assert 0.0 < est.forecast.axial[-1].std_h_um < h_std
    recon = reconstruction_h_fit(fe, jac, noise_c=0.15, prior_cov_h=np.diag((0.3 * H) ** 2))
    sens = sensor_sensitivity(growth.operators, recon)[ia]
    assert np.allclose(est.sensitivity_axial_um_per_k, sens, rtol=1e-9, atol=1e-12)


def test_combined_ci_is_the_root_sum_of_squares(
    ctx: GrowthContext, terms: ConditionTerms, fe: FEModel
) -> None:
    assert ctx.phi is not None
    p = 0.04 * np.eye(ctx.phi.shape[1])
    est = estimate_growth(
        ctx, terms, FieldBelief(mean_c=np.full(fe.n_nodes, AMB), cov=p, includes_h=False), t_ref_c=AMB, at=AT
    )
    v = est.axial
    assert v.std_field_um > 0 and v.std_h_um > 0
    assert v.std_um == pytest.approx(np.hypot(v.std_field_um, v.std_h_um), rel=1e-12)
    assert v.ci95_um[1] - v.um == pytest.approx(Z95 * v.std_um, rel=1e-12)
    assert v.ci95_field_um[1] - v.um == pytest.approx(Z95 * v.std_field_um, rel=1e-12)
    assert v.ci95_h_um[0] == pytest.approx(v.um - Z95 * v.std_h_um, rel=1e-12)


def test_time_is_utc(ctx: GrowthContext, terms: ConditionTerms, fe: FEModel) -> None:
    b = FieldBelief(mean_c=np.full(fe.n_nodes, AMB))
    local = AT.astimezone(timezone(timedelta(hours=2)))
    assert estimate_growth(ctx, terms, b, t_ref_c=AMB, at=local).at.utcoffset() == timedelta(0)
    with pytest.raises(GrowthEstimateError, match="at"):
        estimate_growth(ctx, terms, b, t_ref_c=AMB, at=datetime(2026, 3, 1, 12, 0))


@pytest.mark.parametrize(
    ("belief", "field"),
    [
        (FieldBelief(), "mean_c"),
        (FieldBelief(mean_c=np.zeros(3)), "belief.mean_c"),
        (FieldBelief(state=np.zeros(99)), "belief.state"),
        (FieldBelief(state=np.zeros(4), cov=np.eye(3)), "belief.cov"),
        (FieldBelief(state=np.zeros(4), cov=np.eye(4), std_c=np.ones(4)), "at most one"),
    ],
)
def test_bad_beliefs_are_named(
    ctx: GrowthContext, terms: ConditionTerms, belief: FieldBelief, field: str
) -> None:
    with pytest.raises(GrowthEstimateError, match=field):
        estimate_growth(ctx, terms, belief, t_ref_c=AMB, at=AT)


def test_bad_condition_is_named(ctx: GrowthContext) -> None:
    with pytest.raises(GrowthEstimateError, match="horizons_s"):
        condition_terms(ctx, h=H, cov_h=COV_H, ambient_c=AMB, q_front_w=1, q_rear_w=1, horizons_s=(305.0,))
    with pytest.raises(GrowthEstimateError, match=r"^h:"):
        condition_terms(ctx, h=-H, cov_h=COV_H, ambient_c=AMB, q_front_w=1, q_rear_w=1)
    with pytest.raises(GrowthEstimateError, match="ambient_c"):
        condition_terms(ctx, h=H, cov_h=COV_H, ambient_c=float("nan"), q_front_w=1, q_rear_w=1)


def test_h_cov_from_log_ci_round_trip() -> None:
    sigma_log = np.linspace(0.02, 0.4, 7)
    ci = np.column_stack([H * np.exp(-Z95 * sigma_log), H * np.exp(Z95 * sigma_log)])
    corr = np.eye(7)
    corr[4, 6] = corr[6, 4] = -0.5
    cov = h_cov_from_ci(H, ci, corr)
    assert np.allclose(np.sqrt(np.diag(cov)), H * sigma_log, rtol=1e-12)
    assert cov[4, 6] == pytest.approx(-0.5 * H[4] * sigma_log[4] * H[6] * sigma_log[6], rel=1e-12)
    with pytest.raises(GrowthEstimateError, match="ci95"):
        h_cov_from_ci(H, ci[:, ::-1])
    with pytest.raises(GrowthEstimateError, match="ci95"):
        h_cov_from_ci(H, np.where(np.arange(7)[:, None] == 3, np.inf, ci))


def test_plc_mapping_units_and_sign() -> None:
    down = plc_compensation(12.34)  # tool points to -Z: the tip moved -12.34 µm, the axis must go +
    assert down.correction_um == pytest.approx(12.34)
    assert down.sd43900_mm == pytest.approx(0.01234)
    assert down.isg_offset_0p1um == 123
    assert down.sd42960_tool_axis_mm == pytest.approx(0.01234)  # a longer tool, whatever the axis
    assert down.sd43910_slope == 0.0 and down.isg_coefficient_um_per_m == 0.0
    up = plc_compensation(12.36, tool_dir=1)
    assert up.sd43900_mm == pytest.approx(-0.01236) and up.isg_offset_0p1um == -124
    with pytest.raises(GrowthEstimateError, match="tool_dir"):
        plc_compensation(1.0, tool_dir=0)


@pytest.mark.slow
def test_steady_ci_is_honest_against_the_plant_mesh(spec: SpindleSpec, ctx: GrowthContext) -> None:
    """H drawn from the served Σ_H (as if the identification's CI were right): the plant's own steady growth
    (finer mesh, its own growth model) falls in the served steady CI about 95 % of the time."""
    plant_fe = build_fe_model(spec, mesh_size_m=spec.plant_mesh_size_m)
    plant_growth = build_growth_model(spec, plant_fe)
    ia = plant_growth.names.index("nose_axial")
    qf, qr = _heats(spec, 6000.0)
    cov_h = np.diag((0.25 * H) ** 2)  # wide: H1-H4 are poorly identified in practice
    terms = condition_terms(
        ctx, h=H, cov_h=cov_h, ambient_c=AMB, q_front_w=qf, q_rear_w=qr, horizons_s=(300.0,)
    )
    est = estimate_growth(ctx, terms, FieldBelief(mean_c=np.full(ctx.g.shape[1], AMB)), t_ref_c=AMB, at=AT)
    lo, hi = est.forecast.steady_axial.ci95_um
    rng = np.random.default_rng(7)
    truths = []
    for _ in range(40):
        h = np.maximum(H + rng.multivariate_normal(np.zeros(7), cov_h), 1.0)
        t_ss = steady_state(plant_fe, h, ambient_c=AMB, q_front_w=qf, q_rear_w=qr)
        truths.append(plant_growth.growth_um(t_ss, AMB)[ia])
    assert 0.85 <= np.mean((lo <= np.array(truths)) & (np.array(truths) <= hi)) <= 1.0
    # and not uselessly wide: the served 1σ is the spread of the plant's growths (linearisation holds)
    assert 0.7 < np.std(truths) / est.forecast.steady_axial.std_um < 1.3
