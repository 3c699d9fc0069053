"""SharedAIJ and BlockUpperCopy: PETSc matrices filled by a gather, against scipy (1, 2 ranks)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import scipy.sparse as sp

from meshes.errors import InputError
from models.backend import MPI, PETSc
from solvers.shared_aij import BlockUpperCopy, Gather, SharedAIJ

CASE = """
import json, sys
import numpy as np, scipy.sparse as sp
from models.backend import MPI
sys.path.insert(0, "tests/test_solvers")
from test_shared_aij import block_product_error, product_error, rectangular_error
comm = MPI.COMM_WORLD
err = comm.allreduce(max(product_error(comm, 40), block_product_error(comm, 14),
                         rectangular_error(comm, 40, 11)), op=MPI.MAX)
if comm.rank == 0:
    print("RESULT " + json.dumps({"error": err}))
"""


def _rows(n: int, seed: int) -> sp.csr_matrix:
    """A random n x n matrix with a full diagonal, columns shuffled within every row."""
    a = sp.random(n, n, density=0.2, random_state=seed, format="csr") + sp.eye(n)
    a = sp.csr_matrix(a)
    rng = np.random.default_rng(seed)
    for i in range(n):  # SharedAIJ takes a row's entries in any order
        lo, hi = a.indptr[i], a.indptr[i + 1]
        perm = lo + rng.permutation(hi - lo)
        a.indices[lo:hi], a.data[lo:hi] = a.indices[perm], a.data[perm]
    a.has_sorted_indices = False
    return a


def _split(n: int, comm) -> tuple[int, int]:  # noqa: ANN001
    """(local, start) of n rows split over the ranks in rank order."""
    local = n // comm.size + (comm.rank < n % comm.size)
    return local, int(comm.exscan(local) or 0) if comm.size > 1 else 0


def product_error(comm, n: int) -> float:  # noqa: ANN001
    """Max relative error of ``(A + 0.5 I) v`` on this rank's rows, after two value sets."""
    a = _rows(n, seed=3)
    local, start = _split(n, comm)
    lo, hi = a.indptr[start], a.indptr[start + local]
    indptr, cols, values = a.indptr[start:start + local + 1] - lo, a.indices[lo:hi], a.data[lo:hi]
    shared = SharedAIJ(comm, local, n, indptr, cols)
    shared.set_values(np.zeros_like(values), 1.0)  # first values, then new ones: state moves
    x, y = shared.mat.createVecs()
    v = np.arange(n, dtype=float) + 1.0
    x.setArray(v[start:start + local])
    shared.mat.mult(x, y)
    first = float(np.abs(y.getArray() - v[start:start + local]).max())
    shared.set_values(values, 0.5)
    shared.mat.mult(x, y)
    ref = ((a + 0.5 * sp.eye(n)) @ v)[start:start + local]
    return max(first, float(np.abs(y.getArray() - ref).max() / np.abs(ref).max()))


def rectangular_error(comm, n: int, m: int) -> float:  # noqa: ANN001
    """Max relative error of ``Z v`` and ``Z^T w`` for an n x m Z with split rows and columns."""
    z = sp.csr_matrix(sp.random(n, m, density=0.3, random_state=6))
    rows, start = _split(n, comm)
    cols, col_start = _split(m, comm)
    lo, hi = z.indptr[start], z.indptr[start + rows]
    shared = SharedAIJ(comm, rows, n, z.indptr[start:start + rows + 1] - lo, z.indices[lo:hi],
                       columns=(cols, m))
    shared.set_values(z.data[lo:hi])
    x, y = shared.mat.createVecs()
    v, w = np.cos(np.arange(m, dtype=float)), np.sin(np.arange(n, dtype=float))
    x.setArray(v[col_start:col_start + cols])
    shared.mat.mult(x, y)
    err = np.abs(y.getArray() - (z @ v)[start:start + rows]).max() / np.abs(z @ v).max()
    y.setArray(w[start:start + rows])
    shared.mat.multTranspose(y, x)
    ref = z.T @ w
    return max(float(err), float(np.abs(x.getArray() - ref[col_start:col_start + cols]).max()
                                 / np.abs(ref).max()))


def block_product_error(comm, vertices: int) -> float:  # noqa: ANN001
    """Max relative error of ``(A + 0.5 I) v`` with A symmetric of full 3 x 3 blocks.

    The rows go in as a :class:`BlockUpperCopy` (vertices split over the ranks).
    """
    pattern = sp.random(vertices, vertices, density=0.3, random_state=4) + sp.eye(vertices)
    half = sp.kron(pattern, np.random.default_rng(5).standard_normal((3, 3)))
    a = sp.csr_matrix(half + half.T)
    n = 3 * vertices
    mine = vertices // comm.size + (comm.rank < vertices % comm.size)
    start = 3 * (int(comm.exscan(mine) or 0) if comm.size > 1 else 0)
    local = 3 * mine
    lo, hi = a.indptr[start], a.indptr[start + local]
    copy = BlockUpperCopy(comm, local, n, a.indptr[start:start + local + 1] - lo,
                          a.indices[lo:hi])
    copy.set_values(a.data[lo:hi], 0.5)
    x, y = copy.mat.createVecs()
    v = np.sin(np.arange(n, dtype=float))
    x.setArray(v[start:start + local])
    copy.mat.mult(x, y)
    ref = ((a + 0.5 * sp.eye(n)) @ v)[start:start + local]
    return float(np.abs(y.getArray() - ref).max() / np.abs(ref).max())


