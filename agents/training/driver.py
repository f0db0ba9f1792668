"""The training driver every algorithm shares: runs the jitted training in chunks, vmapped over
seeds and sharded over devices, with a progress bar, `metrics.jsonl`, a checkpoint after each
chunk, resume, the learning curve and the final evaluation.

An algorithm object (e.g. `agents.learners.ppo.PPO`) provides, as pure functions:
`init(key) -> state` (state has `params` and a per-world `worlds` field), `train_chunk(state,
env_params, n) -> (state, metrics)` (metrics stacked over the n iterations, with `episodes`,
`iou_sum`, `return_sum` and losses), `policy(params) -> Policy`, plus `env_params`,
`num_updates` and `steps_per_update` (env steps per iteration per seed).

Resuming restores the state (PRNG keys included) of the last completed chunk and runs the
remaining chunks with the same compiled function, so the result equals an uninterrupted run.
Ctrl-C (SIGINT) waits while a chunk's metrics line and checkpoint are written, so an interrupted
run keeps every chunk it finished.

`metrics.jsonl` is strict JSON: a value that is not finite is written as null. A chunk whose
learner metrics are not finite (a diverged run) is flagged in its line (`"diverged"`: the
metrics' names) and warned about; an episode mean is null without divergence when no episode
ended in the chunk.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import signal
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import NamedSharding, PartitionSpec

from agents.training import checkpoint, sweep, trackers
from agents.training.chunk_programs import ChunkPrograms, compiles_ahead
from agents.training.config import TrainConfig, save_config
from agents.training.registry import build_algorithm
from agents.training.sharding import check_divisible, host_value, replicate, state_shardings, training_mesh
from agents.training.sweep import Sweep
from snac_jax.atomic import atomic_write_json, atomic_write_text


def seed_keys(config: TrainConfig, arms: int = 1) -> jax.Array:
    """Every run's key: seed i uses fold_in(key(seed), i); with a sweep's `arms`, arm-major, run
    `a * seeds + i` has seed i's key (an arm trains as a run of its own settings would)."""
    base = jax.random.key(config.seed)
    return jax.vmap(lambda i: jax.random.fold_in(base, i % config.seeds))(jnp.arange(config.seeds * arms))


def per_run(algorithm, swept: Sweep | None, fn: Callable, in_axes) -> Callable:
    """`fn(learner, *args)` vmapped over the run axis (`in_axes` for `args`): over seeds with
    `algorithm`, or over a sweep's arms x seeds with each run's learner built from its own traced
    swept values (`agents.training.sweep`), so one compiled function trains every arm."""
    if swept is None:
        return jax.vmap(lambda *args: fn(algorithm, *args), in_axes=in_axes)
    values = swept.run_values(algorithm.config.seeds)

    def one_run(value, *args):
        return fn(sweep.learner_for(algorithm.config, value), *args)

    return lambda *args: jax.vmap(one_run, in_axes=(0, *in_axes))(values, *args)


def initial_state(algorithm, mesh=None, swept: Sweep | None = None) -> Any:
    """The run-batched initial state (seeds, or a sweep's arms x seeds), its worlds split over
    `mesh` (default: as many local devices as split the worlds evenly)."""
    mesh = training_mesh(num_envs=algorithm.config.num_envs) if mesh is None else mesh
    check_divisible(algorithm.config.num_envs, mesh)
    arms = 1 if swept is None else swept.num_arms

    def init():  # the keys are made inside the jit: no process-local array enters it
        return per_run(algorithm, swept, lambda learner, key: learner.init(key), (0,))(
            seed_keys(algorithm.config, arms)
        )

    return jax.jit(init, out_shardings=state_shardings(jax.eval_shape(init), mesh))()


