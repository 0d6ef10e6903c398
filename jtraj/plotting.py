"""Thesis-style figures of an optimised trajectory (matplotlib, no pyplot state).

Every function takes a :class:`~jtraj.Problem` and a :class:`~jtraj.Solution` and
returns a :class:`matplotlib.figure.Figure` built without ``pyplot``, so it is safe
with the Agg backend, in threads and in tests; save it with ``fig.savefig(path)``.

The cycloidal initial guess (:func:`jtraj.initial_guess.cycloidal`) is drawn beside
the optimum (thin dashed lines in each joint's colour) so the gain of the optimisation is
visible. Units follow each coordinate's type (rad or m, rad/s or m/s, N m or N: see
:func:`coordinate_units` and :func:`effort_units`). Legends name each joint once (its
colour) and each kind of line once (optimum, guess, bound, between samples).
"""

from __future__ import annotations

import numpy as np

_OPT = dict(lw=1.8)
_GUESS = dict(lw=1.0, ls="--", color="0.55")
_BOUND = dict(lw=0.9, ls="-.")
_BETWEEN = dict(lw=0.7)


def _np(x):
    return np.asarray(x, dtype=float)


def guess_trajectory(problem) -> dict:
    """The cycloidal initial guess as arrays: q, qd (N+1, n), v (N, n), tau (N, m),
    h (N,), t (N+1,)."""
    import jax

    from .initial_guess import cycloidal
    from .transcription import integrate

    v, h = cycloidal(problem)
    q, qd = integrate(problem.q_start, problem.qd_start, v, h)
    tau = jax.vmap(problem.robot.inverse_dynamics)(q[:-1], qd[:-1], v)
    h = _np(h)
    return dict(q=_np(q), qd=_np(qd), v=_np(v), tau=_np(tau), h=h, t=np.concatenate([[0.0], np.cumsum(h)]))


def solution_arrays(solution) -> dict:
    """The solution's trajectory as NumPy arrays, with sample times t (N+1,)."""
    h = _np(solution.h)
    return dict(q=_np(solution.q), qd=_np(solution.qd), v=_np(solution.v), tau=_np(solution.tau), h=h,
                t=np.concatenate([[0.0], np.cumsum(h)]))


def drawable(trajectory) -> bool:
    """Whether a trajectory (anything :func:`plot_solution` draws) holds only finite
    values: :func:`plot_solution` refuses one that does not."""
    return _finite(solution_arrays(trajectory))


def _finite(arrays: dict) -> bool:
    return all(np.all(np.isfinite(x)) for x in arrays.values())


def coordinate_units(robot) -> list[str]:
    """The unit of each generalised coordinate, "rad" or "m": the robot's
    ``coordinate_units`` where it declares them (``gough_stewart``, the planar parallel
    robots), else from its ``joint_types`` (URDF arms: prismatic joints in m), else rad."""
    units = getattr(robot, "coordinate_units", None)
    if units is not None:
        return list(units)
    types = getattr(robot, "joint_types", None)
    if types is not None:
        return ["m" if t == "prismatic" else "rad" for t in types]
    return ["rad"] * robot.n


def effort_units(robot) -> list[str]:
    """The unit of each actuator effort, "N m" or "N": the robot's ``effort_units``
    where it declares them, else per coordinate (a force on a coordinate in m, a torque
    on one in rad) when there is one actuator per coordinate, else N m."""
    units = getattr(robot, "effort_units", None)
    if units is not None:
        return list(units)
    tau_max = robot.limits.tau_max
    m = robot.n if tau_max is None else int(np.shape(tau_max)[0])
    if m == robot.n:
        return ["N" if u == "m" else "N m" for u in coordinate_units(robot)]
    return ["N m"] * m


def _axis_unit(units, rate="") -> str:
    """One axis label's unit for per-line units (e.g. "rad/s" or "rad/s, m/s")."""
    return ", ".join(dict.fromkeys(f"{u}{rate}" for u in units))


def _tip_path(robot, q):
    import jax

    return _np(jax.vmap(robot.forward_kinematics)(q))


