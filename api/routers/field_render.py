"""Bodies of GET /temperature-field, built off the event loop, cached per field content, gzip-ready.

What costs: the mesh body is ~470 KB of JSON (8.7k nodes, 16.4k triangles); pydantic took ~60 ms for it (and
~200 ms on a busy machine), gzip at level 6 another ~60 ms, and both hold the GIL, so every mesh request
stalled the event loop and ``/chtc`` with it. The geometry never changes and the temperatures change once per
sample, so:

- the geometry part (``nodes_r_m``, ``nodes_z_m``, ``triangles``) is serialised once per mesh, and also fed
  once into a gzip compressor whose state is copied for each new field (only the ~70 KB of temperatures and
  metadata are compressed per field);
- a body is cached per content (at, t, identification, a hash of the temperatures, format and grid size);
  its ETag is that key, so a client polling an unchanged field gets a 304;
- a grid's points are located once per grid size (``model.locator.TriangleLocator.grid``).

``FieldGate`` sheds load: at most ``limit`` field requests are in progress; the next one gets a 503 with
``Retry-After`` at once instead of queueing for a thread.
"""

from __future__ import annotations

import hashlib
import json
import math
import threading
import zlib
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from api.schemas import FieldMeta
from api.stdmax import std_max
from service.contracts.snapshots import FieldSnapshot

__all__ = ["FieldGate", "FieldRenderer", "Rendered"]

GZIP_MIN_BYTES = 1024
_GZIP_LEVEL = 6


def _dumps(value: object) -> str:
    return json.dumps(value, separators=(",", ":"), ensure_ascii=False, allow_nan=False)


def _clean(values: np.ndarray) -> list[float | None]:
    """Rounded to 0.1 mK, None for NaN (outside the section) or inf."""
    return [None if not math.isfinite(v) else v for v in np.round(values, 4).tolist()]


def meta_json(f: FieldSnapshot, spindle_id: str) -> str:
    """The metadata members (``spindle_id``, ``at``, ``t``, ``identification_id``, units, min/max) without
    braces."""
    finite = f.temps_c[np.isfinite(f.temps_c)]
    meta = FieldMeta(
        spindle_id=spindle_id,
        at=f.at,
        t=f.t,
        identification_id=f.identification_id,
        t_min_c=round(float(finite.min()), 4) if finite.size else None,
        t_max_c=round(float(finite.max()), 4) if finite.size else None,
        std_max_c=std_max(f),
    )
    return meta.model_dump_json()[1:-1]


@dataclass(kw_only=True)
class Rendered:
    """One response body, its ETag, and its gzip form (made on first demand, then kept)."""

    body: bytes
    etag: str
    _gz: bytes | None = None
    # (compressor copy source, compressed head, dynamic part) for the mesh
    _gzip_tail: tuple[zlib._Compress, bytes, bytes] | None = None
    _lock: threading.Lock = field(default_factory=threading.Lock)

    def gzip(self) -> bytes:
        with self._lock:
            if self._gz is None:
                if self._gzip_tail is not None:
                    base, head, dynamic = self._gzip_tail
                    c = base.copy()
                    self._gz = head + c.compress(dynamic) + c.flush()
                    self._gzip_tail = None
                else:
                    c = zlib.compressobj(_GZIP_LEVEL, zlib.DEFLATED, 31)
                    self._gz = c.compress(self.body) + c.flush()
            return self._gz


class _MeshGeometry:
    """The mesh's JSON members and a gzip compressor primed with them (``{`` + geometry)."""

    def __init__(self, f: FieldSnapshot) -> None:
        geometry = (
            f'"nodes_r_m":{_dumps(np.round(f.nodes_rz[:, 0], 7).tolist())},'
            f'"nodes_z_m":{_dumps(np.round(f.nodes_rz[:, 1], 7).tolist())},'
            f'"triangles":{_dumps(np.asarray(f.triangles, dtype=int).tolist())},'
        )
        self.head = ("{" + geometry).encode()
        self.compressor = zlib.compressobj(_GZIP_LEVEL, zlib.DEFLATED, 31)
        self.head_gz = self.compressor.compress(self.head)
        self.key = hashlib.blake2b(self.head, digest_size=8).hexdigest()


