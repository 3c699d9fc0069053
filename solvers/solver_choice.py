"""The shell Newton's linear solver and thread count when a scene leaves them to the code.

The choices, all by what the run is, not by flags:

* **Linear method by size, structure and load.** CG with geometric multigrid on the
  subdivision hierarchy (:mod:`solvers.multigrid`) when the shell has at least
  :data:`MULTIGRID_FROM_VERTICES` vertices and :data:`MULTIGRID_FROM_LEVELS` subdivision
  levels above the body's surface (:data:`MULTIGRID_STATIC_FROM_LEVELS` under a static load),
  else the sparse LDL^T (:mod:`solvers.linear`); measured on ``wrinkles run``
  (docs/notes/solver-choice.md).
* **The wrinkle-phase coarse space by size.** Multigrid-CG adds the phase space of
  :mod:`solvers.phase_space` to its V-cycle from :data:`PHASE_SPACE_FROM_VERTICES` shell
  vertices. It saves CG iterations at every size, but its set-up (the Galerkin matrix ``Z^T
  A Z`` and its LDL^T at every Newton matrix and shift) costs more than they are worth on
  the smaller shells (docs/notes/phase-space.md, measured over imperfection seeds). Where
  it is added, it serves a Newton solve that starts wrinkled or buckles
  (:func:`wrinkled_start`).
* **The shift ladder by the load.** A shell under a static load sequence (a compressed,
  bent or twisted body: the skin's compression grows frame by frame and its Hessian keeps
  negative curvature through each solve) follows its shifts down slowly: growth 5, decay 2.
  A shell of a dynamic scene (a body struck or dropped: the indefiniteness comes with the
  contact's transient and is gone after a step or two) keeps the textbook growth 10, decay 10
  (:func:`choose_shift_schedule`; docs/notes/shift-schedule.md).
* **Factorisation reuse by the load.** A shell of a dynamic scene moves little between the
  frames of its time steps: its Newton reuses one factorisation (or one multigrid set-up)
  across iterations and into the next frame while the steps keep reducing the gradient
  (modified Newton, :class:`solvers.shell_newton.ModifiedNewtonOptions`). A static load
  sequence factorises at every iteration: there the reuse leads the wrinkles onto other
  branches (:func:`choose_factor_reuse`; docs/notes/factor-reuse.md).
* **Ranks, then threads, by cores and size.** A frame of at least :data:`RANKS_FROM_WORK`
  shell vertices and body dof steps (a body alone :data:`RANKS_FROM_BODY_WORK`) runs a
  serial ``wrinkles run`` on the cores as MPI ranks (:func:`choose_ranks`; two ranks beat
  two threads, which leave PETSc serial); else a
  serial run of at least :data:`THREADS_FROM_VERTICES` vertices uses the cores this process
  may run on (its CPU affinity) as threads; smaller shells and every rank keep one thread.
* **The two-way joint system over the ranks by size.** Under MPI the joint body-shell system
  is split over the ranks (:mod:`solvers.decomposition.split_coupled`) for a multigrid-CG
  shell of at least :data:`SPLIT_JOINT_FROM_VERTICES` vertices; a smaller one is solved
  whole on every rank, where messages bound its CG (:func:`choose_joint_split`).
"""

from __future__ import annotations

import os
from typing import Literal

from meshes.errors import InputError
from solvers.shell_newton import LINEAR_METHODS as CONCRETE_METHODS

ConcreteMethod = Literal["direct", "multigrid"]

LINEAR_METHODS: tuple[str, ...] = ("auto", *CONCRETE_METHODS)
"""``[shell.solver] method`` values; "auto" is resolved by :func:`choose_linear_method`."""

MULTIGRID_FROM_VERTICES: int = 2000
"""Shell vertex count from which "auto" may select multigrid-CG instead of the direct solve."""

MULTIGRID_FROM_LEVELS: int = 2
"""Subdivision levels from which "auto" selects multigrid-CG under any load."""

MULTIGRID_STATIC_FROM_LEVELS: int = 1
"""Subdivision levels from which "auto" selects multigrid-CG under a static load (one level
leaves a coarse problem of a quarter of the unknowns: slower than the direct solve in a
dynamic scene, faster in a load sequence)."""


