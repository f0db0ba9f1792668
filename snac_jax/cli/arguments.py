"""Argument types shared by the subcommands: they reject bad input before JAX is touched."""

from __future__ import annotations

import argparse


def positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be an int >= 1, got {text!r}")
    return value


def task_id(text: str) -> str:
    from snac_jax.tasks import TASKS  # here, not at import: the task registry imports JAX

    if text not in TASKS:
        raise argparse.ArgumentTypeError(f"unknown task {text!r}; allowed: {', '.join(TASKS)}")
    return text


def add_devices_argument(parser: argparse.ArgumentParser) -> None:
    """`--devices N`: how many devices the worlds are split over (`snac_jax.devices`)."""
    parser.add_argument(
        "--devices",
        type=positive_int,
        default=None,
        help="devices to split the worlds over (default: all; on a CPU one per core); 1 turns sharding off",
    )