def _path_constraint_region(robot, points: int = 121):
    """``(x, y, g)``: the largest of the robot's path constraints ``g(q) <= 0`` on a
    ``points`` x ``points`` grid over its workspace box (else, for two coordinates, its
    joint box), non-finite values (where the mechanism does not assemble) counted as
    violated; for a robot whose tip is its first two coordinates and whose constraints
    do not depend on the others (the planar parallel robots, ``wmr``'s obstacles); None
    for any other."""
    import jax
    import jax.numpy as jnp

    path, lim, n = getattr(robot, "path_constraints", None), robot.limits, robot.n
    box = lim.workspace if lim.workspace is not None else (
        (lim.q_min, lim.q_max) if n == 2 and lim.q_min is not None and lim.q_max is not None else None)
    if path is None or box is None:
        return None
    lo, hi = _np(box[0]), _np(box[1])
    if lo.shape != (2,) or not np.all(np.isfinite(lo) & np.isfinite(hi)):
        return None
    x, y = np.meshgrid(np.linspace(lo[0], hi[0], points), np.linspace(lo[1], hi[1], points))
    xy = np.stack([x.ravel(), y.ravel()], axis=1)
    q = np.concatenate([xy, np.zeros((xy.shape[0], n - 2))], axis=1)
    if not np.allclose(_tip_path(robot, jnp.asarray(q)), xy, rtol=0, atol=1e-12):
        return None
    worst = jax.vmap(lambda p: jnp.max(path(p)))
    g = _np(worst(jnp.asarray(q)))
    if n > 2 and not np.allclose(_np(worst(jnp.asarray(q + 0.5 * (np.arange(n) >= 2)))), g, equal_nan=True):
        return None
    return x, y, np.where(np.isfinite(g), g, 1.0).reshape(x.shape)


def _links(robot, q):
    """Polyline of the mechanism at q for drawing, or None when the robot has none."""
    f = getattr(robot, "joint_positions", None)
    if f is None:
        return None
    try:
        pts = _np(f(q))
    except Exception:  # a robot whose drawing helper has another signature
        return None
    return pts if pts.ndim == 2 and pts.shape[1] >= 2 else None


def _stairs(ax, t, y, **kw):
    """Piecewise-constant y_k on [t_k, t_{k+1}) (zero-order hold of per-interval data)."""
    return ax.stairs(y, t, baseline=None, **kw)


def _line(ax, t, y, **kw):
    ax.plot(t, y, **kw)


def _kind_legend(ax, kinds, fontsize=7):
    """A legend with the labelled lines of ``ax`` (one per joint) followed by one grey
    entry per kind of line: ``kinds`` is a list of (style dict, label)."""
    from matplotlib.lines import Line2D

    handles, labels = ax.get_legend_handles_labels()
    for style, label in kinds:
        handles.append(Line2D([], [], **{"color": "0.35", **style}))
        labels.append(label)
    ax.legend(handles, labels, fontsize=fontsize)


def _signals_with_limits(ax, draw, sol, guess, key, bound, ylabel, title, units=None, kinds=(),
                         names=("optimum", "cycloidal guess")):
    """One panel: every joint's ``sol[key]`` (and the guess's, dashed) drawn by
    ``draw(ax, t, y, **style)``, with +-bound as dash-dotted lines in the joint's colour;
    ``units``: each line's unit, in its legend label; ``kinds``: extra legend entries;
    ``names``: the two trajectories' legend names."""
    for j in range(sol[key].shape[1]):
        label = f"{key}{j + 1}" + ("" if units is None else f" [{units[j]}]")
        draw(ax, sol["t"], sol[key][:, j], color=f"C{j}", label=label, **_OPT)
        if guess is not None:
            draw(ax, guess["t"], guess[key][:, j], **{**_GUESS, "color": f"C{j}", "alpha": 0.6})
        if bound is not None:
            b = _np(bound)[j]
            ax.axhline(b, color=f"C{j}", **_BOUND)
            ax.axhline(-b, color=f"C{j}", **_BOUND)
    ax.set_xlabel("t [s]")
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    legend = [(_OPT, names[0])] + ([(_GUESS, names[1])] if guess is not None else [])
    legend += list(kinds) + ([(_BOUND, "bound")] if bound is not None else [])
    _kind_legend(ax, legend)


