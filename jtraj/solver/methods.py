"""The solvers as objects: :class:`AugmentedLagrangian`, :class:`IPM` and the default
:class:`Auto`, each an ``eqx.Module`` holding its own options, passed as
``jtraj.solve(problem, solver=...)`` and ``jtraj.solve_batch(..., solver=...)``.

The fields say how they reach the compiled solver. An ordinary field (a pytree leaf) is
*traced*: it crosses into the compiled programs as a traced scalar, so solvers that
differ only in such numbers share one compilation (a sweep over tolerances compiles
once). A field marked ``eqx.field(static=True)`` is *static*: it shapes the program, and
another value compiles another program. Traced fields marked ``off_at_zero`` also
switch a part of the loop off at 0, so whether they are 0 is static. A solve reads the
values when it starts: they are Python numbers (or concrete 0-d arrays), never traced
values (a solver passed through ``jax.jit`` as an argument is refused; ``eqx.filter_jit``
keeps its numbers static).
:mod:`jtraj.solver.options` reads this marking (:func:`traced_fields`); nothing lists
the traced options by hand.

Choices among named variants are enumerations (:class:`Schedule`, :class:`Guess`,
:class:`LinearSolver`, :class:`InequalityPenalty`, :class:`Curvature`); a field
accepts the member or its string value and holds the string.
"""

from __future__ import annotations

import dataclasses
import enum

import equinox as eqx
import jax
import numpy as np


class Schedule(str, enum.Enum):
    """When the AL loop updates its multipliers (:attr:`AugmentedLagrangian.schedule`)."""

    #: at every outer iteration (ALGENCAN style)
    DEFAULT = "default"
    #: only when the violation meets the current tolerance (Conn-Gould-Toint / Khoukhi)
    THESIS = "thesis"


class Guess(str, enum.Enum):
    """The starting point of a cold solve (:mod:`jtraj.initial_guess`)."""

    #: the minimum-time cycloid slowed until it meets the torque bounds
    CYCLOIDAL_TORQUE = "cycloidal_torque"
    #: Khoukhi's cycloid (kinematic bounds only)
    CYCLOIDAL = "cycloidal"
    #: a trapezoidal velocity profile
    TRAPEZOIDAL = "trapezoidal"


class LinearSolver(str, enum.Enum):
    """How Newton directions are computed."""

    #: RICCATI on a CPU, DENSE on an accelerator
    AUTO = "auto"
    #: a stage-wise Riccati recursion (decoupled transcription, :mod:`jtraj.lq`), linear in N
    RICCATI = "riccati"
    #: Cholesky factorisations of the assembled Hessian, O(N^3)
    DENSE = "dense"


class InequalityPenalty(str, enum.Enum):
    """The inequalities' term in the augmented Lagrangian."""

    #: Rockafellar's ``(max(0, rho + mu g)^2 - rho^2) / (2 mu)``, once differentiable
    PHR = "phr"
    #: Ben-Tal and Zibulevsky's penalty-barrier multiplier term, twice differentiable
    PBM = "pbm"


class Curvature(str, enum.Enum):
    """The interior-point method's Newton model of the dynamics terms
    (:mod:`jtraj.solver.curvature`)."""

    #: GAUSS_NEWTON for spatial arms, EXACT elsewhere
    AUTO = "auto"
    #: the Lagrangian's Hessian
    EXACT = "exact"
    #: without the effort multipliers' second derivatives of the inverse dynamics
    GAUSS_NEWTON = "gauss_newton"


def _choice(kind: type[enum.Enum], name: str):
    """A field converter: a member of ``kind`` or its value, held as the plain string
    (the compiled programs' static values stay strings)."""

    def convert(value):
        try:
            return kind(value).value
        except ValueError:
            raise ValueError(f"{name} must be one of {[m.value for m in kind]}, got {value!r}") from None

    return convert


def _traced(default, *, off_at_zero: bool = False):
    """A traced option (a leaf; see the module docstring)."""
    return eqx.field(default=default, metadata={"off_at_zero": off_at_zero})


def _static(default, converter=None):
    """A static option: it shapes the compiled program."""
    if converter is None:
        return eqx.field(static=True, default=default)
    return eqx.field(static=True, default=default, converter=converter)


def traced_fields(cls) -> dict[str, bool]:
    """``{field name: off_at_zero}`` of the traced options of a solver class."""
    return {f.name: bool(f.metadata.get("off_at_zero", False)) for f in dataclasses.fields(cls)
            if not f.metadata.get("static", False) and "off_at_zero" in f.metadata}


