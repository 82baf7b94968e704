"""The Helm chart (deploy/helm/spindle-chtc) for a plant of cells: rendered by Helm itself, schema-valid, and
consistent with the code and the image.

The renderer is Helm's own Go SDK (v4.2.3), loaded from the ``helm-python-sdk`` wheel (``helm_python``, a
ctypes binding of ``libhelm_c``): the same template engine, Sprig functions, ``required``/``fail`` and value
merging as ``helm template`` (docs/deploy-helm.md, "Why this renderer"). A missing renderer or validator is a
failure, never a skip. No cluster is used: ``kubernetes-validate --strict`` checks every rendered resource
against the Kubernetes 1.30 schemas, and the settings file of each cell is loaded with the service's own
``load_settings`` and split with ``Settings.per_spindle()``.
"""

from __future__ import annotations

import copy
import shutil
import subprocess
import tomllib
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import pytest
import yaml
from fastapi.testclient import TestClient

from api.deps import ClockInfo
from api.fleet import create_fleet_app
from api.routers.health import probes
from model.geometry import load_spindle
from service.cli import build_parser
from service.settings import Settings, load_settings
from tests.deploy.deployhelpers import ROOT, dockerfile_env, dockerfile_exec_form, runtime_stage
from tests.fakehost import bare_host

CHART = ROOT / "deploy" / "helm" / "spindle-chtc"
EXAMPLE = CHART / "examples" / "plant-3x4-values.yaml"
GEOMETRY = ROOT / "model" / "data" / "spindle.toml"
K8S_VERSION = "1.30.0"
RELEASE, NAMESPACE = "chtc", "chtc"


class RenderError(Exception):
    """The chart refused the values (Helm's ``required``/``fail``, or a template error): Helm's message."""


def render(values: dict[str, Any]) -> dict[str, str]:
    """``helm template chtc CHART -n chtc`` with ``values`` (as ``-f``/``--set-file`` give them)."""
    try:
        import helm_python
    except ImportError as err:  # never a skip: CI installs it with the [test] extra
        pytest.fail(f"helm-python-sdk (Helm's Go SDK) not installed (pip install -e '.[test]'): {err}")
    with helm_python.Chart.load(str(CHART)) as chart:
        try:
            return chart.render(values, name=RELEASE, namespace=NAMESPACE)
        except helm_python.HelmRenderError as err:
            raise RenderError(str(err)) from err


def plant_values() -> dict[str, Any]:
    """The 3 cells x 4 spindles example, with its geometry given as ``--set-file`` would."""
    values: dict[str, Any] = yaml.safe_load(EXAMPLE.read_text(encoding="utf-8"))
    values["geometries"] = {"spindle-a.toml": GEOMETRY.read_text(encoding="utf-8")}
    return values


def documents(rendered: dict[str, str]) -> list[dict[str, Any]]:
    return [doc for text in rendered.values() for doc in yaml.safe_load_all(text) if doc]


def of_kind(rendered: dict[str, str], kind: str) -> dict[str, dict[str, Any]]:
    return {d["metadata"]["name"]: d for d in documents(rendered) if d["kind"] == kind}


def pod(deployment: dict[str, Any]) -> dict[str, Any]:
    spec: dict[str, Any] = deployment["spec"]["template"]["spec"]
    return spec


def container(deployment: dict[str, Any]) -> dict[str, Any]:
    (main,) = [c for c in pod(deployment)["containers"] if c["name"] == "chtc"]
    return main


def checksums(rendered: dict[str, str]) -> dict[str, str]:
    return {
        name: d["spec"]["template"]["metadata"]["annotations"]["checksum/config"]
        for name, d in of_kind(rendered, "Deployment").items()
    }


def materialise(cell: str, rendered: dict[str, str], root: Path) -> Path:
    """The cell's config volume as the kubelet lays it out (the Deployment's items), under ``root``."""
    deployment = of_kind(rendered, "Deployment")[f"{RELEASE}-{cell}"]
    (volume,) = [v for v in pod(deployment)["volumes"] if v["name"] == "config"]
    data = of_kind(rendered, "ConfigMap")[volume["configMap"]["name"]]["data"]
    for item in volume["configMap"]["items"]:
        target = root / item["path"]
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_text(data[item["key"]], encoding="utf-8")
    (mount,) = [m["mountPath"] for m in container(deployment)["volumeMounts"] if m["name"] == "config"]
    args = container(deployment)["args"]
    config_path = Path(args[args.index("--config") + 1])
    return root / config_path.relative_to(mount)


