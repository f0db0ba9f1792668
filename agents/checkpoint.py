"""Run directories: orbax checkpoints of the runner state and the run's config.json
(`agents.trained` loads a trained policy back from one).

A run directory holds `config.json`, `metrics.jsonl`, `checkpoints/<chunk>/` (orbax, written to
a temporary folder and renamed when complete, so a crash never leaves a half checkpoint),
`curve.png` and `eval.json`.

Typed PRNG keys do not serialise: they are stored as their raw `key_data` and wrapped again on
restore, guided by the structure of a freshly initialised state.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import jax
import numpy as np

from agents.registry import config_from_json

CONFIG_FILE = "config.json"
METRICS_FILE = "metrics.jsonl"
CHECKPOINT_DIR = "checkpoints"


def _is_key(x: Any) -> bool:
    return isinstance(x, jax.Array) and jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key)


def to_storable(tree: Any) -> Any:
    """Replace typed keys by their uint32 key data."""
    return jax.tree.map(lambda x: jax.random.key_data(x) if _is_key(x) else x, tree)


def from_storable(tree: Any, like: Any) -> Any:
    """Wrap the key data in `tree` back into typed keys wherever `like` holds one."""
    return jax.tree.map(lambda x, ref: jax.random.wrap_key_data(x) if _is_key(ref) else x, tree, like)


def _manager(directory: Path):
    import orbax.checkpoint as ocp

    return ocp.CheckpointManager(
        Path(directory).absolute() / CHECKPOINT_DIR,
        options=ocp.CheckpointManagerOptions(max_to_keep=2, create=True, enable_async_checkpointing=False),
    )


def save_state(directory: str | Path, chunk: int, state: Any) -> None:
    """Checkpoint `state` as chunk number `chunk` (orbax writes a temporary folder, then renames)."""
    import orbax.checkpoint as ocp

    manager = _manager(Path(directory))
    manager.save(chunk, args=ocp.args.StandardSave(to_storable(state)), force=True)
    manager.wait_until_finished()
    manager.close()


def latest_chunk(directory: str | Path) -> int | None:
    path = Path(directory) / CHECKPOINT_DIR
    if not path.is_dir():
        return None
    manager = _manager(Path(directory))
    step = manager.latest_step()
    manager.close()
    return step


def _key_name(entry: Any) -> str:
    """One step of a key path as orbax names it (attribute, dict key or sequence index)."""
    for attribute in ("name", "key", "idx"):
        if hasattr(entry, attribute):
            return str(getattr(entry, attribute))
    return str(entry)


def _leaves_by_path(tree: Any) -> dict[tuple[str, ...], Any]:
    return {tuple(_key_name(k) for k in path): leaf for path, leaf in jax.tree_util.tree_flatten_with_path(tree)[0]}


def _metadata_leaves(tree: Any, prefix: tuple[str, ...] = ()) -> dict[tuple[str, ...], Any]:
    """The stored arrays of an orbax metadata tree by path; empty (None) slots are left out."""
    if isinstance(tree, dict):
        items = tree.items()
    elif isinstance(tree, (list, tuple)):
        items = enumerate(tree)
    else:
        return {} if tree is None else {prefix: tree}
    leaves = {}
    for key, value in items:
        leaves.update(_metadata_leaves(value, prefix + (str(key),)))
    return leaves


def _shaped_like(tree: Any, targets: dict[tuple[str, ...], Any], prefix: tuple[str, ...] = ()) -> Any:
    """The metadata tree's structure with each stored array replaced by its restore target."""
    if isinstance(tree, dict):
        return {k: _shaped_like(v, targets, prefix + (str(k),)) for k, v in tree.items()}
    if isinstance(tree, (list, tuple)):
        return [_shaped_like(v, targets, prefix + (str(i),)) for i, v in enumerate(tree)]
    return None if tree is None else targets[prefix]


def _check_matches(directory, chunk: int, stored: dict, wanted: dict) -> None:
    """Compare what the checkpoint holds with what the config's state needs, before any read."""
    problems = [f"missing {'/'.join(p)}" for p in sorted(set(wanted) - set(stored))]
    problems += [f"unexpected {'/'.join(p)}" for p in sorted(set(stored) - set(wanted))]
    for path in sorted(set(wanted) & set(stored)):
        have, need = stored[path], wanted[path]
        if tuple(have.shape) != tuple(need.shape) or np.dtype(have.dtype) != np.dtype(need.dtype):
            problems.append(f"{'/'.join(path)} is {have.dtype}{list(have.shape)}, the config needs {need.dtype}{list(need.shape)}")
    if problems:
        listed = "; ".join(problems[:5]) + (f"; and {len(problems) - 5} more" if len(problems) > 5 else "")
        raise ValueError(
            f"{directory}: checkpoint {chunk} does not hold the state its {CONFIG_FILE} describes (edited "
            f"{CONFIG_FILE}, or another algorithm's or version's checkpoint): {listed}"
        )


def restore_state(directory: str | Path, like: Any, chunk: int | None = None) -> tuple[int, Any]:
    """The latest (or given) checkpoint, shaped, typed and sharded like `like`.

    Restored by key path: the stored metadata is compared with `like` first (a mismatch is one
    clear error, before anything is read), and slots a checkpoint holds empty (fields that were
    None when it was written) are ignored, so checkpoints of older versions of a state load."""
    import orbax.checkpoint as ocp

    manager = _manager(Path(directory))
    try:
        chunk = manager.latest_step() if chunk is None else chunk
        if chunk is None:
            raise ValueError(f"{directory}: no checkpoint under {CHECKPOINT_DIR}/ to resume from")
        metadata = ocp.StandardCheckpointer().metadata(
            Path(directory).absolute() / CHECKPOINT_DIR / str(chunk) / "default"
        )
        stored_tree = getattr(getattr(metadata, "item_metadata", metadata), "tree", metadata)
        storable = to_storable(like)
        wanted = {path: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=getattr(x, "sharding", None))
                  for path, x in _leaves_by_path(storable).items()}
        _check_matches(directory, chunk, _metadata_leaves(stored_tree), wanted)
        restored = manager.restore(chunk, args=ocp.args.StandardRestore(_shaped_like(stored_tree, wanted)))
    finally:
        manager.close()
    by_path = _metadata_leaves(restored)
    leaves = [by_path[path] for path in _leaves_by_path(storable)]
    return chunk, from_storable(jax.tree_util.tree_unflatten(jax.tree.structure(storable), leaves), like)


def read_config(directory: str | Path):
    """The config of run directory `directory` (its config.json)."""

    path = Path(directory) / CONFIG_FILE
    if not path.is_file():
        raise ValueError(f"{directory} is not a training run directory: {CONFIG_FILE} is missing")
    return config_from_json(json.loads(path.read_text()))
