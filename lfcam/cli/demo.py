"""``lfcam demo``: the whole pipeline on a built-in synthetic scene."""

from __future__ import annotations

import argparse


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``demo`` sub-command."""
    p = sub.add_parser("demo", help="run the pipeline on a built-in synthetic scene")
    p.add_argument("-o", "--output", default="lfcam-demo", help="output folder")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run the demo (placeholder until the distance-map stage lands)."""
    print(
        "lfcam demo: the end-to-end demo (render → calibrate → measure → distance map) is not "
        "built yet; available now: `lfcam optics forward|inverse|refocus-distance`."
    )
    return 0
