"""``ude-fit``: fit mechanistic and UDE models to logged limit cycles, trace and report.

    ude-fit fit DATA... --system flutter|oscillator [--approximator nn|gp]
                [--training trajectory|periodic] [--starts N] [--seed S] --out DIR
    ude-fit diagram MODEL [--data DATA...] [--retrace] [--out DIR]
    ude-fit explain DATA... --system S [--model UDE.eqx] --out DIR
    ude-fit refine DATA... --system S --add EFFECT[=SHAPE]... [--ude] --out DIR
    ude-fit loop DATA... --system S [--max-effects N] [--min-gain G] [--ude] --out DIR
    ude-fit pipeline DATA... --system S [every fit option] --out DIR  (fit, loop, summary)
    ude-fit sweep SWEEP.toml --out DIR [--address ADDR]   (fits on a Ray cluster)

One module per subcommand: it parses, calls the library and prints. User mistakes (a bad
file, an empty dataset, a bad option) end with one line on stderr and exit status 2,
before anything is written; a fit that keeps no UDE (every start diverged, or no start's
diagram reaches a measured point) ends with status 1 after writing what it has, and says
which. The command line runs JAX in float64 and keeps compiled code between runs
(:mod:`.compile_cache`); importing ude_fit does neither.
"""

from __future__ import annotations

import argparse
import sys

from . import diagram, explain, fit, loop, pipeline, sweep
from .common import EXIT_USAGE, Parser, UsageError


def build_parser() -> argparse.ArgumentParser:
    from ..model_file import _version
    p = Parser(prog="ude-fit", description="Fit mechanistic and universal-differential-equation "
               "models to logged limit cycles, trace their bifurcation diagrams, and report.")
    p.add_argument("--version", action="version", version=f"ude-fit {_version()}")
    sub = p.add_subparsers(dest="command", metavar="COMMAND", parser_class=Parser)
    sub.required = True
    fit.add_parser(sub)
    diagram.add_parser(sub)
    explain.add_parser(sub)
    loop.add_parsers(sub)
    pipeline.add_parser(sub)
    sweep.add_parser(sub)
    return p


COMMANDS = {"fit": fit.run, "diagram": diagram.run, "explain": explain.run,
            "refine": loop.run_refine, "loop": loop.run_loop, "pipeline": pipeline.run,
            "sweep": sweep.run}


def main(argv=None) -> int:
    import jax
    jax.config.update("jax_enable_x64", True)   # fitting and continuation need float64
    from ..data import DataError
    from .compile_cache import use_compile_cache

    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)
    use_compile_cache()
    try:
        return COMMANDS[args.command](args, argv)
    except (UsageError, DataError) as exc:
        print(f"ude-fit: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print("ude-fit: interrupted", file=sys.stderr)
        return 130
