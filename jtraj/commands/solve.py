"""Solve one point-to-point trajectory problem and print, save or plot the result.

Give a start and a goal, each either in joint space (--start-q / --goal-q, radians,
or degrees with --deg) or as a task-space point (--start-xy / --goal-xy, metres,
solved by inverse kinematics). Example (the README's first command):

    jtraj solve --robot serial3 --start-q 0,30,30 --goal-xy 1.35,1.30 --deg --plot serial3.png

Negative entries need no quoting: --start-q -10,30,30 works.
Exit status: 0 when the solution converged (strictly verified), 1 when the solver
stopped without convergence (the summary, JSON and plot are still written), 2 on bad
input. Solve time is reported without compilation: the problem is solved twice and the
second, already compiled call is timed (compile_seconds is the difference). Both calls
run the solver's quickly compiled programs (about 2.4x slower to run than the optimised
ones, which take about 2.5x longer to compile) unless the optimised ones are in the cache
already; ``JTRAJ_QUICK_FIRST=0`` compiles the optimised ones (see the performance guide).
"""

HELP = "solve one trajectory problem (summary, --json, --plot)"


#: the CLI pins this command to one CPU core before JAX starts (jtraj._cpu)
PIN_ONE_CPU = True

#: the CLI keeps the solver's quickly compiled programs for this one-shot command
#: (JTRAJ_QUICK_FIRST=keep, see jtraj._tracecache.quick_first_mode)
QUICK_PROGRAMS = True

#: transcriptions whose motion between the samples is known exactly (jtraj.resample)
CONSTANT_ACCELERATION = ("decoupled", "coupled")


def configure(parser):
    from jtraj.commands import add_robot_param_argument, add_solver_arguments, add_urdf_arguments

    parser.add_argument("--robot", default="serial3", help="robot name (see `jtraj robots`), default serial3")
    add_urdf_arguments(parser, "load a serial arm from a URDF file instead of --robot")
    add_robot_param_argument(parser)
    start = parser.add_mutually_exclusive_group()
    start.add_argument("--start-q", metavar="Q1,Q2,...",
                       help="start configuration (angles in rad, or deg with --deg; lengths in m)")
    start.add_argument("--start-xy", metavar="X,Y", help="start task point [m] (X,Y,Z for spatial arms; inverse kinematics)")
    goal = parser.add_mutually_exclusive_group()
    goal.add_argument("--goal-q", metavar="Q1,Q2,...",
                      help="goal configuration (angles in rad, or deg with --deg; lengths in m)")
    goal.add_argument("--goal-xy", metavar="X,Y", help="goal task point [m] (X,Y,Z for spatial arms; inverse kinematics)")
    parser.add_argument("--deg", action="store_true",
                        help="the angles of --start-q / --goal-q are in degrees (lengths stay in m)")
    parser.add_argument("--N", type=int, default=20, help="number of sampling intervals (default 20)")
    parser.add_argument("--weights", default="time=1,energy=1",
                        help="cost weights, keys time, energy, kinetic, singularity (default 'time=1,energy=1')")
    parser.add_argument("--transcription", default="decoupled", choices=("decoupled", "coupled", "collocation", "shooting", "spline"),
                        help="decoupled (thesis ALD, default), coupled, or Chettibi's collocation "
                             "(midpoint rule), shooting (RK4) and spline (clamped cubic knots)")
    parser.add_argument("--T-max", type=float, default=None, help="upper bound on the total time [s]")
    parser.add_argument("--efforts", choices=("samples", "intervals"), default="samples",
                        help="where the torque bound holds: at the samples (default, the thesis) or also at each "
                             "interval's end, so that the executed motion meets it (decoupled; see jtraj.Problem)")
    parser.add_argument("--via", action="append", default=[], metavar="X,Y",
                        help="imposed passage point of the tip (repeatable)")
    parser.add_argument("--via-tol", type=float, default=1e-3, help="via-point tolerance [m] (default 1e-3)")
    parser.add_argument("--inequalities", choices=("phr", "pbm"), default="phr",
                        help="inequality term of the solver: phr (default) or pbm (SolverOptions.pbm(), opt-in)")
    parser.add_argument("--method", choices=("auto", "al", "ip"), default="auto",
                        help="inner method: auto (default: ip where it applies, else al), al (the augmented-Lagrangian "
                             "loop) or ip (the interior-point method, decoupled transcription only); see "
                             "SolverOptions.method")
    add_solver_arguments(parser)
    parser.add_argument("--json", metavar="PATH", help="write the solution as JSON")
    parser.add_argument("--rate", type=float, default=None, metavar="HZ",
                        help="with --json: also write the trajectory resampled at this rate (t, q, qd, qdd, tau "
                             "on a 1/HZ grid, the last step ending at T), as a controller would execute it "
                             "(decoupled and coupled transcriptions)")
    parser.add_argument("--plot", metavar="PATH", help="write the figures (PNG, PDF, SVG by extension)")


