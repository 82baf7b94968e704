"""The identification mode a bench runs in, the same for ``python -m benchmarks chain``, ``restart`` and
``duty``: ``--mode per_condition|speed_map|combined`` (``identification.mode``; default: the settings' own,
i.e. the built-in default or ``CHTC_IDENTIFICATION__MODE``) and ``--set KEY=VALUE`` (any ``identification`` or
``experimental`` setting by its key, e.g. ``--set map_min_window_min=7``, ``--set rom_rank=46``; the two
sections share no key name, ``section.key`` works too), so the modes can be compared in one command line.
Each bench reports the mode it ran as ``mode`` in its JSON.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Iterable
from typing import TYPE_CHECKING, Any

from service.contracts.mode import IdentificationMode

if TYPE_CHECKING:
    from service.contracts.snapshots import IdentificationRecord
    from service.settings import Settings

MODES = tuple(m.value for m in IdentificationMode)


def add_arguments(
    parser: argparse.ArgumentParser,
    *,
    default: str | None = None,
    extra: tuple[str, ...] = (),
    note: str = "",
) -> None:
    """``--mode`` (into ``ident_mode``) and the repeatable ``--set``; ``default`` None: the settings' mode;
    ``extra`` more choices of ``--mode`` that the bench maps itself (``note`` says how)."""
    parser.add_argument(
        "--mode",
        dest="ident_mode",
        choices=MODES + extra,
        default=default,
        help="identification.mode"
        + ("" if default is not None else " (default: the settings', CHTC_IDENTIFICATION__MODE or built-in)")
        + note,
    )
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="an identification or experimental setting, e.g. --set map_min_window_min=7 (repeatable; "
        "JSON values)",
    )


def parse_sets(items: list[str]) -> dict[str, Any]:
    """``KEY=VALUE`` pairs; a value is JSON where it parses (numbers, lists, true), else a string."""
    out: dict[str, Any] = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise ValueError(f"--set {item!r}: expected KEY=VALUE")
        try:
            out[key] = json.loads(value)
        except json.JSONDecodeError:
            out[key] = value
    return out


SET_SECTIONS = ("identification", "experimental")  # the sections ``--set`` reaches


def bench_settings(mode: str | None, overrides: dict[str, Any] | None = None) -> Settings:
    """``Settings()`` (defaults and ``CHTC_*`` environment) with ``identification.mode`` (None: kept) and the
    overrides (``key`` or ``section.key`` of ``SET_SECTIONS``) applied and validated; ``ValueError`` naming
    the key when one is invalid or unknown."""
    from service.commands._common import CommandError, override
    from service.settings import Settings

    settings = Settings()
    by_section: dict[str, dict[str, Any]] = {name: {} for name in SET_SECTIONS}
    for key, value in (overrides or {}).items():
        by_section[_section_of(settings, key)][key.rpartition(".")[2]] = value
    if mode is not None:
        by_section["identification"]["mode"] = mode
    try:
        for name, values in by_section.items():
            settings = override(settings, name, **values) if values else settings
    except CommandError as err:
        raise ValueError(str(err)) from err
    return settings


def _section_of(settings: Settings, key: str) -> str:
    """The section of ``SET_SECTIONS`` holding ``key`` (``section.key`` names it); ``ValueError`` if none."""
    from service.settings import REMOVED_KEYS

    section, _, name = key.rpartition(".")
    for candidate in (section,) if section else SET_SECTIONS:
        if candidate in SET_SECTIONS and name in type(getattr(settings, candidate)).model_fields:
            return candidate
    gone = REMOVED_KEYS.get(("identification", name))
    why = f": {gone}" if gone else f" (keys of [{'], ['.join(SET_SECTIONS)}])"
    raise ValueError(f"--set: unknown setting {key}{why}")


def served_in_order(records: Iterable[IdentificationRecord]) -> list[IdentificationRecord]:
    """The ok identifications in the order ``/chtc`` serves them (oldest first): every per-condition one, and
    each map fit except those at a condition that already has a per-condition one (combined mode serves that
    one while the condition holds). In the per-condition and speed-map modes: every ok one."""
    from service.core.jobbook import MAP_METHOD

    held: set[int] = set()
    out = []
    for rec in records:
        if rec.outcome != "ok":
            continue
        if rec.method != MAP_METHOD:
            held.add(rec.condition.id)
        elif rec.condition.id in held:
            continue
        out.append(rec)
    return out
