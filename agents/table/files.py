"""The files of `snac table`'s cells, read back and checked (each against its schema in
`agents.training.schemas`, then against each other), and the record: each finished cell's small
files (`cell.json`, `config.json`, `eval.json`, its curve `metrics.jsonl`; never checkpoints)
copied into one file, `bench/results/table/<preset>/<algorithm>/<task>[.<arm>].json`, holding
{"cell", "config", "eval", "curve"}, from which the report rebuilds every page. A damaged cell is
a `ValueError` naming the file and the field, never left out."""

from __future__ import annotations

import json
import tomllib
from pathlib import Path
from typing import Any

from agents.training import checkpoint, schemas
from snac_jax.designs import NUM_TEST_DESIGNS
from snac_jax.schema import loads_json
from snac_jax.tasks import task_spec

CELL_FILE = "cell.json"
EVAL_FILE = "eval.json"
CURVE_FILE = "curve.png"
RAW_SUFFIX = ".json"
RAW_COPY_MAX_BYTES = 8 * 2**20
"""The largest raw copy the report reads or writes, so that a huge file under a cell's name is
refused before it takes the machine's memory (the largest committed copy is 26 kB)."""
PAGE_TEXT = tomllib.loads((Path(__file__).parent / "pages.toml").read_text())
"""The fixed prose of the pages the report writes, by name, with the {fields} it fills in."""


def expected_episodes(task: str, protocol: dict[str, int]) -> int:
    if task_spec(task).dynamic:
        return protocol["episodes_per_test_design"] * NUM_TEST_DESIGNS
    return protocol["static_episodes"]


def eval_problem(results: dict, seeds: int, episodes: int, seed: int) -> str | None:
    """Why a schema-checked eval.json is not a finished result of a cell (one row per training
    seed, scored with the evaluation key `seed` over `episodes` episodes each), or None."""
    if len(results) != seeds:
        return f"holds {len(results)} result(s), the run has seeds {seeds}"
    for name, row in results.items():
        if row["seed"] != seed:
            return f"['{name}'].seed is {row['seed']}, the cell is scored with evaluation key {seed}"
        if row["episodes"] != episodes:
            return f"['{name}'].episodes is {row['episodes']}, the cell's protocol has {episodes}"
    return None


def eval_is_valid(path: Path, seeds: int, episodes: int, seed: int) -> bool:
    try:
        return eval_problem(schemas.load(path, schemas.EVAL_JSON), seeds, episodes, seed) is None
    except (OSError, ValueError):
        return False


def _check_parts(path: Path, config, cell: dict, results: dict) -> None:
    """The checks between a cell's parts (`path`: its raw copy, or its directory): cell.json and
    the config name the same algorithm and task, the cell stands where its algorithm and name say,
    and `results` is a finished result of it."""
    for key, value in (("algorithm", config.algorithm), ("task", config.task)):
        if cell[key] != value:
            raise ValueError(f"{path}: cell: {key} is {cell[key]!r}, its config has {value!r}")
    missing = sorted({"variant", "paper_variant", "switches"} - set(cell))
    if 0 < len(missing) < 3:
        raise ValueError(f"{path}: cell: an arm's cell needs variant, paper_variant and switches; {missing} missing")
    own, name = cell["task"] + (f".{cell['variant']}" if "variant" in cell else ""), path.name.removesuffix(RAW_SUFFIX)
    if name != own or path.parent.name != cell["algorithm"]:
        raise ValueError(
            f"{path}: cell: its algorithm and task ({cell['algorithm']}/{own}) are not where it stands "
            f"({path.parent.name}/{name})"
        )
    problem = eval_problem(results, config.seeds, expected_episodes(cell["task"], cell["protocol"]), cell["eval_seed"])
    if problem is not None:
        raise ValueError(f"{path}: eval: {problem} (from its cell and config); evaluate the cell again")


