"""The trajectory solver: the augmented-Lagrangian (:mod:`.al`) and interior-point
(:mod:`.ipm`) methods on the transcribed NLP (:mod:`.nlp`), certified at the end
(:mod:`.certify`); :func:`solve` and :func:`solve_batch` (:mod:`.api`) are the entry
points, with the batch lane driver in :mod:`.lanes`."""

from . import ipm  # noqa: F401
from .results import Solution, Status, _MESSAGES  # noqa: F401
from .options import PBM_SETTINGS, SolverOptions, _SWITCHES, _SplitOptions, _TRACED_OPTIONS, _TracedOptions, _options_jit, _split_cached, _split_options, _static  # noqa: F401
from .nlp import Multipliers, _NLP, _PBM_FLOOR, _kink_curvature, _pbm, _pbm_phi, _pbm_slope, _phr, _stage_axes, _stage_mult, _violation  # noqa: F401
from .certify import _POLISH_DONE, _al_kkt_error, _at_most_once, _chord_jacobian, _estimate_multipliers, _final_polish, _init_multipliers, _kkt_error, _ls_multipliers, _multiplier_kkt_error, _polish, _residual, _ridge_solve, _stationarity  # noqa: F401
from .al import _LADDER, _STEPS, _State, _TRIAL_SHIFT, _TRIAL_STEP, _fallback, _finished, _first_run_iter, _held, _init_state, _loop, _max_restarts, _needs_restart, _newton_step, _next_inner_tol, _restart, _run, _run_with_restart, _with_phase  # noqa: F401
from .core import _check_method, _finish, _ip_result, _ip_run, _ip_solved, _ip_tolerances, _placeholder_init, _prepare, _resolve_method, _resolved, _solve_core, _solve_jit, _stagewise, initial_guess  # noqa: F401
from .lanes import _LanePrograms, _POOL_MIN, _add_ip_iterations, _cpu_lanes, _finish_all, _finish_batch_jit, _finish_lanes, _gather_jit, _ip_init_batch_jit, _ip_merge_jit, _join_jit, _lane_counts, _lane_programs, _pad_rows, _padded, _prepare_batch_jit, _restart_lanes, _run_lanes, _run_pool, _segment, _segment_jit, _solve_batch_ip, _solve_batch_jit, _solve_compacted, _solve_problems, _take  # noqa: F401
from .api import _check_efforts, _check_init, _guess_batch_jit, _problem, _problems_jit, solve, solve_batch  # noqa: F401
