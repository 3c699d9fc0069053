"""Signed hinge (dihedral) bend angle with its exact gradient and Hessian.

Geometry only; the energy and its weights are in :mod:`models.shell.bending`.

Hinge convention (fixed for the whole shell code): ``hinges`` is ``(Hn, 4)`` int64
``[i, j, k, l]``. The interior edge is ``(i, j)``; face 0 is ``(i, j, k)`` and face 1 is
``(j, i, l)``, both in the cyclic orientation of a consistently oriented mesh. With

    e  = x_j - x_i,
    n0 = (x_j - x_i) x (x_k - x_i),        (face 0, right-hand rule)
    n1 = (x_i - x_j) x (x_l - x_j),        (face 1, right-hand rule)

the bend angle is the half-angle ``atan2`` form (never ``acos``, exact near 0 and +-pi):

    theta = 2 atan2((n0 x n1) . e_hat, n0 . n1 + |n0| |n1|)  in (-pi, pi],

evaluated as ``sign((n0 x n1) . e) 2 atan2(|u - v|, |u + v|)`` with unit normals ``u, v``
(no cancellation near +-pi). Past flat-on-flat it jumps from ``+pi`` to ``-pi``;
:func:`on_branch` gives ``theta + 2 pi k`` nearest to a reference angle (same derivatives).

``theta = 0`` for a flat hinge. Sign: ``theta > 0`` for a *convex* fold, i.e. when the two
faces bend away from the side their normals point to (a roof ridge seen from outside a closed
surface with outward normals); ``theta < 0`` for a concave (valley) fold. Rest angles
``theta0`` are computed by the same function, so rest and current angles share one rule.

Gradient (Bridson et al. 2003; Tamstorf & Grinspun 2013, "Discrete bending forces and their
Jacobians", Graph. Models 75(6)). Each face ``(p, q, r)`` with edge ``e' = x_q - x_p``
(``e' = e`` for face 0, ``-e`` for face 1), opposite vertex ``r``, normal
``n = e' x (x_r - x_p)`` and height ``h = |n| / |e|`` contributes

    f = |e| n / |n|^2 = n_hat / h,        t = (x_r - x_p) . e' / |e|^2,
    d theta/d x_p += (1 - t) f,   d theta/d x_q += t f,   d theta/d x_r += -f.

Hessian: each face's contribution differentiated once more (:func:`_face_hess`).

Only ``|n|^2 > 0`` and ``|e| > 0`` are needed: near-degenerate faces (height/edge ~ 1e-3 or
smaller) give finite, accurate values; ``theta`` near +-pi is handled by ``atan2`` (the
gradient and Hessian formulas do not involve ``theta`` at all). A truly degenerate face
(zero area) is rejected upstream (:func:`models.shell.bending.hinge_weights` raises).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numba import njit

from meshes.errors import InputError


@njit(cache=True, inline="always", error_model="numpy")
def _sub(a: tuple, b: tuple) -> tuple:
    """Return ``a - b`` for 3-tuples."""
    return (a[0] - b[0], a[1] - b[1], a[2] - b[2])


@njit(cache=True, inline="always", error_model="numpy")
def _dot(a: tuple, b: tuple) -> float:
    """Return ``a . b`` for 3-tuples."""
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


@njit(cache=True, inline="always", error_model="numpy")
def _cross(a: tuple, b: tuple) -> tuple:
    """Return ``a x b`` for 3-tuples."""
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


_TWO_PI = 2.0 * np.pi


def on_branch(theta: Any, reference: Any) -> Any:
    """Return ``theta + 2 pi k``, the angle of that hinge nearest to ``reference`` [rad].

    ``k = floor((reference - theta) / (2 pi) + 1/2)``: 0, so ``theta`` unchanged bit for bit,
    while ``|reference - theta| < pi``. Scalars or arrays (numpy broadcasting); compiled as
    :func:`on_branch_one` for the kernels.
    """
    return theta + _TWO_PI * np.floor((reference - theta) / _TWO_PI + 0.5)


on_branch_one = njit(cache=True, inline="always", error_model="numpy")(on_branch)
"""Compiled :func:`on_branch` of one angle (numba kernels)."""


@njit(cache=True, inline="always", error_model="numpy")
def _point(x: np.ndarray, v: int) -> tuple:
    """Return vertex ``v`` of ``x`` as a 3-tuple."""
    return (x[v, 0], x[v, 1], x[v, 2])


@njit(cache=True, inline="always", error_model="numpy")
def _theta_from_normals(n0: tuple, n1: tuple, e: tuple) -> float:
    """Signed angle ``2 atan2((n0 x n1).e_hat, n0.n1 + |n0||n1|)``, evaluated accurately.

    With unit normals ``u, v`` the same half angle is ``atan2(|u - v|, |u + v|)`` (Kahan's
    formula), which keeps full relative accuracy near 0 *and* near +-pi where
    ``n0.n1 + |n0||n1|`` cancels; the sign is that of ``(n0 x n1) . e`` (``+pi`` at an exact
    fold, so theta lies in (-pi, pi]).
    """
    i0, i1 = 1.0 / np.sqrt(_dot(n0, n0)), 1.0 / np.sqrt(_dot(n1, n1))
    u = (n0[0] * i0, n0[1] * i0, n0[2] * i0)
    v = (n1[0] * i1, n1[1] * i1, n1[2] * i1)
    dif, tot = _sub(u, v), (u[0] + v[0], u[1] + v[1], u[2] + v[2])
    half = np.arctan2(np.sqrt(_dot(dif, dif)), np.sqrt(_dot(tot, tot)))
    return 2.0 * half if _dot(_cross(n0, n1), e) >= 0.0 else -2.0 * half


@njit(cache=True, inline="always", error_model="numpy")
def _face_grad(xp: tuple, xq: tuple, xr: tuple, slots: tuple, g: np.ndarray) -> tuple:
    """Add one face's ``d theta/dx`` to ``g`` (12,); return ``(n, f, t)``."""
    e = _sub(xq, xp)
    s2 = _dot(e, e)
    a = _sub(xr, xp)
    n = _cross(e, a)
    scale = np.sqrt(s2) / _dot(n, n)
    f = (scale * n[0], scale * n[1], scale * n[2])
    t = _dot(a, e) / s2
    w = (1.0 - t, t, -1.0)
    for m in range(3):
        for c in range(3):
            g[3 * slots[m] + c] += w[m] * f[c]
    return n, f, t


