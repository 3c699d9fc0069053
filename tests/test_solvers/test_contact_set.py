"""Contact penalties on candidate facets: the solves over all facets, at a fraction of them."""

from __future__ import annotations

import numpy as np
import pytest

import solvers.contact_set as contact_set
from models.backend import (
    MPI,
    dolfinx,
    exterior_facet_domain,
    global_scalar,
    ufl,
    with_facet_domains,
)
from models.body import BodyOptions
from models.contact import ContactOptions, PenaltyContact, exterior_facets
from models.materials import Material
from solvers.body import Body

MAT = Material(model="neo_hookean", E=1.0e5, nu=0.3, density=1000.0)


def test_a_form_rebuilt_on_some_facets_assembles_as_one_compiled_on_them():
    mesh = dolfinx.mesh.create_unit_cube(MPI.COMM_WORLD, 4, 4, 4)
    V = dolfinx.fem.functionspace(mesh, ("Lagrange", 1, (3,)))
    u = dolfinx.fem.Function(V)
    u.interpolate(lambda x: np.vstack([x[0] ** 2, x[1] * x[2], np.sin(x[0])]))
    facets = exterior_facets(mesh)
    every, some = (exterior_facet_domain(mesh, f) for f in (facets, facets[::3]))

    def energy(data):
        ds = ufl.Measure("ds", domain=mesh, subdomain_data=data, metadata={"quadrature_degree": 4})
        return ufl.dot(u, u) ** 2 * ds(0) + ufl.dot(u, u) * ds(1) + ufl.inner(u, u) * ufl.dx

    full = dolfinx.fem.form(energy([(0, every), (1, every)]))
    rebuilt = with_facet_domains(full, {0: some, 1: every})
    compiled = dolfinx.fem.form(energy([(0, some), (1, every)]))
    values = [global_scalar(f) for f in (full, rebuilt, compiled)]
    print(f"all facets {values[0]:.12f}, rebuilt on a third {values[1]:.12f}, compiled on "
          f"them {values[2]:.12f}")
    assert values[1] == pytest.approx(values[2], rel=1e-14)
    assert values[0] - values[1] > 0.1 * values[0]  # the facets left out did contribute
    v = ufl.TestFunction(V)
    residual = dolfinx.fem.form(ufl.derivative(energy([(0, every), (1, every)]), u, v))
    vectors = [dolfinx.fem.petsc.assemble_vector(f) for f in (
        with_facet_domains(residual, {0: some, 1: every}),
        dolfinx.fem.form(ufl.derivative(energy([(0, some), (1, every)]), u, v)))]
    for b in vectors:
        b.ghostUpdate(addv=dolfinx.la.petsc.PETSc.InsertMode.ADD,
                      mode=dolfinx.la.petsc.PETSc.ScatterMode.REVERSE)
    assert np.allclose(vectors[0].array, vectors[1].array, rtol=1e-14, atol=1e-14)
    with pytest.raises(ValueError, match=r"ds\(1\)"):
        with_facet_domains(full, {0: some})


@pytest.mark.parametrize("obstacle", ["plane", "sphere"])
def test_gap_lower_bounds_never_exceed_the_gap_inside_the_facet(obstacle):
    mesh = dolfinx.mesh.create_unit_cube(MPI.COMM_WORLD, 1, 1, 1)
    options = ContactOptions(obstacle=obstacle, point=(0.1, 0.2, 0.3), normal=(1, 2, 2),
                             radius=0.4)
    contact = PenaltyContact(options, mesh, 1.0)
    rng = np.random.default_rng(7)
    corners = rng.uniform(-1.0, 1.0, (500, 3, 3)) * rng.uniform(0.01, 0.5, (500, 1, 1))
    corners += rng.uniform(-0.6, 0.6, (500, 1, 3)) + np.array(options.point)
    weights = rng.dirichlet(np.ones(3), 300)                      # points inside a triangle
    inside = np.einsum("pk,fkd->fpd", np.vstack([np.eye(3), weights]), corners)
    if obstacle == "plane":
        gaps = (inside - np.array(options.point)) @ np.array(options.normal)
    else:
        gaps = np.linalg.norm(inside - np.array(options.point), axis=2) - options.radius
    bounds = contact.gap_lower_bounds(corners)
    print(f"{obstacle}: bound - min gap over 500 triangles in [{np.min(bounds - gaps.min(1)):.3e}, "
          f"{np.max(bounds - gaps.min(1)):.3e}]")
    assert np.all(bounds <= gaps.min(axis=1) + 1e-15)
    if obstacle == "plane":  # exact: the gap is linear on a flat facet
        assert np.allclose(bounds, gaps.min(axis=1), atol=1e-15)