def kubernetes_validate(path: Path) -> subprocess.CompletedProcess[str]:
    exe = shutil.which("kubernetes-validate")
    if exe is None:
        pytest.fail("kubernetes-validate not installed (pip install -e '.[test]')")
    argv = [exe, "--strict", "-k", K8S_VERSION, str(path)]
    return subprocess.run(argv, capture_output=True, text=True, timeout=120)


@pytest.fixture(scope="module")
def plant() -> dict[str, str]:
    return render(plant_values())


def test_one_deployment_config_map_and_service_per_cell(plant: dict[str, str]) -> None:
    cells = {f"{RELEASE}-cell{i}" for i in (1, 2, 3)}
    assert set(of_kind(plant, "Deployment")) == cells
    assert set(of_kind(plant, "ConfigMap")) == cells
    assert set(of_kind(plant, "Service")) == cells
    assert set(of_kind(plant, "Job")) == {f"{RELEASE}-migrate"}
    for name, d in of_kind(plant, "Deployment").items():
        assert d["metadata"]["namespace"] == NAMESPACE
        assert d["spec"]["replicas"] == 1 and d["spec"]["strategy"]["type"] == "Recreate"
        selector = d["spec"]["selector"]["matchLabels"]
        assert of_kind(plant, "Service")[name]["spec"]["selector"] == selector
        assert d["spec"]["template"]["metadata"]["labels"].items() >= selector.items()
    selectors = [
        tuple(sorted(d["spec"]["selector"]["matchLabels"].items()))
        for d in of_kind(plant, "Deployment").values()
    ]
    assert len(set(selectors)) == 3  # no Deployment adopts another cell's pod


def test_image_is_the_projects_own_release(plant: dict[str, str]) -> None:
    chart = yaml.safe_load((CHART / "Chart.yaml").read_text(encoding="utf-8"))
    version = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["project"]["version"]
    assert chart["appVersion"] == version
    single = next(
        d
        for d in yaml.safe_load_all((ROOT / "deploy" / "k8s" / "spindle.yaml").read_text())
        if d["kind"] == "Deployment"
    )
    image = single["spec"]["template"]["spec"]["containers"][0]["image"]  # the one-spindle example's
    for d in of_kind(plant, "Deployment").values():
        assert {c["image"] for c in pod(d)["containers"] + pod(d)["initContainers"]} == {image}


def test_each_cell_hosts_its_four_spindles_through_the_services_own_settings(
    plant: dict[str, str], tmp_path: Path
) -> None:
    values = plant_values()
    expected_geometry = load_spindle(GEOMETRY).name
    for cell in values["cells"]:
        config = materialise(cell["name"], plant, tmp_path / cell["name"])
        settings = load_settings(config)
        hosted = settings.per_spindle()
        assert [s.spindle.id for s in hosted] == [s["id"] for s in cell["spindles"]]
        assert len(hosted) == 4
        for got, want in zip(hosted, cell["spindles"], strict=True):
            assert (got.modbus.host, got.modbus.port) == (want["modbus"]["host"], want["modbus"]["port"])
            assert (got.can.interface, got.can.channel) == (want["can"]["interface"], want["can"]["channel"])
            assert got.spindle.description == want["description"]
            if "geometry" in want:  # the file the kubelet mounts, parsed by the model's own loader
                assert got.model.spindle is not None and got.model.spindle.is_file()
                assert load_spindle(got.model.spindle).name == expected_geometry
            else:
                assert got.model.spindle is None  # the packaged geometry (its reduced model is in the image)
        port = container(of_kind(plant, "Deployment")[f"{RELEASE}-{cell['name']}"])["ports"][0][
            "containerPort"
        ]
        assert settings.api.host == "0.0.0.0" and settings.api.port == port


