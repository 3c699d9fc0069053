"""Products over 3 x 3 vertex blocks: ``P^T A P`` (PETSc's MatPtAP chain) and ``Z^T A Z``."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
import shellcases

from meshes.errors import InputError
from meshes.shells import grid_plate
from solvers.block_galerkin import BlockGalerkin, GalerkinChain, block_pattern
from solvers.block_phase import BlockPhaseProduct, TransposeBlockProduct
from solvers.multigrid import ShellHierarchy, galerkin_levels, shift_images, vector_prolongation
from solvers.phase_space import PhaseSpace, hat_matrix, petsc_aij, scipy_csr


def random_block_matrix(n: int, seed: int) -> sp.csr_matrix:
    """A symmetric matrix of full 3 x 3 blocks on a random vertex pattern (diagonal included)."""
    rng = np.random.default_rng(seed)
    pattern = sp.random(n, n, density=0.2, random_state=seed) + sp.identity(n)
    blocks = sp.kron(pattern, np.ones((3, 3)), format="csr")
    blocks.data = rng.standard_normal(blocks.nnz)
    sym = sp.csr_matrix(blocks + blocks.T)
    sym.sort_indices()
    return sym


@pytest.mark.parametrize("threads", [1, 2, 3])
def test_block_product_equals_the_scalar_triple_product(threads: int) -> None:
    """C = (S (x) I_3)^T A (S (x) I_3) to round-off; every thread count gives the same bits."""
    a = random_block_matrix(30, seed=1)
    s = sp.random(30, 12, density=0.15, random_state=2, format="csr")
    s.data[:] = np.random.default_rng(5).uniform(0.2, 1.0, s.nnz)
    p = vector_prolongation(s)
    expected = (p.T @ a @ p).toarray()
    results = {}
    for t in sorted({1, threads}):
        product = BlockGalerkin(a, s, threads=t)
        for _ in range(2):  # the second product writes over the first
            product.update(a.data)
        results[t] = product.csr.toarray()
        assert np.array_equal(scipy_csr(product.mat).toarray(), results[t])  # PETSc's view
    err = np.max(np.abs(results[threads] - expected)) / np.max(np.abs(expected))
    print(f"threads {threads}: max |C - P^T A P| / max |P^T A P| = {err:.1e}")
    assert err < 1e-14
    assert np.array_equal(results[threads], results[1])


def test_chain_equals_petsc_ptap_on_a_shell_hessian() -> None:
    """The level matrices of a 3-level plate's Newton matrix, against MatPtAP from the finest."""
    hier = ShellHierarchy.build(*grid_plate(6, 6), levels=3)
    energy, x0 = shellcases.compressed_plate(hier.vertices, hier.faces, 32)
    hess = sp.csr_matrix(energy.evaluate(x0).hess)
    hess.sort_indices()
    prolongations = hier.prolongations()
    chain = GalerkinChain(hess, tuple(p[::3, ::3] for p in prolongations), threads=2)
    mine = chain.update(hess.data)
    reference = galerkin_levels(petsc_aij(hess, block=3),
                                [petsc_aij(p, block=3) for p in prolongations], [])[:-1]
    assert len(mine) == len(reference) == 3
    for level, (m, r) in enumerate(zip(mine, reference, strict=True)):
        ref = scipy_csr(r)
        err = abs(scipy_csr(m) - ref).max() / abs(ref).max()
        print(f"level {level}: {m.getSize()[0]} dofs, max relative difference {err:.1e}")
        assert m.getSize() == r.getSize() and err < 1e-13


def test_a_matrix_without_full_blocks_is_refused() -> None:
    a = random_block_matrix(6, seed=3).tolil()
    a[0, 1] = 0.0  # the diagonal block loses an entry of its first row
    a = sp.csr_matrix(a)
    a.eliminate_zeros()
    with pytest.raises(InputError, match="full, column-sorted 3 x 3 blocks"):
        block_pattern(a)
    with pytest.raises(InputError, match="S has 4 fine vertices"):
        BlockGalerkin(random_block_matrix(6, seed=3), sp.identity(4, format="csr"))


