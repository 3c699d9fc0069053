"""The overlapped layout of ``mpiexec -n 2 wrinkles run`` (:mod:`wrinkles.overlap`).

The demo scene (a ball dropped onto a coarse sofa, one-way skin) takes it by default on two
ranks: rank 1 steps the body and ball, rank 0 the shell and the output. Its frames must be the
serial run's bit for bit (records, both XDMF series, the checkpoint), a resumed run (on two
ranks or one) the straight run's, and a failure on either rank must end both with exit 2 and
the serial run's one-line message and ``summary.json``. The layout choice is checked on the
shipped scenes' sizes.
"""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from support import REPO, progress_lines, read_series, wrinkles

from meshes.errors import InputError
from wrinkles.checkpoint import read_state
from wrinkles.overlap import MAX_BODY_DOFS, Sizes, body_dofs, layout_for, scene_sizes
from wrinkles.runner import read_tet_mesh
from wrinkles.scene import load_scene

DEMO = REPO / "scenes" / "ball_sofa_coarse.toml"
ARGS = ["--set", "shell.subdivision.levels=1", "--set", "output.render=false"]
"""The demo at one subdivision level (1 306 shell vertices), no render."""
BODY_FAILS = ["--set", "newton.options.max_it=3", "--set", "newton.options.max_halvings=0"]
"""Three body Newton iterations per step, no halving: frames 1-2 pass, frame 3 fails."""
SHELL_FAILS = ["--set", "shell.solver.rtol=1e-16",
               "--set", "shell.solver.options={'newton.stagnation_iterations'=2}"]
"""A tolerance below round-off: the shell Newton stagnates in frame 1 and fails."""
TIMING = ("wall_time", "cpu_time", "stage_times")
"""Record fields that measure the machine, not the frame."""
CLOCKS = re.compile(r"t_\w+=[0-9.]+s")
"""The shell Newton's timings in its failure message."""


def untimed(value: Any) -> Any:
    """``value`` (a message, or a document of them) with the shell Newton's timings blanked."""
    if isinstance(value, str):
        return CLOCKS.sub("t=...", value)
    if isinstance(value, dict):
        return {k: untimed(v) for k, v in value.items()}
    return value


def frames_of(out: Path) -> list[dict[str, Any]]:
    """The frame records of a run without their timings."""
    frames = json.loads((out / "summary.json").read_text())["frames"]
    return [{**{k: v for k, v in f.items() if k not in TIMING},
             "details": {k: v for k, v in f["details"].items() if "time" not in k}}
            for f in frames]


def assert_same_run(reference: Path, out: Path) -> None:
    """Records, both series and the checkpoint of ``out`` equal ``reference``'s bit for bit."""
    assert frames_of(out) == frames_of(reference)
    for name in ("body.xdmf", "shell.xdmf"):
        points, steps = read_series(out / name)
        ref_points, ref_steps = read_series(reference / name)
        np.testing.assert_array_equal(points, ref_points)
        assert [t for t, _ in steps] == [t for t, _ in ref_steps]
        for (_, data), (_, ref) in zip(steps, ref_steps, strict=True):
            assert data.keys() == ref.keys()
            for key in data:
                np.testing.assert_array_equal(data[key], ref[key], err_msg=f"{name} {key}")
    state, ref_state = read_state(out / "checkpoint.h5"), read_state(reference / "checkpoint.h5")
    assert (state.frame, state.time) == (ref_state.frame, ref_state.time)
    for name in ref_state.fields:
        np.testing.assert_array_equal(state.fields[name], ref_state.fields[name])
    for stage, arrays in ref_state.arrays.items():
        for name, values in arrays.items():
            np.testing.assert_array_equal(state.arrays[stage][name], values, err_msg=stage)


@pytest.fixture(scope="module")
def serial(tmp_path_factory) -> Path:
    """The demo's first four frames on one process."""
    out = tmp_path_factory.mktemp("serial")
    proc = wrinkles("run", str(DEMO), "--out", str(out), "--frames", "4", *ARGS)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return out


