"""Hinge bending energy W_B of the discrete shell (Grinspun et al. 2003, "Discrete Shells").

    W_B(x) = sum_h w_h (theta_h(x) - theta0_h)^2,      w_h = 3 |e0_h|^2 / (A1_h + A2_h),

where ``theta`` is the signed hinge angle of :mod:`models.shell.hinge_angle` (one orientation
rule for rest and current angles), ``|e0|`` the rest edge length and ``A1, A2`` the rest
areas of the two faces (``|e0| / h0`` with ``h0`` a third of the mean height of the two
faces). The shell energy multiplies it by ``k_B``; physically ``k_B = D / 2`` with the plate
bending stiffness ``D = E h^3 / (12 (1 - nu^2))`` (ARCSim's weight is 1/24 of this form;
convert explicitly when comparing).

Derivatives (exact, Tamstorf & Grinspun 2013):

    grad W_B = sum_h 2 w_h (theta_h - theta0_h) grad theta_h,
    hess W_B = sum_h 2 w_h (grad theta_h grad theta_h^T + (theta_h - theta0_h) hess theta_h).

``hessian_mode``: "exact"; "gauss_newton" drops the indefinite second part; "projected" clamps
the eigenvalues of each exact 12x12 block to >= 0.

Fold contact (ours, not in the draft; ``contact`` > 0): each hinge also pays ``c w_h b(pi -
|theta_h|)``, the log barrier of :mod:`models.shell.log_barrier` in the gap to flat-on-flat,
so a fold closes until its two faces touch, not through them; bit for bit nothing while every
hinge keeps ``|theta| <= pi - d_hat``. Its derivatives enter as ``f'' grad theta grad theta^T
+ f' hess theta`` like the bending's. It needs each angle on its followed branch (``branch``):
on ``(-pi, pi]`` a trial step across pi would read a wide-open fold and pass through.

Continuum limit: on equilateral meshes the energy density tends to (k1 + k2)^2 + 2 (k1 - k2)^2,
3x a plate with nu = -1/3, so a cylindrical bend costs 3x the plate energy with k_B = D/2
(derivation and measurements: docs/notes/hinge-bending-limit.md).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from meshes.errors import InputError
from models.shell.assembly import (
    HessianMode,
    HessianSink,
    TermEval,
    check_hessian_mode,
    check_order,
    project_psd,
    project_psd_blocks,
    scatter_block,
    translation_complement,
)
from models.shell.hinge_angle import (
    check_hinge_arrays,
    on_branch_one,
    theta_derivs_one,
    theta_one,
)
from models.shell.log_barrier import log_barrier
from models.shell.schedule import StencilSchedule

_MODE_CODE = {"exact": 0, "gauss_newton": 1, "projected": 0}
_HINGE_Q = translation_complement(4)
"""Basis (12, 9) orthogonal to translations for the reduced PSD clamp of hinge blocks."""


def hinge_weights(x_rest: np.ndarray, hinges: np.ndarray) -> np.ndarray:
    """Rest weights ``w_h = 3 |e0|^2 / (A1 + A2)`` (= ``|e0| / h0``, Grinspun et al. 2003).

    Args:
        x_rest: (n, 3) float64 rest positions.
        hinges: (Hn, 4) int64 hinges ``[i, j, k, l]``.

    Returns:
        (Hn,) float64 weights.

    Raises:
        InputError: naming the first hinge whose faces have (numerically) zero area.

    """
    check_hinge_arrays(x_rest, hinges)
    xi, xj = x_rest[hinges[:, 0]], x_rest[hinges[:, 1]]
    e = xj - xi
    a0 = 0.5 * np.linalg.norm(np.cross(e, x_rest[hinges[:, 2]] - xi), axis=1)
    a1 = 0.5 * np.linalg.norm(np.cross(xi - xj, x_rest[hinges[:, 3]] - xj), axis=1)
    e2 = np.einsum("ij,ij->i", e, e)
    bad = np.flatnonzero(~(np.minimum(a0, a1) > 1e-14 * e2))
    if bad.size:
        raise InputError(f"hinges: hinge {bad[0]} {hinges[bad[0]].tolist()} has a degenerate "
                         "(zero-area) rest face")
    return 3.0 * e2 / (a0 + a1)


@njit(cache=True, error_model="numpy", nogil=True)
def _bending_kernel(index: np.ndarray, x: np.ndarray, hinges: np.ndarray, theta0: np.ndarray,
                    weights: np.ndarray, order: int, mode: int, grad: np.ndarray,
                    blocks: np.ndarray, energies: np.ndarray, fused: bool, data: np.ndarray,
                    base: np.ndarray, row_len: np.ndarray, project: bool,
                    q: np.ndarray, branch: np.ndarray, contact: float,
                    gap_hat: float) -> float:  # pragma: no cover - numba
    """Fused pass over the hinges ``index``: energy, gradient scatter and 12x12 block.

    Mode 0 exact, 1 Gauss-Newton. With ``fused`` the block is built in a scratch array,
    PSD-projected if ``project`` (reduced clamp with basis ``q``) and added into ``data``
    (:class:`HessianSink`) instead of stored. ``branch`` (Hn,) or empty: each angle taken
    on the branch nearest to its entry (:func:`on_branch`). ``contact > 0``: the fold
    contact ``contact w_h b(pi - |theta|)`` below ``gap_hat`` (+inf at a closed fold).
    Returns the energy of those hinges.
    """
    g = np.empty(12)
    scratch3 = np.empty((1, 12, 12))
    scratch = scratch3[0]
    total = 0.0
    for ii in range(index.size):
        h = index[ii]
        hb = blocks[h] if (order >= 2 and not fused) else scratch
        if order == 0:
            theta = theta_one(x, hinges[h])
        else:
            theta = theta_derivs_one(x, hinges[h], g, hb, order >= 2 and mode == 0)
        if branch.size:
            theta = on_branch_one(theta, branch[h])
        d = theta - theta0[h]
        energies[h] = weights[h] * d * d
        f1, f2 = 2.0 * weights[h] * d, 2.0 * weights[h]  # dE/dtheta, d2E/dtheta2
        gap = np.pi - abs(theta)
        if contact > 0.0 and gap < gap_hat:
            if gap <= 0.0:
                energies[h] = np.inf
                total += np.inf
                continue
            bv, b1, b2 = log_barrier(gap, gap_hat)
            cw = contact * weights[h]
            energies[h] += cw * bv
            f1 -= cw * b1 if theta > 0.0 else -cw * b1  # d gap / d theta = -sign(theta)
            f2 += cw * b2
        total += energies[h]
        if order >= 1:
            for m in range(4):
                for k in range(3):
                    grad[3 * hinges[h, m] + k] += f1 * g[3 * m + k]
        if order >= 2:
            _fill_block(hb, g, f2, f1, mode == 0)
            if fused:
                if project:
                    project_psd(scratch3, q)
                scatter_block(data, hinges[h], base[h], row_len, scratch, 1.0)
    return total


@njit(cache=True, inline="always", error_model="numpy")
def _fill_block(hb: np.ndarray, g: np.ndarray, f2: float, f1: float,
                exact: bool) -> None:  # pragma: no cover - numba
    """``hb <- f2 g g^T + f1 hb`` (exact) or ``f2 g g^T`` (Gauss-Newton), symmetrised.

    ``g``, ``hb``: the angle's gradient and Hessian; ``f1``, ``f2``: the hinge energy's first
    and second derivatives in the angle.
    """
    s = f1 if exact else 0.0
    for a in range(12):
        for b in range(a, 12):
            v = f2 * g[a] * g[b] + (0.5 * s * (hb[a, b] + hb[b, a]) if exact else 0.0)
            hb[a, b] = v
            hb[b, a] = v


def _check_rest(hinges: np.ndarray, theta0: np.ndarray, weights: np.ndarray,
                branch: np.ndarray | None = None) -> None:
    """Raise InputError naming ``theta0`` / ``weights`` / ``branch`` not matching ``hinges``."""
    for name, arr in (("theta0", theta0), ("weights", weights), ("branch", branch)):
        if arr is not None and (arr.shape != (hinges.shape[0],) or arr.dtype != np.float64):
            raise InputError(f"{name}: expected ({hinges.shape[0]},) float64, "
                             f"got {arr.shape} {arr.dtype}")


def check_contact(contact: float, gap: float) -> None:
    """Raise InputError naming the fold contact's stiffness or gap when out of range."""
    if not (np.isfinite(contact) and contact >= 0.0):
        raise InputError(f"fold_contact: must be finite and >= 0, got {contact!r}")
    if not (np.isfinite(gap) and 0.0 < gap < np.pi):
        raise InputError(f"fold_gap: must be in (0, pi) rad, got {gap!r}")


