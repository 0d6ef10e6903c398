"""The augmented-Lagrangian solver (ALD): outer multiplier/penalty loop around a
projected, damped Newton method on the stage-structured NLP.

Design (why it is fast under ``vmap`` on a CPU):

* **One flat, bounded loop.** Outer (multiplier) and inner (Newton) iterations share
  one ``lax.while_loop``: an outer update is a branch-free ``jnp.where`` taken when
  the inner subproblem is solved to its tolerance. Under ``vmap`` a nested loop would
  run every inner loop to the batch's worst case; the flat one does not.
* **Exact Hessians from small pieces.** The objective is a sum of per-sample terms
  ``l_k(w_k)`` of the stage vector ``w_k = (q_k, qd_k, u_k, h_k)``, composed with the
  polynomial state recursion ``W(z)``. The Hessian is
  ``sum_k J_k^T (d2 l_k) J_k + sum_k (dl_k/dw_k) . d2 W_k``: per-sample (2n+m+1)^2
  Hessians of the inverse dynamics, plus the co-state term of the recursion. The
  co-states ``dl_k/dw_k`` are reverse-mode autodiff, never hand-derived adjoints. In a
  subproblem that stalls, the model adds the penalty curvature of the inequalities just
  short of their PHR kink, which the exact Hessian of a C1 penalty does not see
  (``SolverOptions.kink_margin``).
* **Newton directions stage by stage.** For the decoupled transcription the Hessian in z
  is never formed: the Newton system is the KKT system of a linear-quadratic problem
  over the stages, solved by a Riccati recursion whose cost grows linearly with N
  (:mod:`jtraj.lq`; ``SolverOptions(linear_solver="dense")`` assembles H and factorises
  it instead, O(N^3), as the other transcriptions always do).
* **Bounds kept exactly.** Boxes on the controls and on h are simple bounds on z,
  handled by Bertsekas' projected Newton (no penalty, never violated); all other
  constraints enter the augmented Lagrangian (PHR for inequalities; opt-in, the
  twice-differentiable penalty-barrier multiplier term of ``SolverOptions.pbm()``).
* **Branch-free globalisation (a parallel trust region).** A geometric ladder of
  Levenberg shifts, up to a Gershgorin bound that is always positive definite, is
  factorised at once; every positive-definite shift gives a direction, tried at a few
  step lengths in one vectorised evaluation of the augmented Lagrangian. No iteration
  is spent only on raising the damping after a failed line search.
* **Feasibility polish.** After the loop, a few Gauss-Newton projections onto the
  equalities and nearly-active inequalities remove the O(1/mu) violations the AL
  leaves; the strict verification is made after it.

Shapes follow :mod:`jtraj.transcription`.
"""

from __future__ import annotations

import dataclasses
import enum
import functools
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from . import _packing, _resources, _setup, _tracecache, implicit, ipm, lq
from ._compile import SOLVER_XLA_OPTIONS, cpu_jit, supported_options
from ._compile import solver_jit as _jit
from ._math import log1p
from .problem import Problem, Weights, orientation_error
from .transcription import Layout, StageData, Transcription, decoupled_hessian, decoupled_hessian_bounds

# ----------------------------------------------------------------------------------------
# status codes


class Status(enum.IntEnum):
    """Per-problem outcome. ``int(status)`` is stored in batched results."""

    CONVERGED = 0
    MAX_ITERATIONS = 1
    FEASIBLE_NOT_OPTIMAL = 2
    NUMERICAL_ERROR = 3
    INVALID_INPUT = 4
    VERIFICATION_FAILED = 5
    LIKELY_INFEASIBLE = 6

    @property
    def message(self) -> str:
        return _MESSAGES[self]


_MESSAGES = {
    Status.CONVERGED: "converged: feasible within tolerance and first-order optimal",
    Status.MAX_ITERATIONS: "iteration limit reached before the constraints were met",
    Status.FEASIBLE_NOT_OPTIMAL: "iteration limit reached: feasible, but optimality not certified",
    Status.NUMERICAL_ERROR: "numerical failure (non-finite values); the trajectory is not usable",
    Status.INVALID_INPUT: "invalid input for this sample (non-finite start/goal or infeasible on its face)",
    Status.VERIFICATION_FAILED: "the solver stopped but the re-simulated trajectory violates a bound or misses the goal",
    Status.LIKELY_INFEASIBLE: "stopped early: the violation stopped shrinking while the penalty grew 16x or sat at "
                              "its cap; the problem is likely infeasible (e.g. it needs more time than N h_max or "
                              "T_max allow)",
}


# ----------------------------------------------------------------------------------------
# options


#: the fields :meth:`SolverOptions.pbm` sets (tuned on bench_solver's pairs, see
#: ``SolverOptions.inequality_penalty``); ``jtraj dataset --inequalities pbm`` stores them
#: as the dataset's option overrides
PBM_SETTINGS = dict(inequality_penalty="pbm", penalty_init=100.0, detect_min_viol=1e-2)


