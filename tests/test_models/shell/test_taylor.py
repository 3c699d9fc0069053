"""Taylor tests (fitted remainder slopes) of the membrane terms W_L, W_A and the penalty W_P.

Also holds the small helpers (Taylor remainders, random meshes, dense Hessians) that the other
``test_shell_core_*`` files import.
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from meshes.shells import perturb
from models.shell.membrane import area_membrane, edge_membrane
from models.shell.penalty import PenaltyOperator, penalty_gram, penalty_term
from validation.taylor import (
    EPS,
    random_shell,
    remainders,
    slope,
    term_oracle,
)


def _direction(rng: np.random.Generator, x: np.ndarray, scale: float) -> np.ndarray:
    """Random flat direction with entries of size ``scale``."""
    return scale * rng.standard_normal(x.size)


CASES = ["plate", "sphere", "thin"]


@pytest.mark.parametrize("kind", CASES)
def test_edge_membrane_taylor(kind: str, rng: np.random.Generator) -> None:
    p, top, rest = random_shell(kind)
    scale = rest.rest_lengths.min()
    x = perturb(p, 0.2 * scale, 7).reshape(-1)
    f = term_oracle(edge_membrane, top.edges, top.n_vertices, rest_len=rest.rest_lengths)
    eps = EPS * scale
    r1, r2, r3 = remainders(f, x, _direction(rng, x, 1.0), eps)
    s1, s2, s3 = slope(eps, r1), slope(eps, r2), slope(eps[:4], r3[:4])
    print(f"edge {kind}: slopes value {s1:.3f} grad {s2:.3f} order-3 {s3:.3f}")
    assert 1.9 <= s1 <= 2.1 and 1.9 <= s2 <= 2.1 and 2.8 <= s3 <= 3.2


@pytest.mark.parametrize("kind", CASES)
def test_area_membrane_taylor(kind: str, rng: np.random.Generator) -> None:
    p, top, rest = random_shell(kind)
    scale = np.sqrt(rest.rest_areas.min())
    x = perturb(p, 0.2 * scale, 8).reshape(-1)
    f = term_oracle(area_membrane, top.faces, top.n_vertices, rest_area=rest.rest_areas)
    eps = EPS * scale
    r1, r2, r3 = remainders(f, x, _direction(rng, x, 1.0), eps)
    s1, s2, s3 = slope(eps, r1), slope(eps, r2), slope(eps[:4], r3[:4])
    print(f"area {kind}: slopes value {s1:.3f} grad {s2:.3f} order-3 {s3:.3f}")
    assert 1.9 <= s1 <= 2.1 and 1.9 <= s2 <= 2.1 and 2.8 <= s3 <= 3.2


def _penalty_setup(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, PenaltyOperator]:
    p, top, _ = random_shell("sphere")
    h = sp.random(12, top.n_vertices, density=0.2, random_state=3, format="csr")
    return p, perturb(p, 0.05, 9), PenaltyOperator.from_matrix(h, top.n_vertices)


def test_penalty_taylor_and_values(rng: np.random.Generator) -> None:
    p, y, op = _penalty_setup(rng)
    k_p = 7.0
    hess = 2.0 * k_p * sp.kron(penalty_gram(op), sp.identity(3), format="csr")

    def f(v: np.ndarray) -> tuple[float, np.ndarray, sp.csr_matrix]:
        ev = penalty_term(v.reshape(-1, 3), y, op, stiffness=k_p)
        return ev.value, ev.grad, hess

    x = perturb(p, 0.1, 10).reshape(-1)
    r1, r2, r3 = remainders(f, x, _direction(rng, x, 1.0))
    s1 = slope(EPS, r1)
    dense = op.H.toarray()
    res = dense @ (x.reshape(-1, 3) - y)
    ev = penalty_term(x.reshape(-1, 3), y, op, stiffness=k_p)
    print(f"penalty: slope {s1:.3f}, grad remainder max {r2.max():.2e}, r3 max {r3.max():.2e}")
    assert 1.9 <= s1 <= 2.1
    # W_P is quadratic: the Hessian remainders vanish to round-off
    assert r2.max() <= 1e-10 * np.linalg.norm(ev.grad) and r3.max() <= 1e-10 * ev.value
    assert ev.value == pytest.approx(k_p * np.sum(res**2), rel=1e-13)
    np.testing.assert_allclose(ev.grad, 2 * k_p * (dense.T @ res).ravel(), rtol=1e-12,
                               atol=1e-12 * np.abs(ev.grad).max())
