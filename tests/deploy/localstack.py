"""Run the services of ``docker-compose.yml`` as local processes on loopback ("compose without Docker").

What Docker would provide is emulated from the files themselves:

- each service's process is the image ENTRYPOINT (``deploy/Dockerfile``) + the compose ``command``, with the
  image ENV, then the compose ``environment`` (interpolated with a test ``.env``);
- service hostnames (``postgres``, ``simulator``) resolve to 127.0.0.1 and ``0.0.0.0`` binds become 127.0.0.1;
- each published container port gets a free loopback port (``5432`` maps to the local PostgreSQL);
- container paths are mapped to local ones: mounted files are copied (localised the same way) into a temporary
  directory, ``/opt/chtc/cache`` (the image's prebuilt reduced model) to a local cache directory, the rest
  (``/var/lib/chtc``...) into the temporary directory.

The database URL is rewritten to the local cluster: the host, port and user of ``pg_url`` (the postgres image
would create the ``chtc`` role; the local cluster has ``postgres``) and a dedicated database.
"""

from __future__ import annotations

import os
import re
import shlex
import socket
import subprocess
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

from sqlalchemy.engine import URL, make_url

from tests.deploy.deployhelpers import (
    ROOT,
    dockerfile_env,
    dockerfile_exec_form,
    runtime_stage,
    service_command,
    service_env,
)

DB_VAR = "CHTC_DATABASE__URL"


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def container_ports(compose: Mapping[str, Any]) -> set[int]:
    """Every container port published by any service ("ip:host:container" short syntax)."""
    ports = set()
    for service in compose["services"].values():
        for spec in service.get("ports", []):
            ports.add(int(str(spec).rsplit(":", 1)[1].split("/")[0]))
    return ports


@dataclass
class Localizer:
    """Rewrites container-side strings (hosts, ports, paths) into their loopback equivalents."""

    hosts: tuple[str, ...]
    ports: dict[int, int]
    paths: dict[str, str]
    _host_re: re.Pattern[str] = field(init=False)
    _port_re: re.Pattern[str] = field(init=False)

    def __post_init__(self) -> None:
        names = "|".join(re.escape(h) for h in [*self.hosts, "0.0.0.0"])
        # a hostname stands alone or follows a quote, '@', '=' or '//', and ends at ':', a quote or the end
        self._host_re = re.compile(rf"""(?:^|(?<=["'@=])|(?<=//))(?:{names})(?=[:"']|$)""")
        nums = "|".join(str(p) for p in sorted(self.ports, reverse=True)) or "(?!)"
        self._port_re = re.compile(rf"(?<![\d.])({nums})(?![\d.])")

    def __call__(self, text: str) -> str:
        for container, local in sorted(self.paths.items(), key=lambda kv: -len(kv[0])):
            text = text.replace(container, local)
        text = self._host_re.sub("127.0.0.1", text)
        return self._port_re.sub(lambda m: str(self.ports[int(m.group(1))]), text)


def local_database_url(container_url: str, pg_url: str, database: str) -> str:
    """The compose database URL pointed at the local cluster (its host, port, user) and ``database``."""
    local = make_url(pg_url)
    url = URL.create(
        make_url(container_url).drivername,
        username=local.username,
        password=local.password,
        host=local.host,
        port=local.port,
        database=database,
    )
    return url.render_as_string(hide_password=False)


def image_copies() -> dict[str, str]:
    """COPY <repo file> <container path> of the runtime stage (files baked into the image)."""
    out = {}
    for word, args in runtime_stage():
        if word == "COPY" and "--from" not in args:
            *srcs, dest = shlex.split(args)
            if len(srcs) == 1 and (ROOT / srcs[0]).is_file():
                out[dest] = srcs[0]
    return out


