"""The `clothbench` command. Bad input gets one line on stderr and exit 2, never a traceback.

One module per command, each with register(subparsers); the argument groups they share are
in args.py. Commands import their heavy dependencies only when they run.
"""

from __future__ import annotations

import os
import sys

from clothbench import __version__
from clothbench.cli import accuracy, advise, backends, plot, render, report, run, stability, sweep, view
from clothbench.cli import energy, machine, pbd_study, tuning
from clothbench.cli.args import Parser
from clothbench.errors import INTERRUPTED_EXIT, INTERRUPTED_LINE, BlowUp, ClothbenchError

COMMANDS = (run, backends, sweep, plot, report, accuracy, stability, advise, render, view)
COMMANDS += (pbd_study, energy, tuning, machine)


def build_parser() -> Parser:
    parser = Parser(prog="clothbench", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"clothbench {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=Parser)
    for command in COMMANDS:
        command.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    try:
        args = build_parser().parse_args(argv)
        return args.func(args)
    except BlowUp as e:
        print(f"clothbench: {e}", file=sys.stderr)
        return e.exit_code
    except ClothbenchError as e:
        print(f"clothbench: error: {e}", file=sys.stderr)
        return e.exit_code
    except KeyboardInterrupt:
        print(INTERRUPTED_LINE, file=sys.stderr)
        return INTERRUPTED_EXIT
    except BrokenPipeError:  # `clothbench backends | head`: the reader left, nothing to say
        # point stdout at /dev/null so the interpreter's final flush does not complain
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141


__all__ = ["build_parser", "main"]
