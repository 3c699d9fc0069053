"""Measurements on wrinkled surfaces: dominant wavelength and element-boundary artefacts.

Wavelength. A wrinkled skin compressed along an axis ``s`` has a height
profile ``z(s)`` (out-of-plane displacement relative to the smooth surface it sits on). Its
dominant wavelength is the maximiser of the windowed periodogram averaged over lines
``l`` parallel to the axis,

    P(f) = mean_l |sum_j w_j W(s_j) z~_j exp(-2 pi i f s_j)|^2,

where ``z~`` is the profile with its least-squares linear trend removed, ``W`` a Hann window
over the line's extent and ``w_j`` trapezoid quadrature weights of the (possibly irregular)
sample positions, so ``P`` approximates the continuous Fourier transform of each line
without resampling. The sum is evaluated at any ``f`` (a non-uniform DFT), so the peak is
first located on a grid ``oversampling`` times finer than the natural resolution ``1/span``
(the role of zero padding) and then refined by a bounded scalar maximisation of ``P``
(continuous peak interpolation; Quinn 1994 discusses the bias of such estimators, which the
Hann window keeps small for a few periods). The amplitude is that of the least-squares
sinusoid ``a cos 2 pi f s + b sin 2 pi f s`` (plus a linear trend) at the refined frequency,
root-mean-square over the lines.

Element-boundary artefacts ( Remillard & Kry 2013 use a quadratic interior
so that wrinkles do not seed along coarse element boundaries). For shell samples (vertices
with lumped areas, or hinges with their areas ``(A1 + A2) / 3``, :func:`hinge_energies`)
with an energy density ``e_i``, area ``A_i`` and distance ``d_i`` to the nearest edge of the
coarse boundary triangles, the band of width ``delta`` holds the energy fraction
``F_E = sum_{d_i < delta} e_i A_i / sum_i e_i A_i`` and the area fraction
``F_A = sum_{d_i < delta} A_i / sum_i A_i``; the ratio ``F_E / F_A`` is 1 when the energy
ignores the coarse edges and >> 1 when it concentrates on them. The Pearson correlation of
``e_i`` with ``d_i`` is reported beside it (negative: energy near the edges).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy.optimize import minimize_scalar

from meshes.errors import InputError
from models.shell.bending import hinge_weights
from models.shell.hinge_angle import hinge_angles
from models.shell.rest import vertex_areas, vertex_normals
from models.shell.topology import unique_edges

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]


@dataclass(frozen=True)
class SpectrumOptions:
    """How the dominant wavelength of a height profile is searched.

    Attributes:
        oversampling: frequency grid step is ``1 / (oversampling * span)`` (span = longest
            line extent) [-], >= 1; plays the role of zero padding.
        min_periods: longest wavelength searched is ``span / min_periods`` [-], > 0 (a
            wavelength comparable to the line length is a trend, not a wrinkle).
        min_points: lines with fewer samples are ignored [-], >= 4.
        window: ``"hann"`` or ``"none"`` (rectangular).

    """

    oversampling: int = 16
    min_periods: float = 1.5
    min_points: int = 8
    window: str = "hann"

    def __post_init__(self) -> None:
        if self.oversampling < 1:
            raise InputError(f"oversampling: must be >= 1, got {self.oversampling}")
        if not (np.isfinite(self.min_periods) and self.min_periods > 0.0):
            raise InputError(f"min_periods: must be > 0, got {self.min_periods}")
        if self.min_points < 4:
            raise InputError(f"min_points: must be >= 4, got {self.min_points}")
        if self.window not in ("hann", "none"):
            raise InputError(f"window: expected 'hann' or 'none', got {self.window!r}")


@dataclass(frozen=True)
class Wavelength:
    """The dominant wavelength of a height profile.

    Attributes:
        wavelength: dominant wavelength [unit of s].
        amplitude: root-mean-square over lines of the fitted sinusoid's amplitude [unit of z].
        lines: number of lines used.
        samples: number of samples used.
        span: longest line extent [unit of s].
        rms: root-mean-square of the detrended heights [unit of z].

    """

    wavelength: float
    amplitude: float
    lines: int
    samples: int
    span: float
    rms: float


@dataclass(frozen=True)
class _Line:
    """One detrended, windowed line: positions, weighted heights and raw heights."""

    s: FloatArray
    weighted: FloatArray
    z: FloatArray


def detrend(s: FloatArray, z: FloatArray) -> FloatArray:
    """Return ``z`` minus its least-squares line ``a + b s``."""
    coeffs = np.polyfit(s, z, 1)
    return z - np.polyval(coeffs, s)


def trapezoid_weights(s: FloatArray) -> FloatArray:
    """Quadrature weights of sorted positions ``s``: half the distance to both neighbours."""
    gaps = np.diff(s)
    w = np.zeros_like(s)
    w[:-1] += 0.5 * gaps
    w[1:] += 0.5 * gaps
    return w


def window_values(s: FloatArray, kind: str) -> FloatArray:
    """Hann window ``sin^2(pi (s - s0) / (s1 - s0))`` over the extent of ``s`` (or ones)."""
    if kind == "none":
        return np.ones_like(s)
    span = max(float(s.max() - s.min()), 1e-300)
    return np.sin(np.pi * (s - s.min()) / span) ** 2


def _make_line(s: FloatArray, z: FloatArray, window: str) -> _Line:
    """Sort, detrend and weight one line's samples."""
    order = np.argsort(s, kind="stable")
    s_sorted, z_sorted = s[order], detrend(s[order], z[order])
    weights = trapezoid_weights(s_sorted) * window_values(s_sorted, window)
    return _Line(s_sorted, weights * z_sorted, z_sorted)


