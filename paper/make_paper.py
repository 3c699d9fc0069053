"""Regenerate the paper: run the figure scripts and benchmarks, build tables, fill the template.

``python paper/make_paper.py [--quick] [--large] [--rerun] [--no-benchmarks] [--strict]
[--run-external] [--no-external] [--no-run] [--build DIR]`` (``make paper``, with
``PAPER_ARGS``):

1. runs the steps (:mod:`steps`), each skipped while its inputs are unchanged, so a killed
   run resumes by being run again (``--rerun``: run all): our scripts
   ``paper/scripts/{convergence,shell_limits,taylor,scenes,ball_sofa}.py --build DIR
   [--quick]`` (each writes ``DIR/data/<name>.json`` and figures), in full mode also
   ``paper/scripts/{wavelength,artefacts}.py`` (``--run-external``: in quick mode too;
   ``--no-external``: never), and in full mode the benchmarks (:func:`benchmark_steps`) at
   paper sizes into ``DIR/bench/`` (``--large``: at their own full sizes; quick mode or
   ``--no-benchmarks``: none);
2. reads the optional sources (``DIR/data/wavelength.json``, ``DIR/data/artefacts.json``,
   ``DIR/bench/{speed_accuracy,decomposition*,split_scaling,shell_kernels,shell_solve,scaling*,
   iterative_*conv*}.json``): each gives a Markdown table in ``DIR/tables/`` and a section of the
   paper, or the words "not run" and the step that produces it (``--strict``: an error);
3. fills ``paper/paper.md.in``: ``{{source.key.path:format}}`` is a number read from the JSON
   of ``source`` (keys separated by dots, list indices as integers, ``format`` a Python format
   spec), ``{{block:name}}`` a generated table / figure / section. No number of the text is
   typed by hand: an unresolvable placeholder is an error naming the script to run. Writes
   ``DIR/paper.md`` and ``DIR/data/provenance.json`` (every placeholder, its value and its
   JSON file);
4. when ``pdflatex`` is on the PATH, also writes ``DIR/paper.tex`` and builds ``paper.pdf``.
"""

from __future__ import annotations

import argparse
import json
import re
import shutil
import subprocess
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from dataclasses import replace as with_fields
from pathlib import Path
from typing import Any

from steps import Step, StepError, run_steps

PAPER = Path(__file__).resolve().parent
REPO = PAPER.parent
TEMPLATE = PAPER / "paper.md.in"
OWN_SCRIPTS: tuple[str, ...] = ("convergence", "shell_limits", "taylor", "scenes",
                                 "ball_sofa")
EXTERNAL_SCRIPTS: tuple[str, ...] = ("wavelength", "artefacts")
BENCH_DIR = "bench"
"""Subdirectory of the build directory where the benchmarks' JSON (and plots) go."""
PLACEHOLDER = re.compile(r"\{\{\s*([^{}:]+?)\s*(?::([^{}]*))?\}\}")


class PaperError(RuntimeError):
    """A source is missing or the template cannot be filled (the message says what to run)."""


@dataclass(frozen=True)
class Source:
    """An optional JSON source of a paper section.

    Attributes:
        name: Key of the source in the template (``{{block:<name>}}``).
        title: Section / table title.
        pattern: Glob of its JSON file(s), relative to the repository (``{build}`` = build dir).
        command: The command that produces it (printed when it is missing).
        columns: Preferred table columns (dotted paths into nested row dicts); those absent
            from the rows are skipped; empty: the first scalar columns.
        render: Renderer of the section from ``(source, files)`` instead of one generic
            table per file (None: generic).

    """

    name: str
    title: str
    pattern: str
    command: str
    columns: tuple[str, ...] = ()
    render: Callable[[Source, Sequence[Path]], str] | None = None


DECOMPOSITION_STUDY_COLUMNS: tuple[str, ...] = (
    "study", "k_B_over_k_P", "method", "patches", "outer", "converged", "stopped_by",
    "grad_reduction", "energy_gap", "max_diff", "time", "fitted_rate", "extrapolated_outer",
    "extrapolated_time")


def run_conditions(doc: dict[str, Any]) -> str:
    """Wall-time caps and machine load of a decomposition run, as far as its JSON has them."""
    text = ""
    if doc.get("block_seconds") is not None:
        text += f" Block runs capped at {doc['block_seconds']:g} s"
        text += (f" (studies {doc['study_seconds']:g} s)." if doc.get("study_seconds")
                 not in (None, doc["block_seconds"]) else ".")
    if doc.get("load_average"):
        start, end = doc["load_average"][0], doc["load_average"][-1]
        text += (f" Load average (1/5/15 min) {start[0]:.1f}/{start[1]:.1f}/{start[2]:.1f} at "
                 f"the start, {end[0]:.1f}/{end[1]:.1f}/{end[2]:.1f} at the end (2 cores; the "
                 "run's own 2 ranks account for about 2, more means other jobs ran).")
    return text


