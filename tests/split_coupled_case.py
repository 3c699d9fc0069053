"""Run under ``mpiexec -n N``: the split joint system of a two-way bar against the serial one.

The stretched bar of tests/support.py, two-way coupled, 3 subdivision levels (5 762 shell
vertices, multigrid-CG): one frame through ``prepare``/``run_frames`` (the product's path,
which splits the joint system from :data:`solvers.solver_choice.SPLIT_JOINT_FROM_VERTICES`),
then at a state off the minimum the split energy and CG against the serial
:class:`solvers.monolithic.CoupledEnergy` and :class:`solvers.joint_krylov.JointKrylovSystem`
built on every rank. Prints one ``RESULT {json}`` line on rank 0.
"""

from __future__ import annotations

import dataclasses
import json
import sys
import tempfile
from pathlib import Path

import numpy as np
from support import LENGTH, SKIN, bar_scene

from models.backend import MPI
from solvers.decomposition.split_coupled import SplitCoupledEnergy, SplitJointKrylov
from solvers.joint_krylov import JointKrylovSystem
from solvers.multigrid import MultigridLinearSystem
from wrinkles.runner import prepare, run_frames
from wrinkles.scene import scene_from_dict
from wrinkles.two_way import CoupledStep

TAU = 1.0
"""Shift of the compared systems (the state is near the stretched bar's unique minimum)."""


def main() -> None:
    comm = MPI.COMM_WORLD
    shell = {"subdivision": {"levels": 3}, "skin": SKIN, "energy": {"k_P": 1.0e3},
             "solver": {"rtol": 1e-10, "max_iterations": 300, "method": "multigrid"},
             "imperfection": 0.0, "coupling": {"mode": "two_way"}}
    scene = scene_from_dict(bar_scene((0.04 * LENGTH, 0.0, 0.0), 1, shell), Path.cwd())
    out = Path(comm.bcast(tempfile.mkdtemp() if comm.rank == 0 else None)) / "out"
    run = run_frames(prepare(scene, out, comm), lambda line: None)
    step = run.body._solve
    assert isinstance(step, CoupledStep) and run.shell is not None
    ((energy, solver),) = step.solvers.values()
    split, krylov = solver.energy, solver.krylov
    assert isinstance(split, SplitCoupledEnergy) and isinstance(krylov, SplitJointKrylov)
    # a state off the minimum: the shell moved by 1e-7 m, the same on every rank
    noise = comm.bcast(np.random.default_rng(1).standard_normal(run.shell.x.shape))
    z = np.vstack([run.shell.x + 1e-7 * noise, energy.body.get().reshape(-1, 3)])
    serial_ev, split_ev = energy.evaluate(z), split.evaluate(z)
    assert run.shell.hierarchy is not None
    mg = MultigridLinearSystem(run.shell.hierarchy.prolongations(),
                               dataclasses.replace(krylov.shell.options, phase_space=False))
    serial = JointKrylovSystem(mg, energy.shell.penalty_factor, energy.body_factor)
    ok = serial.factorize(serial_ev, TAU).success and krylov.factorize(split_ev, TAU).success
    v = comm.bcast(np.random.default_rng(2).standard_normal(serial_ev.grad.size))
    product = serial.apply(v)
    split_product = krylov._full(krylov.apply(krylov._local(v)))
    serial.eta = krylov.eta = 1e-8
    before = len(krylov.stats.iterations)
    dz, split_dz = serial.solve(-serial_ev.grad), krylov.solve(-split_ev.grad)
    result = {
        "ranks": comm.size,
        "joint_system": step.joint_system,
        "shared_multigrid": krylov.shell is run.shell.solver.linear,
        "vertices": energy.n,
        "factorized": bool(ok),
        "value_rel": abs(split_ev.value - serial_ev.value) / abs(serial_ev.value),
        "grad_rel": float(np.abs(split_ev.grad - serial_ev.grad).max()
                          / np.abs(serial_ev.grad).max()),
        "diagonal_rel": float(np.abs(split_ev.hess.diagonal() - serial_ev.hess.diagonal()).max()
                              / np.abs(serial_ev.hess.diagonal()).max()),
        "product_rel": float(np.abs(split_product - product).max() / np.abs(product).max()),
        "dot_rel": abs(krylov.dot(krylov._local(v), krylov._local(product)) - float(v @ product))
        / abs(float(v @ product)),
        "solve_rel": float(np.abs(split_dz - dz).max() / np.abs(dz).max()),
        "residual": serial.true_residual(split_dz, -serial_ev.grad),
        "cg_iterations": [serial.stats.iterations[-1], krylov.stats.iterations[before:][-1]],
        "rank_spread": float(np.abs(np.array(comm.allgather(split_dz))
                                    - split_dz[None]).max()),
    }
    if comm.rank == 0:
        print("RESULT " + json.dumps(result), flush=True)


if __name__ == "__main__":
    sys.exit(main())
