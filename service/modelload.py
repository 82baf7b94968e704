"""Load the spindle description, the FE model and the cached reduced model from settings (one place).

Used by the service process (live field, field snapshots) and by the identification worker process (in its
initializer, once per process). ``ModelRef`` is small and picklable so it can cross the process boundary;
the reduced model is read from the cache file there, not pickled.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from model.fem import FEModel
    from model.geometry import SpindleSpec
    from model.rom import ReducedModel
    from service.settings import Settings

__all__ = ["LoadedModel", "ModelRef", "load_model"]


@dataclass(frozen=True, kw_only=True)
class ModelRef:
    """What identifies the model: spindle TOML (None: packaged), mesh size m (None: the model's default),
    ROM rank, cache dir, H box. No defaults here: ``from_settings`` builds it (``[model]``,
    ``[experimental]``)."""

    spindle: str | None
    mesh_size_m: float | None
    rom_rank: int
    cache_dir: str
    h_box: tuple[float, float]

    @classmethod
    def from_settings(cls, settings: Settings) -> ModelRef:
        """From ``service.settings.Settings``: its ``model`` section, and the mesh and rank from
        ``experimental`` (research switches, issue 25)."""
        model, exp = settings.model, settings.experimental
        return cls(
            spindle=str(model.spindle) if model.spindle is not None else None,
            mesh_size_m=exp.mesh_size_m,
            rom_rank=int(exp.rom_rank),
            cache_dir=str(model.rom_cache_dir),
            h_box=(float(model.h_box[0]), float(model.h_box[1])),
        )


@dataclass(frozen=True, eq=False, kw_only=True)
class LoadedModel:
    spec: SpindleSpec
    fe: FEModel
    rom: ReducedModel
    ref: ModelRef

    @property
    def version(self) -> str:
        """Short model id: the reduced-model cache key (geometry + mesh + options)."""
        key = str(self.rom.key or "")
        return key[:16] or "unversioned"


def load_model(ref: ModelRef, *, progress: Callable[[str], None] | None = None) -> LoadedModel:
    """Spec, FE model and reduced model (from the cache, built and saved there on a miss)."""
    from model.fem import build_fe_model
    from model.geometry import load_spindle
    from model.rom import load_or_build_rom

    spec = load_spindle(ref.spindle)
    fe = build_fe_model(spec, mesh_size_m=ref.mesh_size_m)
    cache = Path(ref.cache_dir) if ref.cache_dir else Path.home() / ".cache" / "spindle-chtc"
    cache.mkdir(parents=True, exist_ok=True)
    rom = load_or_build_rom(fe, spec, cache, rank=ref.rom_rank, box=ref.h_box, progress=progress)
    return LoadedModel(spec=spec, fe=fe, rom=rom, ref=ref)
