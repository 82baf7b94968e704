"""The compensation reference's pure parts: the record's validation, the uniform equivalent of a field and
its 1σ, and the zero of a spindle resting in equilibrium from one sample."""

from __future__ import annotations

from datetime import UTC, datetime

import numpy as np
import pytest

from service.contracts.reference import CompensationReference, ReferenceError
from service.estimate.reference import equilibrium_zero, uniform_equivalent

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


def test_an_equilibrium_zero_needs_rest_and_agreeing_channels() -> None:
    rng = np.random.default_rng(5)
    temps = 21.3 + rng.normal(0.0, 0.15, 32)
    off = rng.uniform(-0.2, 0.2, 32)
    good = np.ones(32, dtype=bool)
    good[3] = False
    temps[3] = 80.0  # a broken channel, flagged: not used
    zero = equilibrium_zero(temps + off, good, off, 0.0)
    assert zero is not None
    t, sd = zero
    assert abs(t - 21.3) < 4 * sd and 0.01 < sd < 0.05
    assert equilibrium_zero(temps + off, good, off, 1500.0) is None  # turning
    warm = temps + np.linspace(0.0, 3.0, 32)  # a gradient: not in equilibrium
    assert equilibrium_zero(warm + off, good, off, 0.0) is None
    assert equilibrium_zero(temps, np.arange(32) < 5, None, 0.0) is None  # too few good channels


def test_the_demo_zeroes_on_its_first_start_and_a_plain_service_does_not() -> None:
    from service.cli import build_parser
    from service.commands.demo import demo_settings
    from service.settings import Settings

    args = build_parser(["demo"]).parse_args(["demo", "--port", "8765"])
    settings, _token = demo_settings(args, "sqlite:///:memory:")
    assert settings.compensation.reference_on_first_start is True
    assert Settings().compensation.reference_on_first_start is False
