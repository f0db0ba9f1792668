"""The environment installs and runs without the extras (pyproject.toml: `[train]`, `[render]`,
`[play]`, `[gymnasium]`, `[wandb]`), and a `snac` command whose extra is missing says in one line
which one to install."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import textwrap
import tomllib
from pathlib import Path

import pytest

from snac_jax import plugins

ROOT = Path(__file__).parents[1]
ENV = {**os.environ, "JAX_PLATFORMS": "cpu"}


def _snac_without(modules: list[str], argv: list[str]) -> subprocess.CompletedProcess:
    """`snac ARGV` in a fresh interpreter where importing any of `modules` fails as if it were
    not installed."""
    code = textwrap.dedent(f"""
        import sys
        for name in {modules!r}:
            sys.modules[name] = None  # `import name` now raises ModuleNotFoundError
        from snac_jax.cli import main
        sys.exit(main({argv!r}))
    """)
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=ENV, cwd=ROOT, timeout=300)


def test_every_extra_module_maps_to_the_extra_pyproject_gives_it():
    optional = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    for module, extra in (
        ("optax", "train"),
        ("orbax", "train"),
        ("flashbax", "train"),
        ("distrax", "train"),
        ("scipy", "train"),
        ("tqdm", "train"),
        ("tensorboardX", "train"),
        ("pygame", "play"),
        ("imageio", "render"),
        ("wandb", "wandb"),
        ("gymnasium", "gymnasium"),
    ):
        assert plugins.extra_for(module) == extra, module
        assert any(r.lower().startswith(plugins._DISTRIBUTION_OF.get(module, module).lower()) for r in optional[extra])
    assert plugins.extra_for("jax") is None and plugins.extra_for("no_such_module") is None


def test_the_environment_depends_on_jax_chex_flax_gymnax_and_numpy_only():
    required = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["dependencies"]
    names = {plugins._normalise(r.split(">")[0].split("<")[0].split("=")[0].split(";")[0].strip()) for r in required}
    assert names == {"jax", "chex", "flax", "gymnax", "numpy", "six"}  # six: gymnax imports it undeclared


@pytest.mark.slow  # over 10 s on the 2-core CPU: `pytest -m slow` (CI runs both)
def test_train_without_its_extra_names_the_extra_in_one_line():
    result = _snac_without(["distrax", "optax"], ["train", "ppo", "--task", "1d-static-sin"])
    assert result.returncode == 2, result.stderr[-2000:]
    assert result.stderr.strip().splitlines() == [
        'snac train: error: this needs the [train] extra: pip install "snac-jax[train]"'
    ]
    help_text = _snac_without(["distrax"], ["train", "--help"])
    assert help_text.returncode == 2 and "[train] extra" in help_text.stderr
    listing = _snac_without(["distrax"], ["--help"])  # the other commands stay, the missing one is listed
    assert listing.returncode == 0 and "rollout" in listing.stdout and "train" in listing.stdout


@pytest.mark.slow
def test_play_without_pygame_names_the_play_extra():
    result = _snac_without(["pygame"], ["play", "--task", "1d-static-sin"])
    assert result.returncode == 2, result.stderr[-2000:]
    assert (
        result.stderr.strip().splitlines()[-1]
        == 'snac play: error: this needs the [play] extra: pip install "snac-jax[play]"'
    )


@pytest.mark.slow
def test_a_missing_module_that_no_extra_provides_is_a_bug_with_its_traceback():
    result = _snac_without(["agents.learners.ppo"], ["train", "ppo"])
    assert result.returncode == 1 and "Traceback" in result.stderr


@pytest.mark.slow
def test_a_fresh_install_without_extras_makes_and_steps_every_task(tmp_path):
    source = tmp_path / "src"
    source.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(ROOT / name, source / name)
    for package in ("snac_jax", "agents"):
        shutil.copytree(ROOT / package, source / package, ignore=shutil.ignore_patterns("__pycache__"))
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, timeout=300)
    python = venv / "bin" / "python"
    install = subprocess.run(
        [str(python), "-m", "pip", "install", "--quiet", str(source)], capture_output=True, text=True, timeout=1800
    )
    assert install.returncode == 0, install.stderr[-3000:]
    check = textwrap.dedent("""
        import importlib.util, sys
        import jax, snac_jax
        for task in snac_jax.TASKS:
            env, params = snac_jax.make(task, **({"design_bank_size": 2} if "dynamic" in task else {}))
            obs, state = env.reset(jax.random.key(0), params)
            obs, state, *_ = env.step(jax.random.key(1), state, 0, params)
            assert obs.shape == env.observation_space(params).shape, task
        installed = [m for m in ("pygame", "flashbax", "distrax", "imageio", "tqdm") if importlib.util.find_spec(m)]
        imported = sorted({m.split(".")[0] for m in sys.modules} & {"optax", "orbax", "flashbax", "distrax", "pygame",
                                                                     "imageio", "tqdm", "agents"})
        print("installed:", installed, "imported:", imported)
    """)
    run = subprocess.run([str(python), "-c", check], capture_output=True, text=True, env=ENV, cwd=tmp_path, timeout=600)
    assert run.returncode == 0, run.stderr[-3000:]
    # optax and orbax-checkpoint come with flax, which gymnax needs: installed, but never imported.
    assert "installed: [] imported: []" in run.stdout, run.stdout
    train = subprocess.run(
        [str(venv / "bin" / "snac"), "train", "ppo"], capture_output=True, text=True, env=ENV, cwd=tmp_path, timeout=300
    )
    assert train.returncode == 2
    assert train.stderr.strip().splitlines() == [
        'snac train: error: this needs the [train] extra: pip install "snac-jax[train]"'
    ]
