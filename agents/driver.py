"""The training driver every algorithm shares: runs the jitted training in chunks, vmapped over
seeds and sharded over devices, with a progress bar, `metrics.jsonl`, a checkpoint after each
chunk, resume, the learning curve and the final evaluation.

An algorithm object (e.g. `agents.ppo.PPO`) provides, as pure functions:
`init(key) -> state` (state has `params` and a per-world `worlds` field), `train_chunk(state,
env_params, n) -> (state, metrics)` (metrics stacked over the n iterations, with `episodes`,
`iou_sum`, `return_sum` and losses), `policy(params) -> Policy`, plus `env_params`,
`num_updates` and `steps_per_update` (env steps per iteration per seed).

Resuming restores the state (PRNG keys included) of the last completed chunk and runs the
remaining chunks with the same compiled function, so the result equals an uninterrupted run.
"""

from __future__ import annotations

import contextlib
import json
import math
import sys
import time
from pathlib import Path
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import NamedSharding, PartitionSpec

from agents import checkpoint
from agents.config import TrainConfig, save_config
from agents.registry import build_algorithm
from agents.sharding import check_divisible, host_value, replicate, state_shardings, training_mesh
from snac_jax.atomic import atomic_write_text

def seed_keys(config: TrainConfig) -> jax.Array:
    base = jax.random.key(config.seed)
    return jax.vmap(lambda i: jax.random.fold_in(base, i))(jnp.arange(config.seeds))


def initial_state(algorithm, mesh=None) -> Any:
    """The seed-batched initial state, its worlds split over `mesh` (default: as many local
    devices as split the worlds evenly)."""
    mesh = training_mesh(num_envs=algorithm.config.num_envs) if mesh is None else mesh
    check_divisible(algorithm.config.num_envs, mesh)

    def init():  # the keys are made inside the jit: no process-local array enters it
        return jax.vmap(algorithm.init)(seed_keys(algorithm.config))

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


def _read_metrics(path: Path, up_to_chunk: int) -> list[dict]:
    return [r for r in checkpoint.read_metrics_lines(path) if r["chunk"] <= up_to_chunk]


def _start_run(config: TrainConfig, out_dir: Path, run_options: dict | None) -> None:
    """A new run in `out_dir` (checked empty by the caller, under the lock): its config, the
    caller's options and an empty metrics file."""
    checkpoint.check_new_run_directory(out_dir)  # again under the lock: another run may have begun
    save_config(config, out_dir / checkpoint.CONFIG_FILE)
    if run_options is not None:
        checkpoint.write_run_options(out_dir, run_options)
    atomic_write_text(out_dir / checkpoint.METRICS_FILE, "")


def _resume_point(out_dir: Path, state: Any, warn: Callable[[str], None], writer: bool = True) -> tuple[int, Any, list[dict]]:
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
            raise ValueError(f"{out_dir}: {checkpoint.METRICS_FILE} records {len(recorded)} chunk(s) but there is no "
                             f"checkpoint to resume from ({checkpoint.CHECKPOINT_DIR}/ was removed?); start a new run "
                             "in another directory")
        warn(f"{out_dir}: no chunk was checkpointed yet; starting the run from its beginning")
        if writer:
            atomic_write_text(metrics_path, "")
        return 0, state, []
    history = _read_metrics(metrics_path, last)
    missing = sorted(set(range(last + 1)) - {r["chunk"] for r in history})
    if missing:
        warn(f"{metrics_path} lacks the lines of chunk(s) {missing}; the learning curve will have gaps")
    if writer:
        atomic_write_text(metrics_path, "".join(json.dumps(r) + "\n" for r in history))
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
) -> tuple[Any, Any]:
    """Train `config` into `out_dir` (or continue the run there with `resume=True`).

    Returns `(algorithm, state)`. A new run needs a new or empty `out_dir`; `run_options` (JSON)
    are stored with it (`checkpoint.read_run_options`). The run directory is locked for the
    call (`checkpoint.lock_run`). `stop_after_chunks` ends early after that many chunks of this
    call (the tests' stand-in for a killed run). Across processes (`jax.distributed`), process 0
    checks, locks and writes the run directory; the others only train and checkpoint with it.
    """
    out_dir = Path(out_dir)
    writer = jax.process_index() == 0
    if resume:
        checkpoint.read_config(out_dir)  # a clear error before anything is created
    else:
        config.validate()
        if writer:
            checkpoint.check_new_run_directory(out_dir)
    with checkpoint.lock_run(out_dir) if writer else contextlib.nullcontext():
        if resume:
            config = checkpoint.read_config(out_dir)
        elif writer:
            _start_run(config, out_dir, run_options)
        return _train(config, out_dir, resume, progress, stop_after_chunks, mesh, writer)


