"""The `snac` command line. Each subcommand lives in its own module of this package and
registers itself through `add_parser(subparsers)`; this module only dispatches."""

from __future__ import annotations

import argparse
import importlib
import sys

# One module per subcommand; each defines `add_parser(subparsers)`.
COMMAND_MODULES = ("rollout", "render", "play")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="snac", description="SNAC mobile-construction benchmark in JAX")
    subparsers = parser.add_subparsers(dest="command", required=True)
    for name in COMMAND_MODULES:
        importlib.import_module(f"snac_jax.cli.{name}").add_parser(subparsers)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
