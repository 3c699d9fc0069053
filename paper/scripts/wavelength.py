"""Wrinkle wavelength vs stiffness ratio: theory, volumetric bilayer, embedded shell.

For each skin/body stiffness ratio ``E_f / E_s`` the theory gives (Allen 1969; Cerda &
Mahadevan 2003; the sizing of Remillard & Kry 2013)

    lambda = 2 pi h (Ebar_f / (3 Ebar_s))^(1/3),   Ebar = E / (1 - nu^2).

The film thickness ``h`` is chosen per ratio so that the theoretical wavelength is the same
(``--wavelength``, 10 mm by default, 20 mm with ``--quick``): the meshes then resolve every
case alike (the shell has ``lambda / edge`` edges per wavelength, the bilayer
``elements_per_wavelength`` columns) and only the physics (ratio, h) changes. Two
measurements per ratio, both with
:func:`validation.measure.dominant_wavelength`:

* volumetric: the plane-strain bilayer of :mod:`validation.bilayer` (P2, film resolved by
  ``film_layers`` rows, compressed to ``strain_factor`` eps_c with a random imperfection);
* embedded shell: the scene ``scenes/wrinkle_skin.toml`` (a coarse P1 bar compressed 4 %
  along x, its surface subdivided into the shell: two levels with ``--quick``, three
  otherwise) with ``shell.skin.E`` and ``shell.skin.thickness`` set for the ratio; heights are
  the normal distances of the shell from its embedded target ``B v_q`` on the four lateral
  faces, lines parallel to x.

The shell's clusters are sized from the same formula (spacing lambda/2, sigma lambda/pi), so
the shell does not discover lambda independently: the ablation ``cluster_ablation`` reruns
the middle ratio with clusters sized for 0.75 and 1.5 lambda and reports how far the shell's
wavelength follows the cluster sizing.

Writes ``<build>/data/wavelength.json`` (with the ``meta`` entry of ``common.write_json``) and
``<build>/figures/wavelength.png``.

    python paper/scripts/wavelength.py [--quick] --build paper/build   (--out is an alias)
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

import numpy as np
from common import DEFAULT_BUILD, figure_path, write_json

from models.backend import MPI
from models.embedding.clusters import effective_modulus, wrinkle_wavelength
from validation.bilayer import BilayerOptions, mode_spacing, run_bilayer
from validation.measure import (
    SpectrumOptions,
    dominant_wavelength,
    normal_heights,
    shell_wavelength,
)
from wrinkles.runner import prepare, run_frames
from wrinkles.scene import load_scene

REPO = Path(__file__).resolve().parents[2]

SCENE = REPO / "scenes" / "wrinkle_skin.toml"
SUBSTRATE_E, SUBSTRATE_NU, FILM_NU = 5.0e4, 0.45, 0.3
"""Materials of the scene's body and skin (the ratio sets the skin's E)."""


def thickness_for(ratio: float, wavelength: float) -> float:
    """Film thickness h whose theoretical wavelength is ``wavelength`` at ``E_f/E_s = ratio``."""
    return wavelength / wrinkle_wavelength(1.0, ratio * SUBSTRATE_E, FILM_NU, SUBSTRATE_E,
                                           SUBSTRATE_NU)


BILAYER_QUICK: dict[str, Any] = {"periods": 10.0, "elements_per_wavelength": 12,
                                 "substrate_layers": 12, "depth": 1.0, "steps": 5,
                                 "strain_factor": 1.3}
BILAYER_FULL: dict[str, Any] = {"periods": 16.0, "elements_per_wavelength": 24, "film_layers": 3,
                                "substrate_layers": 24, "depth": 1.5, "steps": 8,
                                "strain_factor": 1.3}
"""Bilayer sizes (:class:`validation.bilayer.BilayerOptions` fields) of the quick and full runs."""
SHELL_FULL = ["shell.subdivision.levels=3"]
"""Full runs: three subdivision levels (edges ~1.2 mm) for the 10 mm wavelength."""
CLUSTER_FACTORS = (0.75, 1.5)
"""Cluster sizing ablation: clusters sized for ``factor * lambda`` (r, sigma scaled)."""


def bilayer_row(ratio: float, h: float, quick: bool) -> dict[str, Any]:
    """Run the plane-strain bilayer for one ratio; return its measured numbers."""
    sizes = BILAYER_QUICK if quick else BILAYER_FULL
    options = BilayerOptions(film_E=ratio * SUBSTRATE_E, film_nu=FILM_NU, thickness=h,
                             substrate_E=SUBSTRATE_E, substrate_nu=SUBSTRATE_NU, **sizes)
    result = run_bilayer(options, MPI.COMM_SELF)
    measured = dominant_wavelength(result.top_x, result.top_w,
                                   options=SpectrumOptions(min_periods=2.0))
    return {"volumetric": measured.wavelength,
            "volumetric_error": measured.wavelength / result.theory - 1.0,
            "volumetric_amplitude": measured.amplitude, "volumetric_strain": result.strain,
            "critical_strain": result.critical_strain, "volumetric_dofs": result.dofs,
            "volumetric_newton": result.newton_iterations,
            "volumetric_wall_time": result.wall_time,
            "volumetric_mode_step": mode_spacing(options), "bilayer_options": sizes}


def shell_overrides(ratio: float, h: float, quick: bool) -> list[str]:
    """``--set`` assignments of the scene for one ratio."""
    sets = [f"shell.skin.E={ratio * SUBSTRATE_E!r}", f"shell.skin.thickness={h!r}"]
    return sets if quick else sets + SHELL_FULL


def cluster_overrides(wavelength: float, factor: float) -> list[str]:
    """Clusters sized for ``factor * lambda``: spacing ``f lambda / 2``, sigma ``f lambda / pi``."""
    return [f"shell.clusters.spacing={factor * wavelength / 2.0!r}",
            f"shell.clusters.sigma={factor * wavelength / np.pi!r}"]


def run_shell(ratio: float, h: float, out: Path, quick: bool,
              extra: list[str] | None = None) -> dict[str, Any]:
    """Run the embedded-shell scene for one ratio; return its measured numbers."""
    scene = load_scene(SCENE, shell_overrides(ratio, h, quick) + (extra or []))
    t0 = time.perf_counter()
    run = run_frames(prepare(scene, out, MPI.COMM_SELF, overwrite=True), lambda line: None)
    shell = run.shell
    assert shell is not None
    heights = normal_heights(shell.x, shell.y, shell.topology.faces)
    a = shell.edge_length
    measured = shell_wavelength(shell.rest, shell.topology.faces, heights, axis=0,
                                margin=1.5 * a, line_width=2.0 * a)
    details = run.records[-1].details
    return {"shell": measured.wavelength, "shell_amplitude": measured.amplitude,
            "shell_edge": a, "shell_vertices": int(shell.rest.shape[0]),
            "shell_iterations": int(details["shell_iterations"]),
            "shell_converged": bool(details["shell_converged"]),
            "shell_wall_time": time.perf_counter() - t0}


def study_row(ratio: float, wavelength: float, out: Path, quick: bool,
              volumetric: bool) -> dict[str, Any]:
    """Theory, bilayer and shell for one ratio, with relative errors."""
    h = thickness_for(ratio, wavelength)
    theory = wrinkle_wavelength(h, ratio * SUBSTRATE_E, FILM_NU, SUBSTRATE_E, SUBSTRATE_NU)
    row: dict[str, Any] = {
        "ratio": ratio, "thickness": h, "theory": theory,
        "ebar_ratio": effective_modulus(ratio * SUBSTRATE_E, FILM_NU)
        / effective_modulus(SUBSTRATE_E, SUBSTRATE_NU)}
    row.update(run_shell(ratio, h, out / f"shell_{ratio:g}", quick))
    row["shell_error"] = row["shell"] / theory - 1.0
    row["shell_edges_per_wavelength"] = theory / row["shell_edge"]
    if volumetric:
        row.update(bilayer_row(ratio, h, quick))
    return row


def cluster_ablation(ratio: float, wavelength: float, out: Path,
                     quick: bool) -> list[dict[str, Any]]:
    """Shell wavelength with clusters sized for ``f * lambda`` instead of lambda."""
    h = thickness_for(ratio, wavelength)
    rows = []
    for factor in CLUSTER_FACTORS:
        row = run_shell(ratio, h, out / f"clusters_{factor:g}", quick,
                        cluster_overrides(wavelength, factor))
        rows.append({"ratio": ratio, "cluster_factor": factor, "shell": row["shell"],
                     "shell_error": row["shell"] / wavelength - 1.0,
                     "shell_converged": row["shell_converged"]})
    return rows


def plot(rows: list[dict[str, Any]], path: Path) -> None:
    """``lambda / h`` vs ``Ebar_f / Ebar_s``: theory line, bilayer and shell markers."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ebar = np.array([r["ebar_ratio"] for r in rows])
    h = np.array([r["thickness"] for r in rows])
    grid = np.geomspace(ebar.min() / 1.5, ebar.max() * 1.5, 50)
    fig, ax = plt.subplots(figsize=(5.0, 3.6))
    ax.loglog(grid, 2 * np.pi * (grid / 3.0) ** (1.0 / 3.0), "k-", label="theory")
    if "volumetric" in rows[0]:
        ax.loglog(ebar, [r["volumetric"] for r in rows] / h, "s", mfc="none",
                  label="volumetric bilayer (P2, plane strain)")
    ax.loglog(ebar, [r["shell"] for r in rows] / h, "o", label="embedded shell")
    ax.set_xlabel(r"$\bar E_f / \bar E_s$")
    ax.set_ylabel(r"$\lambda / h$")
    ax.legend(frameon=False, fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=150)
    plt.close(fig)