def decomposition_section(source: Source, files: Sequence[Path]) -> str:
    """Render the decomposition benchmark: per JSON with a verdict, smallest size first.

    Each ``decomposition_*.json`` of ``benchmarks/decomposition.py`` gives its frame statement,
    the main table (``source.columns``), the studies table, the verdict and the note on the
    extrapolated columns (JSON without a verdict, from older versions, are skipped).
    """
    docs = [(path, json.loads(path.read_text())) for path in files]
    docs = [(p, d) for p, d in docs if isinstance(d, dict) and "verdict" in d]
    parts = []
    for path, doc in sorted(docs, key=lambda pd: (pd[1]["sizes"][0], pd[0].name)):
        rows = [{k: v for k, v in r.items() if v is not None} for r in rows_of(doc)]
        main, studies = ([r for r in rows if ("study" in r) == s] for s in (False, True))
        head = f"n = {doc['sizes'][0]}, {doc['ranks']} rank(s) (`{path.name}`)"
        parts.append(f"Table: {source.title}, {head}. Problem: {doc.get('frame', '')}."
                     f"{run_conditions(doc)}\n\n"
                     + markdown_table(main, table_columns(source, main)))
        if studies:
            study = with_fields(source, columns=DECOMPOSITION_STUDY_COLUMNS)
            parts.append(f"Table: Studies, {head}.\n\n"
                         + markdown_table(studies, table_columns(study, studies)))
        parts.append(f"*Verdict, {head}:* {doc['verdict']}.\n")
        if any("extrapolated_outer" in r for r in rows):
            parts.append(f"*{doc['extrapolation']}.*\n")
    return "\n".join(parts)


# --- speed / accuracy (benchmarks/speed_accuracy.py) ------------------------------------------

PARETO_COLUMNS: tuple[str, ...] = ("setting", "vertices", "frames", "wall_s_per_frame",
                                   "cpu_s_per_frame", "peak_mib", "rms_rel", "max_m",
                                   "bending_energy_rel", "wavelength_rel", "shell_its")
"""Columns of the speed/accuracy tables (one row of the benchmark JSON each)."""


def speed_row(name: str, row: dict[str, Any]) -> dict[str, Any]:
    """Return the table row of one setting of ``benchmarks/speed_accuracy.py``'s JSON.

    "-" marks what was not measurable (e.g. no wavelength on a 0-level shell); the
    reference run has no error entries: 0 by construction.
    """
    cells = {"setting": name, "vertices": row.get("vertices", ""),
             "frames": len(row.get("frame_times", [])),
             "wall_s_per_frame": row.get("time_per_frame", ""),
             "cpu_s_per_frame": row.get("cpu_per_frame", ""),
             "peak_mib": row.get("peak_rss_mib", ""), "rms_rel": row.get("rms_rel", 0.0),
             "max_m": row.get("max", 0.0),
             "bending_energy_rel": row.get("bending_energy_rel_error", 0.0),
             "wavelength_rel": row.get("wavelength_rel_error", 0.0),
             "shell_its": sum(i or 0 for i in row.get("shell_iterations", []))}
    return {k: "-" if v is None else v for k, v in cells.items()}


def preset_rows(doc: dict[str, Any], by_name: dict[str, dict[str, Any]]) -> list[dict[str, Any]]:
    """Return the rows of the quality presets measured in ``doc``.

    ``doc["presets"]`` maps a quality to the name of its measured row; the name "reference"
    is the reference run itself (error 0 by construction).
    """
    rows = []
    for quality, name in doc.get("presets", {}).items():
        row = doc["reference"] if name == "reference" else by_name.get(name)
        if row is not None:
            rows.append({**speed_row(name, row), "setting": f"{quality} ({name})"})
    return rows


def speed_accuracy_intro(doc: dict[str, Any], path: Path) -> str:
    """One paragraph: scene, reference, how many settings ran, the machine load."""
    ref, rows = doc["reference"], doc["rows"]
    failed = [r["name"] for r in rows if "error" in r]
    loads = [x for r in rows for x in r.get("load_avg_1min", [])]
    load = f"{min(loads):.2f}-{max(loads):.2f}" if loads else "not recorded"
    return (f"`{doc['scene']}` (`{path.name}`, {doc['date']}), base overrides "
            f"`{' '.join(doc['base_overrides']) or '(none)'}`. Reference: "
            f"`{' '.join(ref['overrides'])}`, {ref['vertices']} shell vertices, "
            f"{fmt(ref['time_per_frame'])} s/frame wall, {fmt(ref.get('cpu_per_frame', ''))} "
            f"s/frame CPU. Knob groups run: {', '.join(dict.fromkeys(r['group'] for r in rows))}"
            f". {len(rows)} settings run ({len(failed)} failed"
            f"{': ' + ', '.join(failed) if failed else ''}); 1-minute load average during "
            f"the rows {load} on {doc['machine']['cpus']} cores (shared machine: the CPU "
            f"time of the process is the Pareto axis).\n")


