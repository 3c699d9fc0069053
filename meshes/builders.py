"""gmsh builders (OpenCASCADE kernel) for the coarse tet bodies of the scenes.

Each builder makes the solid with the OCC kernel, meshes it with linear tetrahedra of
characteristic length ``h`` (``Mesh.MeshSizeMax = h``, the option formerly called
``Mesh.CharacteristicLengthMax``), validates the result (:func:`meshes.validate.validate`)
and caches it by builder name and parameters (:mod:`meshes.cache`). Lengths are in metres.

gmsh is a process-wide singleton and not thread-safe: every call runs inside
:func:`gmsh_session`, which serialises callers with a lock, initialises gmsh without signal
handlers or config files when needed and finalises it again only if it initialised it
(so builders work when called repeatedly, and inside a user's own gmsh session).
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import asdict, dataclass

import gmsh
import numpy as np

from meshes.cache import cached
from meshes.errors import InputError, SolverError, WrinklesError
from meshes.tetmesh import TetMesh
from meshes.validate import validate

#: Refuse calls whose estimated tet count ``8.5 V / h^3`` exceeds this (a typo in ``h``
#: would otherwise run gmsh for hours).
MAX_ESTIMATED_TETS = 5_000_000

_GMSH_LOCK = threading.RLock()
_TET = 4  # gmsh element type of the 4-node tetrahedron
_AXES = {"x": (1.0, 0.0, 0.0), "y": (0.0, 1.0, 0.0), "z": (0.0, 0.0, 1.0)}


@dataclass(frozen=True)
class Box:
    """An axis-aligned box, one part of a composite solid.

    Attributes:
        origin: Lower corner (x, y, z) in metres.
        size: Edge lengths (dx, dy, dz) in metres.

    """

    origin: tuple[float, float, float]
    size: tuple[float, float, float]

    @property
    def volume(self) -> float:
        """``dx * dy * dz``."""
        return math.prod(self.size)


@dataclass(frozen=True)
class SofaDimensions:
    """Proportions of the sofa (everything but its width), in metres.

    Attributes:
        depth: Front-to-back depth (y extent).
        seat_height: Height of the seat block's top above the floor z = 0.
        back_height: Height of the backrest's top above the floor.
        arm_height: Height of the arms' tops above the floor.
        arm_thickness: Thickness of each arm along x.
        back_thickness: Thickness of the backrest along y.

    """

    depth: float = 0.9
    seat_height: float = 0.45
    back_height: float = 0.85
    arm_height: float = 0.65
    arm_thickness: float = 0.2
    back_thickness: float = 0.2

    def __post_init__(self) -> None:
        for name, value in asdict(self).items():
            _require_positive(f"SofaDimensions.{name}", value)
        if not self.seat_height < self.arm_height < self.back_height:
            raise InputError("SofaDimensions: need seat_height < arm_height < back_height, got "
                             f"{self.seat_height}, {self.arm_height}, {self.back_height}")
        if not self.back_thickness < self.depth:
            raise InputError(f"SofaDimensions.back_thickness must be < depth ({self.depth}), "
                             f"got {self.back_thickness}")


def _require_positive(name: str, value: object) -> float:
    """Return ``value`` as a float if it is a finite number > 0, else raise InputError."""
    if isinstance(value, bool) or not isinstance(value, int | float | np.floating | np.integer):
        raise InputError(f"{name} must be a number, got {value!r}")
    if not (math.isfinite(value) and value > 0):
        raise InputError(f"{name} must be finite and > 0, got {value!r}")
    return float(value)


def _vector(name: str, value: Sequence[float]) -> tuple[float, float, float]:
    """Return ``value`` as a finite 3-tuple of floats, else raise InputError."""
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be 3 numbers, got {value!r}") from None
    if arr.shape != (3,) or not np.isfinite(arr).all():
        raise InputError(f"{name} must be 3 finite numbers, got {value!r}")
    return (float(arr[0]), float(arr[1]), float(arr[2]))


def _check_h(builder: str, h: object, volume: float) -> float:
    """Validate the mesh size ``h`` against the estimated tet count ``8.5 V / h^3``."""
    hv = _require_positive(f"{builder}: h", h)
    estimate = 8.5 * volume / hv**3
    if estimate > MAX_ESTIMATED_TETS:
        raise InputError(f"{builder}: h={hv} would give ~{estimate:.2e} tets "
                         f"(> {MAX_ESTIMATED_TETS}); use a larger h")
    return hv


def describe(builder: str, params: Mapping[str, object]) -> str:
    """Source string of a builder call, e.g. ``"sphere(radius=1.0, h=0.2)"``."""
    return f"{builder}(" + ", ".join(f"{k}={v!r}" for k, v in params.items()) + ")"


#: gmsh options a session sets (quiet, deterministic) and the meshing options of
#: :func:`_mesh_tets`; a user's own gmsh session gets its values back afterwards.
_QUIET = {"General.Terminal": 0.0, "General.Verbosity": 1.0, "General.NumThreads": 1.0}
_TOUCHED = (*_QUIET, "Mesh.MeshSizeMax", "Mesh.MeshSizeMin", "Mesh.MeshSizeFromPoints",
            "Mesh.MeshSizeFromCurvature", "Mesh.ElementOrder")


@contextmanager
def gmsh_session(name: str) -> Iterator[None]:
    """Run a block with gmsh initialised, quiet, single-threaded, on a fresh model.

    Serialised by a process-wide lock. If gmsh is not running it is initialised (no signal
    handlers, no config files) and finalised on exit. Inside a running (user) session, the
    temporary model ``name`` is removed on exit and the previous current model and the
    options this module sets are restored.
    """
    with _GMSH_LOCK:
        owner = not gmsh.isInitialized()
        if owner:
            gmsh.initialize(readConfigFiles=False, interruptible=False)
            saved, previous = {}, ""
        else:
            saved = {k: gmsh.option.getNumber(k) for k in _TOUCHED}
            previous = gmsh.model.getCurrent()
        try:
            for key, value in _QUIET.items():
                gmsh.option.setNumber(key, value)
            gmsh.model.add(name)
            yield
        finally:
            _close_session(owner, saved, previous)


def _close_session(owner: bool, saved: dict[str, float], previous: str) -> None:
    """Remove the session's model; finalise gmsh, or restore the user's model and options."""
    if not gmsh.isInitialized():
        return
    gmsh.model.remove()
    if owner:
        gmsh.finalize()
        return
    for key, value in saved.items():
        gmsh.option.setNumber(key, value)
    if previous:
        gmsh.model.setCurrent(previous)


def _mesh_tets(h: float) -> tuple[np.ndarray, np.ndarray]:
    """Mesh the current OCC model with tets of size ``h``; return (points, tets)."""
    gmsh.model.occ.synchronize()
    gmsh.option.setNumber("Mesh.MeshSizeMax", h)
    gmsh.option.setNumber("Mesh.MeshSizeMin", 0.0)
    gmsh.option.setNumber("Mesh.MeshSizeFromPoints", 0)  # OCC point sizes would cap h
    gmsh.option.setNumber("Mesh.MeshSizeFromCurvature", 0)
    gmsh.option.setNumber("Mesh.ElementOrder", 1)
    gmsh.model.mesh.generate(3)
    tags, coords, _ = gmsh.model.mesh.getNodes()
    _, node_tags = gmsh.model.mesh.getElementsByType(_TET)
    index = np.full(int(tags.max()) + 1, -1, dtype=np.int64)
    index[tags.astype(np.int64)] = np.arange(tags.size)
    tets = index[node_tags.astype(np.int64)].reshape(-1, 4)
    return coords.reshape(-1, 3), tets


def _generate(builder: str, params: Mapping[str, object], h: float,
              make_solid: Callable[[], object], use_cache: bool) -> TetMesh:
    """Build the OCC solid with ``make_solid``, mesh it, validate it (cached).

    Raises:
        SolverError: gmsh failed (its message is kept).

    """
    source = describe(builder, params)

    def build() -> TetMesh:
        try:
            with gmsh_session(builder):
                make_solid()
                points, tets = _mesh_tets(h)
        except WrinklesError:
            raise
        except Exception as exc:  # gmsh raises bare Exception on any failure
            raise SolverError(f"{source}: gmsh failed: {exc}") from exc
        return validate(TetMesh(points, tets, source))

    return cached(builder, params, build, generator=f"gmsh {gmsh.__version__}",
                  use_cache=use_cache)


def _add_box(part: Box) -> int:
    """Add an OCC box; return its volume tag."""
    return gmsh.model.occ.addBox(*part.origin, *part.size)


def box(lx: float, ly: float, lz: float, h: float,
        origin: Sequence[float] = (0.0, 0.0, 0.0), *, cache: bool = True) -> TetMesh:
    """Tet mesh of the box ``origin + [0, lx] x [0, ly] x [0, lz]`` (also a beam).

    Args:
        lx: Length along x (m).
        ly: Length along y (m).
        lz: Length along z (m).
        h: Characteristic tet edge length (m).
        origin: Lower corner (m).
        cache: Read/write the mesh cache.

    Returns:
        A validated :class:`TetMesh` whose volume is ``lx ly lz`` to round-off.

    """
    part = Box(_vector("box: origin", origin), (_require_positive("box: lx", lx),
                                                _require_positive("box: ly", ly),
                                                _require_positive("box: lz", lz)))
    hv = _check_h("box", h, part.volume)
    params = {"lx": part.size[0], "ly": part.size[1], "lz": part.size[2], "h": hv,
              "origin": part.origin}
    return _generate("box", params, hv, lambda: _add_box(part), cache)


def _axis(axis: str | Sequence[float]) -> tuple[float, float, float]:
    """Return the unit axis of ``"x" | "y" | "z"`` or of a non-zero 3-vector."""
    if isinstance(axis, str):
        if axis not in _AXES:
            raise InputError(f"cylinder: axis must be 'x', 'y', 'z' or a 3-vector, got {axis!r}")
        return _AXES[axis]
    x, y, z = _vector("cylinder: axis", axis)
    norm = math.sqrt(x * x + y * y + z * z)
    if norm == 0.0 or not math.isfinite(norm):
        raise InputError(f"cylinder: axis must be non-zero and finite, got {axis!r}")
    return (x / norm, y / norm, z / norm)


def cylinder(radius: float, length: float, h: float, axis: str | Sequence[float] = "z",
             *, cache: bool = True) -> TetMesh:
    """Tet mesh of a solid circular cylinder, base centred at the origin, along ``axis``.

    Args:
        radius: Radius R (m).
        length: Length L along the axis (m).
        h: Characteristic tet edge length (m).
        axis: ``"x"``, ``"y"``, ``"z"`` or a direction vector.
        cache: Read/write the mesh cache.

    Returns:
        A validated :class:`TetMesh`; its volume converges to ``pi R^2 L`` as O(h^2)
        (the boundary polygon's sagitta error).

    """
    r = _require_positive("cylinder: radius", radius)
    length_ = _require_positive("cylinder: length", length)
    direction = _axis(axis)
    hv = _check_h("cylinder", h, math.pi * r * r * length_)
    params = {"radius": r, "length": length_, "h": hv, "axis": direction}
    d = [length_ * c for c in direction]
    return _generate("cylinder", params, hv,
                     lambda: gmsh.model.occ.addCylinder(0.0, 0.0, 0.0, *d, r), cache)


def sphere(radius: float, h: float, center: Sequence[float] = (0.0, 0.0, 0.0),
           *, cache: bool = True) -> TetMesh:
    """Tet mesh of a solid ball.

    Args:
        radius: Radius R (m).
        h: Characteristic tet edge length (m).
        center: Centre (m).
        cache: Read/write the mesh cache.

    Returns:
        A validated :class:`TetMesh`; its volume converges to ``4/3 pi R^3`` as O(h^2).

    """
    r = _require_positive("sphere: radius", radius)
    c = _vector("sphere: center", center)
    hv = _check_h("sphere", h, 4.0 / 3.0 * math.pi * r**3)
    params = {"radius": r, "h": hv, "center": c}
    return _generate("sphere", params, hv, lambda: gmsh.model.occ.addSphere(*c, r), cache)


def sofa_parts(width: float = 2.0, dims: SofaDimensions | None = None) -> tuple[Box, ...]:
    """Return the four overlapping boxes the sofa is fused from: seat, back, two arms.

    The sofa spans ``x in [0, width]`` (width), ``y in [0, depth]`` (front at y = 0) and rests
    on z = 0. The seat block spans the full footprint up to ``seat_height``; the backrest the
    full width at the back up to ``back_height``; each arm the full depth up to
    ``arm_height``. Overlapping (not merely touching) parts make the OCC fuse robust.

    Args:
        width: Overall width along x (m); must exceed twice the arm thickness.
        dims: The other proportions.

    Returns:
        ``(seat, back, left arm, right arm)``.

    """
    d = SofaDimensions() if dims is None else dims
    w = _require_positive("sofa: width", width)
    if not w > 2.0 * d.arm_thickness:
        raise InputError(f"sofa: width must exceed 2 * arm_thickness = {2 * d.arm_thickness}, "
                         f"got {w}")
    ta = d.arm_thickness
    return (Box((0.0, 0.0, 0.0), (w, d.depth, d.seat_height)),
            Box((0.0, d.depth - d.back_thickness, 0.0), (w, d.back_thickness, d.back_height)),
            Box((0.0, 0.0, 0.0), (ta, d.depth, d.arm_height)),
            Box((w - ta, 0.0, 0.0), (ta, d.depth, d.arm_height)))


def _fuse(parts: Sequence[Box]) -> None:
    """Fuse the boxes into one OCC volume (raises InputError if they do not fuse)."""
    tags = [(3, _add_box(p)) for p in parts]
    out, _ = gmsh.model.occ.fuse(tags[:1], tags[1:])
    volumes = [t for t in out if t[0] == 3]
    if len(volumes) != 1:
        raise InputError(f"sofa: parts fused into {len(volumes)} solids, expected 1")


def sofa(width: float = 2.0, h: float = 0.1, dims: SofaDimensions | None = None,
         *, cache: bool = True) -> TetMesh:
    """Tet mesh of a sofa: seat, backrest and two arms fused into one solid on z = 0.

    This is the elastic body of the draft paper's demo (a rigid ball dropped onto a sofa).
    Default proportions: 2 m wide, 0.9 m deep, seat 0.45 m, arms 0.65 m, back 0.85 m high.

    Args:
        width: Overall width along x (m).
        h: Characteristic tet edge length (m).
        dims: The other proportions (:class:`SofaDimensions`).
        cache: Read/write the mesh cache.

    Returns:
        A validated, connected :class:`TetMesh` whose volume is the volume of the union of
        :func:`sofa_parts` (flat faces, so exact to round-off).

    """
    d = SofaDimensions() if dims is None else dims
    parts = sofa_parts(width, d)
    hv = _check_h("sofa", h, sum(p.volume for p in parts))
    params = {"width": float(width), "h": hv, **asdict(d)}
    return _generate("sofa", params, hv, lambda: _fuse(parts), cache)
