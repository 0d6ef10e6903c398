"""The acceptance check of the differentiable solve, end to end, on serial3 (float64).

    python benchmarks/check_grad.py [--N 10] [--step 1e-4] [--json PATH]

1. ``jax.jacobian`` (reverse mode) of T, the cost and q with respect to q_goal, the
   weights (time, energy) and the link masses through ``jtraj.solve``, against central
   differences of independent re-solves (each a cold ``jtraj.solve`` of a concrete
   problem: no warm start, no state shared with the derivative).
2. The same Jacobians through ``jtraj.solve_batch`` on a batch of three goals (T per
   sample against each goal, T against the masses and the weights shared by the batch),
   against central differences of cold ``solve_batch`` re-solves.
3. ``jax.vmap(jax.grad(...))`` of a single solve's T over the batch's goals against the
   batch's per-sample gradients.
4. A batch with an unconverged sample (a T_max 0.9 of its optimal time): its gradient is zero, its
   status says why, ``valid_derivatives`` is False for it only, the others' gradients
   equal their single-solve gradients.

Errors are printed relative to the largest entry of the finite-difference block (the
per-block scale), with the re-solves' tolerance 1e-10 (AL); the figures go to ``--json``.
"""

from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--N", type=int, default=10)
    ap.add_argument("--step", type=float, default=1e-4)
    ap.add_argument("--json", default="")
    args = ap.parse_args(argv)

    from jtraj.cli import setup_jax

    setup_jax(x64=True)
    import jax
    import jax.numpy as jnp

    import jtraj
    from jtraj.implicit import valid_derivatives

    N, step = args.N, args.step
    robot0 = jtraj.robots.get("serial3")
    start = np.array([0.2, -0.3, 0.4])
    goal = np.array([0.3, -0.2, 0.3])  # a short move: N = 10 periods of h_max = 0.1 s leave room
    goals = np.stack([goal, goal + np.array([0.05, -0.02, 0.01]), goal + np.array([-0.04, 0.03, 0.02])])
    tight = jtraj.AugmentedLagrangian(tol_feasibility=1e-10, tol_optimality=1e-10, max_iter=2000)
    theta0 = np.r_[goal, 1.0, 0.1, np.asarray(robot0.masses)]  # q_goal (3), time, energy, masses (3)
    groups = {"q_goal": slice(0, 3), "weights": slice(3, 5), "masses": slice(5, 8)}
    figures, t0 = {"N": N, "step": step}, time.perf_counter()

    def problem(theta, q_goal=None):
        robot = jtraj.robots.get("serial3", masses=theta[5:8])
        return jtraj.Problem(robot, start, theta[0:3] if q_goal is None else q_goal, N=N,
                             weights=jtraj.Weights(time=theta[3], energy=theta[4]))

    def outputs(sol):
        return {"T": sol.T, "cost": sol.cost, "q": sol.q}

    def block_errors(jac, fd):
        out = {}
        for o in ("T", "cost", "q"):
            for g, sl in groups.items():
                a = np.asarray(jac[o])[..., sl]
                b = np.asarray(fd[o])[..., sl]
                out[f"d{o}/d{g}"] = float(np.max(np.abs(a - b)) / max(np.max(np.abs(b)), 1e-12))
        return out

    def steps(theta):  # absolute for the goal [rad], relative otherwise
        return np.where(np.arange(theta.size) < 3, step, step * np.abs(theta))

    # ---- 1. jacobian through solve -------------------------------------------------------
    jac = jax.jacobian(lambda th: outputs(jtraj.solve(problem(th), solver=tight)))(jnp.asarray(theta0))
    cols = {o: [] for o in ("T", "cost", "q")}
    hs = steps(theta0)
    for i in range(theta0.size):
        vals = []
        for sign in (1.0, -1.0):
            th = theta0.copy()
            th[i] += sign * hs[i]
            s = jtraj.solve(problem(th), solver=tight)
            assert bool(s.converged), s.status_message
            vals.append({k: np.asarray(v) for k, v in outputs(s).items()})
        for o in cols:
            cols[o].append((vals[0][o] - vals[1][o]) / (2 * hs[i]))
    fd = {o: np.stack(c, axis=-1) for o, c in cols.items()}
    figures["solve"] = block_errors(jac, fd)
    print(f"1. jax.jacobian through jtraj.solve vs central differences of cold re-solves (step {step:g}), "
          f"max error / block scale ({time.perf_counter() - t0:.0f} s):", flush=True)
    for k, v in figures["solve"].items():
        print(f"   {k:16s} {v:.2e}")

    # ---- 2. jacobian through solve_batch ------------------------------------------------
    B = goals.shape[0]
    w0 = jtraj.Weights(time=1.0, energy=0.1)

    def batch_T(theta, g):
        robot = jtraj.robots.get("serial3", masses=theta[5:8])
        s = jtraj.solve_batch(robot, np.broadcast_to(start, g.shape), g, N=N,
                              weights=jtraj.Weights(time=theta[3], energy=theta[4]), solver=tight, slots=None)
        return s.T

    J_th, J_g = jax.jacobian(batch_T, argnums=(0, 1))(jnp.asarray(theta0), jnp.asarray(goals))
    J_g = np.asarray(J_g)  # (B, B, 3): the sample's T against each sample's goal
    fd_th, fd_g = [], np.zeros((B, B, 3))
    for i in range(3, theta0.size):
        vals = []
        for sign in (1.0, -1.0):
            th = theta0.copy()
            th[i] += sign * hs[i]
            vals.append(np.asarray(batch_T(th, goals)))
        fd_th.append((vals[0] - vals[1]) / (2 * hs[i]))
    fd_th = np.stack(fd_th, axis=-1)
    for b in range(B):
        for j in range(3):
            vals = []
            for sign in (1.0, -1.0):
                g = goals.copy()
                g[b, j] += sign * step
                vals.append(np.asarray(batch_T(theta0, g)))
            fd_g[:, b, j] = (vals[0] - vals[1]) / (2 * step)
    J_th = np.asarray(J_th)[:, 3:]
    off_diag = float(np.max(np.abs(J_g[~np.eye(B, dtype=bool)])))
    figures["solve_batch"] = {
        "dT/dq_goal": float(np.max(np.abs(J_g - fd_g)) / np.max(np.abs(fd_g))),
        "dT/dweights": float(np.max(np.abs(J_th[:, :2] - fd_th[:, :2])) / np.max(np.abs(fd_th[:, :2]))),
        "dT/dmasses": float(np.max(np.abs(J_th[:, 2:] - fd_th[:, 2:])) / np.max(np.abs(fd_th[:, 2:]))),
        "off_diagonal_max": off_diag,
    }
    print(f"2. jax.jacobian of T through jtraj.solve_batch (B = {B}) vs central differences of cold batch "
          f"re-solves ({time.perf_counter() - t0:.0f} s):", flush=True)
    for k, v in figures["solve_batch"].items():
        print(f"   {k:16s} {v:.2e}")

    # ---- 3. vmap(grad) ----------------------------------------------------------------------
    def one_T(g):
        return jtraj.solve(jtraj.Problem(robot0, start, g, N=N, weights=w0), solver=tight).T

    vg = np.asarray(jax.vmap(jax.grad(one_T))(jnp.asarray(goals)))
    diag = np.stack([J_g[b, b] for b in range(B)])
    figures["vmap_grad_vs_batch"] = float(np.max(np.abs(vg - diag)) / np.max(np.abs(diag)))
    figures["vmap_grad_vs_fd"] = float(np.max(np.abs(vg - np.stack([fd_g[b, b] for b in range(B)])))
                                       / np.max(np.abs(diag)))
    print(f"3. vmap(grad(T of one solve)) vs the batch's per-sample gradients: "
          f"{figures['vmap_grad_vs_batch']:.2e}; vs the differences: {figures['vmap_grad_vs_fd']:.2e} "
          f"({time.perf_counter() - t0:.0f} s)", flush=True)

    # ---- 4. an unconverged sample in a batch ---------------------------------------------
    # the third sample's T_max 0.9 of its optimal time: above the face check's lower bound on
    # the time (the problem is accepted), below what the dynamics allow (the solve fails)
    T3 = float(np.asarray(batch_T(theta0, goals))[2])
    T_max = np.array([np.inf, np.inf, 0.9 * T3])

    def total_T(g):
        s = jtraj.solve_batch(robot0, np.broadcast_to(start, g.shape), g, N=N, weights=w0, T_max=T_max,
                              solver=tight, slots=None)
        return jnp.sum(jnp.where(valid_derivatives(s), s.T, 0.0)), s

    (_, sol), grad = jax.value_and_grad(total_T, has_aux=True)(jnp.asarray(goals))
    grad = np.asarray(grad)
    mask = np.asarray(valid_derivatives(sol)).tolist()
    figures["unconverged"] = {
        "valid": mask, "status": [jtraj.Status(int(s)).name for s in np.asarray(sol.status)],
        "zero_gradient_on_invalid": bool(np.all(grad[~np.asarray(mask)] == 0)),
        "finite": bool(np.all(np.isfinite(grad))),
        "valid_vs_batch": float(np.max(np.abs(grad[:2] - diag[:2])) / np.max(np.abs(diag[:2]))),
    }
    print(f"4. batch with T_max = {T_max.tolist()}: valid {mask}, status {figures['unconverged']['status']}, "
          f"gradient of the invalid sample all zero: {figures['unconverged']['zero_gradient_on_invalid']}, "
          f"all finite: {figures['unconverged']['finite']}, valid samples vs the unconstrained batch's "
          f"gradients: {figures['unconverged']['valid_vs_batch']:.2e} ({time.perf_counter() - t0:.0f} s)", flush=True)
    figures["seconds"] = time.perf_counter() - t0
    if args.json:
        os.makedirs(os.path.dirname(os.path.abspath(args.json)), exist_ok=True)
        with open(args.json, "w") as f:
            json.dump(figures, f, indent=1)
        print(f"figures written to {args.json}")


if __name__ == "__main__":
    main()