def split_lines(s: FloatArray, z: FloatArray, labels: IntArray | None,
                options: SpectrumOptions) -> list[_Line]:
    """Group samples by line label (all one line when ``labels`` is None), drop short lines."""
    labels = np.zeros(s.shape, dtype=np.int64) if labels is None else np.asarray(labels)
    lines = []
    for label in np.unique(labels):
        mask = labels == label
        if np.count_nonzero(mask) >= options.min_points and np.ptp(s[mask]) > 0.0:
            lines.append(_make_line(s[mask], z[mask], options.window))
    return lines


def power(lines: list[_Line], frequency: float) -> float:
    """Mean over lines of ``|sum_j w_j W_j z~_j exp(-2 pi i f s_j)|^2`` (module docstring)."""
    total = 0.0
    for line in lines:
        total += abs(np.sum(line.weighted * np.exp(-2j * np.pi * frequency * line.s))) ** 2
    return total / len(lines)


def power_spectrum(lines: list[_Line], frequencies: FloatArray) -> FloatArray:
    """:func:`power` on a grid of frequencies (vectorised over lines' samples)."""
    out = np.zeros(frequencies.shape)
    for line in lines:
        phase = np.exp(-2j * np.pi * np.outer(frequencies, line.s))
        out += np.abs(phase @ line.weighted) ** 2
    return out / len(lines)


def median_gap(lines: list[_Line], span: float) -> float:
    """Median gap between *distinct* sample positions of the lines.

    Repeated positions (e.g. several mesh rows in one line) do not count.
    """
    gaps = np.concatenate([np.diff(np.unique(line.s)) for line in lines])
    gaps = gaps[gaps > 1e-9 * span]
    if gaps.size == 0:
        raise InputError("profile: the samples of every line share one position")
    return float(np.median(gaps))


def frequency_grid(lines: list[_Line], options: SpectrumOptions) -> FloatArray:
    """Frequencies from ``min_periods / span`` to the Nyquist frequency of the median gap."""
    span = max(float(np.ptp(line.s)) for line in lines)
    gap = median_gap(lines, span)
    f_max, f_min = 0.5 / gap, options.min_periods / span
    if f_min >= f_max:
        raise InputError(f"profile: too few samples per line for min_periods = "
                         f"{options.min_periods} (span {span:.3g}, median gap {gap:.3g})")
    step = 1.0 / (options.oversampling * span)
    return np.arange(f_min, f_max + step, step)