def angular(robot):
    """(n,) bool: which coordinates are angles (rad), the others lengths (m)
    (:func:`jtraj.plotting.coordinate_units`): ``--deg`` converts the angles alone, and
    only they are checked for values beyond 2 pi (``wmr``'s x and y are metres)."""
    import numpy as np

    from jtraj.plotting import coordinate_units

    return np.array([u == "rad" for u in coordinate_units(robot)])


def parse_vector(text, name, n=None, *, deg=False, joints=None, angles=None):
    """'a,b,c' -> float array, ValueError naming ``name`` on malformed or non-finite input;
    with ``deg``, the entries where ``angles`` (a bool mask; default all) is True converted
    from degrees to radians."""
    import math

    import numpy as np

    if text is None:
        return None
    parts = [p.strip() for p in str(text).split(",")]
    try:
        vals = [float(p) for p in parts]
    except ValueError:
        raise ValueError(f"{name} must be comma-separated numbers like 0,30,30; got {text!r}") from None
    if not all(math.isfinite(v) for v in vals):
        raise ValueError(f"{name} must be finite numbers (no NaN or inf); got {text!r}")
    if n is not None and len(vals) != n:
        names = f" ({', '.join(joints)})" if joints else ""
        raise ValueError(f"{name} must have {n} values for this robot{names}, got {len(vals)} ({text!r})")
    arr = np.asarray(vals, dtype=float)
    return np.where(True if angles is None else angles, np.deg2rad(arr), arr) if deg else arr


def check_joint_values(robot, values: dict, deg: bool) -> None:
    """The start and goal configurations given on the command line (option -> radians,
    None where not given) checked as :class:`jtraj.Problem` checks them
    (:func:`jtraj.problem.check_configurations`), the error naming the option; where the
    numbers look like degrees given without ``--deg`` (beyond 2 pi, or inside the joint
    box once read as degrees) the message says to add it. Shared by ``solve`` and
    ``query``."""
    import numpy as np

    from jtraj.problem import check_configurations

    given = {k: np.asarray(v, float) for k, v in values.items() if v is not None}
    hint = "; if these are degrees, add --deg"
    rad = angular(robot)
    if not deg:
        for name, q in given.items():
            if np.any(rad) and np.max(np.abs(q[rad])) > 2 * np.pi:
                raise ValueError(f"{name} = {q.tolist()} has an angle beyond 2 pi: radians are expected{hint}")
    try:
        check_configurations(robot, given)
    except ValueError as exc:
        msg = str(exc)
        if not deg:
            try:
                check_configurations(robot, {k: np.where(rad, np.deg2rad(q), q) for k, q in given.items()})
            except ValueError:
                pass
            else:
                msg += hint
        raise ValueError(msg) from None


def _ik(robot, p, q_init, name):
    try:
        from jtraj.problem import ik_or_raise

        return ik_or_raise(robot, p, q_init, name)
    except ModuleNotFoundError as exc:
        if exc.name and exc.name.startswith("jtraj"):
            raise ValueError(f"{name} needs inverse kinematics (jtraj.robots.ik), which is not available in "
                             f"this installation; give the configuration with --{name[2:].split('-')[0]}-q "
                             f"instead") from None
        raise