def check_raw_size(size: int, what: str) -> None:
    if size > RAW_COPY_MAX_BYTES:
        raise ValueError(
            f"{what} {size:,} bytes, over the {RAW_COPY_MAX_BYTES:,}-byte limit of a cell's raw copy "
            "(agents.table.files.RAW_COPY_MAX_BYTES): not a cell's record, or a damaged one; move it away"
        )


def read_cell(directory: Path) -> str:
    """The raw copy's text of a finished cell in a runs directory: each of its files checked
    against its own schema (an error names the file), then the parts together as `read_raw`
    checks a copy. The config is kept as written."""
    cell_path, eval_path = directory / CELL_FILE, directory / EVAL_FILE
    if not cell_path.is_file():
        raise ValueError(f"{cell_path} is missing: {directory} is not a cell of the table")
    read = (cell_path, eval_path, directory / checkpoint.CONFIG_FILE, directory / checkpoint.METRICS_FILE)
    check_raw_size(sum(p.stat().st_size for p in read if p.is_file()), f"{directory}: its cell's files are")
    text = raw_text(
        {
            "cell": schemas.load(cell_path, schemas.CELL_JSON),
            "config": schemas.load(directory / checkpoint.CONFIG_FILE, schemas.CONFIG_JSON),
            "eval": schemas.load(eval_path, schemas.EVAL_JSON),
            "metrics": checkpoint.read_metrics_lines(directory / checkpoint.METRICS_FILE),
        }
    )
    read_raw(directory, text)
    return text


def read_raw(path: Path, text: str | None = None) -> dict[str, Any]:
    """A cell's raw copy, checked (`text`: what is about to be written there, read in its place):
    {"config" (the config class's full settings), "eval", "cell", "metrics" (the curve)}."""
    from agents.training.registry import config_from_json

    check_raw_size(path.stat().st_size if text is None else len(text.encode()), f"{path} is")
    spec = schemas.RAW_CELL_JSON
    record = schemas.load(path, spec) if text is None else loads_json(text, spec, path)
    try:
        config = config_from_json(record["config"])
    except (TypeError, ValueError) as error:
        raise ValueError(f"{path}: config: {error}") from error
    _check_parts(path, config, record["cell"], record["eval"])
    return {"config": config.to_json(), "eval": record["eval"], "cell": record["cell"], "metrics": record["curve"]}


def raw_text(files: dict) -> str:
    """A cell's raw copy as written: {"cell", "config", "eval", "curve"} indented, each curve
    record on one line as metrics.jsonl holds it."""
    parts = [
        f'  "{name}": ' + json.dumps(files[name], indent=2, allow_nan=False).replace("\n", "\n  ")
        for name in ("cell", "config", "eval")
    ]
    from agents.training.driver import metrics_line  # strict JSON: a curve's non-finite values as null

    curve = ",\n".join("    " + metrics_line(r).rstrip("\n") for r in files["metrics"])
    parts.append('  "curve": ' + (f"[\n{curve}\n  ]" if curve else "[]"))
    return "{\n" + ",\n".join(parts) + "\n}\n"


def refuse_links(root: Path, path: Path) -> None:
    """`ValueError` when `path`, or a folder between `root` and it, is a symbolic link."""
    parts = path.relative_to(root).parts
    for depth in range(1, len(parts) + 1):
        if (part := root.joinpath(*parts[:depth])).is_symlink():
            raise ValueError(
                f"{part} is a symbolic link inside {root}; the report writes no file through a link: "
                "replace it with the file or folder itself"
            )


