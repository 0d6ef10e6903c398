"""Generate, inspect and plot datasets of optimal trajectories.

  jtraj dataset [build] --robot serial3 --pairs 10000 --seed 0 --out runs/s3 [--N 20]
                (or --urdf arm.urdf [--tip-link NAME] in place of --robot)
                [--weights time=1,energy=0.1] [--space joint|task] [--batch B] [--workers K | --ray auto]
  jtraj dataset info PATH
  jtraj dataset verify PATH
  jtraj dataset plot PATH [--out overview.png]

build: samples start/goal pairs deterministically from the seed (joint space:
q_start ~ U(-1.2, 1.2)^n intersected with the joint box, q_goal = q_start +
U(-0.8, 0.8)^n inside the joint box, |q_goal - q_start| >= 0.05; task space:
uniform over the reachable workspace through inverse kinematics; both: start and goal
inside the workspace box and the robot's path constraints), solves them with
jtraj.solve_batch in chunks of --batch pairs and writes every finished chunk atomically
into the directory store PATH (manifest.json + chunks/chunk-XXXXXX.h5). Every pair is
kept with its status; failures are flagged, not dropped. Re-running the same command
resumes an interrupted run (a kill loses at most the chunks in flight); other parameters
into an existing dataset are refused. Chunks are solved by one pinned worker
process per CPU (--workers K to choose; 1 solves in this process, whose results equal
the workers' only when it runs on one CPU, e.g. under taskset -c 0); --ray
auto|HOST:PORT|local[:K] distributes them over a Ray cluster instead, with identical results.

info: the dataset's parameters and figures; every chunk file is verified first (all
checksums: Fletcher-32 and SHA-256 of every field, SHA-256 of the header), corrupt ones are
named and left out. verify: only that check, one line per corrupt chunk file. A resumed
build solves corrupt chunks again.

Exit status: build 0 when the dataset is complete, 1 when chunks are left; info and
verify 0 when every chunk present is intact, 1 when one is corrupt; 2 on bad input.
"""

import argparse

HELP = "build (resumable, optionally on Ray), summarise or plot a dataset of optimal trajectories"

ACTIONS = ("build", "info", "verify", "plot")


def configure(parser):
    from jtraj.commands import add_robot_param_argument, add_solver_arguments, add_urdf_arguments

    parser.add_argument("action", nargs="*", metavar="[build | info PATH | verify PATH | plot PATH]",
                        help="what to do (default build)")
    parser.add_argument("--robot", help="robot name (see 'jtraj robots')")
    add_urdf_arguments(parser, "a serial arm's URDF file instead of --robot; the dataset keeps its text, and "
                       "its models need no file")
    add_robot_param_argument(parser)
    parser.add_argument("--pairs", type=int, help="number of start/goal pairs P >= 1")
    parser.add_argument("--seed", type=int, default=0, help="sampling seed (default 0)")
    parser.add_argument("--out", help="build: dataset directory; plot: image file (default <PATH>-overview.png)")
    parser.add_argument("--N", type=int, default=20, help="samples per trajectory (default 20)")
    parser.add_argument("--weights", default="time=1,energy=0.1", help="cost weights (default time=1,energy=0.1)")
    parser.add_argument("--space", choices=("joint", "task"), default="joint", help="sampling space (default joint)")
    parser.add_argument("--batch", type=int, default=None,
                        help="pairs per chunk = solve_batch size (part of the dataset's identity; default: the "
                             "existing dataset's when resuming, else P/16 in multiples of 64 within 64..256 on a "
                             "CPU, P/4 in multiples of 256 within 256..4096 on an accelerator)")
    parser.add_argument("--ray", metavar="ADDRESS", default=None,
                        help="distribute over Ray: auto, HOST:PORT, ray://HOST:PORT, or local[:K] (start one here)")
    parser.add_argument("--workers", type=_workers, default=None,
                        help="local worker processes, one pinned to each core (default: one per "
                             "available CPU; 1 solves in this process, equal to the workers' results in the last "
                             "bits only when it runs on one CPU); ignored with --ray")
    parser.add_argument("--start-range", type=float, default=1.2, help="joint-space start range +-a (default 1.2)")
    parser.add_argument("--step-range", type=float, default=0.8, help="joint-space step range +-b (default 0.8)")
    parser.add_argument("--min-separation", type=float, default=0.05,
                        help="minimum |goal - start| (rad in joint space, task units in task space; default 0.05)")
    parser.add_argument("--ik-method", default="weighted", help="IK method for --space task (default weighted)")
    parser.add_argument("--max-iter", type=int, default=None, help="solver iteration limit (SolverOptions.max_iter)")
    parser.add_argument("--inequalities", choices=("phr", "pbm"), default="phr",
                        help="inequality term of the solver: phr (default) or pbm (SolverOptions.pbm(): about 40 %% "
                             "fewer Newton iterations on the h_max 0.1 s benchmark family, but fewer pairs "
                             "certified with this command's default --h-max; see SolverOptions)")
    parser.add_argument("--method", choices=("auto", "al", "ip"), default="auto",
                        help="inner method: auto (default: ip where it applies, else al), al (the "
                             "augmented-Lagrangian loop) or ip (the interior-point method); see SolverOptions.method")
    parser.add_argument("--h-max", default="auto",
                        help="sampling-period bound [s]: auto (default: twice the robot's, so that the bound "
                             "does not decide which pairs are feasible), robot (the robot's own), or seconds")
    parser.add_argument("--efforts", choices=("samples", "intervals"), default="samples",
                        help="where the torque bound holds: at the samples (default, the thesis) or also at each "
                             "interval's end, so that the executed motion meets it (see jtraj.Problem)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_solver_arguments(parser, functions=True)  # (--solver also takes module:function, for tests)


def _workers(text):
    try:
        k = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"--workers must be a positive integer, got {text!r}") from None
    if k < 1:
        raise argparse.ArgumentTypeError(f"--workers must be a positive integer, got {text!r}")
    return k


