"""The ``fastmesh`` command.  Each verb lives in its own module with a ``register(subparsers)``
function that adds its parser and sets ``func`` (returning an exit code)."""

from __future__ import annotations

import argparse
import importlib
import sys

# One module per verb (group); add yours here.
VERBS = ["data", "train", "generate", "eval", "tokens", "metrics", "submit", "loadtest"]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="fastmesh", description="FastMesh: shapes in, artist meshes out.")
    sub = parser.add_subparsers(dest="command", required=True)
    for name in VERBS:
        importlib.import_module(f"fastmesh.cli.{name}").register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        return 130
    except (ValueError, FileNotFoundError) as e:  # user errors: message, no traceback
        print(f"fastmesh {args.command}: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
