"""List the built-in robots, their degrees of freedom, parameters and limits; or show
the serial arm a URDF file describes, as ``jtraj solve --urdf`` and ``jtraj dataset
--urdf`` would load it."""

HELP = "list the built-in robots and their parameters, or show a URDF arm"


def configure(parser):
    from jtraj.commands import add_robot_param_argument, add_urdf_arguments

    parser.add_argument("name", nargs="?", help="show one robot in detail")
    add_urdf_arguments(parser, "show the serial arm of this URDF file in detail")
    add_robot_param_argument(parser)


def run(args) -> int:
    from jtraj import robots
    from jtraj.commands import robot_params, urdf_robot, with_robot_params

    if args.urdf is not None and args.name is not None:
        raise ValueError(f"give a built-in robot's name or --urdf, not both; got {args.name!r}")
    if args.robot_param and args.urdf is None and args.name is None:
        raise ValueError("--robot-param needs a robot: a name or --urdf PATH")
    robot = urdf_robot(args)
    if robot is None and args.name is None:
        from jtraj.robots.urdf import INSTALL_HINT

        width = max(map(len, robots.names()))
        for name in robots.names():
            try:
                n, note = f"n = {robots.get(name).n}", ""
            except ImportError:  # a URDF arm without example-robot-data
                n, note = "n = ?", f" ({INSTALL_HINT})"
            print(f"{name:{width}s}  {n}  {robots.summary(name)}{note}")
        print("\n`jtraj robots NAME` shows one robot's coordinates, parameters and limits; "
              "`jtraj robots --urdf PATH` shows your own arm.")
        return 0
    if robot is None:
        if args.name not in robots.names():
            raise ValueError(f"name must be one of {robots.names()} (or give --urdf PATH), got {args.name!r}")
        robot = robots.get(args.name)
    _show(args.name or robot.name, with_robot_params(robot, args),
          None if args.name is None else robots.summary(args.name))
    if args.urdf is not None and "qdd_max" not in robot_params(args):
        from jtraj.robots.urdf import DEFAULT_QDD_MAX

        print(f"  (a URDF has no acceleration bounds: qdd_max is jtraj's default {DEFAULT_QDD_MAX:g}; "
              f"set your arm's with --robot-param qdd_max=...)")
    return 0


def _show(name, robot, summary=None):
    import numpy as np

    from jtraj import robots
    from jtraj.plotting import coordinate_units, effort_units

    print(f"{name}: n = {robot.n}, {type(robot).__name__}")
    if summary:
        print(f"  {summary}")
    joints = getattr(robot, "joint_names", None)
    if joints:
        print("  joints  ", ", ".join(joints))
    print(f"  units    coordinates {_runs(coordinate_units(robot))}; efforts {_runs(effort_units(robot))}")
    print("  parameters:", ", ".join(robots.parameter_names(robot)))
    lim = robot.limits
    for f in ("q_min", "q_max", "qd_max", "qdd_max", "tau_max", "h_min", "h_max"):
        val = getattr(lim, f)
        print(f"  {f:8s} {'-' if val is None else np.array2string(np.asarray(val), precision=4)}")


def _runs(units):
    """["rad", "rad", "m"] -> "2 rad, 1 m": the units in order, equal neighbours counted."""
    from itertools import groupby

    return ", ".join(f"{len(list(run))} {unit}" for unit, run in groupby(units))