class SolverOptions(eqx.Module):
    """Options of the solver; the defaults are tuned on the serial3 benchmark family.

    Options that differ only in numbers (tolerances, penalties, iteration limits, the
    stall and kink settings: ``_TRACED_OPTIONS``) share one compiled solver: those fields
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
            primal-dual interior-point method of :mod:`jtraj.ipm`, with the AL loop as a
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

    @classmethod
    def pbm(cls, **overrides) -> "SolverOptions":
        """The penalty-barrier multiplier variant (``inequality_penalty="pbm"``) with the
        settings tuned for it on the serial3 benchmark; ``overrides`` replace any field."""
        return cls(**{**PBM_SETTINGS, **overrides})

    def __check_init__(self):
        if self.schedule not in ("default", "thesis"):
            raise ValueError(f"schedule must be 'default' or 'thesis', got {self.schedule!r}")
        if self.method not in ("auto", "al", "ip"):
            raise ValueError(f"method must be 'auto', 'al' or 'ip', got {self.method!r}")
        if self.inequality_penalty not in ("phr", "pbm"):
            raise ValueError(f"inequality_penalty must be 'phr' or 'pbm', got {self.inequality_penalty!r}")
        if not self.pbm_ratio > 1:
            raise ValueError(f"pbm_ratio must be > 1, got {self.pbm_ratio!r}")
        if self.linear_solver not in ("auto", "riccati", "dense"):
            raise ValueError(f"linear_solver must be 'auto', 'riccati' or 'dense', got {self.linear_solver!r}")
        if self.guess not in ("cycloidal_torque", "cycloidal", "trapezoidal"):
            raise ValueError(f"guess must be 'cycloidal_torque', 'cycloidal' or 'trapezoidal', got {self.guess!r}")
        for name in ("inner_tol_ratio", "pbm_inner_tol_ratio"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)!r}")
        for name in ("max_iter", "max_outer", "max_inner"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1")
        for name in ("restart_iter", "kink_after", "stall_window", "stall_after", "pbm_fallback_iter", "ip_max_iter"):
            value = getattr(self, name)
            if not (isinstance(value, (int, np.integer)) and not isinstance(value, bool) and value >= 0):
                raise ValueError(f"{name} must be an integer >= 0, got {value!r}")
        for name in ("kink_margin", "stall_ratio", "stall_min_viol", "detect_min_viol", "ip_dual_tol", "ip_compl_tol",
                     "ip_project_tol", "ip_damping"):
            value = getattr(self, name)
            try:
                ok = 0 <= float(value) < float("inf")
            except (TypeError, ValueError):
                ok = False
            if not ok:
                raise ValueError(f"{name} must be a finite number >= 0, got {value!r}")
        for name in ("tol_feasibility", "tol_optimality", "verify_tol", "penalty_init", "penalty_max",
                     "damping_init", "restart_penalty_max", "pbm_init", "ip_tol"):
            value = getattr(self, name)
            try:
                ok = 0 < float(value) < float("inf")  # NumPy scalars of any float width too
            except (TypeError, ValueError):
                ok = False
            if not ok:
                raise ValueError(f"{name} must be a positive finite number, got {value!r}")
        if not self.penalty_growth > 1:
            raise ValueError(f"penalty_growth must be > 1, got {self.penalty_growth!r}")
        if not 0 < self.feasibility_ratio < 1:
            raise ValueError(f"feasibility_ratio must be in (0, 1), got {self.feasibility_ratio!r}")


#: SolverOptions fields that enter the compiled programs only as numbers: they cross the
#: jit boundary as traced scalars (:func:`_options_jit`), so that options differing only
#: in them share one compilation (a sweep over tolerances or penalties compiles once).
#: The other fields shape the programs and stay static. Of the ones here, a value of 0
#: also switches a part of the loop off (``_SWITCHES``): the static copy keeps 0 or 1.
_TRACED_OPTIONS = ("max_iter", "max_inner", "tol_feasibility", "tol_optimality", "inner_tol_ratio",
                   "pbm_inner_tol_ratio", "penalty_init", "penalty_growth", "penalty_max", "feasibility_ratio",
                   "damping_init", "verify_tol", "detect_infeasible", "restart_iter", "restart_penalty_max",
                   "kink_margin", "kink_after", "stall_window", "stall_ratio", "stall_min_viol", "stall_after",
                   "pbm_fallback_iter", "detect_min_viol", "ip_dual_tol", "ip_compl_tol", "ip_project_tol",
                   "ip_damping")
_SWITCHES = ("inner_tol_ratio", "pbm_inner_tol_ratio", "kink_margin", "pbm_fallback_iter")


class _SplitOptions(eqx.Module):
    """A :class:`SolverOptions` crossing a jit boundary: ``static`` (the fields of
    ``_TRACED_OPTIONS`` at their defaults, the switches at 0 or 1) and ``values`` (those
    fields' own values, 0-d arrays)."""

    static: SolverOptions = eqx.field(static=True)
    values: dict


class _TracedOptions:
    """The options inside a compiled program: the fields of ``_TRACED_OPTIONS`` read from
    the traced ``values``, the others from the static copy (:func:`_static` gives it)."""

    def __init__(self, split: _SplitOptions):
        self._static, self._values = split.static, split.values

    def __getattr__(self, name):
        values = self.__dict__["_values"]
        return values[name] if name in values else getattr(self.__dict__["_static"], name)


def _static(opts):
    """The options' static copy (a :class:`SolverOptions`): where the program's structure
    is decided (which parts of the loop exist), never for a traced field's value."""
    return opts._static if isinstance(opts, _TracedOptions) else opts


def _split_options(opts: SolverOptions) -> _SplitOptions:
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
def _split_cached(opts: SolverOptions, _width) -> _SplitOptions:
    defaults = SolverOptions.__dataclass_fields__
    static, values = {}, {}
    for name in _TRACED_OPTIONS:
        value = getattr(opts, name)
        static[name] = type(value)(value != 0) if name in _SWITCHES else defaults[name].default
        kind = (np.bool_ if isinstance(value, (bool, np.bool_))
                else np.int64 if isinstance(value, (int, np.integer)) else np.float64)
        values[name] = np.asarray(value, dtype=jax.dtypes.canonicalize_dtype(kind))
    return _SplitOptions(static=dataclasses.replace(opts, **static), values=values)


def _options_jit(xla_options: dict | None = None):
    """Like the solver's jit decorator (:func:`jtraj._compile.solver_jit`), but every
    :class:`SolverOptions` argument crosses the boundary split by :func:`_split_options`
    and is read inside as :class:`_TracedOptions`. On a CPU the traced program is kept
    across processes where the compilation cache is on (:mod:`jtraj._tracecache`).
    ``xla_options``: the XLA CPU options (default ``SOLVER_XLA_OPTIONS``)."""
    xla_options = SOLVER_XLA_OPTIONS if xla_options is None else xla_options

    def decorate(fn):
        def unsplit(*args):
            return fn(*(_TracedOptions(a) if isinstance(a, _SplitOptions) else a for a in args))

        inner = (_jit if xla_options is SOLVER_XLA_OPTIONS else cpu_jit(xla_options))(functools.wraps(fn)(unsplit))

        @functools.lru_cache(maxsize=1)
        def kept():
            # the solver's programs kept across processes (jtraj._tracecache), on a CPU
            return _tracecache.cached(fn.__qualname__, unsplit, f"{fn.__module__}.{fn.__qualname__}",
                                      supported_options(xla_options), fallback=inner, lean=True)

        @functools.wraps(fn)
        def call(*args):
            args = tuple(_split_options(a) if isinstance(a, SolverOptions) else a for a in args)
            if jax.default_backend() == "cpu":
                return kept()(*args)
            return inner(*args)

        return call

    return decorate


# ----------------------------------------------------------------------------------------
# the NLP in AL form


class Multipliers(NamedTuple):
    eq: dict
    ineq: dict
    glob: Array


class _NLP(eqx.Module):
    """The transcribed problem with everything the solver needs, pure functions of z."""

    problem: Problem
    tr: Transcription = eqx.field(static=True)
    layout: Layout
    sd: StageData
    #: the reference path of the tests: stage Hessians by one forward-over-reverse pass
    #: and the decoupled Hessian in z assembled with jacfwd, like the other transcriptions
    generic_hessian: bool = eqx.field(static=True, default=False)
    #: Newton directions by the stage-wise Riccati recursion (decoupled only, see
    #: :mod:`jtraj.lq`) instead of dense Cholesky factorisations of the Hessian in z
    stagewise: bool = eqx.field(static=True, default=False)
    #: the inequalities' AL term: "phr" or "pbm" (see ``SolverOptions.inequality_penalty``)
    ineq_penalty: str = eqx.field(static=True, default=SolverOptions.inequality_penalty)
    pbm_init: float = eqx.field(static=True, default=SolverOptions.pbm_init)
    pbm_ratio: float = eqx.field(static=True, default=SolverOptions.pbm_ratio)

    #: with ``ineq_penalty == "pbm"``: whether the PBM term is on (the first run) or PHR
    #: (a restart, see :func:`_with_phase`); a traced flag, so one compiled loop serves both
    pbm_on: Array | bool = True

    @property
    def pbm_active(self):
        """Whether the PBM term is in use now (a traced bool; False for a PHR problem)."""
        return jnp.asarray(self.pbm_on) & (self.ineq_penalty == "pbm")

    def ineq_term(self, g, rho, mu):
        if self.ineq_penalty == "lagrangian":  # the interior-point method's (jtraj.ipm)
            return jnp.sum(rho * g)
        if self.ineq_penalty == "pbm":
            return jnp.where(self.pbm_on, _pbm(g, rho, mu), _phr(g, rho, mu))
        return _phr(g, rho, mu)

    def ineq_update(self, g, rho, mu):
        """The first-order multiplier update of an inequality term (the multiplier the
        term implies at g)."""
        phr = jnp.clip(rho + mu * g, 0.0, 1e10)
        if self.ineq_penalty == "pbm":
            slope = jnp.clip(_pbm_slope(mu * g), 1.0 / self.pbm_ratio, self.pbm_ratio)
            return jnp.where(self.pbm_on, jnp.clip(rho * slope, _PBM_FLOOR, 1e10), phr)
        return phr

    def W(self, z):
        return self.tr.stage_vectors(self.problem, self.layout, z)

    def stage_al(self, w, sdk, mult_k, mu, kink=None):
        return self._stage_al_parts(w, sdk, mult_k, mu, kink)[0]

    def _stage_al_parts(self, w, sdk, mult_k, mu, kink=None, tau=None):
        """(AL value, equalities, inequalities, cost terms) of one sample. ``tau``: the
        sample's efforts as an input of their own (transcriptions whose control slot is
        the acceleration, see :meth:`_stage_derivatives_split`) instead of the dynamics."""
        # the dynamics once per sample, shared by the cost and the constraints
        if tau is None:
            a_tau = self.tr.accel_and_tau(self.problem, *self.tr.split_stage(self.problem, w)[:3])
        else:
            a_tau = (self.tr.split_stage(self.problem, w)[2], tau)
        eq, ineq = self.tr.stage_constraints(self.problem, w, sdk, a_tau)
        terms = self.tr.stage_cost_terms(self.problem, w, sdk, a_tau)
        val = sum(terms.values())
        for key, c in eq.items():
            val = val + jnp.sum(mult_k.eq[key] * c) + 0.5 * mu * jnp.sum(c**2)
        for key, g in ineq.items():
            val = val + self.ineq_term(g, mult_k.ineq[key], mu)
            if kink is not None:
                val = val + _kink_curvature(g, mult_k.ineq[key], mu, kink)
        return val, eq, ineq, terms

    def al_and_parts(self, z, mult, mu):
        """(AL value, ((equalities, inequalities, global inequalities), cost)) at z, from
        one pass through the dynamics (the parts are what :meth:`constraints` and
        :meth:`cost_terms` compute apart)."""
        val, eq, ineq, terms = jax.vmap(self._stage_al_parts, in_axes=(0, 0, _stage_axes(mult), None))(
            self.W(z), self.sd, _stage_mult(mult), mu)
        cost = sum(jnp.sum(v) for v in terms.values())
        glob = self.tr.global_inequalities(self.problem, self.layout, z)
        return jnp.sum(val) + self.global_al(z, mult, mu), ((eq, ineq, glob), cost)

    def al_grad_and_parts(self, z, mult, mu):
        """(gradient of the AL in z, parts of :meth:`al_and_parts`): the loop's test after
        each Newton step."""
        return jax.grad(self.al_and_parts, has_aux=True)(z, mult, mu)

    def global_al(self, z, mult, mu):
        # (the jerk rows, Problem(jerk=True), are global rows of z; the Riccati paths,
        # which take the global rows as functions of T alone, are not used for them)
        return self.ineq_term(self.tr.global_inequalities(self.problem, self.layout, z), mult.glob, mu)

    def al_value(self, z, mult, mu):
        return self.al_and_parts(z, mult, mu)[0]

    @property
    def split_derivatives(self) -> bool:
        """Whether :meth:`stage_derivatives` goes through the efforts
        (:meth:`_stage_derivatives_split`)."""
        return self.tr.controls_are_accelerations and not self.generic_hessian

    def stage_derivatives(self, W, mult, mu, kink=None, efforts=False):
        """Per-stage values, gradients and Hessians of the AL terms in w_k: (val (N+1,),
        c (N+1, nw), Hk (N+1, nw, nw)). ``kink`` (None, or a traced margin): Hk includes
        :func:`_kink_curvature` with that margin. Where the control slot is the
        acceleration (decoupled, spline) by :meth:`_stage_derivatives_split`, elsewhere
        (and with ``generic_hessian``) by one forward-over-reverse pass per stage.
        ``efforts`` (split only): also the efforts tau (N+1, m) and their Jacobians in
        w_k (N+1, m, nw), which the chain rule computed on the way."""
        if efforts and not self.split_derivatives:
            raise ValueError("stage_derivatives(efforts=True) needs the split derivatives")
        per_stage = (functools.partial(self._stage_derivatives_split, efforts=efforts) if self.split_derivatives
                     else self._stage_derivatives_plain)
        return jax.vmap(per_stage, in_axes=(0, 0, _stage_axes(mult), None, None))(
            W, self.sd, _stage_mult(mult), mu, kink)

    def _stage_derivatives_plain(self, w, sdk, mk, mu, kink):
        def value_grad(w_):
            v, gw = jax.value_and_grad(self.stage_al)(w_, sdk, mk, mu, kink)
            return gw, (v, gw)

        H, (val, g) = jax.jacfwd(value_grad, has_aux=True)(w)
        return val, g, H

    def _stage_derivatives_split(self, w, sdk, mk, mu, kink, efforts=False):
        """(value, gradient, Hessian) of one sample's AL by the chain rule through its
        efforts tau = ID(q, qd, a), exact: with phi(w, tau) the AL with tau as an input,
        lam = d phi / d tau and J = d tau / dw,

            H = phi_ww + phi_wt J + J^T phi_tw + J^T phi_tt J + sum_i lam_i d2 tau_i / dw2.

        phi (boxes, penalties, cost) is cheap to differentiate twice; the dear part, the
        last term, is forward-over-reverse on lam . tau along q and qd only: tau is affine
        in the acceleration for every rigid-body model (M(q) a + b(q, qd), see
        :class:`jtraj.robots.Robot`), so its acceleration block is zero and its cross
        block is the transpose of rows already computed (serial3, 8 lanes: the stage
        derivatives 83 -> 66 us per problem and iteration against one pass over all of w)."""
        n, nw = self.problem.robot.n, w.shape[0]
        nx, na = 2 * n, nw - 2 * n - 1  # state (q, qd), acceleration slot
        x, a = w[:nx], w[nx:nx + na]

        def tau_of(s, acc):
            return self.tr.accel_and_tau(self.problem, s[:n], s[n:], acc)[1]

        tau = tau_of(x, a)
        Hy, val, gy = self._phi_hessian(w, tau, sdk, mk, mu, kink)
        lam = gy[nw:]

        def weighted(s):  # (gradient of lam . tau in (q, qd, a), tau) at state s
            t, vjp = jax.vjp(tau_of, s, a)
            gs, ga = vjp(lam)
            return jnp.concatenate([gs, ga]), t

        R, Js = jax.jacfwd(weighted)(x)  # (nx + na, nx), (m, nx)
        Ja = jax.jacfwd(lambda acc: tau_of(x, acc))(a)  # (m, na)
        J = jnp.zeros((tau.shape[0], nw), w.dtype).at[:, :nx].set(Js).at[:, nx:nx + na].set(Ja)
        Hs = jnp.zeros((nw, nw), w.dtype).at[:nx + na, :nx].set(R).at[:nx, nx:nx + na].set(R[nx:].T)
        A = Hy[:nw, nw:] @ J
        H = Hy[:nw, :nw] + A + A.T + J.T @ Hy[nw:, nw:] @ J + Hs
        if efforts:
            return val, gy[:nw] + J.T @ lam, H, tau, J
        return val, gy[:nw] + J.T @ lam, H

    def _phi_hessian(self, w, tau, sdk, mk, mu, kink):
        """(Hessian (nw + m, nw + m), value, gradient) of phi(w, tau), one sample's AL with
        its efforts as an input (see :meth:`_stage_derivatives_split`), by forward mode over
        the gradient one block of (q, qd, acceleration slot, h, tau) at a time. Each block's
        tangents flow only through the operations that depend on that block (JAX's
        symbolic zeros): the torque box and the energy see tau's, the velocity box qd's,
        nothing in the decoupled AL sees the acceleration's. The same values as one jacfwd
        over the whole of (w, tau) (on 2 x 256 benchmark pairs the same iterations and
        costs to the last bit) for under half its instructions: serial3, N = 20, 8 lanes,
        per problem and Newton iteration (``benchmarks/iteration_cost.py --instructions``),
        the stage derivatives 766 k -> 626 k instructions, the whole iteration 2.297 M ->
        2.096 M (-8.7 %). Splitting the inverse dynamics' forward-over-reverse pass into
        q's and qd's columns the same way cost more (2.135 M: each pass repeats the primal
        and its vjp)."""
        n, nw = self.problem.robot.n, w.shape[0]
        blocks = (w[:n], w[n:2 * n], w[2 * n:nw - 1], w[nw - 1], tau)
        argnums = tuple(range(len(blocks)))

        def phi(q, qd, a, h, t):
            return self._stage_al_parts(jnp.concatenate([q, qd, a, h[None]]), sdk, mk, mu, kink, t)[0]

        def flat(g):  # the blocks' gradients as one vector in (w, tau)'s layout
            return jnp.concatenate([g[0], g[1], g[2], g[3][None], g[4]])

        def flat_grad(*b):
            return flat(jax.grad(phi, argnums=argnums)(*b))

        val, g = jax.value_and_grad(phi, argnums=argnums)(*blocks)
        gy = flat(g)
        cols = [jax.jacfwd(flat_grad, argnums=i)(*blocks) for i in argnums]
        cols[3] = cols[3][:, None]  # the period is a scalar
        return jnp.concatenate(cols, axis=1), val, gy

    def time_al(self, T, mult, mu):
        """The global AL term as a function of the total time T (see global_al)."""
        return self.ineq_term(self.tr.time_inequalities(self.problem, T), mult.glob, mu)

    def al_derivatives(self, z, mult, mu, kink=None):
        """Value, gradient and Hessian of the AL in z, from per-stage pieces (exact; with a
        ``kink`` margin plus the curvature of the inequalities just short of their PHR
        kink, see :func:`_kink_curvature`)."""
        W, W_vjp = jax.vjp(self.W, z)
        val_k, c, Hk = self.stage_derivatives(W, mult, mu, kink)
        # the gradient is reverse-mode autodiff through the recursion (the co-states)
        g = W_vjp(c)[0]
        if self.tr.name == "decoupled" and not self.generic_hessian:
            H = decoupled_hessian(self.layout, W, c, Hk)
        else:
            J = jax.jacfwd(self.W)(z)  # (N+1, nw, nz)
            H = jnp.einsum("kai,kaj->ij", J, jnp.einsum("kab,kbj->kaj", Hk, J))
            # co-state (second-order) term of the recursion: d2/dz2 <c, W(z)>, c fixed
            # (zero where W is linear in z: the collocation's states are unknowns)
            if not self.tr.linear_stage_map:
                c_fixed = jax.lax.stop_gradient(c)
                grad_cw = jax.grad(lambda zz: jnp.sum(c_fixed * self.W(zz)))
                if self.tr.linear_in_controls:
                    # W is linear in the controls: the control-control block vanishes and
                    # only the columns of the N periods are differentiated (N, not nz, passes)
                    nu = self.layout.N * self.layout.m_u
                    cols = jax.jacfwd(lambda zh: grad_cw(jnp.concatenate([z[:nu], zh])))(z[nu:])  # (nz, N)
                    H = H.at[:, nu:].add(cols).at[nu:, :nu].add(cols[:nu].T)
                else:
                    H = H + jax.jacfwd(grad_cw)(z)
        gval, ggrad, ghess = (self.global_al(z, mult, mu), jax.grad(self.global_al)(z, mult, mu),
                              jax.hessian(self.global_al)(z, mult, mu))
        return jnp.sum(val_k) + gval, g + ggrad, H + ghess

    def stage_newton_model(self, z, mult, mu, kink=None):
        """(value, stage model, pieces for :meth:`hessian_bounds`) of the AL for the
        stage-wise Newton solve (decoupled transcription; the Hessian in z is never formed)."""
        W = self.W(z)
        val_k, c, Hk = self.stage_derivatives(W, mult, mu, kink)
        T = jnp.sum(W[:-1, -1])
        d1 = jax.grad(self.time_al)
        dphi, d2phi = d1(T, mult, mu), jax.grad(d1)(T, mult, mu)
        model = lq.stage_model(W, c, Hk, self.layout.u_scale, self.layout.h_scale, (dphi, d2phi))
        return jnp.sum(val_k) + self.time_al(T, mult, mu), model, (W, c, Hk, d2phi)

    def hessian_bounds(self, pieces):
        """diag(H) and a function ``free -> bounds on the free row sums of |H|`` in z (see
        :func:`jtraj.transcription.decoupled_hessian_bounds`), the term of T included."""
        W, c, Hk, d2phi = pieces
        hdiag, stage_rows = decoupled_hessian_bounds(self.layout, W, c, Hk)
        # the term of T: d2phi hs^2 on every pair of periods
        hs2 = self.layout.h_scale**2
        is_h = jnp.arange(hdiag.shape[0]) >= self.layout.N * self.layout.m_u

        def rows(free):
            return stage_rows(free) + jnp.where(is_h, jnp.abs(d2phi) * hs2 * jnp.sum(free & is_h), 0.0)

        return hdiag + jnp.where(is_h, d2phi * hs2, 0.0), rows

    def constraints(self, z):
        W = self.W(z)
        eq, ineq = jax.vmap(lambda w, s: self.tr.stage_constraints(self.problem, w, s))(W, self.sd)
        return eq, ineq, self.tr.global_inequalities(self.problem, self.layout, z)

    def cost_terms(self, z):
        W = self.W(z)
        terms = jax.vmap(lambda w, s: self.tr.stage_cost_terms(self.problem, w, s))(W, self.sd)
        return {k: jnp.sum(v) for k, v in terms.items()}


def _phr(g, rho, mu):
    """Rockafellar/PHR term for g <= 0 with multiplier rho >= 0 and penalty mu."""
    return jnp.sum(jnp.maximum(0.0, rho + mu * g) ** 2 - rho**2) / (2 * mu)


#: the smallest PBM multiplier: a multiplier that decays to 0 would leave its constraint
#: unpenalised (the term is rho / mu phi(mu g))
_PBM_FLOOR = 1e-8


def _pbm_phi(t):
    """Ben-Tal and Zibulevsky's log-quadratic penalty-barrier function: -log(1 - t) for
    t <= 1/2, continued by the quadratic that matches its value and first two
    derivatives there; phi(0) = 0, phi'(0) = 1, convex, twice differentiable everywhere."""
    tl = jnp.minimum(t, 0.5)
    return jnp.where(t <= 0.5, -log1p(-tl), 2.0 * (t - 0.5) ** 2 + 2.0 * (t - 0.5) + np.log(2.0))


def _pbm_slope(t):
    tl = jnp.minimum(t, 0.5)
    return jnp.where(t <= 0.5, 1.0 / (1.0 - tl), 4.0 * (t - 0.5) + 2.0)


def _pbm(g, rho, mu):
    """Penalty-barrier multiplier term for g <= 0 (multiplier rho > 0, penalty mu):
    ``sum rho / mu phi(mu g)``, twice differentiable (PHR's is once)."""
    return jnp.sum(rho * _pbm_phi(mu * g)) / mu


def _kink_curvature(g, rho, mu, margin):
    """A term of value and gradient zero whose Hessian is the penalty's curvature
    ``mu grad g grad g^T`` on the inequalities just short of their PHR kink
    (``-mu margin < rho + mu g <= 0``): added to the Newton model only (see
    ``SolverOptions.kink_margin``)."""
    s = jax.lax.stop_gradient(rho + mu * g)
    near = (s > -mu * margin) & (s <= 0.0)
    dg = g - jax.lax.stop_gradient(g)
    return 0.5 * mu * jnp.sum(jnp.where(near, dg**2, 0.0))


def _stage_mult(mult: Multipliers):
    return Multipliers(eq=mult.eq, ineq=mult.ineq, glob=jnp.zeros(()))


def _stage_axes(mult: Multipliers):
    return Multipliers(eq=jax.tree.map(lambda _: 0, mult.eq), ineq=jax.tree.map(lambda _: 0, mult.ineq), glob=None)


def _violation(eq, ineq, glob, mult=None, mu=None):
    """Max normalised violation; with multipliers, the complementarity-aware measure
    max(|c|, |min(-g, rho/mu)|) used to steer the penalty."""
    parts = [jnp.max(jnp.abs(c)) for c in jax.tree.leaves(eq)]
    if mult is None:
        parts += [jnp.max(jnp.maximum(g, 0.0)) for g in jax.tree.leaves(ineq)]
        parts.append(jnp.max(jnp.maximum(glob, 0.0)))
    else:
        parts += [jnp.max(jnp.abs(jnp.minimum(-g, r / mu)))
                  for g, r in zip(jax.tree.leaves(ineq), jax.tree.leaves(mult.ineq))]
        parts.append(jnp.max(jnp.abs(jnp.minimum(-glob, mult.glob / mu))))
    return jnp.max(jnp.stack(parts))


# ----------------------------------------------------------------------------------------
# the loop


class _State(NamedTuple):
    z: Array
    mult: Multipliers
    mu: Array
    damping: Array
    omega: Array  # current inner tolerance
    eta: Array  # current feasibility tolerance (thesis schedule)
    viol_prev: Array
    inner: Array
    outer: Array
    it: Array
    done: Array
    failed: Array
    stalled: Array  # stopped as likely infeasible
    stationarity: Array
    history: Array  # (max_outer, 3): cost, violation, penalty
    it_max: Array  # iteration budget of this run (max_iter; raised by a restart)
    mu_max: Array  # penalty cap of this run (penalty_max; restart_penalty_max after a restart)
    restarts: Array  # restarts taken so far (see _restart)
    z_start: Array  # the first run's starting point (a PBM run's PHR fallback starts there)
    val_ref: Array  # the AL's value at the last stall checkpoint of this subproblem


# NumPy, not jnp: a jnp constant made at import takes the dtype of that moment (float32
# when x64 is enabled after ``import jtraj``), which changed the iterates between processes
# that enabled x64 before and after the import (Ray workers against the CLI)
# 4 shifts x 4 step lengths. The trial points are about a third of a Newton iteration's
# cost; against 4 shifts x 6 step lengths (down to 0.01) this is about 1.1x faster on the
# benchmark family with the same pairs converged, and 3 shifts cost 13 % more iterations.
_LADDER = np.linspace(0.0, 1.0, 4)  # exponents of the geometric shift ladder
_STEPS = np.array([1.0, 0.5, 0.25, 0.1])
#: the trial points (index into the ladder, step length), shift-major: every step on every shift but
#: the top (Gershgorin) one, which takes only the full step: the top shift rarely wins
#: with a shorter step (0.5 % of the iterations), so 13 trials cost the same iterations
#: as 16 and run a few per cent faster.
_TRIAL_SHIFT = np.concatenate([np.repeat(np.arange(len(_LADDER) - 1), len(_STEPS)), [len(_LADDER) - 1]])
_TRIAL_STEP = np.concatenate([np.tile(_STEPS, len(_LADDER) - 1), _STEPS[:1]])


def _held(z, g, lo, hi, hdiag, eps):
    """The variables the projected Newton step holds at their bounds: Bertsekas'
    eps-active set, narrowed by the diagonal curvature. A variable within ``eps`` of a
    bound is held only if the gradient pushes it there harder than its curvature holds it
    (the diagonal Newton step ``-g / hdiag`` would reach the bound; always where
    ``hdiag <= 0``). Holding a stiff variable that was merely near a bound froze it while
    the free variables, coupled to it, could not become stationary: the projected
    gradient then cycled about eps until the iteration limit (benchmark pairs stopped at a
    KKT error of ~1e-3; 2 of the 3 such pairs of bench_solver converged with this rule)."""
    curv = jnp.maximum(hdiag, 0.0)
    return (((z <= lo + eps) & (g > 0) & (g >= curv * (z - lo)))
            | ((z >= hi - eps) & (g < 0) & (-g >= curv * (hi - z))))


def _newton_step(nlp: _NLP, z, mult, mu, damping, kink=None):
    # the barrier materialises the derivatives once, so that XLA cannot fuse their
    # assembly into each of the shifted factorisations below (a guard: on serial3 the
    # timings with and without it were within the machine's noise)
    if nlp.stagewise:
        val, model, pieces = jax.lax.optimization_barrier(nlp.stage_newton_model(z, mult, mu, kink))
        g = model.g
    else:
        val, g, H = jax.lax.optimization_barrier(nlp.al_derivatives(z, mult, mu, kink))
    lo, hi = nlp.layout.z_lo, nlp.layout.z_hi
    pg = z - jnp.clip(z - g, lo, hi)  # projected-gradient residual
    eps = jnp.minimum(1e-3, jnp.max(jnp.abs(pg)))
    if nlp.stagewise:
        hdiag, rows = nlp.hessian_bounds(pieces)
    else:
        hdiag = jnp.diag(H)
    free = ~_held(z, g, lo, hi, hdiag, eps)
    # Globalisation without serialising control flow (a parallel trust region): the
    # Hessian is factorised with a ladder of Levenberg shifts at once (the last, from
    # Gershgorin's theorem, is always positive definite); every positive-definite shift
    # gives a direction, each is tried at a few step lengths in one vectorised
    # evaluation (Armijo's test); see below for which wins. The next damping is the
    # shift that won, relaxed after a full step.
    if nlp.stagewise:
        # rows bounds the free row sums of |H|: the same Gershgorin test, on a bound
        excess = jnp.where(free, rows(free) - jnp.abs(hdiag) - hdiag, -1.0)
    else:
        Hf = jnp.where(free[:, None] & free[None, :], H, 0.0)
        Hf = Hf + jnp.diag(jnp.where(free, 0.0, 1.0))
        excess = jnp.sum(jnp.abs(Hf), axis=1) - jnp.abs(jnp.diag(Hf)) - jnp.diag(Hf)
    gersh = jnp.maximum(0.0, jnp.max(excess)) + damping
    # geometric ladder from damping / 8 to the Gershgorin bound (always PD)
    low = damping / 8.0
    ladder = jnp.asarray(_LADDER, z.dtype)
    trial_shift, steps = _TRIAL_SHIFT, jnp.asarray(_TRIAL_STEP, z.dtype)
    shifts = low * (jnp.maximum(gersh, 8.0 * low) / low) ** ladder
    if nlp.stagewise:
        d_free, good = lq.newton_directions(model, free, shifts)
    else:
        gf = jnp.where(free, g, 0.0)
        eye = jnp.eye(Hf.shape[0], dtype=Hf.dtype)
        shift_free = jnp.where(free, 1.0, 0.0)
        Ls = jax.vmap(lambda sh: jnp.linalg.cholesky(Hf + sh * jnp.diag(shift_free)))(shifts)
        good = jax.vmap(lambda L: jnp.all(jnp.isfinite(L)))(Ls)
        Ls = jnp.where(good[:, None, None], Ls, eye)
        d_free = -jax.vmap(lambda L: jax.scipy.linalg.cho_solve((L, True), gf))(Ls)
    # variables held at (or within eps of) a bound take a diagonally scaled gradient
    # step under the same shift, so that the ladder also shortens their step (an
    # unscaled -g there overshoots a stiff AL and no step length passes)
    d_held = -g[None, :] / (jnp.abs(hdiag)[None, :] + shifts[:, None])
    d = jnp.where(free[None, :], d_free, d_held)  # (S, nz)
    d = jnp.where(jnp.all(jnp.isfinite(d), axis=1, keepdims=True), d, -g[None, :])
    candidates = jnp.clip(z[None, :] + steps[:, None] * d[trial_shift], lo, hi)
    values = jax.vmap(nlp.al_value, in_axes=(0, None, None))(candidates, mult, mu)
    decrease = jnp.einsum("i,ki->k", g, candidates - z[None, :])
    ok = (values <= val + 1e-4 * decrease) & jnp.isfinite(values) & good[trial_shift]
    # far from a stationary point the lowest value found wins (fewest iterations on the
    # benchmark); close to one (projected gradient < 1e-3) the least-damped direction
    # that takes a long step (>= 1/4) does, which keeps Newton's fast local convergence
    # (the lowest value is then decided by rounding)
    long_ok = ok & (steps >= 0.25) & (jnp.max(jnp.abs(pg)) < 1e-3)
    best = jnp.where(jnp.any(long_ok), jnp.argmax(long_ok), jnp.argmin(jnp.where(ok, values, jnp.inf)))
    any_ok = jnp.any(ok)
    z_new = jnp.where(any_ok, candidates[best], z)
    step = steps[best]
    used = shifts[jnp.asarray(trial_shift)[best]]
    damping = jnp.where(any_ok, jnp.where(step == 1.0, used * 0.5, used * 2.0), shifts[-1])
    damping = jnp.clip(jnp.where(jnp.isfinite(damping), damping, 1e10), 1e-12, 1e10)
    return z_new, damping, jnp.max(jnp.abs(pg)), val, any_ok


def _stationarity(nlp: _NLP, z, g):
    """The largest entry of the projected gradient at z (``g``: the AL's gradient there)."""
    return jnp.max(jnp.abs(z - jnp.clip(z - g, nlp.layout.z_lo, nlp.layout.z_hi)))


def _residual(nlp: _NLP, z, act_tol):
    """Stacked equalities and nearly-active inequalities (g > -act_tol); inactive rows are
    zero. (The polish's holding phase takes the nearly-active rows' max(g, 0): it removes
    violations while keeping satisfied nearly-active rows where they are to first order,
    their Jacobian rows kept, instead of pulling them onto their boundary.)"""
    eq, ineq, glob = nlp.constraints(z)
    rows = [c.ravel() for c in jax.tree.leaves(eq)]
    for g in jax.tree.leaves(ineq) + [glob]:
        rows.append(jnp.where(g.ravel() > -act_tol, g.ravel(), 0.0))
    return jnp.concatenate(rows)


def _ridge_solve(Jf, b, eps, gram=None):
    """``(Jf^T Jf + eps I)^-1 b`` by a Cholesky factorisation (nz x nz): the normal
    equations of the polish's minimum-norm corrections and of the least-squares
    multipliers, each with its own ridge ``eps``. ``gram``: ``Jf^T Jf`` if known."""
    A = (Jf.T @ Jf if gram is None else gram) + eps * jnp.eye(Jf.shape[1], dtype=Jf.dtype)
    return jax.scipy.linalg.cho_solve((jnp.linalg.cholesky(A), True), b)


#: the violation below which the feasibility polish stops (the verification asks 1e-6)
_POLISH_DONE = 1e-12


def _polish(nlp: _NLP, z, iterations: int = 4, chord: bool = True, release_above=None, skip=None):
    """Feasibility polish: a few Gauss-Newton projections of z onto the manifold of the
    equalities and nearly-active inequalities (minimum-norm corrections, simple bounds
    held). The AL leaves O((lambda* - lambda)/mu) violations; this removes them without
    changing the optimum to first order. A step is kept only if the violation shrinks;
    the projections stop after ``iterations`` or at the first that does not shrink it.

    With ``chord`` (the finish) the constraints' Jacobian is computed once, at z, and the
    projections also stop once the violation is below ``_POLISH_DONE``: the corrections
    are as small as the AL's violations, so the chord converges about as fast as
    Gauss-Newton at about half the cost. Without it (the restart's starting point, see
    :func:`_restart`) the Jacobian is recomputed at every projection, because a restart
    runs on from that point for many iterations and is sensitive to it.

    A satisfied nearly-active inequality is held where it is to first order. With
    ``release_above``, a point that this holding phase leaves violated by more than
    ``release_above`` goes on to a releasing phase over all inequality rows: a satisfied
    inequality is left free unless the correction would take it across its boundary.
    Holding fails where a row is nearly parallel to a violated one
    (``Problem(efforts="intervals")``), whose correction it would cancel (see
    :func:`_final_polish`). Both phases are one bounded loop with one body, which halves
    the finish's and the restart's compilation; the normal equations' ``J^T J`` is formed
    once per Jacobian, the fixed variables' rows and columns zeroed in it."""
    lo, hi = nlp.layout.z_lo, nlp.layout.z_hi
    window = 1e-3  # the holding phase's act_tol: the rows nearly active within it
    n_eq = sum(x.size for x in jax.tree.leaves(jax.eval_shape(lambda zz: nlp.constraints(zz)[0], z)))
    n_rows = jax.eval_shape(lambda zz: _residual(nlp, zz, window), z).shape[0]
    is_ineq = jnp.arange(n_rows) >= n_eq
    jac = jax.jacfwd(_residual, argnums=1)
    done = _POLISH_DONE if chord else 0.0
    releasing = release_above is not None

    def viol(zz):
        return _violation(*nlp.constraints(zz))

    def correction(J, r, fixed, gram=None):
        # normal equations in z (nz x nz, smaller than the row space); the tiny ridge
        # selects the minimum-norm correction when J is rank deficient. ``gram``: J^T J,
        # whose rows and columns of the fixed variables are Jf^T Jf's zeros
        Jf = jnp.where(fixed[None, :], 0.0, J)
        if gram is not None:
            gram = jnp.where(fixed[:, None] | fixed[None, :], 0.0, gram)
        return _ridge_solve(Jf, Jf.T @ r, 1e-10 * (1.0 + jnp.max(jnp.sum(Jf**2, axis=0))), gram)

    def body(carry):
        z, v, k, _, rel, v_start = carry
        act_tol = jnp.where(rel, jnp.inf, window)
        if chord:  # the Jacobian at the entry point, of the phase's rows
            J = jnp.where(rel, J_all, J_near) if releasing else J_near
            # J^T J of the holding phase's rows (a releasing lane's first correction
            # below is replaced by its own rounds' in any case)
            gram = G_near
        else:
            J = jac(nlp, z, act_tol)
            gram = J.T @ J
        fixed = (z <= lo + 1e-12) | (z >= hi - 1e-12)
        raw = _residual(nlp, z, act_tol)
        Jr, r = J, jnp.where(is_ineq, jnp.maximum(raw, 0.0), raw)  # holding: violated part only
        dz = correction(Jr, r, fixed, gram)
        if releasing:
            # releasing: equalities and violated inequalities; satisfied rows the
            # correction would take across their boundary join them (four rounds: each
            # correction can cross others)
            def select(c):
                rows, _, i = c
                dz = correction(jnp.where(rows[:, None], J, 0.0), jnp.where(rows, raw, 0.0), fixed)
                return rows | (is_ineq & (raw - J @ dz > 0)), dz, i + 1

            rows, dz, _ = jax.lax.while_loop(lambda c: rel & (c[2] < 4), select,
                                             (~is_ineq | (raw > 0), dz, jnp.asarray(0)))
            Jr = jnp.where(rel, jnp.where(rows[:, None], J, 0.0), J)
            r = jnp.where(rel, jnp.where(rows, raw, 0.0), r)
            # the selected rows' J^T J, formed (like the rounds) only while some lane releases
            gram, _ = jax.lax.while_loop(lambda c: rel & ~c[1], lambda c: (Jr.T @ Jr, jnp.asarray(True)),
                                         (gram, jnp.asarray(False)))
        # variables the correction would push through a bound are held there and the
        # correction recomputed (clipping it would undo part of it)
        dz = correction(Jr, r, fixed | (z - dz < lo) | (z - dz > hi), gram)
        z_new = jnp.clip(z - dz, lo, hi)
        v_new = viol(z_new)
        better = jnp.isfinite(v_new) & (v_new < v)
        z, v, k = jnp.where(better, z_new, z), jnp.where(better, v_new, v), k + 1
        going = better & (v_new > done)
        if releasing:  # the holding phase over: the releasing one starts where needed
            switch = ~rel & ~(going & (k < iterations)) & (v > release_above) & (v_start <= window)
            rel, k, going = rel | switch, jnp.where(switch, 0, k), going | switch
        return z, v, k, going, rel, v_start

    v0 = viol(z)
    need = v0 > done if skip is None else (v0 > done) & ~skip
    if chord:
        # every row's Jacobian at z; the holding phase's rows are those nearly active there
        # (the rows of jac(nlp, z, window)), the releasing phase's all rows (a chord from z,
        # not from where the releasing phase starts: a point the holding phase moved by
        # the size of the AL's violations). J^T J once per chord, not twice per projection
        # (each a (rows x nz)^T (rows x nz) product: serial3, N = 20, 241 x 80). Inside a
        # loop of at most one pass, so that under vmap it runs only if some lane polishes
        J_all, J_near, G_near = _at_most_once(need, lambda zz: _chord_jacobian(nlp, zz, window, is_ineq), z)
    carry = (z, v0, jnp.asarray(0), need, jnp.asarray(False), v0)
    # a bounded loop (under vmap it runs while some lane still improves)
    z, *_ = jax.lax.while_loop(lambda c: c[3] & (c[2] < iterations), body, carry)
    return z


def _at_most_once(pred, fn, x, fill=0.0):
    """``fn(x)`` where ``pred``, else ``fill`` in its shape: a loop of at most one pass, so
    that under vmap (where ``lax.cond`` evaluates both sides) it runs only if some lane
    needs it. The body's argument is x plus zero times the pass count: an argument that
    does not change from pass to pass lets XLA hoist the whole body out of the loop
    (loop-invariant code motion), and it then ran on every call."""
    out = jax.tree.map(lambda a: jnp.full(a.shape, fill, a.dtype), jax.eval_shape(fn, x))

    def body(c):
        return fn(x + 0.0 * c[1]), c[1] + 1

    return jax.lax.while_loop(lambda c: pred & (c[1] < 1), body, (out, jnp.zeros((), x.dtype)))[0]


def _chord_jacobian(nlp: _NLP, z, window, is_ineq):
    """Every constraint row's Jacobian at z, the holding phase's rows of it (those nearly
    active within ``window``), and their J^T J (see :func:`_polish`)."""
    J_all = jax.jacfwd(_residual, argnums=1)(nlp, z, jnp.inf)
    J_near = jnp.where((_residual(nlp, z, jnp.inf) > -window)[:, None] | ~is_ineq[:, None], J_all, 0.0)
    return J_all, J_near, J_near.T @ J_near


def _final_polish(nlp: _NLP, z, opts: SolverOptions, chord: bool = True, skip=None):
    """:func:`_polish` with its releasing phase for a point the holding one leaves violated
    by more than ``verify_tol``. Where the holding polish succeeds its result is kept
    unchanged. ``chord``: chord or Gauss-Newton projections (see :func:`_polish`).

    Measured: on 96 dataset pairs (seed 5, h_max 0.2 s) with ``Problem(efforts="intervals")``
    the holding polish left 4 certified optima violated by 2e-6 to 1.7e-5: nearly parallel
    effort rows cancelled its corrections; the releasing one brought all 4 below 1e-15
    (costs within 2.5e-5). On benchmark pair 16 of seed 21 (``kink_margin=1e-4,
    kink_after=0``) the loop certified a point 6e-6 off the goal whose Gauss-Newton
    correction crossed a torque bound 1e-3 away from its limit, so no step was kept
    (``VERIFICATION_FAILED``); the releasing polish over all rows removed it (cost +5e-5).
    Only for a point the AL brought within the polish's window: a far-off point (an
    infeasible problem's) is beyond its reach. Under vmap the releasing phase runs only
    while some lane needs it (as a ``lax.cond`` whose predicate differs between lanes it
    ran on every lane, and was then 45 % of a batch's finish, 5.7 of 12.6 ms per problem,
    where hardly any lane needed it)."""
    return _polish(nlp, z, chord=chord, release_above=opts.verify_tol, skip=skip)


def _init_multipliers(nlp: _NLP, z) -> Multipliers:
    eq, ineq, glob = nlp.constraints(z)
    r0 = nlp.pbm_init if nlp.ineq_penalty == "pbm" else 0.0
    return Multipliers(eq=jax.tree.map(jnp.zeros_like, eq), ineq=jax.tree.map(lambda g: jnp.full_like(g, r0), ineq),
                       glob=jnp.full_like(glob, r0))


def _ls_multipliers(nlp: _NLP, z, act_tol: float = 1e-3):
    """Least-squares multipliers at z: minimise ||grad f + J_A^T lambda|| over the
    equalities and nearly-active inequalities (rows of :func:`_residual`), in the free
    variables; inequality multipliers are clipped to >= 0, inactive ones are 0.
    Returns (lambda flat, J, grad f, number of equality rows)."""
    lo, hi = nlp.layout.z_lo, nlp.layout.z_hi
    gf = jax.grad(lambda zz: sum(nlp.cost_terms(zz).values()))(z)
    J = jax.jacfwd(_residual, argnums=1)(nlp, z, act_tol)
    free = ~((z <= lo + 1e-12) | (z >= hi - 1e-12))
    Jf = jnp.where(free[None, :], J, 0.0)
    # the ridge-regularised normal equations (Jf Jf^T + eps I) lam = -Jf gf, solved in
    # the variables' space by the push-through identity (Jf Jf^T + eps I)^-1 Jf =
    # Jf (Jf^T Jf + eps I)^-1: an nz x nz instead of a rows x rows system (serial3,
    # N = 20: 80 against 241; the KKT error at the end of a batch 3.6 -> 0.9 ms per problem)
    eps = 1e-10 * (1.0 + jnp.max(jnp.sum(Jf**2, axis=1)))  # max diag(Jf Jf^T)
    lam = -Jf @ _ridge_solve(Jf, jnp.where(free, gf, 0.0), eps)
    lam = jnp.where(jnp.isfinite(lam), lam, 0.0)
    n_eq = sum(x.size for x in jax.tree.leaves(nlp.constraints(z)[0]))
    lam = jnp.where(jnp.arange(lam.size) < n_eq, lam, jnp.clip(lam, 0.0, 1e10))
    return lam, J, gf, n_eq


def _estimate_multipliers(nlp: _NLP, z, act_tol: float = 1e-3, ls=None) -> Multipliers:
    """:func:`_ls_multipliers` (or ``ls``, its result) in the multipliers' tree
    structure (for warm starts)."""
    lam = (_ls_multipliers(nlp, z, act_tol) if ls is None else ls)[0]
    # the rows of _residual are the leaves of (eq, ineq, glob) in this order
    shapes = Multipliers(*nlp.constraints(z))
    leaves, pos = [], 0
    for x in jax.tree.leaves(shapes):
        leaves.append(lam[pos:pos + x.size].reshape(x.shape))
        pos += x.size
    return jax.tree.unflatten(jax.tree.structure(shapes), leaves)


def _kkt_error(nlp: _NLP, z, act_tol: float = 1e-3, ls=None):
    """First-order optimality error of the original problem at z, independent of the AL
    state: the projected gradient of the Lagrangian with least-squares multipliers
    (signs enforced; ``ls``: :func:`_ls_multipliers` at z if already computed), and
    complementarity max lambda_i * |g_i| over the nearly-active inequalities; in the
    units of ``tol_optimality``."""
    lo, hi = nlp.layout.z_lo, nlp.layout.z_hi
    lam, J, gf, n_eq = _ls_multipliers(nlp, z, act_tol) if ls is None else ls
    r = gf + J.T @ lam
    pg = z - jnp.clip(z - r, lo, hi)
    rows = _residual(nlp, z, act_tol)
    comp = jnp.where(jnp.arange(lam.size) < n_eq, 0.0, lam * jnp.abs(rows))
    return jnp.maximum(jnp.max(jnp.abs(pg)), jnp.max(comp))


def _multiplier_kkt_error(nlp: _NLP, z, mult: Multipliers):
    """The KKT error of :func:`_kkt_error` with given multipliers (inequality ones >= 0)
    instead of least-squares ones: the projected gradient of the Lagrangian and the
    complementarity ``lambda_i |g_i|``. Any such multipliers bound the KKT error from
    above."""
    lo, hi = nlp.layout.z_lo, nlp.layout.z_hi

    def lagrangian(zz):
        eq, ineq, glob = nlp.constraints(zz)
        val = sum(nlp.cost_terms(zz).values()) + jnp.sum(mult.glob * glob)
        for c, l in zip(jax.tree.leaves((eq, ineq)), jax.tree.leaves((mult.eq, mult.ineq))):
            val = val + jnp.sum(l * c)
        return val, (ineq, glob)

    g, (ineq, glob) = jax.grad(lagrangian, has_aux=True)(z)
    pg = jnp.max(jnp.abs(z - jnp.clip(z - g, lo, hi)))
    comp = [jnp.max(r * jnp.abs(c)) for c, r in zip(jax.tree.leaves(ineq) + [glob],
                                                      jax.tree.leaves(mult.ineq) + [mult.glob])]
    return jnp.maximum(pg, jnp.max(jnp.stack(comp)))


def _al_kkt_error(nlp: _NLP, z, mult: Multipliers, mu):
    """The smaller KKT error of two multiplier vectors the AL loop provides at its final
    z: its current multipliers (updated at the end of the last subproblem) and the ones
    the AL implies at z (``rho + mu c`` and ``max(0, rho + mu g)``: those of a run stopped
    inside a subproblem). Least-squares multipliers (:func:`_kkt_error`) fail where
    nearly-active constraints are nearly parallel, as the efforts at an interval's end and
    at the next sample are when the acceleration hardly changes
    (``Problem(efforts="intervals")``): least squares splits the multiplier into large
    ones of both signs, and clipping the negative one leaves a projected gradient of ~1
    at a point the AL certified (34 of 57 such benchmark pairs above ``tol_optimality``)."""
    eq, ineq, glob = nlp.constraints(z)
    implied = Multipliers(eq=jax.tree.map(lambda r, c: r + mu * c, mult.eq, eq),
                          ineq=jax.tree.map(lambda r, g: nlp.ineq_update(g, r, mu), mult.ineq, ineq),
                          glob=nlp.ineq_update(glob, mult.glob, mu))
    # both by one vmapped pass (one copy of the Lagrangian's gradient in the program)
    both = jax.tree.map(lambda a, b: jnp.stack([a, b]), mult, implied)
    return jnp.min(jax.vmap(lambda m: _multiplier_kkt_error(nlp, z, m))(both))


def _with_phase(nlp: _NLP, s: "_State") -> _NLP:
    """``nlp`` with its inequality term for the run ``s`` is in: PBM in the first run,
    PHR after a restart (``SolverOptions.inequality_penalty == "pbm"``; else ``nlp``)."""
    if nlp.ineq_penalty != "pbm":
        return nlp
    return eqx.tree_at(lambda n: n.pbm_on, nlp, s.restarts == 0)


def _run(nlp: _NLP, z0, opts: SolverOptions, warm=False):
    """The AL loop from z0 to the end (see :func:`_init_state` and :func:`_loop`)."""
    return _run_with_restart(nlp, _init_state(nlp, z0, opts, warm), opts)


def _init_state(nlp: _NLP, z0, opts: SolverOptions, warm=False) -> _State:
    """The loop's starting state. With ``warm`` (a traced bool), multipliers start from
    their least-squares estimate at z0 and the penalty at its cap / 1e2 instead of zero
    and ``penalty_init``: a warm start near an optimum then stays there. A warm start
    that already meets both tolerances (the KKT error of the original problem and the
    violation) is finished before the first iteration."""
    cold = _init_multipliers(nlp, z0)

    def estimate(_):
        ls = _ls_multipliers(nlp, z0)
        return _estimate_multipliers(nlp, z0, ls=ls), _kkt_error(nlp, z0, ls=ls)

    warm = jnp.asarray(warm)
    # a real branch (warm is one flag for a whole batch): a cold start skips the estimate
    est, kkt0 = jax.lax.cond(warm, estimate, lambda _: (cold, jnp.asarray(jnp.inf, z0.dtype)), None)
    done0 = warm & (kkt0 <= opts.tol_optimality) & (_violation(*nlp.constraints(z0)) <= opts.tol_feasibility)
    if nlp.ineq_penalty == "pbm":
        est = est._replace(ineq=jax.tree.map(lambda r: jnp.maximum(r, _PBM_FLOOR), est.ineq),
                           glob=jnp.maximum(est.glob, _PBM_FLOOR))
    mult0 = jax.tree.map(lambda a, b: jnp.where(warm, a, b), est, cold)
    mu0 = jnp.where(warm, jnp.maximum(opts.penalty_init, opts.penalty_max * 1e-2), opts.penalty_init).astype(z0.dtype)
    return _State(
        z=z0, mult=mult0, mu=mu0, damping=jnp.asarray(opts.damping_init, dtype=z0.dtype),
        omega=jnp.asarray(1e-2, dtype=z0.dtype), eta=jnp.asarray(1e-2, dtype=z0.dtype),
        viol_prev=jnp.asarray(jnp.inf, dtype=z0.dtype), inner=jnp.asarray(0), outer=jnp.asarray(0),
        it=jnp.asarray(0), done=done0, failed=jnp.asarray(False), stalled=jnp.asarray(False),
        stationarity=jnp.where(done0, kkt0, jnp.inf).astype(z0.dtype),
        history=jnp.full((opts.max_outer, 3), jnp.nan, dtype=z0.dtype),
        it_max=jnp.asarray(_first_run_iter(opts)), mu_max=jnp.asarray(opts.penalty_max, dtype=z0.dtype),
        restarts=jnp.asarray(0), z_start=z0, val_ref=jnp.asarray(jnp.inf, dtype=z0.dtype))


def _finished(s: _State, opts: SolverOptions):
    return s.done | s.stalled | (s.it >= s.it_max) | (s.outer >= opts.max_outer)


def _fallback(opts: SolverOptions) -> bool:
    """Whether an uncertified PBM run falls back to a cold PHR run (``pbm_fallback_iter``)."""
    return _static(opts).inequality_penalty == "pbm" and _static(opts).pbm_fallback_iter > 0


def _first_run_iter(opts: SolverOptions):
    return jnp.minimum(opts.max_iter, opts.pbm_fallback_iter) if _fallback(opts) else opts.max_iter


def _max_restarts(opts: SolverOptions):
    """1 or 2 restarts (see :func:`_restart`), or none with ``restart_iter = 0`` and no PBM
    fallback; a traced count inside a compiled program."""
    return int(_fallback(opts)) + (opts.restart_iter > 0)


def _needs_restart(s: _State, opts: SolverOptions):
    """A run that ended uncertified (iteration or outer limit), not as likely infeasible
    nor failed, with a restart left (one; two for a PBM run, see :func:`_restart`)."""
    return ~s.done & ~s.failed & ~s.stalled & (s.restarts < _max_restarts(opts))


def _restart(nlp: _NLP, s: _State, opts: SolverOptions) -> _State:
    """Restart an uncertified run once (where :func:`_needs_restart`; elsewhere ``s``
    unchanged): from its final point after the feasibility polish, with least-squares
    multipliers there, the penalty at ``restart_penalty_max / 100`` and capped at
    ``restart_penalty_max``, for ``restart_iter`` more iterations.

    Why: on problems whose feasible set is thin (minimum time close to N h_max, the
    torques saturated at most samples) the first-order multiplier updates converge
    slowly, the penalty then grows to its cap, and the Newton subproblems with their PHR
    kinks at mu ~ 1e5-1e6 stall at a feasible point with a KKT error of 1e-3..1e-1. From
    that point, with multipliers estimated there and a moderate penalty, the loop
    converges (benchmark family, seeds 1, 2, 11: all 6 pairs that IPOPT solves and the
    first run left uncertified, about 60 to 590 iterations after the restart, cost within
    0.04 % of IPOPT's). A point the polish
    leaves certified (KKT error and violation within tolerance) is not restarted:
    :func:`_finish` certifies it.

    A PBM run (``SolverOptions.pbm_fallback_iter``) has two restarts: the first is PHR's
    own cold run from the first run's starting point, the second the warm one above."""
    # a warm start at the polished point: least-squares multipliers, fresh schedules, and
    # finished at once where that point is already certified
    fresh = _init_state(nlp, _final_polish(nlp, s.z, opts, chord=False), opts, warm=True)
    need = _needs_restart(s, opts) & ~fresh.done
    dt = s.z.dtype
    new = fresh._replace(mu=jnp.asarray(opts.restart_penalty_max * 1e-2, dt),
                         mu_max=jnp.asarray(opts.restart_penalty_max, dt), it=s.it,
                         it_max=s.it + opts.restart_iter, restarts=s.restarts + 1, z_start=s.z_start)
    if _fallback(opts):
        # the first restart of a PBM run is PHR's own cold run from the first run's start
        # (zero multipliers, PHR's default penalty_init, max_iter iterations); the warm one
        # above follows it if that too ends uncertified
        cold = _init_state(nlp, s.z_start, opts)
        cold = cold._replace(mult=jax.tree.map(jnp.zeros_like, cold.mult),
                             mu=jnp.asarray(SolverOptions.penalty_init, dt),
                             it=s.it, it_max=s.it + opts.max_iter, restarts=s.restarts + 1)
        new = jax.tree.map(lambda a, b: jnp.where(s.restarts == 0, a, b), cold, new)
    return jax.tree.map(lambda a, b: jnp.where(need, a, b), new, s)


def _run_with_restart(nlp: _NLP, state: _State, opts: SolverOptions) -> _State:
    """The loop to its end, then (if needed, see :func:`_restart`) once more, or twice
    for a PBM run. Written as
    a loop over runs so that the Newton loop is compiled once (two copies of it doubled
    the solver's compilation)."""
    if not isinstance(opts, _TracedOptions) and _max_restarts(opts) == 0:
        return _loop(nlp, state, opts)

    def run(carry):
        s, k = carry
        # a real branch for one problem; under vmap both sides run on the first pass
        # (the restart is a no-op where it is not needed)
        s = jax.lax.cond(k > 0, lambda t: _restart(nlp, t, opts), lambda t: t, s)
        return _loop(nlp, s, opts), k + 1

    s, _ = jax.lax.while_loop(lambda c: (c[1] == 0) | _needs_restart(c[0], opts), run, (state, jnp.asarray(0)))
    return s


def _next_inner_tol(opts: SolverOptions, omega, viol, pbm_on=False):
    """The next AL subproblem's stationarity tolerance (see ``SolverOptions.inner_tol_ratio``;
    ``pbm_on``: a traced flag, the PBM phase of a PBM run, which takes ``pbm_inner_tol_ratio``)."""

    def tol(name):
        if getattr(_static(opts), name) > 0:
            return jnp.maximum(jnp.minimum(1e-2, getattr(opts, name) * viol), opts.tol_optimality)
        return jnp.maximum(omega * 0.1, opts.tol_optimality)

    if opts.inequality_penalty == "pbm":
        return jnp.where(pbm_on, tol("pbm_inner_tol_ratio"), tol("inner_tol_ratio"))
    return tol("inner_tol_ratio")


def _loop(nlp: _NLP, state: _State, opts: SolverOptions, limit=None):
    """Iterate from ``state`` until finished or until ``state.it`` reaches ``limit``;
    resumable, so a batch can be run in segments (see :func:`solve_batch`)."""

    nlp = _with_phase(nlp, state)
    pbm_on = nlp.pbm_active

    def cond(s: _State):
        return ~_finished(s, opts) if limit is None else ~_finished(s, opts) & (s.it < limit)

    def body(s: _State):
        # the kink curvature's margin, zero until the subproblem has run kink_after iterations
        kink = (None if _static(opts).kink_margin == 0
                else jnp.where((s.inner >= opts.kink_after) & ~pbm_on, opts.kink_margin, 0.0).astype(s.z.dtype))
        z, damping, pg, val, moved = _newton_step(nlp, s.z, s.mult, s.mu, s.damping, kink)
        failed = ~jnp.all(jnp.isfinite(z))
        inner = s.inner + 1
        g, ((eq, ineq, glob), cost) = nlp.al_grad_and_parts(z, s.mult, s.mu)
        stat = _stationarity(nlp, z, g)
        subproblem_done = (stat <= s.omega) | (inner >= opts.max_inner) | (~moved & (damping >= 1e9))
        # ---- outer update (computed always, applied where subproblem_done) ----
        viol = _violation(eq, ineq, glob, s.mult, s.mu)
        # the stall exit (off with stall_window = 0, a traced value like the others)
        stall_on = opts.stall_window > 0
        window = jnp.maximum(opts.stall_window, 1)
        checkpoint = stall_on & (s.inner % window == 0)
        stalled_sub = (checkpoint & (s.inner >= 2 * window) & (s.it >= opts.stall_after)
                       & (viol > opts.stall_min_viol)
                       & (s.val_ref - val < opts.stall_ratio * s.mu * viol**2))
        subproblem_done = subproblem_done | stalled_sub
        val_ref = jnp.where(checkpoint, val, s.val_ref)
        new_eq = jax.tree.map(lambda l, c: jnp.clip(l + s.mu * c, -1e10, 1e10), s.mult.eq, eq)
        new_ineq = jax.tree.map(lambda r, g: nlp.ineq_update(g, r, s.mu), s.mult.ineq, ineq)
        new_glob = nlp.ineq_update(glob, s.mult.glob, s.mu)
        updated = Multipliers(new_eq, new_ineq, new_glob)
        if opts.schedule == "default":
            take_mult = jnp.asarray(True)
            # grow the penalty only while infeasible and not shrinking fast enough
            grow = (viol > opts.feasibility_ratio * s.viol_prev) & (viol > opts.tol_feasibility)
            eta = s.eta
        else:  # Conn-Gould-Toint as in the thesis (alpha = beta = 0.4 family)
            take_mult = viol <= s.eta
            grow = ~take_mult
            mu_next = jnp.where(grow, jnp.minimum(s.mu * opts.penalty_growth, s.mu_max), s.mu)
            eta = jnp.where(take_mult, s.eta * mu_next ** -0.4, 1e-2 * mu_next ** -0.4)
            eta = jnp.maximum(eta, opts.tol_feasibility)
        mult = jax.tree.map(lambda new, old: jnp.where(take_mult, new, old), updated, s.mult)
        mu = jnp.where(grow, jnp.minimum(s.mu * opts.penalty_growth, s.mu_max), s.mu)
        omega = _next_inner_tol(opts, s.omega, viol, pbm_on)
        plain_viol = _violation(eq, ineq, glob)
        converged = (plain_viol <= opts.tol_feasibility) & (stat <= opts.tol_optimality)
        hist = s.history.at[jnp.minimum(s.outer, opts.max_outer - 1)].set(jnp.stack([cost, plain_viol, s.mu]))
        # likely infeasible: two outer iterations ago the violation was hardly larger
        # although the penalty has grown 16x since (history rows: cost, violation, mu),
        # or has sat at its cap since (see SolverOptions.detect_infeasible)
        back = s.history[jnp.maximum(s.outer - 2, 0)]
        hardly_less = plain_viol > 0.95 * back[1]
        prev = s.history[jnp.maximum(s.outer - 1, 0)]
        grown = ((plain_viol > 1e-3) & (s.mu >= 16.0 * back[2])
                 & ((jnp.minimum(prev[1], back[1]) > opts.detect_min_viol) | ~pbm_on))
        capped = (plain_viol > 1e-4) & (back[2] >= s.mu_max)
        stalled = (subproblem_done & (s.outer >= 2) & hardly_less & (grown | capped) & opts.detect_infeasible
                   & (nlp.tr.name == "decoupled"))

        def pick(new, old):
            return jax.tree.map(lambda a, b: jnp.where(subproblem_done, a, b), new, old)

        return _State(
            z=z, mult=pick(mult, s.mult), mu=pick(mu, s.mu), damping=damping,
            omega=pick(omega, s.omega), eta=pick(eta, s.eta), viol_prev=pick(viol, s.viol_prev),
            inner=jnp.where(subproblem_done, 0, inner), outer=s.outer + subproblem_done.astype(int),
            it=s.it + 1, done=(subproblem_done & converged) | failed, failed=failed, stalled=stalled,
            stationarity=stat, history=jnp.where(subproblem_done, hist, s.history),
            it_max=s.it_max, mu_max=s.mu_max, restarts=s.restarts, z_start=s.z_start, val_ref=val_ref)

    return jax.lax.while_loop(cond, body, state)


# ----------------------------------------------------------------------------------------
# public entry points


class Solution(eqx.Module):
    """An optimised trajectory (a leading batch axis in batched results).

    Attributes:
        q, qd: (N+1, n) states; v: (N, n) accelerations; tau: (N, m) actuator efforts;
        h: (N,) periods [s]; T: total time [s]; cost: objective value;
        cost_terms: dict time / energy / kinetic / singularity (weighted, summing to cost);
        energy: sum_k h_k tau_k^T diag(1/tau_max^2) tau_k (unweighted, see Weights);
        max_violation: dict per constraint family plus "overall": relative for boxes,
            absolute for the goal (rad and rad/s) and for via points (the Euclidean
            distance beyond each point's ``tol``); re-simulated from v and h;
        converged: strict: status == CONVERGED, i.e. the solver certified first-order
            optimality and the re-simulated trajectory meets every bound within
            ``verify_tol`` (relative) and the goal within ``verify_tol``;
        status: int code of :class:`Status`; iterations: Newton iterations;
        outer_iterations: multiplier updates;
        history: (max_outer, 3) per outer iteration: cost, violation, penalty (NaN-padded).
        kkt_error: first-order optimality error, in the scaled variables z (units of
            ``SolverOptions.tol_optimality``): the smallest of (a) the projected gradient
            of the Lagrangian and the complementarity at the returned trajectory, with
            the solver's own multipliers or, after the AL loop, least-squares ones, and
            (b) for a certified point, the value of the test that certified it: the AL
            loop's stationarity test (the AL's projected gradient at the end of its last
            subproblem, before the final polish) or the interior-point method's
            (IPOPT's scaled dual infeasibility and complementarity, divided by
            ``s_d = max(1, mean |multiplier| / 100)``, at its last iterate before its
            active bounds are snapped on). Every ``CONVERGED`` solution reports at most
            ``max(tol_optimality, ip_tol)`` (``tol_optimality`` at the defaults); a
            ``FEASIBLE_NOT_OPTIMAL`` one says how far (a) is from it.
    """

    q: Array
    qd: Array
    v: Array
    tau: Array
    h: Array
    T: Array
    cost: Array
    cost_terms: dict
    energy: Array
    max_violation: dict
    converged: Array
    status: Array
    iterations: Array
    outer_iterations: Array
    history: Array
    kkt_error: Array

    @property
    def status_message(self) -> str:
        s = jnp.asarray(self.status)
        if s.ndim:
            raise ValueError("status_message is for a single solution; use Status(int(code)).message")
        return Status(int(s)).message


def initial_guess(problem: Problem, opts: SolverOptions, tr: Transcription):
    """The default starting point (u (N, m_u), h (N,)) of ``opts.guess``, converted to
    the transcription's controls (:meth:`Transcription.initial_controls`)."""
    from .initial_guess import GUESSES

    v0, h0 = GUESSES[opts.guess](problem)
    return tr.initial_controls(problem, v0, h0), h0


def _stagewise(opts: SolverOptions, tr: Transcription, jerk: bool = False) -> bool:
    """Whether the Newton directions come from the stage-wise solve (see
    ``SolverOptions.linear_solver``; never with jerk rows, which couple stages)."""
    solver = opts.linear_solver
    if solver == "auto":
        solver = "riccati" if jax.default_backend() == "cpu" and not jerk else "dense"
    if solver == "riccati" and jerk:
        raise ValueError("options.linear_solver='riccati' does not handle Problem(jerk=True) (its rows couple "
                         "consecutive stages); use linear_solver='auto' or 'dense', or jerk=False")
    return solver == "riccati" and tr.name == "decoupled"


def _prepare(problem: Problem, opts: SolverOptions, tr: Transcription, init, warm=False):
    """(nlp, starting state, valid) for one problem; invalid samples start from a finite
    placeholder and are flagged at the end."""
    layout = tr.layout(problem)
    nlp = _NLP(problem=problem, tr=tr, layout=layout, sd=tr.stage_data(problem),
               stagewise=_stagewise(opts, tr, problem.jerk),
               ineq_penalty=opts.inequality_penalty, pbm_init=opts.pbm_init, pbm_ratio=opts.pbm_ratio)
    u0, h0 = init
    z0 = jnp.clip(layout.pack(u0, h0), layout.z_lo, layout.z_hi)
    # what a single Problem rejects up front (a batch builds its problems unvalidated;
    # non-finite ends included)
    valid = jnp.all(jnp.isfinite(z0)) & ~problem.infeasible_on_its_face()
    z0 = jnp.where(valid, z0, jnp.clip(jnp.zeros_like(z0), layout.z_lo, layout.z_hi))
    # an invalid sample takes no iteration (its lane is free at once in a batch)
    state = _init_state(nlp, z0, opts, warm)
    return nlp, state._replace(done=state.done | ~valid), valid


def _solve_core(problem: Problem, opts: SolverOptions, tr: Transcription, init, warm=False) -> Solution:
    nlp, state, valid = _prepare(problem, opts, tr, init, warm)
    if _static(opts).method == "ip":
        # one problem: a real branch (vmapped, both sides would run; solve_batch does not
        # come here with "ip")
        ip = _ip_run(nlp, state, opts)
        solved = _ip_solved(state, ip)
        state = jax.lax.cond(solved, lambda: _ip_result(nlp, state, ip),
                             lambda: _run_with_restart(nlp, state, opts))
        sol = _finish(nlp, state, opts, valid, light=solved)
        return dataclasses.replace(sol, iterations=sol.iterations + jnp.where(solved, 0, ip.it))
    return _finish(nlp, _run_with_restart(nlp, state, opts), opts, valid)


def _ip_run(nlp: _NLP, state: _State, opts: SolverOptions):
    """The interior-point method (:mod:`jtraj.ipm`) from the state's start; a state the
    AL loop would not run (a warm start already optimal) takes no iteration."""
    return ipm.run(nlp, state.z, jnp.where(state.done, 0, _static(opts).ip_max_iter), _ip_tolerances(opts))


def _ip_tolerances(opts) -> ipm.Tolerances:
    """When the interior-point method's run ends as solved (see ``SolverOptions.method``):
    the residual of every constraint within half ``verify_tol``, so that the strict
    verification passes without a polish. The parts' test is never looser than the AL
    loop's own targets: with ``tol_feasibility`` / ``tol_optimality`` set below them (a
    user asking for a tight solve) it ends only at the overall ``ip_tol``."""
    return ipm.Tolerances(_static(opts).ip_tol, jnp.minimum(opts.ip_dual_tol, opts.tol_optimality),
                          jnp.minimum(0.5 * opts.verify_tol, opts.tol_feasibility),
                          jnp.minimum(opts.ip_compl_tol, opts.tol_optimality), opts.ip_project_tol,
                          opts.ip_damping)


def _ip_solved(state: _State, ip) -> Array:
    """Where the interior-point method decided (solved, or stalled as likely infeasible:
    see :mod:`jtraj.ipm`); elsewhere the AL loop takes over."""
    return ~state.done & ((ip.done & ~ip.failed) | ip.infeasible)


def _ip_result(nlp: _NLP, state: _State, ip) -> _State:
    """The AL loop's state for a problem the interior-point method decided: its point,
    certified or stalled, and its multipliers (``_finish(..., light=True)`` verifies it
    and reports their KKT error)."""
    solved = ip.done & ~ip.failed
    # its active bounds snapped on (ipm.snap_to_bounds), unless that costs feasibility
    snapped = ipm.snap_to_bounds(nlp, ip)
    keep = _violation(*nlp.constraints(snapped)) <= jnp.maximum(1e-7, _violation(*nlp.constraints(ip.z)))
    return state._replace(z=jnp.where(keep, snapped, ip.z), mult=ipm.multipliers(nlp, ip), done=solved,
                          stalled=~solved, it=ip.it,
                          stationarity=jnp.where(solved, ip.certified, jnp.inf).astype(state.stationarity.dtype))


def _finish(nlp: _NLP, s: _State, opts: SolverOptions, valid, light=False) -> Solution:
    """The solution of a finished run: polished (:func:`_final_polish`), verified and
    certified. ``light``: a point the interior-point method decided (converged to
    ``ip_tol``, feasible to ~1e-7, or stalled far from feasible) is verified as it is,
    without the polish, and its KKT error is that of its own multipliers (``s.mult``), not
    of least-squares ones: both cost a Jacobian of every constraint row (serial3, N = 20,
    8 lanes, one core: the finish 1.48 ms per problem, of which the polish about 0.8 and
    the least-squares KKT error about 0.7). Under vmap either runs only while some lane
    needs it, so :func:`_finish_lanes` groups the light problems together."""
    nlp = _with_phase(nlp, s)
    problem, tr = nlp.problem, nlp.tr
    # a Python True (one interior-point result, :mod:`jtraj._staged`): neither the polish
    # nor the least-squares KKT error is in the program
    static_light = light is True
    light = jnp.asarray(light)
    if not static_light:
        s = s._replace(z=_final_polish(nlp, s.z, opts, skip=light))
    _, h = nlp.layout.unpack(s.z)
    W = nlp.W(s.z)
    q, qd, c, _ = jax.vmap(lambda w: tr.split_stage(problem, w))(W)
    a, tau = jax.vmap(lambda q_, qd_, c_: tr.accel_and_tau(problem, q_, qd_, c_))(q[:-1], qd[:-1], c[:-1])
    eq, ineq, glob = nlp.constraints(s.z)
    viol = {k: jnp.max(jnp.maximum(g, 0.0)) for k, g in ineq.items()}
    # bounds kept by projection, reported for completeness (relative)
    lim = problem.robot.limits
    if lim.qdd_max is not None:
        viol["qdd"] = jnp.maximum(viol.get("qdd", 0.0), jnp.max(jnp.maximum(jnp.abs(a) / lim.qdd_max - 1, 0)))
    if lim.tau_max is not None:
        viol["tau"] = jnp.maximum(viol.get("tau", 0.0), jnp.max(jnp.maximum(jnp.abs(tau) / lim.tau_max - 1, 0)))
    viol["h"] = jnp.max(jnp.maximum(jnp.maximum(lim.h_min - h, h - lim.h_max) / lim.h_max, 0.0))
    viol["T"] = jnp.maximum(glob[0], 0.0)
    if problem.jerk:  # the jerk rows (normalised, see jtraj.transcription.jerk_inequalities)
        viol["jerk"] = jnp.max(jnp.maximum(glob[1:], 0.0))
    viol["goal"] = jnp.maximum(jnp.max(jnp.abs(q[-1] - problem.q_goal)), jnp.max(jnp.abs(qd[-1] - problem.qd_goal)))
    if problem.via_points:
        # the Euclidean distance beyond each via point's own tol, absolute (task units)
        # like the goal's: the AL and the polish meet the imposed box to ~1e-7, which a
        # check relative to a tight tol (1e-6 m) could never accept
        sd = nlp.sd
        dist = jnp.linalg.norm(jax.vmap(problem.robot.forward_kinematics)(q) - sd.via_target, axis=-1)
        viol["via"] = jnp.max(jnp.where(sd.is_via > 0, jnp.maximum(dist - sd.via_tol, 0.0), 0.0))
        if sd.via_rotation is not None:  # ||vect(R^T R_l)|| beyond rot_tol, absolute likewise
            rot = jax.vmap(lambda q_, R_l: jnp.linalg.norm(orientation_error(problem.robot.rotation(q_), R_l)))
            err = rot(q, sd.via_rotation)
            viol["via_rotation"] = jnp.max(jnp.where(sd.is_via_rot > 0, jnp.maximum(err - sd.via_rot_tol, 0.0), 0.0))
    for k, c in eq.items():
        if k != "goal":
            viol[k] = jnp.max(jnp.abs(c))
    overall = jnp.max(jnp.stack(list(viol.values())))
    viol["overall"] = overall
    terms = nlp.cost_terms(s.z)
    cost = sum(terms.values())
    finite = jnp.all(jnp.isfinite(s.z)) & jnp.isfinite(cost) & jnp.all(jnp.isfinite(tau))
    verified = overall <= opts.verify_tol
    # the loop certifies optimality on the AL's own measure at the end of a subproblem;
    # a point it left uncertified (iteration limit) may still be a KKT point of the
    # original problem: the KKT error with the best of three multiplier estimates decides
    kkt = _al_kkt_error(nlp, s.z, s.mult, s.mu)
    if not static_light:
        kkt = jnp.minimum(_at_most_once(~light, lambda zz: _kkt_error(nlp, zz), s.z, fill=jnp.inf), kkt)
    # a certified point reports at most its certifying test's value (Solution.kkt_error)
    kkt = jnp.minimum(kkt, jnp.where(s.done & ~s.failed, s.stationarity, jnp.inf))
    certified = s.done | (kkt <= opts.tol_optimality)
    unfinished = jnp.where(s.stalled, Status.LIKELY_INFEASIBLE, Status.MAX_ITERATIONS)
    status = jnp.where(
        ~valid, Status.INVALID_INPUT,
        jnp.where(~finite | s.failed, Status.NUMERICAL_ERROR,
                  jnp.where(certified & verified, Status.CONVERGED,
                            jnp.where(s.done, Status.VERIFICATION_FAILED,
                                      jnp.where(verified, Status.FEASIBLE_NOT_OPTIMAL, unfinished)))))
    scale = 1.0 if lim.tau_max is None else lim.tau_max
    energy = jnp.sum(h * jnp.sum((tau / scale) ** 2, axis=1))
    return Solution(q=q, qd=qd, v=a, tau=tau, h=h, T=jnp.sum(h), cost=cost, cost_terms=terms, energy=energy,
                    max_violation=viol, converged=status == Status.CONVERGED, status=status.astype(jnp.int32),
                    iterations=s.it, outer_iterations=s.outer, history=s.history, kkt_error=kkt)


@_options_jit()  # jtraj._compile.solver_jit (the solver's XLA CPU options), options split
def _solve_jit(problem, opts, transcription, init, warm, guess):
    # init is always arrays, replaced by the default guess where the traced bool ``guess``
    # says so (one program for cold and warm starts, and the guess without a program
    # call of its own: 0.36 ms of a ~6 ms warm single solve), and warm a traced bool
    tr = Transcription(transcription)
    init = jax.lax.cond(guess, lambda: initial_guess(problem, opts, tr), lambda: init)
    return _solve_core(problem, opts, tr, init, warm)


def solve(problem: Problem, *, options: SolverOptions | None = None, transcription: str = "decoupled",
          init: tuple[Any, Any] | None = None, warm: str = "full", on_failure: str = "nan") -> Solution:
    """Solve one trajectory problem; compiled once per robot type, shape and the options'
    structure (see :class:`SolverOptions`).

    On a CPU one problem runs about 1.6x faster in a process pinned to one core
    (:func:`jtraj.pin_to_one_cpu` before JAX's first computation; the CLI does it).

    Solves in float64 only: raises ``ValueError`` where ``jax_enable_x64`` is off or the
    problem holds float32 arrays (built while it was off). A solve that compiles the
    solver (first use in a process) logs a line saying so (logger "jtraj", INFO); JAX's
    persistent compilation cache, on since ``import jtraj``, keeps it (:mod:`jtraj._setup`).

    Args:
        problem: a :class:`jtraj.Problem`.
        options: :class:`SolverOptions` (defaults documented there).
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
            The interior-point method (``options.method``) starts its barrier at ``init``
            either way.
        on_failure: what derivatives of a solve that did not converge are (see
            :mod:`jtraj.implicit`): "nan" (default) or "raise" (a run-time error when
            the solve is differentiated, inside ``jit`` too).

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
    _check_efforts(problem.efforts, transcription)
    Transcription(transcription).check_jerk(problem)
    if warm not in ("full", "primal"):
        raise ValueError(f"warm must be 'full' or 'primal', got {warm!r}")
    warm = init is not None and warm == "full"
    opts = _resolve_method(options, transcription, problem.robot, problem.jerk)
    # float64 only, the compilation cache on, a first compilation logged (jtraj._setup)
    key = _setup.before_solve(problem.robot, problem.N, batch=False, problem=problem, options=opts,
                              transcription=transcription, efforts=problem.efforts)
    guess = init is None
    if guess:  # placeholders of the controls' shapes (the program computes the guess)
        init = _placeholder_init(problem.N, Transcription(transcription).control_dim(problem))
    else:
        init = _check_init(problem, init, transcription)
    _resources.check(problem.N, problem.robot.n)  # ValueError naming N beyond the memory limit
    if implicit.any_traced((problem, init)):  # inside jit / vmap / a derivative
        return implicit.solve_traced(problem, opts, transcription, init, warm, guess, on_failure)
    from . import _staged  # concrete arrays: the programs a problem needs, in stages

    sol = _staged.solve(problem, opts, transcription, init, np.bool_(warm), np.bool_(guess))
    _setup.compiled(key)
    return sol


@functools.lru_cache(maxsize=16)
def _placeholder_init(N: int, m_u: int):
    return np.zeros((N, m_u)), np.zeros(N)


def _resolve_method(opts: SolverOptions | None, transcription: str, robot, jerk: bool = False) -> SolverOptions:
    """The options (the defaults for None) with ``method="auto"`` resolved (see
    :class:`SolverOptions`) and an explicit "ip" checked. Cached: building a
    SolverOptions and checking it costs about 0.15 ms, which one warm solve (about 5 ms)
    paid twice."""
    if opts is not None and not isinstance(opts, SolverOptions):
        raise ValueError(f"options must be a jtraj.SolverOptions, got {type(opts).__name__}")
    return _resolved(opts, transcription, getattr(robot, "path_equalities", None) is not None, bool(jerk))


@functools.lru_cache(maxsize=64)
def _resolved(opts: SolverOptions | None, transcription: str, path_equalities: bool,
              jerk: bool = False) -> SolverOptions:
    opts = SolverOptions() if opts is None else opts
    if opts.method == "auto":
        ip = transcription == "decoupled" and not path_equalities and not jerk and opts.inequality_penalty == "phr"
        return dataclasses.replace(opts, method="ip" if ip else "al")
    _check_method(opts, transcription, path_equalities, jerk)
    return opts


def _check_method(opts: SolverOptions, transcription: str, path_equalities: bool, jerk: bool = False):
    """``method="ip"`` needs the decoupled transcription, no equalities but the goal and
    no jerk rows (its global rows are functions of T alone)."""
    if opts.method != "ip":
        return
    if transcription != "decoupled":
        raise ValueError(f"options.method='ip' needs transcription='decoupled', got {transcription!r}")
    if path_equalities:
        raise ValueError("options.method='ip' does not handle a robot's path_equalities; use method='al'")
    if jerk:
        raise ValueError("options.method='ip' does not handle Problem(jerk=True) (its rows couple consecutive "
                         "stages); use method='al' or 'auto', or jerk=False")


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


@_options_jit()
def _solve_batch_jit(problems, opts, transcription, init, warm):
    tr = Transcription(transcription)
    return eqx.filter_vmap(lambda p, i: _solve_core(p, opts, tr, i, warm))(problems, init)


@_options_jit()
def _prepare_batch_jit(problems, opts, transcription, init, warm):
    tr = Transcription(transcription)
    return eqx.filter_vmap(lambda p, i: _prepare(p, opts, tr, i, warm))(problems, init)


def _segment(nlps, states, opts, steps: int):
    """``steps`` more iterations of each lane's loop (vmapped; a finished lane idles)."""
    return eqx.filter_vmap(lambda n, s: _loop(n, s, opts, s.it + steps))(nlps, states)


def _restart_lanes(nlps, states, need, opts):
    """``states`` (a set of lanes) with the lanes ``need`` restarted (:func:`_restart`)."""
    new = eqx.filter_vmap(lambda n, s: _restart(n, s, opts))(nlps, states)
    return jax.tree.map(lambda a, b: jnp.where(need.reshape(need.shape + (1,) * (a.ndim - 1)), a, b), new, states)


#: :func:`_segment` on pytrees (``benchmarks/iteration_cost.py``; the batch driver runs it on
#: packed arrays, see :func:`_lane_programs`)
_segment_jit = _options_jit()(_segment)


@_jit
def _gather_jit(nlps, states, idx):
    return _take(nlps, idx), _take(states, idx)


@_options_jit()
def _finish_batch_jit(nlps, states, opts, valid, light):
    """:func:`_finish` over a batch, vmapped (see :func:`_finish_lanes` on a CPU)."""
    return eqx.filter_vmap(lambda n, s, v, l: _finish(n, s, opts, v, l))(nlps, states, valid, light)


def _finish_lanes(nlps, states, opts, valid, slots: int, light):
    """:func:`_finish_batch_jit` over ``slots`` problems at a time (the last group padded
    with a repeat of its first problem), the results concatenated in order. On a CPU a
    wide vmap costs more per problem, as the loop's lanes do (serial3, N = 20, one core:
    2.1 ms per problem at 8 lanes, 3.9 at 256, 4.5 at 1024), and the kernel, compiled for
    ``slots`` lanes, does not depend on the batch size. With the restart's kernel also on
    gathered lanes, a first batch of a new size (72 benchmark pairs after 64, one core)
    took 6.9 s instead of 20.4 s (2.9 s warm): as a ``lax.map`` inside one kernel the
    finish took 7 s to compile for each size. The same 1024 pairs: the same results to
    the last bit, 35.8-37.2 against 35.5-36.3 s. The ``light`` problems (NumPy mask, see
    :func:`_finish`) go first, in groups of their own, so that their groups skip the work
    they do not need."""
    B = int(valid.shape[0])
    order = np.argsort(~light, kind="stable")  # the light problems first, each kind in order
    parts = []
    for start in range(0, B, slots):
        idx = _padded(order[start:start + slots], slots)
        sub_nlps, (sub_states, sub_valid) = _gather_jit(nlps, (states, valid), idx)
        parts.append(_finish_batch_jit(sub_nlps, sub_states, opts, sub_valid, jax.device_put(light[idx])))
    # in order already where all or none are light: no permutation
    back = None if not light.any() or light.all() else np.argsort(order)
    return _join_jit(parts, back, B)


@functools.partial(jax.jit, static_argnums=2)
def _join_jit(parts, back, size: int):
    """The groups' results concatenated, cut to ``size`` and put in order by ``back``
    (None: in order already), as one program: leaf by leaf, eager ``concatenate`` and
    slicing dispatched about 50 small programs per batch (a profile of a dataset
    worker's chunk of 256 pairs: 0.10 of its 2.1 s under the profiler)."""
    def one(*xs):
        x = jnp.concatenate(xs)[:size]
        return x if back is None else x[back]

    return jax.tree.map(one, *parts)


def _padded(group, width: int):
    """Lane indices for ``group`` (a NumPy index array, at most ``width`` long) padded to
    ``width`` with repeats of its first entry (a fixed width, one compilation; a repeated
    lane computes and writes back the same result twice). A NumPy array: indexing on the
    host dispatches no program."""
    return np.concatenate([group, np.repeat(group[:1], width - group.size)])


def _take(tree, idx):
    return jax.tree.map(lambda x: x[idx] if eqx.is_array(x) else x, tree)


def _lane_counts(slots: int) -> list[int]:
    """Lane counts a compacted batch steps down through once nothing is pending: on a CPU
    a vmapped iteration costs about its lane count, so the stragglers at the end of a
    batch run on 1/4 and 1/16 of the lanes, but on no fewer than 2 (each count is one
    more compilation, cached); on an accelerator lanes are nearly free and the count
    stays. Stopping at 2 lanes rather than 1 is as fast and compiles one segment program
    less."""
    if jax.default_backend() != "cpu":
        return [slots]
    return sorted({slots, max(slots // 4, min(slots, 2)), max(slots // 16, min(slots, 2))}, reverse=True)


def _cpu_lanes(nz: int) -> int:
    """The default lane count on a CPU for problems of about ``nz`` unknowns: 16 at
    serial3's N = 20 (nz = 80), fewer for larger problems (8 at N = 40), at least 4.
    Beyond that each lane costs more (the working set outgrows the core's cache), and the
    threshold falls as N grows: on one core, 16 lanes solve 256 benchmark pairs at N = 20
    about 5 % faster than 8 and 12 % faster than 24 or 32; at N = 40, 4 lanes beat 8."""
    return int(min(16, max(4, 1280 // max(nz, 1))))


def _solve_compacted(problems, opts, transcription, init, warm, slots: int, steps: int):
    """Solve B problems (more than the smallest lane count) with a fixed number of
    vmapped slots, refilled as problems finish. A vmapped ``while_loop`` runs every
    member until the slowest is done, so one batch costs max(iterations) per problem;
    running segments of ``steps`` iterations and
    handing finished slots to pending problems brings the cost to about the mean. Once
    nothing is pending, the unfinished problems move to fewer lanes (see
    :func:`_lane_counts`). Each problem takes the iterations it takes in a one-shot batch
    (results equal up to rounding at another batch width), restarts included: a run that
    ends uncertified is restarted on its lane (see :func:`_run_lanes`). With lanes held
    throughout, about a third of the lane-iterations would be idle."""
    nlps, states, valid = _prepare_batch_jit(problems, opts, transcription, init, warm)
    states = _run_lanes(nlps, states, np.arange(int(valid.shape[0])), opts, slots, steps)
    return _finish_all(nlps, states, opts, valid, slots)


def _finish_all(nlps, states, opts, valid, slots: int, light=None):
    """:func:`_finish` over a batch; on a CPU ``slots`` problems at a time (see
    :func:`_finish_lanes`). ``light``: (B,) NumPy mask of the problems the interior-point
    method decided (see :func:`_finish`), or None."""
    light = np.zeros(int(valid.shape[0]), bool) if light is None else np.asarray(light, bool)
    if jax.default_backend() == "cpu":
        return _finish_lanes(nlps, states, opts, valid, slots, light)
    return _finish_batch_jit(nlps, states, opts, valid, jnp.asarray(light))


@_options_jit()
def _ip_init_batch_jit(nlps, states, opts):
    """The interior-point states of a batch (a state the AL loop would not run, a warm
    start already optimal, starts finished)."""
    def one(n, s):
        st = ipm.init(n, s.z)
        return st._replace(done=s.done)

    return eqx.filter_vmap(one)(nlps, states)


@_jit
def _ip_merge_jit(nlps, states, ips):
    solved = _ip_solved(states, ips)
    merged = eqx.filter_vmap(_ip_result)(nlps, states, ips)
    return jax.tree.map(lambda a, b: jnp.where(solved.reshape(solved.shape + (1,) * (a.ndim - 1)), a, b),
                        merged, states), solved


def _solve_batch_ip(problems, opts, transcription, init, warm, slots: int, steps: int):
    """``solve_batch`` with ``method="ip"``: the interior-point method on every problem
    through ``slots`` lanes (:func:`_run_pool`), then the AL loop on the problems it left
    unsolved (the same lanes, :func:`_run_lanes`), then the finish."""
    nlps, states, valid = _prepare_batch_jit(problems, opts, transcription, init, warm)
    ips = _ip_init_batch_jit(nlps, states, opts)
    ips = _run_pool(nlps, ips, np.flatnonzero(~np.asarray(ips.done)), opts, slots)
    states, solved = _ip_merge_jit(nlps, states, ips)
    solved = np.asarray(solved)
    todo = np.flatnonzero(~solved & ~np.asarray(states.done) & np.asarray(valid))
    states = _run_lanes(nlps, states, todo, opts, slots, steps)
    sol = _finish_all(nlps, states, opts, valid, slots, light=solved)
    return dataclasses.replace(sol, iterations=_add_ip_iterations(sol.iterations, solved, ips.it))


@jax.jit
def _add_ip_iterations(iterations, solved, ip_iterations):
    """The interior-point iterations added where the AL loop went on after them."""
    return iterations + jnp.where(solved, 0, ip_iterations)


def _run_pool(nlps, states, todo, opts, slots: int):
    """The interior-point method on the problems ``todo`` (indices into the batch) through
    ``slots`` vmapped lanes, refilled inside one compiled loop (``_LanePrograms.pool``);
    returns the states.

    A lane whose problem finishes takes the next pending one at once, in the same loop:
    the AL loop's segments (:func:`_run_lanes`) hand lanes over only between segments of
    ``segment`` iterations, and a problem finishing within one left its lane idle for the
    rest of it, about half a segment per problem (on serial3 at N = 20 about 20-30 % of
    the lane-iterations; refilled at once, 3 %). Once nothing is pending and at most the
    next smaller lane count (:func:`_lane_counts`) of problems is left, the loop returns
    and the rest goes on through that many lanes."""
    B = todo.size
    if B == 0:
        return states
    counts = _lane_counts(slots)
    while len(counts) > 1 and counts[1] >= B:  # few problems: fewer lanes
        counts = counts[1:]
    # (steps 0: the pool runs no segments)
    progs = _lane_programs(_packing.packing(nlps), _packing.packing(states), 0, jax.default_backend())
    split = _split_options(opts)
    total = int(jax.tree.leaves(states)[0].shape[0])
    # the batch padded to a power of two, at least 64 (the pool takes it whole: one
    # program per lane count and size, not per batch size)
    size = max(_POOL_MIN, counts[0], 1 << (total - 1).bit_length())
    all_nlps, all_states = progs.pack(_packing.arrays(nlps), _packing.arrays(states), size)
    queue = todo
    for i, lanes in enumerate(counts):
        q = np.zeros(size, np.int64)  # the queue (problem indices), padded
        q[:queue.size] = queue
        first = np.zeros(lanes, np.int64)
        first[:min(lanes, queue.size)] = queue[:lanes]
        stop_at = counts[i + 1] if i + 1 < len(counts) else 0
        all_states, lane_ids, open_ = progs.pool(all_nlps, all_states, q, np.asarray(queue.size), first,
                                                 np.arange(lanes) < queue.size, np.asarray(stop_at), split)
        queue = np.asarray(lane_ids)[np.asarray(open_)]
        if queue.size == 0:
            break
    return _packing.from_arrays(progs.unpack(all_states, total), progs.states)


#: the smallest batch size the interior-point pool's programs are compiled for (see _run_pool)
_POOL_MIN = 64


def _run_lanes(nlps, states, todo, opts, slots: int, steps: int):
    """Run the problems ``todo`` (indices into the batch) to the end of their loop through
    ``slots`` vmapped lanes (see :func:`_solve_compacted`); returns the states.

    The batch's problems and states travel packed (:mod:`jtraj._packing`): after each
    segment one call writes the lanes back and takes the next ones (:func:`_lane_programs`).
    A run that ended uncertified in a segment is restarted (:func:`_restart`) on its lane
    and goes on there: 256 benchmark pairs of seed 1, one core, PBM (whose fallback is
    such a restart, 13 pairs) 7.7-8.1 s against 8.2-8.9 s with the restarts in a second
    round of lanes after the batch, PHR (3 restarts) unchanged.
    With a gather, a segment and a scatter per segment on the pytrees (``eqx.filter_jit``,
    about 50 leaves), the driver's own work was 14 % of a batch's time (serial3, N = 20,
    128 pairs, one core: 0.25 s gathering and 0.22 s scattering of 5.2 s)."""
    B = todo.size
    counts = _lane_counts(slots)
    while len(counts) > 1 and counts[1] >= B:  # few problems: fewer lanes
        counts = counts[1:]
    # fewer problems than lanes: the other lanes repeat the first problem (the same
    # iterates, written back twice)
    idx = np.concatenate([np.arange(min(counts[0], B)), np.zeros(max(counts[0] - B, 0), int)])
    nxt = min(counts[0], B)
    done = np.zeros(B, bool)
    if todo.size == 0:
        return states
    progs = _lane_programs(_packing.packing(nlps), _packing.packing(states), steps, jax.default_backend())
    split = _split_options(opts)
    all_nlps, all_states = progs.pack(_packing.arrays(nlps), _packing.arrays(states), None)
    lanes = todo[idx]  # NumPy index arrays: the compiled calls take them without jnp's dispatch
    sub_nlps, sub_states = progs.take(all_nlps, all_states, lanes)
    while True:
        sub_states, fin, need = progs.segment(sub_nlps, sub_states, split)
        need = np.asarray(need)
        if need.any():
            # a run that ended uncertified goes on, restarted, on its lane; compiled for a
            # lane count only when a restart first happens there
            sub_states, fin = progs.restart(sub_nlps, sub_states, need, split)
        fin = np.asarray(fin)
        done[idx[fin]] = True
        for j in np.flatnonzero(fin):
            if nxt < B:
                idx[j] = nxt
                nxt += 1
        if done.all():
            return _packing.from_arrays(progs.result(all_states, sub_states, lanes), progs.states)
        open_ = np.flatnonzero(~done)  # running or pending
        if nxt >= B and len(counts) > 1 and len(open_) <= counts[1]:
            counts = counts[1:]
            # the unfinished problems, padded with a finished one (a lane that idles)
            pad = np.flatnonzero(done)[:1]
            idx = np.concatenate([open_, np.repeat(pad, counts[0] - len(open_))])
        new_lanes = todo[idx]
        all_states, sub_nlps, sub_states = progs.exchange(all_nlps, all_states, sub_states, lanes, new_lanes)
        lanes = new_lanes


class _LanePrograms(NamedTuple):
    """The compiled programs of :func:`_run_lanes` on packed batches (tuples of
    ``(B, width)`` arrays, see :mod:`jtraj._packing`)."""

    pack: Any  # (nlps' arrays, states' arrays, rows or None) -> packed nlps, packed states (padded to rows)
    take: Any  # (nlps, states, lanes) -> the lanes' nlps and states
    segment: Any  # (lane nlps, lane states, split options) -> (lane states, finished, to restart)
    restart: Any  # (lane nlps, lane states, which, split options) -> (lane states, finished)
    exchange: Any  # (nlps, states, lane states, lanes, next lanes) -> lanes written back, next taken
    result: Any  # (states, lane states, lanes) -> the states' arrays, lanes written back (_packing.from_arrays)
    pool: Any  # (nlps, states, queue, count, lanes, live, stop_at, split options) -> (states, lanes, unfinished)
    unpack: Any  # (states, rows) -> the first rows' states' arrays (_packing.from_arrays)
    states: _packing.Packing  # how the states are packed


def _pad_rows(packed: tuple, rows: int | None) -> tuple:
    """Packed arrays with rows of zeros added up to ``rows`` (None: as they are)."""
    return packed if rows is None else tuple(jnp.pad(a, ((0, rows - a.shape[0]), (0, 0))) for a in packed)


@functools.lru_cache(maxsize=32)
def _lane_programs(pn: _packing.Packing, ps: _packing.Packing, steps: int, backend: str) -> _LanePrograms:
    """The programs for problems packed as ``pn`` and states as ``ps`` (the AL loop's
    states for ``segment`` and ``restart``, the interior-point method's for ``pool``;
    plain ``jax.jit`` on packed arrays: no pytree partitioning per call), compiled with
    the solver's XLA options on a CPU (see :mod:`jtraj._compile`)."""
    options = supported_options(SOLVER_XLA_OPTIONS) if backend == "cpu" else None
    jit = functools.partial(jax.jit, compiler_options=options)

    def put(states, sub, lanes):  # (a lane index out of bounds: that lane not written)
        return tuple(a.at[lanes].set(b, mode="drop") for a, b in zip(states, sub))

    def take(nlps, states, lanes):
        return tuple(a[lanes] for a in nlps), tuple(a[lanes] for a in states)

    def segment(nlps, states, split):
        opts = _TracedOptions(split)
        nlps, before = _packing.unpack(nlps, pn), _packing.unpack(states, ps)
        out = _segment(nlps, before, opts, steps)
        fin = _finished(out, opts)
        # the lanes whose run ended in this segment uncertified, to restart (_restart)
        need = fin & ~_finished(before, opts) & _needs_restart(out, opts)
        return _packing.pack(_packing.arrays(out), ps), fin, need

    def restart(nlps, states, need, split):
        opts = _TracedOptions(split)
        out = _restart_lanes(_packing.unpack(nlps, pn), _packing.unpack(states, ps), need, opts)
        return _packing.pack(_packing.arrays(out), ps), _finished(out, opts)

    def exchange(nlps, states, sub, lanes, new_lanes):
        states = put(states, sub, lanes)
        return (states, *take(nlps, states, new_lanes))

    def pool(nlps, states, queue, count, lanes, live, stop_at, split):
        # (the interior-point method, see _run_pool) the problems queue[:count] through
        # the lanes (their first problems `lanes`, those `live`), each lane taking the next
        # queued problem as its own finishes, until nothing is queued and at most
        # `stop_at` are unfinished; returns the states with every lane's written back, the
        # lanes' problems and which of them are unfinished. The loop carries the lanes'
        # array leaves (a loop's or a cond's carry turns a static leaf into an array)
        opts = _TracedOptions(split)
        max_iter, tol = _static(opts).ip_max_iter, _ip_tolerances(opts)
        B = states[0].shape[0]
        step = eqx.filter_vmap(lambda n, s: ipm.step(n, s, tol))

        def finished(ls):
            return ipm.finished(_packing.from_arrays(ls, ps), max_iter)

        def select(mask, a, b):
            return [jnp.where(mask.reshape(mask.shape + (1,) * (x.ndim - 1)), x, y) for x, y in zip(a, b)]

        def write_back(states, ls, rows):  # rows B (out of bounds): not written
            return put(states, _packing.pack(ls, ps), rows)

        def gather(states, rows):
            n, s = take(nlps, states, rows)
            return _packing.arrays(_packing.unpack(n, pn)), _packing.arrays(_packing.unpack(s, ps))

        def refill(c):
            ln, ls, states, lanes, live, nxt = c
            fin = finished(ls)
            states = write_back(states, ls, jnp.where(live & fin, lanes, B))
            free = ~live | fin
            pos = nxt + jnp.cumsum(free) - 1
            take = free & (pos < count)
            lanes = jnp.where(take, queue[jnp.clip(pos, 0, queue.shape[0] - 1)], lanes)
            new_n, new_s = gather(states, lanes)
            return (select(take, new_n, ln), select(take, new_s, ls), states, lanes, (live & ~fin) | take,
                    nxt + jnp.sum(take))

        def handover(c):  # only where a lane is free: a real branch (the loop is not vmapped)
            _, ls, _, _, live, nxt = c
            free = jnp.any(live & finished(ls)) | (jnp.any(~live) & (nxt < count))
            return jax.lax.cond(free, refill, lambda c: c, c)

        def body(c):
            # the lanes whose problem finished (in the last iteration, or before its
            # first) handed over, then one iteration
            ln, ls, states, lanes, live, nxt = handover(c)
            new = step(_packing.from_arrays(ln, pn), _packing.from_arrays(ls, ps))
            return ln, select(finished(ls), ls, _packing.arrays(new)), states, lanes, live, nxt

        def cond(c):
            _, ls, _, _, live, nxt = c
            return (nxt < count) | (jnp.sum(live & ~finished(ls)) > stop_at)

        ln, ls = gather(states, lanes)
        _, ls, states, lanes, live, _ = jax.lax.while_loop(cond, body, (ln, ls, states, lanes, live, jnp.sum(live)))
        states = write_back(states, ls, jnp.where(live, lanes, B))
        return states, lanes, live & ~finished(ls)

    return _LanePrograms(
        pack=jit(lambda nlps, states, rows: (_pad_rows(_packing.pack(nlps, pn), rows),
                                             _pad_rows(_packing.pack(states, ps), rows)), static_argnums=2),
        # the segment program kept across processes where the compilation cache is on
        # (jtraj._tracecache; plain jit where it is off: eqx.filter_jit's per-call work is
        # what the packing saves)
        segment=_tracecache.cached("segment", segment, repr((pn, ps, steps)), options, fallback=jit(segment)),
        restart=_tracecache.cached("restart", restart, repr((pn, ps)), options, fallback=jit(restart)),
        take=jit(take), exchange=jit(exchange, donate_argnums=1),
        # (no donation: the unpacked arrays cannot reuse the packed buffers; called once)
        result=jit(lambda states, sub, lanes: _packing.arrays(_packing.unpack(put(states, sub, lanes), ps))),
        pool=_tracecache.cached("pool", pool, repr((pn, ps)), options, fallback=jit(pool)),
        unpack=jit(lambda states, rows: _packing.arrays(_packing.unpack(tuple(a[:rows] for a in states), ps)),
                   static_argnums=1),
        states=ps)


@_options_jit()
def _guess_batch_jit(problems, opts, transcription):
    tr = Transcription(transcription)
    return eqx.filter_vmap(lambda p: initial_guess(p, opts, tr))(problems)


def _problem(robot, q_start, q_goal, qd_start, qd_goal, T_max, N, weights, efforts) -> Problem:
    return Problem(robot, q_start, q_goal, N=N, weights=weights, qd_start=qd_start, qd_goal=qd_goal, T_max=T_max,
                   efforts=efforts, validate=False)


@_jit
def _problems_jit(robot, q_start, q_goal, qd_start, qd_goal, T_max, N, weights, efforts):
    """:class:`Problem` per sample of a batch, as one program (built eagerly under vmap,
    each of its operations was a program of its own: a dozen compiled at a process's
    first batch)."""
    return eqx.filter_vmap(_problem, in_axes=(None, 0, 0, 0, 0, 0, None, None, None))(
        robot, q_start, q_goal, qd_start, qd_goal, T_max, N, weights, efforts)


def solve_batch(robot, q_start, q_goal, *, N: int = 20, weights: Weights | None = None,
                qd_start=None, qd_goal=None, T_max=None, options: SolverOptions | None = None,
                transcription: str = "decoupled", init: tuple[Any, Any] | None = None,
                slots: int | None | str = "auto", segment: int = 10, efforts: str = "samples") -> Solution:
    """Solve B problems sharing one robot, N and weights in one vmapped, compiled call.

    Args:
        robot: a :class:`jtraj.robots.Robot` (shared by the batch).
        q_start, q_goal: (B, n) start and goal configurations.
        qd_start, qd_goal: optional (B, n) boundary velocities (default rest).
        T_max: optional scalar or (B,) bound on the total time.
        init: optional warm start (u (B, N, m_u), h (B, N)).
        efforts: "samples" or "intervals" (see :class:`jtraj.Problem`).
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
            down to 4 for larger problems (:func:`_cpu_lanes`). On a CPU a vmapped
            iteration costs about its lane count, and more per lane once the lanes'
            working set outgrows the core's cache; on an accelerator lanes are nearly
            free, so larger ``slots`` pay there.

    Returns a :class:`Solution` whose fields carry a leading batch axis. Samples with
    non-finite inputs are not solved: their status is ``Status.INVALID_INPUT`` (a batch
    never raises for one bad sample); shapes and the robot are checked up front, and
    float64 as in :func:`solve`.

    Derivatives (``jax.grad``, ``jax.jvp``, ``jax.jacobian``, under ``jit`` and ``vmap``
    too) with respect to traced inputs (q_start, q_goal, boundary velocities, T_max,
    the weights' and the robot's arrays) come per sample from :mod:`jtraj.implicit`;
    a sample that did not converge gets zero derivatives
    (:func:`jtraj.valid_derivatives` gives the mask). With concrete primal values (a
    derivative outside ``jit``) the solve itself runs on the lane driver above; inside
    ``jit`` or ``vmap`` it is one vmapped program.
    """
    from .robots import Robot

    if not isinstance(robot, Robot):
        raise ValueError(f"robot must be a jtraj.robots.Robot, got {type(robot).__name__}")
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
    jerk = robot.limits.qddd_max is not None  # the problems' default (see Problem's jerk)
    if jerk and transcription not in Transcription.JERK:
        raise ValueError(f"robot {robot.name!r} has a jerk bound, which transcription {transcription!r} cannot "
                         f"impose; solve Problem(..., jerk=False) one by one, or use one of {Transcription.JERK}")
    opts = _resolve_method(options, transcription, robot, jerk)
    weights = Weights() if weights is None else weights
    key = _setup.before_solve(robot, N, batch=True, weights=weights, options=opts, transcription=transcription,
                              efforts=efforts)

    def make(a, b, c, d, t):
        return _problem(robot, a, b, c, d, t, N, weights, efforts)

    if slots == "auto":
        slots = _cpu_lanes(N * (n + 1)) if jax.default_backend() == "cpu" else 1024
    if slots is not None and (not isinstance(slots, int) or isinstance(slots, bool) or slots < 1):
        raise ValueError(f"slots must be a positive integer, 'auto' or None, got {slots!r}")
    if not isinstance(segment, int) or segment < 1:
        raise ValueError(f"segment must be a positive integer, got {segment!r}")
    _resources.check(N, n, B, lanes=slots or B)  # ValueError naming N or B beyond the memory limit
    # (inside another trace: the programs without their XLA options, see implicit._nested)
    problems = (implicit._nested(_problems_jit) if traced else _problems_jit)(
        robot, q_start, q_goal, qd_start, qd_goal, T_max, N, weights, efforts)
    warm = init is not None
    if init is None:
        # non-finite samples get a finite placeholder guess; they are flagged invalid
        init = (implicit._nested(_guess_batch_jit) if traced else _guess_batch_jit)(problems, opts, transcription)
    else:
        m_u = Transcription(transcription).control_dim(make(q_start[0], q_goal[0], qd_start[0], qd_goal[0], T_max[0]))
        u, h = jnp.asarray(init[0], float), jnp.asarray(init[1], float)
        if u.shape != (B, N, m_u) or h.shape != (B, N):
            raise ValueError(f"init must be (u (B, N, {m_u}), h (B, N)) = ({(B, N, m_u)}, {(B, N)}), "
                             f"got ({u.shape}, {h.shape})")
        init = (u, h)
    if traced or implicit.any_traced(init):  # derivatives per sample (jtraj.implicit)
        return implicit.solve_batch_traced(problems, opts, transcription, init, warm, slots, segment)
    sol = _solve_problems(problems, opts, transcription, init, warm, slots, segment)
    _setup.compiled(key)
    return sol


def _solve_problems(problems, opts, transcription, init, warm: bool, slots, segment: int) -> Solution:
    """:func:`solve_batch`'s solve of built problems (a batch of :class:`Problem`) from
    ``init`` (arrays), by the host-driven lane driver (see ``slots`` there)."""
    B = int(jax.tree.leaves(problems.q_start)[0].shape[0])
    warm = bool(warm)
    if opts.method == "ip":
        sol = _solve_batch_ip(problems, opts, transcription, init, jax.device_put(warm), slots or B, segment)
    elif slots is not None and B > min(_lane_counts(slots)):
        sol = _solve_compacted(problems, opts, transcription, init, jax.device_put(warm), slots, segment)
    else:
        sol = _solve_batch_jit(problems, opts, transcription, init, jax.device_put(warm))
    return sol
