"""The shift ladder restarted from a Lanczos estimate, on matrices with known spectra."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from solvers.inertia_shift import (
    ISOLATED_NEGATIVES,
    MARGIN,
    OUTLIER,
    is_isolated,
    lowest_ritz_value,
    proven_indefinite,
    restart_ladder,
    restart_shifts,
)
from solvers.linear import (
    LinearSolverOptions,
    ShiftOptions,
    SparseDirectSolver,
    factorize_with_shift,
)


def known_spectrum(eigenvalues: np.ndarray, seed: int = 0) -> sp.csr_matrix:
    """``Q diag(eigenvalues) Q^T`` with a random orthogonal Q (dense, stored sparse)."""
    q, _ = np.linalg.qr(np.random.default_rng(seed).standard_normal((eigenvalues.size,) * 2))
    return sp.csr_matrix((q * eigenvalues) @ q.T)


ISOLATED = np.concatenate([[-50.0, -20.0], np.linspace(1.0, 100.0, 118)])
"""Two isolated negative eigenvalues far below the ladder's first rungs."""


def test_ritz_value_bounds_and_finds_an_isolated_minimum():
    a = known_spectrum(ISOLATED)
    theta = lowest_ritz_value(lambda v: a @ v, a.shape[0])
    assert theta >= ISOLATED.min() - 1e-9  # interlacing: never below lambda_min
    assert theta == pytest.approx(-50.0, rel=1e-3)


@pytest.mark.parametrize("seed", range(5))
def test_ritz_value_never_undercuts_lambda_min_on_a_dense_negative_spectrum(seed):
    spectrum = np.random.default_rng(seed).uniform(-10.0, 10.0, 200)
    a = known_spectrum(spectrum, seed)
    theta = lowest_ritz_value(lambda v: a @ v, a.shape[0], steps=10)
    assert spectrum.min() - 1e-9 <= theta < 0


def count_factorisations(a: sp.csr_matrix, restart: bool) -> tuple[int, float]:
    """Factorisations of the ladder from 0 (growth 10) until A + tau I is SPD; accepted tau."""
    solver = SparseDirectSolver(a, LinearSolverOptions(symmetric="ldlt"))
    shift = ShiftOptions(growth=10.0, max_shifts=14)
    scale = float(np.mean(np.abs(a.diagonal())))

    def again(report, ladder):
        return restart_ladder(report, lambda v: a @ v, a.shape[0], shift, ladder=ladder)

    reports = factorize_with_shift(lambda tau: solver.factorize(a, tau), scale, shift,
                                   restart=again if restart else None)
    assert reports[-1].usable_spd
    return len(reports), reports[-1].shift


def test_isolated_negatives_need_two_factorisations_instead_of_the_ladder():
    a = known_spectrum(ISOLATED)
    ladder, tau_ladder = count_factorisations(a, restart=False)
    restarted, tau = count_factorisations(a, restart=True)
    print(f"ladder {ladder} factorisations (tau {tau_ladder:.3g}), restarted {restarted} "
          f"(tau {tau:.3g})")
    assert restarted == 2 and ladder >= 6
    assert 50.0 < tau <= MARGIN * 50.0 * (1 + 1e-3)  # just above |lambda_min|


@pytest.mark.parametrize("lowest", [-30.0, -3.0e3, -0.05])
def test_a_dense_negative_spectrum_keeps_the_ladders_shift_at_fewer_factorisations(lowest):
    """Many negative eigenvalues down to ``lowest``: the ladder's own accepted shift (no
    restart), without the rungs below ``|theta_min|``, which cannot pass: 2 factorisations
    instead of 9 when the estimate is sharp, 3 instead of 6 when it is not (-0.05)."""
    spectrum = np.concatenate([np.linspace(lowest, lowest / 30.0, 4 * ISOLATED_NEGATIVES),
                               np.linspace(1.0, 100.0, 100)])
    a = known_spectrum(spectrum)
    (ladder, tau_ladder), (skipped, tau) = (count_factorisations(a, restart=r)
                                            for r in (False, True))
    theta = lowest_ritz_value(lambda v: a @ v, a.shape[0])
    rungs = ShiftOptions(growth=10.0).schedule(float(np.mean(np.abs(a.diagonal()))))
    print(f"lambda_min {lowest}: theta_min {theta:.4g}; ladder {ladder} factorisations, "
          f"{skipped} without the proven rungs; tau {tau_ladder:.4g} / {tau:.4g}")
    assert tau == tau_ladder > -lowest
    assert skipped == ladder - proven_indefinite(rungs, theta) < ladder


