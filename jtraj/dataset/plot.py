"""Overview figure of a dataset: workspace coverage and histograms of T, energy and status."""

from __future__ import annotations

import numpy as np


def plot(path: str, out: str) -> str:
    """Draw the overview of the dataset at ``path`` into the image file ``out``; returns ``out``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from jtraj.solver import Status

    from . import load
    from .views import robot_of, task_state

    data = load(path, partial=True)
    md = data.metadata
    fig, ax = plt.subplots(2, 2, figsize=(10, 8))
    fig.suptitle(f"{md['robot']}: {data.pairs if data.chunks else 0}/{md['pairs']} pairs, N = {md['N']}, "
                 f"weights {md['weights_text']}, seed {md['seed']}")
    if not data.chunks:
        for a in ax.flat:
            a.text(0.5, 0.5, "no finished chunk yet", ha="center")
        fig.savefig(out, dpi=110)
        plt.close(fig)
        return out
    conv = data["converged"]
    robot = robot_of(data)
    q = data["q"]
    # workspace coverage: task points of all trajectory samples, start/goal points on top
    p = task_state(robot, q.reshape(-1, q.shape[-1]), np.zeros((q.shape[0] * q.shape[1], q.shape[-1])))[0]
    p0 = task_state(robot, data["q_start"], np.zeros_like(data["q_start"]))[0]
    p1 = task_state(robot, data["q_goal"], np.zeros_like(data["q_goal"]))[0]
    a = ax[0, 0]
    if p.shape[1] >= 2:
        from matplotlib.colors import LogNorm

        *_, image = a.hist2d(p[:, 0], p[:, 1], bins=80, cmap="viridis", cmin=1, norm=LogNorm())
        fig.colorbar(image, ax=a, label="trajectory samples per bin")
        a.scatter(p0[:, 0], p0[:, 1], s=5, c="white", edgecolors="k", linewidths=0.3, label="start")
        a.scatter(p1[:, 0], p1[:, 1], s=5, c="tab:orange", label="goal")
        bad = ~conv
        if bad.any():
            a.scatter(p0[bad, 0], p0[bad, 1], s=14, marker="o", facecolors="none", edgecolors="tab:red",
                      linewidths=0.6, label="start of a non-converged pair")
        a.set_xlabel("x [m]")
        a.set_ylabel("y [m]")
        a.set_aspect("equal", adjustable="datalim")
        a.legend(fontsize=7, loc="upper right")
    else:
        a.hist(p[:, 0], bins=60)
        a.set_xlabel("task coordinate")
    a.set_title("workspace coverage (trajectory samples)")
    for a, key, label in ((ax[0, 1], "T", "T [s]"), (ax[1, 0], "energy", "energy (sum h tau^T U1 tau)")):
        x = data[key]
        ok = np.isfinite(x)
        a.hist([x[ok & conv], x[ok & ~conv]], bins=40, stacked=True, label=["converged", "not converged"],
               color=["tab:green", "tab:red"])
        a.set_xlabel(label)
        a.set_ylabel("pairs")
        a.legend(fontsize=7)
    a = ax[1, 1]
    codes, counts = np.unique(data["status"], return_counts=True)
    names = []
    for c in codes:
        try:
            names.append(f"{int(c)} {Status(int(c)).name.lower()}")
        except ValueError:
            names.append(str(int(c)))
    a.barh(names, counts, color=["tab:green" if c == 0 else "tab:red" for c in codes])
    a.set_xlabel("pairs")
    a.set_title(f"status (converged {100 * conv.mean():.1f} %)")
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out
