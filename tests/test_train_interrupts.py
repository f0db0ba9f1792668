"""Training interrupted or set up to make no sense: Ctrl-C keeps every finished chunk and names
the command that resumes the run; a budget in which no gradient step would happen is refused
before anything runs; a diverged run is flagged in its metrics, warned about and noted beside its
evaluation, and `metrics.jsonl` stays strict JSON."""

from __future__ import annotations

import json
import os
import re
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from agents.training import checkpoint
from agents.training.driver import read_metrics, train
from agents.training.registry import make_config
from snac_jax.cli import main

PPO = dict(num_envs=16, rollout_steps=8, num_minibatches=2, update_epochs=1, hidden_size=8, rnn_size=8)
PPO_FLAGS = [
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
]
REPLAY = dict(num_envs=8, rollout_steps=8, batch_size=16, gradient_steps=1, buffer_size=8 * 40, max_steps=20)
SAC = dict(REPLAY, hidden_sizes="16,16")
DQN = dict(REPLAY, hidden_size=8)


@pytest.fixture
def ctrl_c_raises():
    """Python's own SIGINT handler (KeyboardInterrupt), whatever the test runner inherited."""
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, previous)


def _ctrl_c_when_saving(monkeypatch, chunk: int) -> None:
    """Ctrl-C arrives just as the checkpoint of `chunk` starts to be written."""
    save = checkpoint.save_state

    def save_interrupted(directory, index, state):
        if index == chunk:
            os.kill(os.getpid(), signal.SIGINT)
        save(directory, index, state)

    monkeypatch.setattr(checkpoint, "save_state", save_interrupted)


def _snac(argv: list[str]) -> int:
    """`snac ARGV` in this process; Ctrl-C escaping it fails the test instead of ending the session."""
    try:
        return main(argv)
    except KeyboardInterrupt:
        pytest.fail("Ctrl-C escaped `snac` as a KeyboardInterrupt (a traceback for the user)")


def _strict_json_lines(path: Path) -> list[dict]:
    def refuse(constant):
        raise AssertionError(f"{path} holds {constant}, which is not JSON")

    return [json.loads(line, parse_constant=refuse) for line in path.read_text().splitlines()]


# --- Ctrl-C --------------------------------------------------------------------------------------


@pytest.mark.slow
def test_ctrl_c_in_snac_train_is_one_line_naming_the_resume_command(tmp_path, monkeypatch, capsys, ctrl_c_raises):
    """Ctrl-C as chunk 1's checkpoint is written: that checkpoint is completed first (orbax's save
    also deletes the oldest checkpoint, which an interrupt would leave half-deleted), the run
    stops with one line, and the command it names finishes the run."""
    run = tmp_path / "my run"  # a space: the command shown must still work when pasted
    _ctrl_c_when_saving(monkeypatch, chunk=1)
    argv = ["train", "ppo", *PPO_FLAGS, "--total-steps", str(3 * 16 * 8), "--chunks", "3", "--no-eval", "--no-progress"]
    assert _snac([*argv, "--out", str(run)]) == 130
    err = capsys.readouterr().err
    assert "Traceback" not in err
    command = f"snac train ppo --resume {shlex.quote(str(run))}"
    assert err.splitlines()[-1] == (
        f"snac train ppo: interrupted; 2 of 3 chunks are done and checkpointed, and the run is resumable: {command}"
    )
    assert checkpoint.latest_chunk(run) == 1
    assert [r["chunk"] for r in read_metrics(run)] == [0, 1]
    monkeypatch.undo()
    assert _snac(shlex.split(command)[1:] + ["--no-progress"]) == 0
    assert [r["chunk"] for r in read_metrics(run)] == [0, 1, 2]


def test_ctrl_c_before_a_run_starts_says_there_is_nothing_to_resume(tmp_path, monkeypatch, capsys):
    import agents.training.registry

    def interrupted(config):
        raise KeyboardInterrupt

    monkeypatch.setattr(agents.training.registry, "build_algorithm", interrupted)
    run = tmp_path / "run"
    assert _snac(["train", "ppo", *PPO_FLAGS, "--total-steps", "128", "--out", str(run)]) == 130
    assert capsys.readouterr().err.splitlines()[-1] == (
        "snac train ppo: interrupted before the run started; nothing to resume (start it again)"
    )
    assert not run.exists()


