"""`snac_jax.gymnasium`: Gymnasium's checker, seeding, truncation and same-step autoreset with the
true final observation, the batched `make_vec`, rendering, and (with SB3 installed) SB3 PPO."""

from __future__ import annotations

import json
import subprocess
import sys
import warnings
from pathlib import Path

import gymnasium
import jax
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from gymnasium.vector import AutoresetMode

import snac_jax
import snac_jax.gymnasium as snac_gym

ID_1D = "SNAC/1d-static-sin-v0"
ID_2D = "SNAC/2d-static-dense-v0"


def test_every_task_is_registered():
    for task in snac_jax.TASKS:
        spec = gymnasium.spec(f"SNAC/{task}-v0")
        assert spec.kwargs == {"task_id": task, "registered_task_id": task}
        assert spec.vector_entry_point is not None
        assert spec.max_episode_steps is None  # the env truncates at its own step limit


@pytest.mark.slow
def test_import_snac_jax_leaves_gymnasium_module_out():
    code = "import sys, snac_jax; snac_jax.make('1d-static-sin'); assert 'snac_jax.gymnasium' not in sys.modules"
    subprocess.run([sys.executable, "-c", code], check=True, timeout=300)


@pytest.mark.slow
@pytest.mark.parametrize(
    ("env_id", "overrides"),
    [
        (ID_1D, {}),
        (ID_2D, {"gps": True, "max_steps": 50}),
        ("SNAC/3d-dynamic-sparse-v0", {"landmarks": 4, "design_bank_size": 8}),
    ],
)
def test_check_env_passes_without_warnings(env_id, overrides):
    env = gymnasium.make(env_id, **overrides)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(env.unwrapped)
    assert [str(w.message) for w in caught] == []
    env.close()


def test_spaces_are_the_gymnax_bounds_as_numpy():
    env = gymnasium.make(ID_2D, gps=True, landmarks=True, max_steps=77)
    jax_env, params = env.unwrapped.jax_env, env.unwrapped.env_params
    gymnax_space = jax_env.observation_space(params)
    space = env.observation_space
    assert isinstance(space, gymnasium.spaces.Box) and space.dtype == np.float32
    assert isinstance(space.low, np.ndarray) and isinstance(space.high, np.ndarray)
    np.testing.assert_array_equal(space.low, np.asarray(gymnax_space.low))
    np.testing.assert_array_equal(space.high, np.asarray(gymnax_space.high))
    layout = jax_env.observation_layout
    assert space.high[layout.time] == 77 and space.high[layout.window].max() == 1
    assert env.action_space == gymnasium.spaces.Discrete(5)


def test_make_passes_overrides_and_rejects_unknown_ones():
    env = gymnasium.make(ID_1D, gps=True, max_steps=7)
    config = env.unwrapped.jax_env.config
    assert config.gps and int(env.unwrapped.env_params.max_steps_in_episode) == 7
    assert env.observation_space.shape == (8,)  # window 5, N_b, N_s, position
    with pytest.raises(ValueError, match="unknown override"):
        gymnasium.make(ID_1D, not_an_override=1)


def test_landmark_action_reaches_the_gymnasium_action_space():
    env = gymnasium.make("SNAC/2d-static-sparse-v0", landmark_action=4)
    assert env.action_space.n == 6  # four moves, the drop, the placement (SPEC §14)
    env.reset(seed=0)
    obs, *_ = env.step(5)
    assert obs[24] == -2.0  # the window's centre: the robot's own cell holds the new landmark


def rollout(env, seed, num_steps, action_seed=0):
    rng = np.random.default_rng(action_seed)
    observations = [env.reset(seed=seed)[0]]
    rewards, infos = [], []
    for _ in range(num_steps):
        obs, reward, terminated, truncated, info = env.step(int(rng.integers(env.action_space.n)))
        observations.append(obs)
        rewards.append(reward)
        infos.append(info)
        if terminated or truncated:
            observations.append(env.reset()[0])
    return np.stack(observations), np.asarray(rewards), infos


def test_seeded_reset_is_reproducible():
    env = gymnasium.make("SNAC/2d-dynamic-dense-v0", design_bank_size=64, max_steps=15)
    first = rollout(env, seed=3, num_steps=40)
    again = rollout(env, seed=3, num_steps=40)
    other = rollout(env, seed=4, num_steps=40)
    np.testing.assert_array_equal(first[0], again[0])
    np.testing.assert_array_equal(first[1], again[1])
    assert first[2] == again[2]
    assert [i["stride"] for i in first[2]] != [i["stride"] for i in other[2]]
    fresh = gymnasium.make("SNAC/2d-dynamic-dense-v0", design_bank_size=64, max_steps=15)
    np.testing.assert_array_equal(rollout(fresh, seed=3, num_steps=40)[0], first[0])
    strides = {seed: [i["stride"] for i in rollout(env, seed=seed, num_steps=40)[2]] for seed in (0, 2**32, 2**40)}
    assert len({tuple(s) for s in strides.values()}) == 3  # large seeds are not truncated to 32 bits