def refine_peak(lines: list[_Line], grid: FloatArray, k: int) -> float:
    """Maximise :func:`power` on the grid cell around the grid's peak ``grid[k]``."""
    lo, hi = grid[max(k - 1, 0)], grid[min(k + 1, grid.size - 1)]
    if hi <= lo:
        return float(grid[k])
    result = minimize_scalar(lambda f: -power(lines, f), bounds=(lo, hi), method="bounded",
                             options={"xatol": 1e-6 * (hi - lo)})
    return float(result.x)


def sinusoid_amplitude(line: _Line, frequency: float) -> float:
    """Amplitude ``sqrt(a^2 + b^2)`` of the least-squares ``a cos + b sin`` (+ line) fit."""
    arg = 2.0 * np.pi * frequency * line.s
    basis = np.column_stack([np.cos(arg), np.sin(arg), np.ones_like(arg), line.s])
    coeffs = np.linalg.lstsq(basis, line.z, rcond=None)[0]
    return float(np.hypot(coeffs[0], coeffs[1]))


def dominant_wavelength(s: npt.ArrayLike, z: npt.ArrayLike, labels: npt.ArrayLike | None = None,
                        options: SpectrumOptions | None = None) -> Wavelength:
    """Dominant wavelength and amplitude of heights ``z`` at positions ``s`` (module doc).

    Args:
        s: ``(n,)`` positions along the compression axis (any order, irregular spacing).
        z: ``(n,)`` heights (out-of-plane displacement).
        labels: ``(n,)`` integer line of each sample (lines parallel to the axis); ``None``
            treats all samples as one line.
        options: search options.

    Returns:
        The :class:`Wavelength`.

    Raises:
        InputError: shapes differ, non-finite values, or no line with enough samples.

    """
    opts = options or SpectrumOptions()
    s_arr, z_arr = np.asarray(s, dtype=np.float64), np.asarray(z, dtype=np.float64)
    if s_arr.ndim != 1 or s_arr.shape != z_arr.shape:
        raise InputError(f"profile: s and z must be 1-D of one shape, got {s_arr.shape} "
                         f"and {z_arr.shape}")
    if not (np.all(np.isfinite(s_arr)) and np.all(np.isfinite(z_arr))):
        raise InputError("profile: s and z must be finite")
    lab = None if labels is None else np.asarray(labels, dtype=np.int64)
    lines = split_lines(s_arr, z_arr, lab, opts)
    if not lines:
        raise InputError(f"profile: no line has {opts.min_points} or more samples")
    grid = frequency_grid(lines, opts)
    f = refine_peak(lines, grid, int(np.argmax(power_spectrum(lines, grid))))
    amps = np.array([sinusoid_amplitude(line, f) for line in lines])
    heights = np.concatenate([line.z for line in lines])
    return Wavelength(wavelength=1.0 / f, amplitude=float(np.sqrt(np.mean(amps**2))),
                      lines=len(lines), samples=int(heights.size),
                      span=max(float(np.ptp(line.s)) for line in lines),
                      rms=float(np.sqrt(np.mean(heights**2))))


def line_labels(t: npt.ArrayLike, width: float) -> IntArray:
    """Line label of each sample: its transverse coordinate ``t`` binned by ``width``."""
    t_arr = np.asarray(t, dtype=np.float64)
    if not (np.isfinite(width) and width > 0.0):
        raise InputError(f"width: must be > 0, got {width}")
    return np.floor((t_arr - t_arr.min()) / width).astype(np.int64)


# --------------------------------------------------------------------------------------------
# Shell surfaces


def normal_heights(x: FloatArray, y: FloatArray, faces: IntArray) -> FloatArray:
    """Out-of-plane displacement ``(x - y) . n_y`` of the shell from its target ``y``."""
    return np.einsum("ij,ij->i", x - y, vertex_normals(y, faces))


