"""Run directories: orbax checkpoints of the runner state and the run's config.json
(`agents.training.trained` loads a trained policy back from one).

A run directory holds `config.json`, `run.json` (the caller's options, e.g. the CLI's evaluation
settings, restored on resume), `metrics.jsonl`, `checkpoints/<chunk>/` (orbax, written to a
temporary folder and renamed when complete, so a crash never leaves a half checkpoint),
`curve.png`, `eval.json`, and `.lock`, which a process holds while it works on the run (two
processes never write one run; the kernel drops the lock when its holder dies, even by SIGKILL).
A new run starts only in an empty (or new) directory.

Typed PRNG keys do not serialise: they are stored as their raw `key_data` and wrapped again on
restore, guided by the structure of a freshly initialised state.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import jax
import numpy as np

from agents.training import schemas
from agents.training.registry import config_from_json

CONFIG_FILE = "config.json"
METRICS_FILE = "metrics.jsonl"
CHECKPOINT_DIR = "checkpoints"
RUN_OPTIONS_FILE = "run.json"
LOCK_FILE = ".lock"


class DamagedCheckpoint(ValueError):
    """A checkpoint whose files cannot be read back (truncated or corrupt)."""


# --- the run directory -------------------------------------------------------------------------


def check_new_run_directory(directory: str | Path) -> Path:
    """`ValueError` unless a new run may start in `directory`: absent, or an empty directory
    whose nearest existing folder is writable. Nothing is created. Its `.lock` alone leaves it
    empty only when it is a plain file that no other process holds (a link, a folder or a lock
    in use is named)."""
    from snac_jax.atomic import check_writable

    directory = Path(directory)
    if directory.exists() and not directory.is_dir():
        raise ValueError(f"{directory} is a file, not a run directory")
    entries = sorted(p.name for p in directory.iterdir() if p.name != LOCK_FILE) if directory.is_dir() else []
    if entries:
        shown = ", ".join(entries[:5]) + (", ..." if len(entries) > 5 else "")
        hint = " (if it holds a run, continue it with --resume / resume=True)" if CONFIG_FILE in entries else ""
        raise ValueError(f"{directory} is not empty ({shown}){hint}; a new run needs a new or empty directory")
    if directory.is_dir():
        check_lock_file(directory)
        if not os.access(directory, os.W_OK | os.X_OK):
            raise ValueError(f"run directory {directory} cannot be written: no permission")
    else:
        check_writable(directory, "run directory")
    return directory


_HELD: dict[Path, list] = {}  # run directory -> [open lock file, depth]: this process's locks


def _open_lock(directory: Path, create: bool) -> int | None:
    """A descriptor of `directory/.lock`, opened without following a link (None: there is none
    and `create` is False); `ValueError` when it is a link or anything but a plain file, so a
    lock never writes outside its run directory."""
    import stat

    path = directory / LOCK_FILE
    flags = os.O_RDWR | os.O_NOFOLLOW | os.O_CLOEXEC | os.O_NONBLOCK | (os.O_CREAT if create else 0)
    try:
        fd = os.open(path, flags, 0o644)
    except FileNotFoundError:
        if create:
            raise
        return None
    except OSError:
        if path.is_symlink():
            raise ValueError(
                f"{path} is a symbolic link, not a lock file: a run's lock is never followed; "
                "remove the link if it is not this run's"
            ) from None
        if path.exists() and not path.is_file():
            raise ValueError(
                f"{path} is not a plain file, not a lock file: remove it if it is not this run's"
            ) from None
        raise
    if not stat.S_ISREG(os.fstat(fd).st_mode):
        os.close(fd)
        raise ValueError(f"{path} is not a plain file, not a lock file: remove it if it is not this run's")
    return fd


def _in_use(directory: Path, handle) -> ValueError:
    handle.seek(0)
    holder = handle.read(200).strip() or "another process"
    return ValueError(f"{directory} is in use by {holder}: one run directory takes one process at a time")


def check_lock_file(directory: str | Path) -> None:
    """`ValueError` when `directory/.lock` is not a plain file, or another process holds it; a
    free one (its holder ended, even by SIGKILL) or this process's own is fine."""
    import fcntl

    directory = Path(directory)
    if directory.absolute() in _HELD:
        return
    fd = _open_lock(directory, create=False)
    if fd is None:
        return
    with os.fdopen(fd, "r+", errors="replace") as handle:
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise _in_use(directory, handle) from None


@contextlib.contextmanager
def lock_run(directory: str | Path) -> Iterator[Path]:
    """Hold `directory/.lock` (created with the directory) while working on the run: a second
    process gets a `ValueError` at once. Re-entrant within a process (the CLI holds it across
    training and evaluation, `train` again inside). A `.lock` that is a link is refused, never
    followed (`_open_lock`)."""
    import fcntl

    directory = Path(directory)
    key = directory.absolute()
    if key in _HELD:
        _HELD[key][1] += 1
    else:
        directory.mkdir(parents=True, exist_ok=True)
        handle = os.fdopen(_open_lock(directory, create=True), "r+", errors="replace")
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            error = _in_use(directory, handle)
            handle.close()
            raise error from None
        handle.seek(0)
        handle.truncate()
        handle.write(f"process {os.getpid()}\n")
        handle.flush()
        _HELD[key] = [handle, 1]
    try:
        yield directory
    finally:
        _HELD[key][1] -= 1
        if not _HELD[key][1]:
            _HELD.pop(key)[0].close()  # closing drops the lock


