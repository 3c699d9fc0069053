"""On-disk cache of generated meshes, keyed by builder name and parameters.

A generated mesh is stored as ``<cache dir>/<builder>-<key>.npz`` (arrays ``points``,
``tets``, ``source``) where ``key`` is the first 20 hex digits of the SHA-256 of the
canonical JSON of ``{builder, params, generator, format}``. The cache directory is
``$WRINKLES_CACHE`` when set, else ``<repo>/.cache/meshes`` (gitignored; never commit
generated meshes). Writes are atomic (temporary file + ``os.replace``), so concurrent
processes (e.g. MPI ranks) never read a half-written file; an unreadable cache entry is
regenerated.
"""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
import warnings
import zipfile
from collections.abc import Callable, Mapping
from pathlib import Path

import numpy as np

from meshes.tetmesh import TetMesh
from meshes.validate import validate

#: Bump when the stored layout or the builders' geometry change, to invalidate old entries.
CACHE_FORMAT = 2

_REPO = Path(__file__).resolve().parents[1]


def cache_dir() -> Path:
    """Directory of cached meshes: ``$WRINKLES_CACHE`` or ``<repo>/.cache/meshes``."""
    env = os.environ.get("WRINKLES_CACHE")
    return Path(env) if env else _REPO / ".cache" / "meshes"


def cache_key(builder: str, params: Mapping[str, object], generator: str = "") -> str:
    """Stable hash of a builder call.

    Args:
        builder: Builder name, e.g. ``"sphere"``.
        params: JSON-serialisable parameters (floats are hashed by their exact ``repr``).
        generator: Version string of the mesh generator (a new gmsh invalidates entries).

    Returns:
        20 hex digits of ``sha256(json({builder, params, generator, format}))``.

    """
    blob = json.dumps({"builder": builder, "params": dict(params), "generator": generator,
                       "format": CACHE_FORMAT}, sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()[:20]


def cache_path(builder: str, params: Mapping[str, object], generator: str = "") -> Path:
    """File of the cache entry for this builder call (it may not exist yet)."""
    return cache_dir() / f"{builder}-{cache_key(builder, params, generator)}.npz"


def write_npz(mesh: TetMesh, path: Path) -> None:
    """Atomically write ``mesh`` to ``path`` as .npz (points, tets, source)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=path.name, suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            np.savez(fh, points=mesh.points, tets=mesh.tets, source=np.array(mesh.source))
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def read_npz(path: Path) -> TetMesh | None:
    """Read a cache entry; None when it is missing, corrupt or fails validation."""
    try:
        with np.load(path, allow_pickle=False) as data:
            mesh = TetMesh(data["points"], data["tets"], str(data["source"][()]))
        return validate(mesh)
    except (OSError, KeyError, ValueError, EOFError, zipfile.BadZipFile):
        return None


def cached(builder: str, params: Mapping[str, object], build: Callable[[], TetMesh],
           generator: str = "", use_cache: bool = True) -> TetMesh:
    """Return the cached mesh for this builder call, building and storing it on a miss.

    Args:
        builder: Builder name (part of the file name and key).
        params: Parameters of the call (part of the key).
        build: Generates the mesh on a miss (e.g. runs gmsh).
        generator: Version string of the generator (part of the key).
        use_cache: If False, always build and neither read nor write the cache.

    Returns:
        The mesh, identical arrays whether built or read back. An unwritable cache
        directory only warns (``RuntimeWarning``).

    """
    if not use_cache:
        return build()
    path = cache_path(builder, params, generator)
    hit = read_npz(path) if path.exists() else None
    if hit is not None:
        return hit
    mesh = build()
    try:
        write_npz(mesh, path)
    except OSError as exc:
        warnings.warn(f"mesh cache not written ({exc}); set WRINKLES_CACHE to a writable "
                      "directory", RuntimeWarning, stacklevel=2)
    return mesh
