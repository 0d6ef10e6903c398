"""Plan a trajectory for a start/goal pair with trained models, feasible by construction
(jtraj.repair: goal reached, bounds restored by a time scaling), report its cost,
violations and coverage (distance to the training pairs, out-of-distribution flag), and
optionally refine it with the exact solver.

Open loop: --model of mapping plan. Closed loop (the thesis' NeFOTC with NeFuMOP):
--model of mapping nefotc (the torque controller) and --periods of mapping nefumop
(its output h sets the sampling periods), rolled out through the robot's dynamics;
much closer to the goal on serial3 (median 0.030 rad against 0.20 rad; docs/guides/anfis.md).

The start and the goal are checked as ``jtraj solve`` checks them: finite, inside the
robot's joint box, workspace and path constraints, in radians (--deg for degrees).
--refine solves the exact problem warm-started from the plan, with the dataset's weights
and the model's N unless --weights / --N say otherwise (another N warm-starts from the
plan re-sampled onto N equal periods); --method and --inequalities as in ``jtraj solve``.

Exit status: 0 when a plan was made (and, with --refine, the refined solution converged),
1 when --refine stopped without convergence (the report and JSON are still written), 2 on
bad input."""

HELP = "plan a trajectory with a trained ANFIS planner (optionally refine it exactly)"




#: the CLI pins this command to one CPU core before JAX starts (jtraj._cpu)
PIN_ONE_CPU = True

#: the CLI keeps the solver's quickly compiled programs for this one-shot command
#: (JTRAJ_QUICK_FIRST=keep, see jtraj._tracecache.quick_first_mode)
QUICK_PROGRAMS = True


def configure(parser):
    from jtraj.commands import add_solver_arguments

    parser.add_argument("--model", required=True,
                        help="model file from `jtraj train --mapping plan`, or `--mapping nefotc` with --periods")
    parser.add_argument("--periods", help="with a nefotc --model: a model file from `jtraj train --mapping nefumop` "
                                          "on the same dataset (closed-loop planning)")
    parser.add_argument("--start", required=True, metavar="Q1,Q2,...",
                        help="start joint positions (angles in rad, or deg with --deg; lengths in m), "
                             "e.g. '0,0.52,0.52'")
    parser.add_argument("--goal", required=True, metavar="Q1,Q2,...", help="goal joint positions")
    parser.add_argument("--deg", action="store_true",
                        help="the angles of --start and --goal are in degrees (lengths stay in m)")
    parser.add_argument("--refine", action="store_true", help="warm-start the exact solver from the plan")
    parser.add_argument("--N", type=int, default=None,
                        help="with --refine: sampling intervals of the refined problem (default the model's N)")
    parser.add_argument("--weights", default=None,
                        help="with --refine: cost weights as in jtraj solve (default: the training dataset's)")
    parser.add_argument("--method", choices=("auto", "al", "ip"), default="auto",
                        help="with --refine: inner method of the solver (see jtraj solve)")
    parser.add_argument("--inequalities", choices=("phr", "pbm"), default="phr",
                        help="with --refine: inequality term of the solver (see jtraj solve)")
    add_solver_arguments(parser, when="with --refine: ")
    parser.add_argument("--warm", default="primal", choices=["primal", "full"],
                        help="refine from the plan's primal point only (default; multipliers and penalty as in "
                             "a cold start) or with jtraj.solve's full warm start (estimated multipliers, high "
                             "penalty)")
    parser.add_argument("--no-compare", action="store_true",
                        help="with --refine: skip the comparison solve from the cycloidal guess (the refined "
                             "solve then pays the compilation in a fresh process)")
    parser.add_argument("--json", help="write the result (trajectory included) as JSON")
    parser.add_argument("--plot", metavar="PATH",
                        help="write the figures (PNG, PDF, SVG by extension): the plan, or with --refine the "
                             "refined optimum with the plan dashed beside it")


def _vector(text, name, robot, deg):
    from jtraj.commands.solve import angular, parse_vector

    if not isinstance(text, str):  # a sequence of numbers (a Python caller's args)
        text = ",".join(str(float(x)) for x in text)
    # (spaces separate as well as commas)
    return parse_vector(",".join(text.replace(",", " ").split()), name, robot.n, deg=deg,
                        joints=getattr(robot, "joint_names", None), angles=angular(robot))