def check_flat(values: dict) -> None:
    """``ValueError`` naming the first invalid option of a flat option dict (shared by
    the solver objects and ``SolverOptions``); names not in ``values`` are skipped."""
    def each(*names):
        return [(name, values[name]) for name in names if name in values]

    for name, value in each("method"):
        if value not in ("auto", "al", "ip"):
            raise ValueError(f"method must be 'auto', 'al' or 'ip', got {value!r}")
    choices = {"schedule": Schedule, "ip_curvature": Curvature, "inequality_penalty": InequalityPenalty,
               "linear_solver": LinearSolver, "guess": Guess}
    for name, value in each(*choices):
        _choice(choices[name], name)(value)
    for name, value in each("pbm_ratio"):
        if not value > 1:
            raise ValueError(f"pbm_ratio must be > 1, got {value!r}")
    for name, value in each("inner_tol_ratio", "pbm_inner_tol_ratio"):
        if not value >= 0:
            raise ValueError(f"{name} must be >= 0, got {value!r}")
    for name, value in each("max_iter", "max_outer", "max_inner"):
        if value < 1:
            raise ValueError(f"{name} must be >= 1")
    for name, value in each("restart_iter", "kink_after", "stall_window", "stall_after", "pbm_fallback_iter",
                            "ip_max_iter"):
        if not (isinstance(value, (int, np.integer)) and not isinstance(value, bool) and value >= 0):
            raise ValueError(f"{name} must be an integer >= 0, got {value!r}")
    for name, value in each("kink_margin", "stall_ratio", "stall_min_viol", "detect_min_viol", "ip_dual_tol",
                            "ip_compl_tol", "ip_project_tol", "ip_damping"):
        if not _finite(value, 0.0, strict=False):
            raise ValueError(f"{name} must be a finite number >= 0, got {value!r}")
    for name, value in each("tol_feasibility", "tol_optimality", "verify_tol", "penalty_init", "penalty_max",
                            "damping_init", "restart_penalty_max", "pbm_init", "ip_tol", "ip_mu_init"):
        if not _finite(value, 0.0, strict=True):
            raise ValueError(f"{name} must be a positive finite number, got {value!r}")
    for name, value in each("ip_bound_push"):
        if not (_finite(value, 0.0, strict=True) and value < 0.5):
            raise ValueError(f"ip_bound_push must be a finite number in (0, 0.5), got {value!r}")
    for name, value in each("ip_first_shift"):
        if not (_finite(value, 0.0, strict=True) and 1e-6 <= value <= 1e8):
            raise ValueError(f"ip_first_shift must be a finite number in [1e-6, 1e8], got {value!r}")
    for name, value in each("penalty_growth"):
        if not value > 1:
            raise ValueError(f"penalty_growth must be > 1, got {value!r}")
    for name, value in each("feasibility_ratio"):
        if not 0 < value < 1:
            raise ValueError(f"feasibility_ratio must be in (0, 1), got {value!r}")


def _finite(value, low: float, strict: bool) -> bool:
    try:  # NumPy scalars of any float width too
        v = float(value)
    except (TypeError, ValueError):
        return False
    return (v > low if strict else v >= low) and v < float("inf")


def _validate(solver, renames: dict | None = None):
    """:func:`check_flat` of the solver's own fields (``renames``: field -> flat name),
    the error naming the class's field."""
    renames = renames or {}
    for f in dataclasses.fields(solver):
        if isinstance(getattr(solver, f.name), jax.core.Tracer):
            raise ValueError(f"{type(solver).__name__}.{f.name} must be a concrete number (a solver's options are "
                             f"fixed when a solve starts), got a traced value")
    values = {renames.get(f.name, f.name): getattr(solver, f.name) for f in dataclasses.fields(solver)
              if f.name != "fallback"}
    try:
        check_flat(values)
    except ValueError as err:
        message = str(err)
        for name, flat_name in renames.items():
            if message.startswith(flat_name + " "):
                message = name + message[len(flat_name):]
        raise ValueError(f"{type(solver).__name__}.{message}") from None


#: the fields :meth:`AugmentedLagrangian.pbm` sets (tuned on bench_solver's pairs);
#: ``jtraj dataset --inequalities pbm`` stores them as the dataset's option overrides
PBM_SETTINGS = dict(inequality_penalty="pbm", penalty_init=100.0, detect_min_viol=1e-2)


