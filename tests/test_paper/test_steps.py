"""``paper/steps.py``: a step is rerun exactly when its command or an input file changed.

The steps here are tiny Python commands that count their runs in a file; the module's
repository root is pointed at a temporary tree so its digest covers only files of the test.
"""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path
from types import ModuleType

import pytest
from support import REPO


@pytest.fixture
def steps(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> ModuleType:
    spec = importlib.util.spec_from_file_location("paper_steps", REPO / "paper" / "steps.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, "paper_steps", module)  # dataclasses look it up
    spec.loader.exec_module(module)
    repo = tmp_path / "repo"
    (repo / "models").mkdir(parents=True)
    (repo / "models" / "energy.py").write_text("K = 1\n")
    (repo / "requirements.lock").write_text("numpy==2.0\n")
    (repo / "script.py").write_text("# the step's own source\n")
    monkeypatch.setattr(module, "REPO", repo)
    monkeypatch.setattr(module, "LIBRARY", ("models",))
    return module


def counting_step(steps: ModuleType, name: str = "count", fail: bool = False,
                  resumable: bool = False) -> object:
    """A step appending one line per run to ``{build}/runs.txt`` and writing ``out.json``."""
    code = ("import pathlib, sys; b = pathlib.Path(sys.argv[1]); "
            "open(b / 'runs.txt', 'a').write('run\\n'); "
            "old = (b / 'out.json').read_text() if (b / 'out.json').exists() else ''; "
            "(b / 'out.json').write_text(old + 'x'); "
            f"sys.exit({1 if fail else 0})")
    return steps.Step(name, ("{py}", "-c", code, "{build}"), ("out.json",), ("script.py",),
                      resumable)


def runs(build: Path) -> int:
    return len((build / "runs.txt").read_text().splitlines())


def test_step_runs_once_then_is_reused_until_an_input_changes(steps, tmp_path):
    build, step = tmp_path / "build", counting_step(steps)
    build.mkdir()
    assert steps.run_steps(build, [step]).keys() == {"count"}
    assert steps.run_steps(build, [step]) == {} and runs(build) == 1
    stamp = json.loads((build / "stamps" / "count.json").read_text())
    assert stamp["done"] and stamp["digest"] == step.digest() and stamp["seconds"] > 0
    for path, text in (("models/energy.py", "K = 2\n"), ("requirements.lock", "numpy==2.1\n"),
                       ("script.py", "# changed\n")):
        (steps.REPO / path).write_text(text)
        steps.run_steps(build, [step])
        steps.run_steps(build, [step])
    assert runs(build) == 4
    assert (build / "out.json").read_text() == "x"  # a rerun starts from nothing
    steps.run_steps(build, [step], rerun=True)
    assert runs(build) == 5


def test_changed_command_or_missing_output_reruns(steps, tmp_path):
    build, step = tmp_path / "build", counting_step(steps)
    build.mkdir()
    steps.run_steps(build, [step])
    other = steps.Step(step.name, (*step.argv, "--extra"), step.outputs, step.sources)
    steps.run_steps(build, [other])
    assert runs(build) == 2
    (build / "out.json").unlink()
    steps.run_steps(build, [other])
    assert runs(build) == 3


def test_failed_step_raises_and_is_not_reused(steps, tmp_path):
    build = tmp_path / "build"
    build.mkdir()
    with pytest.raises(steps.StepError, match=r"count failed \(exit 1\)"):
        steps.run_steps(build, [counting_step(steps, fail=True)])
    stamp = json.loads((build / "stamps" / "count.json").read_text())
    assert stamp["done"] is False
    steps.run_steps(build, [counting_step(steps)])
    assert runs(build) == 2


@pytest.mark.parametrize(("resumable", "expected"), [(True, "xx"), (False, "x")])
def test_killed_step_resumes_only_when_resumable(steps, tmp_path, resumable, expected):
    """A kill leaves a started stamp and partial output: kept by a resumable step only."""
    build, step = tmp_path / "build", counting_step(steps, resumable=resumable)
    build.mkdir()
    steps.write_stamp(build, step, step.digest(), None)  # started, never finished
    (build / "out.json").write_text("x")
    assert not steps.is_current(build, step, step.digest())
    steps.run_steps(build, [step])
    assert (build / "out.json").read_text() == expected
    assert steps.is_current(build, step, step.digest())


def test_command_fills_the_interpreter_and_build(steps, tmp_path):
    step = steps.Step("s", ("{mpiexec}", "-n", "2", "{py}", "x.py", "{build}/bench"), ())
    cmd = step.command(tmp_path)
    assert cmd[0] == str(Path(sys.executable).with_name("mpiexec"))
    assert cmd[3] == sys.executable and cmd[5] == f"{tmp_path}/bench"