class FieldRenderer:
    """Thread-safe cache of field bodies (the newest ``entries``) and of the mesh geometry, of one spindle's
    fields (``spindle_id``, named in every body)."""

    def __init__(self, *, spindle_id: str, entries: int = 8) -> None:
        self.spindle_id = spindle_id
        self._entries = entries
        self._bodies: OrderedDict[str, Rendered] = OrderedDict()
        self._geometry: tuple[object, object, _MeshGeometry] | None = None  # (nodes, triangles) by identity
        self._lock = threading.Lock()
        self._build_lock = threading.Lock()  # one build at a time: concurrent misses wait, then hit
        self.builds = 0

    def _geometry_of(self, f: FieldSnapshot) -> _MeshGeometry:
        with self._lock:
            g = self._geometry
            if g is not None and g[0] is f.nodes_rz and g[1] is f.triangles:
                return g[2]
        geom = _MeshGeometry(f)
        with self._lock:
            self._geometry = (f.nodes_rz, f.triangles, geom)
        return geom

    @staticmethod
    def content_key(f: FieldSnapshot, kind: str) -> str:
        h = hashlib.blake2b(digest_size=12)
        h.update(f"{kind}|{f.at}|{f.t.isoformat()}|{f.identification_id}|".encode())
        h.update(np.ascontiguousarray(f.temps_c, dtype=float).tobytes())
        if f.std_c is not None:
            h.update(np.ascontiguousarray(f.std_c, dtype=float).tobytes())
        h.update(np.ascontiguousarray(f.nodes_rz, dtype=float).tobytes()[:4096])  # the mesh, cheaply
        return 'W/"' + h.hexdigest() + '"'

    def _cached(self, key: str, build: Callable[[], Rendered]) -> Rendered:
        with self._lock:
            hit = self._bodies.get(key)
            if hit is not None:
                self._bodies.move_to_end(key)
                return hit
        with self._build_lock:
            with self._lock:
                hit = self._bodies.get(key)
            if hit is None:
                hit = build()
                self.builds += 1
                with self._lock:
                    self._bodies[key] = hit
                    while len(self._bodies) > self._entries:
                        self._bodies.popitem(last=False)
            return hit

    def mesh(self, f: FieldSnapshot) -> Rendered:
        key = self.content_key(f, "mesh")

        def build() -> Rendered:
            geom = self._geometry_of(f)
            std = "null" if f.std_c is None else _dumps(_clean(f.std_c))
            dynamic = (
                f'"format":"mesh",{meta_json(f, self.spindle_id)},'
                f'"temps_c":{_dumps(_clean(f.temps_c))},"std_c":{std}}}'
            ).encode()
            return Rendered(
                body=geom.head + dynamic, etag=key, _gzip_tail=(geom.compressor, geom.head_gz, dynamic)
            )

        return self._cached(key, build)

    def grid(self, f: FieldSnapshot, nr: int, nz: int) -> Rendered:
        key = self.content_key(f, f"grid|{nr}|{nz}")

        def build() -> Rendered:
            r, z, located = f.locator.grid(nr, nz)
            temps = f.locator.interpolate(f.temps_c, located).reshape(nr, nz)
            std = "null"
            if f.std_c is not None:
                sd = f.locator.interpolate(f.std_c, located).reshape(nr, nz)
                std = _dumps([_clean(row) for row in sd])
            body = (
                f'{{"format":"grid",{meta_json(f, self.spindle_id)},"r_m":{_dumps(np.round(r, 7).tolist())},'
                f'"z_m":{_dumps(np.round(z, 7).tolist())},'
                f'"temps_c":{_dumps([_clean(row) for row in temps])},"std_c":{std}}}'
            )
            return Rendered(body=body.encode(), etag=key)

        return self._cached(key, build)


class FieldGate:
    """At most ``limit`` field requests in progress (used on the event loop only: no lock needed)."""

    def __init__(self, limit: int = 4) -> None:
        self.limit = limit
        self.in_progress = 0
        self.shed = 0

    def try_enter(self) -> bool:
        if self.in_progress >= self.limit:
            self.shed += 1
            return False
        self.in_progress += 1
        return True

    def leave(self) -> None:
        self.in_progress -= 1
