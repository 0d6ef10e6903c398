"""Public ANFIS benchmarks: Jang's Mackey-Glass prediction and two-input sinc.

Both follow J.-S. R. Jang, "ANFIS: adaptive-network-based fuzzy inference system",
IEEE Trans. SMC 23(3), 1993. The series are generated here (no data files).

Mackey-Glass: ``dx/dt = 0.2 x(t - tau) / (1 + x(t - tau)^10) - 0.1 x(t)`` with
``tau = 17``, ``x(0) = 1.2`` and ``x(t) = 0`` for ``t < 0``; integrated by classical
fourth-order Runge-Kutta with step ``dt`` (0.01 by default). The delayed value at the
half steps is taken by four-point (cubic) Lagrange interpolation of the stored history,
so the scheme keeps fourth order in the delay term too. Jang's set-up: inputs
``[x(t-18), x(t-12), x(t-6), x(t)]``, target ``x(t+6)``, ``t = 118 .. 1117`` (1000
pairs), the first 500 for training and the last 500 for checking.

Sinc: ``z = sinc(x) sinc(y)`` with ``sinc(u) = sin(u)/u`` on ``[-10, 10]^2``; Jang used
121 training pairs on the 11 x 11 grid of step 2.
"""

from __future__ import annotations

import numpy as np


def mackey_glass(t_max: float = 1200.0, *, tau: float = 17.0, x0: float = 1.2, dt: float = 0.01,
                 a: float = 0.2, b: float = 0.1, power: float = 10.0) -> tuple[np.ndarray, np.ndarray]:
    """Mackey-Glass series sampled at integer times ``0, 1, ..., floor(t_max)``.

    Returns ``(t, x)`` (numpy float64). ``tau / dt`` and ``1 / dt`` must be integers.
    """
    lag = int(round(tau / dt))
    per = int(round(1.0 / dt))
    if abs(lag * dt - tau) > 1e-9 or abs(per * dt - 1.0) > 1e-9:
        raise ValueError(f"tau / dt and 1 / dt must be integers, got tau={tau}, dt={dt}")
    steps = int(round(t_max / dt))
    x = [0.0] * (steps + 1)  # x[k] = x(k dt); x(t) = 0 for t < 0 (Jang's convention)
    x[0] = float(x0)

    def f(xt, xd):
        return a * xd / (1.0 + xd**power) - b * xt

    def hist(j):
        return x[j] if j >= 0 else 0.0

    for k in range(steps):
        j = k - lag  # the delayed argument runs over [j dt, (j + 1) dt]
        if j < 0:  # still on the zero history (left limits at the jump t - tau = 0)
            xd0 = xdm = xd1 = 0.0
        else:
            xd0, xd1 = x[j], x[j + 1]
            if j >= 1:  # cubic Lagrange interpolation at the midpoint
                xdm = (-x[j - 1] + 9.0 * xd0 + 9.0 * xd1 - x[j + 2]) / 16.0
            else:  # quadratic through x(0), x(dt), x(2 dt)
                xdm = (3.0 * xd0 + 6.0 * xd1 - x[j + 2]) / 8.0
        xk = x[k]
        k1 = f(xk, xd0)
        k2 = f(xk + 0.5 * dt * k1, xdm)
        k3 = f(xk + 0.5 * dt * k2, xdm)
        k4 = f(xk + dt * k3, xd1)
        x[k + 1] = xk + dt / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
    x = np.asarray(x)
    series = x[::per][: int(t_max) + 1]
    return np.arange(series.shape[0], dtype=float), series


def jang_mackey_glass(**kwargs) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Jang's (1993) Mackey-Glass set-up: ``(X_train, y_train, X_check, y_check)``.

    X rows are ``[x(t-18), x(t-12), x(t-6), x(t)]``, y is ``x(t+6)``, for
    ``t = 118 .. 1117``; 500 training pairs then 500 checking pairs.
    """
    _, x = mackey_glass(1124.0, **kwargs)
    t = np.arange(118, 1118)
    X = np.stack([x[t - 18], x[t - 12], x[t - 6], x[t]], axis=1)
    y = x[t + 6]
    return X[:500], y[:500], X[500:], y[500:]


def sinc2(X: np.ndarray) -> np.ndarray:
    """``sinc(x) sinc(y)`` with ``sinc(u) = sin(u) / u`` (1 at 0), X of shape (B, 2)."""
    X = np.asarray(X, dtype=float)
    return np.sinc(X[:, 0] / np.pi) * np.sinc(X[:, 1] / np.pi)


def jang_sinc(n_check: int = 41) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Jang's two-input sinc: 121 training pairs on the 11 x 11 grid of [-10, 10]^2 and
    ``n_check^2`` checking pairs on a finer grid of the same square (with 41, the
    check grid contains every training point)."""
    g = np.linspace(-10.0, 10.0, 11)
    Xtr = np.stack(np.meshgrid(g, g, indexing="ij"), -1).reshape(-1, 2)
    c = np.linspace(-10.0, 10.0, n_check)
    Xck = np.stack(np.meshgrid(c, c, indexing="ij"), -1).reshape(-1, 2)
    return Xtr, sinc2(Xtr), Xck, sinc2(Xck)
