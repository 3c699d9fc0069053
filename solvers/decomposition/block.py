"""Block Jacobi / Gauss-Seidel outer iteration over patches (section 5 of the draft).

Each patch ``P`` owns the vertex set ``I_P``; its block problem ``min_{x_I} W(x_I, x_rest)``
(:class:`PatchEnergy`) is solved by the shell Newton solver with everything else held at the
current values. One outer iteration:

* Jacobi: every patch solves from the same state ``x_k``, then the owners' values are written
  back (and exchanged between workers): ``x_{k+1} = x_k + sum_P E_P (argmin_P - x_{k, I_P})``;
* Gauss-Seidel by colouring: patches are greedily coloured so that no two patches of one
  colour depend on each other's owned vertices; colours are swept in order and values are
  exchanged after each colour, so a colour sees the latest values of the earlier ones
  (block Gauss-Seidel decreases W monotonically).

Stopping uses the *global* gradient: the owned rows of a patch gradient are the global
gradient's rows (:mod:`.patch_energy`), so ``||grad W||^2 = sum_P ||grad_{I_P} W||^2`` is summed
over patches and workers; the outer loop stops when ``||grad W|| <= atol + rtol g_ref`` with
``g_ref`` the initial global gradient norm (or a given scale), the monolithic criterion.
Inner solves are inexact: patch P stops at ``||grad_P|| <= max(eta ||grad W_k||,
inner_floor * tol) / sqrt(#patches)`` (forcing term eta, as in inexact Newton).

A wall-time cap (``max_seconds``) stops the outer loop unconverged after the first outer
iteration that ends more than ``max_seconds`` after the solve started. The decision is
collective: every worker's "over time" flag is summed through the exchange once per outer
iteration (only when the cap is finite), so all workers stop after the same iteration even
though their clocks differ.

The exchange between workers is an :class:`Exchange` (serial: nothing to send;
:mod:`.parallel`: MPI client-server or neighbour-to-neighbour). Every exchange also agrees on
errors: a worker whose patch solve raised passes the message, and every worker raises
:class:`SolverError` with it, so no worker waits forever.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Literal, Protocol

import numpy as np

from meshes.errors import InputError, SolverError
from solvers.decomposition.patch_energy import PatchEnergy
from solvers.shell_newton import ShellNewtonOptions, ShellNewtonSolver

Method = Literal["jacobi", "gauss_seidel"]
StopReason = Literal["tolerance", "max_outer", "max_seconds"]


@dataclass(frozen=True)
class BlockOptions:
    """Options of the decomposed (block) solve.

    Attributes:
        method: "jacobi" (all patches from the same state) or "gauss_seidel" (by colours).
        rtol: Global relative gradient tolerance (as ``ShellNewtonOptions.rtol``).
        atol: Global absolute gradient tolerance (energy / length).
        gradient_scale: ``g_ref`` (energy / length); 0 uses the initial global gradient norm.
        max_outer: Outer iterations before giving up (returns unconverged).
        eta: Forcing term of the inexact inner solves (relative to the current global
            gradient norm), in (0, 1).
        inner_floor: Lower bound of the inner tolerance relative to the global tolerance.
        inner: Newton options of the patch solves (rtol/atol/gradient_scale are overridden).
        anderson: Anderson acceleration depth m of the outer fixed-point iteration (0 = off).
        min_damping: Smallest step fraction alpha of the damped (backtracked) outer step.
        fail_patch: Test hook: the patch whose solve raises SolverError (-1 = none).
        max_seconds: Wall-time cap (s) of the outer loop, measured from the start of
            :meth:`BlockSolver.solve` (patch set-up excluded): the loop stops unconverged after
            the first outer iteration that ends later on any worker (inf = no cap; a finite
            cap costs one extra scalar reduction per outer iteration).

    """

    method: Method = "jacobi"
    rtol: float = 1e-8
    atol: float = 0.0
    gradient_scale: float = 0.0
    max_outer: int = 500
    eta: float = 0.1
    inner_floor: float = 0.1
    inner: ShellNewtonOptions = field(default_factory=ShellNewtonOptions)
    anderson: int = 5
    min_damping: float = 1e-3
    fail_patch: int = -1
    max_seconds: float = float("inf")

    def __post_init__(self) -> None:
        if self.method not in ("jacobi", "gauss_seidel"):
            raise InputError(f"BlockOptions.method: expected 'jacobi' or 'gauss_seidel', got "
                             f"{self.method!r}")
        for name in ("rtol", "atol", "gradient_scale"):
            if not (np.isfinite(getattr(self, name)) and getattr(self, name) >= 0):
                raise InputError(f"BlockOptions.{name}: must be finite and >= 0")
        if self.rtol == 0 and self.atol == 0:
            raise InputError("BlockOptions.rtol: rtol and atol cannot both be 0")
        if self.max_outer < 1:
            raise InputError(f"BlockOptions.max_outer: must be >= 1, got {self.max_outer}")
        if not 0 < self.eta < 1:
            raise InputError(f"BlockOptions.eta: must be in (0, 1), got {self.eta}")
        if self.anderson < 0:
            raise InputError(f"BlockOptions.anderson: must be >= 0, got {self.anderson}")
        if not 0 < self.min_damping <= 1:
            raise InputError(f"BlockOptions.min_damping: must be in (0, 1], got "
                             f"{self.min_damping}")
        if not 0 < self.inner_floor <= 1:
            raise InputError(f"BlockOptions.inner_floor: must be in (0, 1], got "
                             f"{self.inner_floor}")
        if not self.max_seconds > 0:  # also refuses NaN; inf means no cap
            raise InputError(f"BlockOptions.max_seconds: must be > 0, got {self.max_seconds}")


@dataclass(frozen=True)
class BlockReport:
    """What the decomposed solve did (identical on every worker).

    Attributes:
        converged: Global gradient tolerance met.
        outer_iterations: Outer iterations (a Gauss-Seidel iteration sweeps all colours).
        grad_norm: Final global gradient norm.
        tolerance: The global tolerance used.
        grad_history: Global gradient norm before each outer iteration and at the end.
        inner_iterations: Newton iterations of this worker's patch solves (summed).
        exchanges: Number of exchanges.
        colours: Number of colours (1 for Jacobi).
        damped_steps: Outer steps whose combined update had to be backtracked (alpha < 1).
        rejected_mixing: Anderson steps rejected because they raised W (history reset).
        time_solve: Seconds in this worker's patch solves.
        time_exchange: Seconds in exchanges (communication and waiting for other workers).
        time_total: Wall time.
        stopped_by: Why the outer loop ended: "tolerance" (converged), "max_outer" or
            "max_seconds".

    """

    converged: bool
    outer_iterations: int
    grad_norm: float
    tolerance: float
    grad_history: tuple[float, ...]
    inner_iterations: int
    exchanges: int
    colours: int
    damped_steps: int
    rejected_mixing: int
    time_solve: float
    time_exchange: float
    time_total: float
    stopped_by: StopReason


class Exchange(Protocol):
    """Communication between the workers of a decomposed solve."""

    def agree(self, values: np.ndarray, error: str | None) -> np.ndarray:
        """Sum ``values`` over workers; raise SolverError on all of them if any had an error."""

    def share(self, x: np.ndarray, patches: Sequence[PatchEnergy]) -> None:
        """Write the owned values of ``patches`` (solved on other workers too) into ``x``."""


class SerialExchange:
    """One worker: owned values are already in ``x``; errors are raised as they are."""

    def agree(self, values: np.ndarray, error: str | None) -> np.ndarray:
        """Return ``values``; raise SolverError with ``error`` when set."""
        if error is not None:
            raise SolverError(error)
        return np.asarray(values, dtype=np.float64)

    def share(self, x: np.ndarray, patches: Sequence[PatchEnergy]) -> None:
        """Nothing to exchange."""


def patch_colours(interiors: Sequence[np.ndarray], halos: Sequence[np.ndarray],
                  n_vertices: int) -> np.ndarray:
    """Greedy colouring: patches P, Q conflict if the halo of one meets the other's owned set.

    Patches are coloured in order of decreasing conflict count (Welsh-Powell).
    """
    owner = np.full(n_vertices, -1, dtype=np.int64)
    for p, interior in enumerate(interiors):
        owner[interior] = p
    conflicts = [set(np.unique(owner[h]).tolist()) - {p} for p, h in enumerate(halos)]
    for p, c in enumerate(conflicts):
        for q in c:
            conflicts[q].add(p)
    colours = np.full(len(interiors), -1, dtype=np.int64)
    for p in sorted(range(len(interiors)), key=lambda q: -len(conflicts[q])):
        used = {int(colours[q]) for q in conflicts[p]}
        colours[p] = min(c for c in range(len(interiors) + 1) if c not in used)
    return colours


@dataclass
class _Tally:
    """Mutable counters of one worker."""

    inner: int = 0
    exchanges: int = 0
    solve: float = 0.0
    exchange: float = 0.0
    damped: int = 0
    rejected: int = 0
    start: float = field(default_factory=time.perf_counter)


class BlockSolver:
    """Outer block iteration of the patches owned by this worker.

    Args:
        patches: This worker's patch energies.
        patch_ids: Global patch number of each (for the colouring and the failure hook).
        colours: Colour of each of this worker's patches (all 0 for Jacobi); the number of
            colours must be the same on every worker.
        n_colours: Total number of colours.
        exchange: Communication with the other workers.
        options: Options.

    """

    def __init__(self, patches: Sequence[PatchEnergy], patch_ids: Sequence[int],
                 colours: np.ndarray, n_colours: int, exchange: Exchange,
                 options: BlockOptions) -> None:
        self.patches, self.patch_ids = list(patches), list(patch_ids)
        self.colours, self.n_colours = np.asarray(colours), int(n_colours)
        self.exchange, self.options = exchange, options
        self.n_total = 0
        # PatchEnergy has the ShellEnergy interface (mypy's protocol check of the keyword
        # ``hessian`` fails for ShellEnergy itself too)
        self._solvers = [ShellNewtonSolver(p, options.inner)  # type: ignore[arg-type]
                         for p in self.patches]

    def _global_gradient(self, x: np.ndarray, tally: _Tally) -> float:
        """``||grad W(x)||`` summed over all workers' patches (errors agreed on)."""
        error, sq = None, 0.0
        try:
            for p in self.patches:
                p.set_state(x)
                sq += float(np.sum(p.gradient_at_state() ** 2))
        except Exception as err:  # noqa: BLE001 - any failure must reach every worker
            error = f"gradient evaluation failed: {type(err).__name__}: {err}"
        start = time.perf_counter()
        total = float(self.exchange.agree(np.array([sq]), error)[0])
        tally.exchange += time.perf_counter() - start
        return float(np.sqrt(total))

    def _solve_patch(self, k: int, x: np.ndarray, atol: float) -> np.ndarray:
        """Newton on patch k from state x to ``||grad_P|| <= atol``; owned values (|I|, 3)."""
        patch, solver = self.patches[k], self._solvers[k]
        if self.patch_ids[k] == self.options.fail_patch:
            raise SolverError(f"forced failure in patch {self.patch_ids[k]} (fail_patch)")
        patch.set_state(x)
        solver.options = _with_tolerance(self.options.inner, atol)
        xp, report = solver.minimize(patch.owned_values())
        self._inner += report.iterations
        return xp

    def _sweep_colour(self, colour: int, x: np.ndarray, atol: float, tally: _Tally) -> None:
        """Solve this worker's patches of one colour from x, write back, exchange."""
        start, error, self._inner = time.perf_counter(), None, 0
        solved: list[tuple[int, np.ndarray]] = []
        current = -1
        try:
            for current in np.flatnonzero(self.colours == colour).tolist():
                solved.append((current, self._solve_patch(current, x, atol)))
        except Exception as err:  # noqa: BLE001 - reported to every worker below
            error = (f"patch solve failed on patch {self.patch_ids[current]}: "
                     f"{type(err).__name__}: {err}")
        for k, xp in solved:
            x[self.patches[k].interior] = xp
        tally.inner += self._inner
        tally.solve += time.perf_counter() - start
        start = time.perf_counter()
        self.exchange.agree(np.zeros(1), error)
        self.exchange.share(x, self.patches)
        tally.exchanges += 1
        tally.exchange += time.perf_counter() - start

    def _owned(self, x: np.ndarray) -> np.ndarray:
        """Return this worker's owned values, flat, in patch order."""
        if not self.patches:
            return np.zeros(0)
        return np.concatenate([x[p.interior].reshape(-1) for p in self.patches])

    def _set_owned(self, x: np.ndarray, values: np.ndarray, tally: _Tally) -> None:
        """Write owned values into x and exchange them."""
        offset = 0
        for p in self.patches:
            x[p.interior] = values[offset: offset + p.n_free_dofs].reshape(-1, 3)
            offset += p.n_free_dofs
        start = time.perf_counter()
        self.exchange.share(x, self.patches)
        tally.exchanges += 1
        tally.exchange += time.perf_counter() - start

    def _global_energy(self, x: np.ndarray, tally: _Tally) -> float:
        """``W(x)`` as the sum over workers of each patch's owned-stencil energy."""
        error, total = None, 0.0
        try:
            for p in self.patches:
                p.set_state(x)
                total += p.owned_energy()
        except Exception as err:  # noqa: BLE001 - any failure must reach every worker
            error = f"energy evaluation failed: {type(err).__name__}: {err}"
        start = time.perf_counter()
        value = float(self.exchange.agree(np.array([total]), error)[0])
        tally.exchange += time.perf_counter() - start
        return value

    def _damp(self, x: np.ndarray, before: np.ndarray, after: np.ndarray, w0: float,
              tally: _Tally) -> tuple[np.ndarray, float]:
        """Backtrack ``x_k + alpha (G(x_k) - x_k)``, alpha = 1, 1/2, ... until W <= W(x_k).

        Block Jacobi's combined step can overshoot where patches are coupled (W_P rows
        straddling patches); Gauss-Seidel steps never increase W and pass at alpha = 1.
        """
        alpha, w = 1.0, self._global_energy(x, tally)
        trial = after
        while w > w0 + _noise(w0) and alpha > self.options.min_damping:
            alpha *= 0.5
            trial = before + alpha * (after - before)
            self._set_owned(x, trial, tally)
            w = self._global_energy(x, tally)
        tally.damped += alpha < 1.0
        return trial, w

    def _outer_step(self, x: np.ndarray, g: float, tol: float, n_patches: float,
                    anderson: _Anderson, tally: _Tally) -> float:
        """One outer iteration: all colours, damping, safeguarded Anderson; new ``||g||``."""
        atol = max(self.options.eta * g, self.options.inner_floor * tol) / np.sqrt(n_patches)
        before, w0 = self._owned(x), self._global_energy(x, tally)
        for colour in range(self.n_colours):
            self._sweep_colour(colour, x, atol, tally)
        after, _ = self._damp(x, before, self._owned(x), w0, tally)
        if anderson.depth == 0:
            return self._global_gradient(x, tally)
        self._set_owned(x, anderson.mix(before, after, self.exchange), tally)
        uphill = self._global_energy(x, tally) > w0 + _noise(w0)
        g_mixed = self._global_gradient(x, tally)
        if uphill and g_mixed > g:  # mixing went uphill (may head for a saddle): plain step
            anderson.reset()
            tally.rejected += 1
            self._set_owned(x, after, tally)
            return self._global_gradient(x, tally)
        return g_mixed

    def _out_of_time(self, tally: _Tally) -> bool:
        """Tell every worker alike whether any worker is past ``max_seconds`` (collective).

        One scalar reduction (the count of workers over time), skipped when there is no cap,
        so every worker takes the same decision after the same outer iteration.
        """
        if not np.isfinite(self.options.max_seconds):
            return False
        over = float(time.perf_counter() - tally.start > self.options.max_seconds)
        start = time.perf_counter()
        count = float(self.exchange.agree(np.array([over]), None)[0])
        tally.exchange += time.perf_counter() - start
        return count > 0

    def solve(self, x0: np.ndarray) -> tuple[np.ndarray, BlockReport]:
        """Run the outer iteration from x0 (n, 3); return ``(x, report)``.

        Stops at the global tolerance, after ``max_outer`` iterations or (collectively) past
        ``max_seconds``. x is this worker's copy: owned and halo values up to date (the
        caller gathers).
        """
        x, tally = np.array(x0, dtype=np.float64), _Tally()
        history: list[float] = []
        g = self._global_gradient(x, tally)
        tol = self.options.atol + self.options.rtol * (self.options.gradient_scale or g)
        n_patches = float(self.exchange.agree(np.array([len(self.patches)], float), None)[0])
        anderson = _Anderson(self.options.anderson)
        timed_out = False
        while g > tol and len(history) < self.options.max_outer and not timed_out:
            history.append(g)
            g = self._outer_step(x, g, tol, n_patches, anderson, tally)
            timed_out = self._out_of_time(tally)
        stopped: StopReason = ("tolerance" if g <= tol else
                               "max_seconds" if timed_out else "max_outer")
        return x, BlockReport(
            converged=g <= tol, outer_iterations=len(history), grad_norm=g, tolerance=tol,
            grad_history=(*history, g), inner_iterations=tally.inner,
            exchanges=tally.exchanges, colours=self.n_colours, damped_steps=tally.damped,
            rejected_mixing=tally.rejected, time_solve=tally.solve,
            time_exchange=tally.exchange, time_total=time.perf_counter() - tally.start,
            stopped_by=stopped)