def write_run_options(directory: str | Path, options: dict[str, Any]) -> None:
    from snac_jax.atomic import atomic_write_json

    atomic_write_json(Path(directory) / RUN_OPTIONS_FILE, options)


def read_run_options(directory: str | Path) -> dict[str, Any]:
    """The caller's options stored with the run (`{}` for runs that stored none), checked
    against `agents.training.schemas.RUN_JSON` (a hand-edited `"no_eval": "false"` is refused, not read
    as true)."""
    path = Path(directory) / RUN_OPTIONS_FILE
    if not path.is_file():
        return {}
    return schemas.load(path, schemas.RUN_JSON)


def read_metrics_lines(path: str | Path) -> list[dict]:
    """The records of a metrics.jsonl. A last line cut short (the process was killed while
    writing it) is left out; a bad line before it is a `ValueError` naming it."""
    path = Path(path)
    if not path.is_file():
        return []
    lines = path.read_text().splitlines()
    records = []
    for number, line in enumerate(lines, start=1):
        if not line.strip():
            continue
        try:
            record = json.loads(line)
        except json.JSONDecodeError as error:
            if number == len(lines):
                break  # torn by a kill: the chunk it describes has no checkpoint either
            raise ValueError(f"{path}:{number}: not a JSON line ({error})") from error
        if not isinstance(record, dict) or not isinstance(record.get("chunk"), int):
            raise ValueError(f"{path}:{number}: not a metrics record (an object with a chunk number)")
        records.append(record)
    return records


# --- checkpoints -------------------------------------------------------------------------------


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
            problems.append(
                f"{'/'.join(path)} is {have.dtype}{list(have.shape)}, the config needs {need.dtype}{list(need.shape)}"
            )
    if problems:
        listed = "; ".join(problems[:5]) + (f"; and {len(problems) - 5} more" if len(problems) > 5 else "")
        raise ValueError(
            f"{directory}: checkpoint {chunk} does not hold the state its {CONFIG_FILE} describes (edited "
            f"{CONFIG_FILE}, a damaged checkpoint, or another algorithm's or version's checkpoint): {listed}"
        )


def restore_state(directory: str | Path, like: Any, chunk: int | None = None) -> tuple[int, Any]:
    """The latest (or given) checkpoint, shaped, typed and sharded like `like`.

    Restored by key path: the stored metadata is compared with `like` first (a mismatch is one
    clear error, before anything is read), and slots a checkpoint holds empty (fields that were
    None when it was written) are ignored, so checkpoints of older versions of a state load."""
    with _orbax_read_quietly():
        return _restore_state(directory, like, chunk)


def _restore_state(directory: str | Path, like: Any, chunk: int | None) -> tuple[int, Any]:
    import orbax.checkpoint as ocp

    manager = _manager(Path(directory))
    try:
        chunk = manager.latest_step() if chunk is None else chunk
        if chunk is None:
            raise ValueError(f"{directory}: no checkpoint under {CHECKPOINT_DIR}/ to resume from")
        with _damage_is_named(directory, chunk):
            metadata = ocp.StandardCheckpointer().metadata(
                Path(directory).absolute() / CHECKPOINT_DIR / str(chunk) / "default"
            )
        item = getattr(metadata, "item_metadata", metadata)
        if item is None:  # orbax answers None when it cannot parse the checkpoint's _METADATA
            raise DamagedCheckpoint(
                f"{directory}: checkpoint {chunk} cannot be read (truncated or corrupt files?): "
                "its metadata does not parse"
            )
        stored_tree = getattr(item, "tree", item)
        storable = to_storable(like)
        wanted = {
            path: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=getattr(x, "sharding", None))
            for path, x in _leaves_by_path(storable).items()
        }
        _check_matches(directory, chunk, _metadata_leaves(stored_tree), wanted)
        with _damage_is_named(directory, chunk):
            restored = manager.restore(chunk, args=ocp.args.StandardRestore(_shaped_like(stored_tree, wanted)))
    finally:
        manager.close()
    by_path = _metadata_leaves(restored)
    leaves = [by_path[path] for path in _leaves_by_path(storable)]
    return chunk, from_storable(jax.tree_util.tree_unflatten(jax.tree.structure(storable), leaves), like)


class _OrbaxReadNoise(logging.Filter):
    """orbax's warnings on every read of a checkpoint this module writes: it looks for a step's
    metadata inside the item's folder, which holds none; they read like damage and are not."""

    MESSAGES = ("Metadata file does not exist", "Failed to get item metadata")

    def filter(self, record: logging.LogRecord) -> bool:
        return not str(record.msg).startswith(self.MESSAGES)


