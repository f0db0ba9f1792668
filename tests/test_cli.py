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


def test_rollout_refuses_steps_past_a_scans_int32_length(capsys):
    with pytest.raises(SystemExit) as caught:
        main(["rollout", "--steps", "2147483648"])
    err = capsys.readouterr().err
    assert caught.value.code == 2 and "--steps: must be an int in 1..2147483647, got '2147483648'" in err
    assert "Traceback" not in err and "OverflowError" not in err


@pytest.mark.slow
def test_installed_entry_point_runs():
    snac = Path(sys.executable).parent / "snac"  # the console script pip installed
    result = subprocess.run(
        [str(snac), "rollout", "--task", "3d-dynamic-sparse", "--num-envs", "4", "--steps", "50"],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert result.returncode == 0, result.stderr
    assert "env-steps/s" in result.stdout


def test_errors_are_one_line_and_bugs_keep_their_traceback(capsys, monkeypatch):
    """Bad input and unwritable files end with `snac CMD: error: ...` and status 2; any other
    exception is a bug and propagates with its traceback."""
    from snac_jax.cli import rollout

    def broken(args):
        raise ValueError("the message")

    monkeypatch.setattr(rollout, "run", broken)
    assert main(["rollout", "--task", "1d-static-sin"]) == 2
    assert capsys.readouterr().err == "snac rollout: error: the message\n"

    def missing(args):
        raise FileNotFoundError(2, "No such file or directory", "/nowhere/file")

    monkeypatch.setattr(rollout, "run", missing)
    assert main(["rollout"]) == 2
    assert capsys.readouterr().err == "snac rollout: error: No such file or directory: /nowhere/file\n"

    def bug(args):
        raise RuntimeError("a bug")

    monkeypatch.setattr(rollout, "run", bug)
    with pytest.raises(RuntimeError, match="a bug"):
        main(["rollout"])
    monkeypatch.setenv("SNAC_TRACEBACK", "1")
    monkeypatch.setattr(rollout, "run", broken)
    with pytest.raises(ValueError, match="the message"):
        main(["rollout"])


def test_rollout_refuses_a_batch_that_cannot_fit(capsys):
    assert main(["rollout", "--task", "2d-static-dense", "--num-envs", "1000000000", "--steps", "2"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("snac rollout: error: 1,000,000,000 worlds needs about ") and "GiB, more than the " in err
    assert "use fewer worlds" in err and err.count("\n") == 1


@pytest.mark.parametrize(
    "command",
    [
        ["rollout"],
        ["eval", "--policy", "random"],
        ["render", "--task", "1d-static-sin", "--out", "x.gif"],
        ["play", "--task", "1d-static-sin"],
    ],
)
@pytest.mark.parametrize("seed", ["4294967296", "-1", "1e3"])
def test_seeds_must_fit_in_32_bits(command, seed, capsys):
    """`jax.random.key` keeps 32 bits: seed 2**32 would silently repeat seed 0."""
    with pytest.raises(SystemExit) as exit_info:
        main([*command, "--seed", seed])
    assert exit_info.value.code == 2
    assert "must be an int in 0..4294967295" in capsys.readouterr().err


def test_ctrl_c_is_one_line_and_status_130(capsys, monkeypatch):
    """Ctrl-C in any subcommand ends with `snac CMD: interrupted`, not a traceback, and the shell's
    status for SIGINT (128 + 2)."""
    from snac_jax.cli import rollout

    def interrupted(args):
        raise KeyboardInterrupt

    monkeypatch.setattr(rollout, "run", interrupted)
    try:
        code = main(["rollout", "--task", "1d-static-sin"])
    except KeyboardInterrupt:
        pytest.fail("Ctrl-C escaped `snac` as a KeyboardInterrupt (a traceback for the user)")
    assert code == 130
    assert capsys.readouterr().err == "snac rollout: interrupted\n"
