"""Clusters and H: spacing, coverage, Gaussian weights, physical sizing, full row rank."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
from scipy.sparse import csgraph

from meshes.errors import InputError
from meshes.shells import equilateral_plate, icosphere
from models.embedding import clusters as cl
from models.embedding.clusters import (
    ClusterOptions,
    build_clusters,
    edge_graph,
    smallest_singular_value,
    wrinkle_wavelength,
)


@pytest.fixture(scope="module")
def sphere():
    return icosphere(4)  # unit sphere, 2562 vertices


def centre_distances(v, f, centres):
    return csgraph.dijkstra(edge_graph(v, f), indices=centres)


@pytest.mark.parametrize("method", ["fps", "bfs"])
def test_spacing_and_coverage(sphere, method):
    v, f = sphere
    c = build_clusters(v, f, ClusterOptions(method=method, spacing=0.3))
    d = centre_distances(v, f, c.centres)
    pair = d[:, c.centres]
    assert pair[~np.eye(c.centres.size, dtype=bool)].min() >= 0.3  # centres >= r apart
    nearest = d.min(axis=0)
    assert nearest.max() < 0.3  # every vertex within r ...
    assert c.report.sigma == pytest.approx(2 * 0.3 / np.pi, rel=1e-15)
    assert nearest.max() < 2 * c.report.sigma  # ... so within 2 sigma
    assert c.report.uncovered == 0
    assert np.abs(np.asarray(c.H.sum(axis=1)).ravel() - 1.0).max() < 1e-14
    # nearest centre (ties on the symmetric sphere may go either way)
    np.testing.assert_allclose(d[c.partition, np.arange(v.shape[0])], nearest, rtol=1e-14)
    assert c.report.min_singular_value > 0.0
    print(method, c.report)


def test_weights_are_truncated_gaussians(sphere):
    v, f = sphere
    c = build_clusters(v, f, ClusterOptions(count=40, sigma=0.2))
    d = centre_distances(v, f, c.centres)
    expected = np.where(d < 0.4, np.exp(-d**2 / (2 * 0.2**2)), 0.0)
    expected /= expected.sum(axis=1, keepdims=True)
    np.testing.assert_allclose(c.H.toarray(), expected, rtol=0, atol=1e-15)
    assert c.H.nnz == np.count_nonzero(d < 0.4)  # supports overlap, sizes reported
    support = np.count_nonzero(d < 0.4, axis=1)
    assert (c.report.min_support, c.report.max_support) == (support.min(), support.max())
    assert c.report.mean_support == pytest.approx(support.mean(), rel=1e-15)


def test_explicit_count_fps(sphere):
    v, f = sphere
    c = build_clusters(v, f, ClusterOptions(count=50))
    assert c.H.shape == (50, v.shape[0])
    d = centre_distances(v, f, c.centres)
    pair = d[:, c.centres][~np.eye(50, dtype=bool)]
    assert pair.min() >= c.report.spacing  # the last selection distance bounds all pairs
    assert d.min(axis=0).max() <= c.report.spacing
    assert c.report.uncovered == 0
    assert c.report.sigma == pytest.approx(2 * c.report.spacing / np.pi, rel=1e-15)


def test_physical_sizing_matches_formula(sphere):
    h, E_f, nu_f, E_s, nu_s = 0.02, 2.0e6, 0.3, 1.0e4, 0.45
    ebar_f, ebar_s = E_f / (1 - nu_f**2), E_s / (1 - nu_s**2)
    lam = 2 * np.pi * h * (ebar_f / (3 * ebar_s)) ** (1 / 3)
    assert wrinkle_wavelength(h, E_f, nu_f, E_s, nu_s) == pytest.approx(lam, rel=1e-15)
    # equal Poisson ratios and E_f / E_s = 3000: lambda = 2 pi h * 10 exactly
    assert wrinkle_wavelength(1.0, 3.0e7, 0.3, 1.0e4, 0.3) == pytest.approx(20 * np.pi,
                                                                             rel=1e-14)
    v, f = sphere
    opts = ClusterOptions(skin_thickness=h, skin_E=E_f, skin_nu=nu_f, body_E=E_s, body_nu=nu_s)
    c = build_clusters(v, f, opts)
    assert c.report.spacing == pytest.approx(lam / 2, rel=1e-15)
    assert c.report.sigma == pytest.approx(lam / np.pi, rel=1e-15)
    assert 10 < c.report.count < v.shape[0] // 10  # clusters much coarser than the shell
    assert c.report.uncovered == 0 and c.report.min_singular_value > 0.0
    print("lambda", lam, c.report)


def test_full_row_rank_and_detector(sphere, monkeypatch):
    v, f = sphere
    c = build_clusters(v, f, ClusterOptions(count=60))
    dense = smallest_singular_value(c.H)
    monkeypatch.setattr(cl, "_DENSE_SVD_LIMIT", 0)  # the large-matrix (Lanczos) route
    lanczos = smallest_singular_value(c.H)
    assert dense > 0.0
    assert lanczos == pytest.approx(dense, rel=1e-6)
    duplicated = sp.vstack([c.H, c.H[:1]], format="csr")  # a repeated row: rank deficient
    assert smallest_singular_value(duplicated) < 1e-4 * dense  # Gram route: ~sqrt(eps) floor
    monkeypatch.setattr(cl, "_DENSE_SVD_LIMIT", 4_000_000)
    assert smallest_singular_value(duplicated) < 1e-12 * dense


def test_open_plate_and_disconnected_components():
    v, f = equilateral_plate(12, 10)
    c = build_clusters(v, f, ClusterOptions(spacing=3.0))
    assert c.report.uncovered == 0 and c.report.min_singular_value > 0.0
    v2 = np.vstack([v, v + [100.0, 0.0, 0.0]])
    f2 = np.vstack([f, f + v.shape[0]])
    c2 = build_clusters(v2, f2, ClusterOptions(spacing=3.0))
    assert c2.H.shape[0] == 2 * c.H.shape[0]  # FPS reaches the second component
    assert np.all(c2.partition >= 0) and c2.report.uncovered == 0


def test_options_validation():
    with pytest.raises(InputError, match="ClusterOptions.method"):
        ClusterOptions(method="kmeans")  # type: ignore[arg-type]
    with pytest.raises(InputError, match="ClusterOptions.count"):
        ClusterOptions(count=0)
    with pytest.raises(InputError, match="ClusterOptions.sigma"):
        ClusterOptions(sigma=-1.0)
    with pytest.raises(InputError, match="ClusterOptions.skin_nu"):
        ClusterOptions(skin_nu=1.0)
    v, f = icosphere(0)
    with pytest.raises(InputError, match="seed_vertex"):
        build_clusters(v, f, ClusterOptions(seed_vertex=12))