class AugmentedLagrangian(eqx.Module):
    """The augmented-Lagrangian method alone: a projected, damped Newton method on
    PHR (or PBM) subproblems (:mod:`jtraj.solver.al`). It also holds what every method
    shares: the targets (``tol_optimality``, ``tol_feasibility``, ``verify_tol``), the
    start (``guess``) and the linear solver. Defaults are tuned on the serial3 benchmark.

    Attributes:
        max_iter: total Newton iterations over all subproblems (500). Raise it for hard
            problems that end ``FEASIBLE_NOT_OPTIMAL``.
        max_outer: maximum number of multiplier updates (30).
        max_inner: Newton iterations per subproblem before a forced outer update (60).
        tol_feasibility: target on the normalised violation (1e-5); the final polish
            removes what remains and ``verify_tol`` decides.
        tol_optimality: target on the projected gradient in the scaled variables and
            on the certificate's KKT error; it caps the interior-point method's dual and
            complementarity tolerances (3e-4). 1e-4 or less where the last 0.01 % of the
            cost matters.
        inner_tol_ratio: subproblems after the first are solved to
            ``max(tol_optimality, min(1e-2, inner_tol_ratio * violation))`` (0.01); 0
            restores the geometric schedule ``omega <- omega / 10``.
        pbm_inner_tol_ratio: ``inner_tol_ratio`` of the PBM phase of a PBM run (0.1).
        penalty_init, penalty_growth, penalty_max: the penalty mu starts at 10 and grows
            by 4 up to 1e6 whenever the violation did not shrink by ``feasibility_ratio``.
        feasibility_ratio: the factor by which the violation must shrink per outer
            iteration for the penalty to stay (0.5).
        schedule: a :class:`Schedule` (``"default"``).
        damping_init: initial Levenberg damping of the Newton system (1e-4).
        verify_tol: tolerance of the final strict verification, relative for bounds and
            absolute for the goal (1e-6); ``converged`` requires it.
        guess: a :class:`Guess`, the starting point of a cold solve
            (``"cycloidal_torque"``).
        detect_infeasible: stop a problem whose violation stalls while the penalty grows
            (status ``LIKELY_INFEASIBLE``; on). Decoupled transcription only.
        linear_solver: a :class:`LinearSolver` (``"auto"``).
        restart_iter: iterations of the one restart of an uncertified run from its
            polished point with least-squares multipliers (600; 0: no restart).
        restart_penalty_max: the penalty cap of a restart (1e4).
        kink_margin, kink_after: from the ``kink_after``-th iteration of a subproblem
            (20) the Newton model adds the penalty curvature of inequalities within
            ``kink_margin`` (1e-3) of their PHR kink; 0 switches it off.
        stall_window, stall_ratio, stall_min_viol, stall_after: an opt-in early exit of
            subproblems that stop making progress (off: ``stall_window=0``; 10 saves 5-7 %
            of the iterations where infeasible problems are common).
        inequality_penalty: an :class:`InequalityPenalty` (``"phr"``); use
            :meth:`AugmentedLagrangian.pbm` for PBM's tuned settings.
        pbm_init, pbm_ratio: the PBM multipliers' start (0.1) and the bound on the
            factor of each multiplicative update (4).
        pbm_fallback_iter: iterations of a PBM run before it falls back to a cold PHR
            run (200; 0: no fallback).
        detect_min_viol: in PBM runs, the violation ``detect_infeasible`` also needs at
            the two previous outer iterations (0; 1e-2 in :meth:`pbm`).
    """

    max_iter: int = _traced(500)
    max_outer: int = _static(30)
    max_inner: int = _traced(60)
    tol_feasibility: float = _traced(1e-5)
    tol_optimality: float = _traced(3e-4)
    inner_tol_ratio: float = _traced(0.01, off_at_zero=True)
    pbm_inner_tol_ratio: float = _traced(0.1, off_at_zero=True)
    penalty_init: float = _traced(10.0)
    penalty_growth: float = _traced(4.0)
    penalty_max: float = _traced(1e6)
    feasibility_ratio: float = _traced(0.5)
    schedule: str = _static("default", _choice(Schedule, "schedule"))
    damping_init: float = _traced(1e-4)
    verify_tol: float = _traced(1e-6)
    guess: str = _static("cycloidal_torque", _choice(Guess, "guess"))
    detect_infeasible: bool = _traced(True)
    linear_solver: str = _static("auto", _choice(LinearSolver, "linear_solver"))
    restart_iter: int = _traced(600)
    restart_penalty_max: float = _traced(1e4)
    kink_margin: float = _traced(1e-3, off_at_zero=True)
    kink_after: int = _traced(20)
    stall_window: int = _traced(0)
    stall_ratio: float = _traced(0.1)
    stall_min_viol: float = _traced(1e-2)
    stall_after: int = _traced(100)
    inequality_penalty: str = _static("phr", _choice(InequalityPenalty, "inequality_penalty"))
    pbm_init: float = _static(0.1)
    pbm_ratio: float = _static(4.0)
    pbm_fallback_iter: int = _traced(200, off_at_zero=True)
    detect_min_viol: float = _traced(0.0)

    @classmethod
    def pbm(cls, **overrides) -> "AugmentedLagrangian":
        """The penalty-barrier multiplier variant with its tuned settings
        (``PBM_SETTINGS``); ``overrides`` replace any field."""
        return cls(**{**PBM_SETTINGS, **overrides})

    def __check_init__(self):
        _validate(self)