def test_single_env_truncates_with_the_final_observation_and_waits_for_reset():
    env = gymnasium.make(ID_1D, max_steps=5)
    layout = env.unwrapped.jax_env.observation_layout
    obs, info = env.reset(seed=0)
    assert info == {} and obs[layout.time] == 0
    actions = [2, 1, 2, 2, 0]  # three drops: a 1D drop always lands
    for t, action in enumerate(actions, start=1):
        obs, reward, terminated, truncated, info = env.step(action)
        assert not terminated
        assert truncated == (t == 5)
        assert obs[layout.time] == t  # never the next episode's first observation
    assert obs[layout.bricks_used] == 3
    assert set(info) == {"iou", "stride"} and 0 < info["iou"] <= 1 and info["stride"] in (1, 2, 3)
    obs, _ = env.reset()
    assert obs[layout.time] == 0 and obs[layout.bricks_used] == 0


def test_reset_option_design_index_pins_a_design():
    env = gymnasium.make("SNAC/1d-dynamic-v0", design_bank_size=8)
    params = env.unwrapped.env_params
    for index in (0, 5):
        env.reset(seed=0, options={"design_index": index})
        np.testing.assert_array_equal(np.asarray(env.unwrapped.state.design), np.asarray(params.designs[index]))
    with pytest.raises(ValueError, match="design_index"):
        env.reset(options={"design_index": 8})
    with pytest.raises(ValueError, match="unknown reset option"):
        env.reset(options={"seed": 1})


def test_make_vec_is_the_batched_vector_env():
    envs = gymnasium.make_vec(ID_2D, num_envs=1024)
    vector = envs.unwrapped
    assert type(vector) is snac_gym.SNACVectorEnv and not hasattr(vector, "envs")
    assert envs.metadata["autoreset_mode"] == AutoresetMode.SAME_STEP
    assert envs.num_envs == 1024
    size = vector.single_observation_space.shape[0]
    assert envs.observation_space.shape == (1024, size)
    assert envs.action_space == gymnasium.spaces.MultiDiscrete([5] * 1024)
    obs, info = envs.reset(seed=0)
    assert isinstance(obs, np.ndarray) and obs.shape == (1024, size) and obs.dtype == np.float32
    actions = envs.action_space.sample()
    obs, reward, terminated, truncated, info = envs.step(actions)
    for array, dtype in ((obs, np.float32), (reward, np.float32), (terminated, np.bool_), (truncated, np.bool_)):
        assert isinstance(array, np.ndarray) and array.dtype == dtype and array.shape[0] == 1024
    assert obs in envs.observation_space
    assert vector.states.grid.shape == (1024, *vector.jax_env.config.grid_shape)
    assert len(np.unique(info["stride"])) == 3  # the worlds draw their own strides
    envs.close()


@pytest.mark.slow
def test_vector_env_seeding_is_reproducible():
    def run(seed):
        envs = gymnasium.make_vec("SNAC/2d-dynamic-sparse-v0", num_envs=16, design_bank_size=64, max_steps=10)
        rng = np.random.default_rng(0)
        out = [envs.reset(seed=seed)[0]]
        for _ in range(25):
            step = envs.step(rng.integers(0, 5, size=16))
            out += [step[0], step[1], step[3]]
        return out

    first, again, other = run(7), run(7), run(8)
    for a, b in zip(first, again):
        np.testing.assert_array_equal(a, b)
    assert not np.array_equal(first[0], other[0])  # the designs drawn at reset differ


@pytest.mark.slow
def test_vector_env_steps_the_same_worlds_whichever_reset_strategy():
    def run(reset):
        envs = gymnasium.make_vec(
            "SNAC/3d-dynamic-dense-v0", num_envs=12, design_bank_size=16, max_steps=15, reset=reset
        )
        rng = np.random.default_rng(3)
        out = [envs.reset(seed=1)[0]]
        for _ in range(40):
            step = envs.step(rng.integers(0, envs.single_action_space.n, size=12))
            out += [step[0], step[1], step[2], step[3]]
        return out

    loop, select = run("loop"), run("select")
    for a, b in zip(loop, select):
        np.testing.assert_array_equal(a, b)
    assert sum(int(done.sum()) for done in loop[3::4]) >= 12  # the worlds reset along the way
    assert snac_gym.SNACVectorEnv("1d-static-sin", 2).reset_strategy == (
        "loop" if jax.default_backend() == "cpu" else "select"
    )
    with pytest.raises(ValueError, match="reset must be one of auto, loop, select"):
        snac_gym.SNACVectorEnv("1d-static-sin", 2, reset="vmap")


