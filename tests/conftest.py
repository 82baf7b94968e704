"""Shared test configuration.

Markers: ``slow`` (more than about 5 s of setup or call on the 2-core box by itself, about 10 s when it is
shared as usual; run in CI, deselected by the fast subset ``-m "not slow"``), ``postgres`` (needs PostgreSQL
at ``CHTC_TEST_PG_URL``, default ``postgresql+psycopg://postgres@127.0.0.1:5432/test``), ``browser`` (needs
``/usr/bin/chromium``; a browser test is also ``slow``: each starts a headless Chromium, 4-11 s).
In CI (``CI=true``) a missing PostgreSQL or Chromium is a failure, not a skip.

A test not marked ``slow`` whose setup (a module or session fixture counts for the first test that needs it)
or call took more than ``SLOW_HINT_S`` is listed at the end of the run, as a hint to mark it or to share its
fixture: not a failure, since wall time on a shared machine is no verdict.
"""

from __future__ import annotations

import os
import shutil

# One BLAS thread, before numpy is imported anywhere (see service/cli.py: thread pools only contend here).
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import pytest  # noqa: E402

PG_URL = os.environ.get("CHTC_TEST_PG_URL", "postgresql+psycopg://postgres@127.0.0.1:5432/test")
IN_CI = os.environ.get("CI", "").lower() == "true"
SLOW_HINT_S = 10.0
_unmarked_slow: list[tuple[str, str, float]] = []


def _pg_available() -> bool:
    try:
        import sqlalchemy as sa

        engine = sa.create_engine(PG_URL, connect_args={"connect_timeout": 3})
        with engine.connect() as conn:
            conn.execute(sa.text("select 1"))
        engine.dispose()
        return True
    except Exception:
        return False


@pytest.fixture(scope="session")
def pg_url() -> str:
    if not _pg_available():
        if IN_CI:
            pytest.fail(f"PostgreSQL not reachable at {PG_URL} (required in CI)")
        pytest.skip(f"PostgreSQL not reachable at {PG_URL}")
    return PG_URL


@pytest.fixture(scope="session")
def chromium_path() -> str:
    path = shutil.which("chromium") or shutil.which("chromium-browser")
    if path is None:
        if IN_CI:
            pytest.fail("chromium not installed (required in CI)")
        pytest.skip("chromium not installed")
    return path


@pytest.hookimpl(tryfirst=True)  # before ``-m`` deselects
def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    for item in items:
        browser = item.get_closest_marker("browser") is not None
        if browser or "chromium_path" in getattr(item, "fixturenames", ()):
            item.add_marker(pytest.mark.slow)


def pytest_runtest_logreport(report: pytest.TestReport) -> None:
    if report.when in ("setup", "call") and report.duration > SLOW_HINT_S and "slow" not in report.keywords:
        _unmarked_slow.append((report.nodeid, report.when, report.duration))


def pytest_terminal_summary(terminalreporter: pytest.TerminalReporter) -> None:
    if _unmarked_slow:
        terminalreporter.section(f"not marked slow, over {SLOW_HINT_S:g} s (mark it, or share its fixture)")
        for nodeid, when, duration in sorted(_unmarked_slow, key=lambda x: -x[2]):
            terminalreporter.write_line(f"{duration:7.1f}s {when:5s} {nodeid}")
