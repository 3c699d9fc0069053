"""Where the shift ladder of a warm-started solve should start when its start is indefinite.

The shifted Newton factorises ``A + tau I`` for ``tau = tau_start growth^j`` until the LDL^T
has no negative pivot beyond the expected ones (Nocedal & Wright, Numerical Optimization, 2nd
ed., Alg. 3.3). A solve starts at ``tau = 0`` and climbs from ``tau_0 = 1e-6 mean|diag A|``,
so a few strongly negative eigenvalues cost one failed factorisation per rung: a matrix whose
smallest eigenvalue is ``lambda_min < 0`` needs about ``log_growth(|lambda_min| / tau_0)`` of
them (eight to ten on a stencil folded by the body's motion between frames). When the first
factorisation of a solve has a few negative pivots beyond the expected ones (at most
:data:`ISOLATED_NEGATIVES`: isolated eigenvalues), the ladder restarts instead at

    tau = margin |theta_min|,

with ``theta_min`` the smallest Ritz value of ``steps`` Lanczos steps on ``A`` (Golub & Van Loan,
Matrix Computations, 4th ed., sec. 10.1). The Ritz values interlace the spectrum, so
``lambda_min <= theta_min``: the restart never lies above ``margin |lambda_min|``, and an
underestimate only leaves the ladder to climb on from there. A dense negative spectrum (a
buckling shell, or a skin pressed by an impact: hundreds of negative pivots) keeps the
ladder's shifts, whose decaying values follow the softest modes down; at a solve's first
iteration it only leaves out the rungs ``tau < -theta_min``, which cannot pass
(``lambda_min + tau <= theta_min + tau < 0``): the shift the ladder would accept, at fewer
factorisations. The later iterations of a solve keep the ladder (restarting at every
indefinite attempt was measured to change the buckling path and cost iterations:
docs/notes/solver-choice.md), except for an outlier: an attempt at ``tau`` whose estimate
lies beyond ``OUTLIER max(tau, floor)``, the floor the larger of the ladder's first rung and
the previous iteration's shift (a stencil whose curvature dwarfs the ladder's
scale, e.g. a hinge across a sliver: docs/notes/sliver-hinges.md) restarts as well. A
buckling path's decayed probe fails by less than its last accepted shift, a rung or two,
and never meets that test; when its negative pivots are isolated, the estimate made for that
test leaves out the rungs it proves indefinite as well.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from solvers.linear import FactorReport, ShiftOptions

LANCZOS_STEPS: int = 30
"""Lanczos steps of the estimate (each one product with A)."""
MARGIN: float = 2.0
"""The restart shift as a multiple of ``|theta_min|`` (> 1: a margin over the estimate)."""
ISOLATED_NEGATIVES: int = 16
"""Most negative pivots (beyond the expected ones) for which the ladder is restarted."""
ROUNDOFF: float = 1e-3
"""Relative slack below ``-theta_min`` within which a rung is not proven indefinite."""
OUTLIER: float = 100.0
"""A later iteration restarts when ``|theta_min|`` exceeds this times the larger of its
attempt's shift and the caller's floor (``restart_ladder``'s ``beyond``)."""


def lowest_ritz_value(matvec: Callable[[np.ndarray], np.ndarray], n: int,
                      steps: int = LANCZOS_STEPS, seed: int = 0) -> float:
    """Smallest Ritz value of ``steps`` Lanczos steps on the symmetric operator ``matvec``.

    Full reorthogonalisation (the basis is at most ``steps`` vectors of length ``n``); the
    start vector is a seeded Gaussian, so the estimate is deterministic. Stops early when the
    Krylov space is invariant.

    Args:
        matvec: ``v -> A v`` for a symmetric ``A`` of order ``n``.
        n: order of A (>= 1).
        steps: Lanczos steps (>= 1).
        seed: seed of the start vector.

    Returns:
        ``theta_min >= lambda_min(A)``.

    """
    q = np.random.default_rng(seed).standard_normal(n)
    basis = np.zeros((min(steps, n), n))
    basis[0] = q / np.linalg.norm(q)
    alpha: list[float] = []
    beta: list[float] = []
    for j in range(basis.shape[0]):
        w = matvec(basis[j])
        alpha.append(float(basis[j] @ w))
        w = w - basis[: j + 1].T @ (basis[: j + 1] @ w)  # full reorthogonalisation, twice
        w = w - basis[: j + 1].T @ (basis[: j + 1] @ w)
        b = float(np.linalg.norm(w))
        if j + 1 == basis.shape[0] or b <= 1e-12 * max(abs(alpha[-1]), 1.0):
            break
        beta.append(b)
        basis[j + 1] = w / b
    off = beta[: len(alpha) - 1]
    t = np.diag(alpha) + np.diag(off, 1) + np.diag(off, -1)
    return float(np.linalg.eigvalsh(t)[0])


def is_isolated(negative_pivots: int | None, expected: int) -> bool:
    """Whether a factorisation's extra negative pivots are few enough to restart the ladder."""
    return negative_pivots is not None and 0 < negative_pivots - expected <= ISOLATED_NEGATIVES


def restart_shifts(theta_min: float, growth: float, count: int,
                   margin: float = MARGIN) -> list[float]:
    """Return the ladder restarted at ``margin |theta_min|``.

    ``count`` shifts growing by ``growth``; empty when ``theta_min >= 0`` (no negative
    curvature found).
    """
    if not theta_min < 0:
        return []
    start = margin * -theta_min
    return [start * growth**j for j in range(count)]


def proven_indefinite(ladder: Sequence[float], theta_min: float) -> int:
    """How many leading rungs of ``ladder`` leave ``A + tau I`` certainly indefinite.

    ``A + tau I`` has the eigenvalue ``lambda_min + tau <= theta_min + tau``, negative for
    ``tau < -theta_min``; a rung within :data:`ROUNDOFF` of ``-theta_min`` is kept (the
    factorisation's inertia decides it).
    """
    count = 0
    for tau in ladder:
        if not tau < (1.0 - ROUNDOFF) * -theta_min:
            break
        count += 1
    return count


def restart_ladder(report: FactorReport, matvec: Callable[[np.ndarray], np.ndarray], n: int,
                   shift: ShiftOptions, beyond: float = 0.0,
                   ladder: Sequence[float] = ()) -> list[float]:
    """Return the shifts that replace ``ladder`` (those left) after the indefinite ``report``.

    The estimate ``theta_min`` of the operator ``matvec`` of order ``n``
    (:func:`lowest_ritz_value`) is made for a solve's first iteration (``beyond`` = 0) and for
    isolated extra negative pivots (:func:`is_isolated`). Isolated ones with ``|theta_min| >
    beyond`` restart: ``shift.max_shifts`` shifts from ``MARGIN |theta_min|``, growing by
    ``shift.growth`` (``beyond`` > 0 restarts only for an outlier, module doc). Otherwise the
    ladder goes on without its rungs that the estimate proves indefinite
    (:func:`proven_indefinite`): the same shift is accepted at fewer factorisations. Empty:
    keep the ladder as it is.
    """
    isolated = is_isolated(report.negative_pivots, report.expected_negative)
    if not report.indefinite or not (isolated or beyond == 0.0):
        return []
    theta = lowest_ritz_value(matvec, n)
    if not theta < 0.0:
        return []
    if isolated and -theta > beyond:
        return restart_shifts(theta, shift.growth, shift.max_shifts)
    skipped = proven_indefinite(ladder, theta)
    return [float(t) for t in ladder[skipped:]] if 0 < skipped < len(ladder) else []