@njit(cache=True, inline="always", error_model="numpy")
def _face_hess(xp: tuple, xq: tuple, xr: tuple, slots: tuple, n: tuple, f: tuple, t: float,
               hess: np.ndarray) -> None:
    """Add one face's ``d^2 theta/dx^2`` to ``hess`` (12, 12).

    With the module docstring's face quantities, ``c_p = x_r - x_q``,
    ``c_q = -(x_r - x_p)``, ``c_r = e'`` (so that ``dn/dx_b = [c_b]_x``), ``sigma = (-1, 1, 0)``
    (``d|e|/dx_b = sigma_b e'^T/|e|``), weights ``w = (1 - t, t, -1)``:

        df/dx_b = f (sigma_b e'/|e|^2 - 2 (n x c_b)/|n|^2)^T + (|e|/|n|^2) [c_b]_x,
        dt/dx_r = e'/|e|^2,  dt/dx_q = (x_r - x_p - 2 t e')/|e|^2,  dt/dx_p = -(dt/dx_q + dt/dx_r),
        H_ab += f (dw_a/dx_b)^T + w_a df/dx_b      (dw_p = -dt, dw_q = dt, dw_r = 0).
    """
    e = _sub(xq, xp)
    a = _sub(xr, xp)
    s2 = _dot(e, e)
    nn = _dot(n, n)
    k = np.sqrt(s2) / nn
    c = (_sub(xr, xq), (-a[0], -a[1], -a[2]), e)
    sigma = (-1.0, 1.0, 0.0)
    w = (1.0 - t, t, -1.0)
    dtq = ((a[0] - 2.0 * t * e[0]) / s2, (a[1] - 2.0 * t * e[1]) / s2, (a[2] - 2.0 * t * e[2]) / s2)
    dtr = (e[0] / s2, e[1] / s2, e[2] / s2)
    dtp = (-dtq[0] - dtr[0], -dtq[1] - dtr[1], -dtq[2] - dtr[2])
    dt = (dtp, dtq, dtr)
    dsign = (-1.0, 1.0, 0.0)
    for b in range(3):
        cb = c[b]
        nxc = _cross(n, cb)
        u = (sigma[b] * e[0] / s2 - 2.0 * nxc[0] / nn, sigma[b] * e[1] / s2 - 2.0 * nxc[1] / nn,
             sigma[b] * e[2] / s2 - 2.0 * nxc[2] / nn)
        skew = ((0.0, -k * cb[2], k * cb[1]), (k * cb[2], 0.0, -k * cb[0]),
                (-k * cb[1], k * cb[0], 0.0))
        col = 3 * slots[b]
        for m in range(3):
            row = 3 * slots[m]
            wm, dm = w[m], dsign[m]
            r = (dm * dt[b][0] + wm * u[0], dm * dt[b][1] + wm * u[1], dm * dt[b][2] + wm * u[2])
            for alpha in range(3):
                for beta in range(3):
                    hess[row + alpha, col + beta] += f[alpha] * r[beta] + wm * skew[alpha][beta]


