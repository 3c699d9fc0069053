"""The shifted-Hessian schedule: fewer wasted factorisations than session 1's, same minimum."""

from __future__ import annotations

import numpy as np
import pytest
import shellcases

import solvers.linear as linear
from meshes.shells import grid_plate
from models.shell.energy import ShellEnergy
from solvers.linear import ShiftOptions, shift_candidates
from solvers.shell_newton import ShellNewtonOptions, ShellSolveReport, minimize


def session1_candidates(diagonal_scale: float, shift: ShiftOptions, start: float = 0.0,
                        zero_first: bool | None = None) -> list[float]:
    """Session 1's schedule: always 0 first, then ``max(tau_0, tau_prev / 10) 10^j``."""
    del zero_first  # session 1 always tried the unshifted matrix first
    return [0.0, *shift.schedule(diagonal_scale, start).tolist()]


def wrinkle_case() -> tuple[ShellEnergy, np.ndarray]:
    """The session-1 case: 20x20 plate, 20 clusters, 7 % compression, exact Hessian."""
    pts, faces = grid_plate(20, 20, 1.0, 1.0)
    return shellcases.compressed_plate(pts, faces, clusters=20)


def solve(energy: ShellEnergy, x0: np.ndarray) -> tuple[np.ndarray, ShellSolveReport]:
    """Exact-Hessian Newton to rtol 1e-9."""
    return minimize(energy, x0,  # type: ignore[arg-type]
                    ShellNewtonOptions(rtol=1e-9, hessian="exact"))


def test_fewer_factorisations_than_session1(monkeypatch: pytest.MonkeyPatch) -> None:
    energy, x0 = wrinkle_case()
    x_new, new = solve(energy, x0)
    monkeypatch.setattr(linear, "shift_candidates", session1_candidates)
    x_old, old = solve(energy, x0)
    for name, r in (("session-1 schedule", old), ("new schedule", new)):
        print(f"{name}: {r.iterations} its, {r.shifted_iterations} shifted, "
              f"{r.factorizations} factorisations ({r.factorizations - r.iterations} failed), "
              f"W = {r.energy:.12f}")
    assert old.converged and new.converged
    # measured: session 1 188 factorisations (109 failed) in 79 its; new 136 (56) in 80 its
    assert new.factorizations <= 0.8 * old.factorizations
    assert (new.factorizations - new.iterations) <= 0.6 * (old.factorizations - old.iterations)
    assert abs(new.energy - old.energy) <= 1e-10 * old.energy
    mirror = x_old * np.array([1.0, 1.0, -1.0])
    assert min(np.max(np.abs(x_new - x_old)), np.max(np.abs(x_new - mirror))) < 1e-6


def test_candidates_reuse_the_last_shift() -> None:
    shift = ShiftOptions(initial=1e-6, growth=10.0, max_shifts=3)
    assert shift_candidates(2.0, shift) == pytest.approx([0.0, 2e-6, 2e-5, 2e-4])
    # a start above tau_0 = 2e-6 skips the unshifted attempt unless asked for
    assert shift_candidates(2.0, shift, 1e-3) == pytest.approx([1e-3, 1e-2, 1e-1])
    assert shift_candidates(2.0, shift, 1e-3, zero_first=True) == pytest.approx(
        [0.0, 1e-3, 1e-2, 1e-1])
    # below tau_0 the schedule starts from tau_0 with the unshifted attempt first
    assert shift_candidates(2.0, shift, 1e-7) == pytest.approx([0.0, 2e-6, 2e-5, 2e-4])