def test_config_values_become_toml_the_settings_accept(tmp_path: Path) -> None:
    values = plant_values()
    values["config"] = {
        "modbus": {"port": 1502, "timeout_s": 0.5, "unit": 3},
        "can": {
            "interface": "socketcan",
            "filters": [{"can_id": 0x181, "can_mask": 0x7FF, "extended": False}],
        },
        "identification": {"schedule_min": [7, 20, 40, 60]},
        "mqtt": {"enabled": False},
    }
    del values["cells"][0]["spindles"][0]["modbus"]["port"]  # falls back to [modbus] port
    settings = load_settings(materialise("cell1", render(values), tmp_path))
    first = settings.per_spindle()[0]
    assert (first.modbus.port, first.modbus.unit, first.modbus.timeout_s) == (1502, 3, 0.5)
    assert first.can.filters is not None and first.can.filters[0].can_id == 0x181
    assert settings.identification.schedule_min == (7, 20, 40, 60)


def test_config_checksum_follows_the_cells_own_files() -> None:
    values = plant_values()
    before = checksums(render(values))
    assert len(set(before.values())) == 3
    moved = copy.deepcopy(values)
    moved["cells"][1]["spindles"][2]["modbus"]["host"] = "10.0.2.99"  # one DAQ of cell 2 re-addressed
    after = checksums(render(moved))
    assert after[f"{RELEASE}-cell2"] != before[f"{RELEASE}-cell2"]
    assert {k: v for k, v in after.items() if k != f"{RELEASE}-cell2"} == {
        k: v for k, v in before.items() if k != f"{RELEASE}-cell2"
    }
    reshaped = copy.deepcopy(values)
    reshaped["geometries"]["spindle-a.toml"] += "\n# housing re-measured\n"  # cells 1 and 2 use it
    changed = {k for k, v in checksums(render(reshaped)).items() if v != before[k]}
    assert changed == {f"{RELEASE}-cell1", f"{RELEASE}-cell2"}
    assert checksums(render(values)) == before  # deterministic


def test_database_url_and_token_come_from_secrets_and_name_real_settings(plant: dict[str, str]) -> None:
    workloads = [container(d) for d in of_kind(plant, "Deployment").values()]
    workloads += [
        c for j in of_kind(plant, "Job").values() for c in j["spec"]["template"]["spec"]["containers"]
    ]
    for c in workloads:
        env = {var["name"]: var for var in c["env"]}
        ref = env["CHTC_DATABASE__URL"]["valueFrom"]["secretKeyRef"]
        assert ref == {"name": "chtc-database", "key": "database-url"}
        for name, var in env.items():
            section, _, key = name.removeprefix("CHTC_").lower().partition("__")
            assert key in Settings.model_fields[section].annotation.model_fields, name
            if "URL" in name or "TOKEN" in name:
                assert "value" not in var and "secretKeyRef" in var["valueFrom"], name
    for c in workloads[:3]:
        assert {
            "name": "CHTC_API__TOKEN",
            "valueFrom": {"secretKeyRef": {"name": "chtc-api", "key": "api-token"}},
        } in c["env"]
    text = "\n".join(plant.values())
    assert "postgresql" not in text and "password" not in text.lower()


def test_probes_are_the_instances_root_health_endpoints(plant: dict[str, str]) -> None:
    served = {route.path for route in probes.routes}  # a one-spindle instance (api/app.py)
    for d in of_kind(plant, "Deployment").values():
        c = container(d)
        paths = {p: c[p]["httpGet"]["path"] for p in ("startupProbe", "livenessProbe", "readinessProbe")}
        assert paths == {"startupProbe": "/healthz", "livenessProbe": "/healthz", "readinessProbe": "/readyz"}
        assert set(paths.values()) <= served
        assert all(c[p]["httpGet"]["port"] == c["ports"][0]["name"] for p in paths)
        startup = c["startupProbe"]
        assert startup["periodSeconds"] * startup["failureThreshold"] >= 300  # a model build: ~1 min


