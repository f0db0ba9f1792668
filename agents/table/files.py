"""The files of `snac table`'s cells: reading them back (each against its schema in
`agents.training.schemas`, then against each other) and what a runner may touch in a runs directory.

A cell directory (`<runs-dir>/<preset>/<algorithm>/<task>[.<arm>]/`) holds one run of `agents.training.driver`
with `cell.json` beside it. A runner deletes nothing and starts no run over files it did not
make: a directory given as a cell's holds nothing (a free lock aside), or this cell's own start cut
short before its first checkpoint (which it trains again from the start), or it is refused,
named, before anything runs. A cell copied from another preset's raw copy (`record_copy`) holds
that run's files but its checkpoints: finished, never trained or evaluated again; so is a cell
whose files came back without checkpoints from the machine it trained on (`own_files`). The report
(`agents.table.raw`) reads finished cells with `read_cell`, and their one-file copies under
`bench/results/table/` with `read_raw`; both refuse a damaged cell naming the file and the field
instead of leaving it out.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from agents.training import checkpoint, schemas
from snac_jax.designs import NUM_TEST_DESIGNS
from snac_jax.evaluation import REPORT_EVAL_SEED
from snac_jax.schema import loads_json
from snac_jax.tasks import task_spec

CELL_FILE = "cell.json"
EVAL_FILE = "eval.json"
RAW_SUFFIX = ".json"
"""A raw copy's file name is its cell's directory name with this suffix (`read_raw`)."""
RAW_COPY_MAX_BYTES = 8 * 2**20
"""The largest raw copy the report reads, and writes. It reads every copy of a preset whole (then
parses and checks it), so a file of hundreds of MB, damaged or another file under a cell's name,
would take the memory and the minutes of the machine before any check named it. The largest
committed copy is 26 kB (bench/results/table/tuned/sac/2d-dynamic-dense.json: 20 chunks of
curve, records of up to 0.9 kB each): 8 MiB holds a curve of some 9,000 chunks."""
RESTARTABLE = {checkpoint.CONFIG_FILE, checkpoint.METRICS_FILE, checkpoint.CHECKPOINT_DIR}
"""What a cell's run leaves before its first checkpoint (`agents.training.driver`), besides its lock."""
RECORD_FIELD = "adopted_record"
"""cell.json's field naming the raw copy a cell was copied from (`record_copy`)."""
CURVE_FILE = "curve.png"
COPY_FILES = {CELL_FILE, checkpoint.CONFIG_FILE, EVAL_FILE, checkpoint.METRICS_FILE, CURVE_FILE}
"""What a cell copied from a raw copy holds: its run's files but the checkpoints (`record_copy`)."""


def expected_episodes(task: str, protocol: dict[str, int]) -> int:
    if task_spec(task).dynamic:
        return protocol["episodes_per_test_design"] * NUM_TEST_DESIGNS
    return protocol["static_episodes"]


def eval_problem(results: dict, seeds: int, episodes: int | None, seed: int) -> str | None:
    """Why a schema-checked eval.json is not a finished result of the cell (one row per training
    seed, scored with the evaluation key `seed` over `episodes` episodes each), or None."""
    if len(results) != seeds:
        return f"holds {len(results)} result(s), the run has seeds {seeds}"
    for name, row in results.items():
        if row["seed"] != seed:
            return f"['{name}'].seed is {row['seed']}, the cell is scored with evaluation key {seed}"
        if episodes is not None and row["episodes"] != episodes:
            return f"['{name}'].episodes is {row['episodes']}, the cell's protocol has {episodes}"
    return None


def eval_is_valid(path: Path, seeds: int, episodes: int | None = None, seed: int = REPORT_EVAL_SEED) -> bool:
    """Whether eval.json holds a finished result of the run (`eval_problem`); a missing, damaged
    or foreign one is not (the runner evaluates the run again)."""
    try:
        results = schemas.load(path, schemas.EVAL_JSON)
    except (OSError, ValueError):
        return False
    return eval_problem(results, seeds, episodes, seed) is None


def new_cell_leftovers(directory: Path, same_settings: Callable[[Any], bool]) -> bool:
    """For a cell without a checkpoint: False where its directory is absent or empty (a free lock
    aside), True where it holds only what this cell's start left before its first checkpoint
    (config.json with the cell's settings, a metrics.jsonl without records, a checkpoints/ folder
    with none in it), which the run trains again from the start. Anything else is a `ValueError`
    naming the directory: the table never deletes or overwrites files it did not make."""
    if directory.is_symlink() or (directory.exists() and not directory.is_dir()):
        raise ValueError(
            f"{directory} is not a directory (a link or a file), where a cell of the table goes; "
            "choose another --runs-dir"
        )
    try:
        checkpoint.check_new_run_directory(directory)
        return False
    except ValueError as error:
        if "is not empty" not in str(error):
            raise
    checkpoint.check_lock_file(directory)
    entries = sorted(p.name for p in directory.iterdir() if p.name != checkpoint.LOCK_FILE)
    ours = set(entries) <= RESTARTABLE and checkpoint.CONFIG_FILE in entries
    try:
        ours = ours and same_settings(checkpoint.read_config(directory))
    except ValueError:
        ours = False
    if ours and checkpoint.read_metrics_lines(directory / checkpoint.METRICS_FILE):
        raise ValueError(
            f"{directory} holds a start of this cell whose {checkpoint.METRICS_FILE} records chunks that "
            "no checkpoint kept; the table deletes nothing it did not make: remove that directory to "
            "train the cell from the start"
        )
    if not ours:
        shown = ", ".join(entries[:6]) + (", ..." if len(entries) > 6 else "")
        raise ValueError(
            f"{directory} holds files that no start of this cell left there ({shown}) and no checkpoint; "
            "the table deletes nothing it did not make: move that directory away, or choose another "
            "--runs-dir"
        )
    return True


