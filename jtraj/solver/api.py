"""The entry points :func:`solve` (one problem) and :func:`solve_batch` (a batch),
with their input checks."""

from __future__ import annotations

import warnings
from typing import Any, Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .. import _kkt_native, _resources, _setup, implicit
from .._compile import nested_jit
from .._compile import solver_jit as _jit
from ..problem import Problem, Weights, default_jerk
from ..transcription import Transcription
from .core import initial_guess, placeholder_init, resolve_method
from .lanes import cpu_lanes, solve_problems
from .methods import IPM, SOLVERS, AugmentedLagrangian, Auto
from .options import SolverOptions, as_solver, options_jit, to_options
from .results import Solution


def solve(problem: Problem, *, solver: Auto | IPM | AugmentedLagrangian | None = None,
          transcription: str = "decoupled", init: tuple[Any, Any] | None = None, warm: str = "full",
          on_failure: str = "nan", options: SolverOptions | None = None) -> Solution:
    """Solve one trajectory problem; compiled once per robot type, shape and the solver's
    static fields (see :mod:`jtraj.solver.methods`).

    On a CPU one problem runs about 1.6x faster in a process pinned to one core
    (:func:`jtraj.pin_to_one_cpu` before JAX's first computation; the CLI does it).

    Solves in float64 only: raises ``ValueError`` where ``jax_enable_x64`` is off or the
    problem holds float32 arrays (built while it was off). A solve that compiles the
    solver (first use in a process) logs a line saying so (logger "jtraj", INFO); JAX's
    persistent compilation cache, on since ``import jtraj``, keeps it (:mod:`jtraj._setup`).

    Args:
        problem: a :class:`jtraj.Problem` (one problem; a batch goes to :func:`solve_batch`).
        solver: :class:`jtraj.Auto` (default), :class:`jtraj.IPM` or
            :class:`jtraj.AugmentedLagrangian`, holding the method's options.
        transcription: "decoupled" (thesis ALD, default), "coupled", or Chettibi's
            "collocation", "shooting", "spline" (see :class:`jtraj.transcription.Transcription`).
        init: optional warm start (u (N, m_u), h (N,)) in the transcription's controls
            (accelerations for "decoupled"; ``Transcription(name).controls_of(solution)``
            turns any Solution of that transcription into them).
        warm: with ``init``, "full" (default) also estimates multipliers at ``init``
            (a point that already meets the tolerances returns at once) and, in the AL
            loop, starts the penalty at ``penalty_max / 100``: right for a point near an
            optimum (a previous solution, a perturbed problem); "primal" keeps the cold
            start's multipliers and penalty: right for a rough guess (a learned plan).
            The interior-point method starts its barrier at ``init`` either way.
        on_failure: what derivatives of a solve that did not converge are (see
            :mod:`jtraj.implicit`): "nan" (default) or "raise" (a run-time error when
            the solve is differentiated, inside ``jit`` too).
        options: deprecated, a :class:`jtraj.SolverOptions`; pass
            ``solver=jtraj.solver.from_options(options)`` instead.

    ``jax.grad``, ``jax.jvp``, ``jax.jacobian``, ``jax.vmap`` and ``jax.jit`` work
    through it: with traced array leaves in ``problem`` the derivatives of the
    solution's q, qd, v, tau, h, T, cost, cost_terms and energy come from implicit
    differentiation of the KKT conditions at the optimum (:mod:`jtraj.implicit`).
    """
    Transcription(transcription)  # validates the name
    if on_failure not in ("nan", "raise"):
        raise ValueError(f"on_failure must be 'nan' or 'raise', got {on_failure!r}")
    if not isinstance(problem, Problem):
        raise ValueError(f"problem must be a jtraj.Problem, got {type(problem).__name__}")
    if problem.batch_size is not None:
        raise ValueError(f"problem is a batch of {problem.batch_size} problems (q_start has shape "
                         f"{problem.q_start.shape}); solve it with jtraj.solve_batch")
    _check_efforts(problem.efforts, transcription)
    if warm not in ("full", "primal"):
        raise ValueError(f"warm must be 'full' or 'primal', got {warm!r}")
    warm = init is not None and warm == "full"
    Transcription(transcription).check_jerk(problem)
    opts = resolve_method(solver_options(solver, options), transcription, problem.robot, problem.jerk)
    # float64 only, the compilation cache on, a first compilation logged (jtraj._setup)
    key = _setup.before_solve(problem.robot, problem.N, batch=False, problem=problem, options=opts,
                              transcription=transcription, efforts=problem.efforts)
    _kkt_native.prefetch(problem.robot.n)  # the native kernel's build runs while the solver is traced
    guess = init is None
    if guess:  # placeholders of the controls' shapes (the program computes the guess)
        init = placeholder_init(problem.N, Transcription(transcription).control_dim(problem))
    else:
        init = _check_init(problem, init, transcription)
    _resources.check(problem.N, problem.robot.n)  # ValueError naming N beyond the memory limit
    if implicit.any_traced((problem, init)):  # inside jit / vmap / a derivative
        return implicit.solve_traced(problem, opts, transcription, init, warm, guess, on_failure)
    from . import staged as _staged  # concrete arrays: the programs a problem needs, in stages

    sol = _staged.solve(problem, opts, transcription, init, np.bool_(warm), np.bool_(guess))
    _setup.compiled(key)
    return sol