def efforts_between_samples(robot, solution, per_interval: int = 8):
    """(t, tau) of the constant-acceleration motion inside every interval (NaN rows
    between intervals, so that a line breaks where the acceleration jumps), or None for
    a trajectory that is not one (see :mod:`jtraj.resample`)."""
    from .resample import interval_times, resample

    try:
        s = resample(solution, robot, times=interval_times(_np(solution.h), per_interval))
    except ValueError:
        return None
    t, tau = _np(s.t).reshape(-1, per_interval), _np(s.tau).reshape(-1, per_interval, s.tau.shape[-1])
    gap = np.full(t.shape[:1] + (1,), np.nan)
    return (np.concatenate([t, gap], axis=1).ravel(),
            np.concatenate([tau, np.full(tau.shape[:1] + (1, tau.shape[2]), np.nan)], axis=1).reshape(-1, tau.shape[2]))


def _energy(tau, h, tau_max):
    scale = 1.0 if tau_max is None else _np(tau_max)
    return np.concatenate([[0.0], np.cumsum(h * np.sum((tau / scale) ** 2, axis=1))])


def plot_path(problem, solution, ax=None, *, guess: dict | None = None, instants: int = 5,
              label: str = "optimum", guess_label: str = "cycloidal guess"):
    """Task-space path of the tip, with the mechanism drawn at ``instants`` samples;
    ``guess`` (arrays as :func:`guess_trajectory` returns them) dashed beside it.
    ``label``, ``guess_label``: the two trajectories' names in the legend."""
    from matplotlib.figure import Figure

    fig = None
    robot = problem.robot
    sol = solution_arrays(solution)
    p = _tip_path(robot, sol["q"])
    if ax is None:
        fig = Figure(figsize=(5, 5))
        ax = fig.add_subplot(projection="3d" if p.shape[1] == 3 else None)
    if p.shape[1] == 3 and getattr(ax, "name", "") == "3d":
        return _plot_path_3d(problem, ax, sol, p, guess, instants, fig, label, guess_label)
    N = p.shape[0] - 1
    for i, k in enumerate(np.unique(np.linspace(0, N, instants).round().astype(int))):
        pts = _links(robot, sol["q"][k])
        if pts is not None:
            shade = 0.75 - 0.6 * k / max(N, 1)
            ax.plot(pts[:, 0], pts[:, 1], "-o", color=(shade, shade, 1.0), lw=2.5, ms=4, zorder=1,
                    label=f"arm ({label})" if i == 0 else None)
    if guess is not None:
        pg = _tip_path(robot, guess["q"])
        ax.plot(pg[:, 0], pg[:, 1], label=guess_label, **_GUESS)
    ax.plot(p[:, 0], p[:, 1], "-", color="C3", label=label, zorder=3, **_OPT)
    ax.plot(p[:, 0], p[:, 1], ".", color="C3", ms=4, zorder=3)
    ps, pg_ = _np(robot.forward_kinematics(problem.q_start)), _np(robot.forward_kinematics(problem.q_goal))
    ax.plot(ps[0], ps[1], "s", color="k", ms=6, zorder=4, label="start")
    ax.plot(pg_[0], pg_[1], "*", color="k", ms=11, zorder=4, label="goal")
    for i, vp in enumerate(problem.via_points):  # (one legend entry for all)
        pt = _np(vp.point)
        ax.plot(pt[0], pt[1], "x", color="C2", ms=9, mew=2, zorder=4, label="via point" if i == 0 else None)
    ws = problem.robot.limits.workspace
    if ws is not None and _np(ws).shape[1] >= 2:
        lo, hi = _np(ws)
        ax.plot([lo[0], hi[0], hi[0], lo[0], lo[0]], [lo[1], lo[1], hi[1], hi[1], lo[1]], ":", color="0.4",
                label="workspace")
    region = _path_constraint_region(robot)
    if region is not None and np.any(region[2] > 0):  # (parallel3's folded-leg discs, for one)
        ax.contourf(*region, levels=[0.0, np.inf], colors=["0.85"], zorder=0)
        ax.fill([], [], color="0.85", label="path constraints violated")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title("tip path")
    ax.legend(fontsize=7, loc="best")
    return fig if fig is not None else ax.figure