def check_finished_without_checkpoints(directory: Path, config, episodes: int) -> None:
    """A cell's own files back without checkpoints (`own_files`) with the cell's settings `config`
    must be a finished run: an eval.json that is a finished result of the cell (`episodes` per
    seed), a metrics.jsonl through the run's last chunk, and files that agree with each other
    (`read_cell`). Else a `ValueError`: nothing is left to resume or evaluate the run from."""
    from agents.training.driver import chunk_sizes

    where = f"{directory} holds this cell's files without checkpoints"
    if not eval_is_valid(directory / EVAL_FILE, config.seeds, episodes):
        raise ValueError(f"{where} and no finished {EVAL_FILE}: nothing is left to evaluate; move that directory away")
    records = checkpoint.read_metrics_lines(directory / checkpoint.METRICS_FILE)
    chunks = len(chunk_sizes(config.num_updates, config.chunks))
    if not records or records[-1]["chunk"] != chunks - 1:
        raise ValueError(
            f"{where}, and its {checkpoint.METRICS_FILE} records {len(records)} of the run's {chunks} "
            "chunks: its training did not finish, and nothing is left to resume it from; move that "
            "directory away"
        )
    read_cell(directory)


def check_cell(
    config, cell: dict, results: dict, *, name: str, algorithm: str, cell_where: str, eval_where: str, config_where: str
) -> None:
    """The checks between a cell's parts, each already read against its schema: `cell` and the
    config name the same algorithm and task, an arm's cell names its arm whole, the cell stands
    where its algorithm and name say (`name`, `algorithm`: its directory's or file's), and
    `results` is a finished result of it (`eval_problem`). `*_where`: how an error names each part."""
    for key, value in (("algorithm", config.algorithm), ("task", config.task)):
        if cell[key] != value:
            raise ValueError(f"{cell_where}: {key} is {cell[key]!r}, its {config_where} has {value!r}")
    arm = [k for k in ("variant", "paper_variant", "switches") if k in cell]
    if arm and len(arm) != 3:
        missing = sorted({"variant", "paper_variant", "switches"} - set(arm))
        raise ValueError(f"{cell_where}: an arm's cell needs variant, paper_variant and switches; {missing} missing")
    own = cell["task"] + (f".{cell['variant']}" if "variant" in cell else "")
    if name != own or algorithm != cell["algorithm"]:
        raise ValueError(
            f"{cell_where}: its algorithm and task ({cell['algorithm']}/{own}) are not where it stands "
            f"({algorithm}/{name})"
        )
    problem = eval_problem(results, config.seeds, expected_episodes(cell["task"], cell["protocol"]), cell["eval_seed"])
    if problem is not None:
        raise ValueError(
            f"{eval_where}: {problem} (from {cell_where} and {config_where}); evaluate the cell "
            "again with `snac table` or move it away"
        )


def check_raw_size(size: int, what: str) -> None:
    """`ValueError` where `size` bytes are past `RAW_COPY_MAX_BYTES`; `what`: the file (or the
    cell's files) that has them, as the error names it."""
    if size > RAW_COPY_MAX_BYTES:
        raise ValueError(
            f"{what} {size:,} bytes, over the {RAW_COPY_MAX_BYTES:,}-byte limit of a cell's raw copy "
            "(agents.table.files.RAW_COPY_MAX_BYTES): not a cell's record, or a damaged one; move it away"
        )


