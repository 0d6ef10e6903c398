"""The ``jtraj`` command line.

Each sub-command lives in its own module under :mod:`jtraj.commands` and exposes

* ``HELP``: one line for ``jtraj --help``;
* ``configure(parser)``: adds its arguments to an :class:`argparse.ArgumentParser`;
* ``run(args) -> int``: does the work and returns the exit status.

Command modules must not import JAX at module level, so that ``jtraj --help`` stays fast;
:func:`main` turns on float64 and JAX's persistent compilation cache (:mod:`jtraj._setup`)
before ``run`` is called, so a second call of the same command does not recompile, and
shows the library's log lines (logger "jtraj", INFO: a solver compiling) on stderr.
"""

from __future__ import annotations

import argparse
import os
import importlib
import re
import sys

COMMANDS = {
    "solve": "jtraj.commands.solve",
    "gradcheck": "jtraj.commands.gradcheck",
    "dataset": "jtraj.commands.dataset",
    "train": "jtraj.commands.train",
    "query": "jtraj.commands.query",
    "robots": "jtraj.commands.robots",
}


def cache_dir() -> str | None:
    """Where compiled programs are kept between calls (see :func:`jtraj._setup.cache_dir`)."""
    from jtraj._setup import cache_dir as where

    return where()


def setup_jax(x64: bool = True) -> None:
    """float64 and the persistent compilation cache (:func:`jtraj._setup.setup_jax`)."""
    from jtraj._setup import setup_jax as setup

    setup(x64)


class _Stderr:
    """A logging handler's stream that is whatever ``sys.stderr`` is at each line (a
    caller of :func:`main` may replace it between calls)."""

    def write(self, text):
        sys.stderr.write(text)

    def flush(self):
        sys.stderr.flush()


def show_progress_lines() -> None:
    """The library's INFO lines (logger "jtraj": a solver compiling, a cache refused) on
    stderr, as they are (they start with "jtraj: ")."""
    import logging

    log = logging.getLogger("jtraj")
    if not any(getattr(h, "_jtraj_cli", False) for h in log.handlers):
        handler = logging.StreamHandler(_Stderr())
        handler.setFormatter(logging.Formatter("%(message)s"))
        handler._jtraj_cli = True
        log.addHandler(handler)
    if log.level == logging.NOTSET or log.level > logging.INFO:
        log.setLevel(logging.INFO)


def _available():
    mods = {}
    for name, modname in COMMANDS.items():
        try:
            mods[name] = importlib.import_module(modname)
        except ModuleNotFoundError as exc:
            if exc.name != modname:
                raise
    return mods


def build_parser() -> argparse.ArgumentParser:
    from jtraj import __version__

    parser = argparse.ArgumentParser(
        prog="jtraj",
        description="Differentiable robot trajectory optimisation in JAX "
                    "(decoupled augmented Lagrangian, batched datasets, ANFIS online planner).",
        epilog="Exit status: 0 done (a solve or refinement converged, a dataset complete and intact); 1 done "
               "but not that (not converged, a gradient check failed, a dataset incomplete or with corrupt "
               "chunks; see each command's --help); 2 bad input or a missing optional package (a message "
               "names the argument, file or package). Compiled programs are kept in ~/.cache/jtraj/jax "
               "($JTRAJ_CACHE_DIR moves it, JTRAJ_CACHE=0 turns it off).")
    parser.add_argument("--version", action="version", version=f"jtraj {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, mod in _available().items():
        p = sub.add_parser(name, help=mod.HELP, description=getattr(mod, "__doc__", None) or mod.HELP,
                           formatter_class=argparse.RawDescriptionHelpFormatter)
        mod.configure(p)
        p.set_defaults(_run=mod.run)
    return parser


#: a comma-separated list of numbers whose first entry is negative ("-10,30,30")
_NEGATIVE_LIST = re.compile(r"-(\d|\.\d)[^,]*(,[^,]*)+")


def attach_negative_lists(argv: list[str]) -> list[str]:
    """``--start-q -10,30,30`` -> ``--start-q=-10,30,30``: argparse takes a token that
    starts with '-' for an option unless it is a single number, so a vector option whose
    first entry is negative would fail with "expected one argument". A comma list never
    names an option, so it is attached to the option before it."""
    out: list[str] = []
    for tok in argv:
        prev = out[-1] if out else ""
        if _NEGATIVE_LIST.fullmatch(tok) and prev.startswith("--") and "=" not in prev:
            out[-1] = f"{prev}={tok}"
        else:
            out.append(tok)
    return out


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(attach_negative_lists(sys.argv[1:] if argv is None else list(argv)))
    if not getattr(args, "_run", None):
        parser.print_help()
        return 2
    if argv is None and getattr(sys.modules[args._run.__module__], "PIN_ONE_CPU", False):
        # one problem runs faster on one core (jtraj._cpu); only from the command line:
        # a Python caller of main(argv) keeps its process's affinity
        from jtraj._cpu import pin_to_one_cpu

        pin_to_one_cpu()
    if argv is None and getattr(sys.modules[args._run.__module__], "QUICK_PROGRAMS", False):
        # a process that solves one problem: the solver's quickly compiled programs serve
        # all its calls (jtraj._tracecache.quick_first_mode); the user's setting wins
        os.environ.setdefault("JTRAJ_QUICK_FIRST", "keep")
    show_progress_lines()
    setup_jax()
    try:
        return int(args._run(args) or 0)
    except ValueError as exc:  # bad input: one readable line, no traceback
        print(f"jtraj {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except ImportError as exc:  # an optional package missing (example-robot-data, ray): its message says which
        print(f"jtraj {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except BrokenPipeError:  # the reader of the output left (``jtraj robots | head``): stop quietly
        if argv is None:  # (Python's own flush of stdout at exit would report it again)
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 1
    except OSError as exc:  # a file the commands' own checks did not catch (removed meanwhile, disk full)
        print(f"jtraj {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
