"""Argument types shared by the subcommands: they reject bad input before JAX is touched."""

from __future__ import annotations

import argparse


def bounded_number(kind: type, minimum: float, strict: bool = False, maximum: float | None = None):
    """An argparse type: `kind` (int or float) >= `minimum` (> with `strict`) and <= `maximum`
    where given, or a clear error."""
    noun = "an int" if kind is int else "a number"
    if maximum is not None and not strict:
        bound = f"in {minimum}..{maximum}"
    else:
        bound = f"{'>' if strict else '>='} {minimum}" + ("" if maximum is None else f" and <= {maximum}")

    def parse(text: str):
        try:
            value = kind(text)
        except ValueError:
            value = None
        if (
            value is None
            or not (value > minimum if strict else value >= minimum)
            or (maximum is not None and value > maximum)
        ):
            raise argparse.ArgumentTypeError(f"must be {noun} {bound}, got {text!r}")
        return value

    parse.__name__ = f"{kind.__name__} {bound}"  # argparse names the type in its messages
    return parse


positive_int = bounded_number(int, 1)

MAX_SEED = 2**32 - 1  # as snac_jax.tasks.MAX_SEED (not imported: the task registry imports JAX)


def seed(text: str) -> int:
    """An argparse type: a seed in 0..2**32-1 (`jax.random.key` keeps 32 bits: larger seeds
    would repeat smaller ones)."""
    try:
        value = int(text)
    except ValueError:
        value = None
    if value is None or not 0 <= value <= MAX_SEED:
        raise argparse.ArgumentTypeError(f"must be an int in 0..{MAX_SEED}, got {text!r}")
    return value


def task_id(text: str) -> str:
    from snac_jax.tasks import TASKS  # here, not at import: the task registry imports JAX

    if text not in TASKS:
        raise argparse.ArgumentTypeError(f"unknown task {text!r}; allowed: {', '.join(TASKS)}")
    return text


def add_seed_index_argument(parser: argparse.ArgumentParser) -> None:
    """`--seed-index K`: which of a `snac train --seeds N` run's seeds a checkpoint command reads.
    A run trains its seeds side by side in one checkpoint, so the policy must be picked out."""
    parser.add_argument(
        "--seed-index",
        type=bounded_number(int, 0),
        default=None,
        metavar="K",
        help="with --checkpoint: which of the run's training seeds to load, 0..seeds-1 (default 0)",
    )


def check_seed_index(args: argparse.Namespace) -> None:
    """`--seed-index` names a seed of a checkpoint's run; without `--checkpoint` it means nothing."""
    if args.seed_index is not None and args.checkpoint is None:
        raise ValueError("--seed-index picks one training seed of a run: give it with --checkpoint DIR")


def add_devices_argument(parser: argparse.ArgumentParser, cpu_default: str = "one per core") -> None:
    """`--devices N`: how many devices the worlds are split over (`snac_jax.devices`)."""
    parser.add_argument(
        "--devices",
        type=positive_int,
        default=None,
        help=f"devices to split the worlds over (default: all; on a CPU {cpu_default}); 1 turns sharding off",
    )


def add_process_arguments(parser: argparse.ArgumentParser) -> None:
    """`--coordinator HOST:PORT --num-processes N --process-id I`: run as one of N processes
    (hosts) of one computation. `snac` joins them before JAX starts (`snac_jax.cli.join_processes_from`)."""
    parser.add_argument(
        "--coordinator",
        default=None,
        metavar="HOST:PORT",
        help="run across processes (hosts): the address of process 0, for jax.distributed",
    )
    parser.add_argument("--num-processes", type=positive_int, default=None, help="with --coordinator: how many")
    parser.add_argument(
        "--process-id",
        type=bounded_number(int, 0),
        default=None,
        help="with --coordinator: this process's index, 0..N-1",
    )