def _plot_path_3d(problem, ax, sol, p, guess, instants, fig, label, guess_label):
    """:func:`plot_path` for a spatial task point: the tip path in 3-D with the arm's
    polyline (base, joints, tip) at ``instants`` samples."""
    robot = problem.robot
    N = p.shape[0] - 1
    for i, k in enumerate(np.unique(np.linspace(0, N, instants).round().astype(int))):
        pts = _links(robot, sol["q"][k])
        if pts is not None and pts.shape[1] == 3:
            shade = 0.75 - 0.6 * k / max(N, 1)
            ax.plot(pts[:, 0], pts[:, 1], pts[:, 2], "-o", color=(shade, shade, 1.0), lw=2.5, ms=3,
                    label=f"arm ({label})" if i == 0 else None)
    if guess is not None:
        pg = _tip_path(robot, guess["q"])
        ax.plot(pg[:, 0], pg[:, 1], pg[:, 2], label=guess_label, **_GUESS)
    ax.plot(p[:, 0], p[:, 1], p[:, 2], ".-", color="C3", label=label, ms=3, **_OPT)
    for q, marker, name in ((problem.q_start, "s", "start"), (problem.q_goal, "*", "goal")):
        pt = _np(robot.forward_kinematics(q))
        ax.plot([pt[0]], [pt[1]], [pt[2]], marker, color="k", ms=8, label=name)
    for i, vp in enumerate(problem.via_points):
        pt = _np(vp.point)
        ax.plot([pt[0]], [pt[1]], [pt[2]], "x", color="C2", ms=9, mew=2, label="via point" if i == 0 else None)
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_zlabel("z [m]")
    ax.set_title("tip path")
    ax.legend(fontsize=7, loc="best")
    return fig if fig is not None else ax.figure


