"""The raw results of `snac table`: each finished cell's small JSON files (`config.json`,
`eval.json`, `cell.json`, and its learning curve `metrics.jsonl`; never checkpoints), copied from
the runs directory to `bench/results/table/<preset>/<algorithm>/<cell>/` and read back from there,
so that every table, curve and training wall time can be rebuilt from the repository. Cells copied
before the curves were kept have no `metrics.jsonl`; their wall times are on the learners' pages.

Every cell is read back whole and checked (`agents.table.files.read_cell`) before anything is
written: a damaged cell stops the report with its file and field named, and no file is written
through a symbolic link inside the results folder."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from agents import checkpoint
from agents.table.files import CELL_FILE, EVAL_FILE, read_cell
from snac_jax.atomic import atomic_write

RAW_FILES = (checkpoint.CONFIG_FILE, EVAL_FILE, CELL_FILE)
OPTIONAL_RAW_FILES = (checkpoint.METRICS_FILE,)


def raw_cells(root: Path) -> list[Path]:
    """The cell directories under a preset's folder that hold an eval.json (finished, or damaged)."""
    return sorted(p.parent for p in root.glob(f"*/*/{EVAL_FILE}"))


def refuse_links(root: Path, path: Path) -> None:
    """`ValueError` when `path`, or a folder between `root` and it, is a symbolic link: what the
    report writes under `root` lands there, never through a link somewhere else."""
    parts = path.relative_to(root).parts
    for depth in range(1, len(parts) + 1):
        part = root.joinpath(*parts[:depth])
        if part.is_symlink():
            raise ValueError(f"{part} is a symbolic link inside {root}; the report writes no file through a link: "
                             "replace it with the file or folder itself")


def copies(runs_dir: str | Path | None, results_dir: str | Path,
           preset: str) -> list[tuple[Path, Path, tuple[str, ...]]]:
    """What `collect` copies: (cell directory, destination, file names) of every finished cell of
    `preset` under `runs_dir` (None: no runs, nothing), each read back whole first
    (`files.read_cell`: a damaged cell is a `ValueError` naming the file and field, never left
    out), and every destination checked to hold no link."""
    if runs_dir is None:
        return []
    runs_dir, results_dir = Path(runs_dir), Path(results_dir)
    if not runs_dir.is_dir():
        raise ValueError(f"--runs-dir {runs_dir} " + ("is a file, not a directory of runs" if runs_dir.exists()
                                                     else "does not exist") + "; give the directory `snac table` trained in")
    source, target = runs_dir / preset, results_dir / "table" / preset
    if source.is_dir() and target.is_dir() and source.resolve() == target.resolve():
        raise ValueError(f"--runs-dir {runs_dir} is the report's own copy under {results_dir / 'table'}; give the "
                         "directory `snac table` trained in")
    planned = []
    for directory in raw_cells(source):
        read_cell(directory)
        names = RAW_FILES + tuple(n for n in OPTIONAL_RAW_FILES if (directory / n).is_file())
        destination = target / directory.relative_to(source)
        for name in names:
            refuse_links(results_dir, destination / name)
        planned.append((directory, destination, names))
    return planned


def collect(runs_dir: str | Path | None, results_dir: str | Path, preset: str) -> list[Path]:
    """Copy every finished cell's JSON files under `results_dir/table/<preset>/` (each file
    atomically; every cell is checked before the first is copied); returns the cells copied."""
    copied = []
    for directory, destination, names in copies(runs_dir, results_dir, preset):
        for name in names:
            data = (directory / name).read_bytes()
            atomic_write(destination / name, lambda f, data=data: f.write(data))
        copied.append(destination)
    return copied


def load_raw(results_dir: str | Path, preset: str) -> dict[str, dict[str, dict]]:
    """algorithm -> cell (its directory's name: the task, and an ablation's arm) -> {"config", "eval",
    "cell", "metrics"} of the copied cells ("metrics": the curve's records, empty where not copied).
    A damaged copy is a `ValueError` naming the file and the field."""
    raw: dict[str, dict[str, dict]] = {}
    plain = []
    for directory in raw_cells(Path(results_dir) / "table" / preset):
        files = raw.setdefault(directory.parent.name, {})[directory.name] = read_cell(directory)
        if "variant" not in files["cell"]:
            plain.append(directory)
    if plain and len(plain) < sum(map(len, raw.values())):
        raise ValueError(f"{plain[0] / CELL_FILE}: no variant, beside cells of an ablation's arms in the same preset")
    return raw


def seed_means(files: dict) -> list[float]:
    """Per-seed protocol means of one cell, in seed order (eval.json keeps it)."""
    return [float(r["mean"]) for r in files["eval"].values()]


def training_wall_s(cells: list[dict]) -> float | None:
    """Training wall time of one or more cells (a column's shapes run one after another), all
    seeds together, from their curves (the driver's cumulative `wall_s`, resumes included); None
    where a cell's curve was not copied."""
    if any(not c.get("metrics") for c in cells):
        return None
    return round(sum(c["metrics"][-1]["wall_s"] for c in cells), 1)


def budget_record(cells: list[dict]) -> dict[str, Any]:
    """The training budget of one or more cells (a column's shapes): env steps per seed per task,
    what was requested before the wall-time cap, whether any was capped, and why, and the
    training wall time it took."""
    budgets = [c["cell"]["budget"] for c in cells]
    return {
        "env_steps_per_seed": {c["config"]["task"]: c["config"]["total_steps"] for c in cells},
        "requested_per_seed": {c["config"]["task"]: b["requested"] for c, b in zip(cells, budgets)},
        "capped": any(b["capped"] for b in budgets),
        "source": "; ".join(dict.fromkeys(b["source"] for b in budgets)),
        "training_wall_s": training_wall_s(cells),
    }


def _steps(n: int) -> str:
    return f"{n / 1e6:.3g}M" if n >= 1e6 else f"{n / 1e3:.3g}k"


def budget_text(budget: dict) -> str:
    """A budget record as the tables print it: env steps per seed, `*` where capped."""
    steps = sorted(set(budget["env_steps_per_seed"].values()))
    text = _steps(steps[0]) if len(steps) == 1 else f"{_steps(steps[0])}–{_steps(steps[-1])}"
    return text + ("*" if budget["capped"] else "")