@pytest.mark.parametrize("threads", [1, 2])
def test_phase_space_product_equals_scipy(threads: int) -> None:
    """``Z^T A Z`` of the wrinkle-phase space (full blocks per vertex and hat) against scipy."""
    hier = ShellHierarchy.build(*grid_plate(4, 4), levels=2)
    energy, x0 = shellcases.compressed_plate(hier.vertices, hier.faces, clusters=8)
    hess = sp.csr_matrix(energy.evaluate(x0).hess)
    hess.sort_indices()
    vertex = tuple(p[::3, ::3].tocsr() for p in hier.prolongations())
    phase = PhaseSpace(hier.vertices, hier.faces, hat_matrix(vertex, 0))
    phase.set_fields(x0 + 1e-2 * np.random.default_rng(4).standard_normal(x0.shape),
                     energy.target.reshape(-1, 3))
    z = scipy_csr(phase.z)
    product = BlockPhaseProduct(hess, z, threads=threads)
    expected = (z.T @ hess @ z).toarray()
    for _ in range(2):  # the intermediate A Z is rewritten by the second product
        mine = product.product(hess.data, z.data).toarray()
    err = np.max(np.abs(mine - expected)) / np.max(np.abs(expected))
    print(f"Z {z.shape}, {z.nnz} entries; max |C - Z^T A Z| / max |Z^T A Z| = {err:.1e}")
    assert err < 1e-14
    assert np.array_equal(mine, BlockPhaseProduct(hess, z).product(hess.data, z.data).toarray())


def random_blocks(rows: int, cols: int, seed: int) -> sp.csr_matrix:
    """A rectangular matrix of full 3 x 3 blocks on a random vertex pattern."""
    rng = np.random.default_rng(seed)
    pattern = sp.random(rows, cols, density=0.3, random_state=seed)
    blocks = sp.kron(pattern, np.ones((3, 3)), format="csr")
    blocks.data = rng.standard_normal(blocks.nnz)
    blocks.sort_indices()
    return blocks


@pytest.mark.parametrize("threads", [1, 2])
def test_transpose_product_of_rectangular_blocks_equals_scipy(threads: int) -> None:
    """``Z^T B`` of two block matrices on the same rows (a rank's own rows of Z and A Z)."""
    z, b = random_blocks(25, 8, seed=6), random_blocks(25, 11, seed=7)
    product = TransposeBlockProduct(z, b, threads=threads)
    mine = product.product(z.data, b.data).toarray()
    expected = (z.T @ b).toarray()
    assert mine.shape == (24, 33)
    assert np.max(np.abs(mine - expected)) <= 1e-14 * np.max(np.abs(expected))
    with pytest.raises(InputError, match="do not make Z\\^T B"):
        TransposeBlockProduct(z, random_blocks(20, 11, seed=7))


def test_a_shifted_chain_equals_the_chain_of_the_shifted_matrix() -> None:
    """Levels of ``A + tau I`` plus ``step M_l`` are those of ``A + (tau + step) I``.

    ``M_l`` is the identity's Galerkin image (:func:`solvers.multigrid.shift_images`); a
    retry of the same matrix with another shift moves the levels' shift this way.
    """
    hier = ShellHierarchy.build(*grid_plate(6, 6), levels=3)
    energy, x0 = shellcases.compressed_plate(hier.vertices, hier.faces, 32)
    hess = sp.csr_matrix(energy.evaluate(x0).hess)
    hess.sort_indices()
    prolongations = hier.prolongations()
    diagonal = np.flatnonzero(np.repeat(np.arange(hess.shape[0]), np.diff(hess.indptr))
                              == hess.indices)
    vertex = [p[::3, ::3] for p in prolongations]
    chain = GalerkinChain(hess, tuple(vertex))
    chain.set_shift_images(shift_images(vertex)[::-1])

    def shifted(tau: float) -> np.ndarray:
        values = hess.data.copy()
        values[diagonal] += tau
        return values

    chain.update(shifted(0.5))
    moved = [scipy_csr(m) for m in chain.shift(2.5)]
    exact = [scipy_csr(m) for m in chain.update(shifted(3.0))]
    for level, (m, e) in enumerate(zip(moved, exact, strict=True)):
        err = abs(m - e).max() / abs(e).max()
        print(f"level {level}: max |shifted - recomputed| / max |recomputed| = {err:.1e}")
        assert err < 1e-14
    outside = [sp.csr_matrix(np.ones((m.shape[0] // 3,) * 2)) for m in exact][::-1]
    with pytest.raises(InputError, match="outside the level's block pattern"):
        chain.set_shift_images(outside)
