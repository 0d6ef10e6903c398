"""wmr (Chettibi et al. example 3; Yamamoto 1999): minimum-time motion of a two-wheel
differential-drive robot from (3, 3, 0) to (23, 23, pi/6) among three circular obstacles,
against the published 17.82 s (simulated annealing) and 18.94 s (reference).

Also solved with the wheel-torque bound at both ends of every interval
(``efforts="intervals"``); both solves report their largest torque between samples.

Writes examples/figures/wmr.png, examples/status/wmr.json and the "wmr" section of
examples/RESULTS.md.
Run: python examples/wmr.py
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from run_all import (publish, FIGURES, setup, solve_with_restart, status_record, status_text, table, # noqa: E402
                     write_status)

setup()

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jtraj  # noqa: E402
from jtraj import plotting  # noqa: E402

NAME = "wmr"
Q_START = (3.0, 3.0, 0.0)
Q_GOAL = (23.0, 23.0, np.pi / 6)
N = 50
# The robot's assumed h_max = 2 s lets the chassis travel up to 4 m between samples, where the
# obstacles are not checked; h_max = 0.5 s bounds that distance to 1 m (the table reports the
# resulting overlap between samples).
H_MAX = 0.5
# minimum time (time weight 1, energy 0)
W_TIME = jtraj.Weights(time=1.0, energy=0.0)


def dense(sol, per_interval=10):
    q, qd, v, h = (np.asarray(a) for a in (sol.q, sol.qd, sol.v, sol.h))
    s = np.linspace(0.0, 1.0, per_interval, endpoint=False)
    pts = [q[k] + (s * h[k])[:, None] * qd[k] + 0.5 * ((s * h[k]) ** 2)[:, None] * v[k] for k in range(len(h))]
    return np.concatenate(pts + [q[-1:]], axis=0)


def clearance(robot, q):
    """Distance from the chassis disc to each obstacle [m], (len(q), k); < 0 = collision."""
    obs = np.asarray(robot.obstacles)
    d = np.linalg.norm(q[:, None, :2] - obs[None, :, :2], axis=-1)
    return d - obs[None, :, 2] - float(robot.body_radius)


def main():
    t_start = time.perf_counter()
    robot = jtraj.robots.get(NAME, h_max=H_MAX)
    tau_max = np.asarray(robot.limits.tau_max)
    pr = jtraj.Problem(robot, jnp.asarray(Q_START), jnp.asarray(Q_GOAL), N=N, weights=W_TIME)
    sol, t_first, t_last, tries = solve_with_restart(pr, restarts=2)
    T = float(sol.T)
    # the same problem with the torque bound at both ends of every interval, warm-started
    pr_i = jtraj.Problem(robot, jnp.asarray(Q_START), jnp.asarray(Q_GOAL), N=N, weights=W_TIME, efforts="intervals")
    sol_i, ti_first, ti_last, tries_i = solve_with_restart(pr_i, init=(sol.v, sol.h), restarts=2)
    records = [status_record("torque bound at the samples", sol, robot),
               status_record("efforts=intervals", sol_i, robot)]
    write_status(NAME, records, t_start)
    q_d = dense(sol)
    clr = clearance(robot, q_d)
    clr_samples = clearance(robot, np.asarray(sol.q))
    lateral = np.abs(np.asarray(jax.vmap(lambda q, qd: robot.constraint_matrix(q) @ qd)(sol.q, sol.qd)))
    sat = np.max(np.abs(np.asarray(sol.tau)) / tau_max, axis=1)
    straight = float(np.hypot(Q_GOAL[0] - Q_START[0], Q_GOAL[1] - Q_START[1]))
    path_len = float(np.sum(np.linalg.norm(np.diff(q_d[:, :2], axis=0), axis=1)))
    # bang-bang time of the straight diagonal with the reduced dynamics (obstacles ignored):
    # (m + 2 J_w / r^2) v' = 2 tau_max / r
    m_eff = float(robot.mass) + 2 * float(robot.wheel_inertia) / float(robot.wheel_radius) ** 2
    a_max = min(2 * float(tau_max[0]) / float(robot.wheel_radius) / m_eff, float(robot.limits.qdd_max[0]) * np.sqrt(2))
    T_free = 2 * np.sqrt(straight / a_max)

    fig = plotting.plot_solution(pr, sol, title=f"wmr: minimum time among three obstacles, T = {T:.2f} s "
                                                f"({jtraj.Status(int(sol.status)).name})")
    ax = fig.axes[0]
    from matplotlib.patches import Circle

    for cx, cy, r in np.asarray(robot.obstacles):
        ax.add_patch(Circle((cx, cy), r, color="0.5", alpha=0.5))
        ax.add_patch(Circle((cx, cy), r + float(robot.body_radius), fill=False, ls=":", color="0.3"))
    ax.plot(q_d[:, 0], q_d[:, 1], "-", color="C1", lw=0.8, label="between samples")
    ax.legend(fontsize=7)
    plotting.save(fig, str(FIGURES / f"{NAME}.png"))

    rows = [
        ("minimum time T [s]", f"{T:.3f}", "17.82 (simulated annealing) / 18.94 (reference)",
         f"{100 * (T / 17.82 - 1):+.1f} % / {100 * (T / 18.94 - 1):+.1f} %; robot parameters and obstacle layout "
         f"are not published and ours were chosen so that the free diagonal takes about 17 s, so the closeness "
         f"is by construction and only the order of magnitude is a real comparison"),
        ("status", status_text(sol, t_last) + "; tries " + " -> ".join(tries), "-",
         f"default solver options from the cycloidal guess (straight line through the obstacles), then warm "
         f"re-solves from the result while not certified; first call {t_first:.0f} s incl. compilation"),
        ("parameters; solve time", f"{N * (robot.n + 1)} ({N} intervals x ({robot.n} accelerations + 1 period)); "
         f"{t_last:.0f} s (the last try), {t_first:.0f} s for the first incl. compilation",
         "10 (6 path control points + 4 time-profile points); 4 min",
         "not comparable: another parameterisation (a path spline and a time profile against jtraj's samples), "
         "another solver (simulated annealing) and another machine"),
        ("bang-bang time of the obstacle-free straight line [s]", f"{T_free:.2f}", "-",
         f"{straight:.2f} m at the acceleration of both wheels at +-{tau_max[0]:g} N m "
         f"({a_max:.3f} m/s^2); the obstacles cost {T - T_free:+.2f} s"),
        ("path length [m]", f"{path_len:.2f}", "-", f"straight line {straight:.2f} m"),
        ("min clearance to the obstacles: samples / between samples [m]",
         f"{np.min(clr_samples):.3f} / {np.min(clr):.3f}", "-",
         f"obstacles enforced at the samples only (path_constraints); between samples the chassis may cut a "
         f"corner (negative = overlap); h_max = {H_MAX:g} s (instead of the robot's 2 s) bounds the distance "
         f"travelled between two samples"),
        ("max lateral velocity |A(q) qd| at the samples [m/s]", f"{np.max(lateral):.1e}", "0 (nonholonomic)",
         "no-slip constraint imposed at every sample (path_equalities)"),
        ("samples with a wheel torque >= 90 % of 1 N m", f"{100 * np.mean(sat >= 0.9):.0f} %", "-",
         "time-optimal signature (bang-bang)"),
        ("max violation (relative)", f"{float(sol.max_violation['overall']):.1e}", "-", "re-simulated"),
        ("largest wheel torque between samples / 1 N m", f"{records[0]['effort_between_samples']:.3f}", "-",
         "intersample_effort: the constant-acceleration motion between samples (the bound holds at the samples)"),
        ("efforts=intervals: T [s], status", f"{float(sol_i.T):.3f} ({100 * (float(sol_i.T) / T - 1):+.2f} %), "
         + status_text(sol_i, ti_last) + "; tries " + " -> ".join(tries_i), "-",
         f"the torque bound also at each interval's end, warm-started from the row above; first call "
         f"{ti_first:.0f} s incl. compilation"),
        ("efforts=intervals: largest wheel torque between samples / 1 N m, max violation",
         f"{records[1]['effort_between_samples']:.3f}, {float(sol_i.max_violation['overall']):.1e}", "-",
         "the bound now holds (nearly) everywhere along the motion"),
    ]
    obs = "; ".join(f"({cx:g}, {cy:g}), r = {r:g}" for cx, cy, r in np.asarray(robot.obstacles))
    text = (f"## wmr: differential-drive robot, minimum time among three obstacles\n\n"
            f"Robot `wmr` (assumed: 50 kg, yaw inertia 2.5 kg m^2, wheel radius 0.1 m, track 0.5 m, wheel inertia "
            f"0.005 kg m^2, chassis disc radius 0.3 m; |tau| <= 1 N m per wheel; |qd| <= (2, 2, 2), |qdd| <= "
            f"(0.5, 0.5, 2.5); h in [0.05, {H_MAX:g}] s (the robot's 2 s overridden, see below); floor [0, 24]^2 m). Obstacles (assumed layout, Chettibi does not "
            f"publish it; centres and radii in m): {obs}, each crossing or touching the straight line. "
            f"Task {Q_START} -> (23, 23, pi/6) at rest; weights time = 1, energy = 0; N = {N}; decoupled "
            f"transcription. Figure: `figures/{NAME}.png` (grey: obstacles; dotted: obstacle + chassis radius)."
            f"\n\n" + table(rows))
    publish(NAME, text, records, t_start)


if __name__ == "__main__":
    main()