def _deprecated_options(solver, stacklevel: int) -> None:
    if solver is not None:
        raise ValueError("pass solver= or the deprecated options=, not both")
    warnings.warn("options=SolverOptions(...) is deprecated and goes in the next release: pass "
                  "solver=jtraj.Auto(), jtraj.IPM(...) or jtraj.AugmentedLagrangian(...) "
                  "(jtraj.solver.from_options(options) gives the solver of given options)",
                  DeprecationWarning, stacklevel=stacklevel + 1)


def _check_solver(solver) -> None:
    if not isinstance(solver, SOLVERS):
        raise ValueError(f"solver must be jtraj.Auto, jtraj.IPM or jtraj.AugmentedLagrangian, "
                         f"got {type(solver).__name__}")


def solver_options(solver, options) -> SolverOptions | None:
    """The flat options the compiled programs read: those ``solver`` maps onto
    (:func:`jtraj.solver.options.to_options`), ``options`` (deprecated, with a warning)
    or None for the defaults."""
    if options is not None:
        _deprecated_options(solver, stacklevel=3)
        return options
    if solver is None:
        return None
    _check_solver(solver)
    return to_options(solver)


def solver_argument(solver, options):
    """The solver object of a function that takes ``solver=`` and the deprecated
    ``options=`` (a :class:`jtraj.SolverOptions` or a solver object, with the warning
    :func:`solve` gives), or None for the default; ``ValueError`` for anything else or
    for both."""
    if options is not None:
        _deprecated_options(solver, stacklevel=3)
        return as_solver(options, "options")
    if solver is not None:
        _check_solver(solver)
    return solver


def _check_efforts(efforts, transcription):
    if efforts != "samples" and transcription != "decoupled":
        raise ValueError(f"efforts={efforts!r} bounds the efforts of the decoupled transcription's "
                         f"constant-acceleration intervals; transcription {transcription!r} supports 'samples' only")


def _check_init(problem, init, transcription):
    u, h = init
    u, h = jnp.asarray(u, float), jnp.asarray(h, float)
    m_u = Transcription(transcription).control_dim(problem)
    if u.shape != (problem.N, m_u):
        raise ValueError(f"init[0] must have shape ({problem.N}, {m_u}), got {u.shape}")
    if h.shape != (problem.N,):
        raise ValueError(f"init[1] must have shape ({problem.N},), got {h.shape}")
    if implicit.any_traced((u, h)):  # values checked only where concrete
        return u, h
    if not (jnp.all(jnp.isfinite(u)) and jnp.all(jnp.isfinite(h))):
        raise ValueError("init must be finite")
    return u, h


