"""jtraj on the arm URDFs of example-robot-data, against CasADi + IPOPT.

    python benchmarks/bench_urdf_arms.py [--pairs 8] [--N 20] [--seed 0] [--arms z1,xarm7,...]
                                         [--workers W] [--json out.json]

What a user gets from their own file: for each arm of :data:`ARMS` (a file of
example-robot-data and its tip link), ``jtraj.robots.from_urdf(path, tip_link=...)``
with its defaults (the file's position, velocity and effort limits, accelerations
bounded by 10 rad/s^2, periods in [0.005, 0.1] s). Problem family: N = 20, weights time
1 / energy 0.1, q_start uniform in the middle 60 % of each joint range (a continuous
joint's range taken as [-pi, pi]), q_goal = q_start + U(-0.5, 0.5) rad per joint
clipped to the range (``bench_spatial.panda_pairs``, seeded).

The peer solves the same decoupled NLP (``jtraj_peers.ipopt_arm``) with a CasADi RNEA of
Pinocchio's model of the same file (``jtraj_peers.casadi_rnea.rnea_function``): the full
model with every joint off the chain locked where ``from_urdf`` locks it (0, clamped
into its limits), and jtraj's limits; both sides start from jtraj's starting point.
Before solving, the two dynamics are compared on random states (``rnea gap``: the
largest difference of the efforts over their largest magnitude). Every trajectory
either side calls a success is re-simulated from its own (v, h) and checked with
Pinocchio (``jtraj_peers.verify_arm``, tolerance 1e-6), so that a "converged" that does
not verify counts as false.

Printed per arm: verified successes of each side, false "converged", the cost gap where
both verify, and the wall time per pair of a warm batch on all cores (jtraj:
``solve_batch`` on one pinned process per core after a compiling pass; IPOPT: one
process per core, its NLP built before the clock starts). Ratios > 1 mean jtraj is
ahead.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np

sys.path.append(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # the repository root: jtraj_peers

from benchmarks.bench_spatial import PEER_WEIGHTS, WEIGHTS, _limits, jtraj_starts, panda_pairs  # noqa: E402

#: label -> (file under example-robot-data's robots folder, tip link)
ARMS = {
    "panda": ("panda_description/urdf/panda.urdf", "panda_link8"),
    "ur3": ("ur_description/urdf/ur3_robot.urdf", "tool0"),
    "ur5": ("ur_description/urdf/ur5_robot.urdf", "tool0"),
    "ur10": ("ur_description/urdf/ur10_robot.urdf", "tool0"),
    "xarm7": ("xarm_description/urdf/xarm7.urdf", None),
    "z1": ("z1_description/urdf/z1.urdf", "link06"),
    "kinova": ("kinova_description/robots/kinova.urdf", "j2s6s200_end_effector"),
    "so101": ("so_arm_description/urdf/so101.urdf", "gripper_link"),
    "baxter_left": ("baxter_description/urdf/baxter.urdf", "left_gripper"),
    "tiago_pro_left": ("tiago_pro_description/robots/tiago_pro.urdf", "arm_left_tool_link"),
}
KEYS = ("v", "h", "cost", "converged", "iterations")


def urdf_path(label: str) -> str:
    from jtraj_peers.casadi_rnea import example_robot_urdf

    return example_robot_urdf(ARMS[label][0])


def jtraj_arm(label: str):
    import jax

    jax.config.update("jax_enable_x64", True)
    from jtraj.robots import from_urdf

    return from_urdf(urdf_path(label), tip_link=ARMS[label][1], name=label)


def pinocchio_chain(path: str, joint_names):
    """Pinocchio's model of the file reduced to the chain: every other joint locked at
    0 clamped into its limits (``from_urdf``'s convention), its coordinates in
    ``joint_names``' order."""
    import pinocchio as pin

    full = pin.buildModelFromUrdf(path)
    names = list(full.names)[1:]
    missing = [nm for nm in joint_names if nm not in names]
    if missing:
        raise ValueError(f"{path}: Pinocchio's model has no joints {missing}")
    reference = pin.neutral(full)
    locked = []
    for nm in names:
        if nm in joint_names:
            continue
        j = full.getJointId(nm)
        if full.nqs[j] == 1:
            i = full.idx_qs[j]
            reference[i] = np.clip(0.0, full.lowerPositionLimit[i], full.upperPositionLimit[i])
        locked.append(j)
    model = pin.buildReducedModel(full, locked, reference)
    if list(model.names)[1:] != list(joint_names):
        raise ValueError(f"{path}: the reduced model's joints {list(model.names)[1:]} are not jtraj's {list(joint_names)}")
    return model


def rnea_gap(robot, model, seed: int = 0, count: int = 32) -> float:
    """The largest difference between jtraj's and Pinocchio's efforts on ``count``
    random states within the limits, over the largest effort."""
    import jax
    import pinocchio as pin

    from jtraj_peers.casadi_rnea import pinocchio_configuration

    lim = _limits(robot)
    lo, hi = joint_range(robot)
    rng = np.random.default_rng(seed)
    q = rng.uniform(lo, hi, (count, robot.n))
    qd, qdd = (rng.uniform(-1, 1, (count, robot.n)) * lim[k] for k in ("qd_max", "qdd_max"))
    ours = np.asarray(jax.jit(jax.vmap(robot.inverse_dynamics))(q, qd, qdd))
    data = model.createData()
    ref = np.stack([pin.rnea(model, data, pinocchio_configuration(model, q[k]), qd[k], qdd[k]) for k in range(count)])
    return float(np.max(np.abs(ours - ref)) / np.max(np.abs(ref)))


def peer_spec(robot, model):
    from jtraj_peers.casadi_rnea import rnea_function
    from jtraj_peers.ipopt_arm import ArmSpec

    lim = _limits(robot)
    return ArmSpec.make(rnea_function(model), q_min=lim["q_min"], q_max=lim["q_max"], qd_max=lim["qd_max"],
                        qdd_max=lim["qdd_max"], tau_max=lim["tau_max"], h_min=lim["h_min"], h_max=lim["h_max"])


def joint_range(robot):
    """The joints' position boxes (q_min, q_max), a continuous joint's as [-pi, pi]."""
    lim = _limits(robot)
    return (np.where(np.isfinite(lim["q_min"]), lim["q_min"], -np.pi),
            np.where(np.isfinite(lim["q_max"]), lim["q_max"], np.pi))


def arm_pairs(robot, pairs: int, seed: int):
    return panda_pairs(pairs, seed, *joint_range(robot))


def _solve_chunk(label, q0, q1, N):
    import jtraj

    sol = jtraj.solve_batch(jtraj_arm(label), q0, q1, N=N, weights=jtraj.Weights(**WEIGHTS))
    return {k: np.asarray(getattr(sol, k)) for k in KEYS}


def jtraj_batch(label, q0, q1, N, workers):
    """``solve_batch`` on ``workers`` pinned processes, the pairs split evenly: one
    untimed pass (compilation), then the median wall time of three."""
    from jtraj.dataset._local import worker_pool

    chunks = [c for c in zip(np.array_split(q0, workers), np.array_split(q1, workers)) if len(c[0])]
    args = ([label] * len(chunks), [c[0] for c in chunks], [c[1] for c in chunks], [N] * len(chunks))
    with worker_pool(len(chunks)) as pool:
        t0 = time.perf_counter()
        list(pool.map(_solve_chunk, *args))
        first = time.perf_counter() - t0
        walls = []
        for _ in range(3):
            t0 = time.perf_counter()
            parts = list(pool.map(_solve_chunk, *args))
            walls.append(time.perf_counter() - t0)
    res = {k: np.concatenate([p[k] for p in parts]) for k in KEYS}
    res["wall"], res["compile_and_first_pass"] = float(np.median(walls)), first
    return res


def verify_all(model, robot, q0, q1, vs, hs):
    from jtraj_peers.verify_arm import verify

    lim = _limits(robot)
    kw = {k: lim[k] for k in ("tau_max", "qd_max", "qdd_max", "q_min", "q_max", "h_min", "h_max")}
    return [verify(model, a, b, v, h, weights=PEER_WEIGHTS, **kw) for a, b, v, h in zip(q0, q1, vs, hs)]


def run_arm(label, pairs, seed, N, workers):
    from jtraj_peers.ipopt_arm import solve_many

    robot = jtraj_arm(label)
    model = pinocchio_chain(urdf_path(label), robot.joint_names)
    gap = rnea_gap(robot, model)
    q0, q1 = arm_pairs(robot, pairs, seed)
    ours = jtraj_batch(label, q0, q1, N, workers)
    starts = jtraj_starts(q0, q1, N, robot)
    peer = solve_many(peer_spec(robot, model), q0, q1, N=N, weights=PEER_WEIGHTS, inits=starts, processes=workers)
    ver_j = verify_all(model, robot, q0, q1, ours["v"], ours["h"])
    ver_p = verify_all(model, robot, q0, q1, [r["v"] for r in peer], [r["h"] for r in peer])
    ok_j = np.array([bool(c) and r["ok"] for c, r in zip(ours["converged"], ver_j)])
    ok_p = np.array([bool(r["success"]) and v["ok"] for r, v in zip(peer, ver_p)])
    both = ok_j & ok_p
    gaps = np.array([(a["cost"] - b["cost"]) / abs(b["cost"]) for a, b in zip(ver_j, ver_p)])[both]
    return {
        "arm": label, "file": ARMS[label][0], "tip_link": ARMS[label][1], "n": robot.n, "pairs": pairs,
        "rnea_gap": gap,
        "jtraj": {"verified": int(ok_j.sum()), "false_converged": int(np.sum(ours["converged"] & ~ok_j)),
                  "iterations_median": float(np.median(ours["iterations"])), "wall": ours["wall"],
                  "compile_and_first_pass": ours["compile_and_first_pass"]},
        "ipopt": {"verified": int(ok_p.sum()),
                  "false_converged": int(sum(bool(r["success"]) and not v["ok"] for r, v in zip(peer, ver_p))),
                  "iterations_median": float(np.median([r["iterations"] for r in peer])),
                  "wall": float(peer.wall_seconds)},
        "cost_gap_median": float(np.median(gaps)) if gaps.size else None,
        "cost_gap_max": float(np.max(np.abs(gaps))) if gaps.size else None,
        "only_jtraj": int(np.sum(ok_j & ~ok_p)), "only_ipopt": int(np.sum(ok_p & ~ok_j)),
    }


def _row(r):
    j, p = r["jtraj"], r["ipopt"]
    gap = "-" if r["cost_gap_median"] is None else f"{100 * r['cost_gap_median']:+.3f} % / {100 * r['cost_gap_max']:.3f} %"
    return (f"| {r['arm']} | {r['n']} | {r['rnea_gap']:.1e} | {j['verified']} / {r['pairs']} ({j['false_converged']}) | "
            f"{p['verified']} / {r['pairs']} ({p['false_converged']}) | {gap} | "
            f"{1e3 * j['wall'] / r['pairs']:.0f} / {1e3 * p['wall'] / r['pairs']:.0f} ms | "
            f"{p['wall'] / j['wall']:.1f}x | {j['iterations_median']:.0f} / {p['iterations_median']:.0f} |")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pairs", type=int, default=8)
    ap.add_argument("--N", type=int, default=20)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--arms", default=",".join(ARMS), help=f"comma-separated, of {', '.join(ARMS)}")
    ap.add_argument("--workers", type=int, default=None, help="processes of each side (default: all cores)")
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    labels = [a.strip() for a in args.arms.split(",") if a.strip()]
    unknown = [a for a in labels if a not in ARMS]
    if unknown:
        ap.error(f"--arms: unknown {unknown}; known: {', '.join(ARMS)}")
    if args.pairs < 1:
        ap.error("--pairs must be >= 1")
    workers = args.workers or os.cpu_count() or 1
    print(f"N = {args.N}, weights time=1 energy=0.1, {args.pairs} pairs per arm (seed {args.seed}), "
          f"{workers} processes per side")
    print("| arm | n | rnea gap | jtraj verified (false) | IPOPT verified (false) | cost gap median / max |"
          " wall per pair jtraj / IPOPT | ratio | Newton iterations jtraj / IPOPT (median) |")
    print("|---|---|---|---|---|---|---|---|---|")
    rows = []
    for label in labels:
        rows.append(run_arm(label, args.pairs, args.seed, args.N, workers))
        print(_row(rows[-1]), flush=True)
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"N": args.N, "pairs": args.pairs, "seed": args.seed, "workers": workers, "arms": rows}, f,
                      indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