@njit(cache=True, error_model="numpy")
def theta_derivs_one(x: np.ndarray, hinge: np.ndarray, g: np.ndarray, hess: np.ndarray,
                      want_hess: bool) -> float:
    """Angle of one hinge; overwrite ``g`` (12,) and, if asked, ``hess`` (12, 12)."""
    xi, xj = _point(x, hinge[0]), _point(x, hinge[1])
    xk, xl = _point(x, hinge[2]), _point(x, hinge[3])
    g[:] = 0.0
    n0, f0, t0 = _face_grad(xi, xj, xk, (0, 1, 2), g)
    n1, f1, t1 = _face_grad(xj, xi, xl, (1, 0, 3), g)
    if want_hess:
        hess[:, :] = 0.0
        _face_hess(xi, xj, xk, (0, 1, 2), n0, f0, t0, hess)
        _face_hess(xj, xi, xl, (1, 0, 3), n1, f1, t1, hess)
    return _theta_from_normals(n0, n1, _sub(xj, xi))


@njit(cache=True, inline="always", error_model="numpy")
def theta_one(x: np.ndarray, hinge: np.ndarray) -> float:
    """Angle of one hinge without its derivatives (the line search's energy values).

    The same normals and formula as :func:`theta_derivs_one`, so bitwise the same value.
    """
    xi, xj = _point(x, hinge[0]), _point(x, hinge[1])
    e = _sub(xj, xi)
    n0 = _cross(e, _sub(_point(x, hinge[2]), xi))
    n1 = _cross(_sub(xi, xj), _sub(_point(x, hinge[3]), xj))
    return _theta_from_normals(n0, n1, e)


@njit(cache=True, error_model="numpy")
def _theta_all(x: np.ndarray, hinges: np.ndarray) -> np.ndarray:
    """Bend angles of all hinges (value only)."""
    out = np.empty(hinges.shape[0])
    for h in range(hinges.shape[0]):
        out[h] = theta_one(x, hinges[h])
    return out


@njit(cache=True, error_model="numpy")
def _theta_derivs_all(x: np.ndarray, hinges: np.ndarray, want_hess: bool) -> tuple:
    """Angles (Hn,), gradients (Hn, 12) and Hessians (Hn, 12, 12) (empty if not asked)."""
    nh = hinges.shape[0]
    theta = np.empty(nh)
    grads = np.empty((nh, 12))
    hess = np.zeros((nh if want_hess else 0, 12, 12))
    scratch = np.empty((12, 12))
    for h in range(nh):
        out = hess[h] if want_hess else scratch
        theta[h] = theta_derivs_one(x, hinges[h], grads[h], out, want_hess)
    return theta, grads, hess


def check_hinge_arrays(x: np.ndarray, hinges: np.ndarray) -> None:
    """Validate positions ``x`` (n, 3) float64 and ``hinges`` (Hn, 4) int64.

    Raises:
        InputError: naming ``x`` or ``hinges`` when a shape, dtype or index is wrong.

    """
    if x.ndim != 2 or x.shape[1] != 3 or x.dtype != np.float64:
        raise InputError(f"x: expected (n, 3) float64 positions, got {x.shape} {x.dtype}")
    if hinges.ndim != 2 or hinges.shape[1] != 4 or hinges.dtype != np.int64:
        raise InputError(f"hinges: expected (Hn, 4) int64, got {hinges.shape} {hinges.dtype}")
    if hinges.size and (hinges.min() < 0 or hinges.max() >= x.shape[0]):
        raise InputError(f"hinges: vertex index outside [0, {x.shape[0]})")


def hinge_angles(x: np.ndarray, hinges: np.ndarray) -> np.ndarray:
    """Signed bend angle of every hinge, ``theta`` in (-pi, pi] (0 when flat).

    ``theta = 2 atan2((n0 x n1) . e_hat, n0 . n1 + |n0||n1|)``, positive for a convex fold
    (module docstring). Use it for the rest angles ``theta0`` too.

    Args:
        x: (n, 3) float64 vertex positions.
        hinges: (Hn, 4) int64 ``[i, j, k, l]`` hinges.

    Returns:
        (Hn,) float64 angles.

    """
    check_hinge_arrays(x, hinges)
    return _theta_all(x, hinges)


def hinge_angle_derivatives(x: np.ndarray, hinges: np.ndarray, *, hessian: bool = True
                            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Angles with their exact gradients and Hessians (Tamstorf & Grinspun 2013).

    Local dof ``3 m + c`` is coordinate ``c`` of hinge vertex ``m`` (``[i, j, k, l]``).

    Args:
        x: (n, 3) float64 vertex positions.
        hinges: (Hn, 4) int64 hinges.
        hessian: also return the (Hn, 12, 12) Hessians (else an empty (0, 12, 12) array).

    Returns:
        ``(theta (Hn,), grad (Hn, 12), hess (Hn, 12, 12))``.

    """
    check_hinge_arrays(x, hinges)
    return _theta_derivs_all(x, hinges, hessian)
