"""``lfcam`` entry point: builds the sub-commands and turns errors into one line + exit 1."""

from __future__ import annotations

import argparse
import importlib
import sys
import traceback
import warnings

from lfcam.cli.common import ArgumentParser
from lfcam.errors import ChecksumError, LfcamError
from lfcam.io.lfp import CHECKSUM_HINT

# Each module registers its own sub-command(s) through ``register(subparsers)``.
COMMAND_MODULES = [
    "lfcam.cli.optics",
    "lfcam.cli.lens",
    "lfcam.cli.demo",
    "lfcam.cli.info",
    "lfcam.cli.simulate",
    "lfcam.cli.decode",
    "lfcam.cli.distance",
    "lfcam.cli.batch",
    "lfcam.cli.calibrate",
]


def build_parser() -> argparse.ArgumentParser:
    """Return the top-level parser with every sub-command registered."""
    parser = ArgumentParser(
        prog="lfcam",
        description="Metric distance maps from plenoptic 1.0 camera captures.",
    )
    parser.add_argument("--debug", action="store_true", help="show tracebacks on errors")
    parser.add_argument("--version", action="version", version="lfcam 0.1.0")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(sub)
    _describe(sub)
    return parser


def _describe(sub: argparse._SubParsersAction) -> None:
    """Give every sub-command (recursively) a description: its one-line help, if it has
    none of its own, so ``lfcam CMD --help`` always says what CMD does."""
    helps = {a.dest: a.help for a in sub._choices_actions}
    for name, parser in sub.choices.items():
        if not parser.description and helps.get(name):
            text = helps[name]
            parser.description = text[:1].upper() + text[1:] + ("" if text.endswith(".") else ".")
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                _describe(action)


def main(argv: list[str] | None = None) -> int:
    """Run the CLI; returns the exit code (0 ok, 1 failed input, 2 bad usage)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    old_format = warnings.formatwarning  # warnings (e.g. --no-verify's) as one line each
    warnings.formatwarning = lambda message, *a, **k: f"lfcam {args.command}: warning: {message}\n"
    try:
        return _run(args)
    finally:
        warnings.formatwarning = old_format


def _run(args: argparse.Namespace) -> int:
    try:
        return int(args.func(args) or 0)
    except LfcamError as exc:
        if args.debug:
            traceback.print_exc()
        msg = " ".join(str(exc).split("\n"))
        if isinstance(exc, ChecksumError):  # name a flag only where the command has it
            hint = "; pass --no-verify to load it anyway" if hasattr(args, "no_verify") else ""
            msg = msg.replace(CHECKSUM_HINT, hint)
        print(f"lfcam {args.command}: error: {msg}", file=sys.stderr)
        return 1
    except BrokenPipeError:  # e.g. `lfcam demo | head`: the reader left, nothing to report
        sys.stderr.close()
        return 0
    except KeyboardInterrupt as exc:
        print(f"lfcam {args.command}: {str(exc) or 'interrupted'}", file=sys.stderr)
        return 130
    except MemoryError:
        if args.debug:
            traceback.print_exc()
        print(f"lfcam {args.command}: error: out of memory (input too large for this machine)",
              file=sys.stderr)
        return 1
    except OSError as exc:
        if args.debug:
            traceback.print_exc()
        where = f": {exc.filename}" if exc.filename else ""
        print(f"lfcam {args.command}: error: {exc.strerror or exc}{where}", file=sys.stderr)
        return 1


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
