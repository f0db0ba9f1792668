"""The `snac` command line, end to end on tiny budgets."""

import subprocess
import sys
from pathlib import Path

import pytest

from snac_jax.cli import main


def test_rollout_prints_throughput_and_episode_iou(capsys):
    assert main(["rollout", "--task", "1d-static-sin", "--num-envs", "8", "--steps", "760", "--seed", "3"]) == 0
    out = capsys.readouterr().out
    assert "env-steps/s" in out and "compile" in out
    assert "episodes ended: 8;" in out  # 750-step episodes: each of the 8 envs ends once
    mean = float(out.split("final IoU mean ")[1].split(",")[0])
    assert 0.0 < mean < 1.0


def test_rollout_rejects_unknown_task(capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["rollout", "--task", "2d-static"])
    assert exit_info.value.code == 2
    assert "allowed: 1d-static-sin" in capsys.readouterr().err


def test_rollout_rejects_non_positive_sizes(capsys):
    with pytest.raises(SystemExit):
        main(["rollout", "--num-envs", "0"])
    assert "must be an int >= 1" in capsys.readouterr().err


def test_installed_entry_point_runs():
    snac = Path(sys.executable).parent / "snac"  # the console script pip installed
    result = subprocess.run(
        [str(snac), "rollout", "--task", "3d-dynamic-sparse", "--num-envs", "4", "--steps", "50"],
        capture_output=True, text=True, timeout=300,
    )
    assert result.returncode == 0, result.stderr
    assert "env-steps/s" in result.stdout
