"""Finite-difference Taylor checks of energies, and random shells to run them on.

For a smooth ``W`` with gradient ``g`` and Hessian ``H``, along a direction ``d``:
``r1(e) = |W(x + e d) - W(x) - e g.d| = O(e^2)`` and ``r2(e) = |g(x + e d) - g(x) - e H d| =
O(e^2)``; the fitted slopes of ``log r`` against ``log e`` are the orders that
``tests/test_shell_core_taylor.py`` and ``paper/scripts/taylor.py`` report.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import scipy.sparse as sp

from meshes.shells import icosphere, irregular_plate
from models.shell.assembly import StencilPattern, TermEval, assemble
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
        assert ev.grad is not None and ev.blocks is not None  # order 2
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
