"""jtraj: differentiable robot trajectory optimisation in JAX.

``import jtraj`` loads the solver and the robots; the subpackages ``jtraj.dataset``,
``jtraj.anfis``, ``jtraj.mappings``, ``jtraj.online``, ``jtraj.gradcheck``, ``jtraj.plotting`` and
``jtraj.resample`` are imported on their first access (``jtraj.dataset.load(...)``
works without ``import jtraj.dataset``), so that the import stays fast.

jtraj solves in float64: call ``jax.config.update("jax_enable_x64", True)`` at the start
of a program, before building robots and problems (:func:`solve` raises ``ValueError``
otherwise; ``import jtraj`` leaves x64 as it is). ``import jtraj`` turns JAX's persistent
compilation cache on in ``~/.cache/jtraj/jax`` (``JTRAJ_CACHE_DIR`` moves it,
``JTRAJ_CACHE=0`` leaves it off; a cache directory the program already set is kept), so
that a later process loads the solver instead of compiling it; see :mod:`jtraj._setup`.
"""

import importlib as _importlib

__version__ = "0.1.0"

from . import _setup  # noqa: E402

# before anything is compiled: the robots' and problems' small programs are kept too
_setup.ensure_cache()

from . import robots  # noqa: E402
from ._cpu import pin_to_one_cpu  # noqa: E402
from .problem import Problem, ViaPoint, Weights  # noqa: E402
from .solver import IPM, AugmentedLagrangian, Auto, Solution, SolverOptions, Status, solve, solve_batch  # noqa: E402
from .sensitivity import sensitivity  # noqa: E402
from .implicit import valid_derivatives  # noqa: E402

#: subpackages imported on first access (PEP 562)
_LAZY = ("anfis", "dataset", "gradcheck", "mappings", "online", "plotting", "resample")

__all__ = ["Problem", "ViaPoint", "Weights", "Solution", "Auto", "IPM", "AugmentedLagrangian", "SolverOptions", "Status",
           "solve", "solve_batch", "sensitivity",
           "valid_derivatives",
           "pin_to_one_cpu", "robots", "__version__", *_LAZY]


def __getattr__(name):
    if name in _LAZY:
        module = _importlib.import_module(f"{__name__}.{name}")
        globals()[name] = module
        return module
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(_LAZY))
