"""gough_stewart (Khoukhi ch. 4, the general 6-DOF model): a platform move under time 1 /
energy 0.1, without and with an orientation passage ``||vect(R^T R_l)|| <= eps_l``;
leg lengths, leg speeds and leg forces against their bounds, and the singularity
measure along the way. Both moves are also solved with the force bound at both ends of
every interval (``efforts="intervals"``), and every solve reports its largest leg force
between samples (``intersample_effort``).

Every try of every solve is saved as it ends (:class:`run_all.SolveCache`), so a run cut
short resumes where it stopped.

Writes examples/figures/gough_stewart_move.png, examples/status/gough_stewart.json and the
"gough_stewart" section of examples/RESULTS.md.
Run: python examples/gough_stewart.py [--resume] (keep the tries a run cut short saved,
solve the rest; with every try saved it only redraws and rewrites the section)
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from run_all import (publish, FIGURES, SolveCache, setup, solve_with_restart, status_record, status_text,  # noqa: E402
                     table)

setup()

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jtraj  # noqa: E402
from jtraj import plotting  # noqa: E402
from jtraj.problem import orientation_error  # noqa: E402
from jtraj.robots.gough_stewart import rpy_matrix  # noqa: E402

NAME = "gough_stewart"
# the platform rises 0.1 m, moves 0.18 m sideways and turns by (0.1, -0.1, 0.2) rad
Q_START = (0.0, 0.0, 1.0, 0.0, 0.0, 0.0)
Q_GOAL = (0.15, -0.1, 1.1, 0.1, -0.1, 0.2)
# the passage: orientation (0.1, 0.0, 0.05) rad (roll, pitch, yaw) to eps = 1e-3 at the
# middle sample; its position tolerance (0.5 m) leaves the position free
VIA_POINT = (0.05, 0.0, 1.05)
VIA_RPY = (0.1, 0.0, 0.05)
VIA_EPS = 1e-3
N = 20
WEIGHTS = jtraj.Weights(time=1.0, energy=0.1)


def dense(sol, per_interval=10):
    """(t, q, qd) of the executed constant-acceleration motion, ``per_interval`` points per interval."""
    q, qd, v, h = (np.asarray(a) for a in (sol.q, sol.qd, sol.v, sol.h))
    s = np.linspace(0.0, 1.0, per_interval, endpoint=False)
    qs = [q[k] + (s * h[k])[:, None] * qd[k] + 0.5 * ((s * h[k]) ** 2)[:, None] * v[k] for k in range(len(h))]
    qds = [qd[k] + (s * h[k])[:, None] * v[k] for k in range(len(h))]
    t = np.concatenate([np.sum(h[:k]) + s * h[k] for k in range(len(h))] + [[np.sum(h)]])
    return t, np.concatenate(qs + [q[-1:]]), np.concatenate(qds + [qd[-1:]])


def leg_profiles(robot, sol):
    t, q, qd = dense(sol)
    rho = np.asarray(jax.vmap(robot.leg_lengths)(jnp.asarray(q)))
    J = np.asarray(jax.vmap(robot.actuator_jacobian)(jnp.asarray(q)))
    rhod = np.einsum("kij,kj->ki", J, qd)
    manip = np.asarray(jax.vmap(robot.manipulability)(jnp.asarray(q)))
    t_s = np.concatenate([[0.0], np.cumsum(np.asarray(sol.h))])[:-1]
    return t, rho, rhod, manip, t_s, np.asarray(sol.tau)


def main(resume=False):
    t_start = time.perf_counter()
    cache = SolveCache(NAME, resume=resume)
    if cache.resumed:
        print("resumed:", [k for k in cache.data if k not in ("seconds", "cpu")], flush=True)
    robot = jtraj.robots.get(NAME)
    R_l = jnp.asarray(rpy_matrix(jnp.asarray(VIA_RPY)))
    # the free move carries the same passage with an inactive tolerance (0.999: any
    # orientation within about 87 degrees), so that both moves share one compiled solver
    free = jtraj.Problem(robot, jnp.asarray(Q_START), jnp.asarray(Q_GOAL), N=N, weights=WEIGHTS,
                         via_points=[jtraj.ViaPoint(jnp.asarray(VIA_POINT), tol=0.5, rotation=R_l, rot_tol=0.999)])
    sol, t_first, t_last, tries = solve_with_restart(free, cache=cache, key="free")
    print(f"free move: {status_text(sol, t_last)}, T = {float(sol.T):.4f} s, first call {t_first:.0f} s", flush=True)
    oriented = jtraj.Problem(robot, jnp.asarray(Q_START), jnp.asarray(Q_GOAL), N=N, weights=WEIGHTS,
                             via_points=[jtraj.ViaPoint(jnp.asarray(VIA_POINT), tol=0.5, rotation=R_l, rot_tol=VIA_EPS)])
    sol2, t2_first, t2_last, tries2 = solve_with_restart(oriented, init=(sol.v, sol.h), cache=cache, key="passage")
    print(f"passage: {status_text(sol2, t2_last)}, T = {float(sol2.T):.4f} s", flush=True)
    k = free.via_samples()[0]
    # the same two moves with the force bound at both ends of every interval, warm-started
    # from the samples-only optima (one more compilation, shared by both)
    solved = {"samples": (sol, sol2)}
    ivals = []
    for move, pr, s0 in (("free", free, sol), ("passage", oriented, sol2)):
        pi = jtraj.Problem(robot, pr.q_start, pr.q_goal, N=N, weights=WEIGHTS, via_points=pr.via_points,
                           efforts="intervals")
        si, ti_first, ti_last, tries_i = solve_with_restart(pi, init=(s0.v, s0.h), cache=cache,
                                                            key=f"{move}, intervals")
        ivals.append((si, ti_first, ti_last, tries_i))
        print(f"intervals: {status_text(si, ti_last)}, T = {float(si.T):.4f} s", flush=True)
    solved["intervals"] = tuple(r[0] for r in ivals)
    records = [status_record(f"{move}, {efforts}", s_, robot) for efforts, pair in solved.items()
               for move, s_ in zip(("free orientation", "passage"), pair)]
    effort = {r["run"]: r["effort_between_samples"] for r in records}

    def via_err(s):
        return float(jnp.linalg.norm(orientation_error(robot.rotation(s.q[k]), R_l)))

    lim = robot.limits
    rho_lo, rho_hi, rhod_max = float(robot.rho_min), float(robot.rho_max), float(robot.rhod_max)
    f_max = float(lim.tau_max[0])
    from matplotlib.figure import Figure

    fig = Figure(figsize=(12, 7.5), layout="constrained")
    axes = fig.subplots(2, 3)
    for col, (s, label) in enumerate(((sol, "free orientation"), (sol2, f"orientation passage (eps {VIA_EPS:g})"))):
        t, rho, rhod, manip, t_s, tau = leg_profiles(robot, s)
        ax = axes[col, 0]
        for j in range(rho.shape[1]):
            ax.plot(t, rho[:, j], color=f"C{j}", label=f"leg {j + 1}")
        for b in (rho_lo, rho_hi):
            ax.axhline(b, ls="--", c="k", lw=0.8)
        ax.set_ylabel("leg length rho_i [m]")
        ax.legend(fontsize=6, ncol=2)
        ax.set_title(f"{label}: T = {float(s.T):.3f} s", fontsize=9)
        ax = axes[col, 1]
        for j in range(rhod.shape[1]):
            ax.plot(t, rhod[:, j], color=f"C{j}")
        for b in (-rhod_max, rhod_max):
            ax.axhline(b, ls="--", c="k", lw=0.8)
        ax.set_ylabel("leg speed [m/s]")
        ax = axes[col, 2]
        for j in range(tau.shape[1]):
            ax.step(t_s, tau[:, j], where="post", color=f"C{j}")
        dense_f = plotting.efforts_between_samples(robot, s)
        if dense_f is not None:
            for j in range(dense_f[1].shape[1]):
                ax.plot(dense_f[0], dense_f[1][:, j], color=f"C{j}", lw=0.6)
        for b in (-f_max, f_max):
            ax.axhline(b, ls="--", c="k", lw=0.8)
        ax.set_ylabel("leg force tau_i [N] (steps: samples; thin: between)")
        ax2 = ax.twinx()
        ax2.plot(t, manip, ":", c="gray")
        ax2.set_ylabel("manipulability |det J D| (1 = home), dotted", fontsize=8)
        ax2.set_ylim(0, 1.5)
        if col == 1:
            for a in axes[col]:
                a.axvline(float(np.sum(np.asarray(s.h)[:k])), c="r", lw=0.6)
        for a in axes[col]:
            a.set_xlabel("t [s]")
    fig.suptitle(f"gough_stewart, N = {N}, time 1 / energy 0.1: {Q_START} -> {Q_GOAL} (m, rad); "
                 f"dashed: bounds; red: the passage", fontsize=10)
    fig.savefig(FIGURES / f"{NAME}_move.png", dpi=110)

    def peak(s):
        _, rho, rhod, manip, _, tau = leg_profiles(robot, s)
        return (f"rho in [{rho.min():.3f}, {rho.max():.3f}] m, |rhod| <= {np.abs(rhod).max():.3f} m/s, "
                f"|tau| <= {np.abs(tau).max():.0f} N, min manipulability {manip.min():.2f}")

    def row(move, s, t_last, key, tries_text):
        return (move, status_text(s, t_last), f"{float(s.T):.3f}", f"{float(s.energy):.4g}", f"{float(s.cost):.5f}",
                f"{float(s.kkt_error):.1e}", f"{float(s.max_violation['overall']):.1e}", f"{via_err(s):.2e}", peak(s),
                f"{effort[key]:.3f}", tries_text)

    rows = [
        row("free orientation", sol, t_last, "free orientation, samples",
            f"{' -> '.join(tries)}; first call {t_first:.0f} s (compilation)"),
        row(f"passage, eps = {VIA_EPS:g}", sol2, t2_last, "passage, samples",
            f"{' -> '.join(tries2)}, warm-started from the free optimum; first call {t2_first:.0f} s"),
    ]
    for move, (si, ti_first, ti_last, tries_i) in zip(("free orientation", f"passage, eps = {VIA_EPS:g}"), ivals):
        key = "free orientation" if move == "free orientation" else "passage"
        rows.append(row(f"{move}, efforts=intervals", si, ti_last, key + ", intervals",
                        f"{' -> '.join(tries_i)}, warm-started from the samples-only optimum; first call "
                        f"{ti_first:.0f} s"))
    tol = jtraj.AugmentedLagrangian().tol_optimality
    named = [("free orientation", sol), ("passage", sol2),
             ("free orientation, efforts=intervals", solved["intervals"][0]),
             ("passage, efforts=intervals", solved["intervals"][1])]
    uncertified = [(m, s) for m, s in named if not bool(s.converged)]
    verdict = ("Every move ends CONVERGED (certified: re-simulated violation within the verification tolerance "
               f"and KKT error below {tol:g})." if not uncertified else
               "Not certified: " + "; ".join(
                   f"{m} ends {jtraj.Status(int(s.status)).name} after a bounded effort (at most two default "
                   f"solves, the second warm-started from the first's end, each within the default iteration limits: "
                   f"interior-point max_iter 150, then the AL fallback's max_iter 500 and restart_iter 600) "
                   f"with KKT error {float(s.kkt_error):.1e} against the target "
                   f"{tol:g} and worst violation {float(s.max_violation['overall']):.1e} (relative for bounds)"
                   for m, s in uncertified)
               + (". Its row is the point" if len(uncertified) == 1 else ". Those rows are the points")
               + " the solver reached, not certified optima.")
    header = ("move", "status", "T [s]", "energy [s]", "cost", "KKT error", "worst violation",
              "||vect(R^T R_l)|| at the passage", "legs", "largest |tau|/tau_max between samples", "tries")
    text = (f"## gough_stewart: 6-DOF Gough-Stewart platform, a move with an orientation passage\n\n"
            f"Robot `gough_stewart` (parameters chosen here, the thesis publishes none: base radius 1.0 m, platform "
            f"radius 0.5 m, base joints at 120 k +- 15 deg, platform joints at 120 k +- 45 deg; platform 50 kg "
            f"(uniform disc), legs 5 kg each (cylinder 3 kg + piston 2 kg, 0.8 m each); gravity along -z; "
            f"leg lengths in [{rho_lo:g}, {rho_hi:g}] m, leg speeds <= {rhod_max:g} m/s, leg forces <= {f_max:g} N; "
            f"pose box x, y in [-0.3, 0.3] m, z in [0.8, 1.3] m, roll/pitch/yaw in [-0.5, 0.5] rad; |qd| <= 0.5, "
            f"|qdd| <= 5 per pose coordinate; h in [0.005, 0.1] s; manipulability |det(J D)| / its home value "
            f">= 0.2). Generalised coordinates: the platform pose (x, y, z, roll, pitch, yaw), R = Rz Ry Rx. "
            f"Move {Q_START} -> {Q_GOAL}, N = {N}, time 1 / energy 0.1, decoupled transcription, default solver "
            f"options. The passage imposes the orientation roll/pitch/yaw = {VIA_RPY} rad at sample {k} to "
            f"||vect(R^T R_l)|| <= {VIA_EPS:g} (the thesis' orientation passage; its position tolerance, 0.5 m, is "
            f"inactive). Figure: `figures/{NAME}_move.png` (leg lengths, speeds and forces against their bounds, "
            f"in m, m/s and N; forces: steps at the samples, thin lines between them). The `efforts=intervals` "
            f"rows bound the leg forces at both ends of every interval as well. Seconds in a status are the "
            f"wall time of that call on a shared, loaded 2-core machine.\n\n" + table(rows, header=header)
            + "\n\n" + verdict)
    publish(NAME, text, records, t_start, cache=cache)


if __name__ == "__main__":
    main(resume="--resume" in sys.argv[1:])
