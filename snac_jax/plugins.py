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
import re
from collections.abc import Callable
from importlib import metadata
from importlib.metadata import entry_points
from typing import Any

COMMANDS = "snac_jax.commands"
CHECKPOINT_LOADERS = "snac_jax.checkpoint_loaders"
DISTRIBUTION = "snac-jax"
# Import names that differ from their distribution's name (the rest match once normalised).
_DISTRIBUTION_OF = {"PIL": "pillow", "orbax": "orbax-checkpoint"}


def commands() -> dict[str, str]:
    """Subcommand name -> the module that provides it, for every installed extension, not
    imported yet: a module whose dependencies are missing must not stop the other commands."""
    return {ep.name: ep.value for ep in entry_points(group=COMMANDS)}


def command_modules() -> dict[str, Any]:
    """Subcommand name -> its module, for every installed extension."""
    return {name: importlib.import_module(module) for name, module in commands().items()}


def _normalise(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def extra_for(module: str) -> str | None:
    """The extra of this package (pyproject.toml's optional-dependencies, as the installed
    metadata records them) whose requirements bring the top-level module `module`; None where no
    extra does, or the package is not installed. Why: the environment installs without the
    learners' and the game's dependencies, and a command that needs one says which extra to add."""
    wanted = _normalise(_DISTRIBUTION_OF.get(module, module))
    try:
        requirements = metadata.requires(DISTRIBUTION) or []
    except metadata.PackageNotFoundError:
        return None
    extras = []
    for requirement in requirements:
        name = re.match(r"\s*([A-Za-z0-9][A-Za-z0-9._-]*)", requirement)
        extra = re.search(r"extra\s*==\s*['\"]([^'\"]+)['\"]", requirement)
        if name and extra and _normalise(name.group(1)) == wanted:
            extras.append(extra.group(1))
    # `dev` holds every extra: name the one a user would add for this command.
    return next((e for e in extras if e != "dev"), extras[0] if extras else None)


def missing_extra_message(error: ModuleNotFoundError) -> str | None:
    """One line naming the extra to install for the module `error` could not find, or None
    where no extra of this package provides it (then the error is a bug, not a missing extra)."""
    extra = extra_for((error.name or "").partition(".")[0])
    if extra is None:
        return None
    return f'this needs the [{extra}] extra: pip install "{DISTRIBUTION}[{extra}]"'


def checkpoint_loader() -> Callable:
    """The installed loader of trained policies; a clear error if no package provides one."""
    loaders = list(entry_points(group=CHECKPOINT_LOADERS))
    if not loaders:
        raise ValueError(
            f"no package provides a checkpoint loader (entry point group {CHECKPOINT_LOADERS!r}); "
            f'install the project with its learners: pip install "{DISTRIBUTION}[train]"'
        )
    return loaders[0].load()


def load_checkpoint(directory, seed_index: int | None = None) -> tuple[Callable, str, str, dict[str, Any]]:
    """`(builder(env) -> Policy, the run's task, its paper row, its make overrides)` of run
    `directory`, through the installed loader (overrides `{}` where the loader gives none). With
    `seed_index` the builder loads that training seed; without it, the loader's default (index 0).
    The builder's `label` names the policy loaded: the loader's `builder.describe(index)` where it
    has one (a sweep's arm and seed), else the training seed index."""
    builder, task, paper_method, *rest = checkpoint_loader()(directory)
    describe = getattr(builder, "describe", None)
    index = 0 if seed_index is None else seed_index
    label = describe(index) if describe is not None else f"training seed index {index}"
    builder = functools.partial(builder, **({} if seed_index is None else {"seed_index": seed_index}))
    builder.label = label
    return builder, task, paper_method, (rest[0] if rest else {})
