"""The canonical benchmark family (NumPy only, so that a machine without CasADi can
draw it too)."""

import numpy as np


def benchmark_pairs(n: int, seed: int = 0, ndof: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """The benchmark family: q_start ~ U(-1.2, 1.2)^3, q_goal = q_start + U(-0.8, 0.8)^3.

    Pair i does not depend on n (the first 8 of 64 are the 8 of ``benchmark_pairs(8)``).
    """
    u = np.random.default_rng(seed).random((n, 2, ndof))
    q0 = -1.2 + 2.4 * u[:, 0]
    return q0, q0 + (-0.8 + 1.6 * u[:, 1])