def test_a_multi_spindle_instance_answers_the_probes_paths() -> None:
    """Cells run ``[[spindles]]`` instances (api/fleet.py): their own /healthz and /readyz answer."""
    host = bare_host(lambda: datetime.now(UTC))
    with TestClient(create_fleet_app(host, {}, clock_info=ClockInfo())) as client:  # type: ignore[arg-type]
        assert client.get("/healthz").status_code == 200
        ready = client.get("/readyz")
        assert ready.status_code == 503 and "no spindle runs" in ready.text  # not ready until models load


def test_commands_parse_and_only_the_hook_job_migrates(plant: dict[str, str]) -> None:
    assert dockerfile_exec_form("ENTRYPOINT") == ["chtc"]  # args are appended to the image's entrypoint
    for d in of_kind(plant, "Deployment").values():
        args = container(d)["args"]
        parsed = build_parser(args).parse_args(args)
        assert parsed.command == "run" and not parsed.migrate
    (job,) = of_kind(plant, "Job").values()
    assert job["metadata"]["annotations"]["helm.sh/hook"] == "pre-install,pre-upgrade"
    args = job["spec"]["template"]["spec"]["containers"][0]["args"]
    parsed = build_parser(args).parse_args(args)
    assert (parsed.command, parsed.action) == ("db", "upgrade")
    values = plant_values()
    values["migrations"] = {"job": False}
    assert of_kind(render(values), "Job") == {}


def test_security_and_model_cache_match_the_image(plant: dict[str, str]) -> None:
    user = next(a for w, a in runtime_stage() if w == "USER").split(":")[0]
    image_cache = dockerfile_env()["CHTC_MODEL__ROM_CACHE_DIR"]
    for d in of_kind(plant, "Deployment").values():
        spec = pod(d)
        assert str(spec["securityContext"]["runAsUser"]) == user and spec["securityContext"]["runAsNonRoot"]
        for c in spec["containers"] + spec["initContainers"]:
            assert c["securityContext"]["readOnlyRootFilesystem"] is True
            assert c["securityContext"]["allowPrivilegeEscalation"] is False
            assert c["resources"]["limits"]["memory"]
        env = {v["name"]: v.get("value") for v in container(d)["env"]}
        cache = env["CHTC_MODEL__ROM_CACHE_DIR"]  # the image's ENV points into its read-only root
        mounts = {m["mountPath"]: m["name"] for m in container(d)["volumeMounts"]}
        assert "emptyDir" in next(v for v in spec["volumes"] if v["name"] == mounts[cache])
        (seed,) = spec["initContainers"]
        assert seed["command"][-2:] == [f"{image_cache}/.", f"{cache}/"]


def test_rendered_plant_passes_kubernetes_validate_strict(plant: dict[str, str], tmp_path: Path) -> None:
    out = tmp_path / "plant.yaml"
    out.write_text("\n---\n".join(plant.values()), encoding="utf-8")
    result = kubernetes_validate(out)
    assert result.returncode == 0, result.stdout + result.stderr
    assert (result.stdout + result.stderr).count(" passed for resource ") == len(documents(plant)) == 10


def test_the_optional_branches_render_valid_manifests(tmp_path: Path) -> None:
    values = plant_values()
    cell = values["cells"][2]
    del cell["nodeName"]
    cell.update(
        nodeSelector={"plant.example/cell": "3"},
        hostNetwork=False,
        resources={"requests": {"cpu": "2", "memory": "3Gi"}, "limits": {"memory": "5Gi"}},
    )
    values.update(imagePullSecrets=[{"name": "regcred"}], apiToken={"existingSecret": ""})
    values["romCache"] = {"seedFromImage": False, "sizeLimit": "2Gi"}
    values["image"] = {"repository": "registry.plant.example/chtc", "tag": "0.2.0", "pullPolicy": "Always"}
    rendered = render(values)
    spec = pod(of_kind(rendered, "Deployment")[f"{RELEASE}-cell3"])
    assert spec["nodeSelector"] == {"plant.example/cell": "3"} and "nodeName" not in spec
    assert spec["hostNetwork"] is False and spec["dnsPolicy"] == "ClusterFirst"
    assert container({"spec": {"template": {"spec": spec}}})["resources"]["limits"]["memory"] == "5Gi"
    assert "initContainers" not in spec and spec["imagePullSecrets"] == [{"name": "regcred"}]
    assert all(c["image"].endswith(":0.2.0") for c in spec["containers"])
    assert "CHTC_API__TOKEN" not in {v["name"] for v in spec["containers"][0]["env"]}
    out = tmp_path / "variant.yaml"
    out.write_text("\n---\n".join(rendered.values()), encoding="utf-8")
    result = kubernetes_validate(out)
    assert result.returncode == 0, result.stdout + result.stderr