def hinge_bending(x: np.ndarray, hinges: np.ndarray, theta0: np.ndarray, weights: np.ndarray,
                  *, order: int = 2, hessian_mode: HessianMode = "exact",
                  sink: HessianSink | None = None,
                  schedule: StencilSchedule | None = None,
                  branch: np.ndarray | None = None, contact: float = 0.0,
                  contact_gap: float = 0.1) -> TermEval:
    """Hinge bending energy ``W_B = sum_h w_h (theta_h - theta0_h)^2`` and its derivatives.

    One fused numba pass computes, per hinge, the angle, its exact gradient and (order 2)
    Hessian, the energy, the gradient scatter and the local 12x12 block (local dof
    ``3 m + c`` = coordinate ``c`` of hinge vertex ``m``, as :mod:`models.shell.assembly`
    expects for stencils ``hinges``).

    Args:
        x: (n, 3) float64 current positions.
        hinges: (Hn, 4) int64 hinges ``[i, j, k, l]`` (:mod:`models.shell.hinge_angle`).
        theta0: (Hn,) rest angles, ``hinge_angles(x_rest, hinges)``.
        weights: (Hn,) weights, ``hinge_weights(x_rest, hinges)`` (times k_B if wanted).
        order: 0 value, 1 value + gradient, 2 value + gradient + Hessian blocks.
        hessian_mode: "exact", "gauss_newton" (``2 w grad theta grad theta^T``) or
            "projected" (exact block with negative eigenvalues clamped to 0).
        sink: If given (order 2), each block is added straight into ``sink.data`` (fused
            assembly, :class:`models.shell.assembly.HessianSink`) and ``blocks`` is None.
        schedule: Thread split of the hinges (:mod:`models.shell.schedule`; default one
            thread, in order).
        branch: (Hn,) reference angles [rad]: each ``theta_h`` is taken as the angle of that
            hinge nearest to ``branch[h]`` (:func:`models.shell.hinge_angle.on_branch`), so
            a fold followed past ``+-pi`` keeps a smooth, growing energy; None: ``theta`` in
            ``(-pi, pi]``. The derivatives do not change.
        contact: Fold contact ``c`` (dimensionless, 0 = off): each hinge also pays
            ``c w_h b(pi - |theta_h|)``, the log barrier of :mod:`models.shell.log_barrier` in
            the gap to flat-on-flat (its two faces touching), +inf at a closed fold.
        contact_gap: The barrier's activation gap ``d_hat`` [rad], in ``(0, pi)``.

    Returns:
        TermEval with ``value``, ``grad`` (3 n,), ``blocks`` (Hn, 12, 12) and
        ``element_values`` (Hn,) (per-hinge energies). If a current face has collapsed to
        zero area (or an edge to zero length) ``value`` is ``+inf`` (so a line search rejects
        the step) and the derivatives are not meaningful. Near-degenerate faces are fine.

    """
    check_order(order)
    check_hessian_mode(hessian_mode)
    check_hinge_arrays(x, hinges)
    _check_rest(hinges, theta0, weights, branch)
    check_contact(contact, contact_gap)
    grad = np.zeros(x.size if order >= 1 else 0)
    fused, data, base, row_len = HessianSink.unpacked(sink if order >= 2 else None, 4)
    blocks = np.empty((hinges.shape[0] if order >= 2 and not fused else 0, 12, 12))
    energies = np.empty(hinges.shape[0])
    xc, mode = np.ascontiguousarray(x), _MODE_CODE[hessian_mode]
    br = np.zeros(0) if branch is None else branch
    value = (schedule or StencilSchedule.serial(hinges.shape[0])).run(
        lambda index: _bending_kernel(index, xc, hinges, theta0, weights, order, mode, grad,
                                      blocks, energies, fused, data, base, row_len,
                                      hessian_mode == "projected", _HINGE_Q, br,
                                      float(contact), float(contact_gap)))
    if not np.isfinite(value):
        if not np.all(np.isfinite(x)):
            raise InputError("x: non-finite coordinate")
        value = np.inf  # a face collapsed to zero area: reject the state
    if order >= 2 and hessian_mode == "projected" and not fused:
        project_psd_blocks(blocks)  # hinge blocks annihilate translations: reduced 9x9 clamp
    return TermEval(value=float(value), grad=grad if order >= 1 else None,
                    blocks=blocks if order >= 2 and not fused else None,
                    element_values=energies)


