"""The Kubernetes example (deploy/k8s/spindle.yaml): schema-valid, and consistent with the code and the image.

No cluster is used: ``kubernetes-validate --strict`` checks every resource against the Kubernetes 1.30 schemas
(unknown fields rejected), and the rest checks the container against the CLI, the settings and the Dockerfile.
"""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path
from typing import Any

import pytest
import yaml

from service.cli import build_parser
from service.settings import Settings, load_settings
from tests.deploy.deployhelpers import ROOT, dockerfile_env, dockerfile_exec_form, runtime_stage

MANIFEST = ROOT / "deploy" / "k8s" / "spindle.yaml"
K8S_VERSION = "1.30.0"


def resources() -> dict[str, dict[str, Any]]:
    return {doc["kind"]: doc for doc in yaml.safe_load_all(MANIFEST.read_text()) if doc}


def container() -> dict[str, Any]:
    return resources()["Deployment"]["spec"]["template"]["spec"]["containers"][0]


def validate(path: Path) -> subprocess.CompletedProcess[str]:
    exe = shutil.which("kubernetes-validate")
    if exe is None:
        pytest.fail("kubernetes-validate not installed (pip install -e '.[test]')")
    argv = [exe, "--strict", "-k", K8S_VERSION, str(path)]
    return subprocess.run(argv, capture_output=True, text=True, timeout=120)


def test_manifests_match_the_kubernetes_schemas() -> None:
    result = validate(MANIFEST)
    assert result.returncode == 0, result.stdout + result.stderr
    assert set(resources()) == {"ConfigMap", "Deployment", "Service"}


def test_schema_check_would_catch_a_misspelt_field(tmp_path: Path) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text(MANIFEST.read_text().replace("readinessProbe:", "readinesProbe:", 1))
    assert validate(bad).returncode != 0


def test_one_instance_per_spindle_never_two() -> None:
    spec = resources()["Deployment"]["spec"]
    assert spec["replicas"] == 1 and spec["strategy"]["type"] == "Recreate"


def test_container_command_parses_and_migrates() -> None:
    argv = container()["args"]
    args = build_parser(argv).parse_args(argv)
    assert args.command == "run" and getattr(args, "migrate", False)
    assert dockerfile_exec_form("ENTRYPOINT") == ["chtc"]  # args are appended to the image entrypoint


def test_config_map_is_a_valid_settings_file_for_the_image(tmp_path: Path) -> None:
    config = tmp_path / "chtc.toml"
    config.write_text(resources()["ConfigMap"]["data"]["chtc.toml"])
    settings = load_settings(config)
    assert settings.api.host == "0.0.0.0" and settings.can.interface == "socketcan"
    assert str(settings.model.rom_cache_dir) == dockerfile_env()["CHTC_MODEL__ROM_CACHE_DIR"]
    mount = {m["name"]: m["mountPath"] for m in container()["volumeMounts"]}["config"]
    assert f"{mount}/chtc.toml" == container()["args"][container()["args"].index("--config") + 1]


def test_secrets_come_from_a_secret_and_name_real_settings() -> None:
    for var in container()["env"]:
        assert "value" not in var, f"{var['name']}: literal value in the manifest"
        assert "secretKeyRef" in var["valueFrom"]
        section, _, key = var["name"][5:].lower().partition("__")
        assert key in Settings.model_fields[section].annotation.model_fields


def test_probes_and_security_match_the_image() -> None:
    c = container()
    port = load_settings(ROOT / "deploy" / "chtc.container.toml").api.port
    assert c["ports"][0]["containerPort"] == port
    for probe in ("startupProbe", "livenessProbe", "readinessProbe"):
        assert c[probe]["httpGet"]["path"] == "/api/v1/healthz"
    user = next(a for w, a in runtime_stage() if w == "USER").split(":")[0]
    pod = resources()["Deployment"]["spec"]["template"]["spec"]["securityContext"]
    assert str(pod["runAsUser"]) == user and pod["runAsNonRoot"] is True
    service = resources()["Service"]["spec"]
    assert service["selector"] == resources()["Deployment"]["spec"]["selector"]["matchLabels"]
