"""The raw results of `snac table`: each finished cell of a runs directory (its `config.json`,
`eval.json`, `cell.json` and learning curve `metrics.jsonl`; never checkpoints) copied into one
JSON file, `bench/results/table/<preset>/<algorithm>/<task>[.<arm>].json`, holding
{"cell", "config", "eval", "curve"} (`schemas.RAW_CELL_JSON`), and read back from there, so that
every table, curve and training wall time can be rebuilt from the repository with one file per
cell. A cell whose curve was not kept has an empty `curve`. An ablation's base arm that adopted
another preset's run is not copied again: it is read from that preset's copy (`with_adopted_bases`).

Every cell is read back whole and checked (`agents.table.files.read_cell`, `read_raw`) before
anything is written: a damaged cell stops the report with its file and field named, and no file
is written through a symbolic link inside the results folder."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

from agents.table.files import EVAL_FILE, RAW_SUFFIX, check_raw_size, read_cell, read_raw, record_path
from agents.table.presets import BASE_ARM, Preset, Variant
from snac_jax.atomic import atomic_write_text


def run_cells_in(root: Path) -> list[Path]:
    """The cell directories under a runs directory's preset folder that hold an eval.json
    (finished, or damaged)."""
    return sorted(p.parent for p in root.glob(f"*/*/{EVAL_FILE}"))


def raw_files(root: Path) -> list[Path]:
    """The raw copies under a preset's folder of the results (`<algorithm>/<cell>.json`). Anything
    else there (a cell's directory, another file) is a `ValueError` naming it: the report leaves
    no cell out unread. Names starting with a dot (an interrupted atomic write's) are skipped."""
    found = []
    for entry in sorted(root.glob("*/*")) if root.is_dir() else []:
        if entry.name.startswith("."):
            continue
        if entry.is_symlink() or not entry.is_file() or entry.suffix != RAW_SUFFIX:
            raise ValueError(
                f"{entry} is not a cell's raw copy (a file <task>[.<arm>]{RAW_SUFFIX}); move it out of the results"
            )
        found.append(entry)
    return found


def refuse_links(root: Path, path: Path) -> None:
    """`ValueError` when `path`, or a folder between `root` and it, is a symbolic link: what the
    report writes under `root` lands there, never through a link somewhere else."""
    parts = path.relative_to(root).parts
    for depth in range(1, len(parts) + 1):
        part = root.joinpath(*parts[:depth])
        if part.is_symlink():
            raise ValueError(
                f"{part} is a symbolic link inside {root}; the report writes no file through a link: "
                "replace it with the file or folder itself"
            )


def _finite(value: Any) -> Any:
    """`value` with every float that is not finite as None: a curve is strict JSON, as
    `agents.training.driver` writes metrics.jsonl (a chunk in which no episode ended has a null mean)."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, list):
        return [_finite(v) for v in value]
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    return value


def raw_text(files: dict) -> str:
    """A cell's raw copy as written: {"cell", "config", "eval", "curve"} indented, each curve
    record on one line, strict JSON (`_finite`)."""
    parts = [
        f'  "{name}": ' + json.dumps(files[name], indent=2, allow_nan=False).replace("\n", "\n  ")
        for name in ("cell", "config", "eval")
    ]
    curve = ",\n".join("    " + json.dumps(_finite(r), allow_nan=False) for r in files["metrics"])
    parts.append('  "curve": ' + (f"[\n{curve}\n  ]" if curve else "[]"))
    return "{\n" + ",\n".join(parts) + "\n}\n"


Pending = dict[Path, "str | None"]
"""What the report is about to do under the results, before it does it: a raw copy's path and the
text it will hold, or None where it removes the file. Readers given it (`load_raw`,
`with_adopted_bases`) see the results as they will be, so everything is checked before a write."""


def copies(runs_dir: str | Path | None, results_dir: str | Path, preset: str) -> list[tuple[Path, Path, str | None]]:
    """What `write_copies` does: (cell directory, destination file, its text) of every finished
    cell of `preset` under `runs_dir` (None: no runs, nothing), each read back whole first
    (`files.read_cell`: a damaged cell is a `ValueError` naming the file and field, never left
    out), and every destination checked to hold no link. A base arm whose run is already in the
    record as the preset's it adopted (`_copy_of_its_record`) is not copied; text None: an older
    copy of it at the destination is removed, so the record holds the run once. A copy that already
    holds the cell's run (`_holds_the_run`) is left as it is, so the record does not depend on which
    report wrote it last or on whether the runs directory was there: two writers (this one, and
    `bases_to_keep` from the old record) give the same run different cell metadata."""
    if runs_dir is None:
        return []
    runs_dir, results_dir = Path(runs_dir), Path(results_dir)
    if not runs_dir.is_dir():
        raise ValueError(
            f"--runs-dir {runs_dir} "
            + ("is a file, not a directory of runs" if runs_dir.exists() else "does not exist")
            + "; give the directory `snac table` trained in"
        )
    source, target = runs_dir / preset, results_dir / "table" / preset
    if source.is_dir() and target.is_dir() and source.resolve() == target.resolve():
        raise ValueError(
            f"--runs-dir {runs_dir} is the report's own copy under {results_dir / 'table'}; give the "
            "directory `snac table` trained in"
        )
    planned = []
    for directory in run_cells_in(source):
        files = read_cell(directory)
        destination = (target / directory.relative_to(source)).with_name(directory.name + RAW_SUFFIX)
        refuse_links(results_dir, destination)
        if not _copy_of_its_record(files, results_dir):
            if not _holds_the_run(destination, files):
                text = raw_text(files)
                check_raw_size(len(text.encode()), f"{directory}: its raw copy would be")
                planned.append((directory, destination, text))
        elif destination.is_file():
            planned.append((directory, destination, None))
    return planned


def _holds_the_run(destination: Path, files: dict) -> bool:
    """Whether the raw copy at `destination` holds the run of the finished cell `files`
    (`_same_run`); a copy that cannot be read does not, so the run's own files replace it."""
    if not destination.is_file():
        return False
    try:
        return _same_run(read_raw(destination), _run_of(files))
    except ValueError:
        return False


def _run_of(files: dict) -> dict:
    """The run of a finished cell (`read_cell`) in `read_raw`'s form, as its raw copy would hold it
    (the curve strict JSON), for `_same_run`."""
    from agents.training.registry import config_from_json

    return {
        "config": config_from_json(files["config"]).to_json(),
        "eval": files["eval"],
        "metrics": json.loads(raw_text(files))["curve"],
    }


def _same_run(a: dict, b: dict) -> bool:
    """Whether two raw copies (`read_raw`'s form) hold the same run: config, scores and curve."""
    return a["config"] == b["config"] and a["eval"] == b["eval"] and a["metrics"] == b["metrics"]


def _copy_of_its_record(files: dict, results_dir: Path) -> bool:
    """Whether a finished cell (`read_cell`) is a plain base arm that adopted another preset's cell
    whose raw copy is in the record with the same run (`_same_run`): the report keeps one copy of a
    run (`with_adopted_bases` reads the base from there), not one per preset that adopts it. An arm
    scored acting otherwise has scores of its own, and a base arm that changes anything is read as
    its own (`with_adopted_bases` reads none such), so both are copied."""
    cell = files["cell"]
    adopted_from = cell.get("adopted_from")
    if (
        not adopted_from
        or cell.get("variant") != BASE_ARM
        or cell.get("evaluation")
        or cell.get("switches")
        or cell.get("settings")
    ):
        return False
    path = record_path(results_dir, *adopted_from.split("/"))  # `<preset>/<algorithm>/<task>`
    return path.is_file() and _same_run(read_raw(path), _run_of(files))


def _as_base(record: dict, adopts: str, algorithm: str, task: str, paper_name: str) -> dict:
    """The base arm read from the raw copy `record` of preset `adopts`' cell it adopted."""
    return {
        **record,
        "cell": {
            **record["cell"],
            "variant": BASE_ARM,
            "paper_variant": paper_name,
            "switches": "",
            "settings": {},
            "adopted_from": f"{adopts}/{algorithm}/{task}",
        },
    }


def _adopted_tasks(raw: dict[str, dict[str, dict]], base: Variant):
    """(algorithm, its cells, task) for every task of `base` an ablation's copies (`load_raw`) have."""
    for algorithm, cells in raw.items():
        for task in sorted({files["cell"]["task"] for files in cells.values()} & set(base.tasks)):
            yield algorithm, cells, task


def _is_file(path: Path, pending: Pending) -> bool:
    return pending[path] is not None if path in pending else path.is_file()


READ_FROM_ADOPTED = "read_from_adopted"
"""The key `with_adopted_bases` sets on a base arm it read from the adopted preset's copy. A base
arm that adopted a run but has a copy of its own holds that run as it was when adopted (the
adopted cell's record now holds another run, e.g. one trained again: `bases_to_keep`), so the
table says where the run lives."""


def with_adopted_bases(
    raw: dict[str, dict[str, dict]], results_dir: str | Path, preset: Preset | None, pending: Pending | None = None
) -> dict[str, dict[str, dict]]:
    """`raw` (`load_raw`, the cells of `preset`, None: a preset budgets.toml no longer has) with
    each base arm the preset adopts from another (`adopts`) read from that preset's raw copy
    (`_copy_of_its_record` left it uncopied), for every (learner, task of the base arm) with
    other arms but no base copy of its own; `pending` as `load_raw`'s. The record must still be
    the run the arms were measured against: its config must equal every other arm's but for what
    that arm changes (its switches and settings), or the report stops, naming the file
    (`bases_to_keep` keeps the old run where the report itself replaces that record)."""
    base, pending = preset.adopted_base() if preset is not None else None, pending or {}
    if base is None:
        return raw
    results_dir = Path(results_dir)
    for algorithm, cells, task in list(_adopted_tasks(raw, base)):
        path = record_path(results_dir, preset.adopts, algorithm, task)
        if f"{task}.{BASE_ARM}" in cells or not _is_file(path, pending):
            continue
        record = read_raw(path, pending.get(path))
        for arm, files in cells.items():
            if files["cell"]["task"] != task:
                continue
            changed = {"switches", *files["cell"].get("settings", {})}
            differ = sorted(
                k
                for k in set(record["config"]) | set(files["config"])
                if k not in changed and record["config"].get(k) != files["config"].get(k)
            )
            if differ:
                raise ValueError(
                    f"{path} is the base of {algorithm}/{arm} (adopted), but their configs differ in "
                    f"{', '.join(differ)} beyond the arm's own changes: the record changed since the "
                    "arm trained; train the base arm again (--arms base) or restore that record"
                )
        cells[f"{task}.{BASE_ARM}"] = {
            **_as_base(record, preset.adopts, algorithm, task, base.paper),
            READ_FROM_ADOPTED: True,
        }
    return raw


def bases_to_keep(
    results_dir: str | Path, reported: str, presets: dict[str, Preset], pending: Pending
) -> dict[Path, str]:
    """The base copies the report must write before it replaces (`pending`) a raw copy of preset
    `reported` that another preset reads as its adopted base (`with_adopted_bases`): that
    preset's own `<task>.base.json` holding the run its arms were measured against, so a cell
    trained again leaves the ablations that adopted the old one as they were."""
    results_dir, keep = Path(results_dir), {}
    for name, preset in presets.items():
        base = preset.adopted_base()
        if base is None or preset.adopts != reported:
            continue
        for algorithm, _, task in _adopted_tasks(load_raw(results_dir, name), base):
            own = record_path(results_dir, name, algorithm, f"{task}.{BASE_ARM}")
            adopted = record_path(results_dir, reported, algorithm, task)
            if own.is_file() or adopted not in pending or not adopted.is_file():
                continue
            old = read_raw(adopted)
            if pending[adopted] is not None and _same_run(old, read_raw(adopted, pending[adopted])):
                continue
            refuse_links(results_dir, own)
            keep[own] = raw_text(_as_base(old, reported, algorithm, task, base.paper))
    return keep


def write_copies(planned: list[tuple[Path, Path, str | None]]) -> list[Path]:
    """Carry out `copies`' plan: each text written atomically, each None's file removed; returns
    the files written."""
    written = []
    for _, destination, text in planned:
        if text is None:
            destination.unlink(missing_ok=True)
        else:
            atomic_write_text(destination, text)
            written.append(destination)
    return written


def load_raw(results_dir: str | Path, preset: str, pending: Pending | None = None) -> dict[str, dict[str, dict]]:
    """algorithm -> cell (the task, and an ablation's arm) -> {"config", "eval", "cell", "metrics"}
    of the raw copies ("metrics": the curve's records, empty where not kept), as they will be
    after `pending`. A damaged copy is a `ValueError` naming the file and the field."""
    pending, root = pending or {}, Path(results_dir) / "table" / preset
    paths = {p for p in raw_files(root) if pending.get(p, "") is not None}
    paths |= {p for p, text in pending.items() if text is not None and p.parent.parent == root}
    raw: dict[str, dict[str, dict]] = {}
    plain = []
    for path in sorted(paths):
        files = raw.setdefault(path.parent.name, {})[path.name.removesuffix(RAW_SUFFIX)] = read_raw(
            path, pending.get(path)
        )
        if "variant" not in files["cell"]:
            plain.append(path)
    if plain and len(plain) < sum(map(len, raw.values())):
        raise ValueError(f"{plain[0]}: cell: no variant, beside cells of an ablation's arms in the same preset")
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
    the budget its preset asked when it was planned (more where the run trained under the
    wall-time cap the table once had, and was kept as it is) and why, and the training wall time
    it took."""
    budgets = [c["cell"]["budget"] for c in cells]
    return {
        "env_steps_per_seed": {c["config"]["task"]: c["config"]["total_steps"] for c in cells},
        "requested_per_seed": {c["config"]["task"]: b["requested"] for c, b in zip(cells, budgets)},
        "source": "; ".join(dict.fromkeys(b["source"] for b in budgets)),
        "training_wall_s": training_wall_s(cells),
    }


def _steps(n: int) -> str:
    return f"{n / 1e6:.3g}M" if n >= 1e6 else f"{n / 1e3:.3g}k"


def budget_text(budget: dict) -> str:
    """A budget record as the tables print it: env steps per seed, `*` where a task trained
    below the budget requested for it."""
    steps = sorted(set(budget["env_steps_per_seed"].values()))
    text = _steps(steps[0]) if len(steps) == 1 else f"{_steps(steps[0])}–{_steps(steps[-1])}"
    below = any(n < budget["requested_per_seed"][task] for task, n in budget["env_steps_per_seed"].items())
    return text + ("*" if below else "")
