"""Running the plan of `snac table`: each unfinished cell is one `agents.training.driver.train` call (a
started one resumes from its last checkpoint), then its learning curve and the reporting
protocol (`REPORT_EVAL_SEED`) on every seed's greedy policy. Finished cells are skipped, and a
cell whose preset adopts another's finished run with the same settings copies that run instead,
or that run's raw copy in the record (`adopt_record`); an arm that only acts otherwise when scored
(`Variant.evaluation`) copies the run and scores its policy again, acting with the arm's settings."""

from __future__ import annotations

import contextlib
import json
import shutil
import tempfile
from pathlib import Path

from agents.table.files import CELL_FILE, EVAL_FILE
from agents.table.plan import Cell, cell_state, own_copy, record_twin
from agents.table.scoring import adoption_kept, scoring_config
from agents.training import checkpoint
from agents.training.config import save_config
from snac_jax.atomic import atomic_write_json
from snac_jax.evaluation import REPORT_EVAL_SEED


def run_cell(
    cell: Cell, *, progress: bool = True, stop_after_chunks: int | None = None, num_devices: int | None = None
) -> bool:
    """Train (or resume) and evaluate one cell; True when it finished (`stop_after_chunks`, the
    tests' stand-in for a killed run, can leave it unfinished). `num_devices`: how many devices
    the worlds are split over (default: as `snac train`).

    The cell's directory is locked first (`checkpoint.lock_run`: another process working on it
    is refused at once), and where it stands is read again under the lock, so nothing another
    process made since the plan is trained over, and a cell finished meanwhile is left as it is."""
    from agents.training.cli import evaluate_run
    from agents.training.driver import chunk_sizes, train
    from agents.training.registry import build_algorithm
    from snac_jax import devices

    if cell.status == "done":
        return True
    with checkpoint.lock_run(cell.directory):
        cell_state(cell)
        if cell.status == "done":
            return True
        started = (cell.directory / checkpoint.CONFIG_FILE).is_file()  # new: this cell's start, cut before a checkpoint
        if cell.status == "new" and cell.adopts_record and (not started or own_copy(cell) is not None):
            adopt_record(cell)  # a copy cut short included: it is completed
            return True
        if cell.status == "new" and cell.adopts_from is not None and not started:
            adopt(cell)
            if not cell.evaluation:
                return True
            started = True  # the twin's finished run, to be scored again acting with the arm's settings
        elif cell.status == "new":  # a start cut before its first checkpoint (a copy's, too) trains afresh
            cell.adopts_from, cell.adopts_record = None, False
        algorithm, state = train(
            cell.config,
            cell.directory,
            resume=started,
            progress=progress,
            stop_after_chunks=stop_after_chunks,
            mesh=devices.env_mesh(num_devices, cell.config.num_envs),
        )
        atomic_write_json(cell.directory / CELL_FILE, adoption_kept(cell.directory, cell.record()))
        last = checkpoint.latest_chunk(cell.directory)
        if last != len(chunk_sizes(cell.config.num_updates, cell.config.chunks)) - 1:
            cell.status = "partial"
            return False
        _plot_curve(cell, cell.directory)
        if cell.evaluation:
            algorithm = build_algorithm(
                scoring_config(algorithm.config, cell.evaluation)
            )  # the trained params, acting so
        evaluate_run(algorithm, state, cell.directory, None, seed=REPORT_EVAL_SEED, counts=cell.preset.protocol)
    cell.status = "done"
    return True


def adopt(cell: Cell) -> None:
    """Take over the cell's twin (`Cell.adopts_from`): its whole run (checkpoints, metrics,
    eval.json; not its lock) copied, with this cell's own cell.json and a curve titled for this
    cell. The copy is assembled in a folder of its own under `<algorithm>/.adopting/`, then moved
    into the cell's (locked, empty) directory one entry at a time with eval.json last: a kill
    leaves either no eval.json (a run with every checkpoint, which the next plan resumes and
    evaluates) or the whole cell. An arm that scores the policy again acting otherwise
    (`Cell.evaluation`) takes everything but eval.json: the run, for `run_cell` to score."""
    skipped = [checkpoint.LOCK_FILE] + ([EVAL_FILE] if cell.evaluation else [])

    def copy(staging: Path) -> None:
        shutil.copytree(
            cell.adopts_from, staging, symlinks=True, dirs_exist_ok=True, ignore=shutil.ignore_patterns(*skipped)
        )

    _assemble(cell, copy, cell_json_first=False)
    if cell.evaluation:
        cell.status = "partial"  # a finished run, not yet scored as this arm


