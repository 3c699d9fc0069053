"""Run a representative subset of the extremes matrix on every rank of COMM_WORLD.

Usage: ``mpiexec -n N python tests/extremes_mpi_case.py OUT.json [CASE ...]`` (used by
tests/test_wrinkles/test_extremes_mpi.py). The cases are the builders of ``extremes_cases``: the
body ones run distributed (dolfinx mesh on COMM_WORLD), the shell ones redundantly on every
rank (serial sparse solvers on COMM_SELF, as in ``wrinkles.shell_stage``). Rank 0 writes one
record per case: iterations, fallbacks, energies; a case that raises a SolverError records its
message instead (the forced divergence: every rank must raise it, none may hang).
"""

from __future__ import annotations

import json
import sys
import time
from collections.abc import Callable
from typing import Any

import extremes_cases as tm
import numpy as np

from meshes.errors import SolverError
from models.backend import MPI
from models.shell.energy import ShellParams
from solvers.body_newton import NewtonOptions
from solvers.shell_newton import ShellNewtonOptions, ShellNewtonSolver


def body_record(case: tm.BodyCase) -> dict[str, Any]:
    """Run a body case; iterations, fallbacks, energy, min det F (global) and reaction."""
    b, steps, before = case
    row = tm.run_body(b, steps, before)
    row["reaction_z"] = float(b.reaction_force()[2]) if b.contacts else 0.0
    return row


def shell_record(params: ShellParams) -> dict[str, Any]:
    """Solve the 15 %-compressed shell case with ``params`` on this rank."""
    energy, x0 = tm.shell_case(params)
    x, report = ShellNewtonSolver(energy, ShellNewtonOptions(rtol=1e-8, max_iterations=100)
                                  ).minimize(x0)
    comm = MPI.COMM_WORLD
    spread = comm.allreduce(float(np.abs(x - comm.bcast(x, root=0)).max()), op=MPI.MAX)
    return {"outcome": "converged" if report.converged else "failed",
            "iterations": report.iterations, "shifted": report.shifted_iterations,
            "backtracks": report.line_search_steps, "energy": report.energy,
            "grad_norm": report.grad_norm, "tolerance": report.tolerance,
            "energies": report.energies.tolist(), "rank_spread": spread}


def forced_divergence() -> dict[str, Any]:
    """50 % compression in one load step with step halving disabled: SNES cannot do it."""
    case = tm.compression_case(1, 1, NewtonOptions(max_it=tm.MAX_IT, max_halvings=0))
    try:
        body_record(case)
    except SolverError as exc:
        return {"outcome": "refused", "error": "SolverError", "message": str(exc)}
    return {"outcome": "converged"}


CASES: dict[str, Callable[[], dict[str, Any]]] = {
    "body nu=0.499": lambda: body_record(tm.nu_case(0.499)),
    "body 50% P1 in 1 step(s)": lambda: body_record(tm.compression_case(1, 1)),
    "body implicit_euler dt=1e-05": lambda: body_record(tm.time_step_case("implicit_euler",
                                                                          1e-5)),
    "body implicit_euler dt=0.1": lambda: body_record(tm.time_step_case("implicit_euler", 0.1)),
    "body sphere 10 m/s": lambda: body_record(tm.sphere_case()),
    "shell E ratio 1e+06": lambda: shell_record(tm.ratio_params(1e6)),
    "shell kP/kB=1e+10 kB=1e-08": lambda: shell_record(ShellParams(k_L=1e3, k_B=1e-8,
                                                                   k_P=1e2)),
    "body forced divergence": forced_divergence,
}


def main(out: str, names: list[str]) -> None:
    comm = MPI.COMM_WORLD
    results = {}
    for name in names or list(CASES):
        start = time.perf_counter()
        row = CASES[name]()
        row["seconds"] = time.perf_counter() - start
        results[name] = row
        if comm.rank == 0:
            print(f"{name}: {row['outcome']} its={row.get('iterations')} "
                  f"{row['seconds']:.1f}s", flush=True)
    if comm.rank == 0:
        with open(out, "w") as fh:
            json.dump({"ranks": comm.size, "cases": results}, fh, indent=1)


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2:])