@pytest.mark.mpi
def test_two_ranks_overlap_the_demo_and_give_the_serial_frames(serial, mpiexec, tmp_path):
    """``mpiexec -n 2 wrinkles run`` on the demo: the stages overlapped by default, every
    record, series step and checkpoint array equal to the serial run's."""
    out = tmp_path / "overlap"
    proc = mpiexec(["-m", "wrinkles", "run", str(DEMO), "--out", str(out), "--frames", "4",
                    *ARGS], timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "layout: the body on rank 1, the shell and the output on rank 0" in proc.stdout
    assert len(progress_lines(proc.stdout)) == 4
    run = json.loads((out / "summary.json").read_text())["run"]
    reference = json.loads((serial / "summary.json").read_text())["run"]
    assert (run["layout"], run["ranks"], run["status"]) == ("overlap", 2, "completed")
    assert reference["layout"] == "serial"
    assert len(run["peak_memory_mb"]) == 2 and run["body_rank"]["wall_time"] > 0.0
    assert run["contact_facets"] == reference["contact_facets"]
    assert_same_run(serial, out)
    import matplotlib.pyplot as plt

    from wrinkles.plot import read_summary, summary_figure

    label = "body on rank 1 (overlapped)"
    summary = read_summary(out)
    (line,) = [x for x in summary_figure(summary, "o").axes[2].lines if x.get_label() == label]
    assert list(line.get_ydata()) == [f["details"]["body_rank_time"] for f in summary["frames"]]
    assert label not in [x.get_label() for x in
                         summary_figure(read_summary(serial), "s").axes[2].lines]
    plt.close("all")


@pytest.mark.mpi
@pytest.mark.parametrize(("scene", "extra"), [
    ("default.toml", []),                                   # static, pins moved by the load
    ("ball_sofa_coarse.toml", ["--set", "body.degree=2"]),  # a P2 body (auto would split it)
])
def test_an_overlap_asked_for_gives_the_serial_frames(scene, extra, mpiexec, tmp_path):
    """``shell.solver.layout = "overlap"`` on scenes ``"auto"`` splits: the frames are the
    serial run's bit for bit all the same (one process: the P2 demo's frame work, 6 087
    body dofs x 2 steps + 1 306 shell vertices, would take the cores as ranks)."""
    args = ["run", str(REPO / "scenes" / scene), "--frames", "2", *ARGS, *extra,
            "--set", "shell.solver.threads=1"]
    serial, out = tmp_path / "serial", tmp_path / "overlap"
    proc = wrinkles(*args, "--out", str(serial), timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    proc = mpiexec(["-m", "wrinkles", *args, "--out", str(out),
                    "--set", "shell.solver.layout='overlap'"], timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert json.loads((out / "summary.json").read_text())["run"]["layout"] == "overlap"
    assert_same_run(serial, out)


@pytest.mark.mpi
def test_a_resumed_overlapped_run_equals_the_resumed_serial_run(serial, mpiexec, tmp_path):
    """Two overlapped frames, then ``--resume --frames 4`` on two ranks (overlapped again)
    and on one rank: both equal the serial run resumed at frame 2 bit for bit, and the
    straight run to the solver's tolerance (a resumed dynamic shell starts a new
    factorisation, docs/notes/factor-reuse.md: other iterations, the same minimiser)."""
    head = ["run", str(DEMO), "--frames", "2", *ARGS]
    tail = ["run", str(DEMO), "--frames", "4", "--resume", *ARGS]
    reference, first = tmp_path / "serial", tmp_path / "first"
    for proc in (wrinkles(*head, "--out", str(reference), timeout=600),
                 wrinkles(*tail, "--out", str(reference), timeout=600),
                 mpiexec(["-m", "wrinkles", *head, "--out", str(first)], timeout=600)):
        assert proc.returncode == 0, proc.stderr[-2000:]
    for ranks in (2, 1):
        out = tmp_path / f"resumed{ranks}"
        shutil.copytree(first, out)
        proc = (mpiexec(["-m", "wrinkles", *tail, "--out", str(out)], timeout=600)
                if ranks == 2 else wrinkles(*tail, "--out", str(out), timeout=600))
        assert proc.returncode == 0, proc.stderr[-2000:]
        assert [line.split()[1] for line in progress_lines(proc.stdout)] == ["3/4", "4/4"]
        assert_same_run(reference, out)
    straight = [f["details"]["shell_energy"] for f in frames_of(serial)]
    resumed = [f["details"]["shell_energy"] for f in frames_of(reference)]
    print("shell energy straight", straight, "resumed", resumed)
    np.testing.assert_allclose(resumed, straight, rtol=1e-9)
    assert [f["energy"] for f in frames_of(reference)] == [f["energy"] for f in frames_of(serial)]


@pytest.mark.mpi
def test_a_killed_overlapped_run_resumes_to_the_straight_run(mpiexec, tmp_path):
    """SIGKILL of ``mpiexec -n 2`` (every rank) after two of six frames, then ``--resume``
    on two ranks: the series intact, the body frames equal to the straight serial run's bit
    for bit, the shell's energies to the solver's tolerance."""
    from killrun import kill_after_frames

    run = ["run", str(DEMO), "--frames", "6", *ARGS]
    straight, out = tmp_path / "straight", tmp_path / "out"
    proc = wrinkles(*run, "--out", str(straight), timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    done = kill_after_frames([*run, "--out", str(out)], out, after=2, delay=0.05, ranks=2)
    assert 2 <= done < 6
    resumed = mpiexec(["-m", "wrinkles", *run, "--out", str(out), "--resume"], timeout=600)
    assert resumed.returncode == 0, resumed.stderr[-2000:]
    for name in ("body.xdmf", "shell.xdmf"):
        assert [t for t, _ in read_series(out / name)[1]] == \
            [t for t, _ in read_series(straight / name)[1]]
    got, ref = frames_of(out), frames_of(straight)
    assert [f["energy"] for f in got] == [f["energy"] for f in ref]
    np.testing.assert_allclose([f["details"]["shell_energy"] for f in got],
                               [f["details"]["shell_energy"] for f in ref], rtol=1e-9)
    run_facts = json.loads((out / "summary.json").read_text())["run"]
    assert run_facts["layout"] == "overlap" and len(run_facts["restarts"]) == 1


@pytest.mark.mpi
@pytest.mark.parametrize("failure", ["body", "shell"])
def test_a_failure_on_either_rank_ends_both_as_the_serial_run_does(failure, mpiexec,
                                                                   tmp_path):
    """A body step failing on rank 1 (frame 3) or a shell solve failing on rank 0 (frame 1)
    ends both ranks with exit 2 and the serial run's one line on stderr; ``summary.json``
    keeps the frames before with the same failure and diagnostic."""
    force = BODY_FAILS if failure == "body" else SHELL_FAILS
    outs = {"serial": tmp_path / "serial", "overlap": tmp_path / "overlap"}
    args = ["run", str(DEMO), "--frames", "4", *ARGS, *force]
    serial = wrinkles(*args, "--out", str(outs["serial"]), timeout=600)
    overlap = mpiexec(["-m", "wrinkles", *args, "--out", str(outs["overlap"])], timeout=300)
    lines = {}
    for name, proc in (("serial", serial), ("overlap", overlap)):
        assert proc.returncode == 2, proc.stderr[-2000:]
        errors = [line for line in proc.stderr.splitlines() if not line.startswith("warning")]
        assert len(errors) == 1 and "Traceback" not in proc.stderr, proc.stderr[-2000:]
        lines[name] = untimed(errors[0])
    assert lines["overlap"] == lines["serial"]
    assert lines["serial"].startswith("error: body step failed at t=0.025" if failure == "body"
                                      else "error: shell solve failed")
    runs = [json.loads((outs[n] / "summary.json").read_text())["run"] for n in outs]
    for key in ("status", "failed_frame", "error", "diagnostic"):
        assert untimed(runs[1][key]) == untimed(runs[0][key]), key
    assert runs[0]["failed_frame"] == (3 if failure == "body" else 1)
    assert frames_of(outs["overlap"]) == frames_of(outs["serial"])


@pytest.mark.mpi
def test_an_overlap_the_run_cannot_take_is_refused(mpiexec):
    """``shell.solver.layout = "overlap"`` on a two-way scene under two ranks: exit 1, one
    line naming the key, before anything is built."""
    proc = mpiexec(["-m", "wrinkles", "run", str(REPO / "scenes" / "two_way_bar.toml"),
                    "--set", "shell.solver.layout='overlap'", "--out", "/nonexistent/out"],
                   timeout=120)
    assert proc.returncode == 1, proc.stderr
    assert proc.stderr.strip() == ("error: shell.solver.layout = \"overlap\": needs a one-way "
                                   "shell on two ranks (this run: two_way on 2 rank(s)); use "
                                   "\"auto\" or \"split\"")


@pytest.mark.parametrize(("scene", "layout", "dofs", "steps", "vertices"), [
    ("ball_sofa_coarse", "overlap", 1050, 2, 5218),
    ("ball_sofa", "split", 4386, 2, 16978),
    ("bunny_drop", "split", 14010, 4, 12534),
    ("default", "split", 516, 1, 2610),
    ("bent_bar", "split", 711, 1, 3586),
    ("twisted_cylinder", "split", 861, 1, 3730),
])
def test_auto_overlaps_only_the_demo_of_the_shipped_scenes(scene, layout, dofs, steps,
                                                           vertices):
    """The sizes counted from the mesh before the run equal the run's (``wrinkles run`` set-up
    lines), and ``"auto"`` overlaps the scene where it measured faster
    (docs/notes/overlap-layout.md): the demo; the larger bodies and the static scenes split."""
    loaded = load_scene(REPO / "scenes" / f"{scene}.toml", [])
    sizes = scene_sizes(loaded)
    assert sizes == Sizes(dofs, steps, vertices)
    assert layout_for(loaded, 2, lambda: sizes) == layout
    assert layout_for(loaded, 3, lambda: sizes) == "split"
    assert layout_for(loaded, 1, lambda: sizes) == "split"


def test_the_layout_key_and_its_refusals():
    """"split" and "overlap" are taken as asked where they apply; "overlap" on three ranks or
    a two-way scene is refused; a serial run ignores the key; "auto" counts the sizes only
    for a one-way scene of two or more frames on two ranks."""

    def never() -> Sizes:
        raise AssertionError("sizes counted")

    demo = load_scene(DEMO, [])
    forced = load_scene(DEMO, ["shell.solver.layout='overlap'"])
    assert layout_for(load_scene(DEMO, ["shell.solver.layout='split'"]), 2, never) == "split"
    assert layout_for(forced, 2, never) == "overlap"
    assert layout_for(forced, 1, never) == "split"
    with pytest.raises(InputError, match="on 3 rank"):
        layout_for(forced, 3, never)
    two_way = load_scene(REPO / "scenes" / "two_way_bar.toml", ["shell.solver.layout='overlap'"])
    with pytest.raises(InputError, match="two_way on 2 rank"):
        layout_for(two_way, 2, never)
    assert layout_for(load_scene(DEMO, ["time.frames=1"]), 2, never) == "split"
    assert layout_for(demo, 2, lambda: Sizes(MAX_BODY_DOFS + 3, 2, 100)) == "split"
    assert layout_for(demo, 2, lambda: Sizes(1050, 2, 20_000)) == "split"  # share 0.095
    assert layout_for(demo, 2, lambda: Sizes(1050, 2, 6000)) == "overlap"  # share 0.26
    assert Sizes(1050, 2, 5218).body_share == pytest.approx(2100 / 7318)


@pytest.mark.parametrize("degree", [1, 2])
def test_body_dofs_count_the_function_space(degree):
    """P1 and P2 dofs counted from the tets equal dolfinx's vector function space's."""
    from models.backend import MPI, dolfinx, mesh_from_arrays

    tet = read_tet_mesh(load_scene(DEMO, []).mesh)
    mesh = mesh_from_arrays(MPI.COMM_SELF, tet.points, tet.tets)
    space = dolfinx.fem.functionspace(mesh, ("Lagrange", degree, (3,)))
    imap = space.dofmap.index_map
    assert body_dofs(tet, degree) == imap.size_global * space.dofmap.index_map_bs


def test_check_prints_the_layout_two_ranks_would_take():
    """``wrinkles check`` names the layout of ``mpiexec -n 2``: the demo's overlap."""
    proc = wrinkles("check", str(DEMO))
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout)["resolved"]["shell"]["layout_on_2_ranks"] == "overlap"


@pytest.mark.mpi
@pytest.mark.parametrize("layout", ["overlap", "split"])
def test_two_ranks_share_the_render_and_draw_the_serial_pictures(layout, mpiexec, tmp_path):
    """With ``output.render`` both ranks of either layout render their share of the frames
    (same colour range, same camera): every PNG equals, pixel for pixel, the serial render of
    the same run's series; so do those of ``mpiexec -n 2 wrinkles render``."""
    from PIL import Image

    from wrinkles.render import render_run

    out = tmp_path / layout
    proc = mpiexec(["-m", "wrinkles", "run", str(DEMO), "--out", str(out), "--frames", "3",
                    "--set", "shell.subdivision.levels=1",
                    "--set", f"shell.solver.layout='{layout}'"], timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "rendered 6 files" in proc.stdout and "(frames over 2 rank(s))" in proc.stdout
    reference, again = tmp_path / "serial", tmp_path / "again"
    for copy in (reference, again):
        shutil.copytree(out, copy)
        shutil.rmtree(copy / "frames")
        for name in ("shell.png", "shell.gif"):
            (copy / name).unlink()
    written = render_run(reference)
    assert len(written) == 6
    for path in written[:-1]:  # the four frames and shell.png; the GIF is built from them
        mine = np.asarray(Image.open(out / path.relative_to(reference)).convert("RGB"))
        assert np.array_equal(mine, np.asarray(Image.open(path).convert("RGB"))), path.name
    with Image.open(out / "shell.gif") as gif:
        assert gif.n_frames == 4
    proc = mpiexec(["-m", "wrinkles", "render", str(again)], timeout=300)  # shared too
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.count("rendered 6 files") == 1
    for path in written[:-1]:
        mine = np.asarray(Image.open(again / path.relative_to(reference)).convert("RGB"))
        assert np.array_equal(mine, np.asarray(Image.open(path).convert("RGB"))), path.name
