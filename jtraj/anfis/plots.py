"""Figures for a trained ANFIS: training curves and membership functions before and
after training (the thesis' Fig. 6.12). Matplotlib with the Agg backend (files only)."""

from __future__ import annotations

import math

import numpy as np


def training_figure(history, model, path: str, input_names=None, title: str = "") -> str:
    """Write one PNG: RMSE per epoch (train and validation, log scale) and, per input,
    the Gaussian memberships of every rule before (dashed) and after (solid) training,
    one colour per rule. ``input_names`` should carry each input's unit, e.g. "x [m]"."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    d = model.n_inputs
    names = list(input_names or [f"x{i + 1}" for i in range(d)])
    cols = min(3, d)
    rows = 1 + math.ceil(d / cols)
    fig = plt.figure(figsize=(4.2 * cols, 3.0 * rows))
    ax = fig.add_subplot(rows, 1, 1)
    ep = np.arange(len(history.train_rmse))
    ax.semilogy(ep, history.train_rmse, label="train")
    ax.semilogy(ep, history.val_rmse, label="validation")
    ax.axvline(history.best_epoch, color="k", lw=0.8, ls=":", label=f"kept (epoch {history.best_epoch})")
    ax.set_xlabel("epoch")
    ax.set_ylabel("RMSE (target units)")
    ax.set_title(title or f"ANFIS, {model.n_rules} rules")
    ax.legend()
    c1, s1 = model.memberships()
    c0, s0 = history.initial.memberships() if history.initial is not None else (c1, s1)
    lo = np.asarray(model.x_lo)
    hi = lo + np.asarray(model.x_span)
    for i in range(d):
        a = fig.add_subplot(rows, cols, cols + i + 1)
        x = np.linspace(lo[i], hi[i], 300)
        for r in range(model.n_rules):
            line, = a.plot(x, np.exp(-0.5 * ((x - c0[r, i]) / s0[r, i]) ** 2), ls="--", lw=0.8)
            a.plot(x, np.exp(-0.5 * ((x - c1[r, i]) / s1[r, i]) ** 2), color=line.get_color(), lw=1.2)
        a.set_xlabel(names[i])
        a.set_ylabel("membership")
        a.set_ylim(0, 1.05)
        if i == 0:  # one entry per kind of line; the colours are the rules
            from matplotlib.lines import Line2D

            a.legend([Line2D([], [], color="0.35", ls="--", lw=0.8), Line2D([], [], color="0.35", lw=1.2)],
                     ["before training", "after training"], fontsize=7)
    fig.suptitle("memberships: dashed before, solid after training", y=0.995, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
