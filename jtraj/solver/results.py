"""The outcome of a solve: status codes and the :class:`Solution`."""

from __future__ import annotations

import enum

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array



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
    CONVERGED_NO_DERIVATIVE = 7

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
    Status.CONVERGED_NO_DERIVATIVE: "converged, but the derivative at the optimum is not valid (a degenerate active set "
                                    "or a singular KKT system, also after refinement); reported by a differentiated "
                                    "solve only, see jtraj.implicit",
}


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
            ``verify_tol`` (relative) and the goal within ``verify_tol`` (a differentiated
            solve reports such a solution ``CONVERGED_NO_DERIVATIVE`` where its
            derivative is not valid, with ``converged`` True);
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
