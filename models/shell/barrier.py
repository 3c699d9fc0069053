"""Flip barrier of the discrete shell: a face energy, unbounded before a face folds over.

Without it nothing resists a face collapsing: a sliver's edge lengths change only to second
order in its height, and at zero area the hinge angles are undefined (docs/notes/flip-barrier.md).

The barrier makes that singular set unreachable. Per face ``f`` with rest area ``A0_f`` and a
unit reference normal ``r_f`` (the rest normal, or the normal of the face on the current
penalty target, see :meth:`models.shell.energy.ShellEnergy.set_target`) the signed area ratio is

    s_f = n_f . r_f / (2 A0_f),   n_f = (x_1 - x_0) x (x_2 - x_0),

i.e. ``A / A0`` times the cosine of the face's tilt from its reference (1 at rest; <= 0 once
the face is collapsed or turned by >= 90 degrees). The energy is the C2 log barrier of
incremental potential contact (Li et al. 2020, "Incremental Potential Contact": their
``b(d, d_hat)`` with the distance d replaced by s):

    W_F = sum_f w_f b(s_f),   w_f = A0_f / q_f  (:func:`barrier_weights`),
    b(s) = -(s - s_hat)^2 ln(s / s_hat)  for 0 < s < s_hat,   0 for s >= s_hat,   +inf for s <= 0.

``b`` is exactly zero (with zero first and second derivatives) above the activation ratio
``s_hat``, so it does not change any state whose faces all keep ``s >= s_hat``, and it is
convex in s below it: ``b' = -2 (s - s_hat) ln(s / s_hat) - (s - s_hat)^2 / s < 0`` and
``b'' = -2 ln(s / s_hat) - 4 (s - s_hat) / s + (s - s_hat)^2 / s^2 > 0``. A line search on W
therefore never crosses ``s = 0`` (the energy there is +inf), with no change to the solver.

Derivatives (cyclic a, b = a + 1; ``d_a = x_{a+2} - x_{a+1}`` as in
:mod:`models.shell.membrane`): ``n . r = sum_a x_a . (x_{a+1} x r)`` is quadratic in x, so

    ds/dx_a = (r x d_a) / (2 A0),   d2s/dx_a dx_{a+1} = -[r]_x / (2 A0),
    d2s/dx_{a+1} dx_a = [r]_x / (2 A0),   d2s/dx_a dx_a = 0,

and ``d2W = w (b'' grad s grad s^T + b' d2s)``. The second part is indefinite (skew blocks);
"gauss_newton" drops it (``b'' > 0`` keeps the rest PSD), "projected" clamps each 9x9 block.

Weights w = A0 / q: the area of the equilateral triangle with the same sum of squared edges,
so the barrier holds a sliver as firmly as a regular face of its size.
"""

from __future__ import annotations

import numba
import numpy as np

from meshes.errors import InputError
from models.shell.assembly import (
    HessianMode,
    HessianSink,
    TermEval,
    check_hessian_mode,
    check_order,
    project_psd_blocks,
    scatter_block,
)
from models.shell.log_barrier import log_barrier
from models.shell.membrane import cyclic_sign, skew_entry
from models.shell.rest import face_normals, squared_edges
from models.shell.schedule import StencilSchedule


def check_activation(s_hat: float, name: str = "flip_activation") -> None:
    """Raise InputError naming ``name`` unless ``0 < s_hat <= 1``."""
    if not (np.isfinite(s_hat) and 0.0 < s_hat <= 1.0):
        raise InputError(f"{name}: must be in (0, 1], got {s_hat!r}")


