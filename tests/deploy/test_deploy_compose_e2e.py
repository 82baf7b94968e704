"""Compose without Docker: the services of ``docker-compose.yml`` as local processes, checked end to end.

The ``simulator`` and ``chtc`` services run from their own compose ``command`` and ``environment`` (with the
image's ENTRYPOINT and ENV from ``deploy/Dockerfile``; see ``tests/deploy/localstack.py`` for how hosts, ports
and paths are mapped to loopback). PostgreSQL is the local cluster (``pg_url``) with a fresh database. The
image build step ``chtc prebuild`` runs first, as ``docker build`` would. Then: the service migrates the empty
database, reaches the simulator over Modbus TCP and the python-can-remote hub, identifies H1-H7 and serves
them for the current condition on ``/api/v1/chtc`` (``fresh``, or ``at-bound`` naming the zones when the short
trial window leaves an H on a bound of the search box); the image's HEALTHCHECK command and the postgres
healthcheck pass; the API token from the ``.env`` is the one the service accepts. Every process is killed at
the end.

The only deviation from the compose file is the identification timing (``TRIAL_TIMING``), for either
``identification.mode``: the shipped per-condition schedule identifies 7 min after a condition change on 7 min
of data, the speed map fits first after 10 min of data; the test asks for 45 s (1-s samples: 45 of them, 30
needed) so that it ends in a few minutes (it asked for 90 s of 2-s samples: 45 s more of the run). The plant
still runs in real time, as in the compose file. The mode is the settings' default (the compose file does not
set it): the test is about the deployment, not the identification.
"""

from __future__ import annotations

import json
import os
import re
import secrets
import shlex
import shutil
import subprocess
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
import sqlalchemy as sa
from sqlalchemy.engine import make_url

from service.settings import default_cache_dir
from service.shell.service import MAP_H_BOX
from tests.deploy.deployhelpers import ROOT, load_compose, runtime_stage
from tests.deploy.localstack import (
    DB_VAR,
    Localizer,
    Proc,
    container_ports,
    free_port,
    process_argv,
    process_env,
    stage_files,
    start,
    tree_rss_mib,
    wait_for,
)

pytestmark = [pytest.mark.slow, pytest.mark.postgres, pytest.mark.timeout(1200)]

DATABASE = f"chtc_compose_test_{os.getpid()}"  # unique: concurrent runs must not drop each other's database
TRIAL_TIMING = {  # identify 45 s after the condition starts on 45 samples (model.identify needs >= 30)
    "CHTC_ACQUISITION__SAMPLE_PERIOD_S": "1",
    "CHTC_IDENTIFICATION__SCHEDULE_MIN": "[0.75]",
    "CHTC_IDENTIFICATION__MIN_WINDOW_S": "45",
    "CHTC_IDENTIFICATION__MAX_WINDOW_S": "45",
    "CHTC_DETECTOR__HOLD_S": "10",
    # speed-map mode: the first map fit after 45 s of data, refits every 45 s
    "CHTC_EXPERIMENTAL__MAP_MIN_WINDOW_MIN": "0.75",
    "CHTC_IDENTIFICATION__MAP_REFIT_MIN": "0.75",
}
CONTAINER_DIRS = ("/etc/chtc", "/var/lib/chtc")  # mapped under the test's work directory
OPERATIONS = ROOT / "deploy" / "OPERATIONS.md"
IMAGE_CACHE = "/opt/chtc/cache"  # mapped to the local reduced-model cache (shared with other runs)


@pytest.fixture
def compose_db(pg_url: str) -> Iterator[str]:
    """An empty database ``chtc_compose_test_<pid>`` in the local cluster, dropped afterwards."""
    admin = sa.create_engine(pg_url, isolation_level="AUTOCOMMIT")
    drop = sa.text(f'DROP DATABASE IF EXISTS "{DATABASE}" WITH (FORCE)')
    with admin.connect() as conn:
        conn.execute(drop)
        conn.execute(sa.text(f'CREATE DATABASE "{DATABASE}"'))
    try:
        yield DATABASE
    finally:
        with admin.connect() as conn:
            conn.execute(drop)
        admin.dispose()


