"""Building a dataset: validate, then solve chunk after chunk (locally or on Ray), streaming
each finished chunk to the store.

A run is described by a :class:`Spec` (plain, picklable values). Chunk ``c`` holds pairs
``[c B, min((c+1) B, P))``; it is a pure function of the spec and ``c``
(:func:`compute_chunk`): pairs from :func:`jtraj.dataset.sampling.sample_pairs`, solved
by one call of ``solve_batch`` on a batch padded to ``B`` rows (the last start with a NaN
goal: the solver flags such rows invalid before any iteration; they are dropped) so that
every chunk runs the same compiled program. That is
why a resumed or Ray-distributed run equals an uninterrupted single-process one.

Chunks are solved by local worker processes (one pinned to each core, see
:mod:`jtraj.dataset._local`), in this process (``workers=1``) or on Ray. Memory is bounded
by the chunks in flight (one per local worker, ``2 x CPUs`` with Ray), never by the
number of pairs.
"""

from __future__ import annotations

import dataclasses
import datetime
import functools
import importlib
import inspect
import math
import os
import platform
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .. import _progress
from . import _local, sampling, store

DEFAULT_SOLVER = "jtraj:solve_batch"
DEFAULT_BATCH = 64  # the smallest default chunk, see default_batch
DEFAULT_WEIGHTS = "time=1,energy=0.1"