class _Anderson:
    """Anderson acceleration (type II, Walker & Ni 2011) of the fixed-point map x -> G(x).

    With residuals ``f_k = G(x_k) - x_k`` and the last ``m`` differences ``dF``, ``dG``:
    ``gamma = argmin ||f_k - dF gamma||`` and ``x_{k+1} = G(x_k) - dG gamma``. The small
    Gram system ``dF^T dF``, ``dF^T f`` is summed over workers (owned rows only), so every
    worker mixes with the same gamma.
    """

    def __init__(self, depth: int) -> None:
        self.depth = depth
        self.f: list[np.ndarray] = []
        self.g: list[np.ndarray] = []

    def reset(self) -> None:
        """Forget the history."""
        self.f.clear()
        self.g.clear()

    def mix(self, before: np.ndarray, after: np.ndarray, exchange: Exchange) -> np.ndarray:
        """Mixed owned values from ``x_k`` (before) and ``G(x_k)`` (after)."""
        self.f.append(after - before)
        self.g.append(after)
        if len(self.f) > self.depth + 1:
            self.f.pop(0)
            self.g.pop(0)
        m = len(self.f) - 1
        d_f = np.diff(np.array(self.f), axis=0).T if m else np.zeros((after.size, 0))
        local = np.concatenate([(d_f.T @ d_f).reshape(-1), d_f.T @ self.f[-1]])
        total = exchange.agree(local, None) if m else local
        if m == 0:
            return after
        gram, rhs = total[: m * m].reshape(m, m), total[m * m:]
        gamma = np.linalg.lstsq(gram, rhs, rcond=1e-12)[0]
        return after - np.diff(np.array(self.g), axis=0).T @ gamma


