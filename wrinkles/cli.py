"""Command-line interface of the ``wrinkles`` console script.

``wrinkles run SCENE.toml [--out DIR] [--frames N] [--set key=value ...] [--restart]`` runs a
scene (``--restart`` continues the run in ``DIR`` from its last completed frame);
``wrinkles check SCENE.toml [--set key=value ...]`` validates it and prints it resolved (JSON).

Exit codes: 0 ok; 1 bad input (``InputError``: one line ``error: <message>`` on stderr, no
traceback; also bad command-line usage); 2 solver failure (``SolverError``: the frames done so
far stay on disk) or an unexpected exception (a bug: its traceback is printed).

Under MPI every rank runs the same code. Errors raised on all ranks (scene validation, mesh
errors broadcast from rank 0, solver failures, which are collective) end the run with the
error's exit code after rank 0 prints the message. An error raised on some ranks only cannot
be agreed on while the others wait in a collective call: after ``AGREE_SECONDS`` without
agreement the failing rank prints its message and calls ``MPI_Abort`` with the exit code.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import sys
import time
import traceback
from collections.abc import Sequence
from pathlib import Path
from typing import Any, NoReturn

from models.errors import InputError, WrinklesError

AGREE_SECONDS = 10.0
"""How long a failing rank waits for the other ranks to fail too before ``MPI_Abort``."""


class ArgumentParser(argparse.ArgumentParser):
    """``argparse`` parser whose usage errors raise ``InputError`` (exit 1, one line)."""

    def error(self, message: str) -> NoReturn:
        """Raise ``InputError`` instead of printing usage and exiting with status 2."""
        raise InputError(f"{message} (see '{self.prog} --help')")


def build_parser() -> ArgumentParser:
    """Return the ``wrinkles`` argument parser."""
    parser = ArgumentParser(prog="wrinkles", description="Embedded thin shells for wrinkle "
                            "simulation on FEniCSx: run a scene file.")
    commands = parser.add_subparsers(dest="command", required=True, parser_class=ArgumentParser)
    run = add_scene_arguments(commands.add_parser("run", help="run a scene file (TOML)"))
    run.add_argument("--out", type=Path, default=None,
                     help="output directory (default: out/<scene name>)")
    run.add_argument("--frames", type=int, default=None, help="number of frames to run "
                     "(replaces time.frames / time.end_time)")
    run.add_argument("--restart", action="store_true", help="continue the run in --out "
                     "from its last completed frame (same scene; time, output, newton may change)")
    add_scene_arguments(commands.add_parser(
        "check", help="validate a scene file and print the resolved scene as JSON"))
    return parser


def add_scene_arguments(parser: ArgumentParser) -> ArgumentParser:
    """Add the scene file and the ``--set`` overrides to a sub-command; return it."""
    parser.add_argument("scene", type=Path, help="scene file, e.g. scenes/default.toml")
    parser.add_argument("--set", dest="overrides", action="append", default=[],
                        metavar="KEY=VALUE", help="override a scene key, value as a TOML "
                        "literal (repeatable), e.g. --set material.E=2e4")
    return parser


def one_line(message: str) -> str:
    """Collapse a message to one line for stderr."""
    return " ".join(message.split())


def command_run(args: argparse.Namespace) -> int:
    """Load the scene, apply ``--frames`` and ``--set``, run it (collective)."""
    from models.backend import MPI
    from wrinkles.runner import run_scene
    from wrinkles.scene import load_scene, with_frames

    scene = load_scene(args.scene, args.overrides)
    if args.frames is not None:
        scene = with_frames(scene, args.frames)
    out = args.out if args.out is not None else Path("out") / args.scene.stem
    run_scene(scene, out, MPI.COMM_WORLD, log=lambda line: print(line, flush=True),
              restart=args.restart)
    return 0


def command_check(args: argparse.Namespace) -> int:
    """Load and validate the scene (no mesh is built) and print it resolved, as JSON."""
    from models.backend import MPI
    from wrinkles.scene import load_scene, scene_dict

    scene = load_scene(args.scene, args.overrides)
    if MPI.COMM_WORLD.rank == 0:
        print(json.dumps(scene_dict(scene), indent=2), flush=True)
    return 0


COMMANDS = {"run": command_run, "check": command_check}
"""Sub-command name -> its function (``args -> exit code``)."""


def report(exc: BaseException) -> int:
    """Print the error as the exit-code contract says; return the exit code."""
    if isinstance(exc, WrinklesError):
        print(f"error: {one_line(str(exc))}", file=sys.stderr, flush=True)
        return exc.exit_code
    traceback.print_exception(exc, file=sys.stderr)
    print(f"error: unexpected {type(exc).__name__} (a bug, please report it with the "
          "traceback above)", file=sys.stderr, flush=True)
    return 2


def fail_collectively(exc: BaseException) -> int:
    """Agree with the other ranks on the failure, or abort them all; return the exit code.

    All ranks failing (the usual case: errors are collective) meet in a non-blocking barrier
    on a private communicator; rank 0 reports and everyone returns. If the others do not
    arrive within ``AGREE_SECONDS`` they are stuck elsewhere: report here and ``Abort``.
    """
    from models.backend import MPI

    comm = MPI.COMM_WORLD
    code = exc.exit_code if isinstance(exc, WrinklesError) else 2
    if comm.size == 1:
        return report(exc)
    request = agreement_comm().Ibarrier()
    deadline = time.monotonic() + AGREE_SECONDS
    while not request.Test():
        if time.monotonic() > deadline:
            print(f"[rank {comm.rank}] ", end="", file=sys.stderr)
            report(exc)
            comm.Abort(code)
        time.sleep(0.01)
    if comm.rank == 0:
        report(exc)
    return code


@functools.cache
def agreement_comm() -> Any:
    """Duplicate of COMM_WORLD used only to agree on failures (never mixed with solver traffic).

    Creating it is collective: :func:`main` calls this on every rank before any work.
    """
    from models.backend import MPI

    return MPI.COMM_WORLD.Dup()


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``wrinkles`` console script; return the exit code."""
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    try:
        args = build_parser().parse_args(argv)
    except InputError as exc:
        return report(exc)
    try:
        agreement_comm()
        return COMMANDS[args.command](args)
    except Exception as exc:  # noqa: BLE001  (mapped to exit codes, see module doc)
        return fail_collectively(exc)


def entry() -> NoReturn:
    """Run :func:`main` and exit with its code (``python -m wrinkles``)."""
    sys.exit(main())


if __name__ == "__main__":
    entry()
