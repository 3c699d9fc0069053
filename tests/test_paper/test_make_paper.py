"""``make paper`` quick mode: the generated files, filled template and traceable numbers.

Runs ``paper/make_paper.py --quick`` once (all scripts on tiny sizes, the scenes on the coarse
settings of tests/test_wrinkles/test_scenes_bend_twist.py) into a temporary build directory.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
from support import REPO

TEMPLATE = REPO / "paper" / "paper.md.in"
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
SECTIONS = ("1 Introduction", "2 Related Work", "3 Method Overview", "4.1 Elastic",
            "4.2 Shell", "4.3 Constraint with Local Support", "5 Acceleration via Cluster",
            "6.1 Interpolation", "6.2 SQP", "6.3 Modules", "7.1 Scenes",
            "7.2 Wrinkle Wavelength", "7.3 Element-Boundary Artefacts",
            "7.4 Speed and Accuracy", "7.5 Ball on sofa (the draft's experiment)",
            "8 Discussion", "9 Conclusion", "10 Reference")


def make_paper(*args: str, timeout: float = 900) -> subprocess.CompletedProcess[str]:
    """Run ``python paper/make_paper.py ARGS``."""
    env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
    return subprocess.run([sys.executable, str(REPO / "paper" / "make_paper.py"), *args],
                          capture_output=True, text=True, timeout=timeout, cwd=REPO, env=env)


@pytest.fixture(scope="module")
def build(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("paper") / "build"
    proc = make_paper("--quick", "--build", str(out))
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return out


def sections(text: str) -> dict[str, str]:
    """Heading text -> body text up to the next heading."""
    parts = re.split(r"^#{2,3} (.+)$", text, flags=re.MULTILINE)
    return {parts[i].strip(): parts[i + 1] for i in range(1, len(parts) - 1, 2)}


def test_every_section_is_filled_and_no_placeholder_is_left(build):
    text = (build / "paper.md").read_text()
    body = sections(text)
    for name in SECTIONS:
        assert name in body, f"section {name} missing"
        assert len(body[name].split()) >= 5, f"section {name} is empty"
    assert "{{" not in text and "}}" not in text


def test_every_figure_listed_exists_and_is_a_png(build):
    text = (build / "paper.md").read_text()
    figures = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", text)
    own = {"figures/body_convergence.png", "figures/torsion.png", "figures/shell_limits.png",
           "figures/taylor.png", "figures/scene_default.png", "figures/scene_bent_bar.png",
           "figures/scene_twisted_cylinder.png", "figures/ball_sofa.png"}
    assert own <= set(figures)
    for rel in figures:
        data = (build / rel).read_bytes()
        assert data[:8] == PNG_MAGIC and len(data) > 1000, rel


def test_numbers_come_from_json(build):
    """Every placeholder resolved from a JSON file; no measured decimal typed in the template."""
    provenance = json.loads((build / "data" / "provenance.json").read_text())["placeholders"]
    assert len(provenance) >= 25
    for entry in provenance:
        path = build / entry["file"]
        doc = json.loads(path.read_text())
        value = doc
        for key in entry["placeholder"].split(".")[1:]:
            value = value[int(key)] if isinstance(value, list) else value[key]
        assert value == entry["value"]
        assert format(value, entry["format"]) == entry["text"]
    template = TEMPLATE.read_text()
    prose = re.sub(r"\{\{[^{}]*\}\}", "", template)
    prose = re.sub(r"^#+ .*$|section \d+(\.\d+)?", "", prose, flags=re.MULTILINE)  # numbering
    typed = re.findall(r"(?<![\w.])\d+\.\d+|\d(?:\.\d+)?e[-+]?\d+|\d+(?:\.\d+)?\s?%", prose)
    assert typed == [], f"numbers typed by hand in paper.md.in: {typed}"


def test_tables_written_from_json(build):
    for name in ("convergence", "taylor", "limits", "scenes"):
        table = (build / "tables" / f"{name}.md").read_text()
        assert table.startswith("| ") and table.count("\n") >= 3
    scenes = json.loads((build / "data" / "scenes.json").read_text())
    assert scenes["meta"]["quick"] is True
    assert scenes["bent_bar"]["amplitude_ratio"] > 2.0  # same bound as test_scenes_extra
    assert abs(scenes["twisted_cylinder"]["end_angle_error"]) < 1e-10


@pytest.mark.mpi
def test_ball_sofa_numbers_match_its_run(build):
    """data/ball_sofa.json against the run's summary.json and
    tests/test_wrinkles/test_scene_ball_sofa.py's bounds.

    Quick mode: scenes/ball_sofa_coarse.toml, 10 frames, one subdivision level, no render.
    """
    ball = json.loads((build / "data" / "ball_sofa.json").read_text())
    frames = json.loads((build / "runs" / "ball_sofa" / "summary.json").read_text())["frames"]
    assert ball["meta"]["quick"] is True and ball["frames"] == len(frames) == 10
    assert ball["series"]["vz"] == [f["details"]["balls"][0]["velocity"][2] for f in frames]
    assert ball["impact_frame"] == 3  # as test_ball_sofa (measured: frame 3, 1.294 m/s)
    assert 0.3 < ball["restitution"] < 1.0  # measured 0.615 (0.796 / 1.294 m/s)
    assert 0.005 < ball["max_penetration_rel"] < 0.02  # measured 0.0137
    assert ball["momentum_residual_rel"] < 1e-9  # measured 2.1e-11 of 13.5 N s
    assert 2 <= ball["max_rigid_iterations"] <= 5  # measured 4
    assert ball["contact_force_peak"] > ball["weight"]  # measured 303 N against 49 N
    assert "render" not in ball  # quick mode renders nothing
    two = ball["two_ranks"]  # the same scene under mpiexec -n 2: overlapped, the same frames
    assert two["layout"] == "overlap" and two["same_frames"] is True
    assert "takes the overlap layout" in (build / "paper.md").read_text()
    assert "not made in quick mode" in (build / "paper.md").read_text()


def test_missing_source_names_the_script(tmp_path):
    """--no-run on an empty build: a one-line error naming the script to run, exit 1."""
    proc = make_paper("--no-run", "--build", str(tmp_path / "empty"), timeout=120)
    assert proc.returncode == 1
    assert "paper/scripts/convergence.py" in proc.stderr


def test_strict_mode_refuses_missing_optional_sources(build):
    """--strict --no-run: wavelength.json etc. absent from the build -> error naming it."""
    if (build / "data" / "wavelength.json").is_file():
        pytest.skip("wavelength.json present in this build")
    proc = make_paper("--strict", "--no-run", "--build", str(build), timeout=120)
    assert proc.returncode == 1
    assert "--strict" in proc.stderr and "wavelength" in proc.stderr
