"""The streamed sensor outputs against the full modal trajectory projected afterwards."""

from __future__ import annotations

import numpy as np
import pytest

from model import rom_modal, rom_stream


def _segments(lengths: list[int], rng: np.random.Generator) -> rom_modal.Segments:
    length = np.asarray(lengths, dtype=np.int64)
    start = np.concatenate([[0], np.cumsum(length)[:-1]]).astype(np.int64)
    k = length.size
    return rom_modal.Segments(
        start, length, rng.uniform(15, 30, k), rng.uniform(0, 300, k), rng.uniform(0, 150, k)
    )


CASES = {
    "every step its own segment": [1] * 50,
    "one constant segment": [50],
    "mixed, crossing chunk ends": [5, 30, 1, 1, 9, 4],
    "exact multiples of the chunk": [8, 8, 1],
    "one step": [1],
}


@pytest.mark.parametrize("chunk", [1, 3, 8, 64])
@pytest.mark.parametrize("lengths", list(CASES.values()), ids=list(CASES))
@pytest.mark.parametrize("theta", [1.0, 0.5])
def test_streamed_outputs_equal_the_projected_trajectory(
    lengths: list[int], chunk: int, theta: float
) -> None:
    rng = np.random.default_rng(len(lengths) + chunk)
    p, r, m = 3, 6, 4
    lam = rng.uniform(1e-3, 50.0, (p, r))  # λ·Δt up to 500: μ < 0 for Crank–Nicolson
    mu, _ = rom_modal.step_factors(lam, 10.0, theta)
    forcing = (rng.normal(size=(p, r)), rng.normal(size=(p, r)), rng.normal(size=(p, r)))
    scale = rng.uniform(0.5, 1.5, (p, 2))
    b0 = rng.normal(size=(p, r))
    gain = rng.normal(size=(p, m, r))
    run = rom_modal.ModalRun(b0, lam, mu, forcing, _segments(lengths, rng), scale)
    traj = rom_modal.modal_trajectory(run, method="loop")
    expected = np.einsum("npr,pmr->pnm", traj, gain)
    got = rom_stream.modal_outputs(run, gain, chunk=chunk)
    assert got.shape == (p, sum(lengths) + 1, m)
    np.testing.assert_allclose(got, expected, atol=1e-9)


@pytest.mark.parametrize("lengths", list(CASES.values()), ids=list(CASES))
def test_pieces_tile_the_window_and_never_cross_a_chunk_end(lengths: list[int]) -> None:
    seg = _segments(lengths, np.random.default_rng(0))
    pieces = rom_stream.chunk_pieces(seg, 8)
    ends = pieces.start + pieces.length
    assert pieces.start[0] == 0 and ends[-1] == sum(lengths)
    np.testing.assert_array_equal(pieces.start[1:], ends[:-1])
    assert np.all(pieces.start // 8 == (ends - 1) // 8)  # inside one chunk
    assert np.all(seg.start[pieces.segment] <= pieces.start)  # inside its segment
    assert np.all(ends <= seg.start[pieces.segment] + seg.length[pieces.segment])
    for c in range(pieces.bounds.size - 1):  # chunk c holds exactly the pieces starting in it
        inside = pieces.start[pieces.bounds[c] : pieces.bounds[c + 1]] // 8
        assert np.all(inside == c)


def test_empty_window_gives_the_start_only_and_bad_chunk_is_named() -> None:
    rng = np.random.default_rng(1)
    b0, gain = rng.normal(size=(2, 3)), rng.normal(size=(2, 4, 3))
    empty = rom_modal.split_segments(np.zeros(0), np.zeros(0), np.zeros(0))
    lam = np.ones((2, 3))
    forcing = (np.zeros((2, 3)),) * 3
    got = rom_stream.modal_outputs(
        rom_modal.ModalRun(b0, lam, 0.5 * lam, forcing, empty, np.ones((2, 2))), gain
    )
    np.testing.assert_allclose(got[:, 0, :], np.einsum("pmr,pr->pm", gain, b0))
    assert got.shape == (2, 1, 4)
    with pytest.raises(ValueError, match="chunk"):
        rom_stream.chunk_pieces(_segments([3], rng), 0)