@pytest.fixture
def stack(tmp_path: Path, pg_url: str, compose_db: str) -> Iterator[dict[str, Any]]:
    """The compose stack as local processes; yields what the test needs, kills everything at the end."""
    dotenv = {"CHTC_API_TOKEN": secrets.token_hex(16), "POSTGRES_PASSWORD": secrets.token_hex(8)}
    compose = load_compose(dotenv)
    services = compose["services"]
    ports = {p: free_port() for p in container_ports(compose)}
    ports[5432] = make_url(pg_url).port or 5432
    paths = {d: str(tmp_path / d.lstrip("/")) for d in CONTAINER_DIRS}
    paths[IMAGE_CACHE] = str(default_cache_dir())
    localize = Localizer(hosts=tuple(services), ports=ports, paths=paths)
    workdir = Path(localize("/var/lib/chtc"))
    workdir.mkdir(parents=True)
    stage_files({}, localize, tmp_path)  # the image's own files (COPY), as `docker build` puts them
    prebuild(localize, workdir)

    procs: list[Proc] = []
    try:
        for name in ("simulator", "chtc"):  # the depends_on order; postgres is the local cluster
            service = services[name]
            stage_files(service, localize, tmp_path)
            extra = TRIAL_TIMING if name == "chtc" else {}
            env = process_env(service, localize, pg_url=pg_url, database=compose_db, extra=extra)
            procs.append(start(name, process_argv(service, localize), env, workdir))
        api = f"http://127.0.0.1:{ports[8000]}"
        yield {"api": api, "procs": procs, "dotenv": dotenv, "localize": localize, "compose": compose}
    finally:
        codes = {p.name: p.stop() for p in reversed(procs)}  # compose stops dependents first
        print("exit codes after SIGTERM:", codes)


def prebuild(localize: Localizer, workdir: Path) -> None:
    """The image's ``RUN ... chtc prebuild ...`` step, localised (builds or finds the reduced model)."""
    runs = " ".join(args for word, args in runtime_stage() if word == "RUN")
    step = re.search(r"(chtc prebuild[^&]*)", runs)
    assert step is not None
    argv = shlex.split(localize(step.group(1)))
    result = subprocess.run(argv, cwd=workdir, capture_output=True, text=True, timeout=900)
    assert result.returncode == 0, result.stdout + result.stderr


def get_json(url: str, **kw: Any) -> tuple[int, Any]:
    r = httpx.get(url, timeout=5.0, **kw)
    return r.status_code, r.json()


def test_compose_stack_serves_fresh_h_from_the_simulator(stack: dict[str, Any], pg_url: str) -> None:
    api, procs = stack["api"], stack["procs"]

    def healthy() -> tuple[bool, Any]:
        code, body = get_json(f"{api}/api/v1/healthz")
        devices = {d["name"]: d["status"] for d in body["devices"]}
        ok = (
            code == 200
            and body["model_loaded"]
            and all(devices.get(k) == "ok" for k in ("modbus", "can", "db"))
        )
        return ok, body

    health = wait_for("the API with modbus, can and db ok", healthy, deadline_s=420, procs=procs)
    assert health["model_version"]

    assert_database_migrated(pg_url)
    assert_image_healthcheck_passes(stack["localize"])
    assert_simulator_healthcheck_passes(stack["compose"], stack["localize"])
    assert_postgres_healthcheck_passes(stack["compose"], stack["localize"])

    def current() -> tuple[bool, Any]:
        # identified at the current condition from fresh data: `fresh`, or `at-bound` when the 45-s trial
        # window leaves an H on a bound of the search box (never `fresh` then, and not usable)
        code, body = get_json(f"{api}/api/v1/chtc")
        return code == 200 and body["status"] in ("fresh", "at-bound"), body

    chtc = wait_for(
        "H of the current condition on /api/v1/chtc", current, deadline_s=600, procs=procs, period_s=2.0
    )
    service_pid = next(p for p in procs if p.name == "chtc").popen.pid
    print(f"resident memory at the first current H: chtc + worker {tree_rss_mib(service_pid):.0f} MiB")
    assert chtc["sample_age_s"] < 60 and chtc["condition"]["state"] == "stable"
    bound = [z["name"] for z in chtc["zones"] if z["at_bound"]]
    assert (chtc["status"] == "at-bound") == bool(bound), chtc
    assert not (bound and chtc["usable_for_compensation"]), chtc
    assert chtc["unit"] == "W/(m²·K)"
    assert [z["name"] for z in chtc["zones"]] == [f"H{i}" for i in range(1, 8)]
    # inside the search box of the mode that ran: model.h_box per condition, the speed map's own box
    # (service.shell.service.MAP_H_BOX; /chtc/map answers 404 in per-condition mode)
    map_mode = get_json(f"{api}/api/v1/chtc/map")[0] != 404
    lo, hi = MAP_H_BOX if map_mode else (5.0, 200.0)
    assert all(lo <= z["h_w_m2k"] <= hi for z in chtc["zones"]), chtc
    assert 2900 <= chtc["condition"]["speed_rpm"] <= 3100  # the simulator's first segment: 3000 rpm
    assert chtc["identification_id"] in stored_identification_ids(pg_url)
    assert_metrics_named_in_the_operations_guide_exist(api)
    assert_token_from_dotenv_is_the_write_token(api, stack["dotenv"]["CHTC_API_TOKEN"])


