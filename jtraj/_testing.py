"""The internals that jtraj's tests and benchmarks reach into, in one explicitly internal
place.

Not a public API: these names follow the solver's modules and change with them. A test
that checks a piece of the solver (a penalty's derivatives, the polish, one Newton
model, the multiplier estimates) imports it from here instead of naming a private
function of the module that holds it; everything a user calls is in :mod:`jtraj`.

This is the one module of ``jtraj`` that imports private names of the others (the
layout test, ``tests/test_layout.py``, exempts it by name).
"""

from .dataset.build import _Progress as DatasetProgress
from .solver import ipm, loop, staged  # modules whose internals tests check
from .solver.al import (ALMethod, ALState, al_finished, al_loop, held_bounds, init_state, next_inner_tol,
                        restart_state, run_al, run_with_restart, with_phase)
from .solver.al import _TRIAL_SHIFT as TRIAL_SHIFT
from .solver.al import _TRIAL_STEP as TRIAL_STEP
from .solver.api import _guess_batch_jit as guess_batch_jit
from .solver.api import _problems_jit as problems_jit
from .solver.certify import (al_kkt_error, estimate_multipliers, final_polish, init_multipliers,
                             kkt_error, ls_multipliers)
from .solver.certify import _polish as polish
from .solver.core import (finish, initial_guess, ip_method, ip_tolerances, run_ip,
                          placeholder_init, prepare, resolve_method, solve_jit, stagewise_directions)
from .solver.lanes import _ip_init_batch_jit as ip_init_batch_jit
from .solver.lanes import _prepare_batch_jit as prepare_batch_jit
from .solver.lanes import _lane_programs as lane_programs
from .solver.lanes import segment_jit, solve_batch_jit, solve_problems
from .solver.nlp import NLP, PBM_FLOOR, Multipliers, kink_curvature, violation
from .solver.nlp import _pbm as pbm
from .solver.nlp import _stage_axes as stage_axes
from .solver.nlp import _stage_mult as stage_mult
from .solver.nlp import _pbm_phi as pbm_phi
from .solver.nlp import _pbm_slope as pbm_slope
from .solver.nlp import _phr as phr
from .solver.options import (TRACED_OPTIONS, SolverOptions, SplitOptions, TracedOptions,
                             split_options, static_options)
from .solver.results import Solution, Status
from .solver.staged import _solve_al_jit as staged_al_jit
from .solver.staged import _solve_ip_jit as staged_ip_jit
from .solver.staged import _start as staged_start
from .solver.ipm import _ALPHAS as IPM_ALPHAS
from .solver.ipm import _RHO_E as IPM_RHO_E
from .solver.ipm import _SHIFT_LADDER as IPM_SHIFT_LADDER
from .solver.ipm import _TRIAL_SHARE as IPM_TRIAL_SHARE
from .solver.ipm import _flat as ipm_flat
from .solver.ipm import _ladder_directions as ipm_ladder_directions
from .solver.ipm import _ladder_directions_xla as ipm_ladder_directions_xla
from .solver.ipm import _model as ipm_model
from .solver.ipm import _parts as ipm_parts
from .solver.ipm import _shorter_trials as ipm_shorter_trials
from .solver.ipm import _trial as ipm_trial
from .solver.ipm import _with_rhs as ipm_with_rhs
from ._kkt_native import _compiler as native_compiler
from ._setup import _state as setup_state
from .robots import Robot as _Robot
from .transcription import prefix_sums, suffix_sums

mass_matrix_mechanism = _Robot._mass_matrix_mechanism  # (robot, q): the mass matrix of the mechanism alone

#: internals of the lazily imported subpackages, resolved on first access (PEP 562) so
#: that importing this module loads neither the ANFIS nor the gradient check
_LAZY = {"auto_radii": ("jtraj.mappings", "_auto_radii"), "gradcheck_rel": ("jtraj.gradcheck", "_rel")}


def __getattr__(name):
    if name in _LAZY:
        import importlib

        module, attr = _LAZY[name]
        return getattr(importlib.import_module(module), attr)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = ["ALMethod", "ALState", "IPM_ALPHAS", "IPM_RHO_E", "IPM_SHIFT_LADDER", "IPM_TRIAL_SHARE", "Multipliers", "NLP",
           "PBM_FLOOR", "Solution", "SolverOptions", "SplitOptions", "Status", "TRACED_OPTIONS", "TRIAL_SHIFT",
           "TRIAL_STEP", "TracedOptions", "al_finished", "al_kkt_error", "al_loop", "estimate_multipliers",
           "final_polish", "finish", "guess_batch_jit", "held_bounds", "init_multipliers", "init_state",
           "initial_guess", "ip_init_batch_jit", "ip_method", "ip_run", "ip_tolerances", "ipm", "loop",
           "ipm_flat", "ipm_ladder_directions", "ipm_ladder_directions_xla", "ipm_model", "ipm_parts",
           "ipm_shorter_trials", "ipm_trial", "ipm_with_rhs", "kink_curvature", "kkt_error", "lane_programs",
           "ls_multipliers", "mass_matrix_mechanism", "native_compiler", "next_inner_tol", "pbm", "pbm_phi",
           "pbm_slope", "phr", "placeholder_init", "polish", "prefix_sums", "prepare", "prepare_batch_jit", "problems_jit",
           "resolve_method", "restart_state", "run_al", "run_with_restart", "segment_jit", "setup_state",
           "solve_batch_jit", "solve_jit", "solve_problems", "split_options", "staged", "staged_al_jit",
           "stage_axes", "stage_mult", "staged_ip_jit", "staged_start", "stagewise_directions", "static_options", "suffix_sums", "violation",
           "with_phase"]  # and the names of _LAZY


def ip_run(nlp, state, opts):
    """The interior-point method's run from the AL state ``state`` as a solve runs it
    (:func:`jtraj.solver.core.solve_core`): its final state."""
    return run_ip(nlp, state, opts)[1]
