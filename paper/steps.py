"""The commands ``make paper`` runs, each skipped while its inputs are unchanged.

A :class:`Step` is one command (a figure script of ``paper/scripts/`` or a benchmark of
``benchmarks/``) and the files it writes under the build directory. Its *digest* is the
SHA-256 of its command line and of the content of every file it depends on: the library
(:data:`LIBRARY`), ``requirements.lock`` and its own sources. ``stamps/<name>.json`` records
the digest when a step starts and its wall time when it ends; the next run skips a step whose
stamp is complete with the same digest and whose outputs exist. A run that is killed loses at
most the step it was in (a *resumable* step, one that continues from its own partial output,
keeps that output if the digest is unchanged), so ``make paper`` resumes by being run again.
"""

from __future__ import annotations

import glob
import hashlib
import json
import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parent.parent
LIBRARY: tuple[str, ...] = ("models", "solvers", "meshes", "wrinkles", "validation", "scenes")
"""Folders every step depends on (their ``.py`` and ``.toml`` files), with the lock file."""


class StepError(RuntimeError):
    """A step's command failed (the message has the tail of its output)."""


@dataclass(frozen=True)
class Step:
    """One command of ``make paper``.

    Attributes:
        name: key of the step (its stamp is ``stamps/<name>.json``).
        argv: the command; ``{py}`` is this interpreter, ``{mpiexec}`` the venv's mpiexec,
            ``{build}`` the build directory.
        outputs: glob patterns of the files it writes, relative to the build directory; the
            step is complete when each matches a file.
        sources: files (globs relative to the repository) it depends on beside the library.
        resumable: the command continues from its partial outputs (e.g. ``--resume``).

    """

    name: str
    argv: tuple[str, ...]
    outputs: tuple[str, ...]
    sources: tuple[str, ...] = ()
    resumable: bool = False

    def command(self, build: Path) -> list[str]:
        """Return the command line with ``{py}``, ``{mpiexec}`` and ``{build}`` filled in."""
        values = {"py": sys.executable, "build": str(build),
                  # wrinkles.launch.mpiexec_path, not imported: importing the package caps
                  # the BLAS threads of every step started from here (wrinkles/__init__.py)
                  "mpiexec": str(Path(sys.executable).with_name("mpiexec"))}
        return [a.format(**values) for a in self.argv]

    def digest(self, library: str | None = None) -> str:
        """Return the SHA-256 of the command line (unfilled) and of every file it depends on.

        ``library`` is :func:`library_digest`, computed once for all steps of a run (``None``:
        computed here).
        """
        h = hashlib.sha256("\0".join(self.argv).encode())
        h.update((library or library_digest()).encode())
        return files_digest(h, [p for pattern in self.sources for p in sorted(REPO.glob(pattern))])

    def complete(self, build: Path) -> bool:
        """Tell whether every output pattern matches a file under ``build``."""
        return all(glob.glob(str(build / pattern)) for pattern in self.outputs)


def files_digest(h: Any, files: Sequence[Path]) -> str:
    """Add each file's path (relative to the repository) and content to ``h``; its hex digest."""
    for path in files:
        if path.is_file() and "__pycache__" not in path.parts:
            h.update(str(path.relative_to(REPO)).encode() + b"\0" + path.read_bytes())
    return str(h.hexdigest())


def library_digest() -> str:
    """Return the SHA-256 of the lock file and the library's ``.py``/``.toml`` files."""
    files = {REPO / "requirements.lock"}
    for folder in LIBRARY:
        for suffix in ("py", "toml"):
            files.update((REPO / folder).rglob(f"*.{suffix}"))
    return files_digest(hashlib.sha256(), sorted(files))


def stamp_path(build: Path, step: Step) -> Path:
    """Return the path of the stamp of ``step``."""
    return build / "stamps" / f"{step.name}.json"


def read_stamp(build: Path, step: Step) -> dict[str, object]:
    """Return the stamp of ``step`` (empty when there is none or it is unreadable)."""
    try:
        stamp = json.loads(stamp_path(build, step).read_text())
    except (OSError, ValueError):
        return {}
    return stamp if isinstance(stamp, dict) else {}


def write_stamp(build: Path, step: Step, digest: str, seconds: float | None) -> None:
    """Record ``digest``; ``seconds`` None marks the step as started, else as done."""
    path = stamp_path(build, step)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({"digest": digest, "done": seconds is not None,
                                "seconds": seconds, "argv": list(step.argv)}, indent=1))


def is_current(build: Path, step: Step, digest: str) -> bool:
    """Tell whether ``step`` ran to the end with ``digest`` and its outputs are there."""
    stamp = read_stamp(build, step)
    return bool(stamp.get("done")) and stamp.get("digest") == digest and step.complete(build)


def run_step(build: Path, step: Step, label: str, digest: str) -> float:
    """Run ``step`` and stamp it.

    Outputs of an earlier attempt are removed first, unless the step is resumable and that
    attempt had the same digest.

    Args:
        build: the build directory.
        step: the step.
        label: progress prefix, e.g. ``"(3/12)"``.
        digest: the step's :meth:`Step.digest`.

    Returns:
        Its wall time [s].

    Raises:
        StepError: non-zero exit; the message holds the end of its output.

    """
    if not (step.resumable and read_stamp(build, step).get("digest") == digest):
        for pattern in step.outputs:
            for old in glob.glob(str(build / pattern)):
                Path(old).unlink()
    write_stamp(build, step, digest, None)
    cmd = step.command(build)
    print(f"[paper] {label} {step.name}: {' '.join(cmd[1:])}", flush=True)
    started = time.perf_counter()
    proc = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True)
    seconds = time.perf_counter() - started
    if proc.returncode != 0:
        raise StepError(f"{step.name} failed (exit {proc.returncode}) after {seconds:.0f} s:\n"
                        f"{proc.stdout[-2000:]}\n{proc.stderr[-4000:]}")
    if not step.complete(build):
        raise StepError(f"{step.name} exited 0 but did not write {', '.join(step.outputs)}")
    write_stamp(build, step, digest, seconds)
    print(f"[paper] {label} {step.name}: done in {seconds:.0f} s", flush=True)
    return seconds


def run_steps(build: Path, steps: Sequence[Step], rerun: bool = False) -> dict[str, float]:
    """Run the steps in order, skipping the current ones unless ``rerun``; their wall times."""
    times: dict[str, float] = {}
    library = library_digest()
    for i, step in enumerate(steps, 1):
        label, digest = f"({i}/{len(steps)})", step.digest(library)
        if not rerun and is_current(build, step, digest):
            print(f"[paper] {label} {step.name}: inputs unchanged, reused", flush=True)
            continue
        times[step.name] = run_step(build, step, label, digest)
    return times