def assert_metrics_named_in_the_operations_guide_exist(api: str) -> None:
    named = set(re.findall(r"\b(chtc_[a-z0-9_]+)", OPERATIONS.read_text(encoding="utf-8")))
    assert named, "the operations guide names no metric"
    text = httpx.get(f"{api}/api/v1/metrics", timeout=10).text
    exposed = {
        line.split("{")[0].split()[0] for line in text.splitlines() if line and not line.startswith("#")
    }
    exposed |= {name.removesuffix(suffix) for name in exposed for suffix in ("_bucket", "_count", "_sum")}
    assert named <= exposed, f"named in OPERATIONS.md but not exposed: {sorted(named - exposed)}"


def assert_database_migrated(pg_url: str) -> None:
    from service.store.migrate import current_revision, head_revision

    url = make_url(pg_url).set(database=DATABASE).render_as_string(hide_password=False)
    assert current_revision(url) == head_revision()


def stored_identification_ids(pg_url: str) -> set[int]:
    engine = sa.create_engine(make_url(pg_url).set(database=DATABASE))
    try:
        with engine.connect() as conn:
            return {row[0] for row in conn.execute(sa.text("SELECT id FROM identifications"))}
    finally:
        engine.dispose()


def assert_image_healthcheck_passes(localize: Localizer) -> None:
    """The Dockerfile's HEALTHCHECK CMD (exec form), localised, exits 0."""
    check = next(args for word, args in runtime_stage() if word == "HEALTHCHECK")
    argv = json.loads(check.split(" CMD ", 1)[1])
    result = subprocess.run([localize(a) for a in argv], capture_output=True, text=True, timeout=30)
    assert result.returncode == 0, result.stderr


def assert_simulator_healthcheck_passes(compose: dict[str, Any], localize: Localizer) -> None:
    """The simulator's own healthcheck (exec form), localised, exits 0 against the running simulator."""
    test = compose["services"]["simulator"]["healthcheck"]["test"]
    assert test[0] == "CMD"
    argv = [localize(a) for a in test[1:]]  # the port inside the Python snippet is mapped too
    result = subprocess.run(argv, capture_output=True, text=True, timeout=30)
    assert result.returncode == 0, result.stderr


def assert_postgres_healthcheck_passes(compose: dict[str, Any], localize: Localizer) -> None:
    """The postgres service's healthcheck against the local cluster (pg_isready checks the server only)."""
    test = compose["services"]["postgres"]["healthcheck"]["test"]
    if shutil.which("pg_isready") is None:
        pytest.skip("pg_isready not installed")
    argv = shlex.split(test[1]) if test[0] == "CMD-SHELL" else test[1:]
    port = localize("5432")
    result = subprocess.run(
        [*argv, "-h", "127.0.0.1", "-p", port], capture_output=True, text=True, timeout=30
    )
    assert result.returncode == 0, result.stdout + result.stderr


def assert_token_from_dotenv_is_the_write_token(api: str, token: str) -> None:
    url = f"{api}/api/v1/identifications"
    assert httpx.post(url, json={"reason": "e2e"}, timeout=10).status_code == 401
    wrong = httpx.post(url, json={"reason": "e2e"}, headers={"Authorization": "Bearer x"}, timeout=10)
    assert wrong.status_code == 403
    right = httpx.post(url, json={"reason": "e2e"}, headers={"Authorization": f"Bearer {token}"}, timeout=10)
    assert right.status_code in (202, 409), right.text  # accepted, or busy: either way authorised


def test_localizer_maps_hosts_ports_and_paths() -> None:
    loc = Localizer(
        hosts=("postgres", "simulator", "chtc"),
        ports={5020: 41000, 8000: 42000},
        paths={"/opt/chtc/cache": "/tmp/c"},
    )
    assert loc("ws://simulator:5020/") == "ws://127.0.0.1:41000/"
    assert loc("--modbus-host=0.0.0.0") == "--modbus-host=127.0.0.1"
    assert (
        loc('host = "simulator"\nport = 8000\nring = 18000')
        == 'host = "127.0.0.1"\nport = 42000\nring = 18000'
    )
    assert loc("/opt/chtc/cache") == "/tmp/c"
    assert loc("simulator-x") == "simulator-x" and loc("docker compose restart chtc") == (
        "docker compose restart chtc"
    )
    assert DB_VAR == "CHTC_DATABASE__URL"
