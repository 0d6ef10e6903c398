"""ANFIS models of optimal-trajectory datasets (the thesis' NeFOTC, NeFuMOP, NeFIK) and a
planner mapping, with honest splits and baselines.

A dataset is any mapping with numpy arrays (``P`` pairs, ``N`` intervals, ``n``
joints): ``q_start (P, n)``, ``q_goal (P, n)``, ``converged (P,)``, ``q (P, N+1, n)``,
``qd (P, N+1, n)``, ``v (P, N, n)``, ``tau (P, N, m)``, ``h (P, N)`` and ``metadata``
(with at least ``"robot"``), e.g. ``jtraj.dataset.load(path)``.

Mappings (one row per time sample of each converged trajectory):

* ``nefotc``: ``(q_k, qd_k) -> tau_k``, k = 0..N-1 (optimal trajectory controller);
* ``nefumop``: ``(p_k, pd_k) -> (tau_k, h_k)`` with the task point ``p = f(q)`` and
  ``pd = J(q) qd`` (motion planner);
* ``nefik``: ``p_k -> q_k``, k = 0..N (inverse kinematics);
* ``plan``: one row per trajectory, ``(q_start, q_goal) -> (v (N n), h (N))``: the
  whole trajectory at once, which is what :class:`jtraj.online.Planner` needs (the three
  thesis mappings carry no goal in their inputs, so they cannot plan a new start/goal
  pair on their own).

Over a dataset of random start/goal pairs the thesis' nefotc and nefumop are not
functions of their inputs; :func:`train_mapping` adds by default the offset to the
trajectory's goal and the sample's phase ``k / N`` (:data:`DEFAULT_INPUTS`, :func:`view`).

Split: the **last 10 % of the converged trajectories in dataset order** are the test
set, never seen in training; early stopping uses the last 10 % of the remaining
training trajectories. Baselines on the same split: linear least squares (with bias)
and k-nearest-neighbour lookup (k = 5, inputs standardised by the training data).
"""

from __future__ import annotations

import math
import time

import numpy as np

from . import _progress

MAPPINGS = ("nefotc", "nefumop", "nefik", "plan")
PLAN_RULES = 8  # default rules of the plan mapping (see train_mapping)
REQUIRED = ("q_start", "q_goal", "converged", "q", "qd", "tau", "h", "metadata")


def load_data(data):
    """``data`` itself if it is a mapping, else ``jtraj.dataset.load(data)``."""
    if isinstance(data, (str, bytes)) or hasattr(data, "__fspath__"):
        from jtraj import dataset

        return dataset.load(str(data))
    return data


def _check(data):
    missing = [k for k in REQUIRED if k not in data]
    if missing:
        raise ValueError(f"dataset lacks the fields {missing}")
    if "robot" not in data["metadata"]:
        raise ValueError("dataset metadata lacks the robot name")


