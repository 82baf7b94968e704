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
    text = format_record(r)
    assert "H1=5.0 [2.5e-12, 2.25e+59]?" in text and "H2=50.0 [40.0, 60.0] " in text