def test_proven_indefinite_counts_the_rungs_below_the_estimate():
    ladder = [0.1, 1.0, 10.0, 100.0]
    assert proven_indefinite(ladder, -50.0) == 3
    assert proven_indefinite(ladder, -10.0 * (1 + 1e-4)) == 2  # within the round-off slack
    assert proven_indefinite(ladder, -0.05) == 0 and proven_indefinite(ladder, 1.0) == 0


def test_is_isolated_and_restart_shifts():
    assert is_isolated(60 + 4, 60) and not is_isolated(60, 60)
    assert not is_isolated(60 + ISOLATED_NEGATIVES + 1, 60) and not is_isolated(None, 0)
    assert restart_shifts(0.5, 10.0, 3) == []
    assert restart_shifts(-2.0, 10.0, 3) == pytest.approx([2 * MARGIN, 20 * MARGIN, 200 * MARGIN])


def restarted_after(a: sp.csr_matrix, tau: float, floor: float) -> list[float]:
    """The restart a later iteration gets after an indefinite attempt at ``tau`` (or none)."""
    solver = SparseDirectSolver(a, LinearSolverOptions(symmetric="ldlt"))
    report = solver.factorize(a, tau)
    assert report.indefinite
    return restart_ladder(report, lambda v: a @ v, a.shape[0], ShiftOptions(growth=10.0),
                          beyond=OUTLIER * max(tau, floor))


def test_a_later_iteration_restarts_only_for_an_outlier_beyond_its_attempt():
    """An eigenvalue 1e4 below a spectrum whose ladder works at tau ~ 1 (a hinge across a
    sliver) restarts the ladder just above it; a buckling probe that fails by a rung (the
    same spectrum without the outlier, lambda_min -2 against an attempt at 1) keeps the
    ladder, as does any attempt whose shift is within 1/OUTLIER of the outlier."""
    soft = np.concatenate([[-2.0], np.linspace(1.0, 100.0, 119)])
    spike = np.concatenate([[-1.0e4], soft[1:]])
    shifts = restarted_after(known_spectrum(spike), 1.0, 1e-6)
    print(f"outlier -1e4 after an attempt at 1: restart at {shifts[0]:.4g}")
    assert 1.0e4 < shifts[0] <= MARGIN * 1.0e4 * (1 + 1e-3)
    assert restarted_after(known_spectrum(soft), 1.0, 1e-6) == []
    assert restarted_after(known_spectrum(spike), 200.0, 1e-6) == []  # 1e4 < OUTLIER * 200
    assert restarted_after(known_spectrum(spike), 0.0, 200.0) == []   # the floor for tau = 0


def test_a_later_iteration_with_a_dense_negative_spectrum_makes_no_estimate():
    """A buckling probe's many negative pivots past the first iteration: the ladder as it is,
    without the cost of a Lanczos estimate."""
    spectrum = np.concatenate([np.linspace(-30.0, -1.0, 4 * ISOLATED_NEGATIVES),
                               np.linspace(1.0, 100.0, 100)])
    a = known_spectrum(spectrum)
    report = SparseDirectSolver(a, LinearSolverOptions(symmetric="ldlt")).factorize(a, 0.5)
    products = []

    def counted(v):
        products.append(1)
        return a @ v

    assert restart_ladder(report, counted, a.shape[0], ShiftOptions(growth=10.0),
                          beyond=OUTLIER, ladder=[5.0, 50.0]) == [] and not products
    assert restart_ladder(report, counted, a.shape[0], ShiftOptions(growth=10.0),
                          ladder=[5.0, 50.0]) == [50.0] and products  # the first iteration
