"""The paper's Table 1 benchmark functions: optimum, bounds and shift."""

from __future__ import annotations

import numpy as np
import pytest

from benchmarks.studies import benchfuncs as bf


@pytest.mark.parametrize("name", bf.NAMES)
@pytest.mark.parametrize("shifted", [False, True])
def test_optimum_is_the_minimum(name: str, shifted: bool) -> None:
    f = bf.make(name, shifted=shifted)
    assert f.dim == 30
    assert f.noise_free(f.x_opt)[0] == pytest.approx(0.0, abs=1e-12)
    rng = np.random.default_rng(3)
    lo, hi = f.bounds[:, 0], f.bounds[:, 1]
    others = lo + rng.random((200, f.dim)) * (hi - lo)
    near = np.clip(f.x_opt + 1e-3 * (hi - lo) * rng.standard_normal((50, f.dim)), lo, hi)
    assert np.all(f.noise_free(np.vstack([others, near])) > 0.0)


def test_classic_bounds() -> None:
    half = {"F1": 100.0, "F2": 10.0, "F7": 1.28, "F9": 5.12}
    for name, h in half.items():
        f = bf.make(name)
        assert np.all(f.bounds[:, 0] == -h)
        assert np.all(f.bounds[:, 1] == h)


def test_shift_moves_optimum_inside_forty_percent_of_box_and_is_fixed() -> None:
    a, b = bf.make("F9", shifted=True), bf.make("F9", shifted=True)
    np.testing.assert_array_equal(a.x_opt, b.x_opt)
    assert np.all(np.abs(a.x_opt) <= 0.4 * 5.12)
    assert np.linalg.norm(a.x_opt) > 0.1 * 5.12 * np.sqrt(30)
    x = np.zeros((1, 30))
    assert a(x)[0] > 10.0  # the origin is no longer optimal


def test_known_values_by_hand() -> None:
    x = np.array([[1.0, -2.0, 0.5]])
    assert bf.sphere(x)[0] == pytest.approx(1 + 4 + 0.25)
    assert bf.schwefel_2_22(x)[0] == pytest.approx(3.5 + 1.0)
    assert bf.quartic(x)[0] == pytest.approx(1 + 2 * 16 + 3 * 0.0625)
    assert bf.rastrigin(np.array([[0.5, 1.0]]))[0] == pytest.approx((0.25 + 10 + 10) + (1 - 10 + 10))


def test_f7_noise_is_in_unit_interval_and_seeded() -> None:
    x = np.zeros((500, 30))
    v1 = bf.make("F7", noise_rng=5)(x)
    v2 = bf.make("F7", noise_rng=5)(x)
    np.testing.assert_array_equal(v1, v2)
    assert np.all((v1 >= 0.0) & (v1 < 1.0))
    assert v1.std() > 0.2


def test_unknown_name_is_named() -> None:
    with pytest.raises(KeyError, match="F3"):
        bf.make("F3")