def _action(args):
    act = list(args.action)
    if not act:
        return "build", None
    if act[0] not in ACTIONS:
        raise ValueError(f"unknown action {act[0]!r}; use build, info PATH, verify PATH or plot PATH")
    if act[0] == "build":
        if len(act) > 1:
            raise ValueError(f"build takes options only, got extra arguments {act[1:]}")
        return "build", None
    if len(act) != 2:
        raise ValueError(f"usage: jtraj dataset {act[0]} PATH")
    return act[0], act[1]


def _h_max(text: str):
    if text in ("auto", "robot"):
        return text
    try:
        return float(text)
    except ValueError:
        raise ValueError(f"--h-max must be auto, robot or a number of seconds, got {text!r}") from None


def run(args) -> int:
    import os
    import sys

    action, path = _action(args)
    if action == "info":
        from jtraj.dataset import summary_and_check

        text, check = summary_and_check(path)
        print(text)
        return 1 if check["corrupt"] else 0
    if action == "verify":
        from jtraj.dataset import verify_report

        text, intact = verify_report(path)
        print(text)
        return 0 if intact else 1
    if action == "plot":
        from jtraj.dataset.plot import plot

        from jtraj.commands import check_output_file

        out = args.out or (os.path.abspath(path).rstrip(os.sep) + "-overview.png")
        check_output_file(out, "--out")
        plot(path, out)
        print(f"wrote {out}")
        return 0

    if args.robot is not None and args.urdf is not None:
        raise ValueError("give --robot (a built-in robot) or --urdf (a URDF file), not both")
    missing = [f"--{k}" for k in ("robot", "pairs", "out") if getattr(args, k) is None
               and not (k == "robot" and args.urdf is not None)]
    if missing:
        raise ValueError(f"build needs {', '.join(missing)}" + (" (or --urdf)" if "--robot" in missing else ""))
    if args.tip_link is not None and args.urdf is None:
        raise ValueError("--tip-link needs --urdf")
    from jtraj import dataset
    from jtraj.dataset.store import read_manifest

    batch = args.batch
    if batch is None and os.path.isdir(args.out):
        try:  # resuming: keep the chunk size the dataset was started with
            batch = read_manifest(args.out)["identity"]["batch"]
        except (ValueError, KeyError):
            batch = None  # not a dataset (yet): the build reports what is wrong there
    from jtraj.commands import cli_limits_hint, robot_params, solve_function, solver_overrides

    # the method recorded too: a dataset resumes only with the same method
    options = solver_overrides(args)
    solve_fn = solve_function(args) or "jtraj:solve_batch"
    try:
        spec = dataset.make_spec(args.robot, args.pairs, args.seed, N=args.N, weights=args.weights,
                                 batch=batch, space=args.space,
                                 start_range=args.start_range, step_range=args.step_range,
                                 min_separation=args.min_separation, ik_method=args.ik_method, options=options,
                                 solver=solve_fn, h_max=_h_max(args.h_max), efforts=args.efforts,
                                 urdf=args.urdf, tip_link=args.tip_link, robot_params=robot_params(args) or None)
    except ValueError as exc:
        msg = str(exc)
        if msg.startswith(("urdf: ", "tip_link", "robot_params: ")):  # the messages name the options
            msg = (msg.replace("urdf: ", "--urdf: ", 1).replace("robot_params: ", "--robot-param: ", 1)
                   .replace("tip_link=", "--tip-link").replace("tip_link", "--tip-link").replace("h_max=", "--h-max"))
            msg = cli_limits_hint(msg)
            raise ValueError(msg) from None
        raise
    stats = dataset.build(spec, args.out, ray=args.ray, workers=getattr(args, "workers", None),
                          progress=not args.no_progress)
    P = stats["pairs_done"]
    rate = stats["pairs_per_s"]
    print(f"{args.out}: {P}/{spec.pairs} pairs, converged {stats['converged']} "
          f"({100 * stats['converged'] / max(P, 1):.1f} %); {stats['new_pairs']} new pairs in "
          f"{stats['seconds']:.1f} s" + (f" ({rate:.2f} pairs/s)" if stats["new_pairs"] else ""),
          file=sys.stdout)
    return 0 if stats["complete"] else 1
