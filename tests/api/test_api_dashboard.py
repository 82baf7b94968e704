"""The dashboard: served by the app without any external resource, and rendered by real headless Chromium,
over the real service (``simulator.served``)."""

from __future__ import annotations

import html
import json
import os
import re
import subprocess
import time
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
from fastapi.testclient import TestClient

from api.app import STATIC_DIR, create_app
from model.geometry import SpindleSpec, load_spindle
from model.plant import Segment
from service.settings import Settings
from simulator.served import DEMO_FED, Plan, Served, feed, served_service
from tests.api.conftest import (
    DEMO_WINDOWS,
    LENIENT_IDENTIFICATION,
    WRITE_TOKEN,
    LiveServer,
    served_map_mode,
    served_with_dead_devices,
    sqlite_url,
)
from tests.modes import PER_CONDITION

# the newest identification has all seven H identified: the banner then names only a case's own cause
LENIENT = Settings(identification={**LENIENT_IDENTIFICATION, **PER_CONDITION})

CHROMIUM_FLAGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--hide-scrollbars",
    "--virtual-time-budget=5000",
]


def test_dashboard_is_served_with_its_assets(ro_client: TestClient) -> None:
    page = ro_client.get("/")
    assert page.status_code == 200 and "text/html" in page.headers["content-type"]
    assert "default-src 'self'" in page.headers["content-security-policy"]
    for asset in ("/static/app.js", "/static/style.css"):
        assert asset in page.text
        assert ro_client.get(asset).status_code == 200


def test_dashboard_loads_nothing_from_outside() -> None:
    for path in STATIC_DIR.iterdir():
        text = path.read_text(encoding="utf-8")
        assert not re.search(r"(src|href)\s*=\s*[\"'](https?:)?//", text), path
        assert 'fetch("http' not in text and "import(" not in text, path


def _chromium(chromium_path: str, tmp: Path, url: str, *extra: str) -> str:
    """Run headless Chromium; fail on a JavaScript error or a CSP refusal logged to the console."""
    cmd = [chromium_path, *CHROMIUM_FLAGS, "--enable-logging=stderr", "--v=0"]
    cmd += [f"--user-data-dir={tmp / 'profile'}", *extra, url]
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=90, check=False)
    assert out.returncode == 0, out.stderr[-2000:]
    js_errors = [line for line in out.stderr.splitlines() if "Uncaught" in line or "Refused to" in line]
    assert not js_errors, js_errors
    return out.stdout


def _server(served: Served, settings: Settings | None = None) -> LiveServer:
    return LiveServer(create_app(settings or Settings(), served.service, clock=served.clock))


@pytest.fixture
def live_demo(served: Served) -> Iterator[tuple[LiveServer, Served]]:
    """The demo service with a new sample every 0.1 s (wall) while the page loads."""
    stop = served.feed_every(0.1)
    with _server(served) as server:
        yield server, served
    stop.set()


@pytest.mark.browser
def test_dashboard_renders_h_field_and_chart_in_chromium(
    chromium_path: str, tmp_path: Path, live_demo: tuple[LiveServer, Served]
) -> None:
    server, served = live_demo
    svc = served.service
    dom = _chromium(chromium_path, tmp_path, server.url + "/", "--dump-dom")
    assert 'data-rendered="1"' in dom, dom[:2000]
    snap = svc.chtc()
    assert snap is not None
    for name, h in zip(snap.zones, snap.h, strict=True):
        assert re.search(rf'id="h-{name}">{h:.2f}<', dom), name
    # the one status on the page is the compensation verdict the API serves (the service does not move
    # between the page's poll and this one: the demo plan's samples hold the state at condition 2)
    comp = httpx.get(server.url + "/api/v1/compensation", timeout=10).json()
    assert _attr(dom, "status", "data-status") == comp["status"]
    assert _attr(dom, "status", "data-usable") == str(comp["usable_for_compensation"]).lower()
    assert _attr(dom, "comp-verdict", "data-status") == comp["status"]
    if not comp["usable_for_compensation"]:  # the reason is the API's text, shown as it is
        assert html.escape(comp["reason"], quote=False) in dom
    # no device is down: no banner
    cls, hidden, text = _banner(dom)
    assert hidden, (cls, text)
    assert "identification #2" in dom
    # the header names the spindle the API says it serves (the layout is read before the first poll)
    spindle_id = httpx.get(server.url + "/api/v1/spindle", timeout=10).json()["spindle_id"]
    assert re.search(rf'id="spindle-id"[^>]*>{re.escape(spindle_id)}<', dom), spindle_id
    shot = tmp_path / "dashboard.png"
    _chromium(chromium_path, tmp_path, server.url + "/", "--window-size=1400,1500", f"--screenshot={shot}")
    assert shot.stat().st_size > 20_000  # a blank page is a few kB


