"""Element-boundary artefacts: how much wrinkle energy sits on the coarse mesh's edges.

Remillard & Kry (2013) give the coarse body a quadratic interior so that wrinkles do not seed
along coarse element boundaries. This script runs the compressed-skin scene
``scenes/wrinkle_skin.toml`` twice, with a P1 and with a P2 body (``body.degree``), and for
the shell's bending energy density per hinge ``e_h = E_h / ((A1 + A2) / 3)``
(:func:`validation.measure.hinge_energies`) on the bar's four lateral faces (away from the
clamps and the bar's own edges, where energy concentrates for physical reasons) reports
:func:`validation.measure.edge_band_report` against the distance ``d_h`` of each hinge's rest
midpoint to the nearest edge of the coarse boundary triangles:

* ``ratio = F_E / F_A``: fraction of the bending energy within ``band`` of a coarse edge over
  the area fraction of that band (1 = no artefact), for two bands: a quarter of a shell edge
  ("on_edges": exactly the hinges lying on coarse edges, since linear subdivision splits
  every coarse edge into shell edges and any other hinge midpoint is farther away) and a
  tenth of the mean coarse edge;
* the Pearson correlation of ``e_i`` with ``d_i``.

Writes ``<build>/data/artefacts.json`` (with the ``meta`` entry of ``common.write_json``).

    python paper/scripts/artefacts.py [--quick] --build paper/build   (--out is an alias)
"""

from __future__ import annotations

import argparse
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
from common import DEFAULT_BUILD, write_json

from models.backend import MPI
from models.embedding.embedding import mesh_surface
from validation.measure import (
    coarse_edge_distances,
    edge_band_report,
    hinge_energies,
    lateral_lines,
    normal_heights,
    shell_wavelength,
    unique_edges,
)
from wrinkles.runner import Run, prepare, run_frames
from wrinkles.scene import load_scene

REPO = Path(__file__).resolve().parents[2]

SCENE = REPO / "scenes" / "wrinkle_skin.toml"
FULL = ["shell.subdivision.levels=3", "shell.skin.thickness=2.3986e-4"]
"""Full size: three subdivision levels (edges ~1.2 mm) and h for lambda = 10 mm."""


def run_degree(degree: int, out: Path, quick: bool) -> Run:
    """Run the scene with a P``degree`` body (quietly)."""
    sets = [f"body.degree={degree}"] + ([] if quick else FULL)
    scene = load_scene(SCENE, sets)
    return run_frames(prepare(scene, out, MPI.COMM_SELF, overwrite=True), lambda line: None)


def coarse_edge_length(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Mean edge length of the coarse boundary triangles [m]."""
    e = unique_edges(faces)
    return float(np.linalg.norm(vertices[e[:, 1]] - vertices[e[:, 0]], axis=1).mean())


def measure_run(run: Run) -> dict[str, Any]:
    """Band reports (two bands), correlation, wavelength and energy of one run."""
    shell = run.shell
    assert shell is not None
    surface = mesh_surface(run.body.mesh)
    faces, rest, a = shell.topology.faces, shell.rest, shell.edge_length
    mask, _ = lateral_lines(rest, faces, 0, 1.5 * a, 2.0 * a)
    hinges = hinge_energies(shell.x, rest, shell.topology.hinges, shell.params.k_B)
    inside = mask[hinges.edge_vertices].all(axis=1)
    d = coarse_edge_distances(hinges.midpoints[inside], surface.vertices, surface.faces)
    density, area = hinges.density[inside], hinges.areas[inside]
    h_coarse = coarse_edge_length(surface.vertices, surface.faces)
    heights = normal_heights(shell.x, shell.y, faces)
    wavelength = shell_wavelength(rest, faces, heights, 0, 1.5 * a, 2.0 * a)
    details = run.records[-1].details
    return {"degree": run.scene.body.degree, "shell_edge": a, "coarse_edge": h_coarse,
            "hinges_measured": int(inside.sum()),
            "on_edges": asdict(edge_band_report(d, density, area, 0.25 * a)),
            "tenth_coarse_edge": asdict(edge_band_report(d, density, area, 0.1 * h_coarse)),
            "wavelength": wavelength.wavelength, "amplitude": wavelength.amplitude,
            "bending_energy": float(details["shell_terms"]["bending"]),
            "shell_iterations": int(details["shell_iterations"]),
            "shell_converged": bool(details["shell_converged"])}


def print_table(rows: list[dict[str, Any]]) -> None:
    """Print one line per body degree."""
    print(f"{'body':>4} {'band':>18} {'F_E':>6} {'F_A':>6} {'ratio':>6} {'corr':>6} "
          f"{'lambda[mm]':>10}")
    for r in rows:
        for name in ("on_edges", "tenth_coarse_edge"):
            b = r[name]
            print(f"  P{r['degree']} {name:>18} {b['energy_fraction']:6.3f} "
                  f"{b['area_fraction']:6.3f} {b['ratio']:6.3f} {b['correlation']:6.3f} "
                  f"{1e3 * r['wavelength']:10.3f}")


def main(argv: list[str] | None = None) -> int:
    """Run P1 and P2, measure, write the JSON."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--build", "--out", dest="out", type=Path, default=DEFAULT_BUILD,
                        help="build directory (writes data/ and figures/ there)")
    parser.add_argument("--quick", action="store_true", help="two subdivision levels")
    args = parser.parse_args(argv)
    t0 = time.perf_counter()
    rows = [measure_run(run_degree(k, args.out / "work" / f"artefacts_p{k}", args.quick))
            for k in (1, 2)]
    print_table(rows)
    document = {"quick": args.quick, "scene": str(SCENE.relative_to(REPO)),
                "overrides": [] if args.quick else FULL, "rows": rows, "figures": []}
    write_json(args.out, "artefacts", document, args.quick, t0)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
