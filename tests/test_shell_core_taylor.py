"""Taylor tests (fitted remainder slopes) of the membrane terms W_L, W_A and the penalty W_P.

Also holds the small helpers (Taylor remainders, random meshes, dense Hessians) that the other
``test_shell_core_*`` files import.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest
import scipy.sparse as sp

from meshes.shells import icosphere, irregular_plate, perturb
from models.shell.assembly import StencilPattern, TermEval, assemble
from models.shell.membrane import area_membrane, edge_membrane
from models.shell.penalty import PenaltyOperator, penalty_gram, penalty_term
from models.shell.rest import RestState
from models.shell.topology import ShellTopology

EPS = np.logspace(-2, -5, 7)

# (value, grad, hess-times-vector) at a point, as flat-vector functions
Oracle = Callable[[np.ndarray], tuple[float, np.ndarray, sp.csr_matrix]]


def remainders(f: Oracle, x: np.ndarray, d: np.ndarray,
               eps: np.ndarray = EPS) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Taylor remainders r1 = |W(x+ed) - W - e g.d|, r2 = |g(x+ed) - g - e H d|, r3 (order 3)."""
    w0, g0, h0 = f(x)
    hd = h0 @ d
    r1, r2, r3 = [], [], []
    for e in eps:
        w, g, _ = f(x + e * d)
        r1.append(abs(w - w0 - e * g0 @ d))
        r2.append(np.linalg.norm(g - g0 - e * hd))
        r3.append(abs(w - w0 - e * g0 @ d - 0.5 * e * e * d @ hd))
    return np.array(r1), np.array(r2), np.array(r3)


def slope(eps: np.ndarray, r: np.ndarray) -> float:
    """Fitted log-log slope of remainder r against eps (np.polyfit)."""
    return float(np.polyfit(np.log(eps), np.log(r), 1)[0])


def term_oracle(term: Callable[..., TermEval], stencils: np.ndarray, n: int,
                **kw: object) -> Oracle:
    """Flat-vector oracle of a stencil term, its blocks assembled by the generic assembler."""
    pattern = StencilPattern.from_stencils([stencils], n)

    def f(v: np.ndarray) -> tuple[float, np.ndarray, sp.csr_matrix]:
        ev = term(v.reshape(-1, 3), stencils, order=2, **kw)
        return ev.value, ev.grad, assemble(pattern, [(pattern.maps[0], ev.blocks)])

    return f


def random_shell(kind: str, seed: int = 1) -> tuple[np.ndarray, ShellTopology, RestState]:
    """Small rest shells: 'plate' (irregular), 'sphere', 'thin' (plate with slivers)."""
    if kind == "sphere":
        p, f = icosphere(2)
    elif kind == "plate":
        p, f = irregular_plate(49, seed)
    elif kind == "thin":
        p, f = irregular_plate(49, seed)
        p = p * np.array([1.0, 2e-3, 1.0])  # squashed: height / longest edge down to ~1e-3
    else:
        raise ValueError(kind)
    top = ShellTopology.from_faces(f, len(p))
    return p, top, RestState.from_positions(top, p)


def dense_sym_eigs(h: sp.csr_matrix) -> np.ndarray:
    """Eigenvalues of a small sparse symmetric matrix (dense)."""
    return np.linalg.eigvalsh(h.toarray())


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
