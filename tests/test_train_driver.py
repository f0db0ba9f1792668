"""The shared training driver: run directory contents, checkpoint round trip, resume equal to an
uninterrupted run, a 2-device run, the CLI and the checkpoint policy loader."""

from __future__ import annotations

import dataclasses
import json
import os
import re
import subprocess
import sys
import textwrap
import time
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from agents.training import checkpoint, trained
from agents.training.driver import chunk_sizes, initial_state, read_metrics, train
from agents.training.registry import make_config

TINY = dict(num_envs=16, rollout_steps=8, num_minibatches=2, update_epochs=1, hidden_size=8, rnn_size=8)


# The run the checkpoint, resume and finished-run tests share (each copies it where it changes
# anything), so that one PPO configuration compiles for them all: four chunks of one update.
RUN = make_config("ppo", "1d-static-gauss", recurrent=True, seeds=2, total_steps=4 * 16 * 8, chunks=4, **TINY)


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory):
    """`(directory, final state)` of `RUN` trained uninterrupted. Read it, or copy it (`_copy_of`) to change it."""
    directory = tmp_path_factory.mktemp("finished") / "run"
    _, state = train(RUN, directory, progress=False)
    return directory, state


def _copy_of(run, tmp_path):
    import shutil

    return Path(shutil.copytree(run, tmp_path / "run", symlinks=True))


def _leaves_equal(a, b) -> bool:
    a, b = checkpoint.to_storable(a), checkpoint.to_storable(b)
    return all(np.array_equal(np.asarray(x), np.asarray(y)) for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)))


def test_chunk_sizes_cover_the_run():
    assert chunk_sizes(10, 3) == [4, 4, 2]
    assert chunk_sizes(9, 3) == [3, 3, 3]
    assert chunk_sizes(2, 20) == [1, 1]


@pytest.mark.slow  # over 10 s on the 2-core CPU: `pytest -m slow` (CI runs both)
@pytest.mark.parametrize("ahead", [True, False])
def test_a_shorter_last_chunk_compiles_once_ahead_or_when_needed_and_changes_nothing(
    tmp_path, capsys, monkeypatch, ahead
):
    """Chunks of 2 and 1 updates: each program compiles once, the 1-update one behind the first
    chunks' training where the driver compiles ahead (an accelerator; forced here) and when its
    chunk comes on a CPU; the run ends where one 3-update chunk ends."""
    import agents.training.driver as driver

    monkeypatch.setattr(driver, "compiles_ahead", lambda: ahead)
    config = make_config("ppo", "1d-static-gauss", recurrent=True, seeds=2, total_steps=3 * 16 * 8, chunks=2, **TINY)
    _, chunked = train(config, tmp_path / "chunked", progress=False)
    printed = capsys.readouterr()
    printed = printed.out + printed.err
    assert printed.count("compiled a chunk of 2 updates in") == 1
    assert printed.count("compiled a chunk of 1 updates in") == 1
    assert bool(re.search(r"compiled a chunk of 1 updates in [0-9.]+ s \(in the background\)", printed)) == ahead
    _, whole = train(dataclasses.replace(config, chunks=1), tmp_path / "whole", progress=False)
    assert _leaves_equal(chunked, whole)


def test_the_driver_compiles_ahead_on_accelerators_only():
    from agents.training.chunk_programs import compiles_ahead

    assert compiles_ahead() == (jax.default_backend() != "cpu")


class _Lowered:
    """A stand-in for a lowered chunk: `compile` records its thread, and holds on `gates[n]` or
    raises `failures[n]` where given."""

    def __init__(self, n, threads, gates=None, failures=None):
        self.n, self.threads, self.gates, self.failures = n, threads, gates or {}, failures or {}

    def compile(self):
        import threading

        self.threads.append((self.n, threading.current_thread().name))
        if self.n in self.gates:
            started, release = self.gates[self.n]
            started.set()
            assert release.wait(10)
        if self.failures.pop(self.n, None):
            raise RuntimeError("RESOURCE_EXHAUSTED: out of memory\nmore")
        return f"program {self.n}"


def test_chunk_programs_compile_the_later_sizes_on_another_thread_and_say_so_when_closing_on_one():
    import threading

    from agents.training.chunk_programs import ChunkPrograms

    started, release, threads, written = threading.Event(), threading.Event(), [], []
    gates = {1: (started, release)}
    programs = ChunkPrograms(lambda n: _Lowered(n, threads, gates), [2, 2, 1], written.append, background=True)
    assert programs.get(2) == "program 2"  # returns while the 1-update compile is still under way
    assert started.wait(10)
    main = threading.current_thread().name
    assert threads[0] == (2, main) and threads[1][0] == 1 and threads[1][1] != main
    closer = threading.Thread(target=programs.close)
    closer.start()  # an interrupted run: it waits for the compile under way, and says so
    time.sleep(0.2)
    assert closer.is_alive() and written[-1].startswith("waiting for a chunk's compile under way")
    release.set()
    closer.join(10)
    assert not closer.is_alive()

    threads, written = [], []
    programs = ChunkPrograms(lambda n: _Lowered(n, threads), [2, 2, 1], written.append, background=True)
    assert programs.get(2) == "program 2" and programs.get(1) == "program 1" and programs.get(2) == "program 2"
    programs.close()
    assert [w.split(" in ")[0] for w in written] == ["compiled a chunk of 2 updates", "compiled a chunk of 1 updates"]
    assert written[1].endswith("(in the background)") and not written[0].endswith("(in the background)")


