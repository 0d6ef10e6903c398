"""The solver's options (:class:`SolverOptions`) and their split into the traced
numbers and the static structure a compiled program depends on."""

from __future__ import annotations

import dataclasses
import functools

import equinox as eqx
import jax
import numpy as np

from .. import _tracecache
from .._compile import SOLVER_XLA_OPTIONS, cpu_jit, supported_options
from .._compile import solver_jit as _jit
from .methods import PBM_SETTINGS, SOLVERS, Auto, check_flat, flat, flat_traced, from_flat


# ----------------------------------------------------------------------------------------
# options


class SolverOptions(eqx.Module):
    """Options of the solver as one flat set. Deprecated: pass a solver object instead,
    ``jtraj.solve(problem, solver=...)`` with :class:`jtraj.Auto` (``method="auto"``),
    :class:`jtraj.IPM` (``"ip"``) or :class:`jtraj.AugmentedLagrangian` (``"al"``);
    :func:`jtraj.solver.from_options` gives the object of given options. The AL fields
    keep their names on :class:`~jtraj.AugmentedLagrangian` (an IPM's ``fallback``);
    the ``ip_`` fields lose the prefix on :class:`~jtraj.IPM`.

    Options that differ only in numbers (tolerances, penalties, iteration limits, the
    stall and kink settings: ``TRACED_OPTIONS``) share one compiled solver: those fields
    are traced. The others (``max_outer``, ``schedule``, ``guess``, ``linear_solver``,
    ``inequality_penalty``, ``pbm_init``, ``pbm_ratio``, ``method``), and whether
    ``pbm_fallback_iter``, ``kink_margin``, ``inner_tol_ratio`` or ``pbm_inner_tol_ratio``
    is 0, shape the program: changing them compiles another. The measurements behind the
    defaults are in the documentation's "Solver methods and options" guide.

    Attributes:
        max_iter: total Newton iterations of the AL loop, over all its subproblems
            (default 500). Raise it for hard problems that end ``FEASIBLE_NOT_OPTIMAL``.
        max_outer: maximum number of multiplier updates of the AL loop (default 30).
        max_inner: Newton iterations per AL subproblem before a forced outer update
            (default 60; fewer lose converged pairs, more gain nothing).
        tol_optimality: target on the projected gradient of the augmented Lagrangian in
            the scaled variables, on the interior-point method's dual and complementarity
            parts (caps ``ip_dual_tol`` and ``ip_compl_tol``) and on the certificate's KKT
            error: a converged solution's ``Solution.kkt_error`` is at most
            ``max(tol_optimality, ip_tol)`` (default 3e-4). Ask for 1e-4 or less where the last
            0.01 % of the cost matters; 1e-3 is faster and about 0.01 % costlier.
        inner_tol_ratio: each AL subproblem after the first is solved to
            ``max(tol_optimality, min(1e-2, inner_tol_ratio * violation))``
            (Conn-Gould-Toint's coupling; default 0.01). 0 restores the geometric
            schedule ``omega <- omega / 10``.
        tol_feasibility: the AL loop's target on the normalised violation (default
            1e-5); the final feasibility polish removes what remains and ``verify_tol``
            decides.
        penalty_init, penalty_growth, penalty_max: the PHR penalty mu starts at
            ``penalty_init`` (10) and grows by ``penalty_growth`` (4) up to
            ``penalty_max`` (1e6) whenever the violation did not shrink by
            ``feasibility_ratio``.
        feasibility_ratio: the factor by which the violation must shrink per outer
            iteration for the penalty to stay (default 0.5).
        schedule: "default" (multipliers updated at every outer iteration, ALGENCAN
            style) or "thesis" (Conn-Gould-Toint / Khoukhi: multipliers updated only
            when the violation meets the current tolerance eta, which tightens as
            ``eta <- eta mu^-beta_eta``; otherwise mu grows and ``eta <- eta0 mu^-alpha_eta``).
        damping_init: initial Levenberg damping of the AL loop's Newton system (default
            1e-4).
        verify_tol: tolerance of the final strict verification, relative for bounds and
            absolute for the goal (default 1e-6). ``converged`` requires it.
        guess: the starting point. "cycloidal_torque" (default): the minimum-time cycloid
            slowed until it meets the torque bounds; "cycloidal": Khoukhi's (kinematic
            bounds only); "trapezoidal" (see :mod:`jtraj.initial_guess`).
        linear_solver: how Newton directions are computed. "auto" (default): "riccati" on
            a CPU, "dense" on an accelerator. "riccati": a stage-wise Riccati recursion
            (decoupled transcription, :mod:`jtraj.lq`), cost linear in N; "dense":
            Cholesky factorisations of the assembled Hessian, O(N^3) (the other
            transcriptions always use it).
        detect_infeasible: stop a problem whose violation shrank by less than 5 % over
            two outer iterations while the penalty grew at least 16x or stayed at its cap
            (status ``LIKELY_INFEASIBLE``; default on). Decoupled transcription only.
        restart_iter: a run that ends uncertified (not ``LIKELY_INFEASIBLE``) is
            restarted once from its polished final point with least-squares multipliers,
            for up to ``restart_iter`` more iterations (default 600; 0 disables it). It
            rescues problems with a thin feasible set (minimum time close to N h_max).
        restart_penalty_max: the penalty cap of a restart (default 1e4; the restart
            starts at a hundredth of it).
        stall_window, stall_ratio, stall_min_viol, stall_after: an opt-in early exit for
            AL subproblems that stop making progress: every ``stall_window`` iterations
            (after ``stall_after`` in the run) a subproblem ends if its AL fell by less
            than ``stall_ratio mu v^2`` while the violation v is above
            ``stall_min_viol``. Off by default (``stall_window=0``); 10 saves 5-7 % of the
            iterations where infeasible problems are common, but can stop a rare feasible
            problem as ``LIKELY_INFEASIBLE``.
        inequality_penalty: the inequalities' term in the augmented Lagrangian. "phr"
            (default): Rockafellar's ``(max(0, rho + mu g)^2 - rho^2) / (2 mu)``, once
            differentiable. "pbm": Ben-Tal and Zibulevsky's penalty-barrier multiplier
            term ``rho / mu phi(mu g)`` (twice differentiable, multiplicative multiplier
            updates); use :meth:`SolverOptions.pbm` for its tuned settings. It takes about
            a third fewer Newton iterations than PHR on the benchmark family and none
            fewer on the dataset family.
        pbm_fallback_iter: Newton iterations of a PBM run before it falls back to PHR's
            own cold run from the same start (default 200; 0: no fallback).
        pbm_inner_tol_ratio: ``inner_tol_ratio`` of the PBM phase of a PBM run (default
            0.1); its PHR fallback and restart use ``inner_tol_ratio``.
        pbm_init, pbm_ratio: the PBM multipliers' starting value (default 0.1) and the
            bound on the factor of each multiplicative update (default 4).
        detect_min_viol: in PBM runs, ``detect_infeasible``'s first rule also needs the
            violation above this at the two previous outer iterations (default 0; 1e-2
            in :meth:`SolverOptions.pbm`). PHR runs ignore it.
        method: the inner method. "auto" (default): "ip" where it applies (decoupled
            transcription, no path equalities, PHR term), "al" elsewhere. "ip": the
            primal-dual interior-point method of :mod:`jtraj.solver.ipm`, with the AL loop as a
            fallback for what it leaves unsolved. "al": the augmented-Lagrangian loop
            alone.
        ip_max_iter: interior-point iterations before the AL fallback (default 150).
        ip_tol, ip_dual_tol, ip_compl_tol: an interior-point run is solved where IPOPT's
            scaled optimality error is at most ``ip_tol`` (default 1e-7), or where the
            dual infeasibility is within ``ip_dual_tol`` (1e-4), the complementarity
            within ``ip_compl_tol`` (1e-5) and every residual within ``verify_tol / 2``.
            Each part is capped by the AL loop's ``tol_optimality`` / ``tol_feasibility``,
            so options asking for a tighter solve make the run go on to ``ip_tol``.
        ip_project_tol: where the dual and complementarity parts are met and every
            residual is within this (default 1e-4), the interior-point method takes a
            closing step onto the constraints (at most two per run; 0 switches it off).
        ip_damping: floor of the interior-point method's damping shift, kept on the
            Hessian's diagonal after a step its line search cut to a quarter or less
            (default 1e-2; 0 switches it off).
        ip_mu_init: the interior-point method's first barrier parameter (default 0.1); a
            smaller one shortens the barrier schedule for a start near an optimum.
        ip_bound_push: how far inside its boxes an interior-point run starts (default
            1e-2): z at least ``ip_bound_push * max(1, |bound|)`` inside each finite bound
            (at most 0.49 of the box), every inequality's slack at least
            ``ip_bound_push``; smaller keeps a warm start where it is.
        ip_first_shift: the reference of the Hessian shifts an interior-point run starts
            with (default 1.0; see ``IPM.first_shift``); smaller suits a start near an
            optimum.
        ip_curvature: the interior-point method's Newton model of the dynamics terms
            (:mod:`jtraj.solver.curvature`). "exact": the Lagrangian's Hessian;
            "gauss_newton": without the effort multipliers' second derivatives of the
            inverse dynamics (same gradients and optimality test, so the same optima, at a
            much cheaper and smaller program). "auto" (default): "gauss_newton" for
            spatial arms, "exact" elsewhere.
        kink_margin, kink_after: from the ``kink_after``-th Newton iteration of an AL
            subproblem on (default 20), its Newton model adds the penalty curvature of the
            inequalities within ``kink_margin`` (default 1e-3) short of their PHR kink,
            which the exact Hessian of the once-differentiable PHR term misses. 0
            switches it off.
    """

    max_iter: int = eqx.field(static=True, default=500)
    max_outer: int = eqx.field(static=True, default=30)
    max_inner: int = eqx.field(static=True, default=60)
    tol_feasibility: float = eqx.field(static=True, default=1e-5)
    tol_optimality: float = eqx.field(static=True, default=3e-4)
    inner_tol_ratio: float = eqx.field(static=True, default=0.01)
    pbm_inner_tol_ratio: float = eqx.field(static=True, default=0.1)
    penalty_init: float = eqx.field(static=True, default=10.0)
    penalty_growth: float = eqx.field(static=True, default=4.0)
    penalty_max: float = eqx.field(static=True, default=1e6)
    feasibility_ratio: float = eqx.field(static=True, default=0.5)
    schedule: str = eqx.field(static=True, default="default")
    damping_init: float = eqx.field(static=True, default=1e-4)
    verify_tol: float = eqx.field(static=True, default=1e-6)
    guess: str = eqx.field(static=True, default="cycloidal_torque")
    detect_infeasible: bool = eqx.field(static=True, default=True)
    linear_solver: str = eqx.field(static=True, default="auto")
    restart_iter: int = eqx.field(static=True, default=600)
    restart_penalty_max: float = eqx.field(static=True, default=1e4)
    kink_margin: float = eqx.field(static=True, default=1e-3)
    kink_after: int = eqx.field(static=True, default=20)
    stall_window: int = eqx.field(static=True, default=0)
    stall_ratio: float = eqx.field(static=True, default=0.1)
    stall_min_viol: float = eqx.field(static=True, default=1e-2)
    stall_after: int = eqx.field(static=True, default=100)
    inequality_penalty: str = eqx.field(static=True, default="phr")
    pbm_init: float = eqx.field(static=True, default=0.1)
    pbm_ratio: float = eqx.field(static=True, default=4.0)
    pbm_fallback_iter: int = eqx.field(static=True, default=200)
    detect_min_viol: float = eqx.field(static=True, default=0.0)
    method: str = eqx.field(static=True, default="auto")
    ip_max_iter: int = eqx.field(static=True, default=150)
    ip_tol: float = eqx.field(static=True, default=1e-7)
    ip_dual_tol: float = eqx.field(static=True, default=1e-4)
    ip_compl_tol: float = eqx.field(static=True, default=1e-5)
    ip_project_tol: float = eqx.field(static=True, default=1e-4)
    ip_damping: float = eqx.field(static=True, default=1e-2)
    ip_mu_init: float = eqx.field(static=True, default=0.1)
    ip_bound_push: float = eqx.field(static=True, default=1e-2)
    ip_first_shift: float = eqx.field(static=True, default=1.0)
    ip_curvature: str = eqx.field(static=True, default="auto")

    @classmethod
    def pbm(cls, **overrides) -> "SolverOptions":
        """The penalty-barrier multiplier variant (``inequality_penalty="pbm"``) with the
        settings tuned for it on the serial3 benchmark; ``overrides`` replace any field."""
        return cls(**{**PBM_SETTINGS, **overrides})

    def __check_init__(self):
        check_flat({f.name: getattr(self, f.name) for f in dataclasses.fields(self)})