def test_vector_env_same_step_autoreset_at_truncation_keeps_the_true_final_observation():
    num_envs = 6
    envs = gymnasium.make_vec(ID_1D, num_envs=num_envs, max_steps=5)
    layout = envs.unwrapped.jax_env.observation_layout
    space = envs.unwrapped.single_observation_space
    first, _ = envs.reset(seed=0)
    rng = np.random.default_rng(0)
    drops = np.zeros(num_envs, int)
    for t in range(1, 6):
        actions = rng.integers(0, 3, size=num_envs)
        drops += actions == 2
        obs, reward, terminated, truncated, info = envs.step(actions)
        assert not terminated.any()
        if t < 5:
            assert not truncated.any() and "final_obs" not in info
            np.testing.assert_array_equal(obs[:, layout.time], t)
            assert info["_iou"].all()
    assert truncated.all()
    assert info["_final_obs"].all() and info["_final_info"].all()
    final = np.stack(info["final_obs"])
    assert final.shape == (num_envs, layout.size) and all(row in space for row in final)
    np.testing.assert_array_equal(final[:, layout.time], 5)
    np.testing.assert_array_equal(final[:, layout.bricks_used], drops)  # the ended episodes' own counts
    assert (info["final_info"]["iou"] > 0).any() and info["final_info"]["_iou"].all()
    assert not info["_iou"].any()
    # The returned observations already start the next episodes (a static task's reset is fixed).
    np.testing.assert_array_equal(obs, first)
    obs, *_ = envs.step(rng.integers(0, 3, size=num_envs))
    np.testing.assert_array_equal(obs[:, layout.time], 1)


def test_vector_env_same_step_autoreset_at_termination():
    envs = gymnasium.make_vec("SNAC/2d-static-sparse-v0", num_envs=3)
    vector = envs.unwrapped
    budget = int(vector.env_params.design_max_bricks[0])
    layout = vector.jax_env.observation_layout
    envs.reset(seed=1)
    drop = np.full(3, 4)
    for _ in range(budget - 1):
        obs, reward, terminated, truncated, info = envs.step(drop)
        assert not terminated.any() and not truncated.any()
    obs, reward, terminated, truncated, info = envs.step(drop)
    assert terminated.all() and not truncated.any()
    final = np.stack(info["final_obs"])
    np.testing.assert_array_equal(final[:, layout.bricks_used], budget)
    np.testing.assert_array_equal(final[:, layout.time], budget)
    np.testing.assert_array_equal(obs[:, layout.counters], 0)


def test_vector_env_rejects_bad_actions():
    envs = gymnasium.make_vec(ID_1D, num_envs=2)
    envs.reset(seed=0)
    with pytest.raises(ValueError):
        envs.step(np.array([0, 3]))
    with pytest.raises(ValueError):
        envs.step(np.array([0, 1, 2]))


def test_render_rgb_array():
    env = gymnasium.make(ID_2D, render_mode="rgb_array")
    env.reset(seed=0)
    env.step(4)
    frame = env.render()
    assert isinstance(frame, np.ndarray) and frame.dtype == np.uint8 and frame.ndim == 3 and frame.shape[2] == 3
    np.testing.assert_array_equal(frame, env.unwrapped.jax_env.render(env.unwrapped.state))

    envs = gymnasium.make_vec(ID_1D, num_envs=2, render_mode="rgb_array")
    envs.reset(seed=0)
    frames = envs.render()
    assert len(frames) == 2 and all(f.dtype == np.uint8 and f.ndim == 3 and f.shape[2] == 3 for f in frames)

    with pytest.raises(ValueError, match="render_mode"):
        snac_gym.SNACGymEnv("2d-static-dense", render_mode="ansi")