def dropped_block() -> Body:
    """A block falling onto the ground with a ball resting against its side."""
    mesh = dolfinx.mesh.create_box(MPI.COMM_WORLD, [[0, 0, 0.05], [0.5, 0.5, 0.55]], [3, 3, 3],
                                   dolfinx.mesh.CellType.tetrahedron)
    ball = ContactOptions(obstacle="sphere", point=(0.72, 0.25, 0.3), radius=0.23)
    opts = BodyOptions(dynamics="implicit_euler", dt=0.02, gravity=(0, 0, -9.81),
                       contacts=(ContactOptions(obstacle="plane"), ball))
    return Body(mesh, MAT, opts)


def run(body: Body, steps: int) -> tuple[np.ndarray, list[int]]:
    iterations = [body.step().newton_iterations for _ in range(steps)]
    return body.u.x.array.copy(), iterations


def test_a_drop_on_candidate_facets_takes_the_steps_of_all_facets():
    everywhere = dropped_block()
    everywhere._active = None  # every solve over all exterior facets
    reference, reference_its = run(everywhere, 30)
    body = dropped_block()
    u, its = run(body, 30)
    stats = body.contact_set
    assert stats is not None
    share = stats.facets / stats.total
    difference = np.abs(u - reference).max()
    print(f"30 steps: Newton iterations {sum(its)} (all facets {sum(reference_its)}); "
          f"facets integrated {share:.1%} of all; retries {stats.retries}; max |u - u_all| "
          f"{difference:.1e} m of max |u| {np.abs(reference).max():.3e} m")
    assert its == reference_its
    assert difference <= 1e-12 * np.abs(reference).max()
    assert stats.retries == 0
    assert share < 0.5
    assert body.reaction_force()[2] > 0.0  # resting on the ground at the end


def test_a_penetrated_facet_left_out_is_caught_and_the_solve_repeated(monkeypatch):
    everywhere = dropped_block()
    everywhere._active = None
    reference, reference_its = run(everywhere, 12)
    body = dropped_block()
    # a selection that leaves every facet out: any contact must be caught after the solve
    monkeypatch.setattr(PenaltyContact, "gap_lower_bounds",
                        lambda self, points: np.full(len(points), np.inf))
    u, its = run(body, 12)
    stats = body.contact_set
    assert stats is not None
    print(f"12 steps with no facet selected: {stats.retries} of {stats.solves} solves repeated; "
          f"max |u - u_all| {np.abs(u - reference).max():.1e} m")
    assert stats.retries == stats.solves  # the ball touches the side from the start
    assert stats.facets == 0
    assert its == reference_its
    assert np.abs(u - reference).max() <= 1e-12 * np.abs(reference).max()


def test_the_margin_grows_with_the_predicted_motion():
    body = dropped_block()
    active = body._active
    assert active is not None
    cell_facets = body.mesh.topology.connectivity(3, 2)
    assert np.array_equal([cell_facets.links(c)[f] for c, f in active.pairs],
                          active.surface.facets)  # the integration pairs are the triangles
    u_n = np.zeros_like(body.u.x.array)
    still = active.select(u_n, u_n)
    moving = u_n.reshape(-1, 3).copy()
    moving[:, 2] -= 0.05  # every corner predicted 5 cm lower
    falling = active.select(moving.ravel(), u_n)
    counts = [[d.size // 2 for d in domains.values()] for domains in (still, falling)]
    print(f"candidate facets (plane, ball) at rest {counts[0]}, falling 5 cm {counts[1]}, of "
          f"{active.pairs.shape[0]}; slack {contact_set.SLACK} x longest edge {active.edge:.3f} m")
    assert counts[0][0] == 0 < counts[1][0]  # 5 cm above the ground: only when falling
    assert counts[0][1] > 0  # the ball touches the side at rest
