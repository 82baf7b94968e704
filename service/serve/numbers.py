"""Readable numbers for people (the CLI's lines; the dashboard's ``fmtBound`` in api/static/app.js is the same
rule): a CI bound of H never prints as ``3.42e-84`` or ``1.5e+26``.

A bound beyond the search box says only that: ``> 200`` / ``< 5`` (the fit cannot tell more than "outside the
range it searched", and a log-H CI of an unseen H can run to any power of ten); inside, 3 significant digits
without an exponent.
"""

from __future__ import annotations

import math

__all__ = ["FALLBACK_BOX", "format_bound", "format_sig"]

FALLBACK_BOX = (0.1, 1e4)  # W/(m²·K): what "outside" means when no search box is known


def format_sig(x: float, digits: int = 3) -> str:
    """``x`` with ``digits`` significant digits and no exponent (``123``, ``45.7``, ``0.0123``); ``–`` for
    None, NaN or infinity. For numbers of everyday size (``format_bound`` keeps the rest out)."""
    if x is None or not math.isfinite(float(x)):
        return "–"
    v = float(x)
    if v == 0.0:
        return "0"
    decimals = max(0, digits - 1 - math.floor(math.log10(abs(v))))
    text = f"{v:.{decimals}f}"
    if decimals == 0 and abs(round(v)) >= 10**digits:  # 12345 -> 12300: keep the significant digits only
        text = f"{round(v, digits - 1 - math.floor(math.log10(abs(v)))):.0f}"
    return text


def format_bound(x: float | None, box: tuple[float, float] | None = None) -> str:
    """A CI bound of H [W/(m²·K)] for people: ``> hi`` / ``< lo`` beyond the search ``box`` (default
    ``FALLBACK_BOX``), else ``format_sig``; ``–`` when unknown."""
    if x is None or math.isnan(float(x)):
        return "–"
    lo, hi = box if box is not None else FALLBACK_BOX
    v = float(x)
    if v > hi:
        return f"> {hi:g}"
    if v < lo:
        return f"< {lo:g}"
    return format_sig(v)
