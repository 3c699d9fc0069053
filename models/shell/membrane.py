"""Membrane energies of the discrete shell: edge springs W_L and the optional area term W_A.

Edge term (Grinspun et al. 2003 "Discrete Shells"; Remillard & Kry 2013 eq. for W_L)::

    W_L = sum_e |e0| (1 - l_e / l0_e)^2 = sum_e (l_e - l0_e)^2 / l0_e,   l_e = |x_j - x_i|.

With ``u = (x_j - x_i) / l``: ``dW/dx_j = -dW/dx_i = 2 (l - l0) / l0 u`` and the 3x3 block

    K = 2 / l0 [u u^T + (l - l0) / l (I - u u^T)],   local 6x6 Hessian [[K, -K], [-K, K]].

The transverse part ``(l - l0)/l (I - u u^T)`` is negative for a compressed edge (l < l0):
this is the indefiniteness that lets a compressed sheet buckle. Its eigenvalues are
``4/l0`` (axial), ``4 (l - l0) / (l l0)`` (twice, transverse) and 0 (x3, rigid translation), so
the "gauss_newton" mode (drop the transverse part where l < l0) and the "projected" mode
(eigenvalue clamp of the 6x6 block) coincide and are computed in closed form.

Area term (the draft omits it; switchable)::

    W_A = sum_T A0 (1 - A / A0)^2 = sum_T (A - A0)^2 / A0,   A = |n| / 2,
    n = (x_1 - x_0) x (x_2 - x_0) = sum_a x_a x x_{a+1}.

For cyclic (a, b, c) let ``d_a = x_c - x_b``; then ``dn/dx_a = [d_a]_x`` and

    dA/dx_a = 1/2 n_hat x d_a,
    d2A/dx_a dx_b = 1/2 ([d_a]_x^T (I - n_hat n_hat^T) [d_b]_x / |n| + S_ab),
    S_{a,a+1} = -[n_hat]_x,  S_{a+1,a} = [n_hat]_x,  S_aa = 0,

so ``d2W_A = 2 / A0 (grad A grad A^T + (A - A0) d2A)``. ``A`` is not a convex function of the
positions (``d2A`` is indefinite whatever the sign of ``A - A0``), so "gauss_newton" drops
``(A - A0) d2A`` for every face (the Gauss-Newton Hessian of the residual
``(A - A0)/sqrt(A0)``) and "projected" clamps the eigenvalues of each 9x9 block.

Both terms are pure functions returning a :class:`models.shell.assembly.TermEval`, evaluated
by fused numba kernels (value + gradient + local Hessian in one pass over the stencils).
A collapsed current edge (``l -> 0``) or face (``A -> 0``) is not differentiable; ``l`` and
``|n|`` are floored at ``1e-12`` times their rest values so the output stays finite.
"""

from __future__ import annotations

import numba
import numpy as np

from models.shell.assembly import (
    HessianMode,
    HessianSink,
    TermEval,
    check_hessian_mode,
    check_order,
    project_psd_blocks,
    scatter_block,
)
from models.shell.schedule import StencilSchedule

_FLOOR = 1e-12
"""Current length / doubled area below ``_FLOOR`` times the rest value is clamped to it, so a
collapsed edge or face yields large but finite derivatives (never inf/NaN)."""


@numba.njit(cache=True, fastmath=False, nogil=True)
def _edge_kernel(index: np.ndarray, x: np.ndarray, edges: np.ndarray, rest_len: np.ndarray,
                 stiffness: float, order: int, clamp: bool, vals: np.ndarray, grad: np.ndarray,
                 blocks: np.ndarray, fused: bool, data: np.ndarray, base: np.ndarray,
                 row_len: np.ndarray) -> float:  # pragma: no cover - numba
    """Fused value / gradient / 6x6 Hessian of ``stiffness (l - l0)^2 / l0`` per edge ``index``.

    With ``fused`` each block goes straight into ``data`` (:class:`HessianSink`). Returns 0
    (the value is the sum of ``vals``).
    """
    scratch = np.empty((6, 6))
    for ii in range(index.size):
        e = index[ii]
        i, j = edges[e, 0], edges[e, 1]
        l0 = rest_len[e]
        d0, d1, d2 = x[j, 0] - x[i, 0], x[j, 1] - x[i, 1], x[j, 2] - x[i, 2]
        ln = max(np.sqrt(d0 * d0 + d1 * d1 + d2 * d2), _FLOOR * l0)
        r = ln - l0
        vals[e] = stiffness * r * r / l0
        if order < 1:
            continue
        u = (d0 / ln, d1 / ln, d2 / ln)
        c = 2.0 * stiffness * r / l0
        for k in range(3):
            grad[3 * j + k] += c * u[k]
            grad[3 * i + k] -= c * u[k]
        if order < 2:
            continue
        tr = r / ln
        if clamp and tr < 0.0:
            tr = 0.0
        a = 2.0 * stiffness / l0
        kb = scratch if fused else blocks[e]
        for p in range(3):
            for q in range(3):
                kpq = a * ((1.0 - tr) * u[p] * u[q] + (tr if p == q else 0.0))
                kb[p, q] = kpq
                kb[3 + p, 3 + q] = kpq
                kb[p, 3 + q] = -kpq
                kb[3 + p, q] = -kpq
        if fused:
            scatter_block(data, edges[e], base[e], row_len, scratch, 1.0)
    return 0.0