def read_cell(directory: Path) -> dict[str, Any]:
    """A finished cell's files in a runs directory, each checked against its schema and against
    the others (`check_cell`): {"config" (as written), "eval", "cell", "metrics"} ("metrics": its
    curve, empty where not kept). `ValueError` naming the file and the field of the first problem;
    files that add up past `RAW_COPY_MAX_BYTES` (their copy would) are refused before any is read."""
    cell_path, eval_path = directory / CELL_FILE, directory / EVAL_FILE
    if not cell_path.is_file():
        raise ValueError(f"{cell_path} is missing: {directory} is not a cell of the table")
    read = (cell_path, eval_path, directory / checkpoint.CONFIG_FILE, directory / checkpoint.METRICS_FILE)
    check_raw_size(sum(p.stat().st_size for p in read if p.is_file()), f"{directory}: its cell's files are")
    config = checkpoint.read_config(directory)
    cell = schemas.load(cell_path, schemas.CELL_JSON)
    results = schemas.load(eval_path, schemas.EVAL_JSON)
    check_cell(
        config,
        cell,
        results,
        name=directory.name,
        algorithm=directory.parent.name,
        cell_where=str(cell_path),
        eval_where=str(eval_path),
        config_where=checkpoint.CONFIG_FILE,
    )
    return {
        "config": schemas.load(directory / checkpoint.CONFIG_FILE, schemas.CONFIG_JSON),
        "eval": results,
        "cell": cell,
        "metrics": checkpoint.read_metrics_lines(directory / checkpoint.METRICS_FILE),
    }


def read_raw(path: Path, text: str | None = None) -> dict[str, Any]:
    """A cell's raw copy under `bench/results/table/<preset>/<algorithm>/<task>[.<arm>].json`, one
    file holding {"cell", "config", "eval", "curve"} (`schemas.RAW_CELL_JSON`: each part against the
    schema of the file it was copied from), checked as `read_cell` checks a cell's files; `text`:
    what the report is about to write there, read in its place. Returns {"config" (the config
    class's full settings), "eval", "cell", "metrics" (the curve)}; `ValueError` naming the file
    and the field (`eval['<seed>'].mean`) of the first problem; a file past `RAW_COPY_MAX_BYTES`
    is refused unread."""
    from agents.training.registry import config_from_json

    check_raw_size(path.stat().st_size if text is None else len(text.encode()), f"{path} is")
    record = (
        schemas.load(path, schemas.RAW_CELL_JSON) if text is None else loads_json(text, schemas.RAW_CELL_JSON, path)
    )
    try:
        config = config_from_json(record["config"])
    except (TypeError, ValueError) as error:
        raise ValueError(f"{path}: config: {error}") from error
    check_cell(
        config,
        record["cell"],
        record["eval"],
        name=path.name.removesuffix(RAW_SUFFIX),
        algorithm=path.parent.name,
        cell_where=f"{path}: cell",
        eval_where=f"{path}: eval",
        config_where="config",
    )
    return {"config": config.to_json(), "eval": record["eval"], "cell": record["cell"], "metrics": record["curve"]}


def record_path(results_dir: str | Path, preset: str, algorithm: str, name: str) -> Path:
    """Where the report keeps the raw copy of `preset`'s cell `<algorithm>/<name>`."""
    return Path(results_dir) / "table" / preset / algorithm / (name + RAW_SUFFIX)


def read_record(path: Path, same_settings: Callable[[Any], bool], episodes: int | None):
    """The config (a `TrainConfig`) and raw copy (`read_raw`) at `path` where it is a finished run
    with a cell's settings (`same_settings(config)`, called last) scored with its protocol
    (`episodes`), seeds and the reporting key; None where there is no such file or it is another
    run. A damaged copy is a `ValueError` naming the file: it is the repository's record, which the
    report refuses as well, so it is mended, never trained over unseen."""
    from agents.training.registry import config_from_json

    if not path.exists() and not path.is_symlink():
        return None
    try:
        raw = read_raw(path)
    except OSError as error:
        raise ValueError(f"{path}: not readable ({error}); restore it from git or move it away") from error
    config = config_from_json(raw["config"])
    if eval_problem(raw["eval"], config.seeds, episodes, REPORT_EVAL_SEED) is not None or not same_settings(config):
        return None
    return config, raw


def record_copy(directory: Path, owner: tuple) -> dict | None:
    """The cell.json of a cell copied from a raw copy (it names the copy in `RECORD_FIELD`) where
    `directory` holds one of the cell `owner` (its preset, algorithm, task, arm or None), whole or
    cut short (a subset of `COPY_FILES` with its cell.json, which the copy writes first); None for
    any other directory, which the table treats as any directory without checkpoints."""
    cell = own_files(directory, owner)
    return cell if cell is not None and RECORD_FIELD in cell else None


def own_files(directory: Path, owner: tuple) -> dict | None:
    """The cell.json where `directory` holds the cell `owner`'s files but its checkpoints (a subset
    of `COPY_FILES` with its cell.json): a raw copy's copy (`record_copy`), or a cell that trained
    on another machine and came back without its checkpoints. None for any other directory."""
    if directory.is_symlink() or not (directory / CELL_FILE).is_file():
        return None
    entries = {p.name for p in directory.iterdir() if p.name != checkpoint.LOCK_FILE}
    if not entries <= COPY_FILES or any((directory / e).is_symlink() or not (directory / e).is_file() for e in entries):
        return None
    try:
        cell = schemas.load(directory / CELL_FILE, schemas.CELL_JSON)
    except (OSError, ValueError):
        return None
    return cell if (cell["preset"], cell["algorithm"], cell["task"], cell.get("variant")) == tuple(owner) else None
