"""The body gives the same answer on 1 and 2 MPI ranks."""

from __future__ import annotations

import numpy as np
import pytest


@pytest.mark.mpi
def test_serial_and_two_ranks_agree(mpiexec, tmp_path):
    results = {}
    for n in (1, 2):
        out = tmp_path / f"body_{n}.npz"
        proc = mpiexec(["tests/body_mpi_case.py", str(out)], n=n, timeout=300, check=True)
        print(proc.stdout.strip())
        results[n] = np.load(out)
    for name in ("compression_p2", "drop_p1", "drop_p1_iterative", "cantilever_from_arrays"):
        one, two = results[1][f"{name}_table"], results[2][f"{name}_table"]
        assert one.shape == two.shape and one.shape[0] > 20
        assert np.allclose(one[:, :3], two[:, :3], atol=1e-12)  # same nodes, same order
        scale = np.abs(one[:, 3:]).max()
        du = np.abs(one[:, 3:] - two[:, 3:]).max() / scale
        e1, e2 = results[1][f"{name}_energies"], results[2][f"{name}_energies"]
        de = np.max(np.abs(e1 - e2)) / np.max(np.abs(e1))
        r1, r2 = results[1][f"{name}_reaction"], results[2][f"{name}_reaction"]
        print(f"{name}: max |u1 - u2| / max |u| = {du:.2e}, energies rel. diff = {de:.2e}, "
              f"reaction 1 rank {r1}, 2 ranks {r2}")
        assert scale > 1e-3
        assert du < 1e-8
        assert de < 1e-8
        assert np.allclose(r1, r2, rtol=1e-8, atol=1e-8 * max(1.0, np.abs(r1).max()))
    for n in (1, 2):  # CG + GAMG (the LU where CG fails) lands where the LU lands
        direct, iterative = (results[n][f"{k}_table"][:, 3:] for k in ("drop_p1",
                                                                       "drop_p1_iterative"))
        assert np.abs(direct - iterative).max() < 1e-8 * np.abs(direct).max()