def face_vertices(rest: FloatArray, normals: FloatArray, direction: npt.ArrayLike,
                  margin: float, cos_min: float = 0.99) -> npt.NDArray[np.bool_]:
    """Vertices of the flat face whose outward rest normal is ``direction``.

    A vertex belongs when its rest normal (``normals``, unit) is within ``acos(cos_min)`` of
    ``direction`` and it lies more than ``margin`` inside the face's bounding box along the
    coordinate axes across ``direction`` (away from the block's edges and corners, whose
    normals are averaged). Empty when no vertex has that normal.
    """
    d = np.asarray(direction, dtype=np.float64)
    d = d / np.linalg.norm(d)
    on_face = normals @ d >= cos_min
    if not np.any(on_face):
        return on_face
    inside = on_face.copy()
    for axis in np.flatnonzero(np.abs(d) < 0.5):
        lo, hi = rest[on_face, axis].min(), rest[on_face, axis].max()
        inside &= (rest[:, axis] > lo + margin) & (rest[:, axis] < hi - margin)
    return inside


def lateral_lines(rest: FloatArray, faces: IntArray, axis: int, margin: float,
                  line_width: float) -> tuple[npt.NDArray[np.bool_], IntArray]:
    """Vertices of the axis-aligned flat faces parallel to ``axis`` and their line labels.

    For a block compressed along coordinate ``axis``, its (up to four) lateral faces have
    outward normals ``+-e_k``, ``k != axis``; on each, lines parallel to ``axis`` are bands
    of width ``line_width`` in the face's other in-plane coordinate (distinct labels per
    face). Vertices within ``margin`` of a face's border are left out.

    Raises:
        InputError: no lateral face found.

    """
    normals = vertex_normals(rest, faces)
    mask = np.zeros(rest.shape[0], dtype=bool)
    labels = np.zeros(rest.shape[0], dtype=np.int64)
    offset = 0
    for k in (c for c in range(3) if c != axis):
        other = 3 - axis - k
        for sign in (1.0, -1.0):
            on = face_vertices(rest, normals, sign * np.eye(3)[k], margin)
            if np.any(on):
                labels[on] = line_labels(rest[on, other], line_width) + offset
                mask |= on
                offset = int(labels[on].max()) + 1
    if not np.any(mask):
        raise InputError(f"axis: no flat face parallel to axis {axis} with vertices "
                         f"{margin} inside its border")
    return mask, labels


def shell_wavelength(rest: FloatArray, faces: IntArray, heights: FloatArray, axis: int,
                     margin: float, line_width: float,
                     options: SpectrumOptions | None = None) -> Wavelength:
    """Dominant wavelength of the shell ``heights`` on the lateral faces along ``axis``.

    Positions are rest (material) coordinates; see :func:`lateral_lines`.
    """
    mask, labels = lateral_lines(rest, faces, axis, margin, line_width)
    return dominant_wavelength(rest[mask, axis], heights[mask], labels[mask], options)


# --------------------------------------------------------------------------------------------
# Element-boundary artefacts


@dataclass(frozen=True)
class ArtefactReport:
    """How much energy sits near the coarse mesh's boundary edges.

    Attributes:
        band: band half-width delta around the coarse edges [m].
        energy_fraction: ``F_E``, energy fraction in the band [-].
        area_fraction: ``F_A``, area fraction of the band [-].
        ratio: ``F_E / F_A`` (1 = no artefact) [-].
        correlation: Pearson correlation of energy density with edge distance [-].
        samples: samples (vertices or hinges) measured.

    """

    band: float
    energy_fraction: float
    area_fraction: float
    ratio: float
    correlation: float
    samples: int


def segment_distances(points: FloatArray, a: FloatArray, b: FloatArray,
                      chunk: int = 2048) -> FloatArray:
    """Distance of every point to the nearest of the segments ``[a_k, b_k]`` (n,).

    Clamped projection ``t = clip((p - a).(b - a) / |b - a|^2, 0, 1)``; processed in chunks
    of ``chunk`` points (memory ``chunk x segments``).
    """
    ab = b - a
    len2 = np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-300)
    out = np.empty(points.shape[0])
    for start in range(0, points.shape[0], chunk):
        p = points[start:start + chunk, None, :] - a[None, :, :]
        t = np.clip(np.einsum("pkj,kj->pk", p, ab) / len2, 0.0, 1.0)
        d = p - t[:, :, None] * ab[None, :, :]
        out[start:start + chunk] = np.sqrt(np.einsum("pkj,pkj->pk", d, d).min(axis=1))
    return out


