"""``lfcam info FILE [--json]``: what a capture is (docs/conventions.md)."""

from __future__ import annotations

import argparse
import json


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``info`` sub-command."""
    p = sub.add_parser(
        "info",
        help="describe a capture: camera, container sections, sizes, optics, raw frame or not",
    )
    p.add_argument("file", help="capture (.lfp/.lfr, .raw + sidecar, camera raw, PNG, TIFF)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--no-verify", action="store_true",
                   help="warn instead of failing on LFP sha1 mismatches")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Describe the file; errors propagate as LfcamError (one line, exit 1)."""
    import warnings

    from lfcam.io.info import describe_file, format_text

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        d = describe_file(args.file, verify="warn" if args.no_verify else "error")
    print(json.dumps(d, indent=1) if args.json else format_text(d))
    return 0
