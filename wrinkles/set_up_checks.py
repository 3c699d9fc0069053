"""Set-up checks of a scene against its mesh: pins, obstacles, rigid balls.

What the run's set-up (:func:`wrinkles.runner.prepare`) refuses or warns about before the
first step, on the body's nodes and collective over its ranks; ``wrinkles check`` runs the
same checks on the mesh's vertices without building the body (:func:`check_mesh_set_up`).
Refusals are :class:`meshes.errors.InputError` naming the key (``body.pins[i]``,
``body.contacts[i]``, ``rigid.balls[i]``); warnings are :class:`meshes.MeshWarning`.
"""

from __future__ import annotations

import warnings
from typing import Any

import numpy as np

import meshes
from meshes.errors import InputError
from meshes.tetmesh import TetMesh, max_edge_lengths
from models.backend import MPI
from models.body import (
    PinSpec,
    free_rigid_motions,
    held_components,
    pin_conflicts,
    refuse_empty_pins,
    refuse_pin_conflicts,
    rigid_motion_gram,
)
from models.embedding.embedding import AffineMaps, affine_maps_of, min_barycentric
from wrinkles.scene import Scene


def check_mesh_set_up(scene: Scene, tet: TetMesh) -> dict[str, Any]:
    """Run the set-up checks of :func:`prepare` that need only the mesh, on its vertices.

    For ``wrinkles check``: pins that hold no node or move a shared node differently, a body
    starting inside an obstacle or around a ball's centre are refused as the run refuses
    them; the pins' and obstacles' warnings are issued. Serial, on the whole mesh; a P2
    body's edge midpoints are not among the vertices (the run counts them too).

    Returns:
        ``{"pin_nodes": [...]}``: the mesh vertices each pin holds.

    Raises:
        InputError: as :func:`prepare` would.

    """
    X = np.asarray(tet.points)
    pins = scene.body.pins
    counts = [int(np.count_nonzero(pin.select(X))) for pin in pins]
    refuse_empty_pins(pins, counts, (X.min(axis=0), X.max(axis=0)))
    refuse_pin_conflicts([(c.first, c.second, c.component, X[c.nodes])
                          for c in pin_conflicts(pins, X)], float(np.abs(X).max(initial=0.0)))
    warn_pins(scene, counts, X, MPI.COMM_SELF)
    h_mean = float(max_edge_lengths(tet.points, tet.tets).mean())  # dolfinx's Mesh.h of a tet
    check_obstacles_clear(X, h_mean, scene, MPI.COMM_SELF)
    check_balls_outside(affine_maps_of(X[tet.tets]), np.arange(tet.n_tets), scene,
                        MPI.COMM_SELF)
    return {"pin_nodes": counts}


def warn_pins(scene: Scene, counts: list[int], nodes: np.ndarray, comm: Any,
              warn: bool = True) -> None:
    """Warn about a static scene's missing pins or free rigid motions, and tiny pins (collective).

    A static scene without pins, pins that leave rigid motions free, a pin holding fewer
    than 3 nodes. The free rigid motions are :func:`models.body.free_rigid_motions` over
    every rank's nodes, the rotations about the held nodes' centroid.

    Args:
        scene: The scene.
        counts: Nodes each of ``scene.body.pins`` holds.
        nodes: Reference positions of the rank's own nodes, (n, 3) [m].
        comm: The body's communicator.
        warn: Issue the warnings (one rank of several).

    """
    pins, static = scene.body.pins, scene.body.dynamics == "static"
    free = _free_motions_over_ranks(pins, np.asarray(nodes, dtype=float), comm) if static and pins \
        else (0, [])
    if not warn:
        return
    if static and not pins:
        warnings.warn("body.pins: a static scene without pins has no unique solution (the "
                      "body's rigid motions are free; frictionless contacts do not hold it): "
                      "add [[body.pins]] or use body.dynamics = \"implicit_euler\"",
                      meshes.MeshWarning, stacklevel=3)
    if free[0]:
        names = ", ".join(free[1]) or "combinations of translations and rotations"
        warnings.warn(f"body.pins: the pins of this static scene leave {free[0]} rigid "
                      f"motion(s) of the body free ({names}): its equilibrium is not unique "
                      "and its Newton systems are singular; hold more components (e.g. "
                      "components = [0, 1, 2] on one pin) or use body.dynamics = "
                      "\"implicit_euler\"", meshes.MeshWarning, stacklevel=3)
    for index, (pin, count) in enumerate(zip(pins, counts, strict=True)):
        if count < 3:
            warnings.warn(f"body.pins[{index}]: holds only {count} node(s) of the mesh (a "
                          f"{pin.kind} pin with tol = {pin.tol:g}); widen tol or the region",
                          meshes.MeshWarning, stacklevel=3)


