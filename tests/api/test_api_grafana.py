"""The fleet dashboard (deploy/grafana, issue 29 item 7) against what ``/metrics`` really exposes: every
metric a panel queries exists on a running service, every query is filtered by the ``$spindle`` variable
(the ``spindle`` label each sample carries), and the provisioning files point Grafana at the dashboard."""

from __future__ import annotations

import json
import re
from pathlib import Path

import yaml
from fastapi.testclient import TestClient
from prometheus_client.parser import text_string_to_metric_families

ROOT = Path(__file__).resolve().parents[2]
GRAFANA = ROOT / "deploy" / "grafana"
DASHBOARD = GRAFANA / "dashboards" / "spindle-chtc-fleet.json"
METRIC = re.compile(r"\b(chtc_[a-z0-9_]+)\b")


def _exprs() -> list[str]:
    dash = json.loads(DASHBOARD.read_text(encoding="utf-8"))
    return [t["expr"] for p in dash["panels"] for t in p["targets"]]


def test_every_panel_queries_exposed_metrics_of_the_selected_spindles(client: TestClient) -> None:
    r = client.get("/api/v1/metrics")
    assert r.status_code == 200
    exposed = {s.name for f in text_string_to_metric_families(r.text) for s in f.samples}
    exprs = _exprs()
    assert len(exprs) >= 9
    for expr in exprs:
        names = METRIC.findall(expr)
        assert names, expr
        missing = [n for n in names if n not in exposed]
        assert not missing, f"{expr}: not exposed by /metrics: {missing}"
        assert expr.count('spindle=~"$spindle"') == len(names), expr


def test_the_dashboard_is_templated_on_the_spindle_label() -> None:
    dash = json.loads(DASHBOARD.read_text(encoding="utf-8"))
    variables = {v["name"]: v for v in dash["templating"]["list"]}
    spindle = variables["spindle"]
    assert spindle["type"] == "query" and spindle["multi"] and spindle["includeAll"]
    assert "label_values(chtc_build_info, spindle)" in json.dumps(spindle["query"])
    titles = " ".join(p["title"] for p in dash["panels"]).lower()
    for what in ("usable", "status", "growth", "ci", "h1", "device health", "identification rate"):
        assert what in titles, what
    ids = [p["id"] for p in dash["panels"]]
    assert len(ids) == len(set(ids))


def test_provisioning_points_at_the_dashboards() -> None:
    dash_prov = yaml.safe_load((GRAFANA / "provisioning" / "dashboards" / "spindle-chtc.yaml").read_text())
    (provider,) = dash_prov["providers"]
    assert dash_prov["apiVersion"] == 1 and provider["type"] == "file"
    assert provider["options"]["path"].startswith("/")
    ds = yaml.safe_load((GRAFANA / "provisioning" / "datasources" / "prometheus.yaml").read_text())
    assert [d["type"] for d in ds["datasources"]] == ["prometheus"]