def build_problem(args):
    """(robot, Problem) from parsed arguments; ValueError naming the argument."""
    import math

    import numpy as np

    from jtraj import Problem, ViaPoint, Weights, robots

    from jtraj.commands import urdf_robot, with_robot_params

    robot = urdf_robot(args)
    if robot is not None:
        args.robot = robot.name
    else:
        if args.robot not in robots.names():
            raise ValueError(f"--robot must be one of {robots.names()}, got {args.robot!r}")
        try:
            robot = robots.get(args.robot)
        except (ModuleNotFoundError, ImportError) as exc:
            raise ValueError(f"--robot {args.robot}: model not available in this installation ({exc})") from None
    robot = with_robot_params(robot, args)
    n = robot.n
    if args.start_q is None and args.start_xy is None:
        raise ValueError("give a start: --start-q Q1,Q2,... (joint space) or --start-xy X,Y (task space)")
    if args.goal_q is None and args.goal_xy is None:
        raise ValueError("give a goal: --goal-q Q1,Q2,... (joint space) or --goal-xy X,Y (task space)")
    if args.N < 2:
        raise ValueError(f"--N must be an integer >= 2, got {args.N}")
    try:
        weights = Weights.parse(args.weights)
    except ValueError as exc:
        raise ValueError(f"--weights: {exc}") from None
    if args.T_max is not None and not (math.isfinite(args.T_max) and args.T_max > 0):
        raise ValueError(f"--T-max must be a finite number > 0, got {args.T_max}")
    if getattr(args, "efforts", "samples") != "samples" and args.transcription != "decoupled":
        raise ValueError(f"--efforts {args.efforts} needs the decoupled transcription, got --transcription "
                         f"{args.transcription}")
    rate = getattr(args, "rate", None)
    if rate is not None:
        if not (math.isfinite(rate) and rate > 0):
            raise ValueError(f"--rate must be a finite number of Hz > 0, got {rate}")
        if args.transcription not in CONSTANT_ACCELERATION:
            raise ValueError(f"--rate needs a constant-acceleration transcription {CONSTANT_ACCELERATION}, "
                             f"got {args.transcription!r}")
        if not args.json:
            raise ValueError("--rate writes into the JSON file: give --json too")
    if not (math.isfinite(args.via_tol) and args.via_tol > 0):
        raise ValueError(f"--via-tol must be a finite number > 0, got {args.via_tol}")
    d = int(np.asarray(robot.forward_kinematics(np.zeros(n))).shape[0])
    joints = getattr(robot, "joint_names", None)
    rad = angular(robot)
    q_start = parse_vector(args.start_q, "--start-q", n, deg=args.deg, joints=joints, angles=rad)
    q_goal = parse_vector(args.goal_q, "--goal-q", n, deg=args.deg, joints=joints, angles=rad)
    p_start = parse_vector(args.start_xy, "--start-xy", d)
    p_goal = parse_vector(args.goal_xy, "--goal-xy", d)
    vias = [ViaPoint(point=parse_vector(v, "--via", d), tol=args.via_tol) for v in args.via]
    check_joint_values(robot, {"--start-q": q_start, "--goal-q": q_goal}, args.deg)
    if q_start is None:
        q_start = np.asarray(_ik(robot, p_start, None, "--start-xy"))
    if q_goal is None:
        q_goal = np.asarray(_ik(robot, p_goal, q_start, "--goal-xy"))
    try:
        problem = Problem(robot, q_start, q_goal, N=args.N, weights=weights, via_points=vias, T_max=args.T_max,
                          efforts=getattr(args, "efforts", "samples"))
    except ValueError as exc:  # name the CLI argument behind the Problem argument
        msg = str(exc)
        for api, cli in (("q_start", "--start-q" if args.start_q else "--start-xy"),
                         ("q_goal", "--goal-q" if args.goal_q else "--goal-xy"), ("T_max", "--T-max"),
                         ("N =", "--N ="), ("via_points", "--via")):
            msg = msg.replace(api, cli)
        raise ValueError(msg) from None
    return robot, problem


def _tolist(x):
    import math

    import numpy as np

    arr = np.asarray(x)
    if arr.dtype.kind in "fc":
        arr = arr.astype(float)
        out = arr.tolist()
        if arr.ndim == 0:
            return out if math.isfinite(out) else None
        return _finite(out)
    return arr.tolist()


def _finite(x):
    import math

    if isinstance(x, list):
        return [_finite(v) for v in x]
    return x if math.isfinite(x) else None


