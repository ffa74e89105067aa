"""``lfcam`` entry point: builds the sub-commands and turns errors into one line + exit 1."""

from __future__ import annotations

import argparse
import importlib
import sys
import traceback

from lfcam.errors import LfcamError

# Each module registers its own sub-command(s) through ``register(subparsers)``.
COMMAND_MODULES = [
    "lfcam.cli.optics",
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
    parser = argparse.ArgumentParser(
        prog="lfcam",
        description="Metric distance maps from plenoptic 1.0 camera captures.",
    )
    parser.add_argument("--debug", action="store_true", help="show tracebacks on errors")
    parser.add_argument("--version", action="version", version="lfcam 0.1.0")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run the CLI; returns the exit code (0 ok, 1 failed input, 2 bad usage)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except LfcamError as exc:
        if args.debug:
            traceback.print_exc()
        print(f"lfcam {args.command}: error: {exc}", file=sys.stderr)
        return 1
    except BrokenPipeError:  # e.g. `lfcam demo | head`: the reader left, nothing to report
        sys.stderr.close()
        return 0
    except KeyboardInterrupt:
        print(f"lfcam {args.command}: interrupted", file=sys.stderr)
        return 130
    except OSError as exc:
        if args.debug:
            traceback.print_exc()
        where = f": {exc.filename}" if exc.filename else ""
        print(f"lfcam {args.command}: error: {exc.strerror or exc}{where}", file=sys.stderr)
        return 1


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
