"""The generic sparse assembly: fixed pattern reuse, dense reference, extra (penalty) pattern."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from meshes.errors import InputError
from meshes.shells import perturb
from models.shell.assembly import StencilPattern, assemble, sorted_unique
from models.shell.dofs import stencil_dofs
from models.shell.energy import ShellEnergy, ShellParams
from validation.taylor import random_shell


def _dense_reference(n: int, stencils: list[np.ndarray], blocks: list[np.ndarray],
                     scales: list[float], extra: np.ndarray) -> np.ndarray:
    """Assemble with an explicit Python loop over stencils into a dense matrix."""
    out = np.kron(extra, np.eye(3))
    for st, bl, sc in zip(stencils, blocks, scales, strict=True):
        dofs = stencil_dofs(st)
        for t in range(st.shape[0]):
            out[np.ix_(dofs[t], dofs[t])] += sc * bl[t]
    return out


@pytest.mark.parametrize("kind", ["plate", "sphere"])
def test_assembly_matches_dense_reference(kind: str, rng: np.random.Generator) -> None:
    p, top, _ = random_shell(kind)
    n = top.n_vertices
    stencils = [top.edges, top.faces, top.hinges]
    blocks = [rng.standard_normal((s.shape[0], 3 * s.shape[1], 3 * s.shape[1]))
              for s in stencils]
    scales = [1.0, 0.5, 2.0]
    extra = sp.random(n, n, density=0.1, random_state=4, format="csr")
    extra = extra + extra.T
    pattern = StencilPattern.from_stencils(stencils, n, extra=[extra])
    mat = assemble(pattern, [(m, b, s) for m, b, s in zip(pattern.maps, blocks, scales,
                                                          strict=True)],
                   base=pattern.extra_data(0, extra, 3.0))
    ref = _dense_reference(n, stencils, blocks, scales, 3.0 * extra.toarray())
    err = np.abs(mat.toarray() - ref).max()
    print(f"{kind}: max |assembled - dense| = {err:.2e}, blocks {pattern.n_blocks}")
    assert err <= 1e-13 * np.abs(ref).max()
    assert mat.has_canonical_format and pattern.nnz == 9 * pattern.n_blocks
    # the expanded per-entry maps scatter the same matrix (np.add.at handles repeats)
    data = pattern.extra_data(0, extra, 3.0)
    for k, (b, sc) in enumerate(zip(blocks, scales, strict=True)):
        np.add.at(data, pattern.entry_map(k), sc * b)
    np.testing.assert_allclose(data, mat.data, rtol=1e-13, atol=1e-13 * np.abs(ref).max())


def test_pattern_reuse_same_objects() -> None:
    p, top, rest = random_shell("sphere")
    energy = ShellEnergy(top, rest, ShellParams(k_A=1.0, k_P=0.0))
    a = energy.evaluate(perturb(p, 0.01, 1)).hess
    b = energy.evaluate(perturb(p, 0.02, 2), hessian="projected").hess
    assert a.indptr is b.indptr and a.indices is b.indices
    assert a.indptr is energy.pattern.indptr and a.indices is energy.pattern.indices
    assert a.data is not b.data and not np.array_equal(a.data, b.data)
    assert a.indptr.dtype == np.int32


def test_block_shape_is_checked(rng: np.random.Generator) -> None:
    _, top, _ = random_shell("plate")
    pattern = StencilPattern.from_stencils([top.edges], top.n_vertices)
    with pytest.raises(InputError, match="blocks"):
        assemble(pattern, [(pattern.maps[0], rng.standard_normal((top.n_edges, 9, 9)))])
    with pytest.raises(InputError, match="stencils"):
        StencilPattern.from_stencils([top.edges + top.n_vertices], top.n_vertices)


def test_sorted_unique_equals_np_unique() -> None:
    """The pattern's key de-duplication gives np.unique's result (random, repeated, empty)."""
    rng = np.random.default_rng(3)
    for keys in (rng.integers(0, 50, 1000), rng.integers(0, 10**12, 5000),
                 np.zeros(7, dtype=np.int64), np.zeros(0, dtype=np.int64)):
        np.testing.assert_array_equal(sorted_unique(keys), np.unique(keys))