def bending_energy_density(x: np.ndarray, hinges: np.ndarray, theta0: np.ndarray,
                           weights: np.ndarray, vertex_areas: np.ndarray,
                           branch: np.ndarray | None = None, contact: float = 0.0,
                           contact_gap: float = 0.1) -> np.ndarray:
    """Per-vertex bending energy density for visualisation.

    ``rho_v = (sum_{h : v in edge(h)} E_h / 2) / A_v`` with ``E_h`` the hinge's energy in
    :func:`hinge_bending` (``w_h (theta_h - theta0_h)^2``, plus its fold contact) split
    equally between the two edge vertices ``i, j`` of each hinge; ``sum_v rho_v A_v = W_B``.

    Args:
        x: (n, 3) current positions.
        hinges: (Hn, 4) hinges.
        theta0: (Hn,) rest angles.
        weights: (Hn,) hinge weights.
        vertex_areas: (n,) positive vertex areas (e.g. a third of the incident face areas).
        branch: (Hn,) reference angles, as in :func:`hinge_bending` (None: none).
        contact: Fold contact stiffness, as in :func:`hinge_bending` (0: off).
        contact_gap: The fold contact's activation gap [rad].

    Returns:
        (n,) energy per unit area at each vertex.

    """
    if vertex_areas.shape != (x.shape[0],) or not np.all(vertex_areas > 0):
        raise InputError(f"vertex_areas: expected ({x.shape[0]},) positive areas")
    e_h = hinge_bending(x, hinges, theta0, weights, order=0, branch=branch, contact=contact,
                        contact_gap=contact_gap).element_values
    assert e_h is not None  # hinge_bending always returns them (internal invariant)
    per_vertex = np.bincount(hinges[:, :2].ravel(), weights=np.repeat(0.5 * e_h, 2),
                             minlength=x.shape[0])
    return per_vertex / vertex_areas
