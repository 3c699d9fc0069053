"""Mesh cache: a hit does not run gmsh, keys separate parameters, bad entries regenerate."""

from __future__ import annotations

from pathlib import Path

import gmsh
import numpy as np
import pytest
from support import REPO

from meshes import box, sphere
from meshes.cache import cache_dir, cache_key, cache_path
from meshes.errors import SolverError


@pytest.fixture
def cache(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    monkeypatch.setenv("WRINKLES_CACHE", str(tmp_path / "meshes"))
    return tmp_path / "meshes"


@pytest.fixture
def no_gmsh(monkeypatch: pytest.MonkeyPatch):
    """Make any gmsh meshing call fail, so a cache hit is the only way to get a mesh."""

    def refuse(*args, **kwargs):
        raise RuntimeError("gmsh was called")

    def apply() -> None:
        monkeypatch.setattr(gmsh.model.mesh, "generate", refuse)
        monkeypatch.setattr(gmsh, "initialize", refuse)

    return apply


def test_second_call_is_a_hit_without_gmsh(cache: Path, no_gmsh) -> None:
    first = sphere(0.5, 0.25)
    files = list(cache.glob("sphere-*.npz"))
    assert files == [cache_path("sphere", {"radius": 0.5, "h": 0.25,
                                           "center": (0.0, 0.0, 0.0)},
                                f"gmsh {gmsh.__version__}")]
    no_gmsh()
    with pytest.raises(SolverError, match=r"sphere\(radius=0\.5, h=0\.25, .*: gmsh was called"):
        sphere(0.5, 0.25, cache=False)  # the patch is effective
    second = sphere(0.5, 0.25)
    np.testing.assert_array_equal(second.points, first.points)
    np.testing.assert_array_equal(second.tets, first.tets)
    assert second.source == first.source == "sphere(radius=0.5, h=0.25, center=(0.0, 0.0, 0.0))"
    with pytest.raises(SolverError, match=r"sphere\(radius=0\.5, h=0\.24, .*: gmsh was called"):
        sphere(0.5, 0.24)  # another parameter is a miss


def test_keys_depend_on_every_parameter() -> None:
    base = {"lx": 1.0, "ly": 1.0, "lz": 1.0, "h": 0.5, "origin": (0.0, 0.0, 0.0)}
    keys = {cache_key("box", base), cache_key("box", {**base, "h": 0.5000000000000001}),
            cache_key("box", {**base, "origin": (0.0, 0.0, 1e-300)}),
            cache_key("sphere", base), cache_key("box", base, "gmsh 0.0")}
    assert len(keys) == 5
    assert cache_key("box", dict(reversed(list(base.items())))) == cache_key("box", base)


def test_corrupt_entry_is_regenerated(cache: Path) -> None:
    first = box(1.0, 1.0, 1.0, 0.5)
    (entry,) = cache.glob("box-*.npz")
    entry.write_bytes(b"PK\x03\x04 truncated")
    again = box(1.0, 1.0, 1.0, 0.5)
    np.testing.assert_array_equal(again.tets, first.tets)
    assert entry.stat().st_size > 1000


def test_default_cache_dir_is_in_repo(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("WRINKLES_CACHE", raising=False)
    repo = REPO
    assert cache_dir() == repo / ".cache" / "meshes"


def test_unwritable_cache_only_warns(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    blocker = tmp_path / "not_a_dir"
    blocker.write_text("a file where the cache directory should be")
    monkeypatch.setenv("WRINKLES_CACHE", str(blocker / "meshes"))
    with pytest.warns(RuntimeWarning, match="mesh cache not written"):
        m = box(1.0, 1.0, 1.0, 0.5)
    assert abs(m.volume - 1.0) <= 1e-12
