"""Extension points of the `snac` command, found through package entry points.

The library never imports the packages that extend it: `agents` (the learners) declares in
pyproject.toml a `train` subcommand (group `snac_jax.commands`: a module with
`add_parser(subparsers)`) and a loader of trained policies (group `snac_jax.checkpoint_loaders`:
`loader(run_directory) -> (builder(env, **options) -> Policy, the run's task, its paper row,
the `make` overrides the run trained with)`, the last optional), and `snac eval --checkpoint` /
`snac render --checkpoint` reach them here by name (`load_checkpoint`). The one option passed to
a builder is `seed_index=K`, and only when the user gives `--seed-index K`: which of a multi-seed
run's training seeds to load (a builder that takes no options serves runs of one seed). The overrides (the
switches and step limit a run trained with) are applied when the run is evaluated, so it is
scored in the world and on the episodes it learned.
"""

from __future__ import annotations

import functools
import importlib
from importlib.metadata import entry_points
from typing import Any, Callable

COMMANDS = "snac_jax.commands"
CHECKPOINT_LOADERS = "snac_jax.checkpoint_loaders"


def command_modules() -> dict[str, Any]:
    """Subcommand name -> its module, for every installed extension."""
    return {ep.name: importlib.import_module(ep.value) for ep in entry_points(group=COMMANDS)}


def checkpoint_loader() -> Callable:
    """The installed loader of trained policies; a clear error if no package provides one."""
    loaders = list(entry_points(group=CHECKPOINT_LOADERS))
    if not loaders:
        raise ValueError(f"no package provides a checkpoint loader (entry point group {CHECKPOINT_LOADERS!r}); "
                         "install the project with `pip install -e .`, which includes the agents")
    return loaders[0].load()


def load_checkpoint(directory, seed_index: int | None = None) -> tuple[Callable, str, str, dict[str, Any]]:
    """`(builder(env) -> Policy, the run's task, its paper row, its make overrides)` of run
    `directory`, through the installed loader (overrides `{}` where the loader gives none). With
    `seed_index` the builder loads that training seed; without it, the loader's default."""
    builder, task, paper_method, *rest = checkpoint_loader()(directory)
    if seed_index is not None:
        builder = functools.partial(builder, seed_index=seed_index)
    return builder, task, paper_method, (rest[0] if rest else {})