@numba.njit(cache=True, fastmath=False, nogil=True)
def _flip_kernel(index: np.ndarray, x: np.ndarray, faces: np.ndarray, rest_area: np.ndarray,
                 weight: np.ndarray, ref: np.ndarray, s_hat: float, stiffness: float,
                 order: int, keep_curv: bool, vals: np.ndarray, grad: np.ndarray,
                 blocks: np.ndarray, fused: bool, data: np.ndarray, base: np.ndarray,
                 row_len: np.ndarray) -> float:  # pragma: no cover - numba
    """Fused value / gradient / 9x9 Hessian of ``stiffness w b(s)`` per face ``index``.

    With ``fused`` only the active faces' blocks are added straight into ``data``
    (:class:`HessianSink`); otherwise every face's block is written (zero when inactive).
    Returns 0 (the value is the sum of ``vals``).
    """
    d = np.empty((3, 3))
    gs = np.empty((3, 3))
    scratch = np.empty((9, 9))
    for ii in range(index.size):
        f = index[ii]
        for a in range(3):
            b, c = faces[f, (a + 1) % 3], faces[f, (a + 2) % 3]
            for k in range(3):
                d[a, k] = x[c, k] - x[b, k]
        r0, r1, r2 = ref[f, 0], ref[f, 1], ref[f, 2]
        n0 = d[1, 1] * d[2, 2] - d[1, 2] * d[2, 1]  # n = d_1 x d_2
        n1 = d[1, 2] * d[2, 0] - d[1, 0] * d[2, 2]
        n2 = d[1, 0] * d[2, 1] - d[1, 1] * d[2, 0]
        a0, w = rest_area[f], stiffness * weight[f]
        s = (n0 * r0 + n1 * r1 + n2 * r2) / (2.0 * a0)
        if s <= 0.0:
            vals[f] = np.inf
        if s <= 0.0 or s >= s_hat:
            if s > 0.0:
                vals[f] = 0.0
            if order >= 2 and not fused:
                blocks[f] = 0.0
            continue
        bv, b1, b2 = log_barrier(s, s_hat)
        vals[f] = w * bv
        if order < 1:
            continue
        for a in range(3):  # ds/dx_a = r x d_a / (2 A0)
            gs[a, 0] = (r1 * d[a, 2] - r2 * d[a, 1]) / (2.0 * a0)
            gs[a, 1] = (r2 * d[a, 0] - r0 * d[a, 2]) / (2.0 * a0)
            gs[a, 2] = (r0 * d[a, 1] - r1 * d[a, 0]) / (2.0 * a0)
            v = faces[f, a]
            for k in range(3):
                grad[3 * v + k] += w * b1 * gs[a, k]
        if order < 2:
            continue
        cg, cc = w * b2, (w * b1 / (2.0 * a0) if keep_curv else 0.0)
        kb = scratch if fused else blocks[f]
        for a in range(3):
            for bb in range(3):
                sgn = cyclic_sign(a, bb)
                for p in range(3):
                    for q in range(3):
                        kb[3 * a + p, 3 * bb + q] = (
                            cg * gs[a, p] * gs[bb, q]
                            + cc * sgn * skew_entry(r0, r1, r2, p, q))
        if fused:
            scatter_block(data, faces[f], base[f], row_len, scratch, 1.0)
    return 0.0


def signed_area_ratio(x: np.ndarray, faces: np.ndarray, rest_area: np.ndarray,
                      ref: np.ndarray) -> np.ndarray:
    """``s_f = n_f . r_f / (2 A0_f)`` per face (1 at rest; <= 0 collapsed or turned over)."""
    return np.einsum("ij,ij->i", face_normals(x, faces), ref) / (2.0 * rest_area)


def reference_normals(x_ref: np.ndarray, faces: np.ndarray, rest_area: np.ndarray,
                      fallback: np.ndarray) -> np.ndarray:
    """Return the unit face normals at ``x_ref`` (F, 3), ``fallback`` rows where degenerate.

    A face whose doubled area at ``x_ref`` is not above ``1e-12 * 2 A0`` has no direction; its
    row of ``fallback`` (the rest normal) is used, so the reference is always a unit vector.
    """
    n = face_normals(x_ref, faces)
    length = np.linalg.norm(n, axis=1)
    good = length > 2e-12 * rest_area
    out = np.array(fallback, dtype=np.float64, copy=True)
    out[good] = n[good] / length[good, None]
    return out


