"""Training across processes (hosts): two CPU processes on 127.0.0.1 join through
`jax.distributed` (as `snac train ... --coordinator` does), split the worlds between them, train
PPO for a few updates, and must end with identical parameters and a finite loss."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import textwrap

import numpy as np
import pytest

WORKER = textwrap.dedent(
    """
    import sys
    import jax
    import numpy as np

    process_id, port, out = int(sys.argv[1]), sys.argv[2], sys.argv[3]
    jax.config.update("jax_num_cpu_devices", 1)
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    jax.distributed.initialize(coordinator_address=f"127.0.0.1:{port}", num_processes=2, process_id=process_id)

    from agents.training.driver import train
    from agents.training.registry import make_config
    from agents.training.sharding import host_value

    config = make_config("ppo", "1d-static-sin", total_steps=4 * 8 * 16, num_envs=8, rollout_steps=16,
                         num_minibatches=2, update_epochs=1, hidden_size=16, chunks=2)
    algorithm, state = train(config, out + "/run", progress=False)
    assert jax.device_count() == 2 and jax.local_device_count() == 1
    leaves = jax.tree.leaves(host_value(state.params))
    np.savez(f"{out}/params{process_id}.npz", *leaves)
    """
)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_two_processes_train_to_identical_parameters(tmp_path):
    port = str(_free_port())
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    workers = [
        subprocess.Popen(
            [sys.executable, "-c", WORKER, str(i), port, str(tmp_path)],
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        for i in (0, 1)
    ]
    outputs = [w.communicate(timeout=540)[0] for w in workers]
    for worker, output in zip(workers, outputs):
        assert worker.returncode == 0, output[-3000:]
    first, second = (np.load(tmp_path / f"params{i}.npz") for i in (0, 1))
    assert len(first.files) == len(second.files) > 0
    for name in first.files:
        np.testing.assert_array_equal(first[name], second[name])
    records = [json.loads(line) for line in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    assert [r["chunk"] for r in records] == [0, 1]  # one writer: no line twice
    assert all(np.isfinite(r["loss"]).all() for r in records)


@pytest.mark.parametrize(
    "argv,message",
    [
        (["train", "ppo", "--num-processes", "2"], "go with --coordinator"),
        (["train", "ppo", "--coordinator", "127.0.0.1:1", "--process-id", "0"], "needs --num-processes"),
        (
            ["train", "ppo", "--coordinator", "127.0.0.1:1", "--num-processes", "2", "--process-id", "2"],
            r"must be in 0\.\.1",
        ),
    ],
)
def test_process_flags_are_checked_before_joining(argv, message):
    from snac_jax.cli import join_processes_from

    with pytest.raises(SystemExit, match=message):
        join_processes_from(argv)
