"""List the built-in robots, their degrees of freedom, parameters and limits."""

HELP = "list the built-in robots and their parameters"


def configure(parser):
    parser.add_argument("name", nargs="?", help="show one robot in detail")


def run(args) -> int:
    import numpy as np

    from jtraj import robots

    names = [args.name] if args.name else robots.names()
    for name in names:
        r = robots.get(name)
        print(f"{name}: n = {r.n}, {type(r).__name__}")
        if args.name:
            print("  parameters:", ", ".join(robots.parameter_names(name)))
            lim = r.limits
            for f in ("q_min", "q_max", "qd_max", "qdd_max", "tau_max", "h_min", "h_max"):
                val = getattr(lim, f)
                print(f"  {f:8s} {'-' if val is None else np.array2string(np.asarray(val), precision=4)}")
    return 0
