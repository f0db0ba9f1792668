"""`snac train --log`: the trackers get the metrics `metrics.jsonl` holds, and a tracker that is
not installed is refused in one line naming its extra."""

from __future__ import annotations

import json
import struct

import pytest

from agents.training import trackers
from snac_jax.cli import main

TINY = [
    "--num-envs",
    "16",
    "--rollout-steps",
    "8",
    "--num-minibatches",
    "2",
    "--update-epochs",
    "1",
    "--hidden-size",
    "8",
    "--rnn-size",
    "8",
    "--no-progress",
    "--devices",
    "1",
]


def read_events(directory) -> dict[str, dict[int, float]]:
    """Every scalar of the TensorBoard event files under `directory`: tag -> {step: value}
    (TFRecord framing: length, its CRC, the Event proto, its CRC)."""
    from tensorboardX.proto import event_pb2

    found: dict[str, dict[int, float]] = {}
    for path in sorted(directory.glob("events.out.tfevents.*")):
        data, offset = path.read_bytes(), 0
        while offset < len(data):
            (length,) = struct.unpack("<Q", data[offset : offset + 8])
            event = event_pb2.Event.FromString(data[offset + 12 : offset + 12 + length])
            offset += 12 + length + 4
            for value in event.summary.value:
                found.setdefault(value.tag, {})[event.step] = value.simple_value
    return found


def test_scalars_are_the_records_numbers_per_seed():
    record = {
        "chunk": 0,
        "updates": 2,
        "env_steps": 256,
        "wall_s": 1.5,
        "steps_per_s": 100.0,
        "episodes": [3, 0],
        "iou": [0.25, None],
        "loss": [float("nan"), 2.0],
        "diverged": ["loss"],
    }
    assert trackers.scalars(record, seeds=2) == {
        "updates": 2.0,
        "wall_s": 1.5,
        "steps_per_s": 100.0,
        "episodes/seed0": 3.0,
        "episodes/seed1": 0.0,
        "iou/seed0": 0.25,
        "loss/seed1": 2.0,
    }
    assert set(trackers.scalars({"env_steps": 1, "iou": [1, 2, 3, 4]}, seeds=2, arms=2)) == {
        "iou/arm0/seed0",
        "iou/arm0/seed1",
        "iou/arm1/seed0",
        "iou/arm1/seed1",
    }


@pytest.mark.slow  # over 10 s on the 2-core CPU: `pytest -m slow` (CI runs both)
def test_train_log_tensorboard_writes_the_metrics_of_metrics_jsonl_across_a_resume(tmp_path):
    from agents.training.driver import train
    from agents.training.registry import make_config

    out = tmp_path / "run"
    config = make_config(
        "ppo",
        "1d-static-sin",
        num_envs=16,
        rollout_steps=8,
        num_minibatches=2,
        update_epochs=1,
        hidden_size=8,
        rnn_size=8,
        seeds=2,
        total_steps=384,
        chunks=3,
        max_steps=8,
    )
    train(
        config,
        out,
        progress=False,
        stop_after_chunks=1,
        run_options={"eval_episodes": None, "no_eval": True},
        log="tensorboard",
    )  # killed after its first chunk; `snac train --resume --log` finishes it
    assert main(["train", "ppo", "--resume", str(out), "--no-progress", "--devices", "1", "--log", "tensorboard"]) == 0
    records = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    events = read_events(out / trackers.TENSORBOARD_DIR)
    assert [r["chunk"] for r in records] == [0, 1, 2]
    expected = {}
    for record in records:
        for name, value in trackers.scalars(record, seeds=2).items():
            expected.setdefault(name, {})[record["env_steps"]] = value
    assert "iou/seed1" in expected and "steps_per_s" in expected
    assert set(events) == set(expected)
    for name, by_step in expected.items():
        assert events[name] == pytest.approx(by_step, rel=1e-6), name


def test_log_without_the_tracker_installed_is_refused_in_one_line(tmp_path, capsys, monkeypatch):
    real = trackers.importlib.util.find_spec
    monkeypatch.setattr(trackers.importlib.util, "find_spec", lambda name: None if name == "wandb" else real(name))
    out = tmp_path / "run"
    assert (
        main(
            [
                "train",
                "ppo",
                "--task",
                "1d-static-sin",
                *TINY,
                "--total-steps",
                "128",
                "--out",
                str(out),
                "--log",
                "wandb",
            ]
        )
        == 2
    )
    err = capsys.readouterr().err.strip().splitlines()
    assert (
        err[-1]
        == 'snac train ppo: error: --log wandb needs wandb, which is not installed: pip install "snac-jax[wandb]"'
    )
    assert not out.exists()  # refused before the run directory was made


def test_log_wandb_offline_gets_the_metrics(tmp_path, monkeypatch):
    wandb = pytest.importorskip("wandb")
    monkeypatch.setenv("WANDB_MODE", "offline")
    monkeypatch.setenv("WANDB_SILENT", "true")
    logged = []
    real_init = wandb.init

    def init(**kwargs):
        run = real_init(**kwargs)
        real_log = run.log
        run.log = lambda values, step: (logged.append((step, values)), real_log(values, step=step))[1]
        return run

    monkeypatch.setattr(wandb, "init", init)
    out = tmp_path / "run"
    assert (
        main(
            [
                "train",
                "ppo",
                "--task",
                "1d-static-sin",
                *TINY,
                "--total-steps",
                "256",
                "--chunks",
                "2",
                "--max-steps",
                "40",
                "--no-eval",
                "--out",
                str(out),
                "--log",
                "wandb",
            ]
        )
        == 0
    )
    records = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    assert logged == [(r["env_steps"], trackers.scalars(r, seeds=1)) for r in records]
    assert (out / "wandb").is_dir()