def speed_accuracy_notes(doc: dict[str, Any]) -> str:
    """Knobs left out of the sweep and why; settings the time budget left unrun."""
    notes = doc.get("notes", {})
    lines = [f"- {notes['scene']}\n"] if notes.get("scene") else []
    lines += [f"- left out: {k}: {v}\n" for k, v in notes.get("dropped", {}).items()]
    if notes.get("not_run"):
        lines.append(f"- not run (time budget): {', '.join(notes['not_run'])}\n")
    return "".join(lines)


def speed_accuracy_part(doc: dict[str, Any], path: Path) -> str:
    """Section of one speed/accuracy JSON: intro, Pareto tables, presets, notes."""
    by_name = {r["name"]: r for r in doc["rows"] if "error" not in r}
    parts = [speed_accuracy_intro(doc, path)]
    for key, what in (("pareto", "shell position error rms_rel"),
                      ("pareto_bending", "bending energy error")):
        front = [speed_row(n, by_name[n]) for n in doc.get(key, []) if n in by_name]
        if front:
            parts.append(f"Table: Pareto-optimal settings on CPU time and {what} "
                         f"(`{path.name}`).\n\n" + markdown_table(front, PARETO_COLUMNS))
    presets = preset_rows(doc, by_name)
    if presets:
        parts.append(f"Table: Quality presets as measured (`{path.name}`).\n\n"
                     + markdown_table(presets, PARETO_COLUMNS))
    parts.append(speed_accuracy_notes(doc))
    return "\n".join(parts)


def speed_accuracy_section(source: Source, files: Sequence[Path]) -> str:
    """Render the speed/accuracy section: per scene JSON its Pareto tables and presets."""
    return "\n".join(speed_accuracy_part(json.loads(f.read_text()), f) for f in files)


def split_scaling_section(source: Source, files: Sequence[Path]) -> str:
    """Render the split shell's scaling: the measured runs, the check, the model's table."""
    parts = []
    for path in files:
        doc = json.loads(path.read_text())
        measured = [{"ranks": r["ranks"], "vertices": r["vertices"],
                     "newton": r["newton_iterations"],
                     "shell_s": max(x["shell_time"] for x in r["per_rank"]),
                     "owned_max": max(x["owned"] for x in r["per_rank"]),
                     "halo_max": max(x["halo"] for x in r["per_rank"]),
                     "products": r["per_rank"][0]["products"],
                     "cg_iterations": r["per_rank"][0]["cg_iterations"]}
                    for r in doc["runs"]]
        parts.append(f"Table: The split shell measured, one frame (`{path.name}`).\n\n"
                     + markdown_table(measured, tuple(measured[0])))
        parts += [f"Check at {c['ranks']} ranks: measured {fmt(c['measured'])} s, the network "
                  f"model with this machine's shared memory {fmt(c['model_shared_memory'])} s; "
                  f"the difference, {fmt(1e6 * c['overhead_per_product'])} us per distributed "
                  "product, is the implementation's own overhead (\"as built\").\n"
                  for c in doc["check"]]
        parts.append(f"Table: Modelled frame time [s] on a cluster (alpha {fmt(doc['alpha'])} s, "
                     f"beta {fmt(doc['beta'])} B/s, compute ~ n^"
                     f"{fmt(doc.get('compute_exponent', 1.0))}; `{path.name}`).\n\n"
                     + markdown_table(doc["predictions"], (
                         "vertices", "ranks", "total", "as_built", "compute", "halo",
                         "reductions", "allgathers")))
    return "\n".join(parts)


