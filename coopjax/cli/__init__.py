"""The `coopjax` command line.

Commands are modules with `NAME`, `add_parser(subparsers)` and `run(args)`: the built-in ones here
(`simulate`, `sweep`, `plot-sweep`, `analyze`, `params`), and any that another package registers
under the entry-point group `coopjax.commands` (the tuner's `tune`, from the `tuning` package).

A mistake in the input is one line on stderr and exit code 2, with no traceback and no output file.
A full disk is one line and exit code 1, with no partial output. Ctrl-C is one line and exit code
130 (see `interrupts`). Anything else is a bug, and keeps its traceback.

Only the standard library is imported at the top of this module: the console script installs the
interrupt handling before JAX is imported.
"""

from __future__ import annotations

import errno
import importlib
import sys

from coopjax import cache
from coopjax.cli import interrupts
from coopjax.errors import InputError

EXIT_BAD_INPUT, EXIT_FAILED, EXIT_INTERRUPTED = 2, 1, 130

BUILT_IN = ("simulate", "sweep", "plot_sweep", "analyze", "params")
GROUP = "coopjax.commands"


def commands() -> list:
    """The command modules: the built-in ones, then the registered ones."""
    from importlib.metadata import entry_points  # here, not at the top: the console script starts faster

    found = [importlib.import_module(f"coopjax.cli.{name}") for name in BUILT_IN]
    for point in sorted(entry_points(group=GROUP), key=lambda p: p.name):
        found.append(point.load())
    return found


def build_parser():
    from coopjax.cli.common import Parser

    parser = Parser(
        prog="coopjax",
        description="Differentiable simulator of two cooperating space robots with virtual-foundation force control "
        "(Pathak et al.). The equations: docs/model.md in the project; tuning: docs/tuning.md; linear analysis: "
        "docs/analysis.md.",
        epilog=cache.describe(),
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=Parser)
    sub.required = True
    parser.field_flags = {}  # API names whose flag is not their own spelling (`names` is --params)
    for module in commands():
        module.add_parser(sub).set_defaults(run=module.run, compiles=getattr(module, "COMPILES", True))
        parser.field_flags.update(getattr(module, "FIELD_FLAGS", {}))
    return parser


def main(argv=None) -> int:
    """Run one command; returns its exit code."""
    parser = None
    try:
        parser = build_parser()
        args = parser.parse_args(argv)
        args.argv = list(sys.argv[1:] if argv is None else argv)  # what a supervised child repeats
        if args.compiles:  # a command that compiles nothing neither needs the cache nor hears of it
            cache.enable()
            from coopjax import devices  # jax with it: only for commands that compile

            devices.wide_vectors()  # before JAX's backend starts (each command starts it later)
        code = args.run(args)
        said = cache.note()
        if said:
            print(f"coopjax: note: {said}", file=sys.stderr)
        return code
    except InputError as error:
        from coopjax.cli.common import message

        print(f"coopjax: error: {message(error, parser)}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except BrokenPipeError:  # `coopjax params | head`: the reader left, nothing is wrong
        _quiet_stdout()
        return 0
    except OSError as error:
        if error.errno not in (errno.ENOSPC, errno.EDQUOT):
            raise
        kept = interrupts.account()
        print(
            f"coopjax: error: no space left on device ({error.filename or 'writing'}); no partial output was left"
            + (f"; {kept}" if kept else ""),
            file=sys.stderr,
        )
        return EXIT_FAILED
    except KeyboardInterrupt:  # only in-process (tests); the console script's interrupts never raise
        kept = interrupts.account()
        print(f"{interrupts.line_start()}coopjax: interrupted; {kept or 'nothing was written'}", file=sys.stderr)
        return EXIT_INTERRUPTED


def _quiet_stdout() -> None:
    """Point stdout at /dev/null: the interpreter's final flush would otherwise hit the closed pipe
    again and print "Exception ignored"."""
    import os

    try:
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
    except (OSError, ValueError):
        pass


def entry() -> None:
    """The console script: interrupts first, then the command."""
    interrupts.install()
    sys.exit(main())


if __name__ == "__main__":
    entry()