def _attr(dom: str, element_id: str, name: str) -> str:
    """The value of attribute ``name`` of the element with ``id``, from a dumped DOM."""
    tag = re.search(rf'<[a-z]+ [^>]*id="{element_id}"[^>]*>', dom)
    assert tag is not None, element_id
    value = re.search(rf' {name}="([^"]*)"', tag.group(0))
    assert value is not None, (element_id, name, tag.group(0))
    return html.unescape(value.group(1))


def _banner(dom: str) -> tuple[str, bool, str]:
    """(class, hidden, text) of the banner."""
    m = re.search(r'<div id="banner" class="([^"]*)"( hidden="")?[^>]*>(.*?)</div>', dom, re.S)
    assert m is not None, dom[:1500]
    return m.group(1), m.group(2) is not None, html.unescape(re.sub(r"<[^>]+>", " ", m.group(3)))


@pytest.fixture(scope="module")
def spec() -> SpindleSpec:
    return load_spindle()


@pytest.mark.browser
def test_every_chart_has_ticks_and_units_and_the_section_names_its_parts(
    chromium_path: str, tmp_path: Path, served: Served, spec: SpindleSpec
) -> None:
    served.feed_next(30)
    svc = served.service
    with _server(served) as server:
        dom = _chromium(chromium_path, tmp_path, server.url + "/", "--window-size=1400,1000", "--dump-dom")
    assert 'data-rendered="1"' in dom, dom[:2000]
    units = {
        "h-chart": ("zone", "W/(m²·K)"),
        "field": ("z, mm", "r, mm"),
        "sensor-chart": ("time, UTC", "temperature, °C"),
        "condition-chart": ("time, UTC", "speed, rpm"),
    }
    for canvas, (x_title, y_unit) in units.items():
        assert x_title in _attr(dom, canvas, "data-x-title"), canvas
        assert y_unit in _attr(dom, canvas, "data-y-title"), canvas
        assert len(_attr(dom, canvas, "data-x-ticks").split()) >= 3, canvas
        y_ticks = [float(v) for v in _attr(dom, canvas, "data-y-ticks").split()]
        assert len(y_ticks) >= 3, canvas
        steps = np.diff(y_ticks)  # the labels as printed are evenly spaced (no rounding 32.5 to 33)
        np.testing.assert_allclose(steps, steps[0], rtol=1e-9, err_msg=canvas)
    assert _attr(dom, "h-chart", "data-x-ticks").split() == list(svc.chtc().zones)  # type: ignore[union-attr]
    assert _attr(dom, "field", "data-c-title") == "T, °C"
    times = _attr(dom, "sensor-chart", "data-x-ticks").split()
    assert all(re.fullmatch(r"\d\d:\d\d(:\d\d)?", t) for t in times), times
    # every named part of the spindle description is labelled on the section
    labelled = set(_attr(dom, "field", "data-parts").split())
    assert labelled == {r.name for r in spec.regions}
    assert {"pulley", "housing", "front_end_cap", "rear_end_cap", "shaft_body", "rear_bearing"} <= labelled
    # full sensor names (the spindle description's) in the legend, zone surfaces in the H table
    for ch in (1, 7, 13, 20, 32):
        name = spec.sensors[ch - 1].name
        assert re.search(rf'data-channel="{ch}">.*?class="sensor-name">{re.escape(name)}<', dom), name
    assert "rear shaft pulley ↔ ambient" in dom
    assert "°C" in _attr(dom, "sensor-chart", "data-y-title")


def _case(tmp_path: Path, case: str) -> Served:
    """The real service in the state of ``case`` (lenient CIs: nothing else is wrong)."""
    url = sqlite_url(tmp_path)
    if case in ("daq-down", "can-down"):  # real drivers that cannot reach their device; 5 min without data
        s = served_with_dead_devices(
            tmp_path, devices=(case.split("-")[0].replace("daq", "modbus"),), settings=LENIENT
        )
        s.clock.advance(300)
    elif case == "db-down":  # the SQLite "file" is a directory
        (tmp_path / "a-directory").mkdir()
        s = served_service(
            database_url=sqlite_url(tmp_path, "a-directory"), settings=LENIENT, feed_samples=DEMO_FED
        )
    elif case == "model":  # still loading: the shell waits for the worker, no sample acquired yet
        s = served_service(database_url=url, settings=LENIENT, loading=True)
    elif case == "map-unvisited":  # speed-map mode, the speed now at one no map fit has covered yet
        s = served_map_mode(tmp_path, feed_samples=0)
        while (snap := s.service.chtc()) is None or not (snap.reason or "").startswith("speed_not_visited"):
            assert s.fed < len(s.samples), "the duty cycle never reached an unvisited speed"
            s.feed_next(1)
    elif case == "first":  # 5 min of samples, half the first window
        s = served_service(database_url=url, settings=LENIENT, feed_samples=30)
    else:
        s = served_service(database_url=url, settings=LENIENT, feed_samples=DEMO_FED)
        if case == "identifying":  # the speed leaves condition 2
            for smp in s.samples[s.fed : s.fed + 3]:
                feed(s, replace(smp, speed_rpm=5000.0))
        else:  # stale: no sample for 5 min
            s.clock.advance(300)
    return s


