"""The compensation reference's pure parts: the record's validation, the uniform equivalent of a field and
its 1σ, the reference's 1σ in the served CI, and the usable flag without a zero."""

from __future__ import annotations

from datetime import UTC, datetime

import numpy as np
import pytest

from service.engine.growthserve import NO_REFERENCE, without_reference
from service.estimate.reference import CompensationReference, ReferenceError, uniform_equivalent

AT = datetime(2026, 11, 27, 8, 0, tzinfo=UTC)


def _ref(**kw: object) -> CompensationReference:
    args: dict[str, object] = {"temperature_c": 21.5, "sd_c": 0.01, "at": AT, "source": "api", "set_by": "op"}
    return CompensationReference(**(args | kw))  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("kw", "field"),
    [
        ({"temperature_c": float("nan")}, "temperature_c"),
        ({"temperature_c": 400.0}, "temperature_c"),
        ({"sd_c": -0.1}, "sd_c"),
        ({"at": datetime(2026, 11, 27, 8, 0)}, "at"),
        ({"source": "guess"}, "source"),
        ({"set_by": " "}, "set_by"),
        ({"set_by": "x" * 65}, "set_by"),
    ],
)
def test_a_reference_refuses_what_is_not_one_naming_the_field(kw: dict[str, object], field: str) -> None:
    with pytest.raises(ReferenceError, match=field):
        _ref(**kw)


def test_the_uniform_equivalent_is_the_uniform_temperature_of_equal_growth() -> None:
    rng = np.random.default_rng(3)
    g = rng.normal(size=5)
    uniform = rng.normal(size=5)  # the reduced state of a uniform 1 K
    g1 = float(g @ uniform)
    a = 23.4 * uniform + 0.3 * rng.normal(size=5)  # 23.4 °C plus a non-uniform part
    cov = np.diag(rng.uniform(0.01, 0.1, 5))
    t, sd = uniform_equivalent(g, g1, a, cov)
    assert g1 * t == pytest.approx(float(g @ a))  # the growth over t is 0 for this field
    assert sd == pytest.approx(np.sqrt(g @ cov @ g) / abs(g1))
    t_exact, sd_exact = uniform_equivalent(g, g1, 23.4 * uniform, np.zeros((5, 5)))
    assert t_exact == pytest.approx(23.4) and sd_exact == 0.0
    with pytest.raises(ReferenceError, match="g1"):
        uniform_equivalent(g, 0.0, a, cov)


def test_without_a_zero_compensation_is_not_usable_and_says_so_first_other_reasons_stay() -> None:
    assert without_reference(True, None, None) == (False, NO_REFERENCE)
    assert NO_REFERENCE.startswith("no_reference: ")
    assert without_reference(False, "stale: no sample", None) == (False, "stale: no sample")
    assert without_reference(True, None, _ref()) == (True, None)
