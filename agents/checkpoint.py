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


def restore_state(directory: str | Path, like: Any, chunk: int | None = None) -> tuple[int, Any]:
    """The latest (or given) checkpoint, shaped, typed and sharded like `like`."""
    import orbax.checkpoint as ocp

    manager = _manager(Path(directory))
    chunk = manager.latest_step() if chunk is None else chunk
    if chunk is None:
        manager.close()
        raise ValueError(f"{directory}: no checkpoint under {CHECKPOINT_DIR}/ to resume from")

    def abstract(x):
        sharding = getattr(x, "sharding", None)
        return jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=sharding)

    target = jax.tree.map(abstract, to_storable(like))
    try:
        restored = manager.restore(chunk, args=ocp.args.StandardRestore(target))
    except (ValueError, KeyError, TypeError) as error:
        # orbax reports a mismatch as a long tree diff; say first what it means.
        raise ValueError(
            f"{directory}: checkpoint {chunk} does not match the network and state its config.json "
            f"describes (edited config.json, or saved by an older snac-jax?): {str(error)[:500]}"
        ) from error
    finally:
        manager.close()
    return chunk, from_storable(restored, like)


def read_config(directory: str | Path):
    """The config of run directory `directory` (its config.json)."""

    path = Path(directory) / CONFIG_FILE
    if not path.is_file():
        raise ValueError(f"{directory} is not a training run directory: {CONFIG_FILE} is missing")
    return config_from_json(json.loads(path.read_text()))