def choose_linear_method(method: str, vertices: int, levels: int, *,
                         static: bool) -> ConcreteMethod:
    """Return the concrete linear method: ``method`` itself, or for "auto" the one that pays.

    Args:
        method: "auto", "direct" or "multigrid".
        vertices: shell vertex count (>= 0).
        levels: subdivision levels of the shell above the body's surface (>= 0).
        static: the body is solved as statics (a load sequence), not as dynamics.

    Returns:
        For "auto": "multigrid" when ``vertices >= MULTIGRID_FROM_VERTICES`` and ``levels >=
        MULTIGRID_FROM_LEVELS`` (``MULTIGRID_STATIC_FROM_LEVELS`` when ``static``), else
        "direct". The same choice on every rank count (the vertex count is the whole shell's).

    Raises:
        InputError: ``method`` is not one of :data:`LINEAR_METHODS`.

    """
    if method not in LINEAR_METHODS:
        raise InputError(f"shell.solver.method: expected one of {list(LINEAR_METHODS)}, got "
                         f"{method!r}")
    if method == "auto":
        deep = MULTIGRID_STATIC_FROM_LEVELS if static else MULTIGRID_FROM_LEVELS
        pays = vertices >= MULTIGRID_FROM_VERTICES and levels >= deep
        return "multigrid" if pays else "direct"
    return "direct" if method == "direct" else "multigrid"


STATIC_SHIFTS: dict[str, float | int] = {"shift.growth": 5.0, "shift_decay": 2.0,
                                          "shift.max_shifts": 20}
"""Shift ladder of a shell under a static load (:class:`solvers.shell_newton.ShellNewtonOptions`
paths): shifts x5 from ``tau_0``, each iteration from the last accepted one over 2; 20 rungs
reach what 14 ten-fold ones do."""

DYNAMIC_SHIFTS: dict[str, float | int] = {"shift.growth": 10.0, "shift_decay": 10.0,
                                           "shift.max_shifts": 14}
"""Shift ladder of a shell in a dynamic scene: the solver's own ten-fold factors."""


def choose_shift_schedule(static: bool) -> dict[str, float | int]:
    """Return the shift ladder (ShellNewtonOptions paths and values) for a scene's load.

    Args:
        static: the body is solved as statics (a load sequence), not as dynamics.

    Returns:
        :data:`STATIC_SHIFTS` for statics, else :data:`DYNAMIC_SHIFTS`. Measured over
        imperfection seeds on ``wrinkles run`` (docs/notes/shift-schedule.md): the static
        wrinkle bars take 0.5-0.6x the CPU at x5 / 2 that they take at x10 / 10; the dynamic
        contact scenes 15-40 % more shell iterations and 5-10 % more CPU.

    """
    return dict(STATIC_SHIFTS if static else DYNAMIC_SHIFTS)


def choose_factor_reuse(static: bool) -> dict[str, bool]:
    """Return whether the shell Newton reuses its factorisation (ShellNewtonOptions path).

    Args:
        static: the body is solved as statics (a load sequence), not as dynamics.

    Returns:
        ``{"modified.enabled": not static}``: the dynamic scenes' frames reuse the previous
        iteration's (and frame's) factorisation while a step reduces ``||g||`` at least by
        :attr:`~solvers.shell_newton.ModifiedNewtonOptions.refresh_ratio`; measured on
        ``wrinkles run`` over imperfection seeds (docs/notes/factor-reuse.md): the same
        minimisers with fewer factorisations and less CPU on one and on two ranks. The static
        wrinkle scenes keep one factorisation per Newton iteration (with the reuse the
        default scene's wrinkles take another branch: docs/notes/presets.md).

    """
    return {"modified.enabled": not static}


PHASE_SPACE_FROM_VERTICES: int = 8000
"""Shell vertex count from which multigrid-CG adds the wrinkle-phase coarse space."""


def choose_phase_space(vertices: int) -> bool:
    """Whether multigrid-CG adds the wrinkle-phase coarse space (:mod:`solvers.phase_space`).

    Returns:
        ``vertices >= PHASE_SPACE_FROM_VERTICES``: the wrinkle scenes' frames from 10 434
        shell vertices take less CPU with it, those up to 7 138 less without it
        (docs/notes/phase-space.md).

    """
    return vertices >= PHASE_SPACE_FROM_VERTICES


WRINKLED_FROM_EDGES: float = 0.2
"""Largest distance of a warm start from its target, in mean rest edge lengths, from which the
shell counts as wrinkled (:func:`wrinkled_start`)."""


def wrinkled_start(offset: float, edge_length: float) -> bool:
    """Whether a Newton solve starts from a wrinkled shell: the phase space serves it at once.

    The space's test fields are the wrinkles ``x - y`` and their derivatives. A solve that
    starts at least :data:`WRINKLED_FROM_EDGES` mean edge lengths off its target somewhere
    (a warm start carries the previous solution's wrinkles) gets the space from its first
    set-up; any other solve gets it only if it buckles, from its first negative curvature on
    (:meth:`solvers.multigrid.KrylovBase.use_phase_space`). A shell that barely leaves its
    target and does not buckle (a ball-dented sofa) then does not pay for it
    (docs/notes/phase-space.md).

    Args:
        offset: ``max_i |x_i - y_i|`` of the warm start [m].
        edge_length: the shell's mean rest edge length [m] (> 0).

    """
    return offset >= WRINKLED_FROM_EDGES * edge_length


