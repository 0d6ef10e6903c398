"""jtraj: differentiable robot trajectory optimisation in JAX."""

__version__ = "0.1.0"

from . import robots  # noqa: E402
from ._cpu import pin_to_one_cpu  # noqa: E402
from .problem import Problem, ViaPoint, Weights  # noqa: E402
from .solver import Solution, SolverOptions, Status, solve, solve_batch  # noqa: E402
from .sensitivity import sensitivity  # noqa: E402
from .implicit import valid_derivatives  # noqa: E402
from . import resample  # noqa: E402  (jtraj.resample.resample, .intersample_effort)

__all__ = ["Problem", "ViaPoint", "Weights", "Solution", "SolverOptions", "Status", "solve", "solve_batch", "sensitivity",
           "valid_derivatives",
           "pin_to_one_cpu", "resample", "robots", "__version__"]