def extrapolate_outer(history: Sequence[float], tolerance: float) -> tuple[float, float]:
    """Fitted convergence rate of an outer iteration and the outer iterations it would need.

    Fits ``log10 ||g_k|| = a + s k`` (least squares, ``np.polyfit``) over the last half of the
    history (k = n/2 .. n, at least 3 points; the early, pre-asymptotic iterations are left
    out) and continues the line from the last value: ``n + (log10 tol - log10 ||g_n||) / s``.
    This is an extrapolation, not a measurement (a linear rate of the block fixed-point
    iteration is assumed to persist).

    Args:
        history: ``BlockReport.grad_history`` (``||g||`` before each outer iteration and at
            the end; n + 1 values for n outer iterations).
        tolerance: The global gradient tolerance.

    Returns:
        ``(rate, outer)``: the reduction factor of ``||g||`` per outer iteration (``10^s``) and
        the extrapolated total outer iterations; ``outer = n`` when already converged, inf when
        the fitted rate is >= 1, NaN for fewer than 3 points to fit.

    """
    g = np.asarray(history, dtype=np.float64)
    n = g.size - 1
    if g[-1] <= tolerance:
        return float("nan"), float(n)
    k = np.arange(n // 2, n + 1)
    if k.size < 3:
        return float("nan"), float("nan")
    slope = float(np.polyfit(k, np.log10(g[k]), 1)[0])
    if slope >= 0:
        return float(10.0**slope), float("inf")
    return float(10.0**slope), float(n + (np.log10(tolerance) - np.log10(g[-1])) / slope)


def _noise(w: float) -> float:
    """Round-off allowance when comparing energies (as the Newton line search)."""
    return 16.0 * np.finfo(float).eps * abs(w)


def _with_tolerance(inner: ShellNewtonOptions, atol: float) -> ShellNewtonOptions:
    """Inner options with an absolute gradient tolerance only."""
    return replace(inner, atol=float(atol), rtol=0.0, gradient_scale=0.0)


def serial_block_solve(patches: Sequence[PatchEnergy], x0: np.ndarray,
                       options: BlockOptions | None = None) -> tuple[np.ndarray, BlockReport]:
    """Decomposed solve on one worker (all patches here); see the module docstring.

    Args:
        patches: Patch energies covering the shell (every vertex owned once).
        x0: (n, 3) start (warm start).
        options: Options.

    Returns:
        ``(x, report)``.

    """
    opts = options or BlockOptions()
    colours = _colours_for(patches, opts.method, x0.shape[0])
    solver = BlockSolver(patches, range(len(patches)), colours, int(colours.max()) + 1,
                         SerialExchange(), opts)
    return solver.solve(x0)


def _colours_for(patches: Sequence[PatchEnergy], method: Method, n: int) -> np.ndarray:
    """All zeros for Jacobi, the greedy colouring for Gauss-Seidel."""
    if method == "jacobi":
        return np.zeros(len(patches), dtype=np.int64)
    return patch_colours([p.interior for p in patches], [p.halo for p in patches], n)