#: SolverOptions fields that enter the compiled programs only as numbers: they cross the
#: jit boundary as traced scalars (:func:`options_jit`), so that options differing only
#: in them share one compilation (a sweep over tolerances or penalties compiles once).
#: The other fields shape the programs and stay static. Of the ones here, a value of 0
#: also switches a part of the loop off (``_SWITCHES``): the static copy keeps 0 or 1.
TRACED_OPTIONS = tuple(flat_traced())
_SWITCHES = tuple(name for name, off_at_zero in flat_traced().items() if off_at_zero)


class SplitOptions(eqx.Module):
    """A :class:`SolverOptions` crossing a jit boundary: ``static`` (the fields of
    ``TRACED_OPTIONS`` at their defaults, the switches at 0 or 1) and ``values`` (those
    fields' own values, 0-d arrays)."""

    static: SolverOptions = eqx.field(static=True)
    values: dict


class TracedOptions:
    """The options inside a compiled program: the fields of ``TRACED_OPTIONS`` read from
    the traced ``values``, the others from the static copy (:func:`static_options` gives it)."""

    def __init__(self, split: SplitOptions):
        self.static_options, self._values = split.static, split.values

    def __getattr__(self, name):
        values = self.__dict__["_values"]
        return values[name] if name in values else getattr(self.__dict__["static_options"], name)


