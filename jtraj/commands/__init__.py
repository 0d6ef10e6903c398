"""Sub-commands of the ``jtraj`` CLI; see :mod:`jtraj.cli` for the protocol."""

from __future__ import annotations

import os
import re


def check_input_file(path, option: str) -> None:
    """ValueError naming ``option`` unless ``path`` is an existing, readable file."""
    if path is None:
        return
    if not os.path.exists(path):
        raise ValueError(f"{option} {path!r} does not exist")
    if os.path.isdir(path):
        raise ValueError(f"{option} {path!r} is a directory, not a file")
    if not os.access(path, os.R_OK):
        raise ValueError(f"{option} {path!r} is not readable")


def check_output_file(path, option: str) -> None:
    """ValueError naming ``option`` unless a file can be written at ``path``: checked
    before any compute, so that a typo in an output path does not throw a finished
    solve or training away."""
    if path is None:
        return
    path = os.fspath(path)
    if not path or os.path.isdir(path):
        raise ValueError(f"{option} {path!r} is a directory, not a file name")
    folder = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(folder):
        raise ValueError(f"{option} {path!r}: the folder {folder!r} does not exist")
    if not os.access(folder, os.W_OK | os.X_OK) or (os.path.exists(path) and not os.access(path, os.W_OK)):
        raise ValueError(f"{option} {path!r} is not writable")


def add_urdf_arguments(parser, use: str) -> None:
    """``--urdf PATH`` and ``--tip-link NAME`` (``use``: what ``--urdf`` does, the start
    of its help)."""
    parser.add_argument("--urdf", metavar="PATH", help=f"{use} (jtraj.robots.from_urdf: limits from the file, "
                        "qdd_max 10 rad/s^2)")
    parser.add_argument("--tip-link", metavar="NAME", help="with --urdf: the tip link (default: the end of the only "
                        "branch of movable joints, which may be a gripper's; see 'jtraj robots --urdf PATH')")


def urdf_robot(args):
    """The arm ``--urdf`` and ``--tip-link`` give, or None without ``--urdf``
    (``ValueError`` naming the option)."""
    if args.tip_link is not None and args.urdf is None:
        raise ValueError("--tip-link needs --urdf")
    if args.urdf is None:
        return None
    from jtraj import robots
    from jtraj.robots.urdf import URDF_LIMITS

    # the file's limits give way to --robot-param's (a file may lack them or hold zeros)
    limits = {k: v for k, v in robot_params(args).items() if k in URDF_LIMITS}
    try:
        return robots.from_urdf(args.urdf, tip_link=args.tip_link, limits=limits)
    except ValueError as exc:
        raise ValueError(f"--urdf {args.urdf}: {cli_limits_hint(str(exc))}") from None


def cli_limits_hint(msg: str) -> str:
    """A loader's message with its hint ``limits=dict(qd_max=..., ...)`` in the command
    line's words (``--robot-param qd_max=...``)."""
    return re.sub(r"limits=dict\(([^)]*)\)",
                  lambda m: " ".join(f"--robot-param {k}=..." for k in re.findall(r"(\w+)=", m[1])), msg)


def add_robot_param_argument(parser) -> None:
    """The repeatable ``--robot-param NAME=VALUE`` (:func:`robot_params`)."""
    parser.add_argument("--robot-param", action="append", default=[], metavar="NAME=VALUE",
                        help="replace a parameter of the robot (repeatable; jtraj.robots.with_params): a limit "
                             "(qdd_max, tau_max, qd_max, ...) or a model parameter (masses, ...), one number for "
                             "every joint or one per joint, e.g. qdd_max=5 or tau_max=87,87,87,87,12,12,12; see "
                             "'jtraj robots NAME' for the names")


def robot_params(args) -> dict:
    """``--robot-param NAME=VALUE`` as {name: number or list of numbers} (``ValueError``
    naming the option)."""
    params = {}
    for item in getattr(args, "robot_param", None) or []:
        name, sep, text = item.partition("=")
        name = name.strip()
        if not sep or not name or not text.strip():
            raise ValueError(f"--robot-param must look like NAME=VALUE (e.g. qdd_max=5), got {item!r}")
        try:
            values = [float(x) for x in text.replace(",", " ").split()]
        except ValueError:
            raise ValueError(f"--robot-param {name}: expected a number or comma-separated numbers, got "
                             f"{text!r}") from None
        if name in params:
            raise ValueError(f"--robot-param {name} given twice")
        params[name] = values[0] if len(values) == 1 else values
    return params


