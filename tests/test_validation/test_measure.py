"""The wavelength measurement (validation.measure) on synthetic profiles with known answers."""

from __future__ import annotations

import numpy as np
import pytest

from meshes.errors import InputError
from validation.measure import SpectrumOptions, dominant_wavelength, line_labels


@pytest.mark.parametrize("wavelength", [0.0213, 0.037, 0.0611])
def test_uniform_sinusoid_with_non_integer_periods(wavelength):
    """One line of 0.2 m sampled every 1 mm (3.3 .. 9.4 periods, none an integer), linear
    trend added: the wavelength comes back within 0.5 % and the amplitude within 2 %
    (measured errors printed)."""
    s = np.arange(0.0, 0.2, 1e-3)
    z = 2e-4 * np.sin(2 * np.pi * s / wavelength + 0.4) + 0.01 * s + 3e-3
    result = dominant_wavelength(s, z)
    err = result.wavelength / wavelength - 1.0
    print(f"lambda {wavelength}: rel. error {err:.2e}, amplitude {result.amplitude:.4e}")
    assert abs(err) < 1e-3  # measured <= 2.4e-4
    assert result.amplitude == pytest.approx(2e-4, rel=0.02)


def test_irregular_points_in_lines_with_noise():
    """2000 random points on a 0.15 x 0.04 face, 8 lines, height A sin(2 pi s / lambda)
    plus 30 % white noise: the wavelength within 2 %, the amplitude within 10 %."""
    rng = np.random.default_rng(3)
    lam, amp = 0.0217, 1e-4
    s, t = rng.uniform(0, 0.15, 2000), rng.uniform(0, 0.04, 2000)
    z = amp * np.sin(2 * np.pi * s / lam + 1.0) + 0.3 * amp * rng.standard_normal(2000)
    result = dominant_wavelength(s, z, line_labels(t, 0.005))
    print("irregular:", result)
    assert result.lines == 8 and result.samples == 2000
    assert result.wavelength == pytest.approx(lam, rel=0.02)
    assert result.amplitude == pytest.approx(amp, rel=0.1)


def test_error_falls_with_the_number_of_periods():
    """Same noisy irregular sinusoid on lines of 3, 6, 12, 24 periods: the wavelength error
    (mean over 5 noise draws) falls with the length (fitted log-log slope < -0.5; an
    estimator limited by leakage/noise gives ~ -1 .. -1.5)."""
    lam, errors = 1.0, []
    periods = np.array([3.0, 6.0, 12.0, 24.0])
    for n in periods:
        errs = []
        for seed in range(5):
            rng = np.random.default_rng(seed)
            s = np.sort(rng.uniform(0, n * lam, int(20 * n)))
            z = np.sin(2 * np.pi * s / lam) + 0.5 * rng.standard_normal(s.size)
            errs.append(abs(dominant_wavelength(s, z).wavelength / lam - 1.0))
        errors.append(np.mean(errs))
    slope = np.polyfit(np.log(periods), np.log(errors), 1)[0]
    print("periods", periods, "errors", errors, "slope", slope)
    assert slope < -0.5
    assert errors[-1] < 2e-3


def test_two_sinusoids_pick_the_stronger():
    """A 3x stronger component at 0.03 beats a weaker one at 0.011."""
    s = np.linspace(0, 0.3, 700)
    z = 3.0 * np.sin(2 * np.pi * s / 0.03) + np.sin(2 * np.pi * s / 0.011)
    assert dominant_wavelength(s, z).wavelength == pytest.approx(0.03, rel=5e-3)


def test_bad_input_is_refused():
    with pytest.raises(InputError, match="profile"):
        dominant_wavelength(np.arange(5.0), np.arange(4.0))
    with pytest.raises(InputError, match="no line"):
        dominant_wavelength(np.arange(5.0), np.arange(5.0))
    with pytest.raises(InputError, match="finite"):
        dominant_wavelength(np.arange(10.0), np.full(10, np.nan))
    with pytest.raises(InputError, match="oversampling"):
        SpectrumOptions(oversampling=0)


def test_lateral_faces_of_a_subdivided_box():
    """A 0.08 x 0.02 x 0.02 box surface (12 triangles, 4 linear subdivision levels) with
    heights A sin(2 pi x / 13 mm) on every vertex: lateral_lines finds the 4 lateral faces
    (not the end faces x = 0, 0.08) and shell_wavelength returns 13 mm within 1 %."""
    from models.embedding.subdivision import SubdivisionOptions, subdivide
    from models.embedding.surface import boundary_surface
    from validation.measure import lateral_lines, shell_wavelength

    corners = np.array([[x, y, z] for x in (0, 0.08) for y in (0, 0.02) for z in (0, 0.02)])
    tets = np.array([[0, 1, 3, 7], [0, 1, 5, 7], [0, 2, 3, 7], [0, 2, 6, 7], [0, 4, 5, 7],
                     [0, 4, 6, 7]], dtype=np.int64)
    surface = boundary_surface(corners, tets)
    sub = subdivide(surface.vertices, surface.faces, SubdivisionOptions(levels=4))
    rest, faces = sub.vertices, sub.faces
    mask, labels = lateral_lines(rest, faces, 0, margin=0.002, line_width=0.003)
    assert not np.any(mask & ((rest[:, 0] < 1e-9) | (rest[:, 0] > 0.08 - 1e-9)))
    assert np.unique(labels[mask]).size >= 4 * 4
    heights = 1e-4 * np.sin(2 * np.pi * rest[:, 0] / 0.013)
    result = shell_wavelength(rest, faces, heights, 0, margin=0.002, line_width=0.003)
    print("box:", result)
    assert result.wavelength == pytest.approx(0.013, rel=0.01)
    assert result.amplitude == pytest.approx(1e-4, rel=0.05)
