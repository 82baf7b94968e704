"""``chtc demo`` shows the product working (issue 26, item 9 and its bar): at its default speed-up, a user who
runs it is served a usable compensation within 5 minutes of wall clock (the user waits in wall time, whatever
the plant's clock does), and the machining goes on: the speed keeps changing, the plant never freezes.

The real command in a process of its own: the simulated Modbus DAQ and CAN node on 127.0.0.1 and a private
virtual CAN channel, the real drivers, the service, its worker process, the API on a free loopback port.
"""

from __future__ import annotations

import re
import subprocess
import sys
import threading
import time
from pathlib import Path

import httpx
import pytest

DEADLINE_S = 300.0  # the bar: usable within 5 min of wall clock from the command's start


@pytest.mark.slow
def test_demo_serves_a_usable_compensation_within_5_wall_minutes(tmp_path: Path) -> None:
    argv = [sys.executable, "-m", "service.cli", "demo", "--port", "0", "--quiet", "--duration", "600"]
    argv += ["--database-url", f"sqlite:///{tmp_path / 'demo.db'}"]
    started = time.monotonic()
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    lines: list[str] = []

    def read() -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            lines.append(line)

    threading.Thread(target=read, daemon=True).start()
    try:
        url = _wait_for_url(lines, proc, started)
        seen: list[tuple[float, str, bool, str | None]] = []  # (wall s, status, usable, reason_code)
        speeds: set[float] = set()
        with httpx.Client(base_url=url, timeout=10.0) as c:
            while time.monotonic() - started < DEADLINE_S:
                assert proc.poll() is None, "".join(lines[-30:])
                r = c.get("/api/v1/compensation")
                if r.status_code == 200:
                    b = r.json()
                    seen.append((time.monotonic() - started, b["status"], b["usable_for_compensation"],
                                 b.get("reason_code")))  # fmt: skip
                    if b["usable_for_compensation"]:
                        break
                cond = c.get("/api/v1/condition")
                if cond.status_code == 200:
                    speeds.add(cond.json()["current"]["speed_rpm"])
                time.sleep(2.0)
            # usable may come before the machining starts (the demo rests first): wait for the cycle to run
            while len(speeds) < 2 and time.monotonic() - started < DEADLINE_S + 120.0:
                cond = c.get("/api/v1/condition")
                if cond.status_code == 200:
                    speeds.add(cond.json()["current"]["speed_rpm"])
                time.sleep(2.0)
            health = c.get("/api/v1/healthz").json()
            token = _printed_token(lines)
            # the printed write token works (the dashboard's buttons use it)
            job = c.post(
                "/api/v1/identifications",
                json={"reason": "test"},
                headers={"Authorization": f"Bearer {token}"},
            )
    finally:
        proc.terminate()
        proc.wait(timeout=60)
    usable = [s for s in seen if s[2]]
    reasons = sorted({str(s[3]) for s in seen if not s[2]})
    assert usable, (
        f"no usable compensation within {DEADLINE_S:.0f} s; reasons seen: {reasons}; last {seen[-3:]}"
    )
    first = usable[0][0]
    print(f"first usable compensation after {first:.0f} s wall; reasons before: {reasons}")
    assert first <= DEADLINE_S
    assert health["clock"] == {"simulated": True, "speedup": 60.0}
    # the token is accepted: a job starts, or the service is busy with one (a map fit may be running)
    busy = job.status_code == 409 and job.json()["error"]["code"] == "busy"
    assert job.status_code == 202 or busy, job.text
    assert len(speeds) >= 2, speeds  # the machining cycle runs (the speed changes)


def _wait_for_url(lines: list[str], proc: subprocess.Popen[str], started: float) -> str:
    while time.monotonic() - started < DEADLINE_S:
        for line in lines:
            if m := re.search(r"dashboard: (http://[^\s#]+?)/?[\s#]", line):
                return m.group(1)
        assert proc.poll() is None, "".join(lines)
        time.sleep(0.2)
    raise AssertionError("chtc demo printed no dashboard URL: " + "".join(lines))


def _printed_token(lines: list[str]) -> str:
    for line in lines:
        if m := re.search(r"dashboard: \S+#write-token=(\S+)", line):
            return m.group(1)
    raise AssertionError("chtc demo printed no write token: " + "".join(lines))