@options_jit()
def _guess_batch_jit(problems, opts, transcription):
    tr = Transcription(transcription)
    return eqx.filter_vmap(lambda p: initial_guess(p, opts, tr))(problems)


def _problem(robot, q_start, q_goal, qd_start, qd_goal, T_max, N, weights, efforts, jerk) -> Problem:
    return Problem(robot, q_start, q_goal, N=N, weights=weights, qd_start=qd_start, qd_goal=qd_goal, T_max=T_max,
                   efforts=efforts, jerk=jerk, validate=False)


@_jit
def _problems_jit(robot, q_start, q_goal, qd_start, qd_goal, T_max, N, weights, efforts, jerk):
    """:class:`Problem` per sample of a batch, as one program (built eagerly under vmap,
    each of its operations was a program of its own: a dozen compiled at a process's
    first batch). ``jerk`` (a Python bool, the robot's :func:`jtraj.problem.default_jerk`
    on its concrete limits): inside the trace the limits are tracers, on which the
    default would always add the jerk rows, and the method chosen for the batch (the
    interior-point method where they are off) would then run on rows it does not model."""
    return eqx.filter_vmap(_problem, in_axes=(None, 0, 0, 0, 0, 0, None, None, None, None))(
        robot, q_start, q_goal, qd_start, qd_goal, T_max, N, weights, efforts, jerk)


