"""Khoukhi's neuro-fuzzy planners (thesis ch. 5-6) with jtraj's ANFIS: NeFIK, NeFOTC and
NeFuMOP trained on a thesis-sized set of jtraj optima (100 serial3 trajectories x 20
samples, 90 / 10 split by trajectory), their RMSE and training times beside Tables 5.3 and
6.3, input noise beside Tables 5.4 and 6.4, NeFuMOP's membership functions before and after
training (Fig. 6.12), and new start/goal pairs planned online (Figs. 5.13-5.14, 6.14-6.15)
with the planner's feasibility and the gap to the exact optimum.

Writes examples/figures/neurofuzzy_*.png, examples/status/neurofuzzy.json (the status of
every exact solve) and the "neurofuzzy" section of examples/RESULTS.md.
Run: python examples/neurofuzzy.py
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from run_all import (FIGURES, batch_status_records, machine, setup, table, wall_and_cpu, write_section,  # noqa: E402
                     write_status)

T_START = time.perf_counter()
setup()

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jtraj  # noqa: E402
from jtraj import anfis, robots  # noqa: E402
from jtraj.anfis.clustering import subclust  # noqa: E402
from jtraj.mappings import linear_baseline, split, train_mapping, view  # noqa: E402

N = 20  # samples per trajectory, as the thesis
PAIRS = 100  # trajectories in the training set (thesis: 100 x 20 = 2000 samples)
NEW_PAIRS = 6  # new start/goal pairs drawn from the same boxes (generalisation)
WIDE_PAIRS = 2  # new pairs from boxes twice as wide (beyond the training data)
SPREAD = 0.3  # rad, half-width of the boxes around the thesis' start and goal
SPREADS = (0.1, 0.03, 0.01)  # narrower boxes: how the thesis-input NeFOTC's error falls with them
SEED = 0
WEIGHTS_TEXT = "time=1,energy=0.1"  # time-dominant (see the serial3 section)
T_MAX = 3.0
Q_START = np.deg2rad([0.0, 30.0, 30.0])  # thesis' start configuration
P_GOAL = (1.35, 1.30)  # thesis' goal tip point (annex A) [m]
NOISE = (0.005, 0.05)  # input noise: 0.5 % (Table 6.4) and 5 % (Table 5.4) of each input's range
# the thesis' settings (SCIENCE.md section 5): rules and epochs; None where not published
SETUPS = {"nefik": (6, 10), "nefotc": (9, 10), "nefumop": (None, 20)}
# the thesis' consequents (monotone logistic) and its clustering settings (SCIENCE.md section 5)
THESIS_KIND = dict(kind="tsukamoto")
THESIS_CLUSTERING = dict(radius=0.9, squash=0.5, accept=1.0, reject=0.8)
PUBLISHED = {  # [K] Tables 5.3, 6.3 and the text: (train RMSE, test RMSE, training seconds)
    "nefik": ("1e-4 (< 10 epochs)", "-", "84"),
    "nefotc": ("3.77e-3", "1.29e-3", "117"),
    "nefumop": ("4.57e-3", "2.39e-4", "213"),
}
UNITS = {"q": "rad", "tau": "N m", "h": "s"}


def unit_of(name: str) -> str:
    return UNITS[name.rstrip("0123456789")]


# ----------------------------------------------------------------------------- data
def scenario(robot):
    """(q_start, q_goal) of the thesis' straight-line scenario (goal by IK)."""
    p0 = robot.forward_kinematics(jnp.asarray(Q_START))
    pr = jtraj.Problem.from_task(robot, p0, P_GOAL, q_init=Q_START, N=N)
    return np.asarray(pr.q_start), np.asarray(pr.q_goal)


def draw_pairs(q0, qg, count, seed, spread):
    rng = np.random.default_rng(seed)
    return q0 + rng.uniform(-spread, spread, (count, 3)), qg + rng.uniform(-spread, spread, (count, 3))


def solve_pairs(robot, qs, qg, record=None):
    """One solve_batch call; a dataset-shaped dict (jtraj.dataset fields) and the seconds.
    ``record``: ``(records, [(run name, rows), ...])``, status records of those rows appended."""
    t0 = time.perf_counter()
    sol = jtraj.solve_batch(robot, qs, qg, N=N, weights=jtraj.Weights.parse(WEIGHTS_TEXT), T_max=T_MAX)
    jax.block_until_ready(sol.T)
    secs = time.perf_counter() - t0
    if record is not None:
        records, groups = record
        for run, rows in groups:
            records += batch_status_records(run, sol, robot, rows)
    data = {k: np.asarray(getattr(sol, k), float) for k in ("q", "qd", "v", "tau", "h", "T", "cost")}
    data.update(index=np.arange(len(qs)), q_start=np.asarray(qs), q_goal=np.asarray(qg),
                converged=np.asarray(sol.converged, bool), status=np.asarray(sol.status),
                max_violation=np.asarray(sol.max_violation["overall"], float),
                metadata={"robot": "serial3", "N": N, "weights_text": WEIGHTS_TEXT,
                          "limits": {"h_max": float(robot.limits.h_max)}})
    return data, secs


