"""Sensitivities of an optimal trajectory with respect to robot parameters.

``sensitivity(problem, wrt="masses")`` returns ``{"cost": dJ*/dtheta, "T": dT*/dtheta}``,
each shaped like the parameter: a thin layer over the differentiable solve
(:mod:`jtraj.implicit`, implicit differentiation of the KKT conditions at the optimum,
never differentiation through the iterations). It is ``jax.jacrev`` of the optimal cost
and time of :func:`jtraj.solve` with the parameter substituted into the robot by
``eqx.tree_at``; see :mod:`jtraj.implicit` for the mathematics (active set, bordered KKT
system, weakly active constraints).

The derivative is that of the active set at the optimum (:mod:`jtraj.implicit`), so it is
as precise as the optimum: :func:`sensitivity` refines the first solve's optimum as
:func:`jtraj.implicit.refine` does (:func:`jtraj.implicit.refinement_stage`) and
differentiates the last stage's solve, warm-started at the point before it. Where the
interior-point method applies, the stages are :data:`jtraj.implicit.REFINE_IP` and
:data:`jtraj.implicit.REFINE_IP_TIGHT` (tolerances 1e-11); where the second does not
converge, and elsewhere, the last stage is the augmented-Lagrangian method at tolerances
1e-10 (:data:`REFINE`). (Where a converged optimum's active set does not give a valid
derivative, the derivative rule itself refines it the same way.)

Parameters are the robot's numeric parameters, arrays and scalars (``masses``,
``lengths``, ``inertias``, ``com``, ``gravity_accel``, ...) and its limit fields
(``tau_max``, ``qd_max``, ``qdd_max``, ``h_min``, ``h_max``, ...); see
:func:`jtraj.robots.parameter_names`. Use float64 (``jax.config.update("jax_enable_x64",
True)``).
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from . import implicit
from ._compile import solver_jit
from .problem import Problem
from .robots import Limits, parameter_names
from .solver import SolverOptions, Status
from .solver.al import run_al as _run
from .solver.core import finish as _finish
from .solver.nlp import NLP as _NLP
from .solver.options import to_options
from .transcription import Transcription

__all__ = ["REFINE", "sensitivity", "solve_with_multipliers"]

#: the solver of the refinement (warm-started at the first solve's optimum) at whose
#: optimum :func:`sensitivity` differentiates: the derivative rule's own
#: (:data:`jtraj.implicit.REFINE`)
REFINE = implicit.REFINE

# ----------------------------------------------------------------------------------------
# solving with the final multipliers exposed


@solver_jit
def _solve_state(problem: Problem, opts: SolverOptions, transcription: str, init):
    from .initial_guess import GUESSES

    tr = Transcription(transcription)
    layout = tr.layout(problem)
    nlp = _NLP(problem=problem, tr=tr, layout=layout, sd=tr.stage_data(problem))
    if init is None:
        v0, h0 = GUESSES[opts.guess](problem)
        u0 = tr.initial_controls(problem, v0, h0)
    else:
        u0, h0 = init
    z0 = jnp.clip(layout.pack(u0, h0), layout.z_lo, layout.z_hi)
    valid = jnp.all(jnp.isfinite(z0)) & jnp.all(jnp.isfinite(problem.q_start)) & jnp.all(jnp.isfinite(problem.q_goal))
    z0 = jnp.where(valid, z0, jnp.clip(jnp.zeros_like(z0), layout.z_lo, layout.z_hi))
    s = _run(nlp, z0, opts)
    sol = _finish(nlp, s, opts, valid)
    return sol, s.mult, s.mu


def solve_with_multipliers(problem: Problem, *, solver=None, transcription: str = "decoupled", init=None,
                           options: SolverOptions | None = None):
    """Solve like :func:`jtraj.solve` (the augmented-Lagrangian loop of ``solver``,
    :class:`jtraj.AugmentedLagrangian` or the fallback of an :class:`jtraj.IPM` or
    :class:`jtraj.Auto`; ``options``, a :class:`jtraj.SolverOptions`, is deprecated) and
    also return the solver's final multipliers.

    Returns ``(solution, multipliers, mu)``: ``multipliers`` is the solver's
    ``Multipliers(eq, ineq, glob)`` after its last outer update (so they are the
    Lagrange multipliers at the optimum, ``lambda_old + mu c``), ``mu`` the final penalty.
    """
    tr = Transcription(transcription)
    from .solver.api import solver_argument

    solver = solver_argument(solver, options)
    opts = SolverOptions() if solver is None else to_options(solver)
    if init is not None:
        u, h = jnp.asarray(init[0], float), jnp.asarray(init[1], float)
        m_u = tr.control_dim(problem)
        if u.shape != (problem.N, m_u) or h.shape != (problem.N,):
            raise ValueError(f"init must be (u ({problem.N}, {m_u}), h ({problem.N},)), got {u.shape}, {h.shape}")
        init = (u, h)
    return _solve_state(problem, opts, tr.name, init)


# ----------------------------------------------------------------------------------------
# the parameter as a traced value


def accepted_parameters(problem: Problem) -> list[str]:
    """Parameter names :func:`sensitivity` accepts for this problem's robot: numeric
    parameters of the robot (arrays and scalars) and limit fields that are set (not
    None), all finite."""
    robot = problem.robot
    limit_fields = {f.name for f in dataclasses.fields(Limits)}
    out = []
    for name in parameter_names(robot):
        value = getattr(robot.limits, name) if name in limit_fields else getattr(robot, name, None)
        if value is None:
            continue
        try:
            arr = np.asarray(value, dtype=float)
        except (TypeError, ValueError):
            continue
        if np.all(np.isfinite(arr)):
            out.append(name)
    return out


def _getter(name: str):
    limit_fields = {f.name for f in dataclasses.fields(Limits)}
    if name in limit_fields:
        return lambda p: getattr(p.robot.limits, name)
    return lambda p: getattr(p.robot, name)


def _with_param(problem: Problem, name: str, theta):
    return eqx.tree_at(_getter(name), problem, theta, is_leaf=lambda x: x is None)


# ----------------------------------------------------------------------------------------
# the sensitivity


def sensitivity(problem: Problem, wrt: str = "masses", *, solution=None, solver=None,
                transcription: str = "decoupled", details: bool = False, options=None) -> dict:
    """Derivatives of the optimal cost and the optimal time with respect to a robot
    parameter, by implicit differentiation of the KKT conditions at the optimum
    (:mod:`jtraj.implicit`).

    Args:
        problem: a :class:`jtraj.Problem`.
        wrt: a robot parameter name: a numeric parameter of the robot, an array or a
            scalar (``"masses"``, ``"lengths"``, ``"platform_mass"``,
            ``"gravity_accel"``, ...), or a limit field (``"tau_max"``, ...).
        solution: optional converged :class:`jtraj.Solution` of ``problem`` (same
            transcription); it warm-starts the solve.
        solver: the solver of that solve: :class:`jtraj.Auto` (None: the default),
            :class:`jtraj.IPM` or :class:`jtraj.AugmentedLagrangian`. Its optimum is
            then refined (warm-started; the module doc), and the derivatives are those
            of the refined optimum.
        transcription: "decoupled" (default) or another transcription.
        details: also return the chain-rule cost derivative (``"cost_chain"``, through
            the implicit tangent; ``"cost"`` is the envelope theorem's, see
            :func:`jtraj.implicit.envelope`: they agree at a KKT point), the active
            set's sizes (``"kkt_size"``, ``"n_active"``, ``"n_bound"``) and the solution.
        options: deprecated, a :class:`jtraj.SolverOptions` (as in :func:`jtraj.solve`);
            pass ``solver=`` instead.

    Returns:
        ``{"cost": dJ*/dtheta, "T": dT*/dtheta}``, numpy arrays shaped like the
        parameter (plus the details).

    Raises:
        ValueError: unknown parameter name (the message lists the accepted ones), or
            the solve or its refinement did not converge (sensitivities need a converged
            KKT point), or the derivative at the refined optimum is not valid.
    """
    from .solver import solve
    from .solver.api import solver_argument

    solver = solver_argument(solver, options)
    if not isinstance(problem, Problem):
        raise ValueError(f"problem must be a jtraj.Problem, got {type(problem).__name__}")
    tr = Transcription(transcription)
    accepted = accepted_parameters(problem)
    if not isinstance(wrt, str) or wrt not in accepted:
        raise ValueError(f"unknown parameter {wrt!r} for robot {problem.robot.name!r}; "
                         f"sensitivity accepts one of {accepted}")
    # the parameter as a float array: a Python float (a scalar field such as a platform's
    # mass) would be static to the solves and absent from the envelope's gradient
    theta0 = jnp.asarray(_getter(wrt)(problem), dtype=float)
    problem = _with_param(problem, wrt, theta0)
    if solution is not None and not bool(np.asarray(solution.converged)):
        raise ValueError(f"the given solution did not converge (status {Status(int(solution.status)).name}); "
                         "sensitivities need a converged KKT point")
    init = None if solution is None else (tr.controls_of(solution), solution.h)
    sol = solve(problem, solver=solver, transcription=tr.name, init=init)
    if not bool(sol.converged):
        raise ValueError(f"the solve did not converge (status {Status(int(sol.status)).name}: "
                         f"{Status(int(sol.status)).message}); sensitivities need a converged KKT point")
    # the optimum to the derivative's precision (the module doc): the refined solve, warm at
    # the first one's optimum, is the one differentiated (the stages of
    # jtraj.implicit.refine; the AL method, whose tolerance 1e-10 can take thousands of
    # iterations, only where the interior-point stages do not apply or do not converge)
    last, warm, _ = implicit.refinement_stage(problem, tr.name, (tr.controls_of(sol), sol.h))
    last_name = ("REFINE_IP_TIGHT: the interior-point method at 1e-11" if last is implicit.REFINE_IP_TIGHT
                 else "REFINE: the AL method at tolerances 1e-10")

    def optimum(theta):
        s = solve(_with_param(problem, wrt, theta), solver=last, transcription=tr.name, init=warm)
        return {"cost": s.cost, "T": s.T}, s

    jac, sol = jax.jacrev(optimum, has_aux=True)(theta0)
    if not bool(sol.converged):
        raise ValueError(f"the refinement of the optimum ({last_name}) did not converge (status "
                         f"{Status(int(sol.status)).name}); sensitivities need a converged KKT point")
    if int(sol.status) == Status.CONVERGED_NO_DERIVATIVE:
        raise ValueError("the optimum's derivative is not valid (status CONVERGED_NO_DERIVATIVE: a degenerate "
                         "active set or a singular KKT system at the refined optimum)")
    env, counts = _envelope(problem, tr, sol)
    result = {"cost": np.asarray(_getter(wrt)(env)).reshape(theta0.shape),
              "T": np.asarray(jac["T"]).reshape(theta0.shape)}
    if details:
        result["cost_chain"] = np.asarray(jac["cost"]).reshape(theta0.shape)
        result.update({k: int(v) for k, v in counts.items()})
        result["solution"] = sol
    return result


@eqx.filter_jit
def _envelope(problem, tr, sol):
    return implicit.envelope(problem, tr, sol)
