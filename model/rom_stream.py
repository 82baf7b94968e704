"""Sensor outputs of the modal closed form (``model.rom_modal``), streamed through the window in time chunks.

For a population (P candidates, rank r) the whole modal trajectory b(n), (n_steps+1, P, r), is several MB
(4 MB for P = 28, r = 50, 360 steps). Materialising it, plus its per-step increments and a transposed copy
for the sensor product, made a call write ~15 MB of fresh arrays. Whether that is cheap depends on the
allocator's history: glibc hands arrays above its (adaptive) mmap threshold out as fresh pages and faults
each one on first touch (~1 µs per 4 KiB page here), which made the same call 1.7x slower in one process
than in another (0.42 vs 0.25 ms per candidate, ``python -m benchmarks model``). This evaluator keeps only
``chunk`` steps of the trajectory and writes the outputs G·b(n) straight into the result: a call touches the
result plus a few chunk-sized buffers, whatever the allocator does. The arithmetic is that of the "loop" path
of ``modal_trajectory`` (exact θ-method recursion; a run of constant input uses the power table), so the two
agree to round-off.

Pure numpy; no I/O.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from model.rom_modal import (
    ModalRun,
    Segments,
    choose_method,
    modal_trajectory,
    power_table,
    segment_inputs,
    unit_responses,
)

Array = NDArray[np.float64]

DEFAULT_CHUNK = 32  # steps per chunk; measured in docs/design/rom.md ("Streaming the window")


@dataclass(frozen=True)
class Pieces:
    """The segments cut at every ``chunk`` steps. Piece k covers ``length[k]`` steps from step ``start[k]``
    of the window with the inputs of segment ``segment[k]``; chunk c holds pieces bounds[c] to bounds[c+1]."""

    segment: NDArray[np.int64]
    start: NDArray[np.int64]
    length: NDArray[np.int64]
    bounds: NDArray[np.int64]


def chunk_pieces(segments: Segments, chunk: int) -> Pieces:
    """Cut the segments at every multiple of ``chunk`` steps (vectorised: no Python loop over segments)."""
    if chunk < 1:
        raise ValueError(f"chunk: must be >= 1 step, got {chunk}")
    n_steps = int(segments.length.sum())
    start = np.union1d(segments.start, np.arange(0, n_steps, chunk)).astype(np.int64)
    length = np.diff(np.append(start, n_steps)).astype(np.int64)
    segment = (np.searchsorted(segments.start, start, side="right") - 1).astype(np.int64)
    bounds = np.searchsorted(start, np.arange(0, n_steps + chunk, chunk)[: -(-n_steps // chunk) + 1])
    return Pieces(segment, start, length, bounds.astype(np.int64))


def window_outputs(run: ModalRun, gain: Array, *, direct: tuple[Array, Array] | None = None) -> Array:
    """Outputs (P, n_steps+1, m) of a modal run through ``gain`` (P, m, r): streamed (``modal_outputs``) for
    few segments or a wide population (``model.rom_modal.choose_method``), else from the whole trajectory;
    ``direct`` as in ``modal_outputs``."""
    seg = run.segments
    n = int(seg.length.sum())
    if n > 0 and choose_method(seg.start.size, n, run.b0.size) == "loop":
        return modal_outputs(run, gain, direct=direct)
    b = modal_trajectory(run)  # (n+1, P, r)
    # contiguous operands: BLAS is ~40 % slower on the transposed views
    b_pnr = np.ascontiguousarray(np.swapaxes(b, 0, 1))
    y = np.matmul(b_pnr, np.ascontiguousarray(np.swapaxes(gain, 1, 2)))
    if direct is not None and n > 0:
        y[:, 1:, :] += np.matmul(direct[0][None, :, :], direct[1])
    return np.asarray(y)


def modal_outputs(
    run: ModalRun, gain: Array, *, chunk: int = DEFAULT_CHUNK, direct: tuple[Array, Array] | None = None
) -> Array:
    """Outputs y_p(n) = G_p·b_p(n), (P, n_steps+1, m), of the trajectory that ``modal_trajectory(run)`` gives.

    ``gain`` (P, m, r) maps modal coordinates to outputs (sensor rows times the candidate's eigenvectors,
    in °C per unit modal coordinate). ``direct`` (rows (n_steps, q), weights (P, q, m)) adds
    rows[n−1]·weights_p to y_p(n) for n ≥ 1, chunk by chunk (no window-sized temporary).
    """
    segments = run.segments
    n_steps = int(segments.length.sum())
    p, r = run.b0.shape
    gain_t = np.ascontiguousarray(np.swapaxes(gain, 1, 2))  # (P, r, m); a strided view is ~40 % slower
    out = np.empty((p, n_steps + 1, gain.shape[1]))
    np.matmul(run.b0[:, None, :], gain_t, out=out[:, 0:1, :])
    if n_steps == 0:
        return out
    ops = unit_responses(run)
    x = segment_inputs(segments)
    pieces = chunk_pieces(segments, chunk)
    longest = int(pieces.length.max())
    work = _Work(
        traj=np.empty((min(chunk, n_steps), p * r)),
        loads=np.empty((min(chunk, n_steps), p * r)),
        mu=run.mu.reshape(p * r),
        pw=power_table(run.mu, longest).reshape(longest + 1, p * r) if longest > 1 else None,
    )
    state = run.b0.reshape(p * r)
    extra = None if direct is None else np.empty((p, min(chunk, n_steps), gain.shape[1]))
    for c in range(pieces.bounds.size - 1):
        k0, k1 = int(pieces.bounds[c]), int(pieces.bounds[c + 1])
        first = int(pieces.start[k0])
        used = int(pieces.start[k1 - 1] + pieces.length[k1 - 1]) - first
        _advance(work, state, pieces, k0, k1, x, ops)
        block = work.traj[:used].reshape(used, p, r)
        np.matmul(np.swapaxes(block, 0, 1), gain_t, out=out[:, first + 1 : first + used + 1, :])
        if direct is not None and extra is not None:
            np.matmul(direct[0][None, first : first + used, :], direct[1], out=extra[:, :used, :])
            out[:, first + 1 : first + used + 1, :] += extra[:, :used, :]
        state = work.traj[used - 1].copy()
    return out


@dataclass(frozen=True)
class _Work:
    """Chunk buffers, flattened to P·r columns: trajectory rows, step increments, μ and its power table."""

    traj: Array
    loads: Array
    mu: Array
    pw: Array | None


def _advance(
    work: _Work, state: Array, pieces: Pieces, k0: int, k1: int, x: Array, ops: tuple[Array, Array]
) -> None:
    """Fill work.traj[0:used] with b(first+1 ..) from b(first) = ``state`` (P·r,), over pieces k0:k1."""
    seg, length = pieces.segment[k0:k1], pieces.length[k0:k1]
    off = pieces.start[k0:k1] - pieces.start[k0]
    singles = length == 1
    n_single = int(np.count_nonzero(singles))
    if n_single:  # the increments of all one-step pieces in one BLAS product: (k, 3) @ (3, P·r)
        np.matmul(x[seg[singles]], ops[1], out=work.loads[:n_single])
    k = 0
    traj, mu = work.traj, work.mu
    for s, o, n in zip(seg.tolist(), off.tolist(), length.tolist(), strict=True):
        prev = state if o == 0 else traj[o - 1]
        if n == 1 or work.pw is None:
            row = traj[o]
            np.multiply(mu, prev, out=row)
            row += work.loads[k]
            k += 1
            continue
        fixed = x[s] @ ops[0]
        block = traj[o : o + n]
        np.multiply(work.pw[1 : n + 1], prev - fixed, out=block)
        block += fixed