def take(data, rows):
    return {k: (v if k == "metadata" else np.asarray(v)[rows]) for k, v in data.items()}


# ----------------------------------------------------------------------------- training
def rmse(a, b, axis=None):
    return np.sqrt(np.mean((np.asarray(a) - np.asarray(b)) ** 2, axis=axis))


def fit_eval(X, Y, tr, te, n_rules, epochs, noise=0.0, seed=0, **options):
    """Train on rows ``tr`` (inputs optionally disturbed by Gaussian noise of standard
    deviation ``noise`` x each input's range), no early stopping (fixed epochs, as the
    thesis); RMSE on the training rows (as trained) and on the test rows (clean, and
    disturbed the same way)."""
    Xtr, Ytr, Xte, Yte = X[tr], Y[tr], X[te], Y[te]
    rng = np.random.default_rng(seed)
    span = Xtr.max(0) - Xtr.min(0)
    Xtr_fit = Xtr + noise * span * rng.standard_normal(Xtr.shape)
    Xte_noisy = Xte + noise * span * rng.standard_normal(Xte.shape)
    kw = dict(epochs=epochs, validation=0.0, ridge=1e-6, **options)
    kw.update(n_rules=n_rules) if n_rules else kw.update(radius=0.5)
    t0 = time.perf_counter()
    model, hist = anfis.train(Xtr_fit, Ytr, **kw)
    jax.block_until_ready(model.theta)
    seconds = time.perf_counter() - t0
    pred = lambda x: np.asarray(model.predict(x)).reshape(len(x), -1)  # noqa: E731
    p_tr, p_te, p_ten = pred(Xtr_fit), pred(Xte), pred(Xte_noisy)
    lin = linear_baseline(Xtr_fit, Ytr, Xte)
    return dict(model=model, hist=hist, seconds=seconds, rules=model.n_rules, epochs=hist.epochs,
                train=rmse(p_tr, Ytr, 0), test=rmse(p_te, Yte, 0), test_noisy=rmse(p_ten, Yte, 0),
                linear=rmse(lin, Yte, 0), range=Y.max(0) - Y.min(0), pred_test=p_te)


def thesis_models(data, seed=0, **options):
    """The three thesis mappings on the thesis' inputs, split 90 / 10 by trajectory."""
    out = {}
    for mapping, (rules, epochs) in SETUPS.items():
        X, Y, traj, names_in, names_out = view(data, mapping)
        tr, te = split(traj, 0.1)
        r = fit_eval(X, Y, tr, te, rules, epochs, seed=seed, **options)
        r.update(X=X, Y=Y, tr=tr, te=te, traj=traj, names_in=names_in, names_out=names_out)
        # rules that the thesis' own clustering settings give on these training samples
        XY = np.c_[X[tr], Y[tr]]
        r["thesis_clustering_rules"] = int(subclust(XY, **THESIS_CLUSTERING).centers.shape[0])
        small = dict(THESIS_CLUSTERING, radius=0.01)
        r["thesis_clustering_rules_small"] = int(subclust(XY, **small).centers.shape[0])
        out[mapping] = r
    return out


def fmt_outputs(values, names, digits=3):
    return ", ".join(f"{n} {v:.{digits}g} {unit_of(n)}" for v, n in zip(values, names))


def relative(values, ranges):
    return float(np.sqrt(np.mean((np.asarray(values) / np.asarray(ranges)) ** 2)))


