"""Design by gradient (Chettibi's "optimal synthesis"): choose the two link lengths of a
planar arm to minimise the mean optimal time of a batch of tip-to-tip tasks, under a
total-length budget, by projected gradient descent through ``jtraj.solve_batch``
(implicit differentiation of each optimum); compare with a grid search over the same
design space and the same tasks.

The arm: two uniform links of linear density RHO (mass and inertia follow the length)
carrying a payload at the tip, in a horizontal plane, fixed actuator limits. The tasks
are given by tip points; their joint configurations come from the closed-form inverse
kinematics of each design (elbow up), so the start and the goal of every problem move
with the design and the derivative follows them.

Writes examples/figures/design_by_gradient.png, examples/status/design_by_gradient.json
(the final design's and the grid's best design's solves) and the "design_by_gradient"
section of examples/RESULTS.md.
Run: python examples/design_by_gradient.py
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from run_all import FIGURES, batch_status_records, setup, table, wall_and_cpu, write_section, write_status  # noqa: E402

setup()

import equinox as eqx  # noqa: E402
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import optax  # noqa: E402

import jtraj  # noqa: E402
from jtraj.resample import intersample_effort  # noqa: E402

N = 10
TASKS = 6
RHO = 8.0  # kg/m, each link
PAYLOAD = 2.0  # kg at the tip
LIMITS = dict(tau_max=(30.0, 10.0), qd_max=3.0, qdd_max=30.0, h_min=0.005, h_max=0.1)
WEIGHTS = jtraj.Weights(time=1.0, energy=0.1)
# the design band REACH <= l1 + l2 <= BUDGET: a material budget, and a reach requirement
# (the arm must reach REACH from its base, beyond the tasks' points)
BUDGET = 1.1  # m
REACH = 0.9  # m
BOX = (0.35, 0.65)  # m: each length (every task reachable by every design in the box)
RADII = (0.42, 0.62)  # m: the tasks' tip points lie at these distances from the base
GRID = 13  # grid points per length (a step of 0.025 m: the band's edges are grid lines)
START = (0.62, 0.58)  # m: the initial design of the gradient descent (projected onto the band)
ITERATIONS = 30
LEARNING_RATE = 0.03  # m (Adam), x0.95 every iteration
SOLVER = jtraj.AugmentedLagrangian(tol_feasibility=1e-9, tol_optimality=1e-9, max_iter=1000)
_BASE = jtraj.robots.serial_planar((0.5, 0.5), (1.0, 1.0), (0.1, 0.1), limits=LIMITS, name="arm2")


def task_points(count: int = TASKS, seed: int = 3):
    """(start tips, goal tips), each (count, 2) [m]: seeded random points at distances
    ``RADII`` from the base, within +-1.2 rad of the x axis."""
    rng = np.random.default_rng(seed)
    angle = rng.uniform(-1.2, 1.2, (count, 2))
    radius = rng.uniform(*RADII, (count, 2))
    points = np.stack([radius * np.cos(angle), radius * np.sin(angle)], axis=-1)
    return points[:, 0], points[:, 1]


def arm(lengths):
    """The two-link arm of link lengths ``lengths`` [m]: masses RHO l, inertias m l^2 / 12
    about mid-link, the payload lumped into link 2 at its tip. Differentiable."""
    lengths = jnp.asarray(lengths)
    m = RHO * lengths
    m2 = m[1] + PAYLOAD
    c2 = (m[1] * lengths[1] / 2 + PAYLOAD * lengths[1]) / m2
    inertia = m * lengths**2 / 12
    i2 = inertia[1] + m[1] * (lengths[1] / 2 - c2) ** 2 + PAYLOAD * (lengths[1] - c2) ** 2
    return eqx.tree_at(lambda r: (r.lengths, r.masses, r.com, r.inertias), _BASE,
                       (lengths, jnp.stack([m[0], m2]), jnp.stack([lengths[0] / 2, c2]),
                        jnp.stack([inertia[0], i2])))


def inverse_kinematics(lengths, points):
    """Joint angles (..., 2) [rad] putting the tip at ``points`` (..., 2) [m], elbow up
    (q2 > 0). Differentiable in the lengths and the points."""
    l1, l2 = lengths[0], lengths[1]
    c2 = (jnp.sum(points**2, axis=-1) - l1**2 - l2**2) / (2 * l1 * l2)
    q2 = jnp.arccos(c2)
    q1 = jnp.arctan2(points[..., 1], points[..., 0]) - jnp.arctan2(l2 * jnp.sin(q2), l1 + l2 * jnp.cos(q2))
    return jnp.stack([q1, q2], axis=-1)


def solve(lengths, tips, init=None, efforts="samples"):
    start, goal = tips
    return jtraj.solve_batch(arm(lengths), inverse_kinematics(lengths, start), inverse_kinematics(lengths, goal),
                             N=N, weights=WEIGHTS, solver=SOLVER, init=init, slots=None, efforts=efforts)


def intervals_check(designs: dict, tips) -> tuple[str, list[dict]]:
    """Each design of ``designs`` (label -> (lengths, its batch solution)) re-solved with
    the effort bound at both ends of every interval (``efforts="intervals"``), warm-started:
    the text comparing the designs' mean optimal times that way, and the solves' status
    records."""
    parts, means, records = [], {}, []
    for label, (lengths, sol) in designs.items():
        si = solve(jnp.asarray(lengths), tips, init=(sol.v, sol.h), efforts="intervals")
        between = np.asarray(intersample_effort(sol, arm(jnp.asarray(lengths))))
        ok = np.asarray(si.status) == 0
        records += batch_status_records(f"{label}, efforts=intervals, task", si, arm(jnp.asarray(lengths)))
        means[label] = float(np.mean(np.asarray(si.T)))
        parts.append(f"{label}: mean T* {means[label]:.4f} s against {float(np.mean(np.asarray(sol.T))):.4f} s with "
                     f"the bound at the samples ({int(ok.sum())}/{len(ok)} CONVERGED; at the samples the largest "
                     f"effort between samples is {between.max():.3f} of the bound)")
    (a, ta), (b, tb) = means.items()
    return ("With the bound at both ends of every interval (`efforts=\"intervals\"`, warm-started): "
            + "; ".join(parts) + f". {a[0].upper() + a[1:]} against {b}: {ta - tb:+.4f} s "
            f"({100 * (ta / tb - 1):+.2f} %).", records)


def mean_time(lengths, tips, init=None):
    """(mean optimal time [s] over the tasks, the batch's solution)."""
    sol = solve(lengths, tips, init)
    return jnp.mean(sol.T), sol


def project(lengths):
    """The nearest design (Euclidean) with REACH <= l1 + l2 <= BUDGET, then clipped to the
    box (exact where the clip does not act, as at every point of this example's path)."""
    total = jnp.sum(lengths)
    shift = jnp.clip(total, REACH, BUDGET) - total
    return jnp.clip(lengths + shift / 2, *BOX)


def tangent(lengths, grad):
    """The gradient with its component normal to the band's edge removed where the design
    lies on that edge (l1 + l2 = REACH or BUDGET) and a descent step would leave the
    band: the direction of steepest descent within the band. (Adam scales each
    coordinate by its own gradient history: fed the raw gradient, whose normal part
    dominates on the edge, it moves both lengths by the same amount and the projection
    cancels the move, so the path would stall on the edge.)"""
    normal = jnp.ones(2) / jnp.sqrt(2.0)
    total, outward = jnp.sum(lengths), jnp.dot(grad, normal)
    on_edge = ((total <= REACH + 1e-9) & (outward > 0)) | ((total >= BUDGET - 1e-9) & (outward < 0))
    return jnp.where(on_edge, grad - outward * normal, grad)


def in_band(axis):
    """(len(axis), len(axis)) mask of the grid designs with REACH <= l1 + l2 <= BUDGET."""
    total = axis[:, None] + axis[None, :]
    return (total >= REACH - 1e-12) & (total <= BUDGET + 1e-12)


def grid_search(tips, grid: int = GRID):
    """Mean optimal time on a grid x grid design grid (infeasible designs included, for the
    landscape); returns (axis values, the (grid, grid) mean times, (grid, grid) count of
    converged tasks, seconds)."""
    axis = np.linspace(*BOX, grid)
    values = np.full((grid, grid), np.nan)
    converged = np.zeros((grid, grid), int)
    t0 = time.perf_counter()
    for i, l1 in enumerate(axis):
        for j, l2 in enumerate(axis):
            value, sol = mean_time(jnp.array([l1, l2]), tips)
            values[i, j] = float(value)
            converged[i, j] = int(np.sum(np.asarray(sol.status) == 0))
        print(f"grid: l1 = {l1:.3f} m done, {time.perf_counter() - t0:.0f} s", flush=True)
    return axis, values, converged, time.perf_counter() - t0


def descend(tips, start=START, iterations: int = ITERATIONS, learning_rate: float = LEARNING_RATE) -> dict:
    """Projected gradient descent (Adam on the gradient within the band, :func:`tangent`,
    then the projection onto the band) from ``start``; each iteration is one batched solve (cold started) and one implicit
    derivative. Returns the path ("design", iterations + 1 designs), "objective" (the
    mean time at each design of the path but the last), "valid", "seconds"."""
    value_and_grad = jax.value_and_grad(mean_time, has_aux=True)
    # mild momentum and a short memory of the squared gradient: steps of about the
    # learning rate, which decays by 0.95 per iteration (no long overshoot)
    opt = optax.adam(optax.exponential_decay(learning_rate, 1, 0.95), b1=0.5, b2=0.9)
    lengths = project(jnp.asarray(start, float))
    state = opt.init(lengths)
    history = {"design": [np.asarray(lengths)], "objective": [], "valid": []}
    t0 = time.perf_counter()
    init = None  # every solve starts cold (its own initial guess)
    for _ in range(iterations):
        (value, sol), grad = value_and_grad(lengths, tips, init)
        updates, state = opt.update(tangent(lengths, grad), state)
        lengths = project(optax.apply_updates(lengths, updates))
        history["objective"].append(float(value))
        history["valid"].append(int(np.sum(np.asarray(jtraj.valid_derivatives(sol)))))
        history["design"].append(np.asarray(lengths))
        print(f"descent {len(history['objective'])}: mean T {float(value):.5f} s, next design "
              f"({float(lengths[0]):.4f}, {float(lengths[1]):.4f}) m, {time.perf_counter() - t0:.0f} s", flush=True)
    history["design"] = np.stack(history["design"])
    history["seconds"] = time.perf_counter() - t0
    return history


def plot(axis, values, best_grid, path_hist, path: Path) -> None:
    import matplotlib.pyplot as plt

    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(11, 4.8), constrained_layout=True)
    cs = ax.contourf(axis, axis, values.T, levels=20, cmap="viridis")
    fig.colorbar(cs, ax=ax, label="mean optimal time [s]")
    ax.plot(axis, BUDGET - axis, "w--", lw=1.5, label=f"budget l1 + l2 = {BUDGET:g} m")
    ax.plot(axis, REACH - axis, "w:", lw=1.5, label=f"reach l1 + l2 = {REACH:g} m")
    ax.fill_between(axis, BUDGET - axis, BOX[1], color="w", alpha=0.35, lw=0)
    ax.fill_between(axis, BOX[0], REACH - axis, color="w", alpha=0.35, lw=0)
    d = path_hist["design"]
    ax.plot(d[:, 0], d[:, 1], "r.-", lw=1.2, ms=5, label="projected gradient path")
    ax.plot(d[0, 0], d[0, 1], "ro", mfc="none", ms=9)
    ax.plot(*best_grid, "w*", ms=14, mec="k", label="grid optimum (within the band)")
    ax.set_xlim(*BOX)
    ax.set_ylim(*BOX)
    ax.set_xlabel("l1, upper-arm length [m]")
    ax.set_ylabel("l2, forearm length [m]")
    ax.set_title("objective landscape (grid) and the gradient path")
    ax.legend(loc="upper right", fontsize=8)
    ax2.plot(np.arange(len(path_hist["objective"])), path_hist["objective"], "o-", ms=3, label="gradient path")
    ax2.axhline(np.nanmin(np.where(in_band(axis), values, np.nan)), color="k", ls="--",
                label="grid optimum within the band")
    ax2.set_xlabel("iteration [-]")
    ax2.set_ylabel("mean optimal time [s]")
    ax2.grid(True, alpha=0.3)
    ax2.legend()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main():
    t_start = time.perf_counter()
    tips = tuple(jnp.asarray(p) for p in task_points())
    hist = descend(tips)
    axis, values, converged, t_grid = grid_search(tips)
    feasible = in_band(axis)
    masked = np.where(feasible & (converged == TASKS), values, np.inf)
    i, j = np.unravel_index(np.argmin(masked), masked.shape)
    best_grid = (axis[i], axis[j])
    final = hist["design"][-1]
    final_value, final_sol = mean_time(jnp.asarray(final), tips)
    final_value = float(final_value)
    # status records: the final design's solves and the grid's best design's (re-solved)
    _, best_sol = mean_time(jnp.asarray(best_grid), tips)
    records = (batch_status_records("gradient's final design, task", final_sol, arm(jnp.asarray(final)))
               + batch_status_records("grid's best design, task", best_sol, arm(jnp.asarray(best_grid))))
    plot(axis, values, best_grid, hist, FIGURES / "design_by_gradient.png")
    intervals, records_i = intervals_check(
        {"the gradient's design": (final, final_sol), "the grid's best": (best_grid, best_sol)}, tips)

    iters = len(hist["objective"])
    rows = [
        ("grid search", f"({best_grid[0]:.3f}, {best_grid[1]:.3f})", f"{best_grid[0] + best_grid[1]:.3f}",
         f"{masked[i, j]:.4f}", f"{GRID * GRID} designs x {TASKS} tasks = {GRID * GRID * TASKS} solves "
         f"({int(feasible.sum())} designs within the band)", f"{t_grid:.0f}"),
        ("projected gradient (Adam)", f"({final[0]:.3f}, {final[1]:.3f})", f"{final.sum():.3f}", f"{final_value:.4f}",
         f"{iters} x {TASKS} tasks = {iters * TASKS} solves + {iters} batched derivatives "
         f"(+ {TASKS} solves to evaluate the final design)", f"{hist['seconds']:.0f}"),
    ]
    header = ("method", "design (l1, l2) [m]", "l1 + l2 [m]", "mean optimal time [s]", "cost", "wall s")
    text = (
        "## design_by_gradient: link lengths of a planar arm by gradient through `solve_batch`\n\n"
        f"A two-link arm in a horizontal plane: uniform links of {RHO:g} kg/m (inertia m l^2/12 about "
        f"mid-link), a {PAYLOAD:g} kg payload at the tip, |tau| <= {LIMITS['tau_max']} N m, |qd| <= "
        f"{LIMITS['qd_max']:g} rad/s, |qdd| <= {LIMITS['qdd_max']:g} rad/s^2, h in [{LIMITS['h_min']:g}, "
        f"{LIMITS['h_max']:g}] s. {TASKS} rest-to-rest tasks between seeded random tip points at "
        f"{RADII[0]:g}-{RADII[1]:g} m from the base; the joint configurations come from each design's "
        f"closed-form inverse kinematics (elbow up), so they move with the design. N = {N}, weights time = 1 "
        f"and energy = 0.1, AL method at tolerances 1e-9. Objective: the mean over the tasks of the optimal "
        f"time T*; design space l1, l2 in [{BOX[0]:g}, {BOX[1]:g}] m under a total-length budget l1 + l2 <= "
        f"{BUDGET:g} m and a reach requirement l1 + l2 >= {REACH:g} m. Gradient: Adam (learning rate "
        f"{LEARNING_RATE:g} m, x0.95 every iteration, b1 = 0.5, b2 = 0.9) on the gradient within the band "
        f"(on an edge of the band, its component along the edge's normal removed where the step would "
        f"leave the band) followed by the Euclidean projection onto the band, from ({START[0]:g}, {START[1]:g}) m, the derivative of every T* by "
        f"implicit differentiation through `jtraj.solve_batch` (inverse kinematics included). Grid: "
        f"{GRID} x {GRID} designs over the same box and the same tasks. Figure: "
        "`figures/design_by_gradient.png` (the landscape from the grid, the designs outside the band "
        "lightened, the gradient path over it; the objective along the path).\n\n"
        + table(rows, header=header)
        + f"\n\nThe gradient's design against the grid's best: {final_value - masked[i, j]:+.4f} s "
        f"({100 * (final_value / masked[i, j] - 1):+.2f} %) in mean optimal time, with "
        f"{iters * TASKS + TASKS} solves against {GRID * GRID * TASKS} (the grid's step is "
        f"{(BOX[1] - BOX[0]) / (GRID - 1):.3f} m). "
        f"Grid designs with every task converged: {int((converged == TASKS).sum())}/{GRID * GRID}. "
        f"Fewest valid derivatives along the path: {min(hist['valid'])}/{TASKS}. Final design's statuses: "
        + ", ".join(jtraj.Status(int(s)).name for s in np.asarray(final_sol.status))
        + ". " + intervals
        + " The gradient's first iteration includes the compilation of the derivative program. "
        + wall_and_cpu(t_start)
    )
    write_status("design_by_gradient", records + records_i, t_start)
    write_section("design_by_gradient", text)
    print(text)


if __name__ == "__main__":
    main()