@pytest.mark.browser
@pytest.mark.parametrize(
    ("case", "banner_class", "first", "also"),
    [
        ("daq-down", "banner banner-alarm", "DAQ unreachable", ["cannot connect (refused or unreachable)",
                                                              "never ok", "Not ready"]),
        ("can-down", "banner banner-alarm", "CAN silent", ["no answer to SpindleStatus frame"]),
        ("db-down", "banner banner-warn", "Database down", ["buffering", "unable to open database file"]),
        # while the model loads, the worker (which loads it) is down too, and named first
        ("model", "banner banner-alarm", "Identification worker down", ["Model not loaded", "Not ready",
                                                                        "model not loaded"]),
    ],
)  # fmt: skip
def test_dashboard_banner_names_the_cause(
    chromium_path: str, tmp_path: Path, case: str, banner_class: str, first: str, also: list[str]
) -> None:
    with _case(tmp_path, case) as s, _server(s) as server:
        dom = _chromium(chromium_path, tmp_path, server.url + "/", "--dump-dom")
    cls, hidden, text = _banner(dom)
    assert not hidden and cls == banner_class, (cls, text)
    assert text.strip().startswith(first), text
    for part in also:
        assert part in text, (part, text)
    assert "no data" not in text.lower()


def _verdict(dom: str) -> dict[str, str]:
    """What the page shows of the compensation: the header pill and the verdict block."""
    text = {k: html.unescape(re.sub(r"<[^>]+>", "", _inner(dom, k))) for k in ("comp-usable", "comp-reason")}
    return {
        "pill_status": _attr(dom, "status", "data-status"),
        "pill_usable": _attr(dom, "status", "data-usable"),
        "pill_class": _attr(dom, "status", "class"),
        "verdict_class": _attr(dom, "comp-verdict", "class"),
        **text,
    }


def _inner(dom: str, element_id: str) -> str:
    m = re.search(rf'<([a-z0-9]+) [^>]*id="{element_id}"[^>]*>(.*?)</\1>', dom, re.S)
    assert m is not None, element_id
    return m.group(2)


@pytest.mark.browser
@pytest.mark.parametrize("case", ["daq-down", "identifying", "stale", "first", "map-unvisited"])
def test_the_compensation_card_shows_the_served_verdict(
    chromium_path: str, tmp_path: Path, case: str
) -> None:
    """Whatever the state, the header pill and the verdict show /compensation's status and usable flag, its
    reason text as served; green only when usable. No identification yet: /compensation answers 503 and the
    card says there is no value, with the API's message."""
    with _case(tmp_path, case) as s, _server(s) as server:
        dom = _chromium(chromium_path, tmp_path, server.url + "/", "--dump-dom")
        r = httpx.get(server.url + "/api/v1/compensation", timeout=10)
    v = _verdict(dom)
    if r.status_code != 200:
        assert case == "first", r.text
        assert v["pill_status"] == "" and v["pill_usable"] == "false"
        assert v["comp-usable"] == "No compensation value"
        assert v["comp-reason"] == r.json()["error"]["message"]
        assert "pill-ok" not in v["pill_class"] and "verdict-ok" not in v["verdict_class"]
        return
    comp = r.json()
    assert v["pill_status"] == comp["status"], (v, comp["status"])
    assert v["pill_usable"] == str(comp["usable_for_compensation"]).lower()
    green = "pill-ok" in v["pill_class"]
    assert green == comp["usable_for_compensation"] == ("verdict-ok" in v["verdict_class"])
    if not comp["usable_for_compensation"]:
        assert v["comp-usable"].startswith("Not usable")
        assert v["comp-reason"] == comp["reason"]


