"""The served modes' MAP fit (``identify(prior=...)``, ``model.identify_prior``) on virtual-plant data (the
plant's finer mesh, never the fitted model's output): an H a short window cannot see keeps the prior's value
and band, finite and flagged ``prior_dominated``; an H the data see is not moved by the wide cold prior."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from model.identify import IdentificationResult, Window, identify
from model.identify_prior import COLD_SD_LOG, HPrior, PriorError, condition_prior, with_map
from model.inputs import inputs_from_operation

from .conftest import Condition

Z95 = 1.959964


def _window(model: Any, cond: Condition, steps: int) -> Window:
    run = cond.run
    inputs = inputs_from_operation(
        model.spec,
        dt_s=10.0,
        speed_rpm=run.speed_rpm[:steps],
        torque_nm=run.torque_nm[:steps],
        ambient_c=run.ambient_c[:steps],
    )
    mask = np.ones(32, dtype=bool)
    return Window(inputs, run.temps_c[: steps + 1], mask, float(run.ambient_c[0]), speed_rpm=cond.speed_rpm)


def _fit(model: Any, window: Window, prior: HPrior | None) -> IdentificationResult:
    return identify(model.rom, window, rng=0, box=model.ref.h_box, prior=prior, offset_sd_c=0.0)


@pytest.fixture(scope="module")
def short(model: Any, cond3000: Condition) -> tuple[IdentificationResult, IdentificationResult, HPrior]:
    """A 10-min window at 3000 rpm from a cold start: too short to see every H."""
    window = _window(model, cond3000, 60)
    prior = condition_prior(model.spec, cond3000.speed_rpm, box=model.ref.h_box)
    return _fit(model, window, None), _fit(model, window, prior), prior


def test_an_unseen_h_keeps_the_priors_value_and_band(model: Any, short: Any) -> None:
    plain, post, prior = short
    lo_box, hi_box = model.ref.h_box
    unseen = plain.h_ci95[:, 1] > 10 * hi_box  # the unregularised fit's CI runs to powers of ten
    assert unseen.any(), plain.h_ci95
    assert np.all(post.prior_dominated[unseen]) and not np.any(post.identified[unseen])
    # the served band: finite, within 10x the search box, about the prior's own (the data halved its
    # variance nowhere there: half-width in ln H between √0.5 and 1 times the prior's, plus a little)
    assert np.all(np.isfinite(post.h_ci95)) and np.all(post.h_ci95 > 0)
    assert np.all(post.h_ci95[:, 1] <= 10 * hi_box) and np.all(post.h_ci95[:, 0] >= lo_box / 10)
    half = 0.5 * np.log(post.h_ci95[unseen, 1] / post.h_ci95[unseen, 0])
    assert np.all(half >= np.sqrt(0.5) * Z95 * COLD_SD_LOG) and np.all(half <= 1.02 * Z95 * COLD_SD_LOG)
    # its value stays within the prior's 1σ of the prior's mean
    assert np.all(np.abs(np.log(post.h[unseen]) - prior.log_mean[unseen]) <= COLD_SD_LOG)


def test_a_prior_dominated_h_is_never_identified(short: Any) -> None:
    _, post, _ = short
    assert not np.any(post.identified & post.prior_dominated)
    assert post.prior_source is not None and "MAP fit" in post.message


def test_an_h_the_data_see_is_not_moved_by_the_wide_prior(model: Any, cond3000: Condition) -> None:
    window = _window(model, cond3000, 360)  # the whole hour
    prior = condition_prior(model.spec, cond3000.speed_rpm, box=model.ref.h_box)
    plain, post = _fit(model, window, None), _fit(model, window, prior)
    seen = plain.identified
    assert seen.sum() >= 3, plain.identified
    assert np.all(post.identified[seen]) and not np.any(post.prior_dominated[seen])
    np.testing.assert_allclose(post.h[seen], plain.h[seen], rtol=0.02)
    width = np.log(post.h_ci95[:, 1] / post.h_ci95[:, 0])
    width0 = np.log(plain.h_ci95[:, 1] / plain.h_ci95[:, 0])
    np.testing.assert_allclose(width[seen], width0[seen], rtol=0.05)
    covered = (post.h_ci95[:, 0] <= cond3000.h_true) & (cond3000.h_true <= post.h_ci95[:, 1])
    assert covered[seen].all()


def test_without_a_prior_nothing_is_flagged(short: Any) -> None:
    plain, _, _ = short
    assert not plain.prior_dominated.any() and plain.prior_source is None


def test_the_cold_prior_is_the_physics_curves_in_the_box(model: Any) -> None:
    lo, hi = model.ref.h_box
    for speed in (0.0, 3000.0, 7000.0):
        p = condition_prior(model.spec, speed, box=(lo, hi))
        h = np.exp(p.log_mean)
        assert np.all((h >= lo * (1 - 1e-12)) & (h <= hi * (1 + 1e-12)))
        np.testing.assert_allclose(np.sqrt(np.diag(p.log_cov)), COLD_SD_LOG)
        # its 95 % band stays within 10x the box for any H in the box
        assert np.all(h * np.exp(Z95 * COLD_SD_LOG) <= 10 * hi) and np.all(
            h * np.exp(-Z95 * COLD_SD_LOG) >= lo / 10
        )


def test_a_map_adds_only_its_data_information() -> None:
    cold = HPrior(np.zeros(7), np.eye(7), source="cold")
    # a map whose posterior is its own cold prior (no data) leaves the cold prior as it is
    same = with_map(
        cold,
        post_mean=np.ones(7),
        post_cov=4 * np.eye(7),
        map_cold_mean=np.ones(7),
        map_cold_cov=4 * np.eye(7),
        weight=0.25,
    )
    np.testing.assert_allclose(same.log_mean, 0.0, atol=1e-12)
    np.testing.assert_allclose(same.log_cov, np.eye(7), atol=1e-12)
    # data information 1/0.01 - 1/4 on H1 at 0.5: weighted by 0.25, fused with the cold N(0, 1)
    post_cov = 4 * np.eye(7)
    post_cov[0, 0] = 0.01
    mean = np.ones(7)
    mean[0] = 0.5
    fused = with_map(
        cold,
        post_mean=mean,
        post_cov=post_cov,
        map_cold_mean=np.ones(7),
        map_cold_cov=4 * np.eye(7),
        weight=0.25,
    )
    lam_data = 1 / 0.01 - 1 / 4
    eta_data = 0.5 / 0.01 - 1 / 4
    assert fused.log_cov[0, 0] == pytest.approx(1 / (1 + 0.25 * lam_data))
    assert fused.log_mean[0] == pytest.approx(0.25 * eta_data / (1 + 0.25 * lam_data))
    np.testing.assert_allclose(fused.reference_var, 1.0)  # prior_dominated stays judged on the cold band


def test_a_bad_prior_is_refused() -> None:
    with pytest.raises(PriorError, match="log_cov"):
        HPrior(np.zeros(7), -np.eye(7))
    with pytest.raises(PriorError, match="log_mean"):
        HPrior(np.zeros(6), np.eye(7))