SOURCES: tuple[Source, ...] = (
    Source("wavelength", "Wrinkle wavelength against theory and a volumetric bilayer",
           "{build}/data/wavelength.json", "python paper/scripts/wavelength.py",
           ("ratio", "thickness", "theory", "shell", "shell_error", "volumetric",
            "volumetric_error", "shell_edges_per_wavelength", "shell_converged")),
    Source("artefacts", "Element-boundary artefacts, P1 against P2",
           "{build}/data/artefacts.json", "python paper/scripts/artefacts.py",
           ("degree", "shell_edge", "coarse_edge", "on_edges.energy_fraction",
            "on_edges.area_fraction", "on_edges.ratio", "on_edges.correlation", "wavelength",
            "amplitude")),
    Source("speed_accuracy", "Speed against accuracy (Pareto front)",
           "{build}/" + BENCH_DIR + "/speed_accuracy*.json", "make paper (step speed_accuracy)",
           render=speed_accuracy_section),
    Source("decomposition", "Solving in parts against solving whole",
           "{build}/" + BENCH_DIR + "/decomposition_*.json", "make paper (step decomposition)",
           ("method", "ranks", "patches", "outer", "converged", "stopped_by", "grad_reduction",
            "energy_gap", "max_diff", "time", "speedup", "extrapolated_outer",
            "extrapolated_time"), render=decomposition_section),
    Source("split_scaling", "The split shell over MPI ranks: measured and modelled",
           "{build}/" + BENCH_DIR + "/split_scaling.json", "make paper (step split_scaling)",
           render=split_scaling_section),
    Source("shell_kernels", "Shell energy kernels",
           "{build}/" + BENCH_DIR + "/shell_kernels.json", "make paper (step shell_kernels)",
           ("kind", "size", "reorder", "n_vertices", "terms_us_per_vertex.membrane_edge.order2",
            "terms_us_per_vertex.bending.order2", "terms_us_per_vertex.penalty.order2",
            "assembly.us_per_block", "peak_rss_mib")),
    Source("shell_solve", "Sparse direct solvers for the shell Newton system",
           "{build}/" + BENCH_DIR + "/shell_solve.json", "make paper (step shell_solve)",
           ("mesh", "size", "system", "dofs", "backend", "ok", "analysis", "first", "refact",
            "solve", "negative_pivots", "mumps_mb")),
    Source("scaling", "Cost against shell size, each size in its own process (seconds; cpu = "
           "process CPU time; frames.1 = the warm-started frame; load_end.0 = one-minute load "
           "average)", "{build}/" + BENCH_DIR + "/scaling*.json", "make paper (step scaling)",
           ("size", "n", "clusters", "method", "setup_cpu", "setup.hierarchy.cpu",
            "setup.clusters.cpu", "setup.energy.cpu", "frames.1.cpu", "frames.1.wall",
            "frames.1.iterations", "frames.1.cg_iterations", "peak_mib", "load_end.0")),
    Source("iterative", "Newton iterations of the warm-started wrinkled frame "
           "(`--to-tolerance`; seconds per Newton iteration; t_iteration = wall, "
           "cpu_iteration = process CPU; "
           "energy_gap and max_vertex_diff against the direct solve)",
           "{build}/" + BENCH_DIR + "/iterative_*conv*.json", "make paper (step iterative)",
           ("size", "n", "method", "threads", "iterations", "extra_iterations", "t_iteration",
            "cpu_iteration", "cg_iterations", "energy_gap", "max_vertex_diff",
            "true_residual_max", "peak_mib")),
)


# --- the steps: our scripts and the benchmarks ----------------------------------------------

SPEED_ACCURACY_PAPER: tuple[str, ...] = ("--only", "subdivision", "hessian", "--budget", "12")
"""The speed/accuracy sweep at paper size: the knobs that decide the presets (the subdivision
levels give the ``preview`` / ``balanced`` / ``final`` rows), at most 12 minutes of starts."""


def script_steps(args: argparse.Namespace) -> list[Step]:
    """Our figure scripts (and the external ones in full mode or with ``--run-external``)."""
    external = (args.run_external or not args.quick) and not args.no_external
    names = list(OWN_SCRIPTS) + [n for n in EXTERNAL_SCRIPTS
                                 if external and (PAPER / "scripts" / f"{n}.py").is_file()]
    quick = ("--quick",) if args.quick else ()
    return [Step(name, ("{py}", f"paper/scripts/{name}.py", "--build", "{build}", *quick),
                 (f"data/{name}.json",), ("paper/scripts/*.py",)) for name in names]