def default_batch(pairs: int, accelerator: bool | None = None) -> int:
    """Chunk size (= ``solve_batch`` size) when none is given.

    On a CPU: P / 16 in multiples of 64, within 64..256, so that a large dataset keeps at
    least 16 chunks for the workers while its chunks are long enough for the solver's
    lanes (each chunk ends with a straggler tail). Measured end to end on 2 cores
    (``bench_dataset.py --batches 64 256``, one worker per core, serial3): chunks of 64
    pairs 4.18 pairs/s, of 256 pairs 5.94.

    On an accelerator (``accelerator=None`` asks JAX's default backend): P / 4 in
    multiples of 256, within 256..4096: one process solves a whole chunk at once, and a
    long chunk keeps the device busy. Measured on an H200 (10,000 serial3 pairs, one
    process, compilation included): chunks of 256 pairs 33.5 s, 1024 30.7 s, 2048 31.3 s,
    4096 25.0 s."""
    if accelerator is None:
        import jax

        accelerator = jax.default_backend() != "cpu"
    if accelerator:
        return int(min(4096, max(256, pairs // 4 // 256 * 256)))
    return int(min(256, max(DEFAULT_BATCH, pairs // 16 // 64 * 64)))


#: default sampling-period bound of a dataset, as a multiple of the robot's own h_max.
#: The robots' bounds come from single published scenarios; with N = 20 serial3's caps
#: T at 2 s, and 8 of 96 pairs of the default joint-space law need 2.0-2.6 s (IPOPT:
#: Infeasible_Problem_Detected at h_max = 0.1 s; all 8 solve at 0.2 s). A dataset
#: wants its bounds not to decide which pairs exist, hence twice the robot's bound.
H_MAX_FACTOR = 2.0


def _plain(x):
    """JSON-able form of a robot/limits/options tree."""
    import equinox as eqx

    if x is None or isinstance(x, (bool, str)):
        return x
    if isinstance(x, (int, np.integer)):
        return int(x)
    if isinstance(x, (float, np.floating)):
        return float(x)
    if isinstance(x, eqx.Module) or dataclasses.is_dataclass(x):
        return {f.name: _plain(getattr(x, f.name)) for f in dataclasses.fields(x)}
    if isinstance(x, dict):
        return {str(k): _plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_plain(v) for v in x]
    try:
        return np.asarray(x).tolist()
    except Exception:  # noqa: BLE001
        return repr(x)


@dataclass(frozen=True)
class Spec:
    """Everything that determines a dataset's values (its *identity*)."""

    robot: str
    pairs: int
    seed: int
    N: int = 20
    weights: str = DEFAULT_WEIGHTS
    batch: int = DEFAULT_BATCH
    distribution: sampling.Distribution = field(default_factory=sampling.Distribution)
    options: tuple = ()  # (name, value) overrides of SolverOptions
    solver: str = DEFAULT_SOLVER
    h_max: float | None = None  # sampling-period bound [s] replacing the robot's (None: the robot's)
    efforts: str = "samples"  # where the torque bound holds (jtraj.Problem's efforts)
    #: a URDF arm's file text and tip link (None: ``robot`` is a built-in robot's name)
    urdf: str | None = None
    tip_link: str | None = None
    #: (name, value) parameters of the robot replaced (jtraj.robots.with_params)
    robot_params: tuple = ()

    @property
    def n_chunks(self) -> int:
        return math.ceil(self.pairs / self.batch)

    def chunk_range(self, c: int) -> tuple[int, int]:
        return c * self.batch, min((c + 1) * self.batch, self.pairs)

    # cached per process (a Ray worker reuses them across chunks)
    def robot_model(self):
        return _cached(("robot", self.robot, self.h_max, self.urdf, self.tip_link, self.robot_params),
                       lambda: _robots().from_metadata(self.robot_record() | {"h_max": self.h_max}))

    def robot_record(self) -> dict:
        """The metadata that names the robot (:func:`jtraj.robots.from_metadata`)."""
        return _robot_record(self.robot, self.urdf, self.tip_link, self.robot_params)

    def weights_obj(self):
        import jtraj

        return jtraj.Weights.parse(self.weights)

    def options_obj(self):
        import jtraj

        return jtraj.SolverOptions(**dict(self.options))

    def solve_fn(self):
        return _cached(("solver", self.solver), lambda: resolve_solver(self.solver))

    def identity(self) -> dict:
        robot = self.robot_model()
        w = self.weights_obj()
        return {
            "robot": self.robot,
            "robot_model": _plain(robot),
            "pairs": self.pairs,
            "seed": self.seed,
            "N": self.N,
            "weights": {k: _plain(getattr(w, k)) for k in ("time", "energy", "kinetic", "singularity", "U", "Q")},
            "batch": self.batch,
            "distribution": self.distribution.describe(),
            "solver": self.solver,
            "solver_options": _option_identity(self.options_obj()),
            # only where it differs from the default, so that datasets started before the
            # option existed keep their identity (and resume)
            **({} if self.efforts == "samples" else {"efforts": self.efforts}),
            **({} if self.urdf is None else {"urdf_tip_link": self.tip_link}),
            **({"robot_params": dict(self.robot_params)} if self.robot_params else {}),
        }


#: SolverOptions fields added after datasets were first made with the current format: they
#: enter a dataset's identity only where they differ from their default, so that a dataset
#: started before they existed (same results: at their defaults they change nothing)
#: still resumes
_LATE_OPTIONS = ("inequality_penalty", "pbm_init", "pbm_ratio", "pbm_fallback_iter", "detect_min_viol",
                 "pbm_inner_tol_ratio")


def _option_identity(opts) -> dict:
    import jtraj

    plain, default = _plain(opts), jtraj.SolverOptions()
    for name in _LATE_OPTIONS:
        if getattr(opts, name) == getattr(default, name):
            plain.pop(name, None)
    return plain


_CACHE: dict = {}


def _cached(key, make):
    if key not in _CACHE:
        _CACHE[key] = make()
    return _CACHE[key]


def _robots():
    from jtraj import robots

    return robots


def resolve_solver(name: str):
    """``"module:function"`` -> the function (``jtraj:solve_batch`` by default)."""
    mod, sep, attr = name.partition(":")
    if not sep:
        raise ValueError(f"solver must look like 'module:function', got {name!r}")
    try:
        return getattr(importlib.import_module(mod), attr)
    except (ImportError, AttributeError) as err:
        raise ValueError(f"cannot load solver {name!r}: {err}") from None


# fields written per pair (besides cost_<term> and violation_<family>)
FIELDS = ("index", "q_start", "q_goal", "converged", "status", "q", "qd", "v", "tau", "h", "T", "cost",
          "energy", "max_violation", "iterations", "outer_iterations", "kkt_error")


def _get(sol, name):
    return sol[name] if isinstance(sol, dict) else getattr(sol, name)


def compute_chunk(spec: Spec, c: int, progress=None) -> dict:
    """Sample and solve chunk ``c`` of ``spec``; numpy arrays for pairs of the chunk only.
    ``progress(k)``: called with the number of the chunk's pairs solved so far, where the
    solve function takes a ``progress`` argument (:func:`jtraj.solve_batch` does)."""
    start, stop = spec.chunk_range(c)
    robot = spec.robot_model()
    qs, qg = sampling.sample_pairs(robot, spec.distribution, spec.seed, start, stop)
    count = stop - start
    pad = spec.batch - count
    # padding rows: the last start with a NaN goal, which solve_batch flags INVALID_INPUT
    # before its first iteration (padding with a real pair solved it B - count times over)
    qs_p = np.concatenate([qs, np.repeat(qs[-1:], pad, 0)]) if pad else qs
    qg_p = np.concatenate([qg, np.full((pad, qg.shape[1]), np.nan)]) if pad else qg
    extra = {} if spec.efforts == "samples" else {"efforts": spec.efforts}
    fn = spec.solve_fn()
    if progress is not None and "progress" in inspect.signature(fn).parameters:
        # (the padding rows count as finished before any iteration)
        extra["progress"] = lambda k, B: progress(min(max(k - pad, 0), count))
    from ..solver import from_options
    sol = fn(robot, qs_p, qg_p, N=spec.N, weights=spec.weights_obj(), solver=from_options(spec.options_obj()),
             **extra)
    import jax

    sol = jax.device_get(sol)

    def take(x, dtype=None):
        x = np.asarray(x)[:count]
        return x.astype(dtype) if dtype else x

    out = {"index": np.arange(start, stop, dtype=np.int64), "q_start": qs, "q_goal": qg}
    for k in ("q", "qd", "v", "tau", "h", "T", "cost", "energy"):
        out[k] = take(_get(sol, k), np.float64)
    out["converged"] = take(_get(sol, "converged"), bool)
    out["status"] = take(_get(sol, "status"), np.int32)
    out["iterations"] = take(_get(sol, "iterations"), np.int32)
    try:
        out["outer_iterations"] = take(_get(sol, "outer_iterations"), np.int32)
    except (AttributeError, KeyError):
        out["outer_iterations"] = np.zeros(count, np.int32)
    try:
        out["kkt_error"] = take(_get(sol, "kkt_error"), np.float64)
    except (AttributeError, KeyError):  # a solver that does not report it
        out["kkt_error"] = np.full(count, np.nan)
    viol = _get(sol, "max_violation")
    out["max_violation"] = take(viol["overall"] if isinstance(viol, dict) else viol, np.float64)
    if isinstance(viol, dict):
        for k, v in viol.items():
            if k != "overall":
                out[f"violation_{k}"] = take(v, np.float64)
    try:
        terms = _get(sol, "cost_terms")
    except (AttributeError, KeyError):
        terms = {}
    for k, v in (terms or {}).items():
        out[f"cost_{k}"] = take(v, np.float64)
    return out


def worker_task(spec: Spec, c: int, progress_dir: str | None = None):
    """``(c, compute_chunk(spec, c))`` in a worker process (Ray task or local process):
    the process on one CPU (a Ray worker claims one, see :func:`_one_cpu`), then float64
    and the compilation cache set up as in the CLI process. ``progress_dir``: a folder
    where the chunk's progress is written (:class:`_Progress`)."""
    _one_cpu()
    from jtraj._setup import setup_jax

    setup_jax()
    progress = None if progress_dir is None else functools.partial(_Progress.write, progress_dir, c)
    return c, compute_chunk(spec, c, progress)


class _Progress:
    """The pairs solved so far in the chunks being solved, for the progress bar: written
    by the workers into one small file per chunk in a private temporary folder
    (:meth:`write`, atomically), or kept in memory for chunks solved in this process."""

    def __init__(self, files: bool):
        import tempfile

        self.dir = tempfile.mkdtemp(prefix="jtraj-progress-") if files else None
        self.here: dict[int, int] = {}

    @staticmethod
    def write(folder: str, c: int, k: int) -> None:
        path = os.path.join(folder, f"chunk-{c}")
        try:
            with open(path + ".tmp", "w") as fh:
                fh.write(str(int(k)))
            os.replace(path + ".tmp", path)
        except OSError:
            pass  # progress only

    def partial(self) -> int:
        total = sum(dict(self.here).values())  # (a copy: the solving thread adds entries)
        if self.dir is not None:
            for name in os.listdir(self.dir):
                if name.startswith("chunk-") and not name.endswith(".tmp"):
                    try:
                        with open(os.path.join(self.dir, name)) as fh:
                            total += int(fh.read() or 0)
                    except (OSError, ValueError):
                        pass
        return total

    def done(self, c: int) -> None:
        self.here.pop(c, None)
        if self.dir is not None:
            try:
                os.remove(os.path.join(self.dir, f"chunk-{c}"))
            except OSError:
                pass

    def close(self) -> None:
        if self.dir is not None:
            import shutil

            shutil.rmtree(self.dir, ignore_errors=True)


def _one_cpu():
    """Restrict a worker process to one CPU before JAX starts in it (a no-op in the local
    workers, pinned when they start). A Ray worker may run on all of its node's CPUs;
    XLA would then spread the solver over threads, which is slower and changes the last
    bits of the results (:mod:`jtraj._cpu`), so it claims a CPU of its own
    (:func:`jtraj._cpu.claim_one_cpu`). A process whose JAX already started keeps its
    threads: its chunks may differ in the last bits (a warning says so)."""
    if _local.available_cpus() <= 1:
        return
    try:  # (JAX's private API: without it, assume JAX has not started)
        from jax._src.xla_bridge import backends_are_initialized
    except ImportError:
        def backends_are_initialized():
            return False
    if backends_are_initialized():
        import warnings

        warnings.warn("jtraj dataset: this worker process started JAX on several CPUs before its first chunk; "
                      "its chunks may differ in the last bits from those solved by single-CPU workers",
                      RuntimeWarning, stacklevel=2)
        return
    from jtraj._cpu import claim_one_cpu

    claim_one_cpu()


def _source_hash() -> str:
    """sha256 of jtraj's Python sources (a solver edited between two runs changes it)."""
    from .._source import source_hash

    return source_hash()


def _versions() -> dict:
    import jax

    import jtraj

    v = {"jtraj": jtraj.__version__, "jax": jax.__version__, "numpy": np.__version__,
         "python": platform.python_version(), "platform": platform.platform(), "machine": platform.machine()}
    v["jtraj_source"] = _source_hash()
    try:
        import jaxlib

        v["jaxlib"] = jaxlib.__version__
    except ImportError:  # pragma: no cover
        pass
    try:
        import h5py

        v["h5py"] = h5py.__version__
    except ImportError:  # pragma: no cover
        pass
    return v


def make_spec(robot: str | None, pairs, seed, *, N=20, weights=DEFAULT_WEIGHTS, batch=None, space="joint",
              start_range=1.2, step_range=0.8, min_separation=0.05, ik_method="weighted", options=None,
              solver=DEFAULT_SOLVER, h_max="auto", efforts="samples", urdf=None, tip_link=None,
              robot_params=None) -> Spec:
    """Validated :class:`Spec` (raises ``ValueError`` naming the bad argument; no compute).

    ``robot``: a built-in robot's name (:func:`jtraj.robots.names`), or None with
    ``urdf``: the path of a URDF file (or its XML text) of a serial arm, loaded by
    :func:`jtraj.robots.from_urdf` with its defaults and ``tip_link``. The dataset keeps
    the file's text, so that its robot (:func:`jtraj.robots.from_metadata`), the models
    trained on it and their queries need no file; it is named by the URDF's robot name.
    ``robot_params``: parameters of the robot replaced (a dict for
    :func:`jtraj.robots.with_params`, e.g. ``{"qdd_max": 5.0}`` or per-joint lists,
    ``{"masses": [...]}``), recorded with the dataset like the URDF.

    ``h_max``: the sampling-period bound [s] of the dataset's problems: ``"auto"``
    (default) is :data:`H_MAX_FACTOR` times the robot's own bound, ``"robot"`` keeps the
    robot's, a number sets it (it must exceed the robot's h_min). ``efforts``: where the
    torque bound holds, "samples" or "intervals" (see :class:`jtraj.Problem`).
    ``batch=None``: see :func:`default_batch`.

    ``options``: the solver of the dataset's solves, as a solver object
    (:class:`jtraj.Auto`, :class:`jtraj.IPM`, :class:`jtraj.AugmentedLagrangian`) or as
    a dict of overrides in the flat option names (``SolverOptions``' fields, ``method``
    among them); the dataset records the overrides (its identity). ``solver``: a solver
    object in place of ``options``, or the batch solve function as
    ``"module:function"`` (default :data:`DEFAULT_SOLVER`)."""
    from jtraj import robots

    if urdf is not None:
        if robot is not None:
            raise ValueError(f"give robot (a built-in robot's name) or urdf (a URDF file), not both; got robot "
                             f"{robot!r}")
        urdf, robot = _urdf_text(urdf, tip_link, robot_params)
    elif tip_link is not None:
        raise ValueError("tip_link needs urdf (it names a link of a URDF arm)")
    elif not isinstance(robot, str) or robot not in robots.names():
        raise ValueError(f"unknown robot {robot!r}; choose one of {robots.names()}")

    def integer(x, name, lo):
        if isinstance(x, bool) or not isinstance(x, (int, np.integer)) or x < lo:
            raise ValueError(f"{name} must be an integer >= {lo}, got {x!r}")
        return int(x)

    pairs = integer(pairs, "pairs", 1)
    seed = integer(seed, "seed", 0)
    N = integer(N, "N", 2)
    batch = integer(default_batch(pairs) if batch is None else batch, "batch", 1)
    batch = min(batch, pairs)  # never pad a small run up to a large batch
    if not isinstance(weights, str):
        raise ValueError("weights must be text like 'time=1,energy=0.1'")
    import jtraj

    jtraj.Weights.parse(weights)  # validates
    dist = sampling.Distribution(space=space, start_range=float(start_range), step_range=float(step_range),
                                 min_separation=float(min_separation), ik_method=ik_method)
    from jtraj.solver import SolverOptions
    from jtraj.solver.methods import SOLVERS
    from jtraj.solver.options import from_overrides, overrides

    if isinstance(solver, SOLVERS):
        if options:
            raise ValueError("pass the solver's options on the solver object (solver=) or in options, not both")
        options, solver = solver, DEFAULT_SOLVER
    if isinstance(options, (*SOLVERS, SolverOptions)):
        options = overrides(options)
    elif options is not None and not isinstance(options, dict):
        raise ValueError(f"options must be a dict of solver options or a solver object (jtraj.Auto, jtraj.IPM, "
                         f"jtraj.AugmentedLagrangian), got {type(options).__name__}")
    opts = tuple(sorted((options or {}).items()))
    from_overrides(dict(opts), "options")  # validates
    if not isinstance(solver, str):
        raise ValueError(f"solver must be a solver object or 'module:function', got {type(solver).__name__}")
    resolve_solver(solver)
    params = _robot_params(robot_params, _robot_record(robot, urdf, tip_link, ()))
    limits = robots.from_metadata(_robot_record(robot, urdf, tip_link, params)).limits
    if isinstance(h_max, str):
        if h_max not in ("auto", "robot"):
            raise ValueError(f"h_max must be 'auto', 'robot' or a number of seconds, got {h_max!r}")
        h_max = H_MAX_FACTOR * float(limits.h_max) if h_max == "auto" else None
    elif h_max is not None:
        if isinstance(h_max, bool) or not isinstance(h_max, (int, float, np.integer, np.floating)) \
                or not (math.isfinite(h_max) and h_max > float(limits.h_min)):
            raise ValueError(f"h_max must be a number of seconds above the robot's h_min = {limits.h_min}, "
                             f"got {h_max!r}")
        h_max = float(h_max)
    from jtraj.problem import EFFORTS

    if efforts not in EFFORTS:
        raise ValueError(f"efforts must be one of {EFFORTS}, got {efforts!r}")
    spec = Spec(robot=robot, pairs=pairs, seed=seed, N=N, weights=weights, batch=batch, distribution=dist,
                options=opts, solver=solver, h_max=h_max, efforts=efforts, urdf=urdf, tip_link=tip_link,
                robot_params=params)
    model = spec.robot_model()
    sampling.check(model, dist)
    T = N * float(model.limits.h_max)
    if space == "joint" and sampling.longest_step_time(model, dist) > T:
        # a step of the law can be infeasible on its face (jtraj.Problem would refuse it):
        # such pairs are redrawn; robots whose every step fits keep their pairs and identity
        spec = dataclasses.replace(spec, distribution=dataclasses.replace(dist, max_move_time=T))
    return spec


def _robot_record(robot: str, urdf: str | None, tip_link: str | None, params: tuple) -> dict:
    record = {"robot": robot} if urdf is None else {"robot": robot, "urdf": {"text": urdf, "tip_link": tip_link}}
    return record | ({"robot_params": dict(params)} if params else {})


def _robot_params(params, record: dict) -> tuple:
    """``robot_params`` (a dict of :func:`jtraj.robots.with_params` overrides) checked on
    the robot and made hashable: sorted (name, number or tuple of numbers) pairs."""
    from jtraj import robots

    if params is None:
        return ()
    if not isinstance(params, dict) or not all(isinstance(k, str) for k in params):
        raise ValueError(f"robot_params must be a dict of parameter names to values, got {params!r}")
    if "h_max" in params:
        raise ValueError("robot_params: h_max is the dataset's own option (h_max=), not a robot parameter here")
    try:
        plain = {k: np.asarray(v, dtype=float).tolist() for k, v in params.items()}
    except (TypeError, ValueError):
        raise ValueError(f"robot_params: values must be numbers or sequences of numbers, got {params!r}") from None
    try:  # (a URDF arm's limits among them replace the file's: jtraj.robots.from_urdf)
        robots.from_metadata(record | {"robot_params": plain})
    except ValueError as exc:
        raise ValueError(f"robot_params: {exc}") from None

    def frozen(v):  # nested lists (a (n, 3) parameter) -> nested tuples
        return tuple(frozen(x) for x in v) if isinstance(v, list) else v

    return tuple(sorted((k, frozen(v)) for k, v in plain.items()))


def _urdf_text(source, tip_link, params=None) -> tuple[str, str]:
    """(the XML text, the arm's name) of a URDF file or text that
    :func:`jtraj.robots.from_urdf` loads with the limits among ``params`` (``robot_params``)
    in place of the file's (``ValueError`` naming ``urdf`` or ``tip_link``)."""
    from jtraj import robots
    from jtraj.robots.urdf import URDF_LIMITS

    if tip_link is not None and not isinstance(tip_link, str):
        raise ValueError(f"tip_link must be a link's name, got {tip_link!r}")
    if isinstance(source, (str, os.PathLike)) and not str(source).lstrip().startswith("<"):
        try:
            text = Path(source).read_text()
        except OSError as exc:
            raise ValueError(f"urdf: cannot read {str(source)!r} ({exc.strerror or exc})") from None
        except UnicodeDecodeError:
            text = ""
        if not text.lstrip().startswith("<"):
            raise ValueError(f"urdf: {str(source)!r} is not a URDF file (expected XML text)")
    elif isinstance(source, str):
        text = source
    else:
        raise ValueError(f"urdf must be a URDF file's path or its XML text, got {type(source).__name__}")
    try:
        limits = {k: v for k, v in params.items() if k in URDF_LIMITS} if isinstance(params, dict) else {}
        arm = robots.from_urdf(text, tip_link=tip_link, limits=limits)
    except ValueError as exc:
        raise ValueError(str(exc) if str(exc).startswith("tip_link") else f"urdf: {exc}") from None
    return text, arm.name


def metadata(spec: Spec) -> dict:
    robot = spec.robot_model()
    d = {
        **spec.robot_record(),
        "n": robot.n,
        "limits": _plain(robot.limits),
        "pairs": spec.pairs,
        "N": spec.N,
        "seed": spec.seed,
        "batch": spec.batch,
        "chunks": spec.n_chunks,
        "weights_text": spec.weights,
        "efforts": spec.efforts,
        "sampling": spec.distribution.describe(),
        "versions": _versions(),
        "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "command": " ".join(sys.argv),
        "fields": {
            "index": "(P,) pair index", "q_start": "(P, n) rad", "q_goal": "(P, n) rad",
            "converged": "(P,) strict convergence (status == 0)", "status": "(P,) jtraj.Status code",
            "q": "(P, N+1, n)", "qd": "(P, N+1, n)", "v": "(P, N, n) accelerations", "tau": "(P, N, m) efforts",
            "h": "(P, N) periods [s]", "T": "(P,) total time [s]", "cost": "(P,)", "energy": "(P,)",
            "max_violation": "(P,) overall (relative boxes, absolute goal)", "iterations": "(P,) Newton",
            "outer_iterations": "(P,)", "cost_<term>": "(P,) weighted cost terms",
            "kkt_error": "(P,) first-order optimality error (jtraj.Solution.kkt_error; NaN where the "
                         "solver or the jtraj version that wrote the chunk did not report it)",
            "violation_<family>": "(P,) per constraint family",
        },
    }
    return d


def _check_ray(address):
    from . import _ray

    return _ray.connect(address, worker_task)


def build(spec: Spec, out: str, *, ray: str | None = None, workers: int | None = None, progress: bool = True,
          max_chunks: int | None = None, log=None) -> dict:
    """Build (or resume) the dataset ``spec`` at ``out``. Returns a summary dict.

    ``ray``: ``None`` (this process), ``"auto"``, ``"local"``/``"local:K"`` (start a
    local Ray instance with K CPUs) or a cluster address ``host:port``/``ray://host:port``.
    ``workers``: without Ray, the number of local worker processes (pinned
    JAX, one per core; ``None``: one per available CPU, or 1 when JAX's default backend
    is an accelerator); 1 solves in this process. Workers are spawned: a script calling
    ``build`` with them must do so under ``if __name__ == "__main__":``. With ``None``,
    where this process may use several CPUs, even a single (last) chunk goes to a worker
    process: XLA's rounding depends on how many CPUs the solving process may use, so
    chunks solved here would differ in the last bits (1e-12) from the workers'.
    ``workers=1`` solves here all the
    same: its values equal the workers' only where this process runs on one CPU
    (restricted before JAX starts, e.g. ``taskset -c 0 python ...``).
    ``max_chunks`` stops after that many new chunks (tests).
    """
    log = log or (lambda s: print(s, file=sys.stderr))
    ident = spec.identity()
    store.inspect(out, ident)  # read-only checks first
    if workers is not None and (not isinstance(workers, int) or isinstance(workers, bool) or workers < 1):
        raise ValueError(f"workers must be a positive integer or None, got {workers!r}")
    backend = _check_ray(ray) if ray else None  # then the cluster; both before any compute
    writer = store.Writer(out, ident, metadata(spec))
    ticker = None
    partial = None
    try:
        done = set(writer.finished(spec.n_chunks))
        for c, why in sorted(writer.rejected.items()):  # corrupt, or of another dataset: solved again
            log(f"jtraj dataset: chunk {c} is solved again: {why}")
        todo = [c for c in range(spec.n_chunks) if c not in done]
        if max_chunks is not None:
            todo = todo[:max_chunks]
        pairs_done = sum(spec.chunk_range(c)[1] - spec.chunk_range(c)[0] for c in done)
        conv_done = 0
        for c in sorted(done):
            conv_done += int(np.sum(store.read_chunk(writer.path, c, ["converged"])["converged"]))
        if writer.resumed:
            log(f"jtraj dataset: resuming {out}: {len(done)}/{spec.n_chunks} chunks already done")
            old = store.read_manifest(writer.path)["metadata"].get("versions", {})
            now = _versions()
            changed = [f"{k} {old.get(k)} -> {now.get(k)}" for k in ("jtraj", "jtraj_source", "jax", "jaxlib",
                                                                          "machine")
                       if old.get(k) != now.get(k)]
            if changed and todo:
                log("jtraj dataset: warning: resuming with different software/hardware (" + ", ".join(changed)
                    + "); new chunks may differ in the last bits from an uninterrupted run")
        stats = {"pairs_done": pairs_done, "converged": conv_done, "new_pairs": 0, "new_chunks": 0}
        bar, live = None, _progress.live()
        if progress:
            from tqdm import tqdm

            # until the first chunk arrives the workers compile the solver (or load it from
            # the compilation cache): the bar says so and its clock runs (ticker)
            bar = tqdm(total=spec.pairs, initial=pairs_done, unit="pair", desc=COMPILING if todo else "dataset",
                       dynamic_ncols=True, smoothing=0.1, file=sys.stderr, mininterval=_progress.interval(0.1))
            bar.set_postfix_str(_postfix(stats))
        t0 = time.perf_counter()
        local = bool(todo) and backend is None
        if local:
            k = min(len(todo), _local.default_workers() if workers is None else workers)
            # by default even one chunk goes to a (pinned) worker process unless this
            # process solves as one would: its rounding would differ (see _local)
            if k > 1 or (workers is None and not _local.solves_here()):
                # the pairs solved inside the chunks in flight, for the bar (not with Ray,
                # whose workers may run elsewhere: the bar moves per chunk there)
                partial = None if bar is None else _Progress(files=True)
                backend = _local.ProcessBackend(k, worker_task, None if partial is None else partial.dir)
            elif bar is not None:
                partial = _Progress(files=False)
        counting = threading.Lock()
        if bar is not None and todo:
            # until the first pairs are solved the workers compile the solver (or load it
            # from the compilation cache): the bar says so and its clock runs (ticker)
            ticker = _Ticker(bar, lambda: _redraw(bar, stats, partial, counting), every=_progress.interval(1.0))

        def finish(c, arrays):
            start, stop = spec.chunk_range(c)
            writer.write_chunk(c, start, arrays)
            k = stop - start
            with counting:  # a chunk moves from "in flight" to "done" at once for the bar
                stats["pairs_done"] += k
                stats["new_pairs"] += k
                stats["new_chunks"] += 1
                stats["converged"] += int(np.sum(arrays["converged"]))
                if partial is not None:
                    partial.done(c)
            if bar is not None:
                bar.set_postfix_str(_postfix(stats), refresh=False)
                _redraw(bar, stats, partial, counting, refresh=live)  # (in a log: the ticker's, once a minute)

        if todo:
            if backend is None:
                for c in todo:
                    progress = None if partial is None else functools.partial(partial.here.__setitem__, c)
                    finish(c, compute_chunk(spec, c, progress))
            else:
                backend.run(spec, todo, finish)
        wall = time.perf_counter() - t0
        if ticker is not None:
            ticker.stop()
        if bar is not None:
            bar.close()
        stats["seconds"] = wall
        stats["complete"] = len(done) + stats["new_chunks"] == spec.n_chunks
        stats["pairs_per_s"] = stats["new_pairs"] / wall if wall > 0 and stats["new_pairs"] else float("nan")
        return stats
    finally:
        if ticker is not None:
            ticker.stop()
        writer.close()
        if backend is not None:
            backend.close()
        if partial is not None:
            partial.close()


#: the progress bar's label until the first chunk is done
COMPILING = "dataset: compiling the solver (first chunk; cached afterwards)"


def _redraw(bar, stats, partial, counting, refresh: bool = True) -> None:
    """The bar at the pairs of the finished chunks plus those solved so far inside the
    chunks in flight (read together under ``counting``, never counting a chunk twice or
    going backwards); labelled "compiling" until the first pairs are solved. Drawn where
    ``refresh``, else only set for the next drawing."""
    with counting:
        inside = 0 if partial is None else partial.partial()
        done = stats["pairs_done"]
        if bar.desc != "dataset" and (inside or stats["new_chunks"]):
            bar.set_description_str("dataset", refresh=False)
        bar.n = max(bar.n, min(done + inside, bar.total))
        if refresh:
            bar.refresh()


class _Ticker:
    """Calls ``redraw`` every ``every`` seconds (a second where stderr is watched live, a
    minute in a log: :mod:`jtraj._progress`): the bar's clock runs while the first chunk
    waits for the solver's compilation (a minute or more), and the pairs solved inside
    the chunks in flight show (:class:`_Progress`)."""

    def __init__(self, bar, redraw, every: float = 1.0):
        import threading

        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, args=(redraw, every), daemon=True)
        self._thread.start()

    def _run(self, redraw, every):
        while not self._stop.wait(every):
            redraw()

    def stop(self):
        self._stop.set()
        self._thread.join()


def _postfix(stats):
    n = stats["pairs_done"]
    return f"converged {100.0 * stats['converged'] / n:.1f}%" if n else "converged -"