# ----------------------------------------------------------------------------- figures
def plot_memberships(res, path):
    """Fig. 6.12: NeFuMOP's Gaussian memberships per input, before and after training."""
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D

    before, after = res["hist"].initial, res["model"]
    X = res["X"][res["tr"]]
    labels = ["x [m]", "y [m]", "xd [m/s]", "yd [m/s]"]
    fig, axes = plt.subplots(2, 2, figsize=(10, 6.5))
    for i, ax in enumerate(axes.ravel()):
        lo, hi = X[:, i].min(), X[:, i].max()
        u = np.linspace(lo - 0.1 * (hi - lo), hi + 0.1 * (hi - lo), 400)
        for model, style in ((before, dict(color="0.55", ls="--", lw=1.0)), (after, dict(color="C0", lw=1.4))):
            c, s = model.memberships()
            for r in range(c.shape[0]):
                ax.plot(u, np.exp(-0.5 * ((u - c[r, i]) / s[r, i]) ** 2), **style)
        ax.set_xlabel(labels[i])
        ax.set_ylabel("membership degree [-]")
        ax.set_ylim(0, 1.05)
    handles = [Line2D([], [], color="0.55", ls="--", label="before training (subtractive clustering)"),
               Line2D([], [], color="C0", label=f"after {res['epochs']} epochs")]
    fig.suptitle(f"NeFuMOP memberships ({res['rules']} rules, one curve per rule)", y=0.99)
    fig.legend(handles=handles, loc="upper center", ncol=2, bbox_to_anchor=(0.5, 0.955))
    fig.tight_layout(rect=(0, 0, 1, 0.9))
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_generalisation(robot, plans, raw, exact, idx, path):
    """Figs. 5.13-5.14 / 6.14-6.15: new pairs planned online against their exact optima."""
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D

    fig, axes = plt.subplots(len(idx), 3, figsize=(13, 3.6 * len(idx)), squeeze=False)
    fk = jax.jit(jax.vmap(robot.forward_kinematics))
    kinds = (("exact optimum (jtraj.solve)", "k", "-"), ("ANFIS plan, repaired", "C0", "--"),
             ("ANFIS closed loop, raw", "C3", ":"))
    for row, i in enumerate(idx):
        ax_q, ax_tau, ax_xy = axes[row]
        for (label, color, ls), (q, tau, h) in zip(kinds, (exact(i), plans(i), raw(i))):
            t = np.r_[0.0, np.cumsum(h)]
            for j in range(q.shape[1]):
                ax_q.plot(t, q[:, j], color=color, ls=ls, lw=1.3)
                ax_tau.step(t[:-1], tau[:, j] / np.asarray(robot.limits.tau_max)[j], where="post", color=color,
                            ls=ls, lw=1.1)
            p = np.asarray(fk(jnp.asarray(q)))
            ax_xy.plot(p[:, 0], p[:, 1], color=color, ls=ls, lw=1.3)
        p_ends = np.asarray(fk(jnp.asarray(np.stack([exact(i)[0][0], exact(i)[0][-1]]))))
        ax_xy.plot(*p_ends[0], "ko", ms=6)
        ax_xy.plot(*p_ends[1], "k*", ms=10)
        ax_q.set_xlabel("t [s]")
        ax_q.set_ylabel("q1, q2, q3 [rad]")
        ax_tau.set_xlabel("t [s]")
        ax_tau.set_ylabel("tau_j / tau_max,j [-]")
        ax_tau.axhline(1, color="0.7", lw=0.8)
        ax_tau.axhline(-1, color="0.7", lw=0.8)
        ax_xy.set_xlabel("x [m]")
        ax_xy.set_ylabel("y [m]")
        ax_xy.set_aspect("equal", adjustable="datalim")
        ax_q.set_title(f"new pair {i + 1}" + (" (box twice as wide)" if i >= NEW_PAIRS else ""))
    handles = [Line2D([], [], color=c, ls=ls, label=lab) for lab, c, ls in kinds]
    handles += [Line2D([], [], color="k", marker="o", ls="", label="start"),
                Line2D([], [], color="k", marker="*", ms=10, ls="", label="goal")]
    fig.legend(handles=handles, loc="upper center", ncol=5)
    fig.tight_layout(rect=(0, 0, 1, 0.965))
    fig.savefig(path, dpi=100)
    plt.close(fig)