def with_robot_params(robot, args):
    """``robot`` with ``--robot-param``'s parameters replaced (``ValueError`` naming the option)."""
    params = robot_params(args)
    if not params:
        return robot
    from jtraj import robots

    try:
        return robots.with_params(robot, **params)
    except ValueError as exc:
        raise ValueError(f"--robot-param: {exc}") from None


#: ``--solver`` names and the method each is (``ipm``/``ip`` the interior-point method
#: with its AL fallback, ``al`` the augmented-Lagrangian method alone)
SOLVER_NAMES = {"auto": "auto", "ipm": "ip", "ip": "ip", "al": "al"}


def add_solver_arguments(parser, when: str = "", functions: bool = False) -> None:
    """``--solver NAME`` and the repeatable ``--option NAME=VALUE`` (``when``: a prefix
    of their help, such as "with --refine: "; ``functions``: ``--solver`` also takes a
    batch solve function as ``module:function``, which tests use)."""
    parser.add_argument("--solver", default=None, metavar="{auto,ipm,al}",
                        help=f"{when}the solver: auto (default: the interior-point method where it applies, else "
                             "the augmented-Lagrangian method), ipm (the interior-point method with the AL "
                             "fallback, decoupled transcription only) or al (jtraj.Auto, jtraj.IPM, "
                             "jtraj.AugmentedLagrangian); the same as --method auto/ip/al")
    parser.add_argument("--option", action="append", default=[], metavar="NAME=VALUE",
                        help=f"{when}a solver option (repeatable) in jtraj.SolverOptions' names: the "
                             "AugmentedLagrangian fields (tol_optimality, max_iter, ...) and the IPM fields "
                             "with the prefix ip_ (ip_max_iter, ...), e.g. --option tol_optimality=1e-6")
    parser.set_defaults(solver_functions=functions)


def solve_function(args) -> str | None:
    """The ``module:function`` a ``--solver`` names, or None."""
    value = getattr(args, "solver", None)
    return value if value is not None and ":" in value else None


def solver_overrides(args) -> dict:
    """The solver of the parsed arguments as flat option overrides (the form
    :func:`jtraj.solver.options.from_overrides` and a dataset take): the method of
    ``--solver`` or ``--method``, the settings of ``--inequalities pbm``, ``--max-iter``
    where the command has it, then each ``--option``. ``ValueError`` naming the argument."""
    from jtraj.solver import PBM_SETTINGS, SolverOptions

    method = getattr(args, "method", "auto")
    name = getattr(args, "solver", None)
    if name is not None and solve_function(args) is None:
        if name not in SOLVER_NAMES:
            raise ValueError(f"--solver must be one of auto, ipm, al, got {name!r}")
        if method != "auto" and SOLVER_NAMES[name] != method:
            raise ValueError(f"--solver {name} and --method {method} disagree; give one of them")
        method = SOLVER_NAMES[name]
    out = dict(PBM_SETTINGS) if getattr(args, "inequalities", "phr") == "pbm" else {}
    if getattr(args, "max_iter", None) is not None:
        out["max_iter"] = args.max_iter
    fields = SolverOptions.__dataclass_fields__
    for text in getattr(args, "option", []):
        key, sep, value = text.partition("=")
        key = key.strip()
        if not sep or not key:
            raise ValueError(f"--option must look like NAME=VALUE, got {text!r}")
        if key not in fields or key == "method":
            raise ValueError(f"--option {key}: unknown solver option; the options are "
                             f"{sorted(set(fields) - {'method'})} (the method is --solver)")
        out[key] = _option_value(key, value.strip(), fields[key].default)
    out["method"] = method
    return out


def _option_value(key: str, text: str, default):
    """``text`` as a value of the option's type (that of its default)."""
    try:
        if isinstance(default, bool):
            if text.lower() not in ("true", "false", "1", "0", "on", "off", "yes", "no"):
                raise ValueError
            return text.lower() in ("true", "1", "on", "yes")
        if isinstance(default, int):
            number = float(text)
            if not number.is_integer():
                raise ValueError
            return int(number)
        if isinstance(default, float):
            return float(text)
        return text
    except ValueError:
        kind = {bool: "true or false", int: "an integer", float: "a number"}.get(type(default), "text")
        raise ValueError(f"--option {key}={text}: the value must be {kind}") from None


def solver_from_args(args):
    """The solver object of the parsed arguments (:func:`solver_overrides`)."""
    from jtraj.solver.options import from_overrides

    return from_overrides(solver_overrides(args), "--option")