def plot_solution(problem, solution, *, guess=True, title: str | None = None, label: str = "optimum",
                  guess_label: str | None = None):
    """The full figure: tip path with the arm, q(t), qd(t) against limits, tau(t)
    against limits (dashed), h_k, and cumulative energy.

    ``solution``: anything with the arrays ``q``, ``qd`` (N+1, n), ``v`` (N, n), ``tau``
    (N, m) and ``h`` (N,): a :class:`jtraj.Solution`, a :class:`jtraj.online.Plan`.
    ``guess``: ``True`` draws the cycloidal initial guess dashed beside it, ``False``
    nothing, and another such trajectory draws that one (``jtraj query --plot`` draws a
    refined optimum with its plan so). ``label``, ``guess_label``: the two trajectories'
    names in the legends (``guess_label`` defaults to "cycloidal guess" for
    ``guess=True``, else "guess")."""
    from matplotlib.figure import Figure

    robot = problem.robot
    lim = robot.limits
    sol = solution_arrays(solution)
    if isinstance(guess, bool):
        g = guess_trajectory(problem) if guess else None
        guess_label = guess_label or "cycloidal guess"
    else:
        g = solution_arrays(guess)
        guess_label = guess_label or "guess"
    for name, arrays in (("solution", sol), ("guess", g)):
        if arrays is not None and not _finite(arrays):
            raise ValueError(f"{name} holds non-finite values: there is no trajectory to draw")
    names = (label, guess_label)
    fig = Figure(figsize=(15, 8.5), layout="constrained")
    axs = fig.subplots(2, 3)
    if _tip_path(robot, sol["q"][:1]).shape[1] == 3:  # a spatial arm: the path in 3-D
        axs[0, 0].remove()
        axs[0, 0] = fig.add_subplot(2, 3, 1, projection="3d")
    plot_path(problem, solution, axs[0, 0], guess=g, label=label, guess_label=guess_label)

    # q(t), in each coordinate's unit (rad or m) and the efforts' (N m or N)
    cu, eu = coordinate_units(robot), effort_units(robot)
    ax = axs[0, 1]
    for j in range(sol["q"].shape[1]):
        ax.plot(sol["t"], sol["q"][:, j], color=f"C{j}", label=f"q{j + 1} [{cu[j]}]", **_OPT)
        if g is not None:
            ax.plot(g["t"], g["q"][:, j], **{**_GUESS, "color": f"C{j}", "alpha": 0.6})
    bounded = False
    if lim.q_min is not None:
        for j, (lo, hi) in enumerate(zip(_np(lim.q_min), _np(lim.q_max))):
            for b in (lo, hi):
                if np.isfinite(b):
                    ax.axhline(b, color=f"C{j}", **_BOUND)
                    bounded = True
    ax.set_xlabel("t [s]")
    ax.set_ylabel(f"q [{_axis_unit(cu)}]")
    ax.set_title("joint positions")
    _kind_legend(ax, [(_OPT, label)] + ([(_GUESS, guess_label)] if g is not None else [])
                 + ([(_BOUND, "bound")] if bounded else []))

    # qd(t)
    _signals_with_limits(axs[0, 2], _line, sol, g, "qd", lim.qd_max, f"qd [{_axis_unit(cu, '/s')}]",
                         "joint velocities and limits", [f"{u}/s" for u in cu], names=names)

    # tau(t): steps at the samples (the transcription's values), thin lines between them
    dense = efforts_between_samples(robot, solution)
    _signals_with_limits(axs[1, 0], _stairs, sol, g, "tau", lim.tau_max, f"tau [{_axis_unit(eu)}]",
                         "actuator efforts and limits" if dense is None else
                         "efforts at the samples (steps), between them (thin)", eu,
                         kinds=() if dense is None else [(_BETWEEN, "between samples")], names=names)
    if dense is not None:
        for j in range(dense[1].shape[1]):
            axs[1, 0].plot(dense[0], dense[1][:, j], color=f"C{j}", **_BETWEEN)

    # h_k
    ax = axs[1, 1]
    k = np.arange(sol["h"].shape[0])
    ax.plot(k, sol["h"], "o-", color="C3", label=f"{label} (T = {sol['t'][-1]:.3f} s)", **_OPT)
    if g is not None:
        ax.plot(np.arange(g["h"].shape[0]), g["h"], marker=".", label=f"{guess_label} (T = {g['t'][-1]:.3f} s)",
                **_GUESS)
    ax.axhline(float(lim.h_min), color="0.3", **_BOUND)
    ax.axhline(float(lim.h_max), color="0.3", **_BOUND, label="h_min, h_max")
    ax.set_xlabel("interval k")
    ax.set_ylabel("h_k [s]")
    ax.set_title("sampling periods")
    ax.legend(fontsize=7)

    # cumulative energy
    ax = axs[1, 2]
    e = _energy(sol["tau"], sol["h"], lim.tau_max)
    ax.plot(sol["t"], e, color="C3", label=f"{label} ({e[-1]:.3g})", **_OPT)
    if g is not None:
        eg = _energy(g["tau"], g["h"], lim.tau_max)
        ax.plot(g["t"], eg, label=f"{guess_label} ({eg[-1]:.3g})", **_GUESS)
    ax.set_xlabel("t [s]")
    ax.set_ylabel("sum h tau^T diag(1/tau_max^2) tau [s]" if lim.tau_max is not None else "sum h tau^T tau")
    ax.set_title("cumulative energy")
    ax.legend(fontsize=7)

    if title:
        fig.suptitle(title)
    return fig


def save(fig, path: str, dpi: int = 110) -> None:
    """Write ``fig`` to ``path`` (format from the extension)."""
    fig.savefig(path, dpi=dpi)
