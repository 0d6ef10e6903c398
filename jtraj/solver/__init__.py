"""The trajectory solver.

Modules, each importing only those above it:

* :mod:`.results`: :class:`Status` and :class:`Solution`, what a solve returns;
* :mod:`.methods`: the solvers as objects (:class:`Auto`, :class:`IPM`,
  :class:`AugmentedLagrangian`), their options marked traced or static on the fields;
* :mod:`.options`: the flat option set the compiled programs read (the deprecated
  :class:`SolverOptions`), the solvers' map onto it and its split into traced numbers and
  the static structure a compiled program depends on;
* :mod:`.nlp`: the transcribed problem in augmented-Lagrangian form and its
  :class:`Multipliers`, shared by both methods;
* :mod:`.certify`: the feasibility polish, multiplier estimates and the KKT error;
* :mod:`.loop`: the methods' protocol (``init``, ``enter``, ``step``, ``terminate``,
  ``postprocess``) and the one bounded driver that runs them;
* :mod:`.al`: the augmented-Lagrangian method (one flat, bounded loop, and its restarts);
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
from .methods import (IPM, PBM_SETTINGS, AugmentedLagrangian, Auto, Curvature, Guess, InequalityPenalty,
                      LinearSolver, Schedule)
from .nlp import Multipliers
from .options import SolverOptions, as_solver, from_options
from .results import Solution, Status

__all__ = ["IPM", "PBM_SETTINGS", "AugmentedLagrangian", "Auto", "Curvature", "Guess", "InequalityPenalty",
           "LinearSolver", "Multipliers", "Schedule", "Solution", "SolverOptions", "Status", "as_solver",
           "from_options", "initial_guess", "solve", "solve_batch"]