def _train(config: TrainConfig, out_dir: Path, resume: bool, progress: bool, stop_after_chunks, mesh, writer: bool):
    metrics_path = out_dir / checkpoint.METRICS_FILE
    algorithm = build_algorithm(config)
    mesh = training_mesh(num_envs=config.num_envs) if mesh is None else mesh
    state = initial_state(algorithm, mesh)
    env_params = replicate(algorithm.env_params, mesh)
    shardings = jax.tree.map(lambda x: x.sharding, state)

    done_chunks, history = 0, []
    if resume:
        done_chunks, state, history = _resume_point(out_dir, state, lambda text: print(text, file=sys.stderr), writer)

    sizes = chunk_sizes(config.num_updates, config.chunks)
    compiled: dict[int, Callable] = {}

    def run_chunk(n: int) -> Callable:
        """The compiled chunk of n updates (compiled ahead, so chunk timings exclude compiling)."""
        if n not in compiled:
            fn = jax.vmap(lambda s, p: algorithm.train_chunk(s, p, n), in_axes=(0, None))
            start = time.perf_counter()
            replicated = NamedSharding(mesh, PartitionSpec())  # metrics: every process reads them
            jitted = jax.jit(fn, out_shardings=(shardings, replicated), donate_argnums=0)
            compiled[n] = jitted.lower(state, env_params).compile()
            bar.write(f"compiled a chunk of {n} updates in {time.perf_counter() - start:.1f} s")
        return compiled[n]

    steps_per_update = config.steps_per_update
    total_steps = sum(sizes) * steps_per_update
    done_steps = sum(sizes[:done_chunks]) * steps_per_update
    wall = history[-1]["wall_s"] if history else 0.0
    bar = _progress_bar(total_steps * config.seeds, done_steps * config.seeds, config, progress and writer)
    try:
        for index in range(done_chunks, len(sizes)):
            if stop_after_chunks is not None and index - done_chunks >= stop_after_chunks:
                break
            chunk_fn = run_chunk(sizes[index])
            start = time.perf_counter()
            state, metrics = chunk_fn(state, env_params)
            metrics = host_value(metrics)
            elapsed = time.perf_counter() - start
            wall += elapsed
            done_steps += sizes[index] * steps_per_update
            record = {
                "chunk": index,
                "updates": int(sum(sizes[: index + 1])),
                "env_steps": done_steps,
                "wall_s": round(wall, 3),
                "steps_per_s": sizes[index] * steps_per_update * config.seeds / elapsed,
                **summarize_chunk(metrics),
            }
            # Metrics first, checkpoint second: a resume trims lines past the last checkpoint.
            if writer:
                with metrics_path.open("a") as f:
                    f.write(json.dumps(record) + "\n")
            checkpoint.save_state(out_dir, index, state)
            bar.update(sizes[index] * steps_per_update * config.seeds)
            postfix = {"steps/s": f"{record['steps_per_s']:,.0f}"}
            if np.any(np.isfinite(record["iou"])):  # no episode may end within a short chunk
                postfix["IoU"] = f"{np.nanmean(record['iou']):.3f}"
                postfix["return"] = f"{np.nanmean(record['return']):.1f}"
            bar.set_postfix(postfix)
    finally:
        bar.close()
    return algorithm, state


def _progress_bar(total: int, initial: int, config: TrainConfig, enabled: bool):
    from tqdm.auto import tqdm

    return tqdm(
        total=total, initial=initial, disable=not enabled, unit="step", unit_scale=True,
        desc=f"{config.algorithm} {config.task}", dynamic_ncols=True,
    )


def read_metrics(out_dir: str | Path) -> list[dict]:
    return checkpoint.read_metrics_lines(Path(out_dir) / checkpoint.METRICS_FILE)
