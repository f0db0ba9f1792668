"""`bench/compile_profile.py`: the plugin counts each test's compiled programs, and the summary
reads them back."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

TINY = """
import jax
import jax.numpy as jnp
import numpy as np


def test_compiles_two_programs():
    jax.jit(lambda x: x * 2.0)(np.ones(3, np.float32)).block_until_ready()
    jax.jit(lambda x: jnp.sin(x) + 1.0)(np.ones(5, np.float32)).block_until_ready()


def test_compiles_nothing():
    assert 1 + 1 == 2
"""


@pytest.mark.slow
def test_each_test_gets_its_own_programs_and_the_summary_reads_them(tmp_path):
    (tmp_path / "test_tiny.py").write_text(TINY)
    out = tmp_path / "profile"
    env = {
        # one process (compile-main.json), whatever the outer run's workers or options
        **{k: v for k, v in os.environ.items() if not k.startswith(("PYTEST_XDIST", "PYTEST_ADDOPTS"))},
        "PYTHONPATH": str(ROOT),
        "COMPILE_PROFILE_OUT": str(out),
        "JAX_COMPILATION_CACHE_DIR": str(tmp_path / "cache"),  # cold: every program compiles
        "JAX_PLATFORMS": "cpu",
    }
    command = [
        sys.executable,
        "-m",
        "pytest",
        "-p",
        "bench.compile_profile",
        "-q",
        "-o",
        "addopts=",
        "-p",
        "no:cacheprovider",
    ]
    done = subprocess.run([*command, "test_tiny.py"], cwd=tmp_path, env=env, capture_output=True, text=True)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    rows = json.loads((out / "compile-main.json").read_text())
    assert rows["test_tiny.py::test_compiles_two_programs"]["programs"] == 2
    assert rows["test_tiny.py::test_compiles_two_programs"]["compile_s"] > 0
    assert "test_tiny.py::test_compiles_nothing" not in rows
    sys.path.insert(0, str(ROOT))
    from bench.compile_profile import summary

    text = summary(out)
    assert "| test_tiny.py | 2 |" in text and "| test_tiny.py::test_compiles_two_programs | 2 |" in text


def test_the_plugin_needs_its_output_folder_and_the_summary_its_files(tmp_path):
    env = {k: v for k, v in os.environ.items() if k != "COMPILE_PROFILE_OUT"} | {"PYTHONPATH": str(ROOT)}
    (tmp_path / "test_none.py").write_text("def test_x():\n    pass\n")
    command = [sys.executable, "-m", "pytest", "-p", "bench.compile_profile", "-q", "-o", "addopts=", "test_none.py"]
    done = subprocess.run(command, cwd=tmp_path, env=env, capture_output=True, text=True)
    assert done.returncode != 0 and "COMPILE_PROFILE_OUT=DIR" in done.stdout + done.stderr
    sys.path.insert(0, str(ROOT))
    from bench.compile_profile import summary

    with pytest.raises(ValueError, match="no compile-"):
        summary(tmp_path)
