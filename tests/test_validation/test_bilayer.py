"""The plane-strain volumetric bilayer (validation/bilayer.py): set-up facts, flat response
below the critical strain, wrinkles above it at the theoretical wavelength."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from meshes.errors import InputError
from models.backend import MPI
from validation.bilayer import (
    Bilayer,
    BilayerOptions,
    mode_spacing,
    row_heights,
    run_bilayer,
)
from validation.measure import SpectrumOptions, dominant_wavelength

QUICK: dict[str, Any] = {"thickness": 4.7973e-4, "periods": 10.0, "elements_per_wavelength": 12,
         "substrate_layers": 12, "depth": 1.0, "steps": 5, "strain_factor": 1.3}
"""E_f / E_s = 1000, theory lambda = 20 mm, 10 wavelengths, coarse P2 mesh."""


def test_theory_numbers_and_mesh_rows():
    """lambda = 2 pi h (Ebar_f / 3 Ebar_s)^(1/3) = 20 mm for h = 0.48 mm;
    eps_c = 1/4 (3 Ebar_s / Ebar_f)^(2/3) = (pi h / lambda)^2 (the two formulas agree);
    rows: graded substrate ending at the interface, uniform film rows of h / 2."""
    o = BilayerOptions(**QUICK)
    assert o.wavelength == pytest.approx(0.02, rel=1e-4)
    assert o.critical_strain == pytest.approx((np.pi * o.thickness / o.wavelength) ** 2,
                                              rel=1e-12)
    rows = row_heights(o)
    assert rows[0] == 0.0 and rows[-1] == pytest.approx(o.substrate_depth + o.thickness)
    assert np.all(np.diff(rows) > 0)
    assert np.diff(rows)[-2:] == pytest.approx([o.thickness / 2] * 2)
    assert mode_spacing(o) == pytest.approx(0.05)


def test_below_critical_strain_stays_flat():
    """Compression to 0.5 eps_c from a bump of 1 % of h: the top stays flat: its height
    varies by less than 5 % of h (measured 0.2 %; the uniform Poisson rise of 10 % h is not
    a wrinkle)."""
    o = BilayerOptions(**{**QUICK, "periods": 4.0})
    bilayer = Bilayer(o, MPI.COMM_SELF)
    bilayer.solve_to(0.5 * o.critical_strain)
    _, w = bilayer.top_profile()
    print("ptp w / h below eps_c:", np.ptp(w) / o.thickness, "mean", w.mean() / o.thickness)
    assert np.ptp(w) < 0.05 * o.thickness


def test_wrinkles_at_the_theoretical_wavelength():
    """1.3 eps_c: wrinkles of amplitude > 10 % of h; the wavelength is an admissible roller
    mode 2 L / n within 10 % of theory (measured n = 19, 2 L / 19 = 1.053 lambda, where the
    formula's lambda is the mode n = 20; the mode spacing is 5 %)."""
    result = run_bilayer(BilayerOptions(**QUICK), MPI.COMM_SELF)
    measured = dominant_wavelength(result.top_x, result.top_w,
                                   options=SpectrumOptions(min_periods=2.0))
    error = measured.wavelength / result.theory - 1.0
    print(f"bilayer: {measured}, error {error:+.3%}, dofs {result.dofs}, "
          f"newton {result.newton_iterations}, wall {result.wall_time:.1f} s")
    assert measured.amplitude > 0.1 * 4.7973e-4
    assert abs(error) < 0.10
    n = 2 * 10.0 * result.theory / measured.wavelength  # the mode number, 2 L / lambda
    assert n == pytest.approx(round(n), abs=0.05)
    assert result.min_det_f > 0.9


def test_bad_options_are_refused():
    with pytest.raises(InputError, match="strain_factor"):
        BilayerOptions(strain_factor=0.9)
    with pytest.raises(InputError, match="imperfection_kind"):
        BilayerOptions(imperfection_kind="bump")
    with pytest.raises(InputError, match="substrate_nu"):
        BilayerOptions(substrate_nu=0.5)