def to_options(solver) -> SolverOptions:
    """The flat :class:`SolverOptions` a solver object (:mod:`jtraj.solver.methods`)
    maps onto: the compiled programs read these, so a solver object and the options it
    maps onto run the same programs. Cached: the same object first by identity (hashing
    a solver costs about as much as hashing a SolverOptions, see :func:`split_options`),
    then per equal object."""
    hit = _TO_OPTIONS_BY_ID.get(id(solver))
    if hit is not None and hit[0] is solver:
        return hit[1]
    try:
        opts = _to_options_cached(solver)
    except TypeError:  # an unhashable field value (an array): not cached
        return SolverOptions(**_plain(flat(solver)))
    if len(_TO_OPTIONS_BY_ID) >= 64:
        _TO_OPTIONS_BY_ID.pop(next(iter(_TO_OPTIONS_BY_ID)))
    _TO_OPTIONS_BY_ID[id(solver)] = (solver, opts)  # (holding solver keeps its id unique)
    return opts


_TO_OPTIONS_BY_ID: dict[int, tuple] = {}


@functools.lru_cache(maxsize=64)
def _to_options_cached(solver) -> SolverOptions:
    return SolverOptions(**_plain(flat(solver)))


def _plain(values: dict) -> dict:
    """Option values as Python numbers: concrete 0-d arrays become scalars; a traced
    value raises (the options are fixed when the solver is compiled)."""
    out = {}
    for name, value in values.items():
        if isinstance(value, (jax.Array, np.ndarray, np.generic)):
            if isinstance(value, jax.core.Tracer) or np.ndim(value) != 0:
                raise ValueError(f"solver option {name} must be a concrete number, got {value!r}")
            value = np.asarray(value).item()
        out[name] = value
    return out


