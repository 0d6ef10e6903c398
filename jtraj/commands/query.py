"""Plan a trajectory for a start/goal pair with trained models, report its feasibility,
and optionally refine it with the exact solver.

Open loop: --model of mapping plan. Closed loop (the thesis' NeFOTC with NeFuMOP):
--model of mapping nefotc (the torque controller) and --periods of mapping nefumop
(its output h sets the sampling periods), rolled out through the robot's dynamics;
much closer to the goal on serial3 (median 0.030 rad against 0.20 rad; docs/guides/anfis.md)."""

HELP = "plan a trajectory with a trained ANFIS planner (optionally refine it exactly)"


def _vec(text):
    return [float(t) for t in text.replace(",", " ").split()]


#: the CLI pins this command to one CPU core before JAX starts (jtraj._cpu)
PIN_ONE_CPU = True


def configure(parser):
    parser.add_argument("--model", required=True,
                        help="model file from `jtraj train --mapping plan`, or `--mapping nefotc` with --periods")
    parser.add_argument("--periods", help="with a nefotc --model: a model file from `jtraj train --mapping nefumop` "
                                          "on the same dataset (closed-loop planning)")
    parser.add_argument("--start", required=True, type=_vec, help="start joint positions, e.g. '0,0.52,0.52'")
    parser.add_argument("--goal", required=True, type=_vec, help="goal joint positions")
    parser.add_argument("--refine", action="store_true", help="warm-start the exact solver from the plan")
    parser.add_argument("--warm", default="primal", choices=["primal", "full"],
                        help="refine from the plan's primal point only (default; multipliers and penalty as in "
                             "a cold start) or with jtraj.solve's full warm start (estimated multipliers, high "
                             "penalty)")
    parser.add_argument("--json", help="write the result (trajectory included) as JSON")


def run(args) -> int:
    import json

    from jtraj.commands import check_input_file, check_output_file
    from jtraj.online import Planner

    check_input_file(args.model, "--model")
    check_input_file(getattr(args, "periods", None), "--periods")
    check_output_file(args.json, "--json")
    planner = Planner(args.model, periods=getattr(args, "periods", None))
    if len(args.start) != planner.n or len(args.goal) != planner.n:
        raise ValueError(f"--start and --goal need {planner.n} values each")
    out = planner.query(args.start, args.goal, refine=args.refine, warm=getattr(args, "warm", "primal"))
    print(f"plan: T = {out['T']:.4f} s, feasible = {out['feasible']}, goal error {out['goal_error']:.3g} rad, "
          f"tau over limit {out['tau_violation']:.3g}, qd over limit {out['qd_violation']:.3g}"
          + (f" (between the samples: up to {out['effort_between_samples']:.4f} x tau_max)"
             if "effort_between_samples" in out else ""))
    if args.refine:
        print(f"refined ({out['refined_warm']} warm start): {out['refined_status']} in "
              f"{out['refined_iterations']} iterations, {out['refined_seconds']:.2f} s "
              f"(cycloidal start: {out['cycloidal_iterations']} iterations, "
              f"{out['cycloidal_seconds']:.2f} s, compilation included when not cached)")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(out, f, indent=2)
    return 0
