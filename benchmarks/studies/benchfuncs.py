"""The paper's Table 1 benchmark functions (30 dimensions) and shifted versions.

F1 sphere Σx² on [−100, 100]; F2 Schwefel 2.22 Σ|x| + Π|x| on [−10, 10]; F7 quartic with noise
Σ i·x_i⁴ + U[0, 1) on [−1.28, 1.28]; F9 Rastrigin Σ(x² − 10·cos 2πx + 10) on [−5.12, 5.12]. All have their
minimum 0 at the origin (F7: 0 plus noise). A shifted version evaluates f(x − s) with s drawn uniformly in
0.4 × the bounds from a fixed seed, so the optimum is no longer at the origin (SPEC §2: the paper's literal
IGWO update favours an optimum at 0).

All functions are vectorized: they take (P, D) and return (P,).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from model.optim._common import FloatArray

SHIFT_SEED = 20250918
SHIFT_FRACTION = 0.4


def sphere(x: FloatArray) -> FloatArray:
    """F1: Σ x_i²."""
    result: FloatArray = np.sum(x * x, axis=-1)
    return result


def schwefel_2_22(x: FloatArray) -> FloatArray:
    """F2: Σ |x_i| + Π |x_i|."""
    ax = np.abs(x)
    result: FloatArray = ax.sum(axis=-1) + ax.prod(axis=-1)
    return result


def quartic(x: FloatArray) -> FloatArray:
    """F7 without its noise term: Σ i·x_i⁴ (i from 1)."""
    i = np.arange(1, x.shape[-1] + 1)
    result: FloatArray = np.sum(i * x**4, axis=-1)
    return result


def rastrigin(x: FloatArray) -> FloatArray:
    """F9: Σ (x_i² − 10·cos(2π·x_i) + 10)."""
    result: FloatArray = np.sum(x * x - 10.0 * np.cos(2.0 * np.pi * x) + 10.0, axis=-1)
    return result


_TABLE: dict[str, tuple[Callable[[FloatArray], FloatArray], float, bool]] = {
    "F1": (sphere, 100.0, False),
    "F2": (schwefel_2_22, 10.0, False),
    "F7": (quartic, 1.28, True),
    "F9": (rastrigin, 5.12, False),
}


@dataclass
class BenchmarkFunction:
    """A benchmark problem: call it with (P, D) → (P,). ``x_opt``/``f_opt`` are the noise-free optimum."""

    name: str
    base: Callable[[FloatArray], FloatArray] = field(repr=False)
    bounds: FloatArray = field(repr=False)
    shift: FloatArray = field(repr=False)
    noise_rng: np.random.Generator | None = field(default=None, repr=False)

    @property
    def dim(self) -> int:
        return len(self.bounds)

    @property
    def x_opt(self) -> FloatArray:
        return self.shift.copy()

    @property
    def f_opt(self) -> float:
        return 0.0

    def noise_free(self, x: FloatArray) -> FloatArray:
        """The function without F7's random term."""
        return self.base(np.atleast_2d(x) - self.shift)

    def __call__(self, x: FloatArray) -> FloatArray:
        vals = self.noise_free(x)
        if self.noise_rng is not None:
            vals = vals + self.noise_rng.random(vals.shape)
        return vals


def shift_vector(half_width: float, dim: int, *, seed: int = SHIFT_SEED) -> FloatArray:
    """A fixed shift uniform in ±``SHIFT_FRACTION``·``half_width`` per dimension."""
    rng = np.random.default_rng(seed)
    result: FloatArray = rng.uniform(-SHIFT_FRACTION * half_width, SHIFT_FRACTION * half_width, size=dim)
    return result


def make(
    name: str, *, dim: int = 30, shifted: bool = False, noise_rng: np.random.Generator | int | None = None
) -> BenchmarkFunction:
    """Benchmark function ``name`` in {"F1", "F2", "F7", "F9"}; ``noise_rng`` seeds F7's noise (default 0).

    Raises:
        KeyError: unknown name (the message lists the known ones).
    """
    if name not in _TABLE:
        raise KeyError(f"unknown benchmark function {name!r}; known: {sorted(_TABLE)}")
    base, half, noisy = _TABLE[name]
    bounds = np.tile([-half, half], (dim, 1)).astype(float)
    shift = shift_vector(half, dim) if shifted else np.zeros(dim)
    rng = None
    if noisy:
        rng = (
            noise_rng if isinstance(noise_rng, np.random.Generator) else np.random.default_rng(noise_rng or 0)
        )
    return BenchmarkFunction(name + ("s" if shifted else ""), base, bounds, shift, rng)


NAMES = tuple(_TABLE)