def view(data, mapping: str = "nefotc", *, goal: bool | str = False, phase: bool = False):
    """``(X, Y, traj, input_names, output_names)`` for the converged trajectories;
    ``traj[i]`` is the dataset index of row i's trajectory.

    ``goal=True`` or ``"append"`` (``nefotc`` and ``nefumop`` only) appends the offset
    to the trajectory's goal to the inputs: ``q_goal - q_k`` (inputs ``dq_goal1..n``)
    for ``nefotc``, ``p_goal - p_k`` (``dx_goal, ...``, ``p_goal = f(q_goal)``) for
    ``nefumop``; ``goal="relative"`` replaces the position by that offset
    (``(q_goal - q_k, qd_k) -> tau_k``: goal-relative coordinates, fewer inputs).
    Over a dataset of random start/goal pairs the plain mappings are not
    functions (the same ``(q, qd)`` is crossed towards different goals with opposite
    torques), so no regressor beats the linear baseline by much on them; with the goal
    offset they are (see docs/guides/anfis.md).

    ``phase=True`` (``nefotc`` and ``nefumop``) appends the sample's place in its
    trajectory, ``k / N`` (input ``phase``), after the other inputs.
    """
    if phase and mapping not in ("nefotc", "nefumop"):
        raise ValueError(f"the phase input is defined for the mappings nefotc and nefumop, not {mapping!r}")
    data = load_data(data)
    X, Y, traj, names_in, names_out = _goal_view(data, mapping, goal)
    if not phase:
        return X, Y, traj, names_in, names_out
    N = int(np.shape(data["h"])[1])
    k = np.tile(np.arange(N), len(X) // N)  # rows are N samples per converged trajectory, in order
    return np.c_[X, k / N], Y, traj, names_in + ["phase"], names_out


def _goal_mode(goal):
    """``goal`` as False, "append" or "relative" (True means "append", "none" False)."""
    if goal is True:
        return "append"
    if goal is False or goal is None or goal == "none":
        return False
    if goal not in ("append", "relative"):
        raise ValueError(f"goal must be False, True, 'none', 'append' or 'relative', got {goal!r}")
    return goal


def _goal_view(data, mapping, goal):
    X, Y, traj, names_in, names_out = _view(data, mapping)
    goal = _goal_mode(goal)
    if not goal:
        return X, Y, traj, names_in, names_out
    if mapping not in ("nefotc", "nefumop"):
        raise ValueError(f"goal inputs are defined for the mappings nefotc and nefumop, not {mapping!r}")
    qg = np.asarray(data["q_goal"], float)[traj]
    if mapping == "nefotc":
        xg, d = qg, qg.shape[1]
        off_names = [f"dq_goal{j + 1}" for j in range(d)]
    else:
        from jtraj.dataset import views

        xg, _ = views.task_state(views.robot_of(data), qg, np.zeros_like(qg))
        d = xg.shape[1]
        off_names = ["d" + c + "_goal" for c in names_in[:d]]
    names = goal_blocks(names_in[:d], names_in[d:], off_names, goal, names=True)
    X = np.concatenate(goal_blocks(X[:, :d], X[:, d:], xg, goal), axis=1)
    return X, Y, traj, [n for block in names for n in block], names_out


def goal_blocks(x, xd, xg, goal, *, names: bool = False) -> list:
    """The input blocks of nefotc / nefumop before the phase, for the position ``x``
    (``q`` or the task point), its velocity ``xd`` and the goal ``xg`` (with ``names``,
    ``xg`` is the offset's names): ``relative`` ``[xg - x, xd]``, ``append``
    ``[x, xd, xg - x]``, none ``[x, xd]``. Shared by :func:`view` and the online
    planner (:func:`jtraj.online.model_inputs`), so that both build the same inputs."""
    off = xg if names else xg - x
    return {"relative": [off, xd], "append": [x, xd, off]}.get(goal or False, [x, xd])


def _view(data, mapping):
    from jtraj.dataset import views

    if mapping not in MAPPINGS:
        raise ValueError(f"mapping must be one of {MAPPINGS}, got {mapping!r}")
    data = load_data(data)
    _check(data)
    conv = np.asarray(data["converged"], bool)
    if not conv.any():
        raise ValueError("dataset has no converged trajectory")
    # the fields used, with row positions as the trajectory ids (a partial dataset's
    # "index" holds pair indices, which are not positions)
    data = {k: data[k] for k in REQUIRED + (("v",) if mapping == "plan" else ())}
    data["index"] = np.arange(conv.size)
    n, m = np.shape(data["q"])[2], np.shape(data["tau"])[2]
    jn, jdn, tn = [f"q{j + 1}" for j in range(n)], [f"qd{j + 1}" for j in range(n)], [f"tau{j + 1}" for j in range(m)]
    f64 = lambda v: (np.asarray(v.X, float), np.asarray(v.Y, float), v.traj)  # noqa: E731
    if mapping == "nefotc":
        return (*f64(views.nefotc(data)), jn + jdn, tn)
    if mapping == "plan":
        v, h = np.asarray(data["v"], float)[conv], np.asarray(data["h"], float)[conv]
        Pc, N = h.shape
        X = np.concatenate([np.asarray(data["q_start"], float)[conv], np.asarray(data["q_goal"], float)[conv]], 1)
        Y = np.concatenate([v.reshape(Pc, N * n), h], axis=1)
        names = [f"v{k}_{j + 1}" for k in range(N) for j in range(n)] + [f"h{k}" for k in range(N)]
        names_in = [f"q_start{j + 1}" for j in range(n)] + [f"q_goal{j + 1}" for j in range(n)]
        return X, Y, np.flatnonzero(conv), names_in, names
    robot = views.robot_of(data)
    if mapping == "nefumop":
        X, Y, traj = f64(views.nefumop(data, robot=robot))
        pn = _task_names(X.shape[1] // 2)
        return X, Y, traj, pn + [c + "d" for c in pn], tn + ["h"]
    X, Y, traj = f64(views.nefik(data, robot=robot))
    return X, Y, traj, _task_names(X.shape[1]), jn


def _task_names(d):
    return ["x", "y", "z"][:d] if d <= 3 else [f"p{i + 1}" for i in range(d)]


def split(traj, test_fraction: float = 0.1):
    """Boolean (train, test) row masks: the last ``test_fraction`` of the distinct
    trajectories (in dataset order) are the test set (at least one, when there are two
    or more)."""
    ids = np.unique(traj)
    n_test = int(round(test_fraction * ids.size))
    if ids.size >= 2:
        n_test = min(max(n_test, 1), ids.size - 1)
    test_ids = ids[ids.size - n_test:] if n_test else ids[:0]
    test = np.isin(traj, test_ids)
    return ~test, test


def linear_baseline(Xtr, Ytr, Xte):
    """Predictions of the least-squares affine map fitted on (Xtr, Ytr)."""
    A = np.c_[Xtr, np.ones(len(Xtr))]
    W, *_ = np.linalg.lstsq(A, Ytr, rcond=None)
    return np.c_[Xte, np.ones(len(Xte))] @ W


def knn_baseline(Xtr, Ytr, Xte, k: int = 5, chunk: int = 2048):
    """Mean target of the ``k`` nearest training inputs (inputs standardised by the
    training data), computed in chunks."""
    mu, sd = Xtr.mean(0), Xtr.std(0)
    sd = np.where(sd > 0, sd, 1.0)
    A, B = (Xtr - mu) / sd, (Xte - mu) / sd
    k = min(k, len(A))
    out = np.empty((len(B), Ytr.shape[1]))
    sqA = np.sum(A**2, 1)
    for s in range(0, len(B), chunk):
        b = B[s:s + chunk]
        d2 = np.sum(b**2, 1)[:, None] + sqA[None, :] - 2 * b @ A.T
        nn = np.argpartition(d2, k - 1, axis=1)[:, :k]
        out[s:s + chunk] = Ytr[nn].mean(1)
    return out


def _rmse(a, b):
    return float(np.sqrt(np.mean((np.asarray(a) - np.asarray(b)) ** 2)))


AUGMENTATIONS = ("auto", "mirror", "none")
#: the fields the mirror q -> -q negates (the periods h and the total time are kept)
MIRRORED_FIELDS = ("q_start", "q_goal", "q", "qd", "v", "tau")


def mirrored(data):
    """The dataset reflected through ``q -> -q``: positions, velocities, accelerations and
    torques negated, periods kept (a shallow copy; the arrays are new)."""
    data = load_data(data)
    return {k: (-np.asarray(v) if k in MIRRORED_FIELDS else v) for k, v in data.items()}


#: augment="auto" mirrors datasets with fewer training trajectories than this: the
#: mirror images lower nefotc's test RMSE / linear from about 0.40 to 0.32 on 86
#: training trajectories, hardly on 268, not at all on 899, for twice the training time
MIRROR_AUTO_BELOW = 500
#: the mappings augment="auto" mirrors. On the 300-pair seed-2 set the others did not
#: gain: plan (8 rules, order 0) 1.12x the linear baseline with the mirror images against
#: 1.01x without, nefik 0.913x against 0.909x
MIRROR_AUTO_MAPPINGS = ("nefotc", "nefumop")


def mirror_symmetry(data, max_samples: int = 4096) -> str | None:
    """``None`` when the reflection ``q -> -q`` maps the dataset's optimal trajectories onto
    optimal trajectories of the reflected start/goal pairs; otherwise why it is not known to.

    It does when the inverse dynamics are odd, ``tau(-q, -qd, -qdd) = -tau(q, qd, qdd)``,
    and every constraint and cost term is unchanged by the reflection. The dynamics are
    tested on the dataset's samples (at most ``max_samples``, evenly spaced; relative
    tolerance 1e-6); torque, velocity and acceleration boxes are symmetric by
    construction, the energy terms are quadratic; the joint box must be symmetric about
    0; a workspace box, robot path constraints or a singularity weight are not tested
    and rule the mirror out. Planar serial arms without gravity (``serial3``) have the
    symmetry, friction included (it is odd in qd); gravity breaks it (``serial3_vertical``).
    The recursion of the decoupled transcription is linear, so the reflected discrete
    trajectory is exactly feasible and as optimal as the original.
    """
    import jax
    import jax.numpy as jnp

    from jtraj.dataset import views

    data = load_data(data)
    md = data["metadata"]
    try:
        robot = views.robot_of(data)
    except (KeyError, ValueError) as e:
        return f"the dataset's robot is not a built-in one ({e})"
    lim = robot.limits
    if lim.workspace is not None:
        return "the robot has a workspace box (its mirror image is not checked)"
    if getattr(robot, "path_constraints", None) is not None:
        return "the robot has path constraints (their mirror image is not checked)"
    from jtraj import Weights

    if float(Weights.parse(md.get("weights_text") or "").singularity) != 0:
        return "the cost has a singularity term (its mirror image is not checked)"
    n = robot.n
    lo = np.full(n, -np.inf) if lim.q_min is None else np.asarray(lim.q_min, float)
    hi = np.full(n, np.inf) if lim.q_max is None else np.asarray(lim.q_max, float)
    if not np.array_equal(lo, -hi):
        return f"the joint box is not symmetric about 0 (q_min {lo.tolist()}, q_max {hi.tolist()})"
    if "v" not in data:
        return "the dataset has no accelerations v"
    conv = np.asarray(data["converged"], bool)
    if not conv.any():
        return "the dataset has no converged trajectory"
    q, qd = np.asarray(data["q"])[conv][:, :-1], np.asarray(data["qd"])[conv][:, :-1]
    q, qd, v = (a.reshape(-1, n) for a in (q, qd, np.asarray(data["v"])[conv]))
    pick = np.unique(np.linspace(0, len(q) - 1, min(max_samples, len(q))).astype(int))
    q, qd, v = (jnp.asarray(a[pick]) for a in (q, qd, v))
    tau = jax.vmap(robot.inverse_dynamics)(q, qd, v)
    tau_m = jax.vmap(robot.inverse_dynamics)(-q, -qd, -v)
    err = float(jnp.max(jnp.abs(tau + tau_m)))
    scale = 1.0 + float(jnp.max(jnp.abs(tau)))
    if not err <= 1e-6 * scale:
        return f"the inverse dynamics are not odd (|tau(q) + tau(-q)| up to {err:.3g}, e.g. gravity)"
    return None


# the ensemble of radius "auto" gains from more candidates: nefotc's test RMSE / linear
# over 18 slices of 96 pairs is about 0.40 with these seven against 0.425 with four
# (0.4, 0.6, 0.9, 1.4), at about 1.8x the training time
RADIUS_CANDIDATES = (0.4, 0.5, 0.6, 0.75, 0.9, 1.1, 1.4)
# radius "auto" skips a radius whose clustering gives more rules than one per
# TRAJECTORIES_PER_RULE training trajectories (the samples of a trajectory are strongly
# correlated) or than MAX_AUTO_RULES (the Levenberg-Marquardt premise step factorises a
# matrix of 2 x rules x inputs rows: 10 inputs at radius 0.4 trained for over 10 min)
TRAJECTORIES_PER_RULE = 4
MAX_AUTO_RULES = 64
# extra inputs (goal, phase) of train_mapping when not given: over a dataset of random
# start/goal pairs the thesis' mappings are not functions (see view); with the goal
# offset and the phase they nearly are (docs/benchmarks.md: nefotc 0.2x and nefumop 0.35-0.4x
# the linear baseline on the thesis' inputs on 300-1000-pair serial3 datasets)
DEFAULT_INPUTS = {"nefotc": ("relative", True), "nefumop": ("append", True)}


def default_inputs(mapping: str):
    """``(goal, phase)`` that :func:`train_mapping` uses for ``mapping`` when not given."""
    return DEFAULT_INPUTS.get(mapping, (False, False))


def _auto_radii(X, Y, traj, options, selection):
    """The radii of ``RADIUS_CANDIDATES`` within the rule cap (skipped ones are recorded
    in ``selection``); the largest radius if none is."""
    from jtraj.anfis.clustering import subclust

    cap = max(2, min(MAX_AUTO_RULES, np.unique(traj).size // TRAJECTORIES_PER_RULE))
    kw = {k: options[k] for k in ("squash", "accept", "reject") if k in options}
    XY = np.concatenate([X, Y], axis=1)
    counts = {r: subclust(XY, r, max_centers=cap + 1, **kw).centers.shape[0] for r in RADIUS_CANDIDATES}
    keep = [r for r in RADIUS_CANDIDATES if counts[r] <= cap]
    for r in RADIUS_CANDIDATES:
        if r not in keep:
            selection[str(r)] = {"n_rules": f"> {cap}", "skipped": f"more than {cap} rules"}
    return keep or [max(RADIUS_CANDIDATES)]  # counts are cut at cap + 1; the largest radius has fewest


def train_mapping(data, mapping: str = "nefotc", *, n_rules: int | None = None, radius="auto",
                  epochs: int = 100, kind: str = "tsk", test_fraction: float = 0.1, progress: bool = False,
                  goal: bool | str | None = None, phase: bool | None = None, ensemble: bool = True,
                  augment: str = "auto", **options):
    """Train an ANFIS for ``mapping`` on a dataset; return ``(model, report, history)``.

    ``report`` (JSON-able) holds ``train_rmse``, ``test_rmse`` (target units, all
    outputs pooled), ``test_rmse_per_output``, ``train_rmse_per_output``, ``n_rules``,
    ``epochs``, ``seconds``, ``linear_test_rmse``, ``knn_test_rmse``,
    ``ratio_to_linear`` (the test RMSE over the linear baseline's: below 1 the model
    beats a linear fit) and the split sizes; with extra inputs also
    ``thesis_linear_test_rmse`` and ``ratio_to_thesis_linear``, the linear baseline on
    the thesis' inputs of the mapping (e.g. ``(q, qd)`` for ``nefotc``). Other keyword
    options go to :func:`jtraj.anfis.train` (``clip_outputs`` defaults to True and
    ``ridge`` to 1e-6 here, as in ``jtraj train``).
    ``goal``, ``phase``: extra inputs, see :func:`view`; ``None`` takes
    :func:`default_inputs` (``nefotc``: ``(q_goal - q, qd, k/N) -> tau``; ``nefumop``:
    ``(p, pd, p_goal - p, k/N) -> (tau, h)``; the other mappings: none). For ``plan``,
    ``n_rules`` defaults to ``PLAN_RULES`` (8): clustering with a radius in its
    high-dimensional joint input-output space makes every trajectory a rule. ``radius="auto"`` (with
    ``n_rules`` None) trains one model per radius of ``RADIUS_CANDIDATES``, skipping radii
    that give more than one rule per ``TRAJECTORIES_PER_RULE`` training trajectories or
    more than ``MAX_AUTO_RULES`` rules, and returns (``ensemble=True``, the default) an
    :class:`~jtraj.anfis.Ensemble` of them weighted by 1 / (validation MSE)^2, or
    (``ensemble=False``) the one with the lowest validation RMSE. Report:
    ``radius_selection`` (rules, validation RMSE and weight per radius), ``n_rules`` (all
    members' rules), ``radius``, ``epochs`` and ``best_epoch`` of the member with the
    lowest validation RMSE; ``history`` is that member's. On 18 slices of 96 pairs of
    serial3 datasets the ensemble's test RMSE was 0.403x the linear baseline on average
    against 0.444x for the best single radius.
    ``augment``: ``"mirror"`` adds the reflection ``q -> -q`` of every training (and
    validation) trajectory, an optimal trajectory too when the robot has that symmetry
    (:func:`mirror_symmetry`; an error if it does not); ``"auto"`` (default) does so
    for nefotc and nefumop when it has and the training split has fewer than
    ``MIRROR_AUTO_BELOW`` (500) trajectories (above, the gain vanished and the time
    doubled; plan and nefik did not gain); ``"none"`` never. The test set and the
    baselines are left as they are; the rule cap counts the mirror images as
    trajectories. On the 18 slices of 96 pairs the mean ratio to the linear baseline went
    from 0.403 to 0.318 (worst 0.576 -> 0.428), at 1.5-8x the training time. Report:
    ``augment`` (``"mirror"`` or ``"none"``), ``augment_note`` (why not, with ``"auto"``).
    """
    from jtraj import coverage
    from jtraj.anfis.ensemble import Ensemble
    from jtraj.anfis.training import train

    plan_default = mapping == "plan" and n_rules is None
    if plan_default:
        # radius 0.5 in the joint (6 + N (n + 1))-dimensional clustering space accepts
        # every trajectory as a rule (150 of 150 on a 300-pair serial3 dataset)
        n_rules = PLAN_RULES
    dgoal, dphase = default_inputs(mapping)
    goal = _goal_mode(dgoal if goal is None else goal)
    phase = dphase if phase is None else phase
    if augment not in AUGMENTATIONS:
        raise ValueError(f"augment must be one of {AUGMENTATIONS}, got {augment!r}")
    data = load_data(data)
    X, Y, traj, in_names, out_names = view(data, mapping, goal=goal, phase=phase)
    tr, te = split(traj, test_fraction)
    if not te.any():
        raise ValueError("need at least two converged trajectories to hold one out for testing")
    tr_traj = traj[tr]
    n_tr = np.unique(tr_traj).size
    if augment == "none":
        why_not = "not asked for"
    elif augment == "auto" and mapping not in MIRROR_AUTO_MAPPINGS:
        why_not = f"'auto' mirrors the mappings {MIRROR_AUTO_MAPPINGS} only"
    elif augment == "auto" and n_tr >= MIRROR_AUTO_BELOW:
        why_not = f"{n_tr} training trajectories ('auto' mirrors below {MIRROR_AUTO_BELOW})"
    else:
        why_not = mirror_symmetry(data)
    if augment == "mirror" and why_not:
        raise ValueError(f"augment='mirror': {why_not}")
    fit_rows, val_rows = split(tr_traj, 0.1)
    if not (val_rows.any() and fit_rows.any()):
        fit_rows, val_rows = np.ones_like(fit_rows), np.zeros_like(val_rows)
    Xtr, Ytr = X[tr], Y[tr]
    Xfit, Yfit, fit_traj, Xval, Yval = Xtr[fit_rows], Ytr[fit_rows], tr_traj[fit_rows], Xtr[val_rows], Ytr[val_rows]
    if not why_not:
        # the mirror images' rows are appended, and count as trajectories of their own for
        # the rule cap: more rules than counting the dataset's trajectories only (18 slices
        # of 96 pairs: mean 0.318 against 0.329, max 0.428 against 0.451; 96-pair
        # task-space sets of seeds 5 and 2: 0.474 / 0.436 against 0.501 / 0.439), at up to
        # 2.5x the training time (47.6 s against 19.2 s on the seed-5 set)
        Xm, Ym = (a[tr] for a in view(mirrored(data), mapping, goal=goal, phase=phase)[:2])
        Xfit, Yfit, Xval, Yval = (np.r_[a, b] for a, b in ((Xfit, Xm[fit_rows]), (Yfit, Ym[fit_rows]),
                                                           (Xval, Xm[val_rows]), (Yval, Ym[val_rows])))
        fit_traj = np.r_[fit_traj, fit_traj + int(traj.max()) + 1]
    validation = (Xval, Yval) if len(Xval) else 0.0
    meta = data["metadata"]
    md = dict(mapping=mapping, robot=meta.get("robot"), N=meta.get("N"), inputs=in_names, outputs=out_names,
              goal_inputs=goal, phase_input=bool(phase), augment="none" if why_not else "mirror")
    for key in ("urdf", "robot_params"):  # the URDF arm's text and tip link, parameters replaced
        if meta.get(key):  # (jtraj.robots.from_metadata)
            md[key] = meta[key]
    if meta.get("weights_text"):
        md["weights"] = meta["weights_text"]  # the cost the trajectories are optimal for (Planner refine)
    h_max = (meta.get("limits") or {}).get("h_max")
    if h_max is not None:
        md["h_max"] = float(h_max)  # the dataset's sampling-period bound (the Planner's robot)
    # the training trajectories' (q_start, q_goal): the online planner's coverage
    # (distance of a query to them, jtraj.coverage)
    pairs = np.c_[np.asarray(data["q_start"], float), np.asarray(data["q_goal"], float)][np.unique(traj[tr])]
    if not why_not:
        pairs = np.r_[pairs, -pairs]  # the mirror images are training trajectories too
    md["train_pairs"] = pairs.tolist()
    md["coverage_radius"] = coverage.radius(pairs)
    t0 = time.perf_counter()
    redraw = _progress.interval(0.1) if progress else False  # the bar's least seconds between redraws
    options.setdefault("clip_outputs", True)  # targets bounded by the robot's limits (see Model)
    options.setdefault("ridge", 1e-6)  # as jtraj train: 1e-10 overfits sparse trajectory data
    selection = {}
    if n_rules is None and radius == "auto":
        # one model per candidate radius, each validated on trajectories held out of the
        # training ones: too many rules overfit sparse trajectory data (56 rules at radius
        # 0.5 on a 96-pair serial3 set: test RMSE 1.38 x linear), one rule is the linear
        # model. With ensemble, all of them are kept, weighted by 1 / (validation MSE)^2;
        # otherwise the one of lowest validation RMSE
        if not isinstance(validation, tuple):
            radius = 0.5
        else:
            trained = []
            for r in _auto_radii(Xfit, Yfit, fit_traj, options, selection):
                m_r, h_r = train(Xfit, Yfit, radius=r, epochs=epochs, kind=kind, validation=validation,
                                 metadata=md, progress=redraw, **options)
                va = float(min(h_r.val_rmse))
                selection[str(r)] = {"n_rules": int(m_r.n_rules), "validation_rmse": va}
                trained.append((va, r, m_r, h_r))
            best = min(trained, key=lambda t: t[0])
            model, hist = best[2], best[3]
            if ensemble and len(trained) > 1:
                # weights 1 / MSE^2 on the validation split (floored: a perfect fit takes all
                # the weight): on small datasets the weighted average is less noisy than the
                # best single radius (nefotc test RMSE / linear about 0.40 against 0.44 over
                # 18 slices of 96 pairs); 1 / MSE weights are slightly worse
                w = np.array([1.0 / max(t[0], 1e-12) ** 4 for t in trained])
                w /= w.sum()
                for t, wk in zip(trained, w):
                    selection[str(t[1])]["weight"] = float(wk)
                model = Ensemble.from_models([t[2] for t in trained], w, md)
    if not selection:
        model, hist = train(Xfit, Yfit, n_rules=n_rules, radius=radius, epochs=epochs, kind=kind,
                            validation=validation, metadata=md, progress=redraw, **options)
    rules_choice = None
    if plan_default and isinstance(validation, tuple):
        # the one-rule model (order 1: the ridge-regularised affine map of the pair; order
        # 0: the mean trajectory) where it validates better than the default rules: on
        # small datasets of spatial arms the rules overfit the whole trajectories (UR5, 32
        # pairs, N = 40, order 1: test RMSE 1.85x the linear baseline with 8 rules, 1.06x
        # with one rule)
        m_1, h_1 = train(Xfit, Yfit, n_rules=1, epochs=epochs, kind=kind, validation=validation, metadata=md,
                         progress=redraw, **options)
        va, va_1 = float(min(hist.val_rmse)), float(min(h_1.val_rmse))
        rules_choice = {"validation_rmse": {str(n_rules): va, "1": va_1}, "chosen": 1 if va_1 < va else n_rules}
        if va_1 < va:
            model, hist = m_1, h_1
    seconds = time.perf_counter() - t0
    Ptr = np.asarray(model.predict(Xtr)).reshape(Ytr.shape)
    Pte = np.asarray(model.predict(X[te])).reshape(Y[te].shape)
    lin = linear_baseline(Xtr, Ytr, X[te])
    knn = knn_baseline(Xtr, Ytr, X[te])
    test_rmse = _rmse(Pte, Y[te])
    lin_rmse = _rmse(lin, Y[te])
    report = dict(
        mapping=mapping, goal_inputs=md["goal_inputs"], phase_input=md["phase_input"], robot=meta.get("robot"),
        kind=kind, inputs=in_names, outputs=out_names,
        n_trajectories_train=int(np.unique(traj[tr]).size), n_trajectories_test=int(np.unique(traj[te]).size),
        n_samples_train=int(tr.sum()), n_samples_test=int(te.sum()),
        train_rmse=_rmse(Ptr, Ytr), test_rmse=test_rmse,
        train_rmse_per_output={k: _rmse(Ptr[:, i], Ytr[:, i]) for i, k in enumerate(out_names)},
        test_rmse_per_output={k: _rmse(Pte[:, i], Y[te][:, i]) for i, k in enumerate(out_names)},
        n_rules=model.n_rules, radius=hist.radius, epochs=hist.epochs, best_epoch=hist.best_epoch,
        stop_reason=hist.stop_reason, seconds=round(seconds, 3), ensemble=isinstance(model, Ensemble),
        augment=md["augment"],
        linear_test_rmse=lin_rmse, knn_test_rmse=_rmse(knn, Y[te]),
        ratio_to_linear=test_rmse / lin_rmse if lin_rmse > 0 else math.inf,
    )
    if goal or phase:
        X0 = _view(data, mapping)[0]  # the same rows without the extra inputs
        thesis = _rmse(linear_baseline(X0[tr], Ytr, X0[te]), Y[te])
        report.update(thesis_linear_test_rmse=thesis,
                      ratio_to_thesis_linear=test_rmse / thesis if thesis > 0 else math.inf)
    if why_not and augment == "auto":
        report["augment_note"] = why_not
    if selection:
        report["radius_selection"] = selection
    if rules_choice:
        report["rules_selection"] = rules_choice
    report["goal_met"] = bool(report["ratio_to_linear"] <= 0.5)
    return model, report, hist


def synthetic_dataset(P: int = 40, N: int = 20, seed: int = 0, robot: str = "serial3", *, T: float = 3.0,
                      kp: float = 4.0, kd: float = 4.0):
    """A small dataset-shaped mapping for tests and examples (no optimisation).

    Every trajectory starts at rest from a random ``q_start`` and is driven towards one
    common goal (the centre of the joint box) by the critically damped law
    ``v = -kp (q - q_goal) - kd qd`` over ``N`` equal periods of ``T / N``; torques by
    the robot's inverse dynamics. ``(q, qd) -> tau`` is then a genuine function (as for
    the thesis' single-scenario NeFOTC), unlike datasets of random start/goal pairs
    where the goal is not among the inputs. ``converged`` is False for every seventh
    pair (to exercise the filtering).
    """
    import jax
    import jax.numpy as jnp

    from jtraj import robots

    rb = robots.get(robot)
    lim = rb.limits
    rng = np.random.default_rng(seed)
    n = rb.n
    lo = np.asarray(lim.q_min) if lim.q_min is not None else -np.pi * np.ones(n)
    hi = np.asarray(lim.q_max) if lim.q_max is not None else np.pi * np.ones(n)
    lo, hi = np.maximum(lo, -1.5), np.minimum(hi, 1.5)
    goal = 0.5 * (lo + hi)
    qs = rng.uniform(lo, hi, (P, n))
    h = np.full((P, N), T / N)

    def one(q0):
        def step(state, _):
            q, qd = state
            v = -kp * (q - goal) - kd * qd
            dt = T / N
            tau = rb.generalized_to_actuator(q, rb.generalized_forces(q, qd, v))
            return (q + dt * qd + 0.5 * dt**2 * v, qd + dt * v), (q, qd, v, tau)

        (qN, qdN), (q, qd, v, tau) = jax.lax.scan(step, (q0, jnp.zeros_like(q0)), None, length=N)
        return (jnp.concatenate([q, qN[None]]), jnp.concatenate([qd, qdN[None]]), v, tau)

    q, qd, v, tau = (np.asarray(a) for a in jax.jit(jax.vmap(one))(jnp.asarray(qs)))
    conv = np.arange(P) % 7 != 6
    return {"index": np.arange(P), "q_start": qs, "q_goal": np.tile(goal, (P, 1)), "converged": conv,
            "status": np.where(conv, 0, 1).astype(np.int32), "q": q, "qd": qd, "v": v, "tau": tau, "h": h,
            "T": h.sum(1), "cost": h.sum(1), "metadata": {"robot": robot, "N": N, "weights": {}}}
