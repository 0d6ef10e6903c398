"""Reference peers for jtraj's tests and benchmarks (independent of jtraj: nothing here
imports it). At the repository root, outside the wheel: pytest puts the root on
``sys.path`` (``pythonpath`` in pyproject.toml), the benchmark scripts append it.

* :mod:`.ipopt_peer` -- the canonical serial3 ALD problem in CasADi + IPOPT:
  :func:`solve_pair`, :func:`solve_many`, :func:`cycloidal_init`.
* :mod:`.pairs` -- :func:`benchmark_pairs`, the canonical problem family (NumPy only).
* :mod:`.verify` -- NumPy + Pinocchio verifier: :func:`verify`, :func:`verify_batch`.
* :mod:`.casadi_rnea` -- a CasADi RNEA from a Pinocchio model's numbers (spatial arms).
* :mod:`.ipopt_arm` -- the decoupled NLP of any arm given as a CasADi function, in IPOPT.
* :mod:`.verify_arm` -- NumPy + Pinocchio verifier of such an arm's trajectories.
* :mod:`.verify_parallel3` -- NumPy + Pinocchio verifier of parallel3's trajectories (its
  legs as 2R arms, the minimum-norm actuator torques, the legs' singularity margins).

Names are imported lazily so that IPOPT workers do not load Pinocchio and vice versa.
"""

import importlib

_NAMES = {
    "solve_pair": "ipopt_peer", "solve_many": "ipopt_peer", "cycloidal_init": "ipopt_peer",
    "benchmark_pairs": "pairs", "get_peer": "ipopt_peer", "SolveBatch": "ipopt_peer",
    "verify": "verify", "verify_batch": "verify", "rnea": "verify", "simulate": "verify",
}

__all__ = sorted(_NAMES)


def __getattr__(name):
    if name in _NAMES:
        return getattr(importlib.import_module(f".{_NAMES[name]}", __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
