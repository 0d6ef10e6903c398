"""Check jax.grad of the cost and of the augmented Lagrangian against the hand-written
discrete adjoint of the decoupled model and against central finite differences, in
float64, at random points of each robot (see jtraj.gradcheck for the derivation).

Exit status 0 when every robot checked meets the tolerances (1e-8 relative against the
adjoint, 1e-6 against finite differences), 1 when one fails; robots whose model is not
available yet are listed as skipped.

    jtraj gradcheck --robot all
    jtraj gradcheck --robot serial3 --N 20 --points 5 --json gradcheck.json
    jtraj gradcheck --urdf arm.urdf --tip-link tool0
    jtraj gradcheck --robot panda --robot-param masses=3,3,3,3,1.5,1.5,0.5
"""

HELP = "check autodiff gradients against the discrete adjoint and finite differences"


def configure(parser):
    from jtraj.commands import add_robot_param_argument, add_urdf_arguments

    parser.add_argument("--robot", default=None, help="a robot name (see `jtraj robots`) or 'all' (default)")
    add_urdf_arguments(parser, "check the serial arm of a URDF file instead of --robot")
    add_robot_param_argument(parser)
    parser.add_argument("--N", type=int, default=10, help="number of intervals (default 10)")
    parser.add_argument("--points", type=int, default=3, help="random points per robot (default 3)")
    parser.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    parser.add_argument("--weights", default=None,
                        help="cost weights, e.g. 'time=1,energy=1,kinetic=0.1,singularity=0.01' (the default)")
    parser.add_argument("--fd-step", type=float, default=None,
                        help="central-difference step in the scaled variables (default 1e-6)")
    parser.add_argument("--json", metavar="PATH", help="write the report as JSON")


def run(args) -> int:
    import json
    import math

    from jtraj import gradcheck as gc
    from jtraj import robots
    from jtraj.problem import Weights

    from jtraj.commands import check_output_file, urdf_robot, with_robot_params

    check_output_file(args.json, "--json")
    if args.robot is not None and args.urdf is not None:
        raise ValueError("give --robot (a built-in robot, or 'all') or --urdf (a URDF file), not both")
    robot = urdf_robot(args) or args.robot or "all"
    if isinstance(robot, str) and robot != "all" and robot not in robots.names():
        raise ValueError(f"--robot must be 'all' or one of {robots.names()}, got {robot!r}")
    if args.robot_param:
        if robot == "all":
            raise ValueError("--robot-param needs one robot: --robot NAME or --urdf PATH")
        robot = with_robot_params(robots.get(robot) if isinstance(robot, str) else robot, args)
    if args.N < 2:
        raise ValueError(f"--N must be >= 2, got {args.N}")
    if args.points < 1:
        raise ValueError(f"--points must be >= 1, got {args.points}")
    step = gc.DEFAULT_FD_STEP if args.fd_step is None else args.fd_step
    if not (math.isfinite(step) and step > 0):
        raise ValueError(f"--fd-step must be a finite number > 0, got {args.fd_step}")
    try:
        weights = None if args.weights is None else Weights.parse(args.weights)
    except ValueError as exc:
        raise ValueError(f"--weights: {exc}") from exc
    report = gc.gradcheck(robot, N=args.N, seed=args.seed, points=args.points, weights=weights,
                          fd_step=step)
    print(gc.format_table(report))
    if args.json:
        def clean(x):  # JSON has no NaN/inf
            if isinstance(x, float) and not math.isfinite(x):
                return None
            if isinstance(x, dict):
                return {k: clean(v) for k, v in x.items()}
            if isinstance(x, list):
                return [clean(v) for v in x]
            return float(x) if hasattr(x, "dtype") else x

        with open(args.json, "w") as fh:
            json.dump(clean(report.to_dict()), fh, indent=2)
    return 0 if report.passed else 1