@pytest.mark.slow  # over 10 s on the 2-core CPU: `pytest -m slow` (CI runs both)
def test_throughput_bench_writes_only_its_results(tmp_path):
    script = Path(__file__).resolve().parent.parent / "bench" / "gymnasium_throughput.py"
    args = [
        "--out",
        str(tmp_path / "out"),
        "--task",
        "1d-static-sin",
        "--num-envs",
        "1",
        "2",
        "--steps",
        "3",
        "--repeats",
        "1",
    ]
    subprocess.run([sys.executable, str(script), *args], check=True, timeout=300, cwd=tmp_path, capture_output=True)
    assert sorted(p.name for p in tmp_path.rglob("*")) == [
        "gymnasium_throughput.json",
        "gymnasium_throughput.md",
        "out",
    ]
    result = json.loads((tmp_path / "out" / "gymnasium_throughput.json").read_text())
    assert [row["num_envs"] for row in result["rows"]] == [1, 2]
    for row in result["rows"]:
        assert row["vector_env_steps_per_s"] > 0 and row["jit_step_steps_per_s"] > 0 and row["jit_scan_steps_per_s"] > 0
    assert "| 2 |" in (tmp_path / "out" / "gymnasium_throughput.md").read_text()


@pytest.mark.sb3
def test_sb3_ppo_trains_on_1d_static_sin():
    sb3 = pytest.importorskip("stable_baselines3")
    from stable_baselines3.common.env_checker import check_env as sb3_check_env

    env = gymnasium.make(ID_1D, max_steps=100)
    sb3_check_env(env.unwrapped)
    model = sb3.PPO("MlpPolicy", env, n_steps=512, batch_size=64, n_epochs=2, seed=0, device="cpu", verbose=0)
    model.learn(total_timesteps=4096)
    episodes = list(model.ep_info_buffer)
    assert len(episodes) >= 30 and all(e["l"] == 100 for e in episodes)
    assert all(np.isfinite(e["r"]) for e in episodes)
    obs, _ = env.reset(seed=0)
    action, _ = model.predict(obs, deterministic=True)
    assert env.action_space.contains(int(action))


def test_an_id_refuses_a_task_id_of_another_task():
    """`SNAC/<task>-v0` always builds <task>: a `task_id` naming another task would put a 2D world
    under a 1D id (and into every record that names the id)."""
    for make in (
        gymnasium.make,
        lambda *a, **k: gymnasium.make_vec(*a, num_envs=2, **k),
        lambda *a, **k: gymnasium.make_vec(*a, num_envs=2, vectorization_mode="sync", **k),
    ):
        with pytest.raises(
            ValueError,
            match=r"SNAC/1d-static-sin-v0 is the task 1d-static-sin, not task_id="
            r"'2d-static-dense': make 'SNAC/2d-static-dense-v0'",
        ):
            make(ID_1D, task_id="2d-static-dense")
    env = gymnasium.make(ID_1D, task_id="1d-static-sin")  # naming the id's own task is harmless
    assert env.unwrapped.jax_env.config.task_id == "1d-static-sin"
    again = gymnasium.make(env.spec)  # the spec the env records builds the same task
    assert again.unwrapped.task_id == "1d-static-sin"
    assert snac_gym.SNACGymEnv("2d-static-dense").task_id == "2d-static-dense"  # the class itself takes any task


@pytest.mark.parametrize("max_steps", [5, 400])
def test_the_single_env_refuses_to_step_an_ended_episode(max_steps):
    """After `terminated or truncated` the env waits for `reset()` (time, bricks and IoU stay those
    of the episode's end), as Gymnasium's `ResetNeeded` says for a step before any reset."""
    env = gymnasium.make("SNAC/2d-static-sparse-v0", max_steps=max_steps)
    layout = env.unwrapped.jax_env.observation_layout
    env.reset(seed=0)
    done, steps = False, 0
    while not done:
        obs, _, terminated, truncated, info = env.step(4)  # drops: out of bricks, or the step limit first
        done, steps = terminated or truncated, steps + 1
    assert (truncated, steps) == ((True, 5) if max_steps == 5 else (False, int(obs[layout.bricks_used])))
    state = env.unwrapped.state
    for action in (4, 0):
        with pytest.raises(
            gymnasium.error.ResetNeeded, match=r"the episode ended \((terminated|truncated)\): call reset\(\)"
        ):
            env.step(action)
    assert env.unwrapped.state is state  # nothing moved: the ended episode's time, bricks and IoU
    obs, _ = env.reset()
    assert obs[layout.time] == 0
    env.step(4)


def test_the_single_env_refuses_a_bool_as_an_action():
    env = gymnasium.make("SNAC/1d-static-sin-v0")
    env.reset(seed=0)
    for action in (True, np.bool_(False)):
        with pytest.raises(ValueError, match="action must be an int in 0..2"):
            env.step(action)
    env.step(np.int64(1))  # a NumPy int is an action
