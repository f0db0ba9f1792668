"""`snac table` never loses or fakes a result: a second process on a runs directory in use is
refused, a runner deletes and overwrites nothing it did not make, a cell named twice runs once, and
`--report` refuses damaged cells, impossible scores and links instead of publishing or following
them (and writes nothing with `--dry-run`)."""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

from agents.table.presets import load_presets
from agents.training import checkpoint
from tests.table_cells import raw_copy_text, unpack_raw, write_cell

PRESETS = load_presets()
ROOT = Path(__file__).resolve().parents[1]
ONE_CELL = ["--preset", "smoke", "--algorithms", "ppo", "--tasks", "1d-static-sin", "--no-progress"]


def _run_cli(argv: list[str]) -> int:
    from agents.table import cli

    parser = argparse.ArgumentParser()
    cli.add_parser(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["table", *argv])
    return args.func(args)


def _main(argv: list[str], capsys) -> tuple[int, str]:
    """`snac table ARGV` as the command line runs it: exit status and stderr."""
    from snac_jax.cli import main

    code = main(["table", *argv])
    return code, capsys.readouterr().err


def _tree(root: Path) -> dict[str, bytes]:
    return {p.relative_to(root).as_posix(): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.fixture
def no_training(monkeypatch):
    """Fail any test that reaches training: these cases must be refused or skipped before it."""
    import agents.training.driver as driver

    def refuse(*args, **kwargs):
        raise AssertionError("trained")

    monkeypatch.setattr(driver, "train", refuse)


class _Holder:
    """Another process holding `directory/.lock`, as a running `snac table` or `snac train` does."""

    def __init__(self, directory: Path):
        directory.mkdir(parents=True, exist_ok=True)
        self.process = subprocess.Popen(
            [
                sys.executable,
                "-c",
                "import fcntl, sys, time; f = open(sys.argv[1], 'a+'); fcntl.flock(f, fcntl.LOCK_EX); "
                "f.truncate(0); f.write('process 4242'); f.flush(); print('locked', flush=True); time.sleep(120)",
                str(directory / checkpoint.LOCK_FILE),
            ],
            stdout=subprocess.PIPE,
            text=True,
        )
        assert self.process.stdout.readline().strip() == "locked"

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.process.kill()
        self.process.wait()


# --- two runners, one runs directory -------------------------------------------------------------


def test_a_second_table_run_is_refused_before_it_touches_a_cell(tmp_path, no_training):
    """The first process holds the preset's folder (and its cell, in its first chunk): the second
    is refused in one line, and the first's cell (config, metrics, lock) is left as it was."""
    from agents.table.plan import make_plan
    from agents.training.config import save_config

    runs = tmp_path / "runs"
    [cell] = make_plan(PRESETS["smoke"], ["ppo"], ["1d-static-sin"], None, runs)
    cell.directory.mkdir(parents=True)
    save_config(cell.config, cell.directory / checkpoint.CONFIG_FILE)
    (cell.directory / checkpoint.METRICS_FILE).write_text("")
    with _Holder(cell.directory):
        before = _tree(cell.directory)
        with _Holder(runs / "smoke"):
            with pytest.raises(
                ValueError, match=r"smoke is in use by process 4242: one run directory takes one process"
            ):
                _run_cli([*ONE_CELL, "--runs-dir", str(runs)])
        # The preset's folder free, the cell still held (a `snac train --resume` on it, say).
        with pytest.raises(ValueError, match=r"1d-static-sin is in use by process 4242"):
            _run_cli([*ONE_CELL, "--runs-dir", str(runs)])
        assert _tree(cell.directory) == before


@pytest.mark.slow  # one smoke cell trained and evaluated in a subprocess (~1 min on a loaded 2-core CPU)
def test_two_table_processes_the_second_refused_the_first_finishes_a_clean_cell(tmp_path):
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "PYTHONPATH": str(ROOT)}
    argv = [sys.executable, "-m", "snac_jax.cli", "table", *ONE_CELL, "--runs-dir", str(tmp_path / "runs")]
    first = subprocess.Popen(argv, env=env, cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        for _ in range(600):  # until the first holds the preset's folder
            try:
                checkpoint.check_lock_file(tmp_path / "runs" / "smoke")
            except ValueError:
                break
            time.sleep(0.1)
        second = subprocess.run(argv, env=env, cwd=tmp_path, capture_output=True, text=True, timeout=300)
        out, err = first.communicate(timeout=900)
    finally:
        first.kill()
    assert second.returncode == 2 and "Traceback" not in second.stderr
    assert (
        second.stderr.strip().splitlines()[-1].startswith("snac table: error: ")
        and "is in use by process" in second.stderr
    )
    assert first.returncode == 0, err[-2000:]
    cell = tmp_path / "runs" / "smoke" / "ppo" / "1d-static-sin"
    assert [r["chunk"] for r in checkpoint.read_metrics_lines(cell / checkpoint.METRICS_FILE)] == [0, 1, 2, 3]
    assert len(json.loads((cell / "eval.json").read_text())) == 2


# --- a runner deletes nothing it did not make -----------------------------------------------------


def test_a_cell_directory_holding_another_runs_files_is_refused_not_deleted(tmp_path, no_training):
    """A directory holding files that are not this cell's (a config.json of its own, no cell.json,
    no checkpoint): the plan refuses the cell, naming it, before anything runs."""
    from agents.table import run as table_run
    from agents.table.plan import make_plan

    runs = tmp_path / "runs"
    mine = runs / "smoke" / "ppo" / "1d-static-sin"
    mine.mkdir(parents=True)
    (mine / "config.json").write_text('{"mine": true}\n')
    before = _tree(runs)
    with pytest.raises(
        ValueError,
        match=r"1d-static-sin holds files that no start of this cell left there \(config.json"
        r"\) and no checkpoint; the table deletes nothing it did not make: move",
    ):
        table_run.run_cells(make_plan(PRESETS["smoke"], ["ppo"], ["1d-static-sin"], None, runs), progress=False)
    with pytest.raises(ValueError, match="deletes nothing it did not make"):
        _run_cli([*ONE_CELL, "--runs-dir", str(runs)])
    assert _tree(runs) == before


def test_a_finished_cell_back_without_its_checkpoints_is_done_and_one_without_its_eval_is_refused(
    tmp_path, no_training
):
    """A cell trained on another machine and copied back with its files but not its checkpoints (a
    committed cell's files written back as a runs directory's) is done: planned so, never trained
    or evaluated again, its files untouched. Files with other settings, or this cell's without a
    finished eval.json (nothing is left to evaluate them with), are refused as foreign."""
    from agents.table import run as table_run
    from agents.table.plan import make_plan

    runs = tmp_path / "runs"
    cell_dir = runs / "paper" / "dqn" / "1d-dynamic"
    unpack_raw(ROOT / "bench" / "results" / "table" / "paper" / "dqn" / "1d-dynamic.json", cell_dir)
    before = _tree(runs)
    [cell] = make_plan(PRESETS["paper"], ["dqn"], ["1d-dynamic"], None, runs)
    assert cell.status == "done"
    assert table_run.run_cells([cell], progress=False) == 1  # finished cells counted, none trained
    assert (
        _run_cli(
            [
                "--preset",
                "paper",
                "--algorithms",
                "dqn",
                "--tasks",
                "1d-dynamic",
                "--runs-dir",
                str(runs),
                "--no-progress",
            ]
        )
        == 0
    )
    after = {name: data for name, data in _tree(runs).items() if not name.endswith(checkpoint.LOCK_FILE)}
    assert after == before

    def plan_with(edit):
        """The plan of the cell after `edit(cell_dir)` on a fresh copy of its files."""
        shutil.rmtree(cell_dir)
        unpack_raw(ROOT / "bench" / "results" / "table" / "paper" / "dqn" / "1d-dynamic.json", cell_dir)
        edit(cell_dir)
        return make_plan(PRESETS["paper"], ["dqn"], ["1d-dynamic"], None, runs)

    def edit_json(name, change):
        return lambda d: (d / name).write_text(json.dumps(change(json.loads((d / name).read_text()))))

    # Not this cell's run: other settings; or this cell's without a finished eval.json.
    foreign = "holds files that no start of this cell left there"
    with pytest.raises(ValueError, match=foreign):
        plan_with(edit_json("config.json", lambda c: {**c, "learning_rate": c["learning_rate"] * 2}))
    with pytest.raises(ValueError, match=foreign):
        plan_with(lambda d: (d / "eval.json").unlink())


def test_a_cells_own_start_cut_before_its_first_checkpoint_trains_again(tmp_path, monkeypatch):
    """What a start of this very cell leaves before its first checkpoint (its config.json, an
    empty metrics.jsonl, a free lock) is resumed from the start, not deleted; a free lock alone
    leaves the directory new."""
    import agents.training.driver as driver
    from agents.table import run as table_run
    from agents.table.plan import make_plan
    from agents.training.config import save_config

    runs = tmp_path / "runs"
    [cell] = make_plan(PRESETS["smoke"], ["ppo"], ["1d-static-sin"], None, runs)
    cell.directory.mkdir(parents=True)
    (cell.directory / checkpoint.LOCK_FILE).write_text("process 999999\n")  # its holder is gone
    assert make_plan(PRESETS["smoke"], ["ppo"], ["1d-static-sin"], None, runs)[0].status == "new"
    save_config(cell.config, cell.directory / checkpoint.CONFIG_FILE)
    (cell.directory / checkpoint.METRICS_FILE).write_text("")
    calls = []

    def spy(config, out_dir, **kwargs):
        calls.append(kwargs["resume"])
        raise KeyboardInterrupt  # stop there: what matters is how it was called

    monkeypatch.setattr(driver, "train", spy)
    [cell] = make_plan(PRESETS["smoke"], ["ppo"], ["1d-static-sin"], None, runs)
    with pytest.raises(KeyboardInterrupt):
        table_run.run_cells([cell], progress=False)
    assert calls == [True] and (cell.directory / checkpoint.CONFIG_FILE).is_file()
    # Cut after a chunk's metrics line but before its checkpoint: named, left for the user to remove.
    (cell.directory / checkpoint.METRICS_FILE).write_text('{"chunk": 0, "env_steps": 512, "wall_s": 1.0}\n')
    with pytest.raises(ValueError, match="records chunks that no checkpoint kept; the table deletes nothing"):
        make_plan(PRESETS["smoke"], ["ppo"], ["1d-static-sin"], None, runs)


def test_a_cell_named_twice_is_planned_once_and_a_finished_cell_is_never_trained_again(
    tmp_path, no_training, monkeypatch, capsys
):
    from agents.table import run as table_run
    from agents.table.plan import make_plan
    from agents.training.config import save_config

    runs = tmp_path / "runs"
    cells = make_plan(PRESETS["smoke"], ["ppo", "ppo"], ["1d-static-sin"], None, runs)
    assert len(cells) == 1
    assert _run_cli([*ONE_CELL[:3], "ppo", *ONE_CELL[3:], "--runs-dir", str(runs), "--dry-run"]) == 0
    assert "1 cells," in capsys.readouterr().out
    # The cell finished (by another process) after this plan was made: it is skipped, not trained.
    [stale] = cells
    write_cell(stale.directory)
    save_config(stale.config, stale.directory / checkpoint.CONFIG_FILE)
    monkeypatch.setattr(checkpoint, "latest_chunk", lambda directory: 3 if Path(directory) == stale.directory else None)
    before = _tree(stale.directory)
    assert stale.status == "new" and table_run.run_cells([stale], progress=False) == 1
    after = _tree(stale.directory)
    assert stale.status == "done" and after.pop(checkpoint.LOCK_FILE).startswith(b"process ") and after == before


# --- the report -----------------------------------------------------------------------------------


def _report(tmp_path: Path) -> tuple[Path, Path, Path]:
    """A runs directory with one finished smoke cell, and an empty results folder."""
    runs, results = tmp_path / "runs", tmp_path / "results"
    cell = runs / "smoke" / "ppo" / "1d-static-sin"
    write_cell(cell)
    results.mkdir()
    return runs, results, cell


def test_report_refuses_an_impossible_iou_naming_the_file_and_the_field(tmp_path, capsys):
    runs, results, cell = _report(tmp_path)
    evaluation = json.loads((cell / "eval.json").read_text())
    evaluation["1d-static-sin (seed 0)"].update(mean=7.5, min=-3.0)
    (cell / "eval.json").write_text(json.dumps(evaluation))
    code, err = _main(["--preset", "smoke", "--report", "--runs-dir", str(runs), "--results-dir", str(results)], capsys)
    assert code == 2 and len(err.strip().splitlines()) == 1
    assert f"{cell / 'eval.json'}: ['1d-static-sin (seed 0)'].mean must be a finite number in [0, 1], got 7.5" in err
    assert not any(results.iterdir())  # nothing published


@pytest.mark.parametrize(
    "name, damage, message, raw_message",
    [
        (
            "eval.json",
            lambda text: text[: len(text) // 2],
            r"eval.json is not valid JSON",
            r"sin.json is not valid JSON",
        ),
        ("eval.json", lambda text: "garbage", r"eval.json is not valid JSON", r"sin.json is not valid JSON"),
        (
            "eval.json",
            lambda text: text.replace('"mean": 0.5', '"mean": NaN'),
            r"eval.json: \['1d-static-sin \(seed 0\)'\].mean must be a finite number in \[0, 1\], got nan",
            r"sin.json: eval\['1d-static-sin \(seed 0\)'\].mean must be a finite number in \[0, 1\], got nan",
        ),
        (
            "eval.json",
            lambda text: text.replace('"mean": 0.5', '"max": 0.5'),
            r"eval.json: unknown field\(s\) \['max'\] in",
            r"sin.json: unknown field\(s\) \['max'\] in eval\['1d-static-sin \(seed 0\)'\]",
        ),
        (
            "config.json",
            lambda text: text.replace('"seeds": 2', '"seeds": "2"'),
            r"config.json: seeds must be an int >= 1, got '2'",
            r"sin.json: config.seeds must be an int >= 1, got '2'",
        ),
        (
            "config.json",
            lambda text: "{}",
            r"config.json: algorithm is missing",
            r"sin.json: config.algorithm is missing",
        ),
        (
            "cell.json",
            lambda text: "[]",
            r"cell.json must hold a JSON object, got list",
            r"sin.json: cell must be an object, got list",
        ),
        (
            "cell.json",
            lambda text: text.replace('"protocol"', '"protocols"'),
            r"cell.json: unknown field\(s\) \['protocols'\]",
            r"sin.json: unknown field\(s\) \['protocols'\] in cell",
        ),
        (
            "cell.json",
            lambda text: json.dumps({k: v for k, v in json.loads(text).items() if k != "protocol"}),
            r"cell.json: protocol is missing",
            r"sin.json: cell.protocol is missing",
        ),
        (
            "cell.json",
            lambda text: text.replace('"task": "1d-static-sin"', '"task": "1d-static-sine"'),
            r"cell.json: unknown task '1d-static-sine'; allowed: 1d-static-sin",
            r"sin.json: unknown cell.task '1d-static-sine'",
        ),
        (
            "cell.json",
            lambda text: text.replace('"static_episodes": 2', '"static_episodes": 3'),
            r"1d-static-sin: eval: \['1d-static-sin \(seed 0\)'\].episodes is 2, the cell's protocol has 3",
            r"sin.json: eval: \['1d-static-sin \(seed 0\)'\].episodes is 2, the cell's protocol has 3",
        ),
        (
            "config.json",
            lambda text: text.replace('"seeds": 2', '"seeds": 3'),
            r"1d-static-sin: eval: holds 2 result\(s\), the run has seeds 3",
            r"sin.json: eval: holds 2 result\(s\), the run has seeds 3",
        ),
    ],
)
def test_report_refuses_a_damaged_cell_naming_the_file_and_the_field(
    tmp_path, capsys, name, damage, message, raw_message
):
    runs, results, cell = _report(tmp_path)
    (cell / name).write_text(damage((cell / name).read_text()))
    code, err = _main(["--preset", "smoke", "--report", "--runs-dir", str(runs), "--results-dir", str(results)], capsys)
    assert code == 2 and len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
    assert err.startswith("snac table: error: ") and str(cell) in err and re.search(message, err), err
    assert not any(results.iterdir())
    # The same cell already copied into the results (one file) is refused there too, naming the part.
    copy = results / "table" / "smoke" / "ppo" / "1d-static-sin.json"
    copy.parent.mkdir(parents=True)
    copy.write_text(raw_copy_text(cell))
    shutil.rmtree(runs / "smoke")
    code, err = _main(["--preset", "smoke", "--report", "--runs-dir", str(runs), "--results-dir", str(results)], capsys)
    assert code == 2 and len(err.strip().splitlines()) == 1 and str(copy) in err and re.search(raw_message, err), err


def test_report_dry_run_checks_everything_and_writes_nothing(tmp_path, capsys):
    runs, results, cell = _report(tmp_path)
    shutil.copytree(ROOT / "bench" / "results" / "table" / "paper", results / "table" / "paper")
    before = _tree(results)
    assert (
        _run_cli(["--preset", "smoke", "--report", "--dry-run", "--runs-dir", str(runs), "--results-dir", str(results)])
        == 0
    )
    out = capsys.readouterr().out
    assert f"would copy {cell} to {results / 'table' / 'smoke' / 'ppo' / '1d-static-sin.json'}" in out
    assert f"would write {results / 'table.md'}" in out and f"would write {results / 'table-paper.png'}" in out
    assert _tree(results) == before and sorted(p.name for p in results.iterdir()) == ["table"]
    assert _run_cli(["--preset", "smoke", "--report", "--runs-dir", str(runs), "--results-dir", str(results)]) == 0
    assert (results / "table" / "smoke" / "ppo" / "1d-static-sin.json").is_file()


def test_report_needs_a_runs_directory_that_exists(tmp_path, capsys, monkeypatch):
    results = tmp_path / "results"
    (tmp_path / "file").write_text("x")
    for runs, phrase in ((tmp_path / "nowhere", "does not exist"), (tmp_path / "file", "is a file")):
        code, err = _main(
            ["--preset", "smoke", "--report", "--runs-dir", str(runs), "--results-dir", str(results)], capsys
        )
        assert (
            code == 2
            and err.strip()
            == f"snac table: error: --runs-dir {runs} {phrase}"
            + (", not a directory of runs" if phrase == "is a file" else "")
            + "; give the directory `snac table` trained in"
        )
    assert not results.exists()
    # The default runs directory may be absent: the report is rebuilt from the results alone.
    monkeypatch.chdir(tmp_path)
    code, err = _main(["--preset", "smoke", "--report", "--results-dir", str(results)], capsys)
    assert code == 0 and "no runs under runs/table (the default --runs-dir)" in err and (results / "table.md").is_file()


def test_report_writes_through_no_link_in_the_results_and_keeps_a_readme_link(tmp_path, capsys):
    from agents.table.readme import BEGIN, END

    runs, results, _ = _report(tmp_path)
    outside = tmp_path / "outside"
    outside.mkdir()
    (results / "table" / "smoke").mkdir(parents=True)
    (results / "table" / "smoke" / "ppo").symlink_to(outside, target_is_directory=True)
    argv = ["--preset", "smoke", "--report", "--runs-dir", str(runs), "--results-dir", str(results)]
    code, err = _main(argv, capsys)
    assert code == 2 and f"{results / 'table' / 'smoke' / 'ppo'} is a symbolic link inside {results}" in err
    assert not any(outside.iterdir())
    (results / "table" / "smoke" / "ppo").unlink()
    (outside / "table.md").write_text("someone else's\n")
    (results / "table.md").symlink_to(outside / "table.md")
    code, err = _main(argv, capsys)
    assert (
        code == 2 and "table.md is a symbolic link" in err and (outside / "table.md").read_text() == "someone else's\n"
    )
    (results / "table.md").unlink()
    readme = tmp_path / "README.md"
    readme.write_text(f"intro\n{BEGIN}\nstale\n{END}\n")
    link = tmp_path / "link.md"
    link.symlink_to(readme)
    code, err = _main([*argv, "--readme", str(link)], capsys)
    assert code == 2 and f"--readme {link} is a symbolic link; give the file it points to ({readme})" in err
    assert link.is_symlink() and "stale" in readme.read_text() and not (results / "table.md").exists()
    assert _main([*argv, "--readme", str(readme)], capsys)[0] == 0 and "stale" not in readme.read_text()


def test_report_reads_every_entry_of_the_results_table_or_refuses_it(tmp_path, capsys):
    """Each cell is one raw file; a cell's directory or any other entry under a learner's folder,
    or a preset's folder budgets.toml does not name, is refused, named, rather than left out of
    the table. A curve with a chunk in which no
    episode ended (NaN in an older metrics.jsonl) is copied as strict JSON, null."""
    runs, results, cell = _report(tmp_path)
    with (cell / "metrics.jsonl").open("a") as f:
        f.write('{"chunk": 1, "env_steps": 4096, "wall_s": 6.0, "iou": [NaN, 0.5]}\n')
    argv = ["--preset", "smoke", "--report", "--runs-dir", str(runs), "--results-dir", str(results)]
    assert _main(argv, capsys)[0] == 0
    copy = results / "table" / "smoke" / "ppo" / "1d-static-sin.json"
    assert json.loads(copy.read_text())["curve"][1]["iou"] == [None, 0.5] and "NaN" not in copy.read_text()
    for stray in (copy.with_name("1d-static-gauss"), copy.with_name("notes.md")):
        stray.mkdir() if stray.suffix == "" else stray.write_text("x")
        code, err = _main(argv, capsys)
        assert code == 2 and f"{stray} is not a cell's raw copy" in err, err
        shutil.rmtree(stray) if stray.is_dir() else stray.unlink()
    # A folder of cells of no preset of budgets.toml (renamed, or removed from it) is refused too.
    (results / "table" / "renamed").mkdir()
    code, err = _main(argv, capsys)
    assert code == 2 and "holds cells of ['renamed'], no preset of budgets.toml" in err, err


def test_report_refuses_a_cell_file_over_the_size_limit_before_reading_it(tmp_path, capsys, monkeypatch):
    """A raw copy past `RAW_COPY_MAX_BYTES` (sparse: no disk used) is refused in one line naming the
    file and the limit, unread; so is a runs directory's cell whose files add up past it (its copy
    would be), and a curve that makes the copy it would write exceed it."""
    from agents.table import files

    runs, results, cell = _report(tmp_path)
    argv = ["--preset", "smoke", "--report", "--runs-dir", str(runs), "--results-dir", str(results)]
    limit = f"{files.RAW_COPY_MAX_BYTES:,}-byte limit"
    copy = results / "table" / "smoke" / "ppo" / "1d-static-gauss.json"
    copy.parent.mkdir(parents=True)
    with copy.open("wb") as f:
        f.truncate(files.RAW_COPY_MAX_BYTES + 1)
    code, err = _main(argv, capsys)
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    assert f"{copy} is {files.RAW_COPY_MAX_BYTES + 1:,} bytes, over the {limit}" in err, err
    copy.unlink()
    with (cell / "metrics.jsonl").open("r+b") as f:  # a runs directory's cell: refused before any file is read
        f.truncate(files.RAW_COPY_MAX_BYTES)
    code, err = _main(argv, capsys)
    assert code == 2 and len(err.strip().splitlines()) == 1 and str(cell) in err and limit in err, err
    assert not any(results.rglob("*.json"))
    # Files under the limit whose copy would be over it (the copy re-indents): the same refusal, nothing written.
    write_cell(cell)
    read = ("cell.json", "config.json", "eval.json", "metrics.jsonl")
    monkeypatch.setattr(files, "RAW_COPY_MAX_BYTES", sum((cell / name).stat().st_size for name in read))
    code, err = _main(argv, capsys)
    assert code == 2 and len(err.strip().splitlines()) == 1 and f"{cell} is " in err and "-byte limit" in err, err
    assert not any(results.rglob("*.json"))