@pytest.mark.parametrize(
    ("broken", "original"),
    [("readinesProbe:", "readinessProbe:"), ("containerPort: http", "containerPort: 8000")],
)
def test_schema_check_would_catch_a_broken_render(
    plant: dict[str, str], tmp_path: Path, broken: str, original: str
) -> None:
    text = "\n---\n".join(plant.values())
    assert original in text
    bad = tmp_path / "bad.yaml"
    bad.write_text(text.replace(original, broken, 1), encoding="utf-8")
    assert kubernetes_validate(bad).returncode != 0


def helm_lint(chart: Path, values: dict[str, Any]) -> dict[str, Any]:
    import helm_python

    report: dict[str, Any] = helm_python.lint(
        str(chart), values, strict=True, namespace=NAMESPACE, kube_version=f"v{K8S_VERSION}"
    )
    return report


def test_helm_lint_strict_finds_nothing_above_info(tmp_path: Path) -> None:
    report = helm_lint(CHART, plant_values())
    assert report["errors"] == [] and [m for m in report["messages"] if m["severity"] >= 2] == []
    broken = tmp_path / "spindle-chtc"
    shutil.copytree(CHART, broken)
    (broken / "templates" / "broken.yaml").write_text("kind: ConfigMap\nmetadata: {name: [\n")
    report = helm_lint(broken, plant_values())  # the same lint does report a broken template
    assert report["errors"] or any(m["severity"] >= 2 for m in report["messages"])


def _edit(path: str, value: Any) -> dict[str, Any]:
    """The plant values with one dotted path (list indices as numbers) set; ``...`` deletes it."""
    values = plant_values()
    *parents, last = [int(p) if p.isdigit() else p for p in path.split(".")]
    node: Any = values
    for p in parents:
        node = node[p]
    if value is ...:
        del node[last]
    else:
        node[last] = value
    return values


@pytest.mark.parametrize(
    ("path", "value", "message"),
    [
        (
            "cells.2.spindles.1.id",
            "cell1-s3",
            'cells[2].spindles[1].id: "cell1-s3" is also cells[0].spindles[2].id',
        ),
        ("cells.0.spindles.3.id", ..., "cells[0].spindles[3].id: required"),
        ("cells.0.spindles.3.id", "3rd", 'cells[0].spindles[3].id: "3rd" is not a spindle id'),
        ("cells.1.spindles.0.modbus", {"port": 502}, "cells[1].spindles[0].modbus.host: required"),
        ("cells.1.spindles.2.modbus.host", "10.0.2.11", "cells[1].spindles[2].modbus: DAQ 10.0.2.11:502"),
        ("cells.0.spindles.1.can.channel", "can0", "cells[0].spindles[1].can: bus socketcan:can0 is also"),
        (
            "cells.0.spindles.1.geometry",
            "spindle-b.toml",
            'cells[0].spindles[1].geometry: "spindle-b.toml" is not',
        ),
        ("cells.2.name", "cell1", 'cells[2].name: "cell1" is also cells[0].name'),
        ("cells.2.name", "Cell_3", 'cells[2].name: "Cell_3" is not a DNS label'),
        ("cells.2.spindles", [], "cells[2].spindles: empty"),
        ("cells", [], "cells: empty"),
        ("database", {"existingSecret": ""}, "database.existingSecret: required"),
        ("config", {"spindle": {"id": "x"}}, "config.spindle: set by the chart"),
    ],
)
def test_bad_values_fail_the_render_naming_the_entry(path: str, value: Any, message: str) -> None:
    with pytest.raises(RenderError) as err:
        render(_edit(path, value))
    assert message in str(err.value)


def test_the_chart_defaults_alone_refuse_to_render() -> None:
    with pytest.raises(RenderError, match="cells: empty; give at least one cell"):
        render({})
