"""``python -m ambots``: the command-line interface; every command but
``ctl`` (which talks to a running cell) works offline, without ROS."""
import argparse
import importlib
import sys

from ambots import __version__
from ambots.errors import AmbotsError

#: modules of :mod:`ambots.commands`, in the order ``--help`` lists them
COMMANDS = ("cell", "info", "slice", "plan", "export", "summary", "ctl")


def build_parser():
    parser = argparse.ArgumentParser(
        prog="python -m ambots",
        description="Cooperative 3D printing with robot arms: offline tools.")
    parser.add_argument("--version", action="version", version="ambots " + __version__)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMANDS:
        importlib.import_module("ambots.commands." + name).register(sub)
    return parser


def main(argv=None):
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 0
    try:
        return args.func(args) or 0
    except AmbotsError as exc:
        print("ambots: error: %s" % exc, file=sys.stderr)
        return 2