def benchmark_steps(large: bool) -> list[Step]:
    """Return the benchmarks behind the optional sections, at paper or at full sizes.

    Paper sizes fit a 2-core machine (the measured minutes are in ``docs/notes/paper.md``);
    ``large`` runs each benchmark at its own default sizes (hours).
    """
    out = "{build}/" + BENCH_DIR
    quick = () if large else ("--quick",)
    size = "160k" if large else "10k"

    def step(name: str, args: tuple[str, ...], output: str, launcher: tuple[str, ...] = (),
             resumable: bool = False) -> Step:
        """``benchmarks/<name>.py ARGS --out DIR/OUTPUT`` (``--out-dir DIR`` for a glob)."""
        target = ("--out-dir", out) if "*" in output else ("--out", f"{out}/{output}")
        return Step(name, (*launcher, "{py}", f"benchmarks/{name}.py", *args, *target),
                    (f"{BENCH_DIR}/{output}",), ("benchmarks/*.py",), resumable)

    return [
        step("shell_kernels", quick, "shell_kernels.json"),
        step("shell_solve", (*quick, *(() if large else ("--systems", "local", "augmented"))),
             "shell_solve.json"),
        step("scaling", quick, "scaling.json"),
        step("iterative", ("--sizes", size, "--hessian", "exact", "--to-tolerance", "1e-8",
                           "--methods", "direct", "multigrid-phase-ew"),
             f"iterative_{size}_conv.json"),
        step("decomposition", quick, "decomposition_*.json", launcher=("{mpiexec}", "-n", "2")),
        step("split_scaling", ("--levels", "4" if large else "3", "--ranks", "1", "2"),
             "split_scaling.json"),
        step("speed_accuracy", ("--resume", *(() if large else SPEED_ACCURACY_PAPER)),
             "speed_accuracy.json", resumable=True),
    ]


def steps_of(args: argparse.Namespace) -> list[Step]:
    """Every step ``make paper`` runs with these options, in order."""
    benches = [] if args.quick or args.no_benchmarks else benchmark_steps(args.large)
    return script_steps(args) + benches


# --- data and placeholders --------------------------------------------------------------------

def load_own(build: Path) -> dict[str, Any]:
    """Load the JSON of our scripts; ``PaperError`` naming the script when one is missing."""
    data = {}
    for name in OWN_SCRIPTS:
        path = build / "data" / f"{name}.json"
        if not path.is_file():
            raise PaperError(f"{path} is missing: run 'python paper/scripts/{name}.py "
                             f"--build {build}' (or 'python paper/make_paper.py --quick')")
        data[name] = json.loads(path.read_text())
    return data


def lookup(data: dict[str, Any], path: str) -> Any:
    """Value at the dotted ``path`` (dict keys, integer list indices) of ``data``."""
    value: Any = data
    for key in path.split("."):
        if isinstance(value, list) and re.fullmatch(r"-?\d+", key):
            value = value[int(key)]
        elif isinstance(value, dict) and key in value:
            value = value[key]
        else:
            raise KeyError(key)
    return value


def fill(template: str, data: dict[str, Any], blocks: dict[str, str],
         provenance: list[dict[str, Any]]) -> str:
    """Replace every placeholder; record each number's source in ``provenance``."""
    def replace(match: re.Match[str]) -> str:
        path, spec = match.group(1), match.group(2) or ""
        if path == "block":
            if spec not in blocks:
                raise PaperError(f"template block {{{{block:{spec}}}}} is not generated")
            return blocks[spec]
        try:
            value = lookup(data, path)
        except (KeyError, IndexError):
            script = path.split(".", 1)[0]
            raise PaperError(f"template placeholder {{{{{path}}}}}: no such key; rerun "
                             f"'python paper/scripts/{script}.py'") from None
        text = format(value, spec)
        provenance.append({"placeholder": path, "format": spec, "value": value, "text": text,
                           "file": f"data/{path.split('.', 1)[0]}.json"})
        return text

    return PLACEHOLDER.sub(replace, template)


# --- tables ---------------------------------------------------------------------------------

def fmt(value: Any) -> str:
    """Format a table cell: 4 significant digits for floats, plain text otherwise."""
    if isinstance(value, bool) or not isinstance(value, float):
        return str(value)
    return f"{value:.4g}"


def rows_of(doc: Any) -> list[dict[str, Any]]:
    """Return the row dicts of a benchmark JSON (``rows``, ``results``, ``cases``, a list)."""
    if isinstance(doc, list):
        return [r for r in doc if isinstance(r, dict)]
    for key in ("rows", "results", "cases", "table", "points"):
        if isinstance(doc, dict) and isinstance(doc.get(key), list):
            return rows_of(doc[key])
    return [doc] if isinstance(doc, dict) else []


def scalar_columns(rows: Sequence[dict[str, Any]], limit: int = 9) -> list[str]:
    """Return the first ``limit`` keys holding scalars (str, int, float, bool) in the rows."""
    columns: list[str] = []
    for row in rows:
        for key, value in row.items():
            if key not in columns and isinstance(value, str | int | float | bool):
                columns.append(key)
    return columns[:limit]


def cell(row: dict[str, Any], column: str) -> Any:
    """Return the value of a (dotted) column in a row; empty when absent."""
    try:
        return lookup(row, column)
    except (KeyError, IndexError):
        return ""


