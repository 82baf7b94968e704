"""``chtc identify``'s text output of one identification."""

from __future__ import annotations

from datetime import UTC, datetime
from types import SimpleNamespace

from service.commands.identify import format_record


def test_ci_bounds_of_a_hopeless_h_print_short_and_positive() -> None:
    """The log-H CI of an unidentifiable H printed as a 60-digit number and a lower bound of 0.0."""
    t = datetime(2026, 3, 2, 6, 0, tzinfo=UTC)
    r = SimpleNamespace(
        id=1,
        outcome="ok",
        condition=SimpleNamespace(id=2, speed_rpm=3000.0, ambient_c=22.0),
        window_from=t,
        window_to=t,
        h=[5.0] + [50.0] * 6,
        ci95_lo=[2.5e-12] + [40.0] * 6,
        ci95_hi=[2.25e59] + [60.0] * 6,
        identified=[False] + [True] * 6,
        fit=0.98,
        rmse_c=0.15,
    )
    text = format_record(r, (5.0, 200.0))
    assert "H1=5.0 [< 5, > 200]?" in text and "H2=50.0 [40.0, 60.0] " in text
    assert "e+" not in text and "e-" not in text
    # without a box: the fallback range, still no exponent
    assert "H1=5.0 [< 0.1, > 10000]?" in format_record(r)


def test_a_prior_dominated_h_is_marked() -> None:
    t = datetime(2026, 3, 2, 6, 0, tzinfo=UTC)
    r = SimpleNamespace(
        id=1,
        outcome="ok",
        condition=SimpleNamespace(id=2, speed_rpm=3000.0, ambient_c=22.0),
        window_from=t,
        window_to=t,
        h=[42.3] + [50.0] * 6,
        ci95_lo=[4.96] + [40.0] * 6,
        ci95_hi=[360.4] + [60.0] * 6,
        identified=[False] + [True] * 6,
        prior_dominated=[True] + [False] * 6,
        fit=0.98,
        rmse_c=0.15,
    )
    text = format_record(r, (5.0, 200.0))
    assert "H1=42.3 [< 5, > 200]? (prior)" in text and "H2=50.0 [40.0, 60.0] " in text


def test_bounds_print_with_three_significant_digits() -> None:
    from service.serve.numbers import format_bound

    box = (5.0, 200.0)
    assert [format_bound(x, box) for x in (3.42e-84, 1.5e26, 123.456, 45.67, 5.123, None)] == [
        "< 5",
        "> 200",
        "123",
        "45.7",
        "5.12",
        "–",
    ]