THREADS_FROM_VERTICES: int = 20000
"""Shell vertex count from which "auto" threads use every available core of a serial run."""


def available_cores() -> int:
    """Cores this process may run on (its CPU affinity; else ``os.cpu_count()``; >= 1)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # platforms without affinity masks
        return max(1, os.cpu_count() or 1)


def choose_threads(threads: int, ranks: int, vertices: int) -> int:
    """Return the thread count of the shell's kernels and multigrid products.

    ``threads`` when >= 1; for 0 ("auto") the available cores (:func:`available_cores`) of a
    serial run of a shell of at least :data:`THREADS_FROM_VERTICES` vertices, else 1 (smaller
    shells, every rank under MPI).

    Raises:
        InputError: ``threads`` < 0.

    """
    if threads < 0:
        raise InputError(f"shell.solver.threads: expected 0 (auto) or a count >= 1, got "
                         f"{threads!r}")
    if threads:
        return threads
    return available_cores() if ranks == 1 and vertices >= THREADS_FROM_VERTICES else 1


RANKS_FROM_WORK: int = 10000
"""Frame work (shell vertices + body dofs x body steps) from which a serial ``wrinkles run``
of a scene with a shell runs on the cores as MPI ranks."""

RANKS_FROM_BODY_WORK: int = 20000
"""Frame work (body dofs x body steps) from which a serial run of a scene without a shell
runs on the cores as MPI ranks: a body's frame costs less per unit of work than a shell's
(5-7 Newton iterations against tens), so the fixed cost of the relaunch (a second start of
the interpreter and its imports) needs a larger frame to pay back over a short run."""

WORK_PER_RANK: int = 5000
"""Least frame work per rank :func:`choose_ranks` gives (caps the ranks of many cores)."""


def choose_ranks(threads: int, work: int, cores: int, shell: bool = True) -> int:
    """Return the MPI ranks a serial ``wrinkles run`` should run on (1: stay).

    ``work`` is a frame's work in shell-vertex solves: the shell's vertices plus the body's
    displacement dofs times its steps per frame (one body dof step costs about one shell
    vertex solve in the shipped scenes; the application's overlap layout weighs the same). With
    ``threads`` 0 ("auto") a frame of at least :data:`RANKS_FROM_WORK` (without a shell
    :data:`RANKS_FROM_BODY_WORK`) takes ``min(cores, work // WORK_PER_RANK)`` ranks. Ranks
    split the whole frame (the shell's energy, CG and set-ups, the body, a two-way joint
    system, or overlap body and shell), where threads speed up only the element kernels and
    multigrid products; measured on ``wrinkles run`` with shells of 10 434 - 41 730 vertices,
    bodies of 5 469 - 13 515 dofs under smaller shells and bodies of 5 469 - 14 010 dofs
    alone (docs/notes/solver-choice.md, "Ranks for a serial command"). A ``threads`` count
    the scene names keeps one process.

    Args:
        threads: ``shell.solver.threads`` (0 = auto; 0 for a scene without a shell).
        work: shell vertices + body dofs x body steps per frame.
        cores: cores the process may run on (:func:`available_cores`).
        shell: whether the scene has a shell.

    """
    if threads or work < (RANKS_FROM_WORK if shell else RANKS_FROM_BODY_WORK):
        return 1
    return max(1, min(cores, work // WORK_PER_RANK))


SPLIT_JOINT_FROM_VERTICES: int = 4000
"""Shell vertex count from which a two-way scene on several ranks splits its joint system."""


def choose_joint_split(ranks: int, vertices: int, method: str) -> bool:
    """Whether the two-way joint Newton system is split over the ranks.

    Returns:
        True on more than one rank for a shell solved by multigrid-CG with at least
        :data:`SPLIT_JOINT_FROM_VERTICES` vertices: split on 2 ranks, a two-way bar's
        iterations are 1.37x faster than whole on every rank at 4 674 shell vertices and
        1.45x at 6 082, as fast at 2 610 (docs/notes/two-way-coupling.md). The direct
        path (small shells) is always solved whole.

    """
    return ranks > 1 and method == "multigrid" and vertices >= SPLIT_JOINT_FROM_VERTICES
