"""Read the deployment files the way Docker would, without Docker.

- :func:`interpolate` implements Compose variable interpolation (``$VAR``, ``${VAR}``, ``${VAR:-default}``,
  ``${VAR-default}``, ``${VAR:?error}``, ``${VAR?error}``, ``$$``) over every string of the parsed file.
- :func:`load_compose` parses ``docker-compose.yml`` and interpolates it with an environment (the ``.env``).
- :func:`service_env` / :func:`service_command` normalise a service's ``environment`` (list or mapping) and
  ``command`` (list or string).
- :func:`dockerfile_instructions` splits a Dockerfile into (INSTRUCTION, arguments) with continuations joined;
  :func:`dockerfile_env` and :func:`dockerfile_entrypoint` read the runtime stage's ENV and ENTRYPOINT.
"""

from __future__ import annotations

import json
import re
import shlex
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import yaml

ROOT = Path(__file__).resolve().parents[2]
COMPOSE = ROOT / "docker-compose.yml"
DOCKERFILE = ROOT / "deploy" / "Dockerfile"

_VAR = re.compile(
    r"\$(?:(?P<escaped>\$)|(?P<plain>[A-Za-z_][A-Za-z0-9_]*)|\{(?P<name>[A-Za-z_][A-Za-z0-9_]*)"
    r"(?:(?P<op>:?[-?])(?P<arg>[^}]*))?\})"
)


class InterpolationError(ValueError):
    """A required variable (``${VAR:?...}``) is unset, as ``docker compose`` would refuse to start."""


def interpolate_text(text: str, env: Mapping[str, str]) -> str:
    """One string with Compose interpolation applied."""

    def repl(m: re.Match[str]) -> str:
        if m.group("escaped"):
            return "$"
        name = m.group("plain") or m.group("name")
        op, arg = m.group("op"), m.group("arg") or ""
        value = env.get(name)
        unset = value is None or (op is not None and op.startswith(":") and value == "")
        if op in (":-", "-"):
            return arg if unset else str(value)
        if op in (":?", "?"):
            if unset:
                raise InterpolationError(f"{name}: {arg or 'required variable is missing'}")
            return str(value)
        return "" if value is None else str(value)

    return _VAR.sub(repl, text)


def interpolate(node: Any, env: Mapping[str, str]) -> Any:
    """Every string in a parsed YAML tree interpolated (keys are left alone, as Compose does)."""
    if isinstance(node, str):
        return interpolate_text(node, env)
    if isinstance(node, list):
        return [interpolate(item, env) for item in node]
    if isinstance(node, dict):
        return {key: interpolate(value, env) for key, value in node.items()}
    return node


def load_compose(env: Mapping[str, str] | None = None, path: Path = COMPOSE) -> dict[str, Any]:
    """The compose file parsed; interpolated with ``env`` unless it is None."""
    data = yaml.safe_load(path.read_text(encoding="utf-8"))
    return data if env is None else interpolate(data, env)


def service_env(service: Mapping[str, Any]) -> dict[str, str]:
    """A service's ``environment`` as a mapping of strings (list ``KEY=VALUE`` form accepted)."""
    raw = service.get("environment") or {}
    if isinstance(raw, list):
        return dict(item.split("=", 1) if "=" in item else (item, "") for item in raw)
    return {str(k): "" if v is None else str(v) for k, v in raw.items()}


def service_command(service: Mapping[str, Any]) -> list[str]:
    """A service's ``command`` as an argument list (string form split like a shell)."""
    raw = service.get("command") or []
    return shlex.split(raw) if isinstance(raw, str) else [str(a) for a in raw]


def dockerfile_instructions(path: Path = DOCKERFILE) -> list[tuple[str, str]]:
    """(INSTRUCTION, arguments) pairs, comments dropped, backslash continuations joined."""
    out: list[tuple[str, str]] = []
    pending = ""
    for line in path.read_text(encoding="utf-8").splitlines():
        stripped = line.strip()
        if not pending and (not stripped or stripped.startswith("#")):
            continue
        if stripped.endswith("\\"):
            pending += stripped[:-1] + " "
            continue
        full = (pending + stripped).strip()
        pending = ""
        word, _, rest = full.partition(" ")
        out.append((word.upper(), rest.strip()))
    return out


def runtime_stage(path: Path = DOCKERFILE) -> list[tuple[str, str]]:
    """The instructions of the last stage (from its FROM on)."""
    instructions = dockerfile_instructions(path)
    last_from = max(i for i, (word, _) in enumerate(instructions) if word == "FROM")
    return instructions[last_from:]


def dockerfile_env(path: Path = DOCKERFILE) -> dict[str, str]:
    """ENV of the runtime stage (``KEY=VALUE`` pairs, shell-quoted values allowed)."""
    env: dict[str, str] = {}
    for word, args in runtime_stage(path):
        if word == "ENV":
            for token in shlex.split(args):
                key, _, value = token.partition("=")
                env[key] = value
    return env


def dockerfile_exec_form(word: str, path: Path = DOCKERFILE) -> list[str]:
    """The last ``ENTRYPOINT``/``CMD`` of the runtime stage, exec (JSON) form."""
    found = [args for w, args in runtime_stage(path) if w == word]
    if not found:
        raise AssertionError(f"{path.name}: no {word} in the runtime stage")
    return [str(a) for a in json.loads(found[-1])]
