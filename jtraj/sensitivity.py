"""Sensitivities of an optimal trajectory with respect to robot parameters.

``sensitivity(problem, wrt="masses")`` returns ``{"cost": dJ*/dtheta, "T": dT*/dtheta}``,
each shaped like the parameter, by **implicit differentiation of the optimality
conditions** at the solver's optimum (never by differentiating through the iterations).

Method. The solver (see :mod:`jtraj.solver`) minimises ``f(z)`` subject to equalities
``c(z) = 0``, inequalities ``g(z) <= 0`` (augmented Lagrangian, PHR) and simple bounds
``lo <= z <= hi`` on the scaled controls and periods (kept by projection). At a
converged point ``z*`` the final multipliers ``lambda`` (equalities) and ``rho >= 0``
(inequalities) of the solver's last outer update, ``lambda_old + mu c(z*)``, satisfy the
KKT conditions of the Lagrangian ``L = f + lambda . c + rho . g``. We

1. fix the active set: every equality row that is not identically zero, every
   inequality whose multiplier is positive, every simple bound that ``z*`` touches;
2. differentiate the KKT system ``grad_free L(z, lambda, theta) = 0``,
   ``c_A(z, theta) = 0`` (bound-fixed variables follow their bound) in ``theta``::

       [ H_ff   J_Af^T ] [dz_f]     [ d/dtheta grad_f L + H_fb dz_b ]
       [ J_Af     0    ] [dlam] = - [ d/dtheta c_A      + J_Ab dz_b ]

   with ``H = d2L/dz2`` (exact, autodiff) and ``J_A`` the active constraint Jacobian;
3. form ``dJ*/dtheta`` twice: by the envelope theorem (partial derivative of the
   Lagrangian plus the bound terms) and by the chain rule ``df/dtheta + grad f . dz``.
   They agree at a KKT point; the returned value is the envelope one, the chain-rule
   value and their difference are available with ``details=True``.
   ``dT*/dtheta = sum_k dh_k/dtheta``.

Why the bordered system and not the AL Hessian alone: with the multipliers held fixed
the AL stationarity ``grad f + J^T (lambda_old + mu c) = 0`` has the Hessian
``H_L + mu J^T J`` (the Lagrangian Hessian at the final multipliers plus the penalty
term), but its root moves with ``theta`` as the solution of the *regularised* system
``J dz + dc/dtheta = dlambda / mu``; that is exact only as mu -> infinity (error
O(1/mu), and the default schedule stops raising mu as soon as it is feasible). The
bordered KKT system has no such error.

Parameters are the robot's array parameters (``masses``, ``lengths``, ``inertias``,
``com``, ...) and its limit fields (``tau_max``, ``qd_max``, ``qdd_max``, ``h_min``,
``h_max``, ...); see :func:`jtraj.robots.parameter_names`. Use float64
(``jax.config.update("jax_enable_x64", True)``).
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._compile import solver_jit
from .problem import Problem
from .robots import Limits, parameter_names
from .solver import _NLP, SolverOptions, Status, _finish, _run
from .transcription import Transcription

__all__ = ["sensitivity", "solve_with_multipliers"]

_BOUND_TOL = 1e-9


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


def solve_with_multipliers(problem: Problem, *, options: SolverOptions | None = None,
                           transcription: str = "decoupled", init=None):
    """Solve like :func:`jtraj.solve` and also return the solver's final multipliers.

    Returns ``(solution, multipliers, mu)``: ``multipliers`` is the solver's
    ``Multipliers(eq, ineq, glob)`` after its last outer update (so they are the
    Lagrange multipliers at the optimum, ``lambda_old + mu c``), ``mu`` the final penalty.
    """
    tr = Transcription(transcription)
    opts = SolverOptions() if options is None else options
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
    """Parameter names :func:`sensitivity` accepts for this problem's robot: array
    parameters of the robot and limit fields that are set (not None)."""
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


def _flat(tree):
    leaves = jax.tree.leaves(tree)
    return jnp.concatenate([jnp.ravel(x) for x in leaves]) if leaves else jnp.zeros(0)


# ----------------------------------------------------------------------------------------
# the sensitivity


def sensitivity(problem: Problem, wrt: str = "masses", *, solution=None, options: SolverOptions | None = None,
                transcription: str = "decoupled", details: bool = False) -> dict:
    """Derivatives of the optimal cost and the optimal time with respect to a robot
    parameter, by implicit differentiation of the KKT conditions at the optimum.

    Args:
        problem: a :class:`jtraj.Problem`.
        wrt: a robot parameter name: an array parameter of the robot (``"masses"``,
            ``"lengths"``, ``"inertias"``, ...) or a limit field (``"tau_max"``, ...).
        solution: optional converged :class:`jtraj.Solution` of ``problem`` (same
            transcription); it warm-starts the solve that recovers the multipliers.
        options: :class:`jtraj.SolverOptions` of that solve.
        transcription: "decoupled" (default) or "coupled".
        details: also return diagnostics (chain-rule cost derivative, KKT residuals,
            active-set sizes, the solution).

    Returns:
        ``{"cost": dJ*/dtheta, "T": dT*/dtheta}``, numpy arrays shaped like the
        parameter (plus diagnostics with ``details=True``).

    Raises:
        ValueError: unknown parameter name (the message lists the accepted ones), or
            the solve did not converge (sensitivities need a converged KKT point).
    """
    if not isinstance(problem, Problem):
        raise ValueError(f"problem must be a jtraj.Problem, got {type(problem).__name__}")
    tr = Transcription(transcription)
    accepted = accepted_parameters(problem)
    if not isinstance(wrt, str) or wrt not in accepted:
        raise ValueError(f"unknown parameter {wrt!r} for robot {problem.robot.name!r}; "
                         f"sensitivity accepts one of {accepted}")
    if solution is not None and not bool(np.asarray(solution.converged)):
        raise ValueError(f"the given solution did not converge (status {Status(int(solution.status)).name}); "
                         "sensitivities need a converged KKT point")
    init = None
    if solution is not None:
        init = (tr.controls_of(solution), solution.h)
    sol, mult, mu = solve_with_multipliers(problem, options=options, transcription=tr.name, init=init)
    if not bool(sol.converged):
        raise ValueError(f"the solve did not converge (status {Status(int(sol.status)).name}: "
                         f"{Status(int(sol.status)).message}); sensitivities need a converged KKT point")

    theta0 = jnp.asarray(_getter(wrt)(problem), dtype=float)
    shape = theta0.shape
    out = _implicit(problem, tr, wrt, theta0, sol, mult)
    result = {"cost": out["cost_envelope"].reshape(shape), "T": out["T"].reshape(shape)}
    if details:
        result.update({k: (v.reshape(shape) if k in ("cost_chain", "cost_envelope") else v)
                       for k, v in out.items() if k not in ("T",)})
        result["solution"] = sol
        result["mu"] = float(mu)
    return result


def _implicit(problem, tr, wrt, theta0, sol, mult):
    flat_theta0 = jnp.ravel(theta0)
    u = tr.controls_of(sol)
    layout0 = tr.layout(problem)
    z = layout0.pack(u, sol.h)
    lam = _flat(mult)
    (gL, H, dgL_dth, Jc, dc_dth, gf, df_dth, dL_dth, dbounds, gT, dT_dth, c, n_eq) = _pieces(
        problem, tr.name, wrt, z, flat_theta0, lam)
    gL, H, dgL_dth, Jc, dc_dth, gf, df_dth, dL_dth, dbounds, gT, dT_dth, c = map(
        np.asarray, (gL, H, dgL_dth, Jc, dc_dth, gf, df_dth, dL_dth, dbounds, gT, dT_dth, c))
    lam = np.asarray(lam)
    is_eq = np.arange(c.shape[0]) < int(n_eq)

    lo, hi = np.asarray(layout0.z_lo), np.asarray(layout0.z_hi)
    zn = np.asarray(z)
    at_lo, at_hi = zn <= lo + _BOUND_TOL, zn >= hi - _BOUND_TOL
    fixed = at_lo | at_hi
    free = ~fixed
    row_norm = np.linalg.norm(Jc, axis=1)
    lam_scale = max(1.0, float(np.max(np.abs(lam), initial=0.0)))
    active = np.where(is_eq, row_norm > 0, (lam > 1e-9 * lam_scale) & (row_norm > 0))

    p = flat_theta0.shape[0]
    dz_b = np.where(at_lo[:, None], dbounds[0], 0.0) + np.where(at_hi[:, None], dbounds[1], 0.0)  # (nz, p)
    dz_b = np.where(fixed[:, None], dz_b, 0.0)
    Hff = H[np.ix_(free, free)]
    JA = Jc[active]
    JAf = JA[:, free]
    nf, na = Hff.shape[0], JAf.shape[0]
    K = np.block([[Hff, JAf.T], [JAf, np.zeros((na, na))]])
    rhs = -np.concatenate([dgL_dth[free] + H[np.ix_(free, fixed)] @ dz_b[fixed],
                           dc_dth[active] + JA[:, fixed] @ dz_b[fixed]], axis=0)
    sol_kkt, _, rank, sv = np.linalg.lstsq(K, rhs, rcond=None)
    dz = dz_b.copy()
    dz[free] = sol_kkt[:nf]

    cost_chain = df_dth + gf @ dz
    cost_envelope = dL_dth + gL[fixed] @ dz_b[fixed]
    T = dT_dth + gT @ dz
    return {
        "cost_envelope": cost_envelope, "cost_chain": cost_chain, "T": T, "dz": dz.reshape(-1, p),
        "stationarity": float(np.max(np.abs(gL[free]), initial=0.0)),
        "active_violation": float(np.max(np.abs(c[active]), initial=0.0)),
        "kkt_residual": float(np.max(np.abs(K @ sol_kkt - rhs), initial=0.0)),
        "kkt_rank": int(rank), "kkt_size": int(K.shape[0]),
        "kkt_condition": float(sv[0] / sv[-1]) if sv.size and sv[-1] > 0 else float("inf"),
        "n_free": int(nf), "n_active": int(na), "n_bound": int(fixed.sum()),
    }


@solver_jit
def _pieces(problem, tr_name: str, wrt: str, z, th, lam):
    """Every derivative the KKT sensitivity needs, at (z, theta) with multipliers lam."""
    tr = Transcription(tr_name)
    shape = _getter(wrt)(problem).shape if hasattr(_getter(wrt)(problem), "shape") else ()

    def nlp_of(t):
        p = _with_param(problem, wrt, t.reshape(shape))
        layout = tr.layout(p)
        return _NLP(problem=p, tr=tr, layout=layout, sd=tr.stage_data(p))

    def cons(zz, t):
        return _flat(nlp_of(t).constraints(zz))

    def cost(zz, t):
        return sum(nlp_of(t).cost_terms(zz).values())

    def lagr(zz, t, ll):
        return cost(zz, t) + jnp.dot(ll, cons(zz, t))

    def bounds(t):
        lay = nlp_of(t).layout
        return jnp.stack([lay.z_lo, lay.z_hi])

    def T_of(zz, t):
        return jnp.sum(nlp_of(t).layout.unpack(zz)[1])

    eq0, _, _ = nlp_of(th).constraints(z)
    n_eq = sum(x.size for x in jax.tree.leaves(eq0))
    return (jax.grad(lagr)(z, th, lam), jax.hessian(lagr)(z, th, lam),
            jax.jacfwd(jax.grad(lagr), argnums=1)(z, th, lam),
            jax.jacfwd(cons)(z, th), jax.jacfwd(cons, argnums=1)(z, th),
            jax.grad(cost)(z, th), jax.grad(cost, argnums=1)(z, th),
            jax.grad(lagr, argnums=1)(z, th, lam), jax.jacfwd(bounds)(th),
            jax.grad(T_of)(z, th), jax.grad(T_of, argnums=1)(z, th), cons(z, th), n_eq)
