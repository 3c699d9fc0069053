"""The README's commands and examples are ones the code takes.

A user copies them first: every ``wrinkles`` command of its shell blocks parses, and the
scene it runs (with its ``--set`` keys) passes ``wrinkles check``; the expert-mapping example
is accepted; every file it names exists; every benchmark command of its results table names a
script that has each of the command's flags, every test it names exists.
"""

from __future__ import annotations

import functools
import json
import re
import shlex
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from wrinkles.cli import build_parser, main

REPO = Path(__file__).resolve().parents[1]
README = (REPO / "README.md").read_text()


def shell_blocks(text: str) -> list[str]:
    """The lines of the fenced ``bash`` blocks, comments removed, continuations joined."""
    lines: list[str] = []
    for block in re.findall(r"```bash\n(.*?)```", text, flags=re.S):
        for line in block.replace("\\\n", " ").splitlines():
            command = line.split("#", 1)[0].strip()
            if command:
                lines.append(command)
    return lines


def wrinkles_argv(line: str) -> list[str] | None:
    """The arguments after ``wrinkles`` in a shell line (``mpiexec -n N`` before it), or None."""
    words = shlex.split(line)
    for k, word in enumerate(words):
        if Path(word).name == "wrinkles":
            return words[k + 1:]
    return None


COMMANDS = [argv for line in shell_blocks(README)
            if (argv := wrinkles_argv(line)) and not argv[0].startswith("-")]  # not --version
SCENE_RUNS = sorted({(args.scene, tuple(args.overrides)) for args in (  # a bad flag: below
    build_parser().parse_known_args(argv)[0] for argv in COMMANDS if argv[0] == "run")})


def test_the_readme_has_the_commands_this_test_reads() -> None:
    """The blocks hold run, check, render, view and plot commands (the parsing found them)."""
    assert {argv[0] for argv in COMMANDS} == {"run", "check", "render", "view", "plot"}
    assert len(SCENE_RUNS) >= 8


@pytest.mark.parametrize("argv", COMMANDS, ids=[" ".join(a) for a in COMMANDS])
def test_every_wrinkles_command_of_the_readme_parses(argv: list[str]) -> None:
    args = build_parser().parse_args(argv)
    assert args.command == argv[0]


@pytest.mark.parametrize(("scene", "overrides"), SCENE_RUNS,
                         ids=[" ".join([str(s), *o]) for s, o in SCENE_RUNS])
def test_every_scene_the_readme_runs_passes_the_check(
        scene: Path, overrides: tuple[str, ...], monkeypatch, capsys) -> None:
    """``wrinkles check`` of the run's scene and keys exits 0 (its pins, obstacles, sizes)."""
    monkeypatch.chdir(REPO)
    argv = ["check", str(scene)] + [a for key in overrides for a in ("--set", key)]
    assert main(argv) == 0
    resolved = json.loads(capsys.readouterr().out)
    for key in overrides:  # the scene the check resolved carries each key the command sets
        path, value = key.split("=", 1)
        node = resolved["scene"]
        for part in path.split("."):
            node = node[part]
        assert node == tomllib.loads(f"v = {value}")["v"], key


def dotted(table: dict, prefix: str = "") -> dict:
    """A nested table's leaves under dotted keys (keys already dotted stay as they are)."""
    out: dict = {}
    for key, value in table.items():
        out |= dotted(value, f"{prefix}{key}.") if isinstance(value, dict) else {
            prefix + key: value}
    return out


