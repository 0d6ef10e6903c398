"""serial3 (Khoukhi ch. 5, annex A): the chapter 5 minimum-time-only run (a 0.75 m move,
published 1.4 s, Figs. 5.9-5.12) and annex A's second straight line to (0.64, 0.45) m
(Fig. A.8).

Writes examples/figures/serial3_min_time_ch5.png, examples/figures/serial3_line2_*.png,
examples/status/serial3_lines.json and the "serial3_lines" section of examples/RESULTS.md.
Run: python examples/serial3_lines.py
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from run_all import (FIGURES, intervals_cell, publish, setup, solve_with_restart, status_record, status_text,  # noqa: E402
                     table)

setup()

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jtraj  # noqa: E402
from jtraj import plotting  # noqa: E402
from jtraj.problem import ik_or_raise  # noqa: E402
from jtraj.resample import intersample_effort  # noqa: E402

NAME = "serial3_lines"
N = 20
T_MAX = 3.0
Q_START = np.deg2rad([0.0, 30.0, 30.0])
P_GOAL_CH6 = np.array([1.35, 1.30])
MOVE = 0.75  # m, chapter 5's minimum-time run
T_PUBLISHED_CH5 = 1.4  # s
H_MIN_CH5 = 0.001  # s, chapter 5's period bounds [0.001, 0.1]
W_TIME = jtraj.Weights(time=1.0, energy=0.0)  # minimum time only
W_ALL = jtraj.Weights(time=1.0, energy=1.0, kinetic=1.0)  # annex A's "all weights 1"
MASSES_ANNEX_A = (8.0, 4.0, 2.0)
# annex A's second line: stated start q = (0, 15, 20) deg with tip (0.2, 0.9) m (the two
# disagree: forward kinematics of the angles gives (2.14, 0.47) m), goal tip (0.64, 0.45) m
Q_LINE2 = np.deg2rad([0.0, 15.0, 20.0])
P_LINE2_START, P_LINE2_GOAL = np.array([0.2, 0.9]), np.array([0.64, 0.45])


def fk(robot, q):
    return np.asarray(robot.forward_kinematics(jnp.asarray(q)))


def describe(robot, problem, sol, t_first, t_last, tries):
    """Common measurements of one solved problem."""
    lim = robot.limits
    tau = np.abs(np.asarray(sol.tau)) / np.asarray(lim.tau_max)
    qd = np.abs(np.asarray(sol.qd)) / np.asarray(lim.qd_max)
    v = np.abs(np.asarray(sol.v)) / np.asarray(lim.qdd_max)
    h = np.asarray(sol.h)
    tip = fk(robot, sol.q[-1])
    return dict(
        status=status_text(sol, t_last), tries=" -> ".join(tries), t_first=t_first, T=float(sol.T),
        E=float(sol.energy), viol=float(sol.max_violation["overall"]), kkt=float(sol.kkt_error),
        tip_err=float(np.linalg.norm(tip - fk(robot, problem.q_goal))),
        sat=100.0 * float(np.mean(np.any(tau >= 0.9, axis=1))), peak_tau=tau.max(axis=0),
        peak_qd=float(qd.max()), acc=100.0 * float(np.mean(np.any(v >= 1 - 1e-6, axis=1))),
        n_hmin=int(np.sum(h <= float(lim.h_min) + 1e-9)), n_hmax=int(np.sum(h >= float(lim.h_max) - 1e-9)),
        between=float(intersample_effort(sol, robot)),
        path_len=float(np.sum(np.linalg.norm(np.diff(np.asarray(jax.vmap(robot.forward_kinematics)(sol.q)),
                                                       axis=0), axis=1))))


def main():
    t_start = time.perf_counter()

    # ------------------------------------------------ chapter 5: minimum time, 0.75 m
    robot5 = jtraj.robots.get("serial3", h_min=H_MIN_CH5)
    p0 = fk(robot5, Q_START)
    direction = (P_GOAL_CH6 - p0) / np.linalg.norm(P_GOAL_CH6 - p0)
    p_goal5 = p0 + MOVE * direction
    def task5(efforts="samples"):
        return jtraj.Problem.from_task(robot5, p0, p_goal5, q_init=Q_START, N=N, weights=W_TIME, T_max=T_MAX,
                                       efforts=efforts)

    pr5 = task5()
    s5, *rest5 = solve_with_restart(pr5)
    r5 = describe(robot5, pr5, s5, *rest5)
    records = [status_record("ch. 5 minimum time", s5, robot5)]
    r5["intervals"] = intervals_cell(lambda: task5("intervals"), s5, robot5, "ch. 5 minimum time", records)
    fig = plotting.plot_solution(pr5, s5, title=f"serial3, minimum time, a {MOVE} m move (ch. 5): "
                                                f"T = {r5['T']:.3f} s ({jtraj.Status(int(s5.status)).name})")
    plotting.save(fig, str(FIGURES / "serial3_min_time_ch5.png"))

    # ------------------------------------------------ annex A: the second straight line
    robotA = jtraj.robots.get("serial3", masses=MASSES_ANNEX_A)
    q_tips = np.asarray(ik_or_raise(robotA, jnp.asarray(P_LINE2_START), jnp.asarray(Q_LINE2), "p_start"))
    def line2(p_start, efforts="samples"):
        return jtraj.Problem.from_task(robotA, p_start, P_LINE2_GOAL, q_init=Q_LINE2, N=N, weights=W_ALL,
                                       T_max=T_MAX, efforts=efforts)

    variants = [
        ("tips", "stated tips (0.2, 0.9) -> (0.64, 0.45) m, start configuration by IK from (0, 15, 20) deg",
         P_LINE2_START),
        ("angles", "stated start angles (0, 15, 20) deg (tip (2.14, 0.47) m) -> tip (0.64, 0.45) m",
         fk(robotA, Q_LINE2)),
    ]
    lines = []
    for key, label, p_start in variants:
        pr = line2(p_start)
        sol, *rest = solve_with_restart(pr)
        r = describe(robotA, pr, sol, *rest)
        records.append(status_record(f"second line, {key}", sol, robotA))
        r["intervals"] = intervals_cell(lambda p_start=p_start: line2(p_start, "intervals"), sol, robotA,
                                        f"second line, {key}", records)
        r.update(key=key, label=label, q0=np.rad2deg(np.asarray(pr.q_start)), qT=np.rad2deg(np.asarray(pr.q_goal)),
                 p0=fk(robotA, pr.q_start), pT=fk(robotA, pr.q_goal),
                 straight=float(np.linalg.norm(fk(robotA, pr.q_goal) - fk(robotA, pr.q_start))))
        fig = plotting.plot_solution(pr, sol, title=f"serial3 (annex A masses 8, 4, 2 kg), second line, {label}: "
                                                    f"T = {r['T']:.3f} s ({jtraj.Status(int(sol.status)).name})")
        plotting.save(fig, str(FIGURES / f"serial3_line2_{key}.png"))
        lines.append(r)

    # ------------------------------------------------ text
    peak5 = ", ".join(f"{x:.2f}" for x in r5["peak_tau"])
    rows5 = [
        ("move", f"({p0[0]:.3f}, {p0[1]:.3f}) -> ({p_goal5[0]:.3f}, {p_goal5[1]:.3f}) m, {MOVE} m", "0.75 m",
         "the chapter 6 start (0, 30, 30) deg and the direction of its line to (1.35, 1.30) m (that line is "
         f"{np.linalg.norm(P_GOAL_CH6 - p0):.3f} m long), shortened to 0.75 m; the chapter's own start and goal "
         "are not restated here"),
        ("T [s]", f"{r5['T']:.3f}", f"{T_PUBLISHED_CH5}",
         f"{100 * (r5['T'] / T_PUBLISHED_CH5 - 1):+.1f} %; "
         + ("reproduced within 10 %" if abs(r5["T"] / T_PUBLISHED_CH5 - 1) <= 0.10 else
            "trend reproduced (faster than the cycloid, limits saturated), not the value")
         + ": chapter 5's masses and exact line are not restated, Table 6.1's are used"),
        ("status; worst violation (relative); KKT error", f"{r5['status']}; {r5['viol']:.1e}; {r5['kkt']:.1e}", "-",
         f"tries {r5['tries']}; first call {r5['t_first']:.0f} s (compilation)"),
        ("time-optimal signature", f"{r5['sat']:.0f} % of samples with a torque >= 90 %; {r5['acc']:.0f} % of "
                                   f"intervals with a joint at |qdd| = qdd_max; peak |qd|/qd_max {r5['peak_qd']:.2f}",
         "-", f"peak |tau|/tau_max per joint {peak5}; h at h_min on {r5['n_hmin']}/{N}, at h_max on "
              f"{r5['n_hmax']}/{N} intervals"),
        ("max |tau|/tau_max between samples", f"{r5['between']:.3f}", "-",
         "`jtraj.resample.intersample_effort`: the bound is imposed at the samples (`efforts=\"samples\"`, the "
         "thesis' discretisation); the executed motion exceeds it between them by this much"),
        ("bound at both ends of every interval (`efforts=\"intervals\"`)", r5["intervals"], "-",
         "the motion that meets the bound everywhere, not only at the samples"),
        ("tip goal error [m]", f"{r5['tip_err']:.1e}", "-", "re-simulated"),
    ]
    rowsA = []
    for r in lines:
        rowsA.append((r["label"],
                      f"({r['p0'][0]:.3f}, {r['p0'][1]:.3f}) -> ({r['pT'][0]:.3f}, {r['pT'][1]:.3f}) m; q "
                      f"({', '.join(f'{x:.1f}' for x in r['q0'])}) -> ({', '.join(f'{x:.1f}' for x in r['qT'])}) deg",
                      f"{r['T']:.3f} ({r['n_hmax']}/{N} h_k at h_max)", f"{r['E']:.4g}", f"{r['path_len']:.3f} / {r['straight']:.3f}",
                      f"{r['status']}; tries {r['tries']}", f"{r['viol']:.1e}", f"{r['between']:.3f}", r["intervals"],
                      f"`figures/serial3_line2_{r['key']}.png`"))
    text = (f"## serial3_lines: chapter 5's minimum-time run and annex A's second straight line\n\n"
            f"Robot `serial3` (horizontal plane; |tau| <= 40, 25, 20 N m; |qd| <= 2 rad/s; |qdd| <= 3 rad/s^2), "
            f"N = {N}, T_max = {T_MAX} s, decoupled transcription, default solver options (one warm re-solve "
            f"when not certified). Figures draw the cycloidal initial guess dashed.\n\n"
            f"### Chapter 5: minimum time only (Figs. 5.9-5.12)\n\n"
            f"Table 6.1 masses (10, 8, 4 kg), chapter 5's period bounds h in [{H_MIN_CH5}, 0.1] s, weights "
            f"time = 1, energy = 0. Figure: `figures/serial3_min_time_ch5.png`.\n\n" + table(rows5)
            + f"\n\n### Annex A: the second straight line (Fig. A.8)\n\n"
              f"Annex A masses ({', '.join(f'{m:g}' for m in MASSES_ANNEX_A)} kg), h in [0.005, 0.1] s, all "
              f"weights 1 (time = energy = kinetic = 1). The annex states the start as q = (0, 15, 20) deg and as "
              f"tip (0.2, 0.9) m, which disagree (forward kinematics of the angles: "
              f"({fk(robotA, Q_LINE2)[0]:.2f}, {fk(robotA, Q_LINE2)[1]:.2f}) m), so both readings are run; "
              f"the goal configuration comes from the weighted-pseudo-inverse IK. The thesis publishes the figure, "
              f"not its T or energy, so the rows are jtraj's alone (not comparable: nothing printed to compare; "
              f"the IK start for the stated tips is ({', '.join(f'{x:.1f}' for x in np.rad2deg(q_tips))}) deg). "
              f"As in the serial3 section, all weights 1 with torques normalised by their limits makes the energy "
              f"term dominate: the periods run to h_max and T to about N h_max = 2 s.\n\n"
            + table(rowsA, header=("reading", "move", "T [s]", "energy [s]", "tip path / straight [m]",
                                   "status", "worst violation", "max |tau|/tau_max between samples",
                                   "bound at both ends of every interval", "figure")))
    publish(NAME, text, records, t_start)


if __name__ == "__main__":
    main()