def _free_motions_over_ranks(pins: tuple[PinSpec, ...], nodes: np.ndarray,
                        comm: Any) -> tuple[int, list[str]]:
    """:func:`models.body.free_rigid_motions` of the pins over every rank's ``nodes``."""
    held = held_components(pins, nodes)
    points = nodes[held.any(axis=1)]
    total = comm.allreduce(np.append(points.sum(axis=0), points.shape[0]), op=MPI.SUM)
    center = total[:3] / max(total[3], 1.0)
    reach = float(np.linalg.norm(points - center, axis=1).max(initial=0.0))
    length = comm.allreduce(reach, op=MPI.MAX) or 1.0
    return free_rigid_motions(comm.allreduce(rigid_motion_gram(held, nodes, center, length),
                                             op=MPI.SUM))


def check_obstacles_clear(points: np.ndarray, h_mean: float, scene: Scene, comm: Any,
                          warn: bool = True) -> None:
    """Refuse an obstacle the body starts deeper inside than a mean cell; warn for less.

    The obstacles of ``body.contacts`` and the rigid balls' spheres; the depth of the body's
    nodes inside each at t = 0 (:meth:`models.contact.ContactOptions.start_depth`, round-off
    ignored): a body starting inside an obstacle is shoved out by the penalty in the first
    step. Collective over ``comm`` (``points``: this rank's nodes); ``warn`` on one rank.

    Args:
        points: (n, 3) reference positions of this rank's nodes [m].
        h_mean: Mean cell diameter of the whole mesh [m].
        scene: The scene (its contacts and balls).
        comm: Communicator of the ranks holding the nodes.
        warn: Issue the warning for a shallow start (one rank).

    Raises:
        InputError: naming ``body.contacts[i]`` or ``rigid.balls[i]``, the depth and the mean
            cell size.

    """
    balls = scene.rigid.balls if scene.rigid is not None else ()
    obstacles = [(f"body.contacts[{i}]", c) for i, c in enumerate(scene.body.contacts)]
    obstacles += [(f"rigid.balls[{i}]", ball.contact()) for i, ball in enumerate(balls)]
    for name, contact in obstacles:
        depth, count = contact.start_depth(points)
        depth = comm.allreduce(depth, op=MPI.MAX)
        count = comm.allreduce(count, op=MPI.SUM)
        where = f"{name} ({contact.describe()})"
        if depth > h_mean:
            raise InputError(f"{where}: the body starts up to {depth:.4g} m inside it ({count} "
                             f"node(s)), more than a mean cell ({h_mean:.3g} m): move the "
                             "obstacle or the mesh (or turn the normal to the body's side)")
        if depth > 0.0 and warn:
            warnings.warn(f"{where}: {count} node(s) of the body start inside it, up to "
                          f"{depth:.3g} m deep: the penalty pushes them out in the first step",
                          meshes.MeshWarning, stacklevel=2)


def check_balls_outside(maps: AffineMaps, owned: np.ndarray, scene: Scene, comm: Any) -> None:
    """Refuse a rigid ball whose centre starts inside the body (collective over ``comm``).

    A centre is inside when it lies in one of the ``owned`` cells of ``maps``: its smallest
    barycentric coordinate in the cell's affine map is >= 0
    (:func:`models.embedding.embedding.affine_maps`).

    Raises:
        InputError: naming ``rigid.balls[i].center``.

    """
    balls = scene.rigid.balls if scene.rigid is not None else ()
    for index, ball in enumerate(balls):
        center = np.broadcast_to(np.asarray(ball.center, dtype=float), (owned.size, 3))
        inside = bool(np.any(min_barycentric(maps.pull_back(owned, center)) >= -1e-12))
        if comm.allreduce(inside, op=MPI.LOR):
            raise InputError(f"rigid.balls[{index}].center = {list(ball.center)}: inside the "
                             f"body (a ball must start outside it)")
