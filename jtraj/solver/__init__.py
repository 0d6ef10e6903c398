"""The trajectory solver.

Modules, each importing only those above it:

* :mod:`.results`: :class:`Status` and :class:`Solution`, what a solve returns;
* :mod:`.options`: :class:`SolverOptions` and their split into traced numbers and the
  static structure a compiled program depends on;
* :mod:`.nlp`: the transcribed problem in augmented-Lagrangian form and its
  :class:`Multipliers`, shared by both methods;
* :mod:`.certify`: the feasibility polish, multiplier estimates and the KKT error;
* :mod:`.al`: the augmented-Lagrangian method (one flat, bounded loop);
* :mod:`.ipm`: the primal-dual interior-point method;
* :mod:`.core`: one problem's solve as traced programs and its finish;
* :mod:`.staged`: the single solve on concrete arrays, in stages;
* :mod:`.lanes`: the batch solve and its host-driven lane driver;
* :mod:`.api`: the entry points :func:`solve` and :func:`solve_batch`.

The names below are the public API; the modules' other names are shared inside the
package (tests and benchmarks reach them through :mod:`jtraj._testing`).
"""

from .api import solve, solve_batch
from .core import initial_guess
from .nlp import Multipliers
from .options import PBM_SETTINGS, SolverOptions
from .results import Solution, Status

__all__ = ["PBM_SETTINGS", "Multipliers", "Solution", "SolverOptions", "Status", "initial_guess", "solve",
           "solve_batch"]
