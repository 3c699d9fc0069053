"""Mesh convergence of the hyperelastic solve on a manufactured solution (P1 and P2)."""

from __future__ import annotations

import numpy as np
import pytest

from validation.manufactured import l2_error


@pytest.mark.parametrize(("degree", "sizes"), [(1, (4, 8, 16)), (2, (2, 4, 8))])
def test_manufactured_convergence_rate(degree, sizes):
    errors = [l2_error(n, degree) for n in sizes]
    h = 1.0 / np.asarray(sizes, dtype=float)
    rate = np.polyfit(np.log(h), np.log(errors), 1)[0]
    shown = ", ".join(f"{e:.3e}" for e in errors)
    print(f"P{degree}: n={sizes} L2 errors=[{shown}] fitted rate={rate:.3f}")
    assert rate > degree + 0.8