def test_product_equals_scipy_on_one_rank() -> None:
    assert product_error(MPI.COMM_SELF, 30) < 1e-14
    assert rectangular_error(MPI.COMM_SELF, 30, 7) < 1e-14
    assert block_product_error(MPI.COMM_SELF, 10) < 1e-14


def test_block_copy_refuses_rows_without_full_blocks() -> None:
    rows = sp.csr_matrix(sp.eye(6))  # 3 x 3 diagonal blocks with off-diagonal holes
    with pytest.raises(InputError, match="full 3 x 3 blocks"):
        BlockUpperCopy(MPI.COMM_SELF, 6, 6, rows.indptr, rows.indices)


def test_product_equals_scipy_on_two_ranks(mpiexec) -> None:
    proc = mpiexec(["-c", CASE], n=2, timeout=120, check=True)
    line = next(s for s in proc.stdout.splitlines() if s.startswith("RESULT "))
    assert json.loads(line[len("RESULT "):])["error"] < 1e-14


def test_diagonal_positions_and_products_keep_their_pattern() -> None:
    a = _rows(12, seed=5)
    shared = SharedAIJ(MPI.COMM_SELF, 12, 12, a.indptr, a.indices)
    assert shared.diagonal.size == 12
    shared.set_values(a.data)
    p = PETSc.Mat().createAIJ((12, 4), comm=MPI.COMM_SELF)
    p.setPreallocationNNZ(1)
    for i in range(12):
        p.setValue(i, i // 3, 1.0)
    p.assemble()
    coarse = shared.mat.PtAP(p)
    shared.set_values(2.0 * a.data)  # in place: the reused product must see the new values
    shared.mat.PtAP(p, result=coarse)
    ref = sp.csr_matrix((np.ones(12), (np.arange(12), np.arange(12) // 3)), shape=(12, 4))
    expected = (ref.T @ (2.0 * a) @ ref).toarray()
    assert np.allclose(coarse.getValues(range(4), range(4)), expected, rtol=1e-14, atol=0)


def test_refuses_a_repeated_entry_and_wrong_value_counts() -> None:
    with pytest.raises(InputError, match="given twice"):
        SharedAIJ(MPI.COMM_SELF, 2, 2, np.array([0, 2, 3]), np.array([1, 1, 1]))
    shared = SharedAIJ(MPI.COMM_SELF, 2, 2, np.array([0, 2, 3]), np.array([1, 0, 1]))
    with pytest.raises(InputError, match="expected 3 values"):
        shared.set_values(np.ones(2))


@pytest.mark.parametrize("kind", ["rows", "triples", "shuffled", "empty"])
def test_gather_by_runs_equals_the_positions(kind: str) -> None:
    """``Gather`` gives ``values[take]``; runs of consecutive positions are kept as runs."""
    rng = np.random.default_rng(5)
    values = rng.standard_normal(1000)
    starts = np.sort(rng.choice(900, size=40, replace=False))
    take = {"rows": np.concatenate([np.arange(s, s + 20) for s in starts]) % 1000,
            "triples": np.concatenate([np.arange(s, s + 3) for s in starts]),
            "shuffled": rng.permutation(1000)[:300],
            "empty": np.zeros(0, dtype=np.int64)}[kind]
    gather = Gather(take)
    out = np.full(take.size, np.nan)
    gather(values, out)
    assert np.array_equal(out, values[take])
    assert np.array_equal(gather.expanded(), take)
    assert (gather.take is None) == (kind in ("rows", "triples"))
    if gather.take is None:
        assert gather.in_starts.size <= take.size // 2


def test_values_written_at_the_entry_positions_equal_set_values() -> None:
    """Writing entry k's value at ``entry_positions()[k]`` of the blocks is ``set_values``."""
    a = _rows(30, seed=8)
    values = np.random.default_rng(2).standard_normal(a.nnz)
    by_gather = SharedAIJ(MPI.COMM_SELF, 30, 30, a.indptr, a.indices)
    by_gather.set_values(values)
    direct = SharedAIJ(MPI.COMM_SELF, 30, 30, a.indptr, a.indices)
    blocks = np.concatenate(direct.block_values)
    blocks[direct.entry_positions()] = values
    diagonal, other = direct.block_values
    diagonal[:], other[:] = blocks[: diagonal.size], blocks[diagonal.size:]
    direct.values_changed()
    x, y = direct.mat.createVecs()
    x.setArray(np.arange(30.0))
    y_ref = y.duplicate()
    direct.mat.mult(x, y)
    by_gather.mat.mult(x, y_ref)
    assert np.array_equal(y.getArray(), y_ref.getArray())
    assert np.allclose(y.getArray(), sp.csr_matrix((values, a.indices, a.indptr)) @ np.arange(30.0))