def test_the_readme_expert_mapping_example_is_accepted(tmp_path: Path, monkeypatch,
                                                        capsys) -> None:
    """The ``[shell.solver.options]`` / ``[newton.options]`` / ``[rigid.options]`` example,
    appended to the demo's scene (a ball, a shell), resolves to the values it writes."""
    example = re.findall(r"```toml\n(.*?)```", README, flags=re.S)
    assert len(example) == 1 and "[shell.solver.options]" in example[0]
    scene = tmp_path / "expert.toml"
    scene.write_text((REPO / "scenes" / "ball_sofa_coarse.toml").read_text() + "\n" + example[0])
    monkeypatch.chdir(REPO)
    assert main(["check", str(scene)]) == 0
    resolved = json.loads(capsys.readouterr().out)["resolved"]
    written = tomllib.loads(example[0])
    tables = {("shell", "solver", "options"): ("shell", "internals"), ("newton", "options"):
              ("newton",), ("rigid", "options"): ("rigid",)}
    checked = 0
    for table, home in tables.items():
        values = written
        for part in table:
            values = values[part]
        node = resolved
        for part in home:
            node = node[part]
        found = dotted(node)
        for key, value in values.items():  # "newton.shift_decay" = 10.0 -> internals' path
            assert found[key] == value, ".".join((*table, key))
            checked += 1
    assert checked == 8


FILE = re.compile(r"`((?:docs|scenes|wrinkles|models|solvers|meshes|benchmarks|paper|tests|"
                  r"tools|validation)/[\w./-]+\.(?:py|md|toml|png))")


@pytest.mark.parametrize("doc", ["README.md", "CONTRIBUTING.md", "paper/README.md"])
def test_every_file_the_readme_names_exists(doc: str) -> None:
    """Every backticked path of the repository in the README (and the other guides) exists."""
    text = (REPO / doc).read_text()
    named = sorted({name for name in FILE.findall(text) if "/build/" not in name})  # not made
    assert len(named) >= 3
    missing = [name for name in named if not (REPO / name).exists()]
    assert not missing, missing


@functools.cache
def script_help(script: str) -> str:
    """The ``--help`` text of a script of the repository."""
    proc = subprocess.run([sys.executable, script, "--help"], cwd=REPO, capture_output=True,
                          text=True, timeout=300, check=False)
    assert proc.returncode == 0, f"{script} --help: {proc.stderr}"
    return proc.stdout


def table_commands(text: str) -> list[list[str]]:
    """The backticked ``python SCRIPT ...`` / ``pytest ...`` commands of the tables' rows."""
    found = []
    for command in re.findall(r"`([^`]*)`", text):
        words = re.sub(r"[\[\]]", " ", command).split()
        words = words[words.index("python"):] if "python" in words else words
        if words and words[0] in ("python", "pytest") and len(words) > 1:
            found.append(words)
    return found


TABLE_COMMANDS = table_commands(README)


@pytest.mark.parametrize("words", TABLE_COMMANDS, ids=[" ".join(w) for w in TABLE_COMMANDS])
def test_every_script_command_of_the_readme_names_what_exists(words: list[str]) -> None:
    """A script's every ``--flag`` is in its ``--help``; a test node is a test."""
    if words[0] == "python":
        assert (REPO / words[1]).is_file(), words[1]
        flags = set(re.findall(r"--[\w-]+", script_help(words[1])))
        for flag in (w for w in words[2:] if w.startswith("--")):
            assert flag in flags, f"{words[1]}: {flag}"
        return
    for word in (w for w in words[1:] if w.startswith("tests/")):
        path, _, name = word.partition("::")
        assert (REPO / path).is_file(), path
        if name:
            assert re.search(rf"^def {re.escape(name)}\(", (REPO / path).read_text(),
                             flags=re.M), word


def test_the_readme_counts_the_scene_keys_the_tool_counts() -> None:
    """"N keys in all: `python tools/scene_keys.py --list`" says the tool's first number."""
    said = re.search(r"(\d+) keys in all: `python tools/scene_keys.py --list`", README)
    assert said is not None
    proc = subprocess.run([sys.executable, "tools/scene_keys.py"], cwd=REPO, capture_output=True,
                          text=True, timeout=300, check=True)
    assert int(proc.stdout.split()[0]) == int(said.group(1))