def barrier_weights(x_rest: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Per-face weight ``w_f = sqrt(3) / 12 sum |e0|^2 = A0_f / q_f`` (area unit).

    The area of the equilateral triangle with the same sum of squared rest edges (``q_f`` is
    the rest quality of :func:`models.shell.rest.face_quality`): a sliver is held as firmly as
    a regular face of its size instead of by its own vanishing area.
    """
    return np.sqrt(3.0) / 12.0 * squared_edges(x_rest, faces).sum(axis=1)


def flip_barrier(x: np.ndarray, faces: np.ndarray, rest_area: np.ndarray, weight: np.ndarray,
                 ref: np.ndarray, *,
                 s_hat: float = 0.1, order: int = 2, hessian_mode: HessianMode = "exact",
                 stiffness: float = 1.0, sink: HessianSink | None = None,
                 schedule: StencilSchedule | None = None) -> TermEval:
    """Flip barrier ``stiffness * sum_f A0_f b(s_f)`` (module docstring).

    Args:
        x: (n, 3) positions.
        faces: (F, 3) int64 oriented faces.
        rest_area: (F,) rest areas A0 > 0.
        weight: (F,) energy weights w_f (area; :func:`barrier_weights`).
        ref: (F, 3) unit reference normals r_f.
        s_hat: Activation ratio in (0, 1]: the barrier is zero while ``s_f >= s_hat``.
        order: 0 value, 1 + gradient, 2 + local Hessians (F, 9, 9).
        hessian_mode: "exact"; "gauss_newton" (``A0 b'' grad s grad s^T`` only); "projected"
            (exact 9x9 blocks with eigenvalues clamped to >= 0).
        stiffness: Factor k_F (energy / area) multiplying the energy and its derivatives.
        sink: If given (order 2, not "projected"), the active faces' 9x9 blocks are added
            straight into ``sink.data`` (:class:`models.shell.assembly.HessianSink`) and
            ``blocks`` is None: no (F, 9, 9) array is written (207 MB at 160k vertices).
        schedule: Thread split of the faces (:mod:`models.shell.schedule`; default one
            thread, in order).

    Returns:
        TermEval with per-face energies in ``element_values``; the value is +inf (and that
        face's gradient and Hessian are zero) when some ``s_f <= 0``. ``blocks`` is None when
        no face is below the activation (all blocks would be zero).

    """
    check_order(order)
    check_hessian_mode(hessian_mode)
    check_activation(s_hat, "s_hat")
    m = faces.shape[0]
    use_sink = sink if order >= 2 and hessian_mode != "projected" else None
    fused, data, base, row_len = HessianSink.unpacked(use_sink, 3)
    vals, grad = np.empty(m), np.zeros(3 * x.shape[0] if order >= 1 else 0)
    blocks = np.empty((m, 9, 9) if order >= 2 and not fused else (0, 9, 9))
    r, keep = np.ascontiguousarray(ref, dtype=np.float64), hessian_mode != "gauss_newton"
    (schedule or StencilSchedule.serial(m)).run(
        lambda index: _flip_kernel(index, x, faces, rest_area, weight, r, float(s_hat),
                                   float(stiffness), order, keep, vals, grad, blocks, fused,
                                   data, base, row_len))
    active = np.flatnonzero(vals > 0.0)
    if order >= 2 and hessian_mode == "projected" and active.size:
        sub = np.ascontiguousarray(blocks[active])
        project_psd_blocks(sub)  # only active faces: the other blocks are zero
        blocks[active] = sub
    # no face below the activation: every block is zero, so none is handed to the assembly
    return TermEval(value=float(vals.sum()), grad=grad if order >= 1 else None,
                    blocks=blocks if order >= 2 and active.size and not fused else None,
                    element_values=vals)
