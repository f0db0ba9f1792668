"""Running the plan of `snac table`: each new or partial cell is one `agents.training.driver.train`
call (a started one resumes from its last checkpoint), then its learning curve and the reporting
protocol (`REPORT_EVAL_SEED`) on every seed's greedy policy. Finished cells are skipped. An arm with `evaluation` settings trains nothing: it scores the base arm's finished run
(`Cell.base_run`) again, acting with them, beside a copy of that run's config and curve."""

from __future__ import annotations

import shutil

from agents.table.files import CELL_FILE, CURVE_FILE
from agents.table.plan import Cell, cell_state, scoring_config
from agents.training import checkpoint
from snac_jax.atomic import atomic_write_json
from snac_jax.evaluation import REPORT_EVAL_SEED


def run_cell(
    cell: Cell, *, progress: bool = True, stop_after_chunks: int | None = None, num_devices: int | None = None
) -> bool:
    """Train (or resume) and evaluate one cell; True when it finished (`stop_after_chunks`, the
    tests' stand-in for a killed run, can leave it unfinished). The cell's directory is locked
    (another process on it is refused), and where it stands is read again under the lock."""
    from agents.training.cli import evaluate_run
    from agents.training.driver import chunk_sizes, read_metrics, train
    from agents.training.plotting import plot_curve
    from agents.training.registry import build_algorithm
    from agents.training.trained import load_trained
    from snac_jax import devices

    if cell.status == "done":
        return True
    with checkpoint.lock_run(cell.directory):
        cell_state(cell)
        if cell.status == "done":
            return True
        if cell.evaluation:  # the base arm's run, its config and curve beside this arm's scores
            algorithm, state, _ = load_trained(cell.base_run)
            for name in (checkpoint.CONFIG_FILE, checkpoint.METRICS_FILE):
                shutil.copyfile(cell.base_run / name, cell.directory / name)
        else:
            algorithm, state = train(
                cell.config,
                cell.directory,
                resume=(cell.directory / checkpoint.CONFIG_FILE).is_file(),
                progress=progress,
                stop_after_chunks=stop_after_chunks,
                mesh=devices.env_mesh(num_devices, cell.config.num_envs),
            )
        atomic_write_json(cell.directory / CELL_FILE, cell.record())
        last = len(chunk_sizes(cell.config.num_updates, cell.config.chunks)) - 1
        if not cell.evaluation and checkpoint.latest_chunk(cell.directory) != last:
            records = checkpoint.read_metrics_lines(cell.directory / checkpoint.METRICS_FILE)
            cell.status, cell.done_steps = "partial", (records[-1]["env_steps"] if records else 0)
            return False
        title = f"{cell.algorithm} on {cell.task} ({cell.preset.name} preset)"
        plot_curve(read_metrics(cell.directory), cell.task, title, cell.directory / CURVE_FILE)
        if cell.evaluation:
            algorithm = build_algorithm(scoring_config(algorithm.config, cell.evaluation))
        evaluate_run(algorithm, state, cell.directory, None, seed=REPORT_EVAL_SEED, counts=cell.preset.protocol)
    cell.status, cell.done_steps = "done", cell.total_steps
    return True


def run_cells(
    cells: list[Cell], *, progress: bool = True, stop_after_chunks: int | None = None, num_devices: int | None = None
) -> int:
    """Run every unfinished cell in order under one progress bar over the grid's env steps, the
    preset's folder locked for the whole grid; returns how many cells are finished."""
    from tqdm.auto import tqdm

    if not cells:
        return 0
    with checkpoint.lock_run(cells[0].directory.parent.parent):
        total = sum(c.total_steps * c.config.seeds for c in cells)
        done = sum(c.done_steps * c.config.seeds for c in cells)
        name = cells[0].preset.name
        bar = tqdm(total=total, initial=done, unit="step", unit_scale=True, desc=f"table {name}", disable=not progress)
        try:
            for index, cell in enumerate(cells):
                if cell.status == "done":
                    continue
                bar.set_postfix_str(f"cell {index + 1}/{len(cells)}: {cell.algorithm} {cell.task}")
                before = cell.done_steps
                run_cell(cell, progress=progress, stop_after_chunks=stop_after_chunks, num_devices=num_devices)
                bar.update((cell.done_steps - before) * cell.config.seeds)
        finally:
            bar.close()
    return sum(c.status == "done" for c in cells)