def markdown_table(rows: Sequence[dict[str, Any]], columns: Sequence[str]) -> str:
    """Markdown table of ``rows`` (dotted columns reach into nested dicts; missing: empty)."""
    head = "| " + " | ".join(columns) + " |\n|" + "---|" * len(columns) + "\n"
    body = "".join("| " + " | ".join(fmt(cell(r, c)) for c in columns) + " |\n"
                   for r in rows)
    return head + body


def table_columns(source: Source, rows: Sequence[dict[str, Any]]) -> list[str]:
    """Return the source's preferred columns present in the rows, else the first scalars."""
    present = [c for c in source.columns if any(cell(r, c) != "" for r in rows)]
    return present if len(present) >= 2 else scalar_columns(rows)


def source_block(source: Source, build: Path, strict: bool) -> tuple[str, list[Path]]:
    """Markdown section of an optional source: its tables and figures, or "not run"."""
    pattern = source.pattern.format(build=build)
    base = Path(pattern).parent if Path(pattern).is_absolute() else REPO / Path(pattern).parent
    files = sorted(base.glob(Path(pattern).name))
    if not files:
        if strict:
            raise PaperError(f"--strict: {pattern} is missing; run '{source.command}'")
        return (f"*Not run* (no `{source.pattern.format(build='paper/build')}`; "
                f"produce it with `{source.command}`).\n", [])
    if source.render is not None:  # its own text, then the plots beside the JSON files
        figures = [line for path in files for line in sibling_figure(path, build)]
        return "\n".join([source.render(source, files), *figures]), files
    parts = []
    for path in files:
        doc = json.loads(path.read_text())
        rows = mark_pareto(doc, rows_of(doc))
        parts.append(f"Table: {source.title} (`{path.name}`).\n\n"
                     + markdown_table(rows, table_columns(source, rows)))
        parts.extend(figure_lines(doc, build) + sibling_figure(path, build) + fit_lines(doc))
    named = f"figures/{source.name}.png"
    if (build / named).is_file() and not any(named in part for part in parts):
        parts.append(f"![{source.name}]({named})\n")  # e.g. wavelength.py's figure
    return "\n".join(parts), files


def fit_lines(doc: Any) -> list[str]:
    """Table of the growth exponents a JSON lists in ``meta.exponents`` (benchmarks/scaling.py).

    Each entry ``{name: {"p", "rms_log_residual", "max_log_residual", "local"}}`` is the
    least-squares line of ``log y`` on ``log n``; older JSON (bare floats) gives nothing.
    """
    fits = doc.get("meta", {}).get("exponents") if isinstance(doc, dict) else None
    if not isinstance(fits, dict) or not all(isinstance(v, dict) for v in fits.values()):
        return []
    rows = [{"quantity": k, "exponent_p": v["p"], "rms_log_residual": v["rms_log_residual"],
             "max_log_residual": v["max_log_residual"],
             "local_slopes": " / ".join(f"{s:.3g}" for s in v["local"])}
            for k, v in fits.items()]
    return ["Table: Fitted growth exponents, y ~ n^p (least squares on log-log).\n\n"
            + markdown_table(rows, ("quantity", "exponent_p", "rms_log_residual",
                                    "max_log_residual", "local_slopes"))]


