"""Restart files: the body state after the last completed frame (``checkpoint.h5``).

The state is the displacement, velocity and acceleration at every dof node (P1 vertices or
P2 vertices and edge midpoints) and the time. It is stored keyed by the *reference
coordinates* of the nodes, not by dof numbers, so a run can be restarted on another number of
MPI ranks (dolfinx numbers dofs per partition): on restart every rank looks its own nodes up
in the stored coordinates (k-d tree) and copies their values. Rank 0 gathers and writes the
file atomically (temporary file + ``os.replace``) after every frame, so a killed run restarts
from its last completed frame.

Other stages (the embedded shell, rigid bodies) keep their state in the same file as named
arrays: ``BodyState.arrays[stage][name]`` (serial numpy arrays, gathered by the stage on rank
0), stored under ``stages/<stage>/<name>``; :func:`with_arrays` adds a stage's arrays before
the file is written. Layout: attributes ``frame``, ``time``, ``format``; datasets
``coords``, ``fields/<name>``, ``stages/<stage>/<name>``.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import h5py
import numpy as np
from scipy.spatial import cKDTree

from meshes.errors import InputError
from models.backend import MPI
from solvers.body import Body

CHECKPOINT_NAME = "checkpoint.h5"
FORMAT = 2
"""Checkpoint layout version (1: no ``stages`` group; still read)."""
MATCH_TOL = 1e-9
"""Largest node distance accepted when matching stored nodes, relative to the mesh size."""


@dataclass(frozen=True)
class BodyState:
    """The body's state at the end of a frame, on all dof nodes, in any node order.

    Attributes:
        frame: last completed frame (0 = the initial state).
        time: physical time of the state [s].
        coords: (n, 3) reference coordinates of the dof nodes [m].
        fields: name -> (n, 3) nodal values (``displacement``, ``velocity``, ``acceleration``).
        arrays: stage name -> array name -> array: the state of the other stages (e.g.
            ``{"shell": {"positions": x}}``), restored verbatim.

    """

    frame: int
    time: float
    coords: np.ndarray
    fields: dict[str, np.ndarray] = field(default_factory=dict)
    arrays: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)


def with_arrays(state: BodyState, stage: str, arrays: dict[str, np.ndarray]) -> BodyState:
    """Return ``state`` with the named arrays of ``stage`` added (replacing earlier ones).

    Raises:
        InputError: an empty or ``/``-containing stage or array name.

    """
    for name in (stage, *arrays):
        if not name or "/" in name:
            raise InputError(f"checkpoint: invalid stage or array name {name!r}")
    copied = {name: np.array(values, copy=True) for name, values in arrays.items()}
    return replace(state, arrays={**state.arrays, stage: copied})


def state_functions(body: Body) -> dict[str, Any]:
    """Return the body's state functions by checkpoint name (``load_rate``: statics' guess)."""
    return {"displacement": body.u, "velocity": body.v, "acceleration": body.a,
            "load_rate": body.rate}


def _owned_nodes(body: Body) -> tuple[np.ndarray, int]:
    """Return the reference coordinates of the local dof nodes and the number owned."""
    owned = body.V.dofmap.index_map.size_local
    return body.V.tabulate_dof_coordinates(), owned


def gather_state(body: Body, frame: int) -> BodyState | None:
    """Collect the state of the owned nodes of every rank on rank 0 (collective).

    Returns:
        The state on rank 0, ``None`` on the other ranks.

    """
    coords, owned = _owned_nodes(body)
    local = {name: f.x.array.reshape(-1, 3)[:owned].copy()
             for name, f in state_functions(body).items()}
    parts = body.mesh.comm.gather((coords[:owned].copy(), local), root=0)
    if parts is None:
        return None
    fields = {name: np.concatenate([p[1][name] for p in parts]) for name in local}
    return BodyState(frame, body.t, np.concatenate([p[0] for p in parts]), fields)


def write_state(path: Path, state: BodyState) -> None:
    """Write ``state`` to ``path`` atomically (rank 0 only): temporary file, fsync, rename."""
    tmp = path.with_name(f".{path.name}.tmp")
    with h5py.File(tmp, "w") as h5:
        h5.attrs["frame"], h5.attrs["time"], h5.attrs["format"] = state.frame, state.time, FORMAT
        h5["coords"] = state.coords
        for name, values in state.fields.items():
            h5[f"fields/{name}"] = values
        for stage, arrays in state.arrays.items():
            for name, values in arrays.items():
                h5[f"stages/{stage}/{name}"] = values
    with open(tmp, "rb+") as handle:
        os.fsync(handle.fileno())
    os.replace(tmp, path)


def _stage_arrays(h5: h5py.File) -> dict[str, dict[str, np.ndarray]]:
    """Read the ``stages`` group (absent in format 1) as nested dicts."""
    group = h5.get("stages", {})
    return {stage: {name: group[stage][name][...] for name in group[stage]} for stage in group}


def read_state(path: Path) -> BodyState:
    """Read a checkpoint; ``InputError`` naming the file if it is missing or unreadable."""
    if not path.is_file():
        raise InputError(f"{path}: no checkpoint to restart from")
    try:
        with h5py.File(path, "r") as h5:
            fields = {name: h5["fields"][name][...] for name in h5["fields"]}
            return BodyState(int(h5.attrs["frame"]), float(h5.attrs["time"]),
                             h5["coords"][...], fields, _stage_arrays(h5))
    except (OSError, KeyError) as exc:
        raise InputError(f"{path}: unreadable checkpoint ({exc})") from None


def scatter_state(body: Body, state: BodyState) -> None:
    """Set the body's state from a checkpoint, matching nodes by coordinates (collective).

    Raises:
        InputError: a node of the mesh is not in the checkpoint (another mesh or degree).

    """
    coords, _ = _owned_nodes(body)
    distance, index = cKDTree(state.coords).query(coords)
    scale = float(np.ptp(state.coords, axis=0).max()) or 1.0
    worst = float(body.mesh.comm.allreduce(distance.max(initial=0.0), op=MPI.MAX))
    if worst > MATCH_TOL * scale or len(state.coords) != body.V.dofmap.index_map.size_global:
        raise InputError(f"{CHECKPOINT_NAME}: the checkpoint does not match the scene's mesh "
                         f"({len(state.coords)} stored nodes, node distance {worst:.3e} m)")
    values = {name: state.fields[name][index].reshape(-1) for name in state_functions(body)
              if name in state.fields}  # no load_rate in checkpoints of earlier versions
    body.set_state(state.time, values["displacement"], values["velocity"],
                   values["acceleration"], values.get("load_rate"))