def stage_files(service: Mapping[str, Any], localize: Localizer, workdir: Path) -> None:
    """Copy the image's files and the service's mounted files to their local paths, localised."""
    files = dict(image_copies())
    for volume in service.get("volumes", []):
        parts = str(volume).split(":")
        if parts[0].startswith("."):
            files[parts[1]] = parts[0]
    for container, host in files.items():
        target = Path(localize(container))
        assert target.is_relative_to(workdir), f"{container} is not mapped under the work directory"
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_text(localize((ROOT / host).read_text(encoding="utf-8")), encoding="utf-8")


def process_env(
    service: Mapping[str, Any], localize: Localizer, *, pg_url: str, database: str, extra: Mapping[str, str]
) -> dict[str, str]:
    """Host environment without CHTC_*, then image ENV, compose environment and ``extra`` (all localised)."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("CHTC_")}
    merged = {**dockerfile_env(), **service_env(service)}
    for key, value in merged.items():
        env[key] = local_database_url(value, pg_url, database) if key == DB_VAR else localize(value)
    env.update(extra)
    return env


def process_argv(service: Mapping[str, Any], localize: Localizer) -> list[str]:
    """ENTRYPOINT + command, localised."""
    return [*dockerfile_exec_form("ENTRYPOINT"), *(localize(a) for a in service_command(service))]


@dataclass
class Proc:
    name: str
    popen: subprocess.Popen[bytes]
    log_path: Path
    log: IO[bytes]

    def tail(self, n: int = 40) -> str:
        if not self.log.closed:
            self.log.flush()
        lines = self.log_path.read_text(errors="replace").splitlines()
        return f"--- {self.name} (rc={self.popen.poll()}) last lines:\n" + "\n".join(lines[-n:])

    def stop(self, timeout_s: float = 20.0) -> int | None:
        """SIGTERM, then SIGKILL after ``timeout_s``; the exit code."""
        if self.popen.poll() is None:
            self.popen.terminate()
            try:
                self.popen.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self.popen.kill()
                self.popen.wait(10)
        self.log.close()
        return self.popen.returncode


def start(name: str, argv: list[str], env: Mapping[str, str], cwd: Path) -> Proc:
    log_path = cwd / f"{name}.log"
    log = log_path.open("wb")
    popen = subprocess.Popen(argv, env=dict(env), cwd=cwd, stdout=log, stderr=subprocess.STDOUT)
    return Proc(name, popen, log_path, log)


def wait_for(
    what: str,
    check: Callable[[], tuple[bool, Any]],
    *,
    deadline_s: float,
    procs: list[Proc],
    period_s: float = 1.0,
) -> Any:
    """Poll ``check() -> (done, info)`` until done (returns info); fail at once if a process died, or late."""
    end = time.monotonic() + deadline_s
    last: Any = None
    while time.monotonic() < end:
        for p in procs:
            if p.popen.poll() is not None:
                raise AssertionError(f"{p.name} exited while waiting for {what}\n{p.tail()}")
        try:
            done, last = check()
        except Exception as err:  # connection refused while starting, etc.
            done, last = False, err
        if done:
            return last
        time.sleep(period_s)  # polling period of a deadline-bounded wait, not a wait for an event
    tails = "\n".join(p.tail() for p in procs)
    raise AssertionError(f"timed out after {deadline_s:.0f} s waiting for {what}; last: {last!r}\n{tails}")


def tree_rss_mib(pid: int) -> float:
    """Resident memory of a process and all its descendants, MiB (Linux /proc; diagnostic figure only)."""
    children: dict[int, list[int]] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        children.setdefault(int(fields[1]), []).append(int(stat.parent.name))
    total_kib, todo = 0, [pid]
    while todo:
        p = todo.pop()
        todo.extend(children.get(p, []))
        try:
            status = Path(f"/proc/{p}/status").read_text()
        except OSError:
            continue
        total_kib += next(
            (int(line.split()[1]) for line in status.splitlines() if line.startswith("VmRSS:")), 0
        )
    return total_kib / 1024.0