def mark_pareto(doc: Any, rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Add ``pareto = True/False`` to rows when the JSON lists Pareto-optimal row names."""
    front = doc.get("pareto") if isinstance(doc, dict) else None
    if not isinstance(front, list):
        return rows
    return [{**r, "pareto": r.get("name") in front} for r in rows]


def sibling_figure(path: Path, build: Path) -> list[str]:
    """Copy ``<json stem>.png`` beside a benchmark JSON into ``figures/``; its image line."""
    png = path.with_suffix(".png")
    if path.parent == build / "data" or not png.is_file():
        return []
    (build / "figures").mkdir(parents=True, exist_ok=True)
    shutil.copyfile(png, build / "figures" / png.name)
    return [f"![{png.stem}](figures/{png.name})\n"]


def figure_lines(doc: Any, build: Path) -> list[str]:
    """Markdown image lines for the ``figures`` a JSON lists (paths relative to the build)."""
    figures = doc.get("figures", []) if isinstance(doc, dict) else []
    return [f"![{Path(f).stem}]({f})\n" for f in figures if (build / f).is_file()]


# --- our blocks -------------------------------------------------------------------------------

def scene_table(scenes: dict[str, Any]) -> str:
    """Table of the three scenes: sizes, iterations, wall times, amplitudes."""
    columns = ("scene", "frames", "body_vertices", "shell_vertices", "clusters",
               "body_newton_iterations", "shell_iterations", "wall_time_s",
               "wrinkle_amplitude_max")
    rows = [{"scene": name, **entry} for name, entry in scenes.items()
            if isinstance(entry, dict) and "figure" in entry]
    return markdown_table(rows, columns)


def convergence_table(conv: dict[str, Any]) -> str:
    """Table of the body L2 errors per size and degree."""
    rows = [{"degree": k, "n": n, "l2_error": e, "fitted_rate": v["rate"]}
            for k, v in conv["body"].items() for n, e in zip(v["n"], v["l2_error"],
                                                              strict=True)]
    return markdown_table(rows, ("degree", "n", "l2_error", "fitted_rate"))


def taylor_table(taylor: dict[str, Any]) -> str:
    """Table of the fitted Taylor slopes per shell term."""
    rows = [{"term": k, "value_slope": v["slope_value"], "gradient_slope": v["slope_gradient"]}
            for k, v in taylor["terms"].items()]
    return markdown_table(rows, ("term", "value_slope", "gradient_slope"))


def limits_table(limits: dict[str, Any]) -> str:
    """Table of the cylinder / sphere bending limits against the closed forms."""
    rows = [{"case": f"cylinder, {v['lattice']} lattice, {v['angle_deg']:g} deg",
             "limit": v["limit"], "closed_form": v["predicted"], "order": v["order"],
             "rel_error": v["limit_rel_error"]} for v in limits["cylinder"].values()]
    s = limits["sphere"]
    rows.append({"case": "icosphere / 16 pi", "limit": s["limit"], "closed_form":
                 s["predicted"], "order": s["order"], "rel_error": s["limit_abs_error"]})
    return markdown_table(rows, ("case", "limit", "closed_form", "order", "rel_error"))


def figure(build: Path, rel: str, caption: str) -> str:
    """Markdown image with caption; ``PaperError`` when the file is missing."""
    if not (build / rel).is_file():
        raise PaperError(f"figure {rel} missing from {build}")
    return f"![{caption}]({rel})\n\n*{caption}*\n"


SCENE_CAPTIONS: dict[str, str] = {
    "default": "Default scene: soft bar with a stiff skin compressed along its axis.",
    "bent_bar": "Bent bar: end faces turned in opposite directions; the lower face is "
                "compressed.",
    "twisted_cylinder": "Twisted cylinder: one end clamped, the other turned about the axis.",
}
FIGURES: dict[str, tuple[str, str]] = {
    "figure_convergence": ("figures/body_convergence.png",
                           "L2 error of the body displacement against h, P1 and P2."),
    "figure_torsion": ("figures/torsion.png", "Relative torque error of the twisted P2 "
                       "cylinder against the circular and the meshed polar moment."),
    "figure_limits": ("figures/shell_limits.png", "Hinge bending energy density on a unit "
                      "cylinder: relative distance to the extrapolated limit."),
    "figure_taylor": ("figures/taylor.png", "Taylor remainders of the shell energy terms "
                      "(value and gradient)."),
}


def ball_sofa_blocks(ball: dict[str, Any], build: Path) -> dict[str, str]:
    """Figures of the ball on the sofa: the time plot, and the shell render (full mode only)."""
    plot = figure(build, "figures/ball_sofa.png", "Rigid ball on the sofa: centre height, "
                  "vertical velocity and contact force against time.")
    render = ball.get("render")
    if render is None:
        return {"figure_ball_sofa": plot, "figure_scene_ball_sofa": "*Shell render not made "
                "in quick mode (`python paper/scripts/ball_sofa.py` makes it).*\n"}
    return {"figure_ball_sofa": plot, "figure_scene_ball_sofa": figure(
        build, render, "Ball on sofa: the shell at the frame of deepest penetration (the "
        "ball is not drawn), coloured by log10 of the bending energy density.")}


def own_blocks(data: dict[str, Any], build: Path) -> dict[str, str]:
    """Tables and figures of our scripts."""
    scenes = data["scenes"]
    captions: dict[str, Callable[[], str]] = {
        "table_convergence": lambda: convergence_table(data["convergence"]),
        "table_taylor": lambda: taylor_table(data["taylor"]),
        "table_limits": lambda: limits_table(data["shell_limits"]),
        "table_scenes": lambda: scene_table(scenes),
    }
    blocks = {k: f() for k, f in captions.items()}
    blocks.update(ball_sofa_blocks(data["ball_sofa"], build))
    for name, what in SCENE_CAPTIONS.items():
        blocks[f"figure_{name}"] = figure(build, scenes[name]["figure"], f"{what} Last frame, "
                                          "coloured by log10 of the bending energy density.")
    for key, (rel, caption) in FIGURES.items():
        blocks[key] = figure(build, rel, caption)
    return blocks


def write_tables(build: Path, blocks: dict[str, str]) -> None:
    """Write every table block to ``tables/<name>.md``."""
    folder = build / "tables"
    folder.mkdir(parents=True, exist_ok=True)
    for name, text in blocks.items():
        if "| " in text:
            (folder / f"{name.removeprefix('table_')}.md").write_text(text)


# --- LaTeX (only when pdflatex exists) ---------------------------------------------------------

def markdown_to_latex(markdown: str) -> str:
    """Convert Markdown to LaTeX minimally (headings, images, tables as verbatim)."""
    out = [r"\documentclass{article}", r"\usepackage{graphicx,amsmath}", r"\begin{document}"]
    in_table = False
    for line in markdown.splitlines():
        if line.startswith("|") != in_table:
            out.append(r"\begin{verbatim}" if not in_table else r"\end{verbatim}")
            in_table = not in_table
        heading = re.match(r"(#+) (.*)", line)
        image = re.match(r"!\[(.*)\]\((.*)\)", line)
        if heading and not in_table:
            level = min(len(heading.group(1)), 3)
            out.append("\\" + "sub" * (level - 1) + "section*{" + heading.group(2) + "}")
        elif image:
            out.append(r"\begin{center}\includegraphics[width=0.7\linewidth]{"
                       + image.group(2) + "}\\end{center}")
        else:
            out.append(line if in_table else line.replace("%", r"\%").replace("_", r"\_"))
    out += [r"\end{verbatim}"] if in_table else []
    return "\n".join(out + [r"\end{document}", ""])


def build_pdf(build: Path, markdown: str) -> str:
    """Write ``paper.tex`` and run pdflatex when available; return what was done."""
    if shutil.which("pdflatex") is None:
        return "pdflatex not found: Markdown only"
    (build / "paper.tex").write_text(markdown_to_latex(markdown))
    proc = subprocess.run(["pdflatex", "-interaction=nonstopmode", "paper.tex"], cwd=build,
                          capture_output=True, text=True)
    return "paper.pdf built" if proc.returncode == 0 else "pdflatex failed (see paper.log)"


# --- main -------------------------------------------------------------------------------------

def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    """Command line of ``make_paper.py``."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--build", type=Path, default=PAPER / "build", help="build directory")
    parser.add_argument("--quick", action="store_true", help="tiny sizes, few frames (CI)")
    parser.add_argument("--strict", action="store_true",
                        help="fail when an optional source (benchmarks, wavelength, ...) is "
                        "missing instead of writing 'not run'")
    parser.add_argument("--rerun", action="store_true",
                        help="run every step, also those whose inputs did not change")
    parser.add_argument("--large", action="store_true",
                        help="run the benchmarks at their own full sizes (hours)")
    parser.add_argument("--no-benchmarks", action="store_true",
                        help="run no benchmark (their sections use existing JSON or say "
                        "'not run')")
    parser.add_argument("--run-external", action="store_true",
                        help="run paper/scripts/wavelength.py and artefacts.py in --quick "
                        "mode too (the full mode runs them by default)")
    parser.add_argument("--no-external", action="store_true",
                        help="never run wavelength.py / artefacts.py (use their JSON if any)")
    parser.add_argument("--no-run", action="store_true",
                        help="run no script: only rebuild the paper from existing JSON")
    args = parser.parse_args(argv)
    args.build = args.build.resolve()
    return args