class _Page:
    """One headless Chromium tab driven over the DevTools protocol on a pipe (no extra package).

    Chromium reads commands from fd 3 and writes replies and events to fd 4, each a JSON text ended by NUL.
    """

    def __init__(self, chromium_path: str, profile: Path) -> None:
        r_cmd, self._w_cmd = os.pipe()
        self._r_out, w_out = os.pipe()

        def to_3_and_4() -> None:  # in the child, before exec: the pipe ends become fds 3 and 4
            a, b = os.dup(r_cmd), os.dup(w_out)
            os.dup2(a, 3)
            os.dup2(b, 4)

        cmd = [chromium_path, *CHROMIUM_FLAGS[:-1], "--remote-debugging-pipe", f"--user-data-dir={profile}"]
        cmd += ["--window-size=1400,1000", "about:blank"]
        self.proc = subprocess.Popen(
            cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, close_fds=False, preexec_fn=to_3_and_4
        )
        os.close(r_cmd)
        os.close(w_out)
        self._buf, self._id, self._session = b"", 0, None
        target = self.call("Target.createTarget", url="about:blank")["targetId"]
        self._session = self.call("Target.attachToTarget", targetId=target, flatten=True)["sessionId"]

    def call(self, method: str, **params: Any) -> Any:
        self._id += 1
        msg: dict[str, Any] = {"id": self._id, "method": method, "params": params}
        if self._session is not None:
            msg["sessionId"] = self._session
        os.write(self._w_cmd, json.dumps(msg).encode() + b"\0")
        while True:
            while b"\0" not in self._buf:
                chunk = os.read(self._r_out, 1 << 16)
                assert chunk, "chromium closed the DevTools pipe"
                self._buf += chunk
            raw, self._buf = self._buf.split(b"\0", 1)
            reply = json.loads(raw)
            if reply.get("id") == self._id:
                assert "error" not in reply, (method, reply["error"])
                return reply["result"]

    def eval(self, expression: str) -> Any:
        out = self.call("Runtime.evaluate", expression=expression, returnByValue=True, awaitPromise=True)
        assert "exceptionDetails" not in out, out["exceptionDetails"]
        return out["result"].get("value")

    def wait(self, expression: str, *, timeout_s: float = 20.0) -> Any:
        """Poll a JavaScript expression until it is truthy (deadline, not a fixed sleep)."""
        deadline = time.monotonic() + timeout_s
        while True:
            value = self.eval(expression)
            if value:
                return value
            assert time.monotonic() < deadline, f"timed out waiting for {expression}"
            time.sleep(0.05)

    def close(self) -> None:
        self.proc.kill()
        self.proc.wait(timeout=10)
        os.close(self._w_cmd)
        os.close(self._r_out)


@pytest.fixture
def page(chromium_path: str, tmp_path: Path) -> Iterator[_Page]:
    p = _Page(chromium_path, tmp_path / "profile")
    yield p
    p.close()


RENDERED = "document.body?.dataset.rendered === '1'"
POINTS = "document.getElementById('sensor-chart')?.dataset.points"
RESULT = "document.getElementById('identify-result').textContent"


@pytest.mark.browser
def test_chart_history_comes_from_the_server_and_survives_a_reload(page: _Page, served: Served) -> None:
    n = len(served.service.sensor_history(None).t)  # 22 min of samples before the page is opened
    assert n == DEMO_FED
    with _server(served) as server:
        page.call("Page.navigate", url=server.url + "/")
        page.wait(RENDERED)
        assert page.wait(POINTS) == str(n)
        served.feed_next(3)
        page.eval("window.beforeReload = true")  # gone with the old page's window
        page.call("Page.reload", ignoreCache=True)
        page.wait(f"!window.beforeReload && {RENDERED} && {POINTS} === '{n + 3}'")
        ticks = page.eval("document.getElementById('sensor-chart').dataset.xTicks").split()
        meta = page.eval("document.getElementById('sensor-meta').textContent")
    assert f"{n + 3} samples from the server's history" in meta
    assert len(ticks) >= 3  # the time axis spans the 22 min of history, not one sample


