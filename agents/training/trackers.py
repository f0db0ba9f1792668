"""Experiment tracking: `snac train --log tensorboard` or `--log wandb` sends each chunk's
metrics to the tracker as the driver writes them to `metrics.jsonl`, so a run can be followed
where the field follows runs, while `metrics.jsonl` stays the record the project reads back.

Each chunk's line becomes scalars at step `env_steps` (per seed): a per-run list `name` gives
`name/seed<i>` (in a sweep `name/arm<a>/seed<s>`), a number its own scalar; the chunk counter,
step count and divergence flag are not scalars. A value that is not finite (null in
`metrics.jsonl`) is left out. TensorBoard's event files go to `DIR/tensorboard/` (tensorboardX,
in the `[train]` extra: no TensorFlow); wandb (the `[wandb]` extra) writes under `DIR/wandb/`
and follows `WANDB_MODE` (`offline` keeps the run on disk). A resumed run purges what its
trackers hold past the resume point, as the driver trims `metrics.jsonl`.
"""

from __future__ import annotations

import hashlib
import importlib.util
import math
from pathlib import Path
from typing import Any

TRACKERS = {"tensorboard": ("tensorboardX", "train"), "wandb": ("wandb", "wandb")}
"""`--log` name -> (the module it needs, the extra that installs it)."""
TENSORBOARD_DIR = "tensorboard"
NOT_SCALARS = ("chunk", "env_steps", "diverged")


def check(kind: str | None) -> None:
    """A `ValueError` in one line, before any training, if `kind` is not a tracker or its module
    is not installed (naming the extra to install)."""
    if kind is None:
        return
    if kind not in TRACKERS:
        raise ValueError(f"--log must be one of {', '.join(TRACKERS)}, got {kind!r}")
    module, extra = TRACKERS[kind]
    if importlib.util.find_spec(module) is None:
        raise ValueError(f'--log {kind} needs {module}, which is not installed: pip install "snac-jax[{extra}]"')


def scalars(record: dict[str, Any], seeds: int, arms: int = 1) -> dict[str, float]:
    """The scalars of one `metrics.jsonl` record (see the module's docstring)."""
    found = {}
    for name, value in record.items():
        if name in NOT_SCALARS:
            continue
        if isinstance(value, (list, tuple)):
            for index, item in enumerate(value):
                run = f"seed{index}" if arms == 1 else f"arm{index // seeds}/seed{index % seeds}"
                found[f"{name}/{run}"] = item
        else:
            found[name] = value
    return {
        name: float(v)
        for name, v in found.items()
        if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
    }


class Tracker:
    """Sends chunk records to one tracker; `log` after each chunk's metrics line, `close` at the end."""

    def __init__(self, kind: str, out_dir: Path, config, seeds: int, arms: int, start_step: int):
        check(kind)
        self.kind, self.seeds, self.arms = kind, seeds, arms
        out_dir = Path(out_dir)
        if kind == "tensorboard":
            from tensorboardX import SummaryWriter

            # purge_step: TensorBoard drops what an earlier process wrote from this step on.
            self._run = SummaryWriter(str(out_dir / TENSORBOARD_DIR), purge_step=start_step or None)
        else:
            import wandb

            # One wandb run per run directory, continued on resume.
            run_id = hashlib.sha1(str(out_dir.resolve()).encode()).hexdigest()[:16]
            self._run = wandb.init(
                project="snac-jax",
                name=out_dir.name,
                id=run_id,
                resume="allow",
                dir=str(out_dir),
                config=config.to_json(),
            )

    def log(self, record: dict[str, Any]) -> None:
        values, step = scalars(record, self.seeds, self.arms), int(record["env_steps"])
        if self.kind == "tensorboard":
            for name, value in values.items():
                self._run.add_scalar(name, value, global_step=step)
            self._run.flush()
        else:
            self._run.log(values, step=step)

    def close(self) -> None:
        if self.kind == "tensorboard":
            self._run.close()
        else:
            self._run.finish()


def open_tracker(kind: str | None, out_dir: Path, config, seeds: int, arms: int = 1, start_step: int = 0):
    """The tracker `kind` for the run in `out_dir`, or None without one."""
    return None if kind is None else Tracker(kind, out_dir, config, seeds, arms, start_step)