def from_options(options: SolverOptions):
    """The solver object (:class:`jtraj.Auto`, :class:`jtraj.IPM` or
    :class:`jtraj.AugmentedLagrangian`, by ``options.method``) holding ``options``:
    ``jtraj.solve(p, solver=from_options(o))`` solves as ``jtraj.solve(p, options=o)``."""
    if not isinstance(options, SolverOptions):
        raise ValueError(f"options must be a jtraj.SolverOptions, got {type(options).__name__}")
    return _from_options_cached(options)


@functools.lru_cache(maxsize=64)
def _from_options_cached(options: SolverOptions):
    return from_flat({f.name: getattr(options, f.name) for f in dataclasses.fields(options)})


def as_solver(value, name: str = "options"):
    """A solver object from what the functions that still take ``options`` accept: None
    (the default solver), a solver object, or a :class:`SolverOptions`
    (:func:`from_options`); ``ValueError`` naming ``name`` otherwise."""
    if value is None or isinstance(value, SOLVERS):
        return value
    if isinstance(value, SolverOptions):
        return from_options(value)
    raise ValueError(f"{name} must be jtraj.Auto, jtraj.IPM, jtraj.AugmentedLagrangian or a jtraj.SolverOptions, "
                     f"got {type(value).__name__}")


def overrides(solver) -> dict:
    """A solver's options that differ from the defaults, in the flat option names
    (``SolverOptions``' fields: the AL fields, the ``ip_`` fields), with its ``method``
    always: the form a dataset records (:func:`jtraj.dataset.make_spec`)."""
    solver = as_solver(solver, "solver")
    values = _plain(flat(Auto() if solver is None else solver))
    defaults = SolverOptions.__dataclass_fields__
    return {name: value for name, value in values.items()
            if name == "method" or value != defaults[name].default}