def test_a_failed_background_compile_is_warned_about_and_compiled_again_in_the_foreground():
    import threading

    from agents.training.chunk_programs import ChunkPrograms

    threads, written, failures = [], [], {1: True}  # the first compile of 1 fails, the second succeeds
    programs = ChunkPrograms(lambda n: _Lowered(n, threads, failures=failures), [2, 1], written.append, background=True)
    programs.get(2)
    assert programs.get(1) == "program 1"
    programs.close()
    assert [n for n, _ in threads] == [2, 1, 1] and threads[2][1] == threading.current_thread().name
    assert written[1] == (
        "warning: compiling the chunk of 1 updates in the background failed (RuntimeError: "
        "RESOURCE_EXHAUSTED: out of memory); compiling it now"
    )
    assert written[2].startswith("compiled a chunk of 1 updates in ") and "background" not in written[2]


def test_without_compiling_ahead_every_program_compiles_on_the_callers_thread_when_first_needed():
    import threading

    from agents.training.chunk_programs import ChunkPrograms

    threads, written = [], []
    programs = ChunkPrograms(lambda n: _Lowered(n, threads), [2, 2, 1], written.append, background=False)
    programs.get(2)
    assert [n for n, _ in threads] == [2]
    programs.get(1)
    programs.close()
    assert threads == [(2, threading.current_thread().name), (1, threading.current_thread().name)]


@pytest.mark.slow
def test_checkpoint_round_trip(tmp_path):
    from agents.training.registry import build_algorithm

    algorithm = build_algorithm(RUN)
    state = initial_state(algorithm)
    checkpoint.save_state(tmp_path, 0, state)
    assert checkpoint.latest_chunk(tmp_path) == 0
    chunk, restored = checkpoint.restore_state(tmp_path, initial_state(algorithm))
    assert chunk == 0 and _leaves_equal(state, restored)
    assert jax.dtypes.issubdtype(restored.key.dtype, jax.dtypes.prng_key)


@pytest.mark.slow
def test_resume_equals_uninterrupted(tmp_path, finished_run):
    config = RUN
    straight_run, straight = finished_run
    straight_lines = read_metrics(straight_run)
    killed = tmp_path / "killed"
    _, first = train(config, killed, progress=False, stop_after_chunks=2)
    assert int(first.update[0]) == 2
    # A crash after the metrics line but before the checkpoint, then one in the middle of the
    # next line: resume drops both.
    with (killed / checkpoint.METRICS_FILE).open("a") as f:
        f.write(json.dumps({"chunk": 2, "wall_s": 0.0}) + "\n" + '{"chunk": 3, "wa')
    _, resumed = train(config, killed, resume=True, progress=False)
    assert int(resumed.update[0]) == 4
    assert _leaves_equal(straight, resumed)
    resumed_lines = read_metrics(killed)
    assert [r["chunk"] for r in resumed_lines] == [0, 1, 2, 3]
    assert [r["iou"] for r in resumed_lines] == [r["iou"] for r in straight_lines]