# ----------------------------------------------------------------------------- main
def main():
    t_start = time.perf_counter()
    records = []
    robot = robots.get("serial3")
    q0, qg = scenario(robot)
    qs, qgs = draw_pairs(q0, qg, PAIRS, SEED, SPREAD)
    ns, ngs = draw_pairs(q0, qg, NEW_PAIRS, SEED + 1, SPREAD)
    ws, wgs = draw_pairs(q0, qg, WIDE_PAIRS, SEED + 2, 2 * SPREAD)
    # the new pairs' exact optima come from the same compiled batch as the training set
    all_data, solve_s = solve_pairs(robot, np.r_[qs, ns, ws], np.r_[qgs, ngs, wgs], record=(records, [
        ("training pair", range(PAIRS)), ("new pair", range(PAIRS, PAIRS + NEW_PAIRS)),
        ("wide pair", range(PAIRS + NEW_PAIRS, PAIRS + NEW_PAIRS + WIDE_PAIRS))]))
    data = take(all_data, np.arange(PAIRS))
    new = take(all_data, np.arange(PAIRS, PAIRS + NEW_PAIRS + WIDE_PAIRS))
    n_conv = int(data["converged"].sum())
    print(f"solved {len(all_data['T'])} pairs in {solve_s:.1f} s", flush=True)

    # --- the thesis' three mappings, thesis inputs
    res = thesis_models(data)
    tsuk = thesis_models(data, **THESIS_KIND)
    # NeFOTC on narrower sets of pairs (same compiled solve: the batch keeps its shape)
    narrow = {}
    for k, spread in enumerate(SPREADS):
        a, b = draw_pairs(q0, qg, PAIRS, SEED + 10 + k, spread)
        d_s, _ = solve_pairs(robot, np.r_[a, ns, ws], np.r_[b, ngs, wgs],
                             record=(records, [(f"+- {spread:g} rad pair", range(PAIRS))]))
        d_s = take(d_s, np.arange(PAIRS))
        X, Y, traj, _, _ = view(d_s, "nefotc")
        tr, te = split(traj, 0.1)
        narrow[spread] = dict(fit_eval(X, Y, tr, te, *SETUPS["nefotc"]), conv=int(d_s["converged"].sum()))
    print("thesis models:", {m: (r["rules"], r["seconds"]) for m, r in res.items()}, flush=True)
    # the same models on a split by random samples (test samples interleaved with training
    # samples of the same trajectories), to read the thesis' test RMSE below its train RMSE
    interleaved = {}
    for mapping in ("nefotc", "nefumop"):
        r = res[mapping]
        te = np.zeros(len(r["X"]), bool)
        te[np.random.default_rng(SEED).choice(len(te), len(te) // 10, replace=False)] = True
        interleaved[mapping] = fit_eval(r["X"], r["Y"], ~te, te, r["rules"] if mapping == "nefotc" else None,
                                        SETUPS[mapping][1])
    # repeat of the training (compiled programs warm) for the training time
    warm = {m: fit_eval(r["X"], r["Y"], r["tr"], r["te"], SETUPS[m][0], SETUPS[m][1])["seconds"]
            for m, r in res.items()}
    # --- input noise
    noisy = {(m, lvl): fit_eval(res[m]["X"], res[m]["Y"], res[m]["tr"], res[m]["te"], SETUPS[m][0],
                                SETUPS[m][1], noise=lvl, seed=SEED + 7)
             for m in ("nefotc", "nefumop") for lvl in NOISE}
    # NeFIK: tip error of the predicted joint angles
    fk = jax.jit(jax.vmap(robot.forward_kinematics))
    ik = res["nefik"]
    tip_err = np.linalg.norm(np.asarray(fk(jnp.asarray(ik["pred_test"]))) - ik["X"][ik["te"]], axis=1)
    # share of NeFIK's joint-angle error along the self-motion (null space of the 2 x 3
    # tip Jacobian at the true configuration): the redundancy the tip point leaves open
    q_true = ik["Y"][ik["te"]]
    J = np.asarray(jax.jit(jax.vmap(jax.jacfwd(robot.forward_kinematics)))(jnp.asarray(q_true)))
    null = np.cross(J[:, 0], J[:, 1])
    null /= np.linalg.norm(null, axis=1, keepdims=True)
    e = ik["pred_test"] - q_true
    null_share = float(np.sum(np.sum(e * null, 1) ** 2) / np.sum(e**2))

    plot_memberships(res["nefumop"], FIGURES / "neurofuzzy_memberships.png")
    print("noise study and memberships done", flush=True)

    # --- generalisation: jtraj's online planner (goal offset and phase as inputs)
    from jtraj.online import Planner
    from jtraj.repair import cost_of

    t0 = time.perf_counter()
    otc, otc_rep, _ = train_mapping(data, "nefotc", n_rules=SETUPS["nefotc"][0], epochs=SETUPS["nefotc"][1],
                                    augment="none")
    mop, mop_rep, _ = train_mapping(data, "nefumop", n_rules=SETUPS["nefotc"][0], epochs=SETUPS["nefumop"][1],
                                    augment="none")
    planner_s = time.perf_counter() - t0
    print(f"planner models trained in {planner_s:.1f} s", flush=True)
    planner = Planner(otc, periods=mop)
    raw_planner = Planner(otc, periods=mop, correct=False)
    plans = planner.plan(new["q_start"], new["q_goal"])
    raw = raw_planner.plan(new["q_start"], new["q_goal"])
    jax.block_until_ready(plans.T)
    t0 = time.perf_counter()
    for _ in range(5):
        jax.block_until_ready(planner.plan(new["q_start"], new["q_goal"]).T)
    plan_ms = (time.perf_counter() - t0) / 5 * 1e3
    feasible = np.asarray(planner.feasible(plans))
    W = jtraj.Weights.parse(WEIGHTS_TEXT)
    cost = jax.jit(jax.vmap(lambda q, qd, tau, h: cost_of(robot, W, q, qd, tau, h)))
    exact_cost = np.asarray(cost(*(jnp.asarray(new[k]) for k in ("q", "qd", "tau", "h"))))
    plan_cost = np.asarray(plans.cost)
    # independent re-check of the repaired plans: decoupled recursion and inverse dynamics
    # recomputed here from (v, h), bounds compared with NumPy
    lim = robot.limits
    recheck = []
    idyn = jax.jit(jax.vmap(jax.vmap(robot.inverse_dynamics)))
    v, h = np.asarray(plans.v), np.asarray(plans.h)
    q = np.zeros((len(h), N + 1, 3))
    qd = np.zeros_like(q)
    q[:, 0] = new["q_start"]
    for k in range(N):
        q[:, k + 1] = q[:, k] + h[:, k, None] * qd[:, k] + 0.5 * h[:, k, None] ** 2 * v[:, k]
        qd[:, k + 1] = qd[:, k] + h[:, k, None] * v[:, k]
    tau = np.asarray(idyn(jnp.asarray(q[:, :-1]), jnp.asarray(qd[:, :-1]), jnp.asarray(v)))
    tmax, qdmax, qddmax = (np.asarray(x) for x in (lim.tau_max, lim.qd_max, lim.qdd_max))
    for b in range(len(h)):
        parts = {"torque": np.max(np.abs(tau[b]) / tmax), "velocity": np.max(np.abs(qd[b]) / qdmax),
                 "acceleration": np.max(np.abs(v[b]) / qddmax),
                 "period": max(np.max(h[b]) / float(lim.h_max), float(lim.h_min) / np.min(h[b]))}
        worst = max(parts, key=parts.get)
        recheck.append((parts[worst], np.linalg.norm(q[b, -1] - new["q_goal"][b]), np.linalg.norm(qd[b, -1]),
                        worst))

    def exact_traj(i):
        return new["q"][i], new["tau"][i], new["h"][i]

    def plan_traj(i):
        return np.asarray(plans.q[i]), np.asarray(plans.tau[i]), np.asarray(plans.h[i])

    def raw_traj(i):
        return np.asarray(raw.q[i]), np.asarray(raw.tau[i]), np.asarray(raw.h[i])

    plot_generalisation(robot, plan_traj, raw_traj, exact_traj, [0, 1, NEW_PAIRS],
                        FIGURES / "neurofuzzy_generalisation.png")

    write_status("neurofuzzy", records, t_start)
    write_section("neurofuzzy", report(robot, q0, qg, data, n_conv, solve_s, res, interleaved, warm, noisy,
                                       tip_err, new, plans, raw, feasible, recheck, exact_cost, plan_cost,
                                       otc_rep, mop_rep, planner_s, plan_ms, null_share, narrow, tsuk))


# ----------------------------------------------------------------------------- report
def report(robot, q0, qg, data, n_conv, solve_s, res, interleaved, warm, noisy, tip_err, new, plans, raw,
           feasible, recheck, exact_cost, plan_cost, otc_rep, mop_rep, planner_s, plan_ms, null_share, narrow, tsuk):
    lim = robot.limits
    T = data["T"][data["converged"]]
    h_at_max = float(np.mean(data["h"][data["converged"]] >= float(lim.h_max) * (1 - 1e-3)))
    lines = [
        "## Neuro-fuzzy planners: NeFIK, NeFOTC, NeFuMOP (Khoukhi ch. 5-6)", "",
        f"Training set: {PAIRS} serial3 optima (horizontal plane, Table 6.1 masses; |tau| <= "
        f"{', '.join(f'{x:g}' for x in np.asarray(lim.tau_max))} N m, h in [{float(lim.h_min):g}, "
        f"{float(lim.h_max):g}] s), N = {N} samples each, weights `{WEIGHTS_TEXT}`, T_max = {T_MAX:g} s, "
        f"one `jtraj.solve_batch` call ({solve_s:.1f} s, compilation included; {n_conv}/{PAIRS} CONVERGED). "
        f"Starts uniform in q_start +- {SPREAD} rad per joint around the thesis' (0, 30, 30) deg, goals "
        f"around the IK configuration of its goal tip (1.35, 1.30) m "
        f"(({', '.join(f'{np.degrees(x):.1f}' for x in qg)}) deg): the thesis' generating pairs are not "
        f"published. T from {T.min():.2f} to {T.max():.2f} s, {100 * h_at_max:.0f} % of the periods within 0.1 % "
        "of h_max. "
        f"Split 90 / 10 by trajectory (of the {n_conv} converged trajectories the last "
        f"{len(np.unique(res['nefotc']['traj'][res['nefotc']['te']]))} are the test set, never seen in training), "
        "training by jtraj's hybrid rule (least squares + Levenberg-Marquardt), Gaussian memberships from "
        "subtractive clustering, fixed epochs (no early stopping). "
        "RMSE per output in its own unit; 'relative' pools the outputs divided by their ranges in the data.",
        "",
        "### Tables 5.3 and 6.3: accuracy and training time", "",
    ]
    pooled = lambda x: float(np.sqrt(np.mean(np.asarray(x) ** 2)))  # noqa: E731
    rows = []
    for m, r in res.items():
        names = r["names_out"]
        pub = PUBLISHED[m]
        for label, rr, secs in (("Sugeno", r, f"{r['seconds']:.1f} ({warm[m]:.1f} warm)"),
                                ("Tsukamoto", tsuk[m], f"{tsuk[m]['seconds']:.1f}")):
            rows.append((
                f"{m}, {label}: {', '.join(r['names_in'])} -> {', '.join(names)}",
                f"{rr['rules']} / {rr['epochs']}" + ("" if SETUPS[m][0] else " (radius 0.5)"),
                fmt_outputs(rr["train"], names), fmt_outputs(rr["test"], names),
                f"{relative(rr['train'], rr['range']):.2e} / {relative(rr['test'], rr['range']):.2e}",
                f"{pooled(rr['test']) / pooled(rr['linear']):.2f}", secs,
                f"{pub[0]} / {pub[1]}, {pub[2]} s" if label == "Tsukamoto" else "",
            ))
    for m, rep in (("nefotc", otc_rep), ("nefumop", mop_rep)):
        names, rng_ = res[m]["names_out"], res[m]["range"]
        tr_ = [rep["train_rmse_per_output"][n] for n in names]
        te_ = [rep["test_rmse_per_output"][n] for n in names]
        rows.append((
            f"{m}, jtraj inputs: {', '.join(rep['inputs'])}", f"{rep['n_rules']} / {rep['epochs']}",
            fmt_outputs(tr_, names), fmt_outputs(te_, names),
            f"{relative(tr_, rng_):.2e} / {relative(te_, rng_):.2e}", f"{rep['ratio_to_linear']:.2f}",
            f"{rep['seconds']:.1f}", "-"))
    lines.append(table(rows, header=("model", "rules / epochs", "train RMSE", "test RMSE",
                                     "relative train / test", "test RMSE / linear map's",
                                     "training s (compile incl.)", "published train / test, time")))
    n_thesis = ", ".join(f"{m} {r['thesis_clustering_rules']}" for m, r in res.items())
    n_small = ", ".join(f"{m} {r['thesis_clustering_rules_small']}" for m, r in res.items())
    lines += ["", "'Sugeno': first-order Sugeno consequents; 'Tsukamoto': the thesis' monotone logistic "
              "consequents. Both cluster with jtraj's default ratios (squash 1.25, accept 0.5, reject 0.15), "
              "the radius set by bisection to give the published number of rules (NeFuMOP's is not published: "
              "radius 0.5). The thesis' own clustering settings (radius 0.9, squash 0.5, accept 1.0, reject "
              f"0.8) give {n_thesis} rules on these training samples, not the published 6 and 9: with accept 1.0 "
              "and reject 0.8 the clustering stops at the first candidate whose potential falls to 0.8 of the "
              "first centre's, and above that a candidate must still pass the distance test; radius 0.01 "
              f"gives {n_small}. The last two rows add the goal offset and the phase k/N "
              "to the inputs (jtraj's defaults, "
              "`jtraj.mappings.train_mapping`, with early stopping on the last 10 % of the training "
              "trajectories): over pairs with different goals the same (q, qd) is driven towards different "
              "goals, so the thesis' mappings are not functions of their inputs, and on them 9 rules get little "
              "below the affine least-squares map (column 'test RMSE / linear map's'). These two models plan "
              "the new pairs below."]
    lines += ["", f"NeFIK's predicted joint angles put the tip {np.median(tip_err) * 1e3:.1f} mm (median) / "
              f"{tip_err.max() * 1e3:.1f} mm (max) from the test points (forward kinematics of the prediction): "
              f"{100 * null_share:.0f} % of its squared joint-angle error lies along the arm's self-motion (the "
              "null space of the 2 x 3 tip Jacobian), which the tip point does not determine. The thesis' "
              "1e-4 needs joint angles that are a function of the tip point (one redundancy resolution)."]

    ratio = {m: relative(res[m]["test"], res[m]["range"]) / relative(res[m]["train"], res[m]["range"])
             for m in ("nefotc", "nefumop")}
    ratio_i = {m: relative(interleaved[m]["test"], res[m]["range"]) / relative(interleaved[m]["train"],
                                                                                 res[m]["range"])
               for m in ("nefotc", "nefumop")}
    tau_span = float(np.max(res["nefotc"]["range"]))
    rows = [(f"+- {SPREAD}", f"{n_conv}/{PAIRS}", f"{relative(res['nefotc']['train'], res['nefotc']['range']):.2e}",
             f"{relative(res['nefotc']['test'], res['nefotc']['range']):.2e}",
             fmt_outputs(res["nefotc"]["test"], res["nefotc"]["names_out"]))]
    for spread, r in narrow.items():
        rows.append((f"+- {spread}", f"{r['conv']}/{PAIRS}", f"{relative(r['train'], r['range']):.2e}",
                     f"{relative(r['test'], r['range']):.2e}", fmt_outputs(r["test"], res["nefotc"]["names_out"])))
    lines += ["", "**Why the published RMSEs are not comparable number for number.** (1) Units: the thesis "
              "gives one RMSE per model over outputs of different units (torques in N m up to "
              f"{float(np.max(np.asarray(lim.tau_max))):g}, periods in s below {float(lim.h_max):g}) and does not "
              "say whether the data were scaled; read as N m, NeFOTC's 3.77e-3 would be "
              f"{3.77e-3 / tau_span:.1e} of the torque range our data span, read as scaled data 3.77e-3 of it; "
              f"9 rules reach {relative(res['nefotc']['train'], res['nefotc']['range']):.2e} here. "
              "(2) The data: the thesis' 100 pairs are not published. NeFOTC's error falls with the spread of "
              "the pairs (thesis inputs, 9 rules, 10 epochs, boxes of half-width below around the same start "
              "and goal, each set from one more solve_batch call):", "",
              table(rows, header=("start / goal box [rad]", "converged", "relative train RMSE",
                                  "relative test RMSE", "test RMSE")),
              "", f"The error scales about linearly with the spread; at +- {min(narrow)} rad the relative "
              f"training RMSE is {relative(narrow[min(narrow)]['train'], narrow[min(narrow)]['range']):.1e}, the "
              "order of the published 3.77e-3 if the thesis' data were scaled, from a set of nearly identical "
              "trajectories. "
              "(3) The split: the thesis' test RMSE is below its train RMSE "
              "(1.29e-3 < 3.77e-3; 2.39e-4 < 4.57e-3, 19x). Measured here, test / train relative RMSE is "
              f"{ratio['nefotc']:.2f} (NeFOTC) and {ratio['nefumop']:.2f} (NeFuMOP) on held-out trajectories and "
              f"{ratio_i['nefotc']:.2f} / {ratio_i['nefumop']:.2f} on 10 % of the samples drawn at random "
              "(interleaved with training samples of the same trajectories); neither split gives a test "
              "error far below the training error, so the thesis' test sets differ from its training sets in "
              "a way its text does not describe."]

    lines += ["", "### Tables 5.4 and 6.4: input noise", "",
              "Gaussian noise of standard deviation 0.5 % (Table 6.4) or 5 % (Table 5.4, NeFOTC on 5 %-disturbed "
              "data) of each input's range added to the training inputs; the test RMSE on clean and on equally "
              "disturbed test inputs. Relative RMSE as above.", ""]
    rows = []
    for m in ("nefotc", "nefumop"):
        clean = res[m]
        rows.append((m, "none", f"{relative(clean['train'], clean['range']):.2e}",
                     f"{relative(clean['test'], clean['range']):.2e}", "-",
                     "3.77e-3 / 1.29e-3" if m == "nefotc" else "4.57e-3 / 2.39e-4"))
        for lvl in NOISE:
            r = noisy[(m, lvl)]
            pub = {("nefotc", 0.05): "2.415e-3 (Table 5.4)", ("nefumop", 0.005): "5.91e-3 / 5.01e-3 / 6.21e-3 "
                   "(Table 6.4)"}.get((m, lvl), "-")
            rows.append((m, f"{100 * lvl:g} %", f"{relative(r['train'], clean['range']):.2e}",
                         f"{relative(r['test'], clean['range']):.2e}",
                         f"{relative(r['test_noisy'], clean['range']):.2e}", pub))
    lines.append(table(rows, header=("model", "input noise", "train (noisy inputs)", "test, clean inputs",
                                     "test, noisy inputs", "published")))
    lines += ["", "Table 6.4's three values are quoted as printed; which sets they belong to is not distilled "
              "in SCIENCE.md, so they are listed beside our three columns without a pairing."]

    nm = res["nefumop"]
    lines += ["", "### Fig. 6.12: membership functions", "",
              f"`figures/neurofuzzy_memberships.png`: NeFuMOP's {nm['rules']} Gaussian memberships on each input "
              f"(x, y [m]; xd, yd [m/s]) after subtractive clustering (dashed) and after {nm['epochs']} epochs "
              "(solid). Largest centre shift over the inputs' ranges: "
              f"{shift(nm):.2f}; width ratio after / before: {width_ratio(nm)}."]

    # generalisation
    nb = NEW_PAIRS + WIDE_PAIRS
    gap = 100 * (plan_cost / exact_cost - 1)
    raw_goal = np.asarray(raw.goal_error)
    rows = []
    for i in range(nb):
        rr = recheck[i]
        rows.append((f"{i + 1}" + (" (wide)" if i >= NEW_PAIRS else ""),
                     "yes" if feasible[i] else "no", f"{rr[0]:.3f} ({rr[3]})", f"{rr[1]:.1e} / {rr[2]:.1e}",
                     f"{raw_goal[i]:.3f}", f"{float(plans.T[i]):.3f}",
                     f"{float(new['T'][i]):.3f} ({jtraj.Status(int(new['status'][i])).name}, violation "
                     f"{float(new['max_violation'][i]):.1e})",
                     f"{gap[i]:+.1f} %" if bool(new["converged"][i]) else "- (no optimum)",
                     "yes" if bool(plans.ood[i]) else "no"))
    lines += ["", "### Figs. 5.13-5.14 and 6.14-6.15: new start/goal pairs, planned online", "",
              "The thesis' (q, qd) -> tau and (x, y, xd, yd) -> (tau, h) carry no goal, so they cannot steer to a "
              "new goal; jtraj's online planner (`jtraj.online.Planner`, closed loop) runs a NeFOTC with the "
              "goal offset and the phase k/N as extra inputs, (q_goal - q, qd, k/N) -> tau, and a NeFuMOP "
              "(x, y, xd, yd, goal offset, k/N) -> (tau, h) for the periods, trained on the same "
              f"{otc_rep['n_trajectories_train']} trajectories (the 'jtraj inputs' rows of the first table; "
              f"{planner_s:.1f} s for both). The controller's torque "
              "drives the robot's forward dynamics for the predicted period; the repair (`jtraj.repair`) "
              "projects the result onto the goal and time-scales it into the bounds. "
              f"{NEW_PAIRS} new pairs from the training boxes and {WIDE_PAIRS} from boxes twice as wide; exact "
              "optima from the same solve_batch call as the training set. 'Bounds' is the largest of |tau|/tau_max, "
              "|qd|/qd_max, |qdd|/qdd_max and the period ratios, recomputed here from the plan's (v, h) by the "
              "decoupled recursion and the robot's inverse dynamics (feasible: <= 1).", "",
              table(rows, header=("pair", "planner: feasible", "bounds (re-checked)", "goal error [rad] / [rad/s]",
                                  "raw closed-loop goal error [rad]", "plan T [s]", "exact T [s]",
                                  "cost gap to exact", "flagged out of distribution")),
              "",
              infeasible_text(robot, plans, feasible, recheck, new),
              "",
              f"`figures/neurofuzzy_generalisation.png`: pairs 1, 2 and the first wide pair; joint angles, torques "
              f"over their bounds and the tip path. One batched plan of the {nb} pairs takes {plan_ms:.1f} ms "
              "(jitted, warm). The thesis' figures show the planned motion reaching each new goal; here the "
              "raw closed loop misses the goal by the column above and the repair lands on it."]
    lines += ["", f"{wall_and_cpu(T_START)} {machine()}; a machine shared with other jobs, so times are upper "
              "bounds."]
    return "\n".join(lines)


def infeasible_text(robot, plans, feasible, recheck, new):
    """Why the plans the planner reports infeasible are so (measured on the plans)."""
    bad = [i for i in range(len(feasible)) if not feasible[i]]
    if not bad:
        return "Every plan is feasible."
    T_cap = N * float(robot.limits.h_max)
    at_cap = [i for i in bad if float(plans.T[i]) >= T_cap * (1 - 1e-6)]
    text = "Infeasible plans: " + ", ".join(f"pair {i + 1} ({recheck[i][3]} bound exceeded {recheck[i][0]:.2f}x)"
                                            for i in bad) + ". "
    if at_cap:
        text += (f"Pair(s) {', '.join(str(i + 1) for i in at_cap)} already run at T = N h_max = {T_cap:g} s: the "
                 "repair's time scaling cannot slow them further within the period box, so the excess of the "
                 "predicted shape remains (reported, `feasible` False), as `jtraj.online` documents.")
    none = [i for i in bad if not bool(new["converged"][i])]
    if none:
        text += (f" For pair(s) {', '.join(str(i + 1) for i in none)} the exact solver finds no feasible "
                 "trajectory either (status in the table), so no plan of N samples within the period box exists "
                 "that the solver can find.")
    return text


def shift(r):
    c0, _ = r["hist"].initial.memberships()
    c1, _ = r["model"].memberships()
    span = r["X"][r["tr"]].max(0) - r["X"][r["tr"]].min(0)
    return float(np.max(np.abs(c1 - c0) / span))


def width_ratio(r):
    _, s0 = r["hist"].initial.memberships()
    _, s1 = r["model"].memberships()
    q = s1 / s0
    return f"{q.min():.2f} to {q.max():.2f}"


if __name__ == "__main__":
    main()