def _outputs(n_vertices: int, m: int, s: int, order: int,
             keep_blocks: bool = True) -> tuple[np.ndarray, ...]:
    """Allocate per-stencil values, flat gradient and local blocks (empty when not needed)."""
    grad = np.zeros(3 * n_vertices if order >= 1 else 0)
    rows = m if order >= 2 and keep_blocks else 0
    blocks = np.empty((rows, 3 * s, 3 * s))  # all written
    return np.empty(m), grad, blocks


def _term_eval(vals: np.ndarray, grad: np.ndarray, blocks: np.ndarray | None,
               order: int) -> TermEval:
    """Package kernel outputs as a TermEval (None for orders not requested or fused)."""
    return TermEval(value=float(vals.sum()), grad=grad if order >= 1 else None,
                    blocks=blocks if order >= 2 else None, element_values=vals)


def edge_membrane(x: np.ndarray, edges: np.ndarray, rest_len: np.ndarray, *, order: int = 2,
                  hessian_mode: HessianMode = "exact", stiffness: float = 1.0,
                  sink: HessianSink | None = None,
                  schedule: StencilSchedule | None = None) -> TermEval:
    """Edge-spring membrane energy ``stiffness * sum_e (l_e - l0_e)^2 / l0_e``.

    Args:
        x: (n, 3) positions.
        edges: (E, 2) int64 vertex pairs.
        rest_len: (E,) rest lengths l0 > 0.
        order: 0 value, 1 + gradient, 2 + local Hessians (E, 6, 6).
        hessian_mode: "exact", "gauss_newton" or "projected" (the last two coincide here:
            the transverse part of compressed edges is dropped).
        stiffness: Factor k_L multiplying the energy and its derivatives.
        sink: If given (order 2), each 6x6 block is added straight into ``sink.data`` (fused
            assembly, :class:`models.shell.assembly.HessianSink`) and ``blocks`` is None.
        schedule: Thread split of the edges (:mod:`models.shell.schedule`; default one
            thread, in order).

    Returns:
        TermEval with per-edge energies in ``element_values``.

    """
    check_order(order)
    check_hessian_mode(hessian_mode)
    fused, data, base, row_len = HessianSink.unpacked(sink if order >= 2 else None, 2)
    vals, grad, blocks = _outputs(x.shape[0], edges.shape[0], 2, order, keep_blocks=not fused)
    k, clamp = float(stiffness), hessian_mode != "exact"
    (schedule or StencilSchedule.serial(edges.shape[0])).run(
        lambda index: _edge_kernel(index, x, edges, rest_len, k, order, clamp, vals, grad,
                                   blocks, fused, data, base, row_len))
    return _term_eval(vals, grad, None if fused else blocks, order)


@numba.njit(cache=True, inline="always")
def skew_entry(c0: float, c1: float, c2: float, p: int, q: int) -> float:  # pragma: no cover
    """Entry (p, q) of the cross-product matrix ``[c]_x`` (``[c]_x y = c x y``)."""
    if p == q:
        return 0.0
    if p == 0:
        return -c2 if q == 1 else c1
    if p == 1:
        return c2 if q == 0 else -c0
    return -c1 if q == 0 else c0


@numba.njit(cache=True, inline="always")
def cyclic_sign(a: int, b: int) -> float:  # pragma: no cover
    """-1 if b follows a in the cyclic order (0, 1, 2), +1 if a follows b, 0 if a == b.

    The sign of the cross-product block ``d^2 A / dx_a dx_b`` of a triangle's area vector.
    """
    if b == (a + 1) % 3:
        return -1.0
    if a == (b + 1) % 3:
        return 1.0
    return 0.0