@pytest.mark.slow  # four tiny training runs: ~1-2 min on a loaded 2-core CPU
def test_resume_past_a_damaged_checkpoint_or_before_the_first_equals_uninterrupted(tmp_path, capsys):
    config = make_config("ppo", "1d-static-gauss", recurrent=True, seeds=2, total_steps=4 * 16 * 8, chunks=4, **TINY)
    _, straight = train(config, tmp_path / "straight", progress=False)
    straight_lines = read_metrics(tmp_path / "straight")
    killed = tmp_path / "killed"
    train(config, killed, progress=False)

    # The newest checkpoint damaged (its metadata cut in half): evaluating it is refused with the
    # way out, and a resume recomputes its chunk from the one before, to the same state.
    cut = killed / checkpoint.CHECKPOINT_DIR / "3" / "default" / "_METADATA"
    cut.write_bytes(cut.read_bytes()[: cut.stat().st_size // 2])
    with pytest.raises(ValueError, match=r"checkpoint 3 .*; checkpoint 2 is intact: `snac train ppo --resume "):
        trained.load_trained(killed)
    capsys.readouterr()
    _, repaired = train(config, killed, resume=True, progress=False)
    assert "resuming from an earlier checkpoint" in capsys.readouterr().err
    assert _leaves_equal(straight, repaired) and _leaves_equal(straight, trained.load_trained(killed)[1])
    assert [r["iou"] for r in read_metrics(killed)] == [r["iou"] for r in straight_lines]

    # Killed before the first checkpoint: the run starts again from its beginning.
    early = tmp_path / "early"
    early.mkdir()
    (early / checkpoint.CONFIG_FILE).write_text(json.dumps(config.to_json()))
    _, restarted = train(config, early, resume=True, progress=False)
    assert _leaves_equal(straight, restarted)


@pytest.mark.parametrize("damaged", ["data", "_METADATA"])
def test_a_checkpoint_that_cannot_be_read_is_named_and_the_one_before_restores(tmp_path, damaged):
    """Truncated files are named as damage (not blamed on an edited config.json), and the newest
    intact checkpoint is found."""
    weights = [jax.random.normal(jax.random.key(chunk), (64, 64)) for chunk in (0, 1)]  # incompressible
    for chunk in (0, 1):
        checkpoint.save_state(tmp_path, chunk, {"w": weights[chunk]})
    files = [p for p in (tmp_path / checkpoint.CHECKPOINT_DIR / "1").rglob("*") if p.is_file()]
    cut = (
        max(files, key=lambda p: p.stat().st_size) if damaged == "data" else next(p for p in files if p.name == damaged)
    )
    cut.write_bytes(cut.read_bytes()[: cut.stat().st_size // 2])
    like = {"w": jnp.zeros((64, 64))}
    with pytest.raises(checkpoint.DamagedCheckpoint, match="checkpoint 1 cannot be read .truncated or corrupt files"):
        checkpoint.restore_state(tmp_path, like, 1)
    chunk, state, notes = checkpoint.restore_latest(tmp_path, like)
    assert chunk == 0 and np.array_equal(state["w"], weights[0]) and "checkpoint 1 cannot be read" in notes[0]
    with pytest.raises(ValueError, match="does not hold the state"):  # every checkpoint mismatches: the config's fault
        checkpoint.restore_latest(tmp_path, {"w": jnp.zeros((2, 2))})
    with pytest.raises(ValueError, match="metrics.jsonl records 1 chunk"):  # checkpoints gone, metrics kept
        import shutil

        shutil.rmtree(tmp_path / checkpoint.CHECKPOINT_DIR)
        (tmp_path / checkpoint.METRICS_FILE).write_text('{"chunk": 0}\n')
        from agents.training.driver import _resume_point

        _resume_point(tmp_path, like, print)
    (tmp_path / checkpoint.METRICS_FILE).write_text("")  # killed before its first chunk ended: start again
    assert _resume_point(tmp_path, like, print) == (0, like, [])


def test_new_run_refuses_an_existing_run_and_resume_needs_one(tmp_path, finished_run):
    run = _copy_of(finished_run[0], tmp_path)
    with pytest.raises(
        ValueError,
        match=r"run is not empty \(checkpoints, config.json, metrics.jsonl\) \(if it holds a run, continue it with --resume",
    ):
        train(RUN, run, progress=False)
    with pytest.raises(ValueError, match="config.json is missing"):
        train(RUN, tmp_path / "empty", resume=True, progress=False)


@pytest.mark.slow
def test_checkpoint_that_does_not_match_its_config_is_a_clear_error(tmp_path, finished_run):
    run = _copy_of(finished_run[0], tmp_path)
    saved = json.loads((run / checkpoint.CONFIG_FILE).read_text())
    saved["hidden_size"] = 2 * saved["hidden_size"]
    (run / checkpoint.CONFIG_FILE).write_text(json.dumps(saved))
    with pytest.raises(ValueError, match=r"does not hold the state its config.json describes .*the config needs"):
        trained.load_trained(run)


TWO_DEVICES = textwrap.dedent(
    """
    import json, sys
    import jax
    from agents.training.registry import make_config
    from agents.training.driver import train
    from snac_jax.evaluation import run_episodes
    from snac_jax.devices import env_mesh
    import numpy as np

    devices = int(sys.argv[1])
    config = make_config("ppo", "1d-static-step", recurrent=False, update_epochs=4, num_minibatches=4, reward_scale=0.1, ent_coef_end=0.01, total_steps=200_000, num_envs=64, rollout_steps=40,
                         hidden_size=32, learning_rate=3e-3, max_steps=40, chunks=2)
    mesh = env_mesh(devices)
    algorithm, state = train(config, sys.argv[2], progress=False, mesh=mesh)
    before = algorithm.init(jax.random.key(0)).params
    def iou(params):
        out = run_episodes(algorithm.env, algorithm.env_params, algorithm.policy(params), jax.random.key(5), np.zeros(64, np.int32))
        return float(np.mean(out.iou))
    shardings = {tuple(x.sharding.spec) for x in jax.tree.leaves(state.worlds)}
    print(json.dumps({
        "devices": len(jax.devices()),
        "shapes": [list(x.shape) for x in jax.tree.leaves(state)],
        "world_specs": [list(s) for s in shardings],
        "iou_before": iou(before),
        "iou_after": iou(jax.tree.map(lambda x: x[0], state.params)),
    }))
    """
)


def _run_devices(devices: int, out_dir) -> dict:
    env = {**os.environ, "XLA_FLAGS": f"--xla_force_host_platform_device_count={devices}", "JAX_PLATFORMS": "cpu"}
    result = subprocess.run(
        [sys.executable, "-c", TWO_DEVICES, str(devices), str(out_dir)],
        capture_output=True,
        text=True,
        env=env,
        timeout=600,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    return json.loads(result.stdout.strip().splitlines()[-1])


@pytest.mark.slow  # two training subprocesses: ~1 min idle, minutes on a loaded 2-core CPU
def test_two_device_run_matches_one_device_shapes_and_learns(tmp_path):
    two = _run_devices(2, tmp_path / "two")
    one = _run_devices(1, tmp_path / "one")
    assert two["devices"] == 2 and one["devices"] == 1
    assert two["shapes"] == one["shapes"]
    assert two["world_specs"] == [[None, "envs"]]
    # The bar of tests/test_ppo.py's short-episode run: 85% of the best IoU 40 steps allow.
    assert two["iou_after"] > 0.85 * 40 / 600 and two["iou_after"] > two["iou_before"], two


@pytest.mark.slow
def test_cli_train_writes_the_run_directory_and_eval_loads_it(tmp_path):
    out = tmp_path / "run"
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    cmd = [
        sys.executable,
        "-m",
        "snac_jax.cli",
        "train",
        "ppo",
        "--task",
        "1d-static-sin",
        "--recurrent",
        "--total-steps",
        "256",
        "--num-envs",
        "16",
        "--chunks",
        "2",
        "--out",
        str(out),
        "--eval-episodes",
        "4",
        "--no-progress",
    ]
    result = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]
    for name in ("config.json", "metrics.jsonl", "curve.png", "eval.json"):
        assert (out / name).is_file(), name
    assert "| 1d-static-sin |" in result.stdout
    assert "worlds split over 1 cpu device(s)" in result.stderr  # training's CPU default
    evaluation = json.loads((out / "eval.json").read_text())
    assert 0.0 <= evaluation["1d-static-sin"]["mean"] <= 1.0

    from snac_jax.evaluation import evaluate_task

    again = evaluate_task("1d-static-sin", lambda env: trained.checkpoint_policy(env, out), static_episodes=4)
    assert again.mean == pytest.approx(evaluation["1d-static-sin"]["mean"])

    from snac_jax.cli import main  # and `snac render --checkpoint` draws the trained policy

    gif = tmp_path / "run.gif"
    assert (
        main(["render", "--task", "1d-static-sin", "--checkpoint", str(out), "--out", str(gif), "--max-steps", "8"])
        == 0
    )
    assert gif.stat().st_size > 0


@pytest.mark.slow  # over 10 s on the 2-core CPU: `pytest -m slow` (CI runs both)
def test_eval_and_render_read_the_training_seed_that_seed_index_names(tmp_path, capsys, monkeypatch):
    """A `--seeds 2` run keeps both policies in one checkpoint: `snac eval --checkpoint
    --seed-index 1` and `snac render` load the second (the first by default), an index past the
    run's seeds is refused by range, and `--seed-index` without a checkpoint is refused by name."""
    run = tmp_path / "run"
    train(make_config("ppo", "1d-static-sin", seeds=2, total_steps=128, chunks=1, **TINY), run, progress=False)
    loaded = []
    load = trained.checkpoint_policy

    def recording(env, directory, **options):  # records the option as passed (None: not passed)
        loaded.append(options.get("seed_index"))
        return load(env, directory, **options)

    monkeypatch.setattr(trained, "checkpoint_policy", recording)
    code, out, err = _cli(
        ["eval", "--checkpoint", str(run), "--seed-index", "1", "--episodes", "2", "--devices", "1"], capsys
    )
    assert code == 0, err
    assert "training seed index 1" in out and "| 1d-static-sin | 2 |" in out and set(loaded) == {1}
    loaded.clear()
    code, out, err = _cli(["eval", "--checkpoint", str(run), "--episodes", "2", "--devices", "1"], capsys)
    # without the flag the builder gets no option (a loader whose builder takes none still works)
    assert code == 0 and "training seed index 0" in out and set(loaded) == {None}, err
    loaded.clear()
    code, out, err = _cli(
        [
            "render",
            "--task",
            "1d-static-sin",
            "--checkpoint",
            str(run),
            "--seed-index",
            "1",
            "--out",
            str(tmp_path / "r.gif"),
            "--max-steps",
            "6",
        ],
        capsys,
    )
    assert code == 0 and loaded == [1] and "(training seed index 1)" in out, err

    code, _, err = _cli(["eval", "--checkpoint", str(run), "--seed-index", "2", "--episodes", "2"], capsys)
    assert code == 2 and "seed index (seed_index, --seed-index) must be in 0..1" in err
    code, _, err = _cli(["eval", "--policy", "random", "--seed-index", "0"], capsys)
    assert code == 2 and "--seed-index picks one training seed of a run: give it with --checkpoint DIR" in err
    code, _, err = _cli(
        ["render", "--task", "1d-static-sin", "--seed-index", "0", "--out", str(tmp_path / "r.gif")], capsys
    )
    assert code == 2 and "give it with --checkpoint DIR" in err


def test_checkpoint_policy_rejects_another_task(finished_run):
    from snac_jax.tasks import make

    env, _ = make("1d-static-step")
    with pytest.MonkeyPatch.context() as patch:  # refused from config.json, before any checkpoint is read
        patch.setattr(trained, "load_trained", lambda *a: pytest.fail("the checkpoint was loaded"))
        with pytest.raises(ValueError, match="trained on '1d-static-gauss'"):
            trained.checkpoint_policy(env, finished_run[0])


def test_a_checkpoint_with_empty_slots_restores_into_a_state_without_them(tmp_path):
    """A state saved when a field held None (as the DQN's hindsight fields did before hindsight
    got its own module) restores into the same state without that field."""
    from flax import struct

    @struct.dataclass
    class Before:
        weights: jax.Array
        extra: Any = None

    @struct.dataclass
    class After:
        weights: jax.Array

    checkpoint.save_state(tmp_path, 0, Before(weights=jnp.arange(6.0).reshape(2, 3)))
    chunk, restored = checkpoint.restore_state(tmp_path, After(weights=jnp.zeros((2, 3))))
    assert chunk == 0 and isinstance(restored, After)
    np.testing.assert_array_equal(restored.weights, np.arange(6.0).reshape(2, 3))


def test_a_checkpoint_of_another_shape_is_refused_before_reading(tmp_path):
    checkpoint.save_state(tmp_path, 3, {"w": jnp.zeros((2, 3)), "b": jnp.zeros(3)})
    with pytest.raises(
        ValueError,
        match=r"checkpoint 3 does not hold the state .*w is float32\[2, 3\], the config needs float32\[4, 3\]",
    ):
        checkpoint.restore_state(tmp_path, {"w": jnp.zeros((4, 3)), "b": jnp.zeros(3)})
    with pytest.raises(ValueError, match="missing c; unexpected b"):
        checkpoint.restore_state(tmp_path, {"w": jnp.zeros((2, 3)), "c": jnp.zeros(3)})


# --- run directories: nothing is overwritten, two processes never share one ----------------------


def test_a_new_run_refuses_any_non_empty_directory(tmp_path):
    """A finished run whose checkpoints/ is gone, or an unrelated config.json, is not written over
    (refused before anything is built, so it takes milliseconds)."""
    config = make_config("ppo", "1d-static-sin", total_steps=128, chunks=1, **TINY)
    finished = tmp_path / "finished"
    finished.mkdir()
    for name in ("config.json", "metrics.jsonl", "eval.json"):
        (finished / name).write_text("{}\n")
    unrelated = tmp_path / "mine"
    unrelated.mkdir()
    (unrelated / "config.json").write_text('{"mine": true}\n')
    for directory in (finished, unrelated):
        before = {p.name: p.read_text() for p in directory.iterdir()}
        with pytest.raises(ValueError, match=r"is not empty \(config.json.*a new run needs a new or empty directory"):
            train(config, directory, progress=False)
        assert {p.name: p.read_text() for p in directory.iterdir()} == before
    (tmp_path / "file").write_text("x")
    with pytest.raises(ValueError, match="is a file, not a run directory"):
        train(config, tmp_path / "file", progress=False)
    with pytest.raises(ValueError, match="is not a directory"):
        train(config, tmp_path / "file" / "run", progress=False)


def test_two_processes_cannot_work_on_one_run_directory(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    holder = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import fcntl, sys, time; f = open(sys.argv[1], 'a+'); fcntl.flock(f, fcntl.LOCK_EX); "
            "f.write('process 4242'); f.flush(); print('locked', flush=True); time.sleep(120)",
            str(run / checkpoint.LOCK_FILE),
        ],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert holder.stdout.readline().strip() == "locked"
        config = make_config("ppo", "1d-static-sin", total_steps=128, chunks=1, **TINY)
        with pytest.raises(ValueError, match="is in use by process 4242: one run directory takes one process"):
            train(config, run, progress=False)
        assert [p.name for p in run.iterdir()] == [checkpoint.LOCK_FILE]  # nothing written
    finally:
        holder.kill()
        holder.wait()
    with checkpoint.lock_run(run), checkpoint.lock_run(run):  # free again (the kernel dropped it); re-entrant
        assert f"process {os.getpid()}" in (run / checkpoint.LOCK_FILE).read_text()


def test_a_lock_is_never_followed_through_a_link(tmp_path):
    """A `.lock` that is a symbolic link (to a file outside the run, or nowhere) is refused in
    one line by the lock and by the emptiness check; the file it points to is left alone."""
    outside = tmp_path / "precious.txt"
    outside.write_text("someone's file\n")
    config = make_config("ppo", "1d-static-sin", total_steps=128, chunks=1, **TINY)
    for name, target in (("run", outside), ("dangling", tmp_path / "nowhere")):
        run = tmp_path / name
        run.mkdir()
        (run / checkpoint.LOCK_FILE).symlink_to(target)
        with pytest.raises(
            ValueError, match=r"\.lock is a symbolic link, not a lock file: a run's lock is never followed"
        ):
            with checkpoint.lock_run(run):
                pass
        for check in (checkpoint.check_new_run_directory, lambda d: train(config, d, progress=False)):
            with pytest.raises(ValueError, match="is a symbolic link"):
                check(run)
        assert (run / checkpoint.LOCK_FILE).is_symlink() and [p.name for p in run.iterdir()] == [checkpoint.LOCK_FILE]
    assert outside.read_text() == "someone's file\n" and not (tmp_path / "nowhere").exists()
    (tmp_path / "folder" / checkpoint.LOCK_FILE).mkdir(parents=True)
    with pytest.raises(ValueError, match=r"\.lock is not a plain file"):
        checkpoint.check_new_run_directory(tmp_path / "folder")
    # A plain lock its holder left (killed) leaves a directory empty; one held elsewhere does not.
    (tmp_path / "stale").mkdir()
    (tmp_path / "stale" / checkpoint.LOCK_FILE).write_text("process 999999\n")
    checkpoint.check_new_run_directory(tmp_path / "stale")


def _stored_run(tmp_path, options: str):
    """A run directory with its config.json and the given run.json, and no chunk trained yet."""
    from agents.training.config import save_config

    save_config(
        make_config("ppo", "1d-static-sin", total_steps=128, chunks=1, **TINY), tmp_path / checkpoint.CONFIG_FILE
    )
    (tmp_path / checkpoint.RUN_OPTIONS_FILE).write_text(options)
    return tmp_path


@pytest.mark.parametrize(
    "options, message",
    [
        ('{"eval_episodes": 2, "no_eval": "false"}', r"run.json: no_eval must be true or false, got 'false'"),
        ('{"eval_episodes": -5, "no_eval": false}', r"run.json: eval_episodes must be an int >= 1 or null, got -5"),
        ('{"eval_episode": 2}', r"run.json: unknown field\(s\) \['eval_episode'\]; allowed: eval_episodes, no_eval"),
        ("[]", r"run.json must hold a JSON object, got list"),
    ],
)
def test_resume_checks_run_json_before_training(tmp_path, capsys, options, message):
    import re

    run = _stored_run(tmp_path, options)
    code, _, err = _cli(["train", "ppo", "--resume", str(run), "--no-progress", "--devices", "1"], capsys)
    assert code == 2 and len(err.strip().splitlines()) == 1 and re.search(message, err), err
    assert not (run / checkpoint.CHECKPOINT_DIR).exists() and not (run / "eval.json").exists()


def test_metrics_lines_survive_a_torn_last_line(tmp_path):
    path = tmp_path / checkpoint.METRICS_FILE
    path.write_text('{"chunk": 0, "iou": [0.1]}\n{"chunk": 1, "iou": [0.2]}\n{"chunk": 2, "io')
    assert [r["chunk"] for r in checkpoint.read_metrics_lines(path)] == [0, 1]
    path.write_text('{"chunk": 0}\n{"chu\n{"chunk": 2}\n')
    with pytest.raises(ValueError, match=r"metrics.jsonl:2: not a JSON line"):
        checkpoint.read_metrics_lines(path)


@pytest.mark.parametrize(
    "content, message",
    [
        ('{"algorithm": "ppo", ', r"config.json is not valid JSON"),
        ("[1, 2]", r"config.json must hold a JSON object, got list"),
        ('{"algorithm": "ppo", "hidden_size": -3}', r"config.json: hidden_size must be an int >= 1"),
        ('{"algorithm": "nope"}', r"config.json: unknown algorithm 'nope'"),
    ],
)
def test_a_corrupt_config_json_is_named(tmp_path, content, message):
    (tmp_path / checkpoint.CONFIG_FILE).write_text(content)
    with pytest.raises(ValueError, match=message):
        checkpoint.read_config(tmp_path)


def _cli(argv, capsys) -> tuple[int, str, str]:
    from snac_jax.cli import main

    code = main(argv)
    out, err = capsys.readouterr()
    return code, out, err


TINY_FLAGS = [
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


def test_resume_refuses_options_the_run_fixed(tmp_path, capsys):
    from agents.training.config import save_config

    save_config(make_config("ppo", "1d-static-sin", total_steps=128, **TINY), tmp_path / checkpoint.CONFIG_FILE)
    code, _, err = _cli(
        ["train", "ppo", "--resume", str(tmp_path), "--total-steps", "5000", "--task", "1d-static-step"], capsys
    )
    assert code == 2
    assert (
        err.startswith("snac train ppo: error: --resume continues the run as ")
        and "--task, --total-steps cannot change it" in err
    )
    code, _, err = _cli(["train", "dqn", "--resume", str(tmp_path)], capsys)
    assert code == 2 and "holds a ppo run, not dqn" in err


def test_training_banner_and_memory_checks_come_before_any_training(tmp_path, capsys):
    """--total-steps 1 trains one whole update (16 worlds x 8 steps): the banner says 128, not 1.
    Sizes whose memory cannot fit are refused with the estimate before anything is allocated:
    the final evaluation's episodes too, before the training rather than after it."""
    out = tmp_path / "a"
    code, _, err = _cli(
        ["train", "ppo", "--total-steps", "1", *TINY_FLAGS, "--out", str(out), "--eval-episodes", "1000000000000"],
        capsys,
    )
    assert "128 env steps (total_steps 1 rounded to whole updates of 128) x 1 seed(s)" in err
    assert code == 2 and "snac train ppo: error: 1,000,000,000,000 episodes at once needs about" in err
    huge = [f if f != "16" else "1000000000" for f in TINY_FLAGS]
    code, _, err = _cli(["train", "ppo", "--total-steps", "1", *huge, "--out", str(out)], capsys)
    assert code == 2 and "snac train ppo: error: training 1 seed(s) x 1,000,000,000 worlds needs about" in err
    assert "more than the" in err and not out.exists()


@pytest.mark.slow  # a whole CLI run with its evaluations, then eval and render of it: ~45 s on 2 cores
def test_a_cli_run_keeps_its_options_and_its_files_are_readable(tmp_path, capsys, monkeypatch):
    """One tiny `snac train` run with a short step limit and few evaluation episodes, then:
    its files are 0644 under umask 022; a resume evaluates with the run's own options (not the
    protocol's 500 episodes at the task's step limit); `snac eval --checkpoint` scores it on its
    step limit and refuses another task before loading it; `snac render --checkpoint` draws it."""
    import imageio.v3 as iio

    old_umask = os.umask(0o022)
    try:
        run = tmp_path / "run"
        code, out, err = _cli(
            [
                "train",
                "ppo",
                "--total-steps",
                "256",
                "--chunks",
                "2",
                *TINY_FLAGS,
                "--max-steps",
                "40",
                "--eval-episodes",
                "2",
                "--out",
                str(run),
            ],
            capsys,
        )
    finally:
        os.umask(old_umask)
    assert code == 0, err
    for name in ("config.json", "run.json", "metrics.jsonl", "curve.png", "eval.json"):
        assert (run / name).stat().st_mode & 0o777 == 0o644, name
    assert json.loads((run / "run.json").read_text()) == {"eval_episodes": 2, "no_eval": False}
    first = json.loads((run / "eval.json").read_text())["1d-static-sin"]
    assert first["episodes"] == 2 and first["mean_length"] <= 40

    code, out, err = _cli(["train", "ppo", "--resume", str(run), "--no-progress"], capsys)
    assert code == 0, err
    again = json.loads((run / "eval.json").read_text())["1d-static-sin"]
    assert again["episodes"] == 2 and again["mean_length"] <= 40 and again["mean"] == first["mean"]
    assert len(read_metrics(run)) == 2  # one run's chunks, once

    code, out, err = _cli(["eval", "--checkpoint", str(run), "--episodes", "3"], capsys)
    assert code == 0, err
    assert "{'max_steps': 40}" in err and "| 1d-static-sin | 3 |" in out
    monkeypatch.setattr(trained, "load_trained", lambda *a: pytest.fail("the checkpoint was loaded"))
    code, _, err = _cli(["eval", "--checkpoint", str(run), "--task", "1d-static"], capsys)
    assert code == 2 and "trained on '1d-static-sin'; it cannot be evaluated on 1d-static-gauss, 1d-static-step" in err
    monkeypatch.undo()

    gif = tmp_path / "run.gif"
    code, out, err = _cli(
        ["render", "--task", "1d-static-sin", "--checkpoint", str(run), "--out", str(gif), "--max-steps", "12"], capsys
    )
    assert code == 0, err
    assert "1d-static-sin, policy " in out and "final IoU" in out
    assert iio.imread(gif, index=None).shape[0] >= 2


@pytest.mark.slow  # a tiny 2D run, then eval and render of its checkpoint
def test_a_run_with_switches_is_scored_and_drawn_with_them(tmp_path, capsys):
    """A run trained with `--switches gps=true` (one more input per step) is evaluated, re-scored
    from its checkpoint and rendered in a world with gps; a world without it is refused by name."""
    from snac_jax import make

    run = tmp_path / "run"
    code, out, err = _cli(
        [
            "train",
            "ppo",
            "--task",
            "2d-static-dense",
            "--total-steps",
            "256",
            "--chunks",
            "1",
            *TINY_FLAGS,
            "--switches",
            "gps=true",
            "--max-steps",
            "20",
            "--eval-episodes",
            "2",
            "--out",
            str(run),
        ],
        capsys,
    )
    assert code == 0, err
    assert "{'gps': True, 'max_steps': 20}" in err
    code, out, err = _cli(["eval", "--checkpoint", str(run), "--episodes", "2"], capsys)
    assert code == 0, err
    assert "'gps': True" in err and "| 2d-static-dense | 2 |" in out
    code, out, err = _cli(
        [
            "render",
            "--task",
            "2d-static-dense",
            "--checkpoint",
            str(run),
            "--out",
            str(tmp_path / "run.gif"),
            "--max-steps",
            "6",
        ],
        capsys,
    )
    assert code == 0, err
    env, _ = make("2d-static-dense")
    with pytest.raises(ValueError, match="trained with switches 'gps=true'; build the env with them"):
        trained.checkpoint_policy(env, run)


@pytest.mark.slow
def test_a_run_trained_without_stride_noise_is_refused_in_a_noisy_world(tmp_path):
    """The −uncertainty switch changes `EnvParams` only, not `EnvConfig`: a policy trained with
    strides of one cell must not be scored, silently, in the default world of strides 1-3. The
    check reads the run's config.json alone, before any checkpoint."""
    from agents.training.config import save_config
    from snac_jax import make

    save_config(make_config("ppo", "2d-static-dense", switches="stride_probs=1/0/0", **TINY), tmp_path / "config.json")
    env, _ = make("2d-static-dense")
    with pytest.raises(ValueError, match="trained with switches 'stride_probs=1/0/0'; build the env with them"):
        trained.checkpoint_policy(env, tmp_path)
    with pytest.raises(ValueError, match="no checkpoint"):  # the matching world passes the check
        trained.checkpoint_policy(make("2d-static-dense", stride_probs=(1.0, 0.0, 0.0))[0], tmp_path)


KILLER = textwrap.dedent(
    """
    import json, os, pathlib, signal, sys
    from agents.training import driver
    from agents.training.config import TrainConfig
    from agents.training.registry import config_from_json
    from snac_jax.devices import env_mesh

    out, where, chunk = sys.argv[1], sys.argv[2], int(sys.argv[3])
    config = config_from_json(json.loads(sys.argv[4]))
    die = lambda: os.kill(os.getpid(), signal.SIGKILL)

    if where == "mid-chunk":  # chunk computed, nothing of it written yet
        summarize, seen = driver.summarize_chunk, []
        def hook(metrics):
            if len(seen) == chunk:
                die()
            seen.append(1)
            return summarize(metrics)
        driver.summarize_chunk = hook
    elif where == "metrics-line":  # half of the chunk's metrics line written
        open_path = pathlib.Path.open
        def hook(self, mode="r", *args, **kwargs):
            f = open_path(self, mode, *args, **kwargs)
            if self.name == "metrics.jsonl" and mode == "a" and sum(1 for _ in open_path(self)) == chunk:
                write = f.write
                class Torn:
                    def __enter__(s): return s
                    def __exit__(s, *a): f.close()
                    def write(s, text):
                        write(text[: len(text) // 2]); f.flush(); die()
                return Torn()
            return f
        pathlib.Path.open = hook
    elif where == "checkpoint-write":  # every file of the checkpoint written, its commit (rename) not
        from orbax.checkpoint._src.path import async_path
        rename = async_path.rename
        async def hook(src, dst, *args, **kwargs):
            if pathlib.Path(str(dst)).name == str(chunk):
                die()
            return await rename(src, dst, *args, **kwargs)
        async_path.rename = hook
    driver.train(config, out, progress=False, mesh=env_mesh(1))
    """
)


@pytest.mark.slow  # three killed training subprocesses and their resumes: ~1-2 min on 2 cores
def test_sigkill_at_any_point_then_resume_equals_an_uninterrupted_run(tmp_path):
    """SIGKILL after a chunk is computed, halfway through its metrics line, and while its
    checkpoint is being written (files there, commit not): `resume` ends equal to a run that was
    never interrupted, state and metrics alike."""
    from snac_jax.devices import env_mesh

    config = make_config("ppo", "1d-static-gauss", recurrent=True, total_steps=4 * 16 * 8, chunks=4, **TINY)
    _, straight = train(config, tmp_path / "straight", progress=False, mesh=env_mesh(1))
    expected = [(r["chunk"], r["iou"], r["return"]) for r in read_metrics(tmp_path / "straight")]
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    env.pop("XLA_FLAGS", None)
    for where in ("mid-chunk", "metrics-line", "checkpoint-write"):
        out = tmp_path / where
        done = subprocess.run(
            [sys.executable, "-c", KILLER, str(out), where, "2", json.dumps(config.to_json())],
            capture_output=True,
            text=True,
            env=env,
            timeout=600,
        )
        assert done.returncode == -9, (where, done.stderr[-3000:])  # killed, not finished
        assert checkpoint.latest_chunk(out) == 1, where
        _, resumed = train(config, out, resume=True, progress=False, mesh=env_mesh(1))
        assert _leaves_equal(straight, resumed), where
        assert [(r["chunk"], r["iou"], r["return"]) for r in read_metrics(out)] == expected, where


def test_run_files_are_readable_by_others(tmp_path):
    """Every file of a run goes through `snac_jax.atomic` and gets 0666 less the umask (0644
    under 022), not the 0600 of a bare temporary file."""
    from agents.training.driver import _start_run
    from agents.training.plotting import plot_curve
    from snac_jax.atomic import atomic_write_json

    config = make_config("ppo", "1d-static-sin", total_steps=128, **TINY)
    old_umask = os.umask(0o022)
    try:
        _start_run(config, tmp_path, {"eval_episodes": 2, "no_eval": False})
        records = [{"chunk": 0, "env_steps": 128, "iou": [0.1], "return": [1.0]}]
        plot_curve(records, config.task, "title", tmp_path / "curve.png")
        atomic_write_json(tmp_path / "eval.json", {})
    finally:
        os.umask(old_umask)
    modes = {p.name: p.stat().st_mode & 0o777 for p in tmp_path.iterdir()}
    assert modes == {name: 0o644 for name in ("config.json", "run.json", "metrics.jsonl", "curve.png", "eval.json")}


@pytest.mark.slow  # about 10 s on the 2-core CPU, cold: `pytest -m slow` (CI runs both)
def test_a_run_scored_with_its_own_step_limit_is_shown_without_the_papers_row(tmp_path, capsys):
    """The paper scored the task as defined: a run trained (and so scored) with max_steps 5 has
    no paper row or delta beside it, as `snac eval` of its checkpoint says."""
    argv = ["train", "ppo", *TINY_FLAGS, "--total-steps", "128", "--chunks", "1", "--max-steps", "5"]
    code, out, err = _cli([*argv, "--eval-episodes", "2", "--out", str(tmp_path / "run")], capsys)
    assert code == 0, err
    assert "(no paper row)" in out and "paper row: ppo" not in out
    row = next(line for line in out.splitlines() if line.startswith("| 1d-static-sin |"))
    assert row.split("|")[7:10] == [" — ", " — ", " — "]  # paper mean, paper min, delta


@pytest.mark.slow
def test_a_bit_flipped_checkpoint_is_one_line_of_damage_without_orbaxs_noise(tmp_path):
    """Bytes flipped in a checkpoint's metadata store: the damage is named in one note and the one
    before restores, without orbax's "Metadata file does not exist" warnings (printed on every
    read) or the tracebacks of its abandoned callbacks ("Event loop is closed"), at exit included."""
    script = textwrap.dedent(
        """
        import sys
        from pathlib import Path
        import jax, jax.numpy as jnp
        from agents.training import checkpoint

        run = Path(sys.argv[1])
        for chunk in (0, 1):
            checkpoint.save_state(run, chunk, {"w": jax.random.normal(jax.random.key(chunk), (64, 64))})
        for path in (run / "checkpoints" / "1" / "default" / "d").iterdir():
            data = bytearray(path.read_bytes())
            for i in range(0, len(data), max(1, len(data) // 8)):
                data[i] ^= 0x10
            path.write_bytes(bytes(data))
        chunk, _, notes = checkpoint.restore_latest(run, {"w": jnp.zeros((64, 64))})
        print(chunk, notes, file=sys.stderr)
        """
    )
    done = subprocess.run([sys.executable, "-c", script, str(tmp_path)], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert done.stderr.strip().splitlines() == [done.stderr.strip()], done.stderr[-3000:]
    assert done.stderr.startswith("0 [") and "checkpoint 1 cannot be read" in done.stderr