def adopt_record(cell: Cell) -> None:
    """Take over the cell's twin from the record (`Cell.adopts_record`: `adopts_from` is a raw
    copy, read and checked again here, under the cell's lock): its config.json, eval.json and
    curve as metrics.jsonl, with this cell's cell.json naming the copy and a curve titled for this
    cell; no checkpoints, so the cell is never trained or evaluated again. Assembled and moved in
    as `adopt` does, cell.json first and eval.json last: a kill leaves either the whole cell or a
    copy cut short without eval.json, which the next plan sees as this cell's and completes
    (`plan.cell_state`)."""
    found = record_twin(cell, cell.adopts_from)
    if found is None:
        raise ValueError(
            f"{cell.adopts_from} is no longer a finished run with the settings of {cell.directory}; plan again"
        )
    config, raw = found

    def copy(staging: Path) -> None:
        save_config(config, staging / checkpoint.CONFIG_FILE)
        (staging / checkpoint.METRICS_FILE).write_text("".join(json.dumps(r) + "\n" for r in raw["metrics"]))
        atomic_write_json(staging / EVAL_FILE, raw["eval"])

    _assemble(cell, copy, cell_json_first=True)


def _assemble(cell: Cell, copy, *, cell_json_first: bool) -> None:
    """Fill a folder of the cell's own under `<algorithm>/.adopting/` (`copy(folder)`, then this
    cell's cell.json and curve), then move it into the cell's (locked) directory one entry at a
    time, eval.json last. `cell_json_first`: a record's copy moves cell.json first, so a copy cut
    short is recognised as this cell's and completed (`plan.own_copy`); a run's copy keeps
    cell.json for the end (before eval.json), so a copy cut short is a run with its checkpoints,
    which the next plan resumes."""
    holder = cell.directory.parent / ".adopting"
    holder.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f"{cell.directory.name}.", dir=holder))
    try:
        copy(staging)
        atomic_write_json(staging / CELL_FILE, cell.record())
        _plot_curve(cell, staging)
        first = (lambda p: p.name != CELL_FILE) if cell_json_first else (lambda p: p.name == CELL_FILE)
        for entry in sorted(staging.iterdir(), key=lambda p: 2 * (p.name == EVAL_FILE) + first(p)):
            entry.rename(cell.directory / entry.name)
    finally:
        shutil.rmtree(staging, ignore_errors=True)  # made by this call; empty unless the copy failed
    with contextlib.suppress(OSError):  # another cell's copy may be under way there
        holder.rmdir()
    cell.status = "done"


def _plot_curve(cell: Cell, directory: Path) -> None:
    """The cell's learning curve from the run's metrics in `directory`, titled with its preset."""
    from agents.training.driver import read_metrics
    from agents.training.plotting import plot_curve

    plot_curve(
        read_metrics(directory),
        cell.task,
        f"{cell.algorithm} on {cell.task} ({cell.preset.name} preset)",
        directory / "curve.png",
    )


def run_cells(
    cells: list[Cell], *, progress: bool = True, stop_after_chunks: int | None = None, num_devices: int | None = None
) -> int:
    """Run every unfinished cell in order under one progress bar over the grid's env steps;
    returns how many cells are finished. The preset's folder is locked for the whole grid, so a
    second `snac table` on the same runs directory and preset is refused before it touches a
    cell."""
    if not cells:
        return 0
    with checkpoint.lock_run(cells[0].directory.parent.parent):
        return _run_cells(cells, progress, stop_after_chunks, num_devices)


def _run_cells(cells: list[Cell], progress: bool, stop_after_chunks: int | None, num_devices: int | None) -> int:
    from tqdm.auto import tqdm

    total = sum(c.total_steps * c.config.seeds for c in cells)
    done = sum(c.done_steps * c.config.seeds for c in cells)
    name = cells[0].preset.name
    bar = tqdm(
        total=total,
        initial=done,
        unit="step",
        unit_scale=True,
        desc=f"table {name}",
        disable=not progress,
        dynamic_ncols=True,
        position=0,
    )
    try:
        for index, cell in enumerate(cells):
            if cell.status == "done":
                continue
            bar.set_postfix_str(f"cell {index + 1}/{len(cells)}: {cell.algorithm} {cell.task}")
            before = cell.done_steps
            finished = run_cell(cell, progress=progress, stop_after_chunks=stop_after_chunks, num_devices=num_devices)
            steps = cell.total_steps if finished else _done_steps(cell)
            bar.update((steps - before) * cell.config.seeds)
    finally:
        bar.close()
    return sum(c.status == "done" for c in cells)


def _done_steps(cell: Cell) -> int:
    records = checkpoint.read_metrics_lines(cell.directory / checkpoint.METRICS_FILE)
    return records[-1]["env_steps"] if records else 0