def copies(runs_dir: Path | None, results_dir: Path, preset: str) -> list[tuple[Path, Path, str]]:
    """(cell directory, raw copy path, its text) of every finished cell of `preset` under
    `runs_dir` (one holding an eval.json), each read back and checked first."""
    if runs_dir is None:
        return []
    if not runs_dir.is_dir():
        what = "is a file, not a directory of runs" if runs_dir.exists() else "does not exist"
        raise ValueError(f"--runs-dir {runs_dir} {what}; give the directory `snac table` trained in")
    source, target = runs_dir / preset, results_dir / "table" / preset
    if source.is_dir() and target.is_dir() and source.resolve() == target.resolve():
        raise ValueError(f"--runs-dir {runs_dir} is the report's own copy under {results_dir / 'table'}")
    planned = []
    for directory in sorted(p.parent for p in source.glob(f"*/*/{EVAL_FILE}")):
        text = read_cell(directory)
        destination = target / directory.parent.name / (directory.name + RAW_SUFFIX)
        refuse_links(results_dir, destination)
        planned.append((directory, destination, text))
    return planned


def load_raw(results_dir: Path, preset: str, pending: dict[Path, str]) -> dict[str, dict[str, dict]]:
    """algorithm -> cell name -> its raw copy (`read_raw`) of every copy of `preset`, as they
    will be once `pending` is written. Anything else in the preset's folder is refused, named."""
    root = results_dir / "table" / preset
    paths = {p for p in pending if p.parent.parent == root}
    for entry in sorted(root.glob("*/*")) if root.is_dir() else []:
        if entry.name.startswith("."):  # an interrupted atomic write's
            continue
        if entry.is_symlink() or not entry.is_file() or entry.suffix != RAW_SUFFIX:
            raise ValueError(
                f"{entry} is not a cell's raw copy (a file <task>[.<arm>]{RAW_SUFFIX}); move it out of the results"
            )
        paths.add(entry)
    raw: dict[str, dict[str, dict]] = {}
    for path in sorted(paths):
        raw.setdefault(path.parent.name, {})[path.name.removesuffix(RAW_SUFFIX)] = read_raw(path, pending.get(path))
    arms = [n for cells in raw.values() for n, f in cells.items() if "variant" in f["cell"]]
    if arms and len(arms) < sum(map(len, raw.values())):
        raise ValueError(f"{root}: cells without a variant beside cells of an ablation's arms in the same preset")
    return raw


def seed_means(files: dict) -> list[float]:
    """Per-seed protocol means of one cell, in seed order."""
    return [float(r["mean"]) for r in files["eval"].values()]


def budget_record(cells: list[dict]) -> dict[str, Any]:
    """The budget of one or more cells (a column's shapes): env steps per seed per task, the
    budget requested, why, and the training wall time from their curves (None where not kept)."""
    kept = all(c.get("metrics") for c in cells)
    return {
        "env_steps_per_seed": {c["config"]["task"]: c["config"]["total_steps"] for c in cells},
        "requested_per_seed": {c["config"]["task"]: c["cell"]["budget"]["requested"] for c in cells},
        "source": "; ".join(dict.fromkeys(c["cell"]["budget"]["source"] for c in cells)),
        "training_wall_s": round(sum(c["metrics"][-1]["wall_s"] for c in cells), 1) if kept else None,
    }


def number(value: float | None, digits: int = 3) -> str:
    return "—" if value is None else f"{value:.{digits}f}"


def interval(value: float, ci: list[float], signed: bool = False) -> str:
    """`mean [low, high]` as the pages print a cell (`signed`: a difference, with its sign)."""
    sign = "+" if signed else ""
    return f"{value:{sign}.3f} [{ci[0]:{sign}.3f}, {ci[1]:{sign}.3f}]"


def steps_text(n: int) -> str:
    return f"{n / 1e6:.3g}M" if n >= 1e6 else f"{n / 1e3:.3g}k" if n >= 1e3 else str(n)


def budget_text(budget: dict) -> str:
    """A budget record as the tables print it: env steps per seed, `*` where a task trained
    below the budget requested for it."""
    steps = sorted(set(budget["env_steps_per_seed"].values()))
    text = steps_text(steps[0]) if len(steps) == 1 else f"{steps_text(steps[0])}–{steps_text(steps[-1])}"
    below = any(n < budget["requested_per_seed"][task] for task, n in budget["env_steps_per_seed"].items())
    return text + ("*" if below else "")
