"""`bench/throughput.py` runs and writes its JSON rows, table and plots."""

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
SCRIPT = ROOT / "bench" / "throughput.py"
KEYS = {"task", "num_envs", "steps_per_s", "compile_s", "numpy_steps_per_s", "ratio"}


def _run(args, tmp_path):
    done = subprocess.run(
        [sys.executable, str(SCRIPT), *args, "--out", str(tmp_path)], capture_output=True, text=True, cwd=ROOT
    )
    assert done.returncode == 0, done.stderr
    return json.loads((tmp_path / "throughput.json").read_text())


def _committed_results() -> dict[str, int]:
    return {p.name: p.stat().st_mtime_ns for p in (ROOT / "bench" / "results").rglob("*") if p.is_file()}


@pytest.mark.slow  # over 10 s on the 2-core CPU: `pytest -m slow` (CI runs both)
def test_tiny_run_writes_rows_table_and_plots(tmp_path):
    committed = _committed_results()
    rows = _run(
        [
            "--tasks",
            "3d-dynamic-sparse",
            "1d-static-sin",
            "--num-envs",
            "1",
            "4",
            "--steps",
            "60",
            "--numpy-steps",
            "200",
            "--no-e2e",
            "--reset",
            "loop",
            "select",
        ],
        tmp_path,
    )
    assert [(r["task"], r["reset"], r["num_envs"]) for r in rows] == [
        (task, reset, n)
        for task in ("1d-static-sin", "3d-dynamic-sparse")
        for reset in ("loop", "select")
        for n in (1, 4)
    ]
    loop, select = rows[5], rows[7]  # 3d-dynamic-sparse, N = 4
    assert loop["episodes"] == select["episodes"] > 0  # the same worlds, whichever strategy resets them
    rows = [r for r in rows if r["reset"] == "loop"]
    for row in rows:
        assert KEYS <= set(row)
        assert row["steps_per_s"] > 0 and row["numpy_steps_per_s"] > 0 and row["compile_s"] > 0
        assert row["ratio"] == pytest.approx(row["steps_per_s"] / row["numpy_steps_per_s"])
    assert rows[3]["episodes"] > 0  # random 3D episodes end fast (stuck): auto-reset ran
    table = (tmp_path / "throughput.md").read_text()
    assert "## 1D" in table and "## 3D" in table and "## 2D" not in table
    for family in ("1d", "3d"):
        assert (tmp_path / f"throughput_{family}.png").read_bytes()[:4] == b"\x89PNG"
    assert _committed_results() == committed  # everything went under --out
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "throughput.json",
        "throughput.md",
        "throughput_1d.png",
        "throughput_3d.png",
    ]


@pytest.mark.slow
def test_the_output_directory_is_required_and_the_only_one():
    for args in ([], ["--json", "rows.json", "--out", "x"]):
        done = subprocess.run([sys.executable, str(SCRIPT), *args], capture_output=True, text=True, cwd=ROOT)
        assert done.returncode == 2, (args, done.stderr)
    assert not (ROOT / "rows.json").exists() and not (ROOT / "x").exists()


@pytest.mark.slow
def test_bad_arguments_are_rejected(tmp_path):
    for args in (["--repeats", "2"], ["--num-envs", "0"], ["--devices", "x"], ["--reset", "vmap"]):
        done = subprocess.run(
            [sys.executable, str(SCRIPT), *args, "--out", str(tmp_path)], capture_output=True, text=True, cwd=ROOT
        )
        assert done.returncode == 2, (args, done.stderr)


@pytest.mark.slow
def test_quick_run_covers_every_task(tmp_path):
    from snac_jax import TASKS

    rows = _run(["--quick"], tmp_path)
    assert sorted(r["task"] for r in rows) == sorted(TASKS)
    e2e = json.loads((tmp_path / "snac_rollout_e2e.json").read_text())
    assert e2e and all(item["wall_s"] > 0 and "env-steps/s" in item["output"] for item in e2e)


