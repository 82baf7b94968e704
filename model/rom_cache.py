"""On-disk cache of the reduced model: a hash key and an atomic npz file per key.

The key covers everything that changes the reduced model: the FE matrices and mesh (hence geometry, materials,
mesh size and sensor positions), the spec's text form, and the build options (rank, θ, H box, training and
check settings). Files are named ``rom-<key[:20]>.npz`` inside the cache directory, written to a temporary
name and renamed, so a crashed build never leaves a half file under the real name.
"""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
import zipfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from model.errors import ModelError

FORMAT_VERSION = 2  # bump when the training changes: old cache files are then ignored


class CacheReadError(ModelError, OSError):
    """The file is missing, truncated, not an npz, or lacks a field (named in the message)."""


def _feed_array(digest: Any, value: Any) -> None:
    if sp.issparse(value):
        csr = sp.csr_matrix(value)
        csr.sort_indices()
        for part in (csr.data, csr.indices, csr.indptr, np.asarray(csr.shape)):
            _feed_array(digest, part)
        return
    arr = np.ascontiguousarray(np.asarray(value))
    digest.update(str(arr.dtype).encode() + str(arr.shape).encode())
    digest.update(arr.tobytes())


def cache_key(fe: Any, spec: Any, options: Mapping[str, Any]) -> str:
    """SHA-256 hex key of the FE matrices and mesh, ``repr(spec)`` and the build options."""
    digest = hashlib.sha256()
    digest.update(f"chtc-rom-v{FORMAT_VERSION}".encode())
    for name in ("E", "K0", "z_zone", "q_front", "q_rear", "sensor_op", "nodes_rz", "triangles"):
        value = getattr(fe, name, None)
        digest.update(name.encode())
        if value is not None:
            _feed_array(digest, value)
    for k in getattr(fe, "K_zone", ()):
        _feed_array(digest, k)
    digest.update(repr(spec).encode())
    digest.update(json.dumps(dict(options), sort_keys=True, default=str).encode())
    return digest.hexdigest()


def cache_path(cache_dir: Path, key: str) -> Path:
    """File of one key inside ``cache_dir``."""
    return Path(cache_dir) / f"rom-{key[:20]}.npz"


def save(path: Path, arrays: Mapping[str, NDArray[Any]], meta: Mapping[str, Any]) -> None:
    """Write arrays plus a JSON ``meta`` record atomically to ``path`` (npz, uncompressed)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    payload: dict[str, Any] = dict(arrays)
    payload["meta_json"] = np.frombuffer(json.dumps(dict(meta), sort_keys=True).encode(), dtype=np.uint8)
    fd, tmp = tempfile.mkstemp(prefix=path.name, suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            np.savez(fh, **payload)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def load(path: Path, names: tuple[str, ...]) -> tuple[dict[str, NDArray[Any]], dict[str, Any]]:
    """Read the named arrays and the meta record; ``CacheReadError`` names what is wrong."""
    try:
        with np.load(Path(path), allow_pickle=False) as data:
            missing = [n for n in (*names, "meta_json") if n not in data.files]
            if missing:
                raise CacheReadError(f"{path}: missing field(s) {', '.join(missing)}")
            arrays = {n: np.asarray(data[n]) for n in names}
            meta = json.loads(bytes(data["meta_json"]).decode())
    except CacheReadError:
        raise
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, json.JSONDecodeError) as err:
        raise CacheReadError(f"{path}: unreadable reduced-model cache ({err})") from err
    if not isinstance(meta, dict):
        raise CacheReadError(f"{path}: field meta_json is not an object")
    return arrays, meta