def print_table(rows: list[dict[str, Any]]) -> None:
    """Print ratio, theory, volumetric, shell and relative errors (mm and %)."""
    print(f"{'Ef/Es':>7} {'h[mm]':>7} {'theory':>7} {'volum.':>7} {'err%':>6} "
          f"{'shell':>7} {'err%':>6} {'edges/l':>7}")
    for r in rows:
        vol = (f"{1e3 * r['volumetric']:7.3f} {100 * r['volumetric_error']:6.1f}"
               if "volumetric" in r else f"{'-':>7} {'-':>6}")
        print(f"{r['ratio']:7g} {1e3 * r['thickness']:7.4f} {1e3 * r['theory']:7.3f} {vol} "
              f"{1e3 * r['shell']:7.3f} {100 * r['shell_error']:6.1f} "
              f"{r['shell_edges_per_wavelength']:7.2f}")


def main(argv: list[str] | None = None) -> int:
    """Run the study and write the JSON and the figure."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--build", "--out", dest="out", type=Path, default=DEFAULT_BUILD,
                        help="build directory (writes data/ and figures/ there)")
    parser.add_argument("--quick", action="store_true",
                        help="lambda 20 mm, two subdivision levels, smaller bilayer meshes")
    parser.add_argument("--ratios", type=float, nargs="+", default=[300.0, 1000.0, 3000.0,
                                                                        10000.0])
    parser.add_argument("--wavelength", type=float, default=None,
                        help="theory lambda [m] (default 0.02 with --quick, else 0.01)")
    parser.add_argument("--no-volumetric", action="store_true", help="skip the bilayer")
    parser.add_argument("--no-ablation", action="store_true", help="skip the cluster sizing "
                        "ablation")
    args = parser.parse_args(argv)
    t0 = time.perf_counter()
    lam = args.wavelength or (0.02 if args.quick else 0.01)
    work = args.out / "work" / "wavelength"
    rows = [study_row(r, lam, work, args.quick, not args.no_volumetric) for r in args.ratios]
    print_table(rows)
    middle = args.ratios[len(args.ratios) // 2]
    ablation = [] if args.no_ablation else cluster_ablation(middle, lam, work, args.quick)
    for a in ablation:
        print(f"clusters sized for {a['cluster_factor']:g} lambda (ratio {a['ratio']:g}): "
              f"shell {1e3 * a['shell']:.3f} mm, error {100 * a['shell_error']:+.1f} %")
    figure = figure_path(args.out, "wavelength")
    plot(rows, figure)
    document = {"quick": args.quick, "wavelength_target": lam, "cluster_ablation": ablation,
                "substrate": {"E": SUBSTRATE_E, "nu": SUBSTRATE_NU}, "film_nu": FILM_NU,
                "scene": str(SCENE.relative_to(REPO)), "rows": rows,
                "figures": [f"figures/{figure.name}"]}
    write_json(args.out, "wavelength", document, args.quick, t0)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