@pytest.mark.parametrize("algorithm", [pytest.param(name, marks=pytest.mark.slow) for name in ("ppo", "pqn", "dqn")])
def test_training_throughput_bench_prints_median_and_baseline(algorithm, tmp_path):
    script = ROOT / "bench" / "train_throughput.py"
    done = subprocess.run(
        [
            sys.executable,
            str(script),
            "--algorithm",
            algorithm,
            "--tasks",
            "1d-static-step",
            "--updates",
            "1",
            "--repeats",
            "2",
            "--num-envs",
            "8",
            "--rollout-steps",
            "4",
            "--hidden-size",
            "8",
            "--rnn-size",
            "8",
            "--update-epochs",
            "2",
            "--out",
            str(tmp_path / "rates.md"),
        ],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=600,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    assert f"{algorithm}; jax" in done.stdout and "median of 2 repeats of 1 updates" in done.stdout
    row = next(line for line in done.stdout.splitlines() if line.startswith("| 1d-static-step"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[1] == ("feed-forward, hidden 8" if algorithm == "dqn" else "GRU 8, hidden 8") and cells[2] == "8"
    with_learning, acting_only = (float(c.replace(",", "")) for c in cells[6:8])
    # Both rates are measured and positive; which is faster is not asserted: two repeats of one tiny
    # update are noise-dominated on a loaded machine (a timed unit test; the bench's own medians judge speed).
    assert with_learning > 0 and acting_only > 0
    params = int(cells[4].replace(",", ""))
    network_gflops, matmul_gflops = float(cells[9].removeprefix("≈ ")), float(cells[10])
    # The FLOPs counted from the traced chunk, per env step, are about what two epochs of a dense
    # network of this size do: an acting forward pass plus two forward-and-backward passes
    # (2 FLOPs a weight each; PQN's targets add a forward pass, the recurrent core its gates).
    per_step = network_gflops * 1e9 / with_learning
    if algorithm != "dqn":
        assert 0.5 < per_step / (2 * params * (1 + 3 * 2)) < 2.5
    else:  # one gradient step on 16 sampled windows per update of 8 worlds x 4 steps, each a few rows
        assert per_step > 2 * params
    assert matmul_gflops > 0
    assert (tmp_path / "rates.md").read_text().splitlines()[-1] == row
    bad = subprocess.run([sys.executable, str(script), "--repeats", "0"], capture_output=True, text=True, cwd=ROOT)
    assert bad.returncode == 2 and "--repeats must be >= 1" in bad.stderr


@pytest.mark.slow
def test_design_runs_ab_refuses_a_task_without_a_design_in_one_line():
    script = ROOT / "bench" / "design_runs_ab.py"
    done = subprocess.run(
        [sys.executable, str(script), "--task", "2d-static-dense"], capture_output=True, text=True, cwd=ROOT
    )
    assert done.returncode == 2 and "holds no design to encode; allowed: 1d-dynamic" in done.stderr.splitlines()[-1]


@pytest.mark.slow  # compiles PPO's training twice
@pytest.mark.parametrize(
    "compare,ways", [("loop", ("loop", "bounded pass")), ("first-layer", ("once per run", "every step"))]
)
def test_design_runs_ab_times_both_ways_interleaved(compare, ways):
    script = ROOT / "bench" / "design_runs_ab.py"
    args = ["--algorithm", "ppo", "--task", "1d-dynamic", "--updates", "1", "--repeats", "1", "--compare", compare]
    done = subprocess.run([sys.executable, str(script), *args], capture_output=True, text=True, cwd=ROOT, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    line = done.stdout.strip().splitlines()[-1]
    assert line.startswith("ppo on 1d-dynamic, ") and f"; {ways[0]} / {ways[1]} " in line, line
    rates = re.search(rf"interleaved: {ways[0]} ([\d,]+), {ways[1]} ([\d,]+);", line)
    assert rates and all(float(rate.replace(",", "")) > 0 for rate in rates.groups()), line


def _throughput_rows(script, args, prefix):
    """The table rows starting with `prefix` that `script` prints with `args`, each as its cells."""
    done = subprocess.run([sys.executable, str(script), *args], capture_output=True, text=True, cwd=ROOT, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    lines = done.stdout.splitlines()
    return [[c.strip() for c in line.strip("|").split("|")] for line in lines if line.startswith(prefix)]


@pytest.mark.slow  # compiles PPO's training twice
def test_training_throughput_bench_times_the_bounded_design_pass_beside_the_loop():
    """`--design-runs both`: a dynamic task's row again with the design runs in one bounded pass,
    the same network (its parameter count), each row's rate measured; a static task has one row."""
    script = ROOT / "bench" / "train_throughput.py"
    tiny = ["--updates", "1", "--repeats", "1", "--num-envs", "4", "--rollout-steps", "8", "--hidden-size", "8"]
    args = ["--algorithm", "ppo", "--tasks", "1d-dynamic", "1d-static-step", *tiny, "--rnn-size", "8"]
    rows = _throughput_rows(script, [*args, "--design-runs", "both"], "| 1d-")
    assert [(row[0], row[1]) for row in rows] == [
        ("1d-dynamic", "GRU 8, hidden 8"),
        ("1d-dynamic", "GRU 8, hidden 8; design runs in one bounded pass"),
        ("1d-static-step", "GRU 8, hidden 8"),
    ]
    assert rows[0][4] == rows[1][4] and all(float(row[6].replace(",", "")) > 0 for row in rows)


@pytest.mark.slow  # compiles pqn-belief's training twice
def test_training_throughput_bench_times_each_variant_beside_the_tuned_row():
    """A setting's cost is read off two rows of one run: the tuned row and the variant's, whose
    network cell names the settings it changed (and whose parameter count they change)."""
    script = ROOT / "bench" / "train_throughput.py"
    args = [
        "--algorithm",
        "pqn-belief",
        "--tasks",
        "2d-dynamic-sparse",
        "--updates",
        "1",
        "--repeats",
        "1",
        "--num-envs",
        "4",
        "--rollout-steps",
        "4",
        "--hidden-size",
        "8",
        "--rnn-size",
        "8",
        "--variant",
        "view_radius=3,design_encoder=false",
    ]
    rows = _throughput_rows(script, args, "| 2d-dynamic-sparse")
    assert [row[1] for row in rows] == ["GRU 8, hidden 8", "GRU 8, hidden 8; view_radius=3; design_encoder=False"]
    assert rows[0][4] != rows[1][4]  # the tuned row (view 7, no encoder) and the variant are different networks
    for variant, message in (
        ("view_radius", "--variant takes NAME=VALUE"),
        ("no_such=1", "got 'no_such=1'"),
        ("design_encoder=maybe", "--variant design_encoder: true or false, got 'maybe'"),
        ("view_radius=x", "--variant view_radius: must be an int"),
        ("num_envs=8", "--variant: num_envs has its own flag (--num-envs)"),
        ("view_radius=3,view_radius=4", "--variant: view_radius is named twice"),
        ("view_radius=1", "1d-static-sin: view_radius must be 0 or in 2..29 on 1d-static-sin, got 1"),
    ):
        # two CPU devices: the variants are read after the device count is set, not before
        bad = subprocess.run(
            [sys.executable, str(script), "--algorithm", "pqn-belief", "--devices", "2", "--variant", variant],
            capture_output=True,
            text=True,
            cwd=ROOT,
            timeout=120,
        )
        assert bad.returncode == 2 and message in bad.stderr, (variant, bad.stderr[-500:])
        assert "| 1d-static-sin" not in bad.stdout  # refused before any row was timed


@pytest.mark.slow
def test_device_check_quick_writes_its_two_files_with_every_part(tmp_path):
    committed = _committed_results()
    # a budget no busy machine spends, so that every part runs (the default stops starting parts after 150 s)
    done = subprocess.run(
        [
            sys.executable,
            str(ROOT / "bench" / "device_check.py"),
            "--quick",
            "--budget-s",
            "1200",
            "--out",
            str(tmp_path),
        ],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=600,
    )
    assert done.returncode == 0, done.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "device.json",
        "device.md",
    ]  # the README run's scratch is gone
    report = json.loads((tmp_path / "device.json").read_text())
    assert report["context"]["jax"] and report["context"]["commit"] and report["context"]["auto_reset"] == "loop"
    measured = [row for row in report["step"] if "steps_per_s" in row]
    assert {(row["task"], row["reset"]) for row in measured} >= {
        ("3d-static-sparse", "loop"),
        ("3d-static-sparse", "select"),
    }
    for row in measured:
        assert row["episodes"] >= row["num_envs"]  # T = the step limit: every world ended an episode
    assert {row["algorithm"] for row in report["learn"] if row.get("env_steps_per_s", 0) > 0} == {"ppo-rnn", "pqn-rnn"}
    assert 0 <= report["readme"][0]["iou_mean"] <= 1
    assert report["gymnasium"][0]["scan_steps_per_s"] > 0
    table = (tmp_path / "device.md").read_text()
    assert "## Stepping" in table and "## Learning" in table and "README" in table
    assert _committed_results() == committed


@pytest.mark.slow  # over 10 s on the 2-core CPU: `pytest -m slow` (CI runs both)
def test_device_check_refuses_bad_arguments_before_measuring(tmp_path):
    script = ROOT / "bench" / "device_check.py"
    (tmp_path / "file").write_text("")
    for args in (
        ["--repeats", "2"],
        ["--point-s", "0"],
        ["--skip", "everything"],
        ["--tasks", "4d-static"],
        ["--skip", "step", "learn", "readme", "gymnasium"],  # would say it wrote files and write none
        ["--budget-s", "0"],  # was read as the default, 150 s
        ["--budget-s", "-5"],
        ["--out", str(tmp_path / "file")],
    ):
        done = subprocess.run(
            [sys.executable, str(script), "--out", str(tmp_path / "x"), *args], capture_output=True, text=True, cwd=ROOT
        )
        assert done.returncode == 2, (args, done.stderr)
        assert done.stderr.strip().splitlines()[-1].startswith(("usage", "device_check.py: error")), done.stderr
    assert not (tmp_path / "x" / "device.json").exists()


def test_robustness_refuses_bad_inputs_in_one_line_and_writes_nothing(tmp_path):
    script = ROOT / "bench" / "robustness.py"
    (tmp_path / "garbage.json").write_text("{not json")
    (tmp_path / "list.json").write_text('{"seconds": 1, "results": [1]}')
    (tmp_path / "file").write_text("")
    out = tmp_path / "out"
    for args, phrase in (
        (["--out", str(out), "--from-json", str(tmp_path / "garbage.json")], "is not JSON"),
        (["--out", str(out), "--from-json", str(tmp_path / "missing.json")], "cannot be read"),
        (["--out", str(out), "--from-json", str(tmp_path / "list.json")], "is not a robustness.json"),
        (["--out", str(out), "--before", str(tmp_path / "garbage.json"), "--from-json", "x"], "--before"),
        (["--out", str(tmp_path / "file")], "is a file"),
        (["--out", str(out), "--only", "no case has this"], "matches no case"),  # was: an empty record
    ):
        done = subprocess.run([sys.executable, str(script), *args], capture_output=True, text=True, cwd=ROOT)
        last = done.stderr.strip().splitlines()[-1]
        assert done.returncode == 2 and last.startswith("robustness.py: error:") and phrase in last, done.stderr
        assert "Traceback" not in done.stderr
    assert not out.exists()


def test_robustness_only_merges_its_cases_into_the_record_and_keeps_the_before_column(tmp_path):
    sys.path.insert(0, str(ROOT))
    from bench import robustness

    def row(what, verdict):
        return {"what": what, "input": "snac x", "verdict": verdict, "note": "n", "seconds": 1}

    before = {"a": row("a", "bad")}
    robustness.write(tmp_path, [row("a", "good"), row("b", "poor")], 60.0, before)
    robustness.write_merged(
        tmp_path,
        robustness.load_record(tmp_path / "robustness.json"),
        [row("b", "good"), row("c", "good")],
        "b",
        5.0,
        None,
    )
    record = json.loads((tmp_path / "robustness.json").read_text())
    assert [(r["what"], r["verdict"]) for r in record["results"]] == [("a", "good"), ("b", "good"), ("c", "good")]
    assert record["seconds"] == 60.0 and record["reruns"] == [{"only": "b", "cases": 2, "seconds": 5.0}]
    assert record["before"] == before and "| 1 | a | `snac x` | bad |" in (tmp_path / "robustness.md").read_text()


@pytest.mark.slow  # over 10 s on the 2-core CPU: `pytest -m slow` (CI runs both)
def test_acting_probe_times_each_way_of_reading_the_design_and_refuses_other_learners():
    """`bench/acting_probe.py` prints one rate per run for the cache, the per-step encoding and
    the unrefreshed cache, writes nothing, and refuses an on-policy learner in one line."""
    script = ROOT / "bench" / "acting_probe.py"
    before = _committed_results()
    base = [sys.executable, str(script), "--algorithm", "dqn", "--task", "1d-dynamic", "--num-envs", "4"]
    for design in ("cache", "every-step", "no-refresh"):
        done = subprocess.run([*base, "--design", design, "--repeats", "1"], capture_output=True, text=True, cwd=ROOT)
        assert done.returncode == 0, done.stderr[-2000:]
        assert f"dqn 1d-dynamic (4 worlds, design: {design}): " in done.stdout and "env-steps/s acting" in done.stdout
    done = subprocess.run(
        [sys.executable, str(script), "--algorithm", "ppo", "--task", "1d-dynamic"], capture_output=True, text=True
    )
    assert done.returncode == 2 and "is not a replay learner" in done.stderr
    assert _committed_results() == before