def coarse_edge_distances(points: FloatArray, coarse_vertices: FloatArray,
                          coarse_faces: IntArray) -> FloatArray:
    """Distance of each point to the nearest edge of the coarse boundary triangles."""
    edges = unique_edges(coarse_faces)
    return segment_distances(points, coarse_vertices[edges[:, 0]], coarse_vertices[edges[:, 1]])


@dataclass(frozen=True)
class HingeEnergies:
    """Bending energy per hinge, where it sits and the area it stands for.

    Attributes:
        energy: ``(Hn,)`` hinge energies ``k_B w_h (theta_h - theta0_h)^2`` [J].
        midpoints: ``(Hn, 3)`` rest midpoints of the hinge edges [m].
        areas: ``(Hn,)`` hinge areas ``(A1 + A2) / 3 = |e0|^2 / w_h`` (they partition the
            area of a closed surface) [m^2].
        edge_vertices: ``(Hn, 2)`` the hinge edge's vertices.

    """

    energy: FloatArray
    midpoints: FloatArray
    areas: FloatArray
    edge_vertices: IntArray

    @property
    def density(self) -> FloatArray:
        """Energy per unit area of each hinge [J/m^2]."""
        return self.energy / self.areas


def hinge_energies(x: FloatArray, rest: FloatArray, hinges: IntArray,
                   k_B: float) -> HingeEnergies:
    """Discrete-shell hinge energies (Grinspun et al. 2003) of positions ``x`` over ``rest``.

    ``E_h = k_B w_h (theta_h(x) - theta_h(X))^2`` with ``w_h = 3 |e0|^2 / (A1 + A2)``, the
    terms of :mod:`models.shell.bending` (same angle and weight functions).
    """
    weights = hinge_weights(rest, hinges)
    dtheta = hinge_angles(x, hinges) - hinge_angles(rest, hinges)
    e0 = rest[hinges[:, 1]] - rest[hinges[:, 0]]
    return HingeEnergies(energy=k_B * weights * dtheta**2,
                         midpoints=0.5 * (rest[hinges[:, 0]] + rest[hinges[:, 1]]),
                         areas=np.einsum("ij,ij->i", e0, e0) / weights,
                         edge_vertices=np.ascontiguousarray(hinges[:, :2]))


def edge_band_report(distance: npt.ArrayLike, density: npt.ArrayLike, area: npt.ArrayLike,
                     band: float) -> ArtefactReport:
    """Energy vs area fraction within ``band`` of the coarse edges (module docstring).

    Args:
        distance: ``(n,)`` distance of each sample (vertex or hinge) to the nearest coarse edge.
        density: ``(n,)`` energy density per unit area (>= 0).
        area: ``(n,)`` area each sample stands for (> 0).
        band: band half-width delta (> 0).

    Raises:
        InputError: shapes differ, band <= 0, or zero total energy or area.

    """
    d, e, a = (np.asarray(v, dtype=np.float64) for v in (distance, density, area))
    if not (d.shape == e.shape == a.shape and d.ndim == 1):
        raise InputError("artefacts: distance, density and area must be 1-D of one shape")
    if not (np.isfinite(band) and band > 0.0):
        raise InputError(f"band: must be > 0, got {band}")
    energy, near = e * a, d < band
    if not (energy.sum() > 0.0 and a.sum() > 0.0):
        raise InputError("artefacts: total energy and area must be > 0")
    f_e, f_a = float(energy[near].sum() / energy.sum()), float(a[near].sum() / a.sum())
    corr = float(np.corrcoef(e, d)[0, 1]) if np.ptp(e) > 0 and np.ptp(d) > 0 else 0.0
    return ArtefactReport(band=float(band), energy_fraction=f_e, area_fraction=f_a,
                          ratio=f_e / f_a if f_a > 0 else float("nan"), correlation=corr,
                          samples=int(d.size))


__all__ = ["ArtefactReport", "HingeEnergies", "SpectrumOptions", "Wavelength",
           "coarse_edge_distances", "hinge_energies",
           "dominant_wavelength", "edge_band_report", "face_vertices", "lateral_lines",
           "line_labels", "normal_heights", "segment_distances", "shell_wavelength",
           "unique_edges", "vertex_areas"]