@numba.njit(cache=True, fastmath=False)
def _area_kernel(x: np.ndarray, faces: np.ndarray, rest_area: np.ndarray, stiffness: float,
                 order: int, keep_curv: bool, vals: np.ndarray, grad: np.ndarray,
                 blocks: np.ndarray) -> None:  # pragma: no cover - numba
    """Fused value / gradient / 9x9 Hessian of ``stiffness (A - A0)^2 / A0`` per face."""
    d = np.empty((3, 3))
    ga = np.empty((3, 3))
    sk = np.empty((3, 3, 3))
    for f in range(faces.shape[0]):
        for a in range(3):
            b, c = faces[f, (a + 1) % 3], faces[f, (a + 2) % 3]
            for k in range(3):
                d[a, k] = x[c, k] - x[b, k]
        # n = (x1 - x0) x (x2 - x0) = d_2 x (-d_1) = d_1 x d_2
        n0 = d[1, 1] * d[2, 2] - d[1, 2] * d[2, 1]
        n1 = d[1, 2] * d[2, 0] - d[1, 0] * d[2, 2]
        n2 = d[1, 0] * d[2, 1] - d[1, 1] * d[2, 0]
        nn = max(np.sqrt(n0 * n0 + n1 * n1 + n2 * n2), 2.0 * _FLOOR * rest_area[f])
        h0, h1, h2 = n0 / nn, n1 / nn, n2 / nn
        area, a0 = 0.5 * nn, rest_area[f]
        r = area - a0
        vals[f] = stiffness * r * r / a0
        if order < 1:
            continue
        for a in range(3):  # dA/dx_a = 1/2 n_hat x d_a
            ga[a, 0] = 0.5 * (h1 * d[a, 2] - h2 * d[a, 1])
            ga[a, 1] = 0.5 * (h2 * d[a, 0] - h0 * d[a, 2])
            ga[a, 2] = 0.5 * (h0 * d[a, 1] - h1 * d[a, 0])
            v = faces[f, a]
            for k in range(3):
                grad[3 * v + k] += 2.0 * stiffness * r / a0 * ga[a, k]
        if order < 2:
            continue
        cg = 2.0 * stiffness / a0
        cc = cg * r if keep_curv else 0.0
        if cc != 0.0:
            for a in range(3):  # sk[a] = (I - n_hat n_hat^T) [d_a]_x
                for p in range(3):
                    for q in range(3):
                        s = skew_entry(d[a, 0], d[a, 1], d[a, 2], p, q)
                        proj = (h0 * skew_entry(d[a, 0], d[a, 1], d[a, 2], 0, q)
                                + h1 * skew_entry(d[a, 0], d[a, 1], d[a, 2], 1, q)
                                + h2 * skew_entry(d[a, 0], d[a, 1], d[a, 2], 2, q))
                        hp = h0 if p == 0 else (h1 if p == 1 else h2)
                        sk[a, p, q] = s - hp * proj
        for a in range(3):
            for b in range(3):
                sgn = cyclic_sign(a, b)
                for p in range(3):
                    for q in range(3):
                        hab = cg * ga[a, p] * ga[b, q]
                        if cc != 0.0:
                            m = 0.0
                            for t in range(3):  # [d_a]_x^T P [d_b]_x = sk_a^T sk_b (P idempotent)
                                m += sk[a, t, p] * sk[b, t, q]
                            nh = sgn * skew_entry(h0, h1, h2, p, q)
                            hab += cc * 0.5 * (m / nn + nh)
                        blocks[f, 3 * a + p, 3 * b + q] = hab


def area_membrane(x: np.ndarray, faces: np.ndarray, rest_area: np.ndarray, *, order: int = 2,
                  hessian_mode: HessianMode = "exact", stiffness: float = 1.0) -> TermEval:
    """Area membrane energy ``stiffness * sum_T (A_T - A0_T)^2 / A0_T``.

    Args:
        x: (n, 3) positions.
        faces: (F, 3) int64 oriented faces.
        rest_area: (F,) rest areas A0 > 0.
        order: 0 value, 1 + gradient, 2 + local Hessians (F, 9, 9).
        hessian_mode: "exact"; "gauss_newton" (2/A0 grad A grad A^T only); "projected"
            (exact 9x9 blocks with eigenvalues clamped to >= 0).
        stiffness: Factor k_A multiplying the energy and its derivatives.

    Returns:
        TermEval with per-face energies in ``element_values``.

    """
    check_order(order)
    check_hessian_mode(hessian_mode)
    vals, grad, blocks = _outputs(x.shape[0], faces.shape[0], 3, order)
    _area_kernel(x, faces, rest_area, float(stiffness), order, hessian_mode != "gauss_newton",
                 vals, grad, blocks)
    if order >= 2 and hessian_mode == "projected":
        project_psd_blocks(blocks)
    return _term_eval(vals, grad, blocks, order)