@pytest.mark.slow  # two processes that each compile a tiny run: ~30-60 s on a loaded 2-core CPU
def test_sigint_to_snac_train_leaves_a_run_its_printed_command_finishes(tmp_path, ctrl_c_raises):
    snac = Path(sys.executable).parent / "snac"
    run = tmp_path / "run"
    chunks = 40  # one update each: the run is still going when the signal comes
    argv = [
        str(snac),
        "train",
        "ppo",
        "--task",
        "1d-static-sin",
        *PPO_FLAGS,
        "--total-steps",
        str(chunks * 16 * 8),
        "--chunks",
        str(chunks),
        "--no-eval",
        "--no-progress",
        "--out",
        str(run),
    ]
    # A shell may start a background job with SIGINT ignored, and a child inherits that; with a
    # handler here (`ctrl_c_raises`) the child starts with the default, as under a terminal.
    process = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=tmp_path)
    deadline = time.monotonic() + 300
    while (
        not (run / checkpoint.CHECKPOINT_DIR / "1").is_dir() and process.poll() is None and time.monotonic() < deadline
    ):
        time.sleep(0.05)
    process.send_signal(signal.SIGINT)
    _, err = process.communicate(timeout=300)
    assert process.returncode == 130, err
    assert "Traceback" not in err and "asyncio" not in err and "Exception" not in err
    said = [line for line in err.splitlines() if "interrupted" in line]
    assert len(said) == 1 and said[0] == err.splitlines()[-1]
    found = re.fullmatch(
        rf"snac train ppo: interrupted; (\d+) of {chunks} chunks are done and checkpointed, and "
        r"the run is resumable: (snac train ppo --resume .+)",
        said[0],
    )
    assert found, said[0]
    done = int(found.group(1))
    assert checkpoint.latest_chunk(run) == done - 1
    assert [r["chunk"] for r in read_metrics(run)] == list(range(done))
    command = shlex.split(found.group(2))
    resumed = subprocess.run(
        [str(snac), *command[1:], "--no-progress"], capture_output=True, text=True, cwd=tmp_path, timeout=600
    )
    assert resumed.returncode == 0, resumed.stderr
    assert [r["chunk"] for r in read_metrics(run)] == list(range(chunks))


# --- a budget in which nothing is learned ---------------------------------------------------------


def test_learning_starts_beyond_the_budget_is_refused_naming_the_largest_value():
    budget = 4 * 8 * 8  # four updates of 8 worlds x 8 steps
    config = make_config("sac", "1d-static-sin", **SAC, total_steps=budget, learning_starts=budget)
    assert config.first_learning_update() == config.num_updates  # the largest value still learns
    for algorithm, options in (("sac", SAC), ("dqn", DQN)):
        with pytest.raises(
            ValueError,
            match=rf"learning_starts \({budget + 1}\) is beyond the run's {budget} env steps "
            rf"per seed .*no gradient step .*at most {budget}",
        ):
            make_config(algorithm, "1d-static-sin", **options, total_steps=budget, learning_starts=budget + 1)


def test_a_run_too_short_to_fill_one_replay_window_is_refused():
    with pytest.raises(
        ValueError,
        match=r"fewer than one sampled window \(sample_length 5\): no gradient step would be "
        r"taken; total_steps must be at least 40",
    ):
        make_config("dqn", "1d-static-sin", **{**DQN, "rollout_steps": 1}, learning_starts=0, total_steps=8)


def test_snac_train_refuses_learning_starts_beyond_the_budget_in_one_line(tmp_path, capsys):
    run = tmp_path / "run"
    code = main(
        [
            "train",
            "dqn",
            "--num-envs",
            "8",
            "--rollout-steps",
            "8",
            "--total-steps",
            "256",
            "--learning-starts",
            "100000",
            "--out",
            str(run),
        ]
    )
    assert code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert err.startswith("snac train dqn: error: learning_starts (100,000) is beyond the run's 256 env steps per seed")
    assert "learning_starts must be at most 256" in err
    assert not run.exists()


# --- divergence ----------------------------------------------------------------------------------


@pytest.mark.slow  # over 10 s on the 2-core CPU: `pytest -m slow` (CI runs both)
def test_a_diverged_run_is_flagged_resumed_and_noted_beside_its_evaluation(tmp_path, capsys):
    """Rewards scaled past float32 make the critic's loss infinite from its first gradient step,
    which `learning_starts` puts in the last two of three chunks."""
    from agents.training.cli import evaluate_run
    from agents.training.plotting import plot_curve

    config = make_config(
        "sac", "1d-static-sin", **SAC, total_steps=3 * 64, chunks=3, learning_starts=2 * 64, reward_scale=1e38
    )
    run = tmp_path / "run"
    train(config, run, progress=False, stop_after_chunks=2)
    algorithm, state = train(config, run, resume=True, progress=False)  # reads and rewrites the nulls
    records = _strict_json_lines(run / checkpoint.METRICS_FILE)
    assert [r["chunk"] for r in records] == [0, 1, 2]
    assert "diverged" not in records[0] and records[0]["gradient_steps"] == [0]
    for record in records[1:]:
        assert "critic_loss" in record["diverged"] and record["critic_loss"] == [None]
    warnings = [line for line in capsys.readouterr().err.splitlines() if "diverged" in line]
    assert warnings == [
        f"warning: training diverged in chunk 1: {', '.join(records[1]['diverged'])} not finite "
        f"(recorded as null in {run / checkpoint.METRICS_FILE}, the chunk flagged)"
    ]
    plot_curve(read_metrics(run), config.task, "diverged", run / "curve.png")  # nulls plot as gaps

    evaluate_run(algorithm, state, run, episodes=1)
    out = capsys.readouterr().out
    assert re.search(
        r"note: training diverged: .*critic_loss.* not finite in chunks 1-2 \(2 chunks\) of metrics.jsonl", out
    )