def solve_batch(problem, q_start=None, q_goal=None, *, N: int | None = None, weights: Weights | None = None,
                qd_start=None, qd_goal=None, T_max=None, solver: Auto | IPM | AugmentedLagrangian | None = None,
                transcription: str = "decoupled", init: tuple[Any, Any] | None = None,
                slots: int | None | str = "auto", segment: int = 10, efforts: str | None = None,
                progress: Callable[[int, int], Any] | None = None, options: SolverOptions | None = None) -> Solution:
    """Solve B problems sharing one robot, N and weights in one vmapped, compiled call.

    ``solve_batch(problem)`` takes a batched :class:`jtraj.Problem` (``q_start`` and
    ``q_goal`` of shape (B, n)); ``solve_batch(robot, q_start, q_goal, N=..., ...)`` is
    the same solve built from arrays.

    Args:
        problem: a batched :class:`jtraj.Problem` (without via points, with the robot's
            default ``jerk``), or a :class:`jtraj.robots.Robot` for the array form.
        q_start, q_goal: the array form's (B, n) start and goal configurations.
        N, weights, efforts: the array form's shared N (default 20), :class:`jtraj.Weights`
            and efforts ("samples" or "intervals", see :class:`jtraj.Problem`).
        qd_start, qd_goal: the array form's optional (B, n) boundary velocities (default rest).
        T_max: the array form's optional scalar or (B,) bound on the total time.
        solver: :class:`jtraj.Auto` (default), :class:`jtraj.IPM` or
            :class:`jtraj.AugmentedLagrangian` (see :func:`solve`).
        init: optional warm start (u (B, N, m_u), h (B, N)).
        slots, segment: the batch is solved by ``slots`` vmapped lanes, each lane
            taking the next pending problem when its own finishes (the interior-point
            method at once, inside its compiled loop; the AL loop, which the default
            method falls back on, after segments of ``segment`` iterations), and on a
            CPU the last unfinished problems move to slots / 4 and slots / 16 lanes
            (same results up to rounding, cost ~ mean instead of max iterations;
            compiled once per lane count). This applies when B exceeds the
            smallest lane count: on a CPU a batch smaller than ``slots`` steps down too
            (64 benchmark pairs in batches of 32, one core: 4.05 s against 9.62 s solved
            at once, whose cost is the slowest problem's iterations on every lane); on an
            accelerator when B > slots. ``slots=None`` solves all B at once. "auto"
            (default) is 1024 on an accelerator and, on a CPU, 16 for serial3 at N = 20,
            down to 4 for larger problems (:func:`jtraj.solver.lanes.cpu_lanes`). On a CPU a vmapped
            iteration costs about its lane count, and more per lane once the lanes'
            working set outgrows the core's cache; on an accelerator lanes are nearly
            free, so larger ``slots`` pay there.
        progress: optional ``progress(finished, B)``, called on the host as problems
            finish (a problem counts once its interior-point run ends, also where the
            AL fallback goes on from it), last with (B, B); not called inside ``jit``,
            ``vmap`` or a derivative. With it the interior-point pool returns to the
            host every eighth of the batch (same programs, same results).
        options: deprecated, a :class:`jtraj.SolverOptions`; pass
            ``solver=jtraj.solver.from_options(options)`` instead.

    Returns a :class:`jtraj.Solution` whose fields carry a leading batch axis. Samples with
    non-finite inputs (array form) or infeasible on their face are not solved: their
    status is ``Status.INVALID_INPUT`` (a batch never raises for one bad sample); shapes
    and the robot are checked up front, and float64 as in :func:`solve`.

    Derivatives (``jax.grad``, ``jax.jvp``, ``jax.jacobian``, under ``jit`` and ``vmap``
    too) with respect to traced inputs (q_start, q_goal, boundary velocities, T_max,
    the weights' and the robot's arrays) come per sample from :mod:`jtraj.implicit`;
    a sample that did not converge gets zero derivatives
    (:func:`jtraj.valid_derivatives` gives the mask). With concrete primal values (a
    derivative outside ``jit``) the solve itself runs on the lane driver above; inside
    ``jit`` or ``vmap`` it is one vmapped program.
    """
    from ..robots import Robot

    opts = solver_options(solver, options)
    if isinstance(problem, Problem):
        robot, q_start, q_goal, N, weights, qd_start, qd_goal, T_max, efforts = _batched_problem(
            problem, q_start=q_start, q_goal=q_goal, N=N, weights=weights, qd_start=qd_start, qd_goal=qd_goal,
            T_max=T_max, efforts=efforts)
    elif isinstance(problem, Robot):
        robot = problem
        if q_start is None or q_goal is None:
            raise ValueError("q_start and q_goal are needed with a robot (or pass a batched jtraj.Problem)")
        N = 20 if N is None else N
        efforts = "samples" if efforts is None else efforts
    else:
        raise ValueError(f"problem must be a batched jtraj.Problem or a jtraj.robots.Robot, "
                         f"got {type(problem).__name__}")
    n = robot.n
    traced = implicit.any_traced((robot, q_start, q_goal, qd_start, qd_goal, T_max, weights, init))
    # the inputs on the host (NumPy): their checks and broadcasts dispatch no programs;
    # traced inputs (jit, vmap, derivatives) stay arrays
    xp = jnp if traced else np
    q_start = xp.asarray(q_start, float)
    q_goal = xp.asarray(q_goal, float)
    if q_start.ndim != 2 or q_start.shape[1] != n:
        raise ValueError(f"q_start must have shape (B, {n}), got {q_start.shape}")
    if q_goal.shape != q_start.shape:
        raise ValueError(f"q_goal must have shape {q_start.shape} like q_start, got {q_goal.shape}")
    B = q_start.shape[0]
    if B < 1:
        raise ValueError("q_start must hold at least one problem (B >= 1)")

    def per_sample(x, name):
        if x is None:
            return xp.zeros((B, n))
        x = xp.asarray(x, float)
        if x.shape not in ((), (n,), (B, n)):
            raise ValueError(f"{name} must be a scalar, ({n},) or ({B}, {n}), got shape {x.shape}")
        return xp.broadcast_to(x, (B, n))

    qd_start, qd_goal = per_sample(qd_start, "qd_start"), per_sample(qd_goal, "qd_goal")
    T_max = xp.broadcast_to(xp.asarray(np.inf if T_max is None else T_max, float), (B,))
    Transcription(transcription)
    _check_efforts(efforts, transcription)
    jerk = default_jerk(robot)  # the problems' default (see Problem's jerk)
    if jerk and transcription not in Transcription.JERK:
        raise ValueError(f"robot {robot.name!r} has a jerk bound, which transcription {transcription!r} cannot "
                         f"impose; solve Problem(..., jerk=False) one by one, or use one of {Transcription.JERK}")
    opts = resolve_method(opts, transcription, robot, jerk)
    weights = Weights() if weights is None else weights
    key = _setup.before_solve(robot, N, batch=True, weights=weights, options=opts, transcription=transcription,
                              efforts=efforts)
    _kkt_native.prefetch(robot.n)  # the native kernel's build runs while the solver is traced

    def make(a, b, c, d, t):
        return _problem(robot, a, b, c, d, t, N, weights, efforts, jerk)

    if slots == "auto":
        slots = cpu_lanes(N * (n + 1)) if jax.default_backend() == "cpu" else 1024
    if slots is not None and (not isinstance(slots, int) or isinstance(slots, bool) or slots < 1):
        raise ValueError(f"slots must be a positive integer, 'auto' or None, got {slots!r}")
    if not isinstance(segment, int) or segment < 1:
        raise ValueError(f"segment must be a positive integer, got {segment!r}")
    if progress is not None and not callable(progress):
        raise ValueError(f"progress must be a callable progress(finished, B) or None, got {progress!r}")
    _resources.check(N, n, B, lanes=slots or B)  # ValueError naming N or B beyond the memory limit
    # (inside another trace: the programs without their XLA options, see jtraj._compile.nested_jit)
    problems = (nested_jit(_problems_jit) if traced else _problems_jit)(
        robot, q_start, q_goal, qd_start, qd_goal, T_max, N, weights, efforts, jerk)
    warm = init is not None
    if init is None:
        # non-finite samples get a finite placeholder guess; they are flagged invalid
        init = (nested_jit(_guess_batch_jit) if traced else _guess_batch_jit)(problems, opts, transcription)
    else:
        m_u = Transcription(transcription).control_dim(make(q_start[0], q_goal[0], qd_start[0], qd_goal[0], T_max[0]))
        u, h = jnp.asarray(init[0], float), jnp.asarray(init[1], float)
        if u.shape != (B, N, m_u) or h.shape != (B, N):
            raise ValueError(f"init must be (u (B, N, {m_u}), h (B, N)) = ({(B, N, m_u)}, {(B, N)}), "
                             f"got ({u.shape}, {h.shape})")
        init = (u, h)
    if traced or implicit.any_traced(init):  # derivatives per sample (jtraj.implicit)
        return implicit.solve_batch_traced(problems, opts, transcription, init, warm, slots, segment)
    sol = solve_problems(problems, opts, transcription, init, warm, slots, segment, progress)
    _setup.compiled(key)
    return sol