#: IPM's fields and the flat option each is (``SolverOptions``' ``ip_`` names)
IPM_NAMES = {"max_iter": "ip_max_iter", "tol": "ip_tol", "dual_tol": "ip_dual_tol", "compl_tol": "ip_compl_tol",
             "project_tol": "ip_project_tol", "damping": "ip_damping", "mu_init": "ip_mu_init",
             "bound_push": "ip_bound_push", "first_shift": "ip_first_shift", "curvature": "ip_curvature"}

#: the options every method shares: the targets, the start and the linear solver. The
#: :class:`AugmentedLagrangian` holds them (an :class:`IPM`'s ``fallback``);
#: :class:`IPM` and :class:`Auto` take them as keywords and forward them there, so
#: ``Auto(tol_optimality=1e-5)`` is ``Auto(ipm=IPM(fallback=AugmentedLagrangian(tol_optimality=1e-5)))``
SHARED = ("tol_optimality", "tol_feasibility", "verify_tol", "guess", "linear_solver")


def _shared(owner: str, options: dict, own=()) -> dict:
    """The :data:`SHARED` options among ``options`` (``TypeError`` naming any other
    keyword that is not in ``own``)."""
    unknown = sorted(set(options) - set(SHARED) - set(own))
    if unknown:
        raise TypeError(f"{owner}() got an unexpected keyword argument {unknown[0]!r} (it takes its own fields "
                        f"and the shared options {', '.join(SHARED)})")
    return {name: value for name, value in options.items() if name in SHARED}


def _forwarded(fallback, shared: dict):
    """``fallback`` with the shared options set."""
    if not isinstance(fallback, AugmentedLagrangian):
        raise ValueError(f"fallback must be a jtraj.AugmentedLagrangian, got {type(fallback).__name__}")
    return dataclasses.replace(fallback, **shared) if shared else fallback


class IPM(eqx.Module):
    """The primal-dual interior-point method (:mod:`jtraj.solver.ipm`) with the AL loop
    (``fallback``) as the fallback for what it leaves unsolved. It needs the decoupled
    transcription, no path equalities and no jerk rows; :class:`Auto` picks it where
    it applies. The targets, the start and the linear solver are the fallback's.

    Attributes:
        max_iter: interior-point iterations before the fallback takes over (150).
        tol: a run is solved where IPOPT's scaled optimality error is at most ``tol``
            (1e-7), or where the parts below are met and every residual is within
            ``fallback.verify_tol / 2``.
        dual_tol, compl_tol: the dual infeasibility (1e-4) and complementarity (1e-5)
            parts, each capped by ``fallback.tol_optimality``.
        project_tol: where the parts are met and every residual is within this (1e-4),
            a closing step onto the constraints (at most two per run; 0 switches it off).
        damping: floor of the damping shift kept after a step cut to a quarter or less
            (1e-2; 0 switches it off).
        mu_init: the first barrier parameter (0.1); smaller for a start near an optimum.
        bound_push: how far inside its boxes a run starts (1e-2, IPOPT's ``bound_push``):
            the start's z at least ``bound_push * max(1, |bound|)`` inside each finite
            bound (at most 0.49 of the box), every slack of an inequality at least
            ``bound_push``. Smaller keeps a warm start where it is: with ``mu_init``
            near the optimum's barrier parameter, a start at or near an optimum needs far
            fewer iterations (see the solver guide's "Warm starts").
        first_shift: the reference of the Hessian shifts a run starts with (1.0): where
            the unshifted Newton model is not positive definite, the least of 0.25, 2
            and 16 times the reference that makes it so is taken, and the reference then
            follows the shift taken. Smaller suits a start near an optimum.
        curvature: a :class:`Curvature` (``"auto"``): the Newton model of the dynamics.
        fallback: the :class:`AugmentedLagrangian` that finishes what the method leaves.

    The options every method shares (:data:`SHARED`: ``tol_optimality``,
    ``tol_feasibility``, ``verify_tol``, ``guess``, ``linear_solver``) are also taken as
    keywords and set on ``fallback``: ``IPM(tol_optimality=1e-5)`` is
    ``IPM(fallback=AugmentedLagrangian(tol_optimality=1e-5))``.
    """

    max_iter: int = _static(150)
    tol: float = _static(1e-7)
    dual_tol: float = _traced(1e-4)
    compl_tol: float = _traced(1e-5)
    project_tol: float = _traced(1e-4)
    damping: float = _traced(1e-2)
    mu_init: float = _traced(0.1)
    bound_push: float = _traced(1e-2)
    first_shift: float = _traced(1.0)
    curvature: str = _static("auto", _choice(Curvature, "curvature"))
    fallback: AugmentedLagrangian = AugmentedLagrangian()

    def __init__(self, *, fallback: AugmentedLagrangian | None = None, **options):
        own = [f.name for f in dataclasses.fields(IPM) if f.name != "fallback"]
        shared = _shared("IPM", options, own)
        for name in own:
            setattr(self, name, options.get(name, IPM.__dataclass_fields__[name].default))
        self.fallback = _forwarded(AugmentedLagrangian() if fallback is None else fallback, shared)

    def __check_init__(self):
        if not isinstance(self.fallback, AugmentedLagrangian):
            raise ValueError(f"fallback must be a jtraj.AugmentedLagrangian, got {type(self.fallback).__name__}")
        _validate(self, IPM_NAMES)


