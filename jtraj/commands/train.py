"""Train an ANFIS on an optimal-trajectory dataset and report its accuracy.

Mappings: nefotc (q, qd) -> tau [default]; nefumop (p, pd) -> (tau, h); nefik p -> q;
plan (q_start, q_goal) -> (v, h) of the whole trajectory (for `jtraj query`).
Only converged trajectories are used. The test set is the last 10 % of them in dataset
order; the report compares with a linear least-squares and a 5-nearest-neighbour baseline on the
same split and inputs (goal: ANFIS test RMSE at most half the linear one).

Over a dataset of random start/goal pairs, nefotc, nefumop and nefik are not functions
of the thesis' inputs (the goal is missing), and no regressor gets far below the linear
baseline on them. --goal-inputs adds the offset to the goal, --phase the sample's place
k/N in its trajectory. By default nefotc is (q_goal - q, qd, k/N) -> tau and nefumop
(p, pd, p_goal - p, k/N) -> (tau, h); `--goal-inputs none --no-phase` gives the thesis'
inputs (see docs/guides/anfis.md).

With --radius auto (the default when --rules is not given) one model is trained per
candidate radius and all of them are kept, weighted by 1 / (validation MSE)^2
(an ensemble; --no-ensemble keeps only the best).

Where the robot is mirror-symmetric (odd inverse dynamics and symmetric limits, as
serial3), the reflection q -> -q of each training trajectory is an optimal trajectory
too, and --augment auto (the default) adds it to small nefotc and nefumop training sets:
twice the training data for free.
"""

import argparse

HELP = "train an ANFIS (NeFOTC, NeFuMOP, NeFIK or planner) on a dataset"


def configure(parser):
    parser.add_argument("--data", required=True, help="dataset directory (jtraj dataset --out ...)")
    parser.add_argument("--mapping", default="nefotc", choices=["nefotc", "nefumop", "nefik", "plan"])
    parser.add_argument("--out", required=True, help="model file to write")
    parser.add_argument("--json", help="report file (JSON)")
    parser.add_argument("--plot", help="training curves and memberships (PNG)")
    parser.add_argument("--rules", type=int, default=None, help="number of rules (radius found by bisection)")
    parser.add_argument("--radius", type=_radius, default="auto",
                        help="clustering radius when --rules is not given; 'auto' (default) trains one model "
                             "per radius of 0.4, 0.5, 0.6, 0.75, 0.9, 1.1, 1.4 and weighs them on the validation split "
                             "(see --ensemble)")
    parser.add_argument("--ensemble", action=argparse.BooleanOptionalAction, default=True,
                        help="with --radius auto: keep every radius' model, weighted by 1 / validation MSE^2 "
                             "(default), or only the best one (--no-ensemble)")
    parser.add_argument("--kind", default="tsk", choices=["tsk", "tsukamoto"])
    parser.add_argument("--order", type=int, default=1, choices=[0, 1], help="Sugeno order (tsk)")
    parser.add_argument("--epochs", type=int, default=100)
    parser.add_argument("--ridge", type=float, default=1e-6,
                        help="relative ridge of the least squares (1e-10 overfits sparse trajectory data)")
    parser.add_argument("--goal-inputs", nargs="?", const="append", default=None,
                        choices=["none", "append", "relative"],
                        help="nefotc / nefumop: append the offset to the trajectory's goal (q_goal - q, or "
                             "p_goal - p) to the inputs ('append', the default of the bare flag and of "
                             "nefumop), or replace the position by it ('relative', the default of nefotc); "
                             "'none': the thesis' inputs, which are not a function over a dataset of random "
                             "start/goal pairs")
    parser.add_argument("--phase", action=argparse.BooleanOptionalAction, default=None,
                        help="nefotc / nefumop: add the sample's place k/N in its trajectory to the inputs "
                             "(default: on)")
    parser.add_argument("--augment", default="auto", choices=["auto", "mirror", "none"],
                        help="add the mirror image q -> -q of every training trajectory where the robot has that "
                             "symmetry (odd inverse dynamics, symmetric limits: serial3); 'auto' (default) does so "
                             "for nefotc and nefumop on fewer than 500 training trajectories where the symmetry "
                             "holds, 'mirror' always (an error where it does not hold)")
    parser.add_argument("--no-progress", action="store_true")


def _radius(text):
    if text == "auto":
        return text
    try:
        r = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"--radius must be 'auto' or a number, got {text!r}") from None
    if not 0 < r:
        raise argparse.ArgumentTypeError(f"--radius must be positive, got {text!r}")
    return r


def run(args) -> int:
    import json
    import os

    from jtraj import mappings

    from jtraj.commands import check_output_file

    if not os.path.exists(args.data):
        raise ValueError(f"--data {args.data!r} does not exist")
    for option in ("out", "json", "plot"):
        check_output_file(getattr(args, option), f"--{option}")
    model, report, hist = mappings.train_mapping(
        args.data, args.mapping, n_rules=args.rules, radius=args.radius, epochs=args.epochs, kind=args.kind,
        order=args.order, ridge=args.ridge, progress=not args.no_progress,
        goal=getattr(args, "goal_inputs", None), phase=getattr(args, "phase", None),
        ensemble=getattr(args, "ensemble", True), augment=getattr(args, "augment", "auto"))
    model.save(args.out)
    report["model"] = os.path.abspath(args.out)
    if args.plot:
        from jtraj.anfis.plots import training_figure

        # of an ensemble, its leading member (the largest weight: the lowest validation
        # RMSE, whose history train_mapping returns)
        shown = model.leading if report["ensemble"] else model
        title = f"{args.mapping}: {shown.n_rules} rules" + (", best ensemble member" if report["ensemble"] else "")
        training_figure(hist, shown, args.plot, report["inputs"], title=title)
        report["plot"] = os.path.abspath(args.plot)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(report, f, indent=2)
    members = f" in {len(model.sizes)} models" if report["ensemble"] else ""
    print(f"{args.mapping}: {report['n_rules']} rules{members}, {report['epochs']} epochs, {report['seconds']:.1f} s; "
          f"RMSE train {report['train_rmse']:.4g}, test {report['test_rmse']:.4g} "
          f"(linear {report['linear_test_rmse']:.4g}, 5-NN {report['knn_test_rmse']:.4g}; "
          f"ratio to linear {report['ratio_to_linear']:.3f}: below 1 the model beats a linear fit)")
    if report.get("augment") == "mirror":
        print("training data: each trajectory and its mirror image q -> -q (--augment none: without)")
    elif report.get("augment_note") and args.mapping in mappings.MIRROR_AUTO_MAPPINGS:  # the others never are
        print(f"no mirror augmentation: {report['augment_note']}")
    if "thesis_linear_test_rmse" in report:
        print(f"inputs {', '.join(report['inputs'])}; linear on the thesis' inputs: test "
              f"{report['thesis_linear_test_rmse']:.4g} (ratio {report['ratio_to_thesis_linear']:.3f})")
    return 0
