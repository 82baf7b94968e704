"""The root of the model layer's typed error tree.

Every exception class defined in ``model/`` derives from :class:`ModelError` (``tests/test_layers.py``
checks it); the builtin base each had before (``ValueError`` for a bad argument or file, ``OSError`` for a
cache file) is kept beside it. Every message names the field, argument or file at fault. The tree::

    ModelError(Exception)                               model.errors
    ├── SpindleError(ModelError, ValueError)            model.geometry: the spindle description
    ├── MeshError(ModelError, ValueError)               model.mesh
    ├── FEError(ModelError, ValueError)                 model.fem
    ├── SolverError(ModelError, ValueError)             model.banded
    ├── InputError(ModelError, ValueError)              model.inputs
    ├── PlantError(ModelError, ValueError)              model.plant: the virtual plant
    ├── RomError(ModelError, ValueError)                model.rom: the reduced model
    │   └── RomCacheError(RomError)                     its cache
    ├── CacheReadError(ModelError, OSError)             model.rom_cache: a cache file that cannot be read
    ├── SegmentError(ModelError, ValueError)            model.rom_segments
    ├── EstimatorError(ModelError, ValueError)          model.estimator: the Kalman filter
    ├── IdentificationError(ModelError, ValueError)     model.identify
    │   └── InsufficientDataError(IdentificationError)  too few usable data in the window
    ├── HMapError(ModelError, ValueError)               model.hmap: H = F(n, Ti)
    ├── HMapIdentifyError(ModelError, ValueError)       model.hmap_identify
    ├── CarryError(ModelError, ValueError)              model.carry
    ├── GrowthError(ModelError, ValueError)             model.growth
    ├── ThermoelasticError(ModelError, ValueError)      model.thermoelastic
    └── OptimizerError(ModelError)                      model.optim (its tree in model/optim/_common.py)
        ├── BoundsError(OptimizerError, ValueError)
        └── ObjectiveError(OptimizerError, ValueError)
"""

from __future__ import annotations

__all__ = ["ModelError"]


class ModelError(Exception):
    """Base of every error raised by ``model/``."""