class Auto(eqx.Module):
    """The default solver: ``ipm`` where the interior-point method applies (decoupled
    transcription, no path equalities, no jerk rows, the PHR term), its fallback
    ``ipm.fallback`` alone elsewhere.

    Attributes:
        ipm: the :class:`IPM` (its ``fallback`` is the AL method used where the
            interior-point method does not apply).

    The options both methods share (:data:`SHARED`: ``tol_optimality``,
    ``tol_feasibility``, ``verify_tol``, ``guess``, ``linear_solver``) are also taken as
    keywords and set on ``ipm.fallback``, which both read (the interior-point method's
    tolerances are capped by the fallback's targets): ``Auto(tol_optimality=1e-5)``
    asks both methods for the tighter solve.
    """

    ipm: IPM = IPM()

    def __init__(self, ipm: IPM | None = None, **shared):
        shared = _shared("Auto", shared)
        ipm = IPM() if ipm is None else ipm
        if not isinstance(ipm, IPM):
            raise ValueError(f"ipm must be a jtraj.IPM, got {type(ipm).__name__}")
        self.ipm = dataclasses.replace(ipm, fallback=_forwarded(ipm.fallback, shared)) if shared else ipm

    def __check_init__(self):
        if not isinstance(self.ipm, IPM):
            raise ValueError(f"ipm must be a jtraj.IPM, got {type(self.ipm).__name__}")


#: the solver classes :func:`jtraj.solve` accepts
SOLVERS = (Auto, IPM, AugmentedLagrangian)

#: the ``method`` each solver class resolves to
METHODS = {Auto: "auto", IPM: "ip", AugmentedLagrangian: "al"}


def flat(solver) -> dict:
    """The solver's options as one flat ``{name: value}`` dict in the names of the flat
    option set (``method``, the AL fields, the ``ip_`` fields)."""
    if isinstance(solver, AugmentedLagrangian):  # the interior-point fields at their defaults
        al, ip = solver, {flat_name: IPM.__dataclass_fields__[name].default for name, flat_name in IPM_NAMES.items()}
    else:
        ipm = solver.ipm if isinstance(solver, Auto) else solver
        al, ip = ipm.fallback, {flat_name: getattr(ipm, name) for name, flat_name in IPM_NAMES.items()}
    out = {f.name: getattr(al, f.name) for f in dataclasses.fields(AugmentedLagrangian)}
    out.update(ip)
    out["method"] = METHODS[type(solver)]
    return out


def from_flat(values: dict):
    """The solver object of a flat option dict (the inverse of :func:`flat`)."""
    al = AugmentedLagrangian(**{f.name: values[f.name] for f in dataclasses.fields(AugmentedLagrangian)})
    if values["method"] == "al":
        return al
    ipm = IPM(**{name: values[flat_name] for name, flat_name in IPM_NAMES.items()}, fallback=al)
    return ipm if values["method"] == "ip" else Auto(ipm=ipm)


def flat_traced() -> dict[str, bool]:
    """``{flat option name: off_at_zero}`` of every traced option."""
    out = dict(traced_fields(AugmentedLagrangian))
    out.update({IPM_NAMES[name]: zero for name, zero in traced_fields(IPM).items()})
    return out