@pytest.mark.browser
def test_identify_now_asks_for_the_token_posts_and_shows_the_result(page: _Page, served: Served) -> None:
    svc = served.service
    served.worker.hold()  # the first job waits in the worker until the page has shown it
    with _server(served, Settings(api={"token": WRITE_TOKEN})) as server:
        page.call("Page.navigate", url=server.url + "/")
        page.wait(RENDERED)
        page.eval("document.getElementById('identify-now').click()")
        assert page.eval("document.getElementById('identify-dialog').open") is True
        page.eval("document.getElementById('write-token').value = 'not-the-token'")
        page.eval("document.getElementById('identify-submit').click()")
        refused = page.wait(f"{RESULT}.startsWith('refused') && {RESULT}")
        assert "403" in refused and "not valid for writes" in refused
        assert page.eval("sessionStorage.getItem('chtc-write-token')") is None  # a refused token is forgotten

        page.eval("document.getElementById('identify-now').click()")
        page.eval(f"document.getElementById('write-token').value = '{WRITE_TOKEN}'")
        page.eval("document.getElementById('identify-submit').click()")
        queued = page.wait(f"{RESULT}.startsWith('job-') && {RESULT}")
        job_id = queued.split()[0]
        # the page sends "operator request from the dashboard"; the service keeps 32 characters of it
        assert svc.job(job_id).reason == "operator request from the dashboard"[:32]
        served.worker.release()
        served.settle()
        rec = svc.job(job_id).identification_id
        assert rec == 3
        done = page.wait(f"{RESULT}.includes('done') && {RESULT}")
        assert done == f"{job_id} done: identification #{rec}"
        # the token stays in this tab only
        assert page.eval("sessionStorage.getItem('chtc-write-token')") == WRITE_TOKEN
        assert page.eval("localStorage.length") == 0 and page.eval("document.cookie") == ""
        page.eval("document.getElementById('identify-now').click()")
        page.eval("document.getElementById('identify-submit').click()")  # the kept token, no retyping
        busy = page.wait(f"{RESULT}.startsWith('job-') && !{RESULT}.startsWith('{job_id}') && {RESULT}")
        assert busy.split()[0] != job_id


@pytest.mark.browser
def test_hovering_a_sensor_on_the_section_names_its_channel(
    page: _Page, served: Served, spec: SpindleSpec
) -> None:
    with _server(served) as server:
        page.call("Page.navigate", url=server.url + "/")
        page.wait(f"{RENDERED} && state.sensorsNow && state.fieldMap")
        ch = 13
        x, y = page.eval(
            f"(() => {{ const m = state.fieldMap, s = state.sensorsNow[{ch - 1}];"
            " const c = document.getElementById('field'); c.scrollIntoView();"
            " const r = c.getBoundingClientRect();"
            " return [r.left + m.x0 + (s.z_m - m.zmin) * m.s, r.top + m.yAxis - s.r_m * m.s]; })()"
        )
        page.call("Input.dispatchMouseEvent", type="mouseMoved", x=x, y=y)
        title = page.wait("document.getElementById('field').title")
    assert spec.sensors[ch - 1].role == "housing"
    assert title.startswith(f"ch {ch} {spec.sensors[ch - 1].name} (housing): measured ")
    assert "°C" in title


@pytest.mark.browser
def test_a_missing_read_token_is_named_and_the_token_in_the_url_fragment_is_used(
    page: _Page, tmp_path: Path
) -> None:
    settings = LENIENT.model_copy(
        update={"api": Settings(api={"token": WRITE_TOKEN, "read_token": "reader-token-for-tests"}).api}
    )
    s = served_service(database_url=sqlite_url(tmp_path), settings=LENIENT, feed_samples=DEMO_FED)
    with s, _server(s, settings) as server:  # all seven H identified: nothing else wrong
        page.call("Page.navigate", url=server.url + "/")
        causes = page.wait("document.getElementById('banner')?.dataset.causes")
        assert causes.split("|")[0] == "Read token needed"
        assert "/#token=" in page.eval("document.getElementById('banner').textContent")
        page.eval("window.withoutToken = true")  # gone once the page is loaded anew
        page.call("Page.navigate", url=server.url + "/index-with-token")  # a 404 page in between
        page.call("Page.navigate", url=server.url + "/#token=reader-token-for-tests")
        page.wait(f"!window.withoutToken && {RENDERED} && document.getElementById('banner')?.hidden")
        assert page.eval("sessionStorage.getItem('chtc-token')") == "reader-token-for-tests"


FIRST_SCREEN = ("comp-um", "comp-ci", "comp-verdict", "comp-usable", "comp-status", "status")
SHOWN = "document.getElementById('comp-verdict')?.dataset.status"