def _batched_problem(problem: Problem, **array_form):
    """The array form's arguments of a batched :class:`Problem`; ``ValueError`` naming what
    a batch cannot hold or what was passed twice."""
    for name, value in array_form.items():
        if value is not None:
            raise ValueError(f"{name} is the problem's own in solve_batch(problem); pass it to jtraj.Problem")
    if problem.batch_size is None:
        raise ValueError(f"problem must be a batch (q_start of shape (B, {problem.robot.n})), got q_start of shape "
                         f"{problem.q_start.shape}; solve one problem with jtraj.solve")
    if problem.via_points:
        raise ValueError("problem.via_points: a batch has none; solve problems with via points with jtraj.solve")
    if problem.jerk != default_jerk(problem.robot):
        raise ValueError(f"problem.jerk={problem.jerk} is not robot {problem.robot.name!r}'s default: a batch takes "
                         f"the default; solve such problems with jtraj.solve")
    for name in ("time", "energy", "kinetic", "singularity"):
        if jnp.ndim(getattr(problem.weights, name)) != 0:
            raise ValueError(f"weights.{name} must be a scalar: a batch shares its weights, got shape "
                             f"{jnp.shape(getattr(problem.weights, name))}")
    return (problem.robot, problem.q_start, problem.q_goal, problem.N, problem.weights, problem.qd_start,
            problem.qd_goal, problem.T_max, problem.efforts)