def finite_json(x):
    """``x`` (dicts, lists, numbers) with every non-finite float replaced by None (JSON
    has no NaN or inf: ``json.dump(..., allow_nan=False)`` then cannot fail)."""
    import math

    if isinstance(x, dict):
        return {k: finite_json(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [finite_json(v) for v in x]
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def solution_dict(args, problem, sol, solve_s, compile_s) -> dict:
    from jtraj import Status

    w = problem.weights
    return {
        "robot": args.robot, "N": problem.N, "transcription": args.transcription, "efforts": problem.efforts,
        "inequalities": getattr(args, "inequalities", "phr"), "method": getattr(args, "method", "auto"),
        "weights": {k: float(getattr(w, k)) for k in ("time", "energy", "kinetic", "singularity")},
        "q_start": _tolist(problem.q_start), "q_goal": _tolist(problem.q_goal),
        "qd_start": _tolist(problem.qd_start), "qd_goal": _tolist(problem.qd_goal),
        "T_max": _tolist(problem.T_max), "via_points": [_tolist(v.point) for v in problem.via_points],
        "converged": bool(sol.converged), "status": int(sol.status), "status_name": Status(int(sol.status)).name,
        "status_message": sol.status_message, "T": _tolist(sol.T), "cost": _tolist(sol.cost),
        "cost_terms": {k: _tolist(v) for k, v in sol.cost_terms.items()}, "energy": _tolist(sol.energy),
        "max_violation": {k: _tolist(v) for k, v in sol.max_violation.items()},
        "iterations": int(sol.iterations), "outer_iterations": int(sol.outer_iterations),
        "kkt_error": _tolist(sol.kkt_error), "solve_seconds": solve_s, "compile_seconds": compile_s,
        "q": _tolist(sol.q), "qd": _tolist(sol.qd), "v": _tolist(sol.v), "tau": _tolist(sol.tau),
        "h": _tolist(sol.h), "history": _tolist(sol.history),
    }


def _f(x, fmt):
    return "nan" if x is None else format(x, fmt)


def summary(d: dict) -> str:
    """A readable multi-line summary of :func:`solution_dict`'s output."""
    from jtraj.solver import SolverOptions

    lines = [f"robot {d['robot']}, N = {d['N']}, {d['transcription']} transcription, weights "
             + ", ".join(f"{k}={v:g}" for k, v in d["weights"].items() if v),
             f"status: {d['status_name']} ({d['status_message']})",
             f"T = {_f(d['T'], '.4f')} s, cost = {_f(d['cost'], '.6g')} ("
             + ", ".join(f"{k} {_f(v, '.4g')}" for k, v in d["cost_terms"].items())
             + f"), energy = {_f(d['energy'], '.4g')}",
             "max violation: " + ", ".join(f"{k} {_f(v, '.1e')}" for k, v in d["max_violation"].items()),
             f"KKT error (optimality; a converged solution's is <= {SolverOptions().tol_optimality:g} by default): "
             f"{_f(d['kkt_error'], '.1e')}",
             f"iterations: {d['iterations']} Newton, {d['outer_iterations']} outer; solve {d['solve_seconds']:.3f} s "
             f"(compile {d['compile_seconds']:.1f} s)"]
    if "effort_between_samples" in d:
        where = ("at the samples only; --efforts intervals bounds the interval ends too"
                 if d.get("efforts", "samples") == "samples" else "at the samples and the interval ends")
        lines.append(f"efforts between the samples (constant acceleration, inverse dynamics): up to "
                     f"{d['effort_between_samples']:.4f} x tau_max (bounded {where})")
    return "\n".join(lines)


def run(args) -> int:
    import json
    import time

    import jax
    import jax.numpy as jnp

    import jtraj
    from jtraj.commands import check_output_file, solver_from_args

    check_output_file(args.json, "--json")
    check_output_file(args.plot, "--plot")
    solver = solver_from_args(args)
    robot, problem = build_problem(args)
    t0 = time.perf_counter()
    sol = jtraj.solve(problem, transcription=args.transcription, solver=solver)
    jax.block_until_ready(sol)
    first = time.perf_counter() - t0
    t0 = time.perf_counter()
    sol = jtraj.solve(problem, transcription=args.transcription, solver=solver)
    jax.block_until_ready(sol)
    solve_s = time.perf_counter() - t0
    d = solution_dict(args, problem, sol, solve_s, max(first - solve_s, 0.0))
    if args.transcription in CONSTANT_ACCELERATION and bool(jnp.all(jnp.isfinite(sol.q))):
        from jtraj.resample import intersample_effort, resample

        if robot.limits.tau_max is not None:
            d["effort_between_samples"] = float(intersample_effort(sol, robot))
        if getattr(args, "rate", None):
            s = resample(sol, robot, dt=1.0 / args.rate)
            d["resampled"] = dict(rate=args.rate, **{k: _tolist(getattr(s, k))
                                                    for k in ("t", "q", "qd", "qdd", "tau")})
    print(summary(d))
    if args.json:
        d = finite_json(d)
        with open(args.json, "w") as fh:
            json.dump(d, fh, indent=1, allow_nan=False)
        print(f"wrote {args.json}")
    if args.plot:
        from jtraj.plotting import drawable, plot_solution, save

        if drawable(sol):
            title = (f"{args.robot}: {d['status_name']}, T = {d['T']:.3f} s, cost = {d['cost']:.4g} "
                     f"(weights {args.weights})")
            save(plot_solution(problem, sol, title=title), args.plot)
            print(f"wrote {args.plot}")
        else:
            import sys

            print(f"no figure written to {args.plot}: the solution holds non-finite values", file=sys.stderr)
    return 0 if d["converged"] else 1