@pytest.mark.browser
@pytest.mark.parametrize("lenient", [False, True], ids=["not-usable", "all-h-identified"])
def test_the_first_screen_at_1400x1000_is_the_compensation_as_served(
    page: _Page, tmp_path: Path, lenient: bool
) -> None:
    """At 1400×1000, without scrolling: the growth to correct with its 95 % CI, whether it may be applied
    and, when not, why and what to do; the one status there is the one /compensation serves, and the H card
    shows /chtc's (each card the API's own, never the page's)."""
    settings = LENIENT if lenient else Settings(identification={**DEMO_WINDOWS, **PER_CONDITION})
    s = served_service(database_url=sqlite_url(tmp_path), settings=settings, feed_samples=DEMO_FED)
    with s, _server(s) as server:  # a 1400×1000 viewport (the window's own is smaller by its frame)
        page.call(
            "Emulation.setDeviceMetricsOverride",
            width=1400,
            height=1000,
            deviceScaleFactor=1,
            mobile=False,
        )
        page.call("Page.navigate", url=server.url + "/")
        page.wait(f"{RENDERED} && {SHOWN}")
        view = page.eval("[window.innerWidth, window.innerHeight, window.scrollY]")
        boxes = page.eval(
            "Object.fromEntries(" + json.dumps(FIRST_SCREEN) + ".map((id) => {"
            " const r = document.getElementById(id).getBoundingClientRect();"
            " return [id, [r.top, r.bottom, r.left, r.right, r.height]]; }))"
        )
        shown = page.eval(
            "({um: document.getElementById('comp-um').textContent,"
            " ci: document.getElementById('comp-ci').textContent,"
            " usable: document.getElementById('comp-usable').textContent,"
            " reason: document.getElementById('comp-reason').textContent,"
            " action: document.getElementById('comp-action').textContent,"
            " pill: document.getElementById('status').textContent,"
            " pillStatus: document.getElementById('status').dataset.status,"
            " h: document.getElementById('h-status').textContent})"
        )
        comp = httpx.get(server.url + "/api/v1/compensation", timeout=10).json()
        chtc = httpx.get(server.url + "/api/v1/chtc", timeout=10).json()
    assert view == [1400, 1000, 0]
    for name, (top, bottom, left, right, height) in boxes.items():
        assert height > 0 and top >= 0 and bottom <= 1000 and left >= 0 and right <= 1400, (name, boxes[name])
    a = comp["axial"]
    sign = lambda v: ("−" if v < 0 else "+") + f"{abs(v):.1f}"  # noqa: E731
    assert shown["um"] == sign(a["um"])
    assert f"[{sign(a['ci95_um'][0])}, {sign(a['ci95_um'][1])}] µm" in shown["ci"]
    usable = comp["usable_for_compensation"]
    assert shown["pillStatus"] == comp["status"]
    assert shown["pill"] == f"{'usable' if usable else 'not usable'} · {comp['status']}"
    if usable:
        assert shown["usable"].startswith("Usable") and shown["reason"] == shown["action"] == ""
    else:
        assert shown["usable"].startswith("Not usable") and shown["reason"] == comp["reason"]
        assert shown["action"].startswith("What to do: ")  # the API's action, or a hint by its status
        if comp.get("action"):
            assert shown["action"] == "What to do: " + comp["action"]
    assert shown["h"].startswith(f"H: {chtc['status']} · ")


@pytest.mark.browser
def test_the_write_token_in_the_url_fragment_arms_the_buttons_and_leaves_the_address_bar(
    page: _Page, served: Served
) -> None:
    """``chtc demo`` prints ``/#write-token=...``: the page keeps it in this tab only, removes the fragment
    from the address bar (a fragment never reaches the server's logs), and "Identify now" needs no typing."""
    with _server(served, Settings(api={"token": WRITE_TOKEN})) as server:
        page.call("Page.navigate", url=server.url + f"/#write-token={WRITE_TOKEN}")
        page.wait(RENDERED)
        kept = page.eval("sessionStorage.getItem('chtc-write-token')")
        where = page.eval("location.href")
        page.eval("document.getElementById('identify-now').click()")
        filled = page.eval("document.getElementById('write-token').value")
        page.eval("document.getElementById('identify-submit').click()")
        queued = page.wait(f"{RESULT}.startsWith('job-') && {RESULT}")
    assert kept == WRITE_TOKEN == filled
    assert where == server.url + "/"
    assert page.eval("sessionStorage.getItem('chtc-token')") is None  # not sent as a read token
    assert " queued" in queued or " running" in queued or " done" in queued, queued


BASELINE = "document.getElementById('baseline-meta').textContent"
BASELINE_RESULT = "document.getElementById('baseline-result').textContent"