def _is_abandoned_orbax_work(unraisable) -> bool:
    """Whether an unraisable error is one of a damaged checkpoint's aftermath: orbax's asyncio
    callbacks, abandoned when its read failed, that tensorstore later calls on a closed event
    loop, or its coroutines collected unfinished."""
    if isinstance(unraisable.exc_value, RuntimeError) and str(unraisable.exc_value) == "Event loop is closed":
        return True
    code = getattr(unraisable.object, "cr_code", None)
    return code is not None and ("orbax" in code.co_filename or "tensorstore" in code.co_filename)


def _drop_abandoned_orbax_work() -> None:
    """From now on, leave out the errors of a damaged checkpoint's abandoned reads (dozens to
    hundreds of tracebacks, some at exit) after the one line that names the damage; any other
    unraisable error is passed on as before."""
    previous = sys.unraisablehook
    if getattr(previous, "drops_abandoned_orbax_work", False):
        return

    def hook(unraisable) -> None:
        if not _is_abandoned_orbax_work(unraisable):
            previous(unraisable)

    hook.drops_abandoned_orbax_work = True
    sys.unraisablehook = hook


@contextlib.contextmanager
def _orbax_read_quietly() -> Iterator[None]:
    """A checkpoint read without orbax's noise: its warnings that a step's metadata is missing
    (`_OrbaxReadNoise`), and, once a checkpoint proves damaged, the errors of its abandoned
    reads (`_drop_abandoned_orbax_work`), those raised during the read included: they are held
    until the read's outcome is known, then passed on unless they are that aftermath."""
    absl = logging.getLogger("absl")
    noise = _OrbaxReadNoise()
    absl.addFilter(noise)
    collected: list = []
    previous = sys.unraisablehook
    sys.unraisablehook = collected.append
    damaged = False
    try:
        yield
    except DamagedCheckpoint:
        damaged = True
        raise
    finally:
        sys.unraisablehook = previous
        absl.removeFilter(noise)
        if damaged:
            _drop_abandoned_orbax_work()
        for unraisable in collected:
            sys.unraisablehook(unraisable)


@contextlib.contextmanager
def _damage_is_named(directory, chunk: int) -> Iterator[None]:
    """Any failure to read checkpoint files (orbax and tensorstore raise many kinds) becomes
    one `DamagedCheckpoint` naming the checkpoint; the original stays chained."""
    try:
        yield
    except Exception as error:
        first = (str(error).strip().splitlines() or [type(error).__name__])[0][:200]
        raise DamagedCheckpoint(
            f"{directory}: checkpoint {chunk} cannot be read (truncated or corrupt files?): {type(error).__name__}: {first}"
        ) from error


def restore_latest(directory: str | Path, like: Any) -> tuple[int | None, Any, list[str]]:
    """`(chunk, state, notes)` of the newest checkpoint that restores; `notes` say why newer ones
    did not. A damaged newest checkpoint falls back to the one before it (orbax keeps two), so
    a resume recomputes that chunk instead of failing. `(None, like, [])` without checkpoints.

    When no checkpoint restores, a mismatch with config.json is raised if there is one (the
    config's fault, not damage), else the newest checkpoint's damage."""
    path = Path(directory) / CHECKPOINT_DIR
    if not path.is_dir():
        return None, like, []
    manager = _manager(Path(directory))
    steps = sorted(manager.all_steps(), reverse=True)
    manager.close()
    errors: list[ValueError] = []
    for chunk in steps:
        try:
            return chunk, restore_state(directory, like, chunk)[1], [str(e) for e in errors]
        except ValueError as error:
            errors.append(error)
    if errors:  # a mismatch with config.json is the config's fault, whatever else is damaged
        raise next((e for e in errors if not isinstance(e, DamagedCheckpoint)), errors[0])
    return None, like, []


def discard_after(directory: str | Path, chunk: int) -> list[int]:
    """Delete the checkpoints newer than `chunk` (unreadable ones a resume recomputes, so
    that their chunks can be saved again); the chunks deleted."""
    manager = _manager(Path(directory))
    try:
        newer = [step for step in manager.all_steps() if step > chunk]
        for step in newer:
            manager.delete(step)
    finally:
        manager.close()
    return newer


def read_config(directory: str | Path):
    """The config of run directory `directory` (its config.json, checked against
    `agents.training.schemas.CONFIG_JSON`, then the config's own rules); errors name the file."""
    path = Path(directory) / CONFIG_FILE
    if not path.is_file():
        raise ValueError(f"{directory} is not a training run directory: {CONFIG_FILE} is missing")
    data = schemas.load(path, schemas.CONFIG_JSON)
    try:
        return config_from_json(data)
    except (TypeError, ValueError) as error:
        raise ValueError(f"{path}: {error}") from error