def chunk_sizes(num_updates: int, chunks: int) -> list[int]:
    """Updates per chunk: equal chunks (at most two distinct sizes, so at most two compiles)."""
    chunks = min(chunks, num_updates)
    per_chunk = math.ceil(num_updates / chunks)
    sizes = [per_chunk] * (num_updates // per_chunk)
    if num_updates % per_chunk:
        sizes.append(num_updates % per_chunk)
    return sizes


def summarize_chunk(metrics: dict[str, np.ndarray]) -> dict[str, list[float]]:
    """Per-seed summary of a chunk's stacked metrics (seeds, updates)."""
    episodes = metrics["episodes"].sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        iou = np.where(episodes > 0, metrics["iou_sum"].sum(axis=1) / episodes, np.nan)
        ret = np.where(episodes > 0, metrics["return_sum"].sum(axis=1) / episodes, np.nan)
    summary = {"episodes": episodes.tolist(), "iou": iou.tolist(), "return": ret.tolist()}
    for name, values in metrics.items():
        if name not in ("episodes", "iou_sum", "return_sum"):
            summary[name] = values[:, -1].tolist()  # the chunk's last update
    return summary


EPISODE_MEANS = ("iou", "return")
"""Per-seed means over the episodes that ended in a chunk: null, not divergence, when none did."""


def nonfinite_metrics(summary: dict[str, list[float]]) -> list[str]:
    """The names of the metrics of a chunk summary (`summarize_chunk`) that hold a value that is
    not finite for some seed: the run diverged. An episode mean counts only for seeds whose
    episodes ended."""
    names = []
    for name, values in summary.items():
        values = np.asarray(values, dtype=float)
        if name in EPISODE_MEANS:
            values = values[np.asarray(summary["episodes"]) > 0]
        if not np.all(np.isfinite(values)):
            names.append(name)
    return names


def _json_safe(value: Any) -> Any:
    """`value` with every float that is not finite replaced by None (JSON's null): `json.dumps`
    would write bare NaN/Infinity, which no strict JSON reader accepts."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_safe(v) for v in value]
    return value


def metrics_line(record: dict[str, Any]) -> str:
    """One `metrics.jsonl` line of strict JSON (non-finite values as null)."""
    return json.dumps(_json_safe(record), allow_nan=False) + "\n"


def diverged_chunks(records: list[dict]) -> list[tuple[int, list[str]]]:
    """`(chunk, metric names)` of every chunk its metrics line flags as diverged."""
    return [(r["chunk"], list(r["diverged"])) for r in records if r.get("diverged")]


def divergence_note(records: list[dict]) -> str | None:
    """One line saying that (and where) the run's training diverged, or None if it did not."""
    found = diverged_chunks(records)
    if not found:
        return None
    chunks = [chunk for chunk, _ in found]
    names = sorted({name for _, listed in found for name in listed})
    where = f"chunk {chunks[0]}" if len(chunks) == 1 else f"chunks {chunks[0]}-{chunks[-1]} ({len(chunks)} chunks)"
    return (
        f"training diverged: {', '.join(names)} not finite in {where} of metrics.jsonl; the policy scored "
        "is a diverged one"
    )


@contextlib.contextmanager
def interrupts_deferred():
    """Ctrl-C (SIGINT) arriving inside the block takes effect when it ends: the block's files are
    written whole. orbax's save also deletes the oldest checkpoint, and an interrupt there leaves
    a half-deleted folder; deferred, an interrupted run keeps every chunk it finished. Only the
    main thread can handle signals; elsewhere, or where SIGINT is ignored or handled outside
    Python, the block runs as it is."""
    previous = signal.getsignal(signal.SIGINT)
    if threading.current_thread() is not threading.main_thread() or previous in (None, signal.SIG_IGN):
        yield
        return
    received: list[int] = []
    signal.signal(signal.SIGINT, lambda signum, frame: received.append(signum))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
    if received:
        if callable(previous):
            previous(signal.SIGINT, None)  # Python's default handler raises KeyboardInterrupt
        elif previous == signal.SIG_DFL:
            os.kill(os.getpid(), signal.SIGINT)


def arm_record(record: dict[str, Any], arm: int, seeds: int, arms: int) -> dict[str, Any]:
    """One arm's share of a sweep's chunk record: its seeds' entries of every per-run list, its
    share of the throughput, and its own divergence flag."""
    share = {
        k: v[arm * seeds : (arm + 1) * seeds] if isinstance(v, list) and len(v) == seeds * arms else v
        for k, v in record.items()
        if k != "diverged"
    }
    share["steps_per_s"] = record["steps_per_s"] / arms
    summary = {k: v for k, v in share.items() if isinstance(v, list)}
    diverged = nonfinite_metrics(summary)
    return {**share, **({"diverged": diverged} if diverged else {})}


def _write_arm_metrics(out_dir: Path, swept: Sweep, seeds: int, history: list[dict]) -> None:
    """Each arm's `metrics.jsonl` under `arms/<i>/`, rewritten whole from the run's history (the
    run's own `metrics.jsonl` is the record a resume trims; these follow it)."""
    for arm in range(swept.num_arms):
        lines = "".join(metrics_line(arm_record(r, arm, seeds, swept.num_arms)) for r in history)
        atomic_write_text(sweep.arm_dir(out_dir, arm) / checkpoint.METRICS_FILE, lines)


def _read_metrics(path: Path, up_to_chunk: int) -> list[dict]:
    return [r for r in checkpoint.read_metrics_lines(path) if r["chunk"] <= up_to_chunk]


def _warn(text: str) -> None:
    print(text, file=sys.stderr)


def _start_run(config: TrainConfig, out_dir: Path, run_options: dict | None, swept: Sweep | None = None) -> None:
    """A new run in `out_dir` (checked empty by the caller, under the lock): its config, the
    caller's options, an empty metrics file, and for a sweep its grid and each arm's config."""
    checkpoint.check_new_run_directory(out_dir)  # again under the lock: another run may have begun
    if swept is None:
        save_config(config, out_dir / checkpoint.CONFIG_FILE)
    else:
        atomic_write_json(out_dir / checkpoint.CONFIG_FILE, sweep.base_config_json(config, swept))
    if run_options is not None:
        checkpoint.write_run_options(out_dir, run_options)
    if swept is not None:
        sweep.save(swept, out_dir)
        for arm in range(swept.num_arms):
            sweep.arm_dir(out_dir, arm).mkdir(parents=True)
            save_config(swept.arm_config(config, arm), sweep.arm_dir(out_dir, arm) / checkpoint.CONFIG_FILE)
    atomic_write_text(out_dir / checkpoint.METRICS_FILE, "")


def _resume_point(
    out_dir: Path, state: Any, warn: Callable[[str], None], writer: bool = True
) -> tuple[int, Any, list[dict]]:
    """`(chunks done, state, metrics history)` of the run in `out_dir`: the newest checkpoint
    that restores (a damaged newest one falls back to the one before), the metrics up to it
    (lines past it, or cut short by a kill, are dropped and rewritten)."""
    metrics_path = out_dir / checkpoint.METRICS_FILE
    last, state, notes = checkpoint.restore_latest(out_dir, state)
    for note in notes:
        warn(f"{note}; resuming from an earlier checkpoint")
    if notes and writer:
        checkpoint.discard_after(out_dir, -1 if last is None else last)  # recomputed, then saved again
    if last is None:
        recorded = checkpoint.read_metrics_lines(metrics_path)
        if recorded:
            raise ValueError(
                f"{out_dir}: {checkpoint.METRICS_FILE} records {len(recorded)} chunk(s) but there is no "
                f"checkpoint to resume from ({checkpoint.CHECKPOINT_DIR}/ was removed?); start a new run "
                "in another directory"
            )
        warn(f"{out_dir}: no chunk was checkpointed yet; starting the run from its beginning")
        if writer:
            atomic_write_text(metrics_path, "")
        return 0, state, []
    history = _read_metrics(metrics_path, last)
    missing = sorted(set(range(last + 1)) - {r["chunk"] for r in history})
    if missing:
        warn(f"{metrics_path} lacks the lines of chunk(s) {missing}; the learning curve will have gaps")
    if writer:
        atomic_write_text(metrics_path, "".join(metrics_line(r) for r in history))
    return last + 1, state, history


def train(
    config: TrainConfig,
    out_dir: str | Path,
    *,
    resume: bool = False,
    progress: bool = True,
    stop_after_chunks: int | None = None,
    mesh=None,
    run_options: dict | None = None,
    swept: Sweep | None = None,
    log: str | None = None,
) -> tuple[Any, Any]:
    """Train `config` into `out_dir` (or continue the run there with `resume=True`).

    Returns `(algorithm, state)`. A new run needs a new or empty `out_dir`; `run_options` (JSON)
    are stored with it (`checkpoint.read_run_options`). With `swept` (`agents.training.sweep`), every arm
    of the grid trains beside the others in one compiled function, the state's leading axis
    being arms x seeds; a resume reads the grid back from the run. The run directory is locked for the
    call (`checkpoint.lock_run`). `stop_after_chunks` ends early after that many chunks of this
    call (the tests' stand-in for a killed run). Across processes (`jax.distributed`), process 0
    checks, locks and writes the run directory; the others only train and checkpoint with it.
    `log` (`agents.training.trackers.TRACKERS`) also sends each chunk's metrics to TensorBoard or wandb.
    """
    out_dir = Path(out_dir)
    writer = jax.process_index() == 0
    trackers.check(log)
    if resume:
        checkpoint.read_config(out_dir)  # a clear error before anything is created
    else:
        config.validate()
        if writer:
            checkpoint.check_new_run_directory(out_dir)
    with checkpoint.lock_run(out_dir) if writer else contextlib.nullcontext():
        if resume:
            config = checkpoint.read_config(out_dir)
            swept = sweep.load(out_dir, config)
            if swept is not None:
                sweep.check_arms(out_dir, config, swept, restore=_warn if writer else None)
        elif writer:
            _start_run(config, out_dir, run_options, swept)
        return _train(config, out_dir, resume, progress, stop_after_chunks, mesh, writer, swept, log)


def _train(
    config: TrainConfig,
    out_dir: Path,
    resume: bool,
    progress: bool,
    stop_after_chunks,
    mesh,
    writer: bool,
    swept: Sweep | None = None,
    log: str | None = None,
):
    metrics_path = out_dir / checkpoint.METRICS_FILE
    algorithm = build_algorithm(config)
    mesh = training_mesh(num_envs=config.num_envs) if mesh is None else mesh
    state = initial_state(algorithm, mesh, swept)
    env_params = replicate(algorithm.env_params, mesh)
    shardings = jax.tree.map(lambda x: x.sharding, state)
    runs = config.seeds * (1 if swept is None else swept.num_arms)

    done_chunks, history = 0, []
    if resume:
        with interrupts_deferred():  # Ctrl-C inside orbax's asyncio restore strands its tasks, which print at exit
            done_chunks, state, history = _resume_point(out_dir, state, _warn, writer)
    if swept is not None and writer:
        _write_arm_metrics(out_dir, swept, config.seeds, history)

    sizes = chunk_sizes(config.num_updates, config.chunks)
    abstract = jax.tree.map(_abstract, (state, env_params))

    def lower_chunk(n: int):
        """The chunk of n updates, lowered for `ChunkPrograms` (compiled before its chunk's timing
        starts)."""
        fn = per_run(algorithm, swept, lambda learner, s, p: learner.train_chunk(s, p, n), (0, None))
        replicated = NamedSharding(mesh, PartitionSpec())  # metrics: every process reads them
        return jax.jit(fn, out_shardings=(shardings, replicated), donate_argnums=0).lower(*abstract)

    steps_per_update = config.steps_per_update
    total_steps = sum(sizes) * steps_per_update
    done_steps = sum(sizes[:done_chunks]) * steps_per_update
    wall = history[-1]["wall_s"] if history else 0.0
    bar = _progress_bar(total_steps * runs, done_steps * runs, config, progress and writer)
    last = len(sizes) if stop_after_chunks is None else min(len(sizes), done_chunks + stop_after_chunks)
    programs = ChunkPrograms(lower_chunk, sizes[done_chunks:last], bar.write, background=compiles_ahead())
    warned = list(history[-1].get("diverged") or []) if history else []  # said once per change
    tracker = trackers.open_tracker(
        log if writer else None,
        out_dir,
        config,
        config.seeds,
        1 if swept is None else swept.num_arms,
        start_step=done_steps,
    )
    try:
        for index in range(done_chunks, len(sizes)):
            if stop_after_chunks is not None and index - done_chunks >= stop_after_chunks:
                break
            chunk_fn = programs.get(sizes[index])
            start = time.perf_counter()
            state, metrics = chunk_fn(state, env_params)
            metrics = host_value(metrics)
            elapsed = time.perf_counter() - start
            wall += elapsed
            done_steps += sizes[index] * steps_per_update
            summary = summarize_chunk(metrics)
            record = {
                "chunk": index,
                "updates": int(sum(sizes[: index + 1])),
                "env_steps": done_steps,
                "wall_s": round(wall, 3),
                "steps_per_s": sizes[index] * steps_per_update * runs / elapsed,
                **summary,
            }
            diverged = nonfinite_metrics(summary)
            if diverged:
                record["diverged"] = diverged
                if diverged != warned and writer:
                    bar.write(
                        f"warning: training diverged in chunk {index}: {', '.join(diverged)} not finite "
                        f"(recorded as null in {metrics_path}, the chunk flagged)",
                        file=sys.stderr,
                    )
            warned = diverged
            # Metrics first, checkpoint second: a resume trims lines past the last checkpoint.
            with interrupts_deferred():
                if writer:
                    with metrics_path.open("a") as f:
                        f.write(metrics_line(record))
                checkpoint.save_state(out_dir, index, state)
            if tracker is not None:
                tracker.log(record)
            if swept is not None and writer:
                history.append(record)
                _write_arm_metrics(out_dir, swept, config.seeds, history)
            bar.update(sizes[index] * steps_per_update * runs)
            postfix = {"steps/s": f"{record['steps_per_s']:,.0f}"}
            if np.any(np.isfinite(record["iou"])):  # no episode may end within a short chunk
                postfix["IoU"] = f"{np.nanmean(record['iou']):.3f}"
                postfix["return"] = f"{np.nanmean(record['return']):.1f}"
            bar.set_postfix(postfix)
    finally:
        try:
            bar.close()
            if tracker is not None:
                tracker.close()
        finally:
            programs.close()
    return algorithm, state


def _abstract(leaf):
    """An array's shape, dtype and sharding, for lowering without reading it."""
    if not isinstance(leaf, jax.Array):
        return leaf
    return jax.ShapeDtypeStruct(
        leaf.shape, leaf.dtype, sharding=leaf.sharding, weak_type=getattr(leaf, "weak_type", False)
    )  # a key array has none


def _progress_bar(total: int, initial: int, config: TrainConfig, enabled: bool):
    from tqdm.auto import tqdm

    return tqdm(
        total=total,
        initial=initial,
        disable=not enabled,
        unit="step",
        unit_scale=True,
        desc=f"{config.algorithm} {config.task}",
        dynamic_ncols=True,
    )


def read_metrics(out_dir: str | Path) -> list[dict]:
    return checkpoint.read_metrics_lines(Path(out_dir) / checkpoint.METRICS_FILE)