@pytest.mark.browser
def test_a_refused_baseline_names_why(page: _Page, tmp_path: Path) -> None:
    """The real service with the spindle running: no baseline (offsets named unknown); a request through the
    dialog with the write token is refused and the 409's reason is shown."""
    with served_service(database_url=sqlite_url(tmp_path), feed_samples=DEMO_FED) as s:
        app = create_app(Settings(api={"token": WRITE_TOKEN}), s.service, clock=s.clock)
        with LiveServer(app) as server:
            page.call("Page.navigate", url=server.url + "/")
            page.wait(RENDERED)
            assert page.wait(BASELINE).startswith("no offset baseline: sensor offsets unknown")
            page.eval("document.getElementById('baseline-now').click()")
            assert page.eval("document.getElementById('baseline-dialog').open") is True
            page.eval(f"document.getElementById('baseline-token').value = '{WRITE_TOKEN}'")
            page.eval("document.getElementById('baseline-submit').click()")
            refused = page.wait(f"{BASELINE_RESULT}.startsWith('refused') && {BASELINE_RESULT}")
    assert refused == "refused (409): no baseline taken: no baseline: no samples at rest"


@pytest.mark.browser
def test_a_baseline_taken_at_rest_is_shown_in_the_card_and_per_channel(page: _Page, tmp_path: Path) -> None:
    """The real service after 7 min at rest: a baseline taken through the dialog shows its source, time and
    offset range in the card, and each channel's offset (as ``/sensors`` serves it) in the legend table."""
    at_rest = Plan(profile=(Segment(420.0, 0.0, 0.0, 22.0),))
    with served_service(database_url=sqlite_url(tmp_path), plan=at_rest) as s:
        app = create_app(Settings(api={"token": WRITE_TOKEN}), s.service, clock=s.clock)
        with LiveServer(app) as server:
            page.call("Page.navigate", url=server.url + "/")
            # nothing identified at rest (no H, so not "rendered"): the sensors card is what this page shows;
            # 5 min at rest at the ambient have already given the automatic baseline
            meta0 = page.wait("document.getElementById('baseline-meta')?.textContent")
            assert meta0.startswith("offset baseline: auto, at rest until 2026-11-22 07:07:00 UTC")
            page.eval("document.getElementById('baseline-now').click()")
            page.eval(f"document.getElementById('baseline-token').value = '{WRITE_TOKEN}'")
            page.eval("document.getElementById('baseline-submit').click()")
            taken = page.wait(f"{BASELINE_RESULT}.startsWith('baseline taken') && {BASELINE_RESULT}")
            meta = page.wait(f"{BASELINE}.startsWith('offset baseline: manual') && {BASELINE}")
            cell = page.wait(
                "document.querySelector('#sensor-legend tr[data-channel=\"7\"] td:nth-child(8)')?.textContent"
                " || ''"
            )
            with TestClient(app) as c:
                ch = c.get("/api/v1/sensors").json()["channels"]
    offsets = [c["offset_c"] for c in ch]
    assert taken == "baseline taken (31 samples until 2026-11-22 07:07:00 UTC)"
    assert meta == (
        f"offset baseline: manual, at rest until 2026-11-22 07:07:00 UTC · offsets {min(offsets):.2f}.."
        f"{max(offsets):.2f} °C over 32 channels (subtracted before the fit)"
    )
    assert cell == f"{ch[6]['offset_c']:.2f} °C"


HMAP = "document.getElementById('hmap-chart')"
CARD_MODE = "document.getElementById('card-hmap')?.dataset.mode"