def from_overrides(values: dict, name: str = "options"):
    """The solver object of flat option overrides (``{SolverOptions field: value}``,
    ``method`` among them or ``"auto"``): the inverse of :func:`overrides`.
    ``ValueError`` naming ``name`` and the option for an unknown name or a bad value."""
    fields = SolverOptions.__dataclass_fields__
    for key in values:
        if key not in fields:
            raise ValueError(f"{name}: unknown solver option {key!r}; the options are {sorted(fields)}")
    try:
        return from_options(SolverOptions(**values))
    except (TypeError, ValueError) as err:
        raise ValueError(f"{name}: {err}") from None


def static_options(opts):
    """The options' static copy (a :class:`SolverOptions`): where the program's structure
    is decided (which parts of the loop exist), never for a traced field's value."""
    return opts.static_options if isinstance(opts, TracedOptions) else opts


def split_options(opts: SolverOptions) -> SplitOptions:
    # cached per options and float width (jax_enable_x64 may change between calls); the
    # same options object (the defaults' is one, see _resolved) first by identity: hashing
    # a SolverOptions for the lru_cache costs ~30 us of a ~4 ms warm single solve
    width = jax.dtypes.canonicalize_dtype(np.float64)
    hit = _SPLIT_BY_ID.get(id(opts))
    if hit is not None and hit[0] is opts and hit[1] == width:
        return hit[2]
    split = _split_cached(opts, width)
    if len(_SPLIT_BY_ID) >= 64:
        _SPLIT_BY_ID.pop(next(iter(_SPLIT_BY_ID)))
    _SPLIT_BY_ID[id(opts)] = (opts, width, split)  # (holding opts keeps its id unique)
    return split


_SPLIT_BY_ID: dict[int, tuple] = {}


@functools.lru_cache(maxsize=64)
def _split_cached(opts: SolverOptions, _width) -> SplitOptions:
    defaults = SolverOptions.__dataclass_fields__
    static, values = {}, {}
    for name in TRACED_OPTIONS:
        value = getattr(opts, name)
        static[name] = type(value)(value != 0) if name in _SWITCHES else defaults[name].default
        kind = (np.bool_ if isinstance(value, (bool, np.bool_))
                else np.int64 if isinstance(value, (int, np.integer)) else np.float64)
        values[name] = np.asarray(value, dtype=jax.dtypes.canonicalize_dtype(kind))
    return SplitOptions(static=dataclasses.replace(opts, **static), values=values)


def options_jit(xla_options: dict | None = None, quick_first: bool = False):
    """Like the solver's jit decorator (:func:`jtraj._compile.solver_jit`), but every
    :class:`SolverOptions` argument crosses the boundary split by :func:`split_options`
    and is read inside as :class:`TracedOptions`. On a CPU the traced program is kept
    across processes where the compilation cache is on (:mod:`jtraj._tracecache`).
    ``xla_options``: the XLA CPU options (default ``SOLVER_XLA_OPTIONS``);
    ``quick_first``: a kept program compiles quickly for its first call in a process
    (:func:`jtraj._tracecache.tiered`)."""
    xla_options = SOLVER_XLA_OPTIONS if xla_options is None else xla_options

    def decorate(fn):
        def unsplit(*args):
            return fn(*(TracedOptions(a) if isinstance(a, SplitOptions) else a for a in args))

        inner = (_jit if xla_options is SOLVER_XLA_OPTIONS else cpu_jit(xla_options))(functools.wraps(fn)(unsplit))

        @functools.lru_cache(maxsize=1)
        def kept():
            # the solver's programs kept across processes (jtraj._tracecache), on a CPU
            return _tracecache.cached(fn.__qualname__, unsplit, f"{fn.__module__}.{fn.__qualname__}",
                                      supported_options(xla_options), fallback=inner, lean=True,
                                      quick_first=quick_first)

        @functools.wraps(fn)
        def call(*args):
            args = tuple(split_options(a) if isinstance(a, SolverOptions) else a for a in args)
            if jax.default_backend() == "cpu":
                return kept()(*args)
            return inner(*args)

        return call

    return decorate