def run(args) -> int:
    import json
    import sys

    from jtraj.commands import check_input_file, check_output_file
    from jtraj.commands.solve import finite_json, check_joint_values
    from jtraj.online import Planner

    check_input_file(args.model, "--model")
    check_input_file(getattr(args, "periods", None), "--periods")
    check_output_file(args.json, "--json")
    check_output_file(getattr(args, "plot", None), "--plot")
    refine_opts = [f"--{k.replace('_', '-')}" for k, default in (("N", None), ("weights", None), ("method", "auto"),
                                                              ("inequalities", "phr"), ("no_compare", False))
                   if getattr(args, k, default) != default]
    if refine_opts and not args.refine:
        raise ValueError(f"{', '.join(refine_opts)} set(s) the refinement: give --refine too")
    if getattr(args, "N", None) is not None and args.N < 2:
        raise ValueError(f"--N must be an integer >= 2, got {args.N}")
    weights = None
    if getattr(args, "weights", None) is not None:
        import jtraj

        try:
            weights = jtraj.Weights.parse(args.weights)
        except ValueError as exc:
            raise ValueError(f"--weights: {exc}") from None
    planner = Planner(args.model, periods=getattr(args, "periods", None))
    deg = getattr(args, "deg", False)
    q_start = _vector(args.start, "--start", planner.robot, deg)
    q_goal = _vector(args.goal, "--goal", planner.robot, deg)
    check_joint_values(planner.robot, {"--start": q_start, "--goal": q_goal}, deg)
    solver = None
    if args.refine:
        from jtraj.commands import solver_from_args, solver_overrides

        # no solver argument: the planner's own warm-start settings (jtraj.online.WARM_IPM)
        if solver_overrides(args) != {"method": "auto"}:
            solver = solver_from_args(args)
    out = planner.query(q_start, q_goal, refine=args.refine, warm=getattr(args, "warm", "primal"),
                        weights=weights, solver=solver, N=getattr(args, "N", None),
                        compare=not getattr(args, "no_compare", False))
    cov = out["coverage"]
    from jtraj.plotting import coordinate_units

    units = set(coordinate_units(planner.robot))
    unit = units.pop() if len(units) == 1 else "(rad or m)"
    print(f"plan: T = {out['T']:.4f} s, cost {out['cost']:.6g}, feasible = {out['feasible']} (worst violation "
          f"{out['violation']:.3g}, goal error {out['goal_error']:.3g} {unit}"
          + (f", model's own goal error {out['predicted_goal_error']:.3g} {unit}, time scaling {out['scale']:.4g}, "
             f"the repair's {out['candidate']} candidate"
             + (", bent inside the position constraints" if out["bent"] else "") if out["corrected"] else "") + ")"
          + (f"; between the samples: efforts up to {out['effort_between_samples']:.4f} x tau_max"
             if "effort_between_samples" in out else ""))
    if cov["kind"] is None:
        print("coverage: unknown (the model records no training pairs)")
    else:
        print(f"coverage: distance {cov['distance']:.3g} to the {cov['kind']} (radius {cov['radius']:.3g}), "
              f"{cov['outside_box']:.3g} outside the training box: "
              + ("OUT OF DISTRIBUTION, the model has not seen such a query" if cov["out_of_distribution"]
                 else "in distribution"))
    if args.refine:
        print(f"refined ({out['refined_warm']} warm start, N = {out['refined_N']}): {out['refined_status']} in "
              f"{out['refined_iterations']} iterations, {out['refined_seconds']:.2f} s"
              + (f" (cycloidal start: {out['cycloidal_iterations']} iterations, {out['cycloidal_seconds']:.2f} s, "
                 f"compilation included when not cached)" if "cycloidal_iterations" in out else
                 " (compilation included when not cached)")
              + (f"; plan's cost gap {100 * out['gap']:.2f} %" if "gap" in out else ""))
    if args.json:
        with open(args.json, "w") as f:
            json.dump(finite_json(out), f, indent=2, allow_nan=False)
    if getattr(args, "plot", None):
        if _plot(planner, q_start, q_goal, out, args.plot):
            print(f"wrote {args.plot}")
        else:
            print(f"no figure written to {args.plot}: neither the plan nor the refined solution holds a finite "
                  f"trajectory", file=sys.stderr)
    return 1 if args.refine and not out["refined_converged"] else 0


def _plot(planner, q_start, q_goal, out, path) -> bool:
    """The plan's figures (:func:`jtraj.plotting.plot_solution`), or the refined optimum's
    with the plan dashed beside it; a trajectory with non-finite values is left out.
    Whether a figure was written."""
    from types import SimpleNamespace

    import numpy as np

    import jtraj
    from jtraj.plotting import drawable, plot_solution, save

    def trajectory(prefix):
        return SimpleNamespace(**{k: np.asarray(out[prefix + k], float) for k in ("q", "qd", "v", "tau", "h")})

    plan = trajectory("")
    refined = trajectory("refined_") if "refined_q" in out else None
    plan = plan if drawable(plan) else None
    refined = refined if refined is not None and drawable(refined) else None
    if plan is None and refined is None:
        return False
    title = (f"{planner.robot.name}: plan T = {out['T']:.3f} s, cost {out['cost']:.5g}, feasible = {out['feasible']}"
             + (", OUT OF DISTRIBUTION" if out["out_of_distribution"] else ""))
    if "refined_q" in out:
        status = "converged" if out["refined_converged"] else "NOT converged"
        title += (f"; refined ({status}) T = {out['refined_T']:.3f} s, cost {out['refined_cost']:.5g}"
                  + (f", the plan's gap {100 * out['gap']:.2f} %" if "gap" in out else ""))
    first = refined if refined is not None else plan
    problem = jtraj.Problem(planner.robot, q_start, q_goal, N=len(first.h), validate=False)
    if refined is not None:
        fig = plot_solution(problem, refined, guess=False if plan is None else plan, label="refined optimum",
                            guess_label="plan")
    else:
        fig = plot_solution(problem, plan, guess=False, label="plan")
    fig.suptitle(title)
    save(fig, path)
    return True
