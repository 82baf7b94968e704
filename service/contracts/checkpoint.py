"""The live state's checkpoint: what a restart needs to resume the filtered state instead of starting over
(pure, no I/O).

After a restart the filter would start from its prior at the ambient (``FilteredState.initialize``). The
sensors then see the housing at once, but the shaft's inside only through the slow heat flow, so the served
growth stays off by what the prior did not know of the warm shaft until the data have seen it (measured: up to
2.9 µm for an hour after a warm restart, docs/design/estimator.md "Resuming after a restart"). The service
therefore stores the filter's belief every ``database.live_checkpoint_s`` of sample time (one row, replaced:
``service.store.livestate``) and a restart resumes from it when the first sample comes within the filter's
``max_gap_s`` (300 s) of the checkpoint. Across the gap the state runs open loop with the inputs held at the
checkpoint, its covariance growing by the process noise, as over any gap in the data; a longer gap starts
from the prior as before. The resumed state serves as converged at once; identification windows start only
once it has passed the convergence test on the new process's data (``FilteredState.resume``).

A checkpoint holds the belief (reduced ``mean`` (r,) [°C], ``cov`` (r, r) [°C²], ``cross`` (r, 9)), the
unknown offsets' share (``bias_s`` (r, n), ``bias_m`` (r, r): ``service.estimate.offsetbias``), the held
``inputs`` (ambient °C, speed rpm, torque N·m), its time ``t`` [s since the epoch], whether the state had
converged, the considered parameters' 1σ ``param_std`` (9,) that ``cross`` goes with (None in checkpoints
written before 2026-11-27: the resumed cross is then taken as it is), and the ``model_version`` it was
computed with: a checkpoint of another reduced model (a new mesh,
rank or geometry) is refused (``CheckpointError``) and the state starts from the prior.

Errors::

    CheckpointError(ServiceError, ValueError)   a checkpoint that cannot be used; the message names the field
"""

from __future__ import annotations

import io
import math
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Any

import numpy as np
from numpy.typing import NDArray

from service.contracts.columns import Column
from service.errors import ServiceError

__all__ = ["CheckpointError", "LiveCheckpoint"]

Array = NDArray[np.float64]
_ARRAYS = ("mean", "cov", "cross", "bias_s", "bias_m")


class CheckpointError(ServiceError, ValueError):
    """A live-state checkpoint that cannot be used (bad shape, non-finite, another model); names the field."""


@dataclass(frozen=True, eq=False, kw_only=True)
class LiveCheckpoint:
    """The filtered live state at ``t`` [s] (module docstring)."""

    t: float
    model_version: str
    converged: bool
    inputs: tuple[float, float, float]
    mean: Array
    cov: Array
    cross: Array
    bias_s: Array
    bias_m: Array
    param_std: Array | None = None  # (9,) the considered parameters' 1σ at the checkpoint (``cross``'s)
    # the served verdict's CI gate and the command value at the checkpoint, as numbers
    # (``service.serve.controlled.ControlState.to_array``; None in checkpoints before issue 42)
    control: Array | None = None

    def __post_init__(self) -> None:
        if not math.isfinite(self.t):
            raise CheckpointError(f"live checkpoint: t must be finite, got {self.t}")
        if len(self.inputs) != 3 or not all(math.isfinite(float(x)) for x in self.inputs):
            raise CheckpointError(f"live checkpoint: inputs must be 3 finite values, got {self.inputs}")
        r = self.mean.shape[0] if self.mean.ndim == 1 else -1
        shapes = {"mean": (r,), "cov": (r, r), "bias_m": (r, r)}
        for name in _ARRAYS:
            arr = getattr(self, name)
            want = shapes.get(name)
            ok = arr.shape == want if want is not None else arr.ndim == 2 and arr.shape[0] == r
            if r < 1 or not ok:
                raise CheckpointError(f"live checkpoint: {name} has shape {arr.shape}, state size {r}")
            if not np.all(np.isfinite(arr)):
                raise CheckpointError(f"live checkpoint: {name} holds non-finite values")
        ps = self.param_std
        if ps is not None and (
            ps.shape != (self.cross.shape[1],) or not np.all(np.isfinite(ps)) or np.any(ps < 0)
        ):
            raise CheckpointError(
                f"live checkpoint: param_std must be {self.cross.shape[1]} finite values >= 0, got {ps!r}"
            )

    @property
    def rank(self) -> int:
        """The reduced state's size r."""
        return int(self.mean.shape[0])

    def check_for(self, model_version: str, rank: int, n_channels: int) -> None:
        """Raise ``CheckpointError`` unless this checkpoint fits a state of ``rank`` over ``n_channels`` of
        the reduced model ``model_version``."""
        if self.model_version != model_version:
            raise CheckpointError(
                f"live checkpoint: computed with model {self.model_version!r}, "
                f"the service runs {model_version!r}"
            )
        if self.rank != rank or self.bias_s.shape != (rank, n_channels):
            raise CheckpointError(
                f"live checkpoint: state size {self.rank} over {self.bias_s.shape[1]} channels, "
                f"the model has {rank} over {n_channels}"
            )

    def to_bytes(self) -> bytes:
        """The arrays as an ``.npz`` archive (float64, no pickles)."""
        buf = io.BytesIO()
        arrays: dict[str, Any] = {name: np.asarray(getattr(self, name), dtype="<f8") for name in _ARRAYS}
        if self.param_std is not None:
            arrays["param_std"] = np.asarray(self.param_std, dtype="<f8")
        if self.control is not None:
            arrays["control"] = np.asarray(self.control, dtype="<f8")
        np.savez(buf, **arrays)
        return buf.getvalue()

    def values(self) -> dict[str, Column]:
        """The one ``live_state`` row (``service.store``): the time, the model, the held inputs and the arrays
        as an ``.npz`` ``payload``; the writer keeps only the newest."""
        return {
            "at": datetime.fromtimestamp(self.t, tz=UTC),
            "model_version": self.model_version[:64],
            "converged": bool(self.converged),
            "ambient_c": float(self.inputs[0]),
            "speed_rpm": float(self.inputs[1]),
            "torque_nm": float(self.inputs[2]),
            "payload": self.to_bytes(),
        }

    @classmethod
    def from_parts(
        cls,
        payload: bytes,
        *,
        t: float,
        model_version: str,
        converged: bool,
        inputs: tuple[float, float, float],
    ) -> LiveCheckpoint:
        """Rebuild from ``to_bytes``'s archive and the scalar fields; ``CheckpointError`` naming what is
        wrong (a missing array, a damaged archive)."""
        try:
            with np.load(io.BytesIO(payload), allow_pickle=False) as npz:
                arrays = {name: np.array(npz[name], dtype=np.float64) for name in _ARRAYS}
                for name in ("param_std", "control"):  # older checkpoints lack them
                    if name in npz.files:
                        arrays[name] = np.array(npz[name], dtype=np.float64)
        except KeyError as err:
            raise CheckpointError(f"live checkpoint: payload lacks the array {err}") from err
        except (OSError, ValueError, EOFError) as err:
            raise CheckpointError(f"live checkpoint: payload is not an array archive ({err})") from err
        return cls(
            t=float(t),
            model_version=str(model_version),
            converged=bool(converged),
            inputs=(float(inputs[0]), float(inputs[1]), float(inputs[2])),
            **arrays,
        )