@pytest.mark.browser
def test_the_h_versus_speed_card_draws_the_map_in_speed_map_mode(
    page: _Page, chromium_path: str, tmp_path: Path
) -> None:
    """The real service in speed-map mode (a duty cycle, several map fits): the card is shown with seven
    curves and their bands over 0-7000 rpm, the visited speeds as a rug, the current speed, the map's status
    and fit time (UTC)."""
    with served_map_mode(tmp_path) as s, _server(s) as server:
        snap = s.service.chtc_map()
        assert snap is not None
        page.call("Page.navigate", url=server.url + "/")
        page.wait(f"{CARD_MODE} === 'speed_map' && {HMAP}.dataset.curves")
        data = page.eval(f"Object.assign({{}}, {HMAP}.dataset)")
        pill = page.eval("document.getElementById('hmap-status').className")
        meta = page.eval("document.getElementById('hmap-meta').textContent")
        visited = page.eval("document.getElementById('hmap-visited').textContent")
        legend = page.eval("document.getElementById('hmap-legend').textContent")
        swatch = page.eval("getComputedStyle(document.querySelector('#hmap-legend .hz .sw')).backgroundColor")
        page.eval("document.querySelector('#hmap-legend .hz[data-zone=\"H1\"]').click()")
        without_h1 = page.eval(f"{HMAP}.dataset.curves")
        page.eval("document.querySelector('#hmap-legend .hz[data-zone=\"H1\"]').click()")
        page.eval("document.getElementById('hmap-scale').value = 'linear'")
        page.eval("document.getElementById('hmap-scale').dispatchEvent(new Event('change'))")
        linear = page.eval(f"Object.assign({{}}, {HMAP}.dataset)")
        # the whole page in one run: no JavaScript error, no CSP refusal (e.g. an inline style attribute)
        dom = _chromium(chromium_path, tmp_path / "dump", server.url + "/", "--dump-dom")
    assert re.search(r'<section [^>]*id="card-hmap"[^>]*data-mode="speed_map"', dom)
    assert not re.search(r'<section [^>]*id="card-hmap"[^>]*hidden', dom)
    assert data["curves"] == "7" and data["bands"] == "7"
    assert swatch == "rgb(76, 155, 232)"  # H1's colour, set through the CSSOM
    assert without_h1 == "6"  # a click on a zone in the legend hides its curve
    assert data["visited"].split() == [f"{v:.0f}" for v in snap.visited_rpm]
    assert data["current"] == f"{snap.current_speed_rpm:.0f}"
    assert data["xTitle"] == "speed, rpm" and data["yScale"] == "log"
    assert data["yTitle"] == "H, W/(m²·K) (log)"
    x_ticks = [float(v) for v in data["xTicks"].split()]
    assert x_ticks[0] == 0.0 and x_ticks[-1] == 7000.0 and len(x_ticks) >= 4
    y_ticks = [float(v) for v in data["yTicks"].split()]
    assert len(y_ticks) >= 3 and np.all(np.diff(np.log10(y_ticks)) > 0)
    h = snap.h_w_m2k  # the log axis spans every served H
    assert y_ticks[0] <= 2.0 * h.min() and y_ticks[-1] >= 0.5 * h.max()
    assert pill == f"pill pill-{snap.status.value}"
    assert meta.startswith(f"map fitted at {snap.fitted_at:%Y-%m-%d %H:%M:%S} UTC (window end)")
    assert f"identification #{snap.identification_id}" in meta and "family nodes" in meta
    for v in snap.visited_rpm:
        assert f"{v:.0f} rpm " in visited
    assert all(f"H{i}" in legend for i in range(1, 8))
    assert linear["yScale"] == "linear" and linear["yTitle"] == "H, W/(m²·K)"
    steps = np.diff([float(v) for v in linear["yTicks"].split()])
    np.testing.assert_allclose(steps, steps[0], rtol=1e-9)


@pytest.mark.browser
def test_the_h_versus_speed_card_is_hidden_in_per_condition_mode(page: _Page, served: Served) -> None:
    with _server(served) as server:
        page.call("Page.navigate", url=server.url + "/")
        page.wait(f"{RENDERED} && {CARD_MODE}")
        mode = page.eval("document.getElementById('card-hmap').dataset.mode")
        hidden = page.eval("document.getElementById('card-hmap').hidden")
        shown = page.eval("document.getElementById('card-hmap').getBoundingClientRect().height")
    assert mode == "per_condition" and hidden is True and shown == 0


DEFORMED = "document.getElementById('deformed')?.dataset"


@pytest.mark.browser
def test_deformed_section_is_drawn_and_follows_the_field(page: _Page, served: Served) -> None:
    """The section deformed by the live field (×k, k shown), next to its undeformed outline; feeding samples
    changes the field, and the drawing follows (the page polls, no reload)."""
    with _server(served) as server:
        page.call("Page.navigate", url=server.url + "/")
        page.wait(f"{DEFORMED}.digest")
        first = page.eval(f"JSON.stringify({DEFORMED})")
        meta = page.eval("document.getElementById('deformed-meta').textContent")
        unit = page.eval("document.getElementById('deformed-unit').textContent")
        body = served.service.compensation_section()
        assert body is not None
        served.feed_next(12)  # 2 min more at 4000 rpm: the spindle keeps warming
        page.wait(f"{DEFORMED}.at !== {json.loads(first)['at']!r}", timeout_s=30.0)
        second = json.loads(page.eval(f"JSON.stringify({DEFORMED})"))
    first = json.loads(first)
    assert int(first["edges"]) == len(body.edges) > 100
    k = int(first["exaggeration"])
    assert k >= 100 and f"×{k}" in unit and f"×{k}" in meta and "µm" in unit
    assert float(first["maxUm"]) == pytest.approx(float(np.hypot(*body.u_um).max()), abs=2e-3)
    assert " UTC" in meta and "T_ref" in meta and "°C" in meta
    assert second["at"] > first["at"] and second["digest"] != first["digest"]
    assert float(second["maxUm"]) > float(first["maxUm"])  # warmer: larger displacement