def make(args: argparse.Namespace) -> Path:
    """Run everything and write ``paper.md``; return its path."""
    args.build.mkdir(parents=True, exist_ok=True)
    steps = [] if args.no_run else steps_of(args)
    try:
        times = run_steps(args.build, steps, args.rerun)
    except StepError as exc:
        raise PaperError(str(exc)) from None
    data = load_own(args.build)
    blocks = own_blocks(data, args.build)
    used: dict[str, list[str]] = {}
    for source in SOURCES:
        blocks[source.name], files = source_block(source, args.build, args.strict)
        used[source.name] = [str(f) for f in files]
    write_tables(args.build, blocks)
    provenance: list[dict[str, Any]] = []
    text = fill(TEMPLATE.read_text(), data, blocks, provenance)
    path = args.build / "paper.md"
    path.write_text(text)
    (args.build / "data" / "provenance.json").write_text(json.dumps(
        {"placeholders": provenance, "optional_sources": used, "script_wall_times_s": times,
         "quick": args.quick}, indent=1, default=str) + "\n")
    print(f"[paper] wrote {path} ({len(provenance)} numbers from JSON); "
          f"{build_pdf(args.build, text)}", flush=True)
    return path


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; exit 1 with a one-line message on a missing source."""
    try:
        make(parse_args(argv))
    except PaperError as exc:
        print(f"error: {exc}", file=sys.stderr, flush=True)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
