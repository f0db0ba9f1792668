"""The command-line cases of `bench/robustness.py` and the scratch folder they run in: a tiny
trained run, damaged copies of it, doctored human records, files in the way."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

SHORT = ["--total-steps", "256", "--num-envs", "16", "--rollout-steps", "8", "--no-progress", "--eval-episodes", "2"]
TINY = [
    "--num-envs",
    "16",
    "--rollout-steps",
    "8",
    "--num-minibatches",
    "2",
    "--update-epochs",
    "1",
    "--hidden-size",
    "8",
    "--rnn-size",
    "8",
    "--no-progress",
    "--devices",
    "1",
]


def setup(work: Path, snac) -> dict:
    """The run, records and files the cases use (`snac(work, *argv)` runs the command)."""
    made = {}
    made["run"] = snac(
        work,
        "train",
        "ppo",
        "--task",
        "1d-static-sin",
        *TINY,
        "--total-steps",
        "256",
        "--chunks",
        "2",
        "--max-steps",
        "40",
        "--eval-episodes",
        "2",
        "--out",
        "run",
    )
    run = work / "run"
    for name in ("finished", "torn", "damaged", "damaged-eval", "edited"):
        shutil.copytree(run, work / name)
    shutil.rmtree(work / "finished" / "checkpoints")
    with (work / "torn" / "metrics.jsonl").open("a") as f:
        f.write('{"chunk": 2, "wa')
    for name in ("damaged", "damaged-eval"):
        cut = work / name / "checkpoints" / "1" / "default" / "_METADATA"
        cut.write_bytes(cut.read_bytes()[: cut.stat().st_size // 2])
    edited = json.loads((work / "edited" / "config.json").read_text())
    (work / "edited" / "config.json").write_text(json.dumps({**edited, "hidden_size": 16}))
    (work / "corrupt").mkdir()
    (work / "corrupt" / "config.json").write_text('{"algorithm": "ppo", ')
    (work / "mine").mkdir()
    (work / "mine" / "config.json").write_text('{"mine": true}\n')
    (work / "locked").mkdir()
    (work / "file").write_text("a file, not a folder\n")
    (work / "bad_paper.json").write_text("{")
    (work / "empty_traces.json").write_text("[]")
    human_records(work)
    table_files(work)
    made["sweep"] = sweep_files(work, snac)
    return made


SWEEP_VALUES = "0.001,0.03"


def sweep_files(work: Path, snac) -> dict:
    """A tiny finished sweep (2 arms x 2 seeds) and hand-edited copies of it; a run whose newest
    checkpoint's metadata store has bytes flipped."""
    made = snac(
        work,
        "train",
        "ppo",
        "--task",
        "1d-static-sin",
        *TINY,
        "--total-steps",
        "256",
        "--chunks",
        "2",
        "--max-steps",
        "40",
        "--seeds",
        "2",
        "--no-eval",
        "--sweep",
        f"learning-rate={SWEEP_VALUES}",
        "--out",
        "sweep",
    )
    edits = {
        "sweep-negative": {"names": ["learning_rate"], "arms": [[-1.0], [0.03]]},
        "sweep-valid-edit": {"names": ["learning_rate"], "arms": [[0.001], [0.02]]},
        "sweep-int": {"names": ["num_envs"], "arms": [[8], [16]]},
        "sweep-unknown": {"names": ["lr"], "arms": [[0.001], [0.03]]},
    }
    for name, grid in edits.items():
        shutil.copytree(work / "sweep", work / name)
        (work / name / "sweep.json").write_text(json.dumps(grid))
    shutil.copytree(work / "sweep", work / "sweep-link")
    shutil.move(work / "sweep-link" / "arms" / "0", work / "outside-arm")
    (work / "sweep-link" / "arms" / "0").symlink_to(work / "outside-arm")
    shutil.copytree(work / "sweep", work / "sweep-lost-arm")
    (work / "sweep-lost-arm" / "arms" / "1" / "config.json").unlink()
    shutil.copytree(work / "run", work / "bitflip")
    for path in (work / "bitflip" / "checkpoints" / "1" / "default" / "d").iterdir():
        data = bytearray(path.read_bytes())
        for i in range(0, len(data), max(1, len(data) // 8)):
            data[i] ^= 0x10
        path.write_bytes(bytes(data))
    (work / "garbage.json").write_text("{not json")
    return made


def human_records(work: Path) -> None:
    """An honest record from the game, and doctored copies of it, one file each."""
    os.environ.setdefault("SDL_VIDEODRIVER", "dummy")
    import numpy as np

    from snac_jax.human.game import GameSession
    from snac_jax.human.records import EpisodeRecord

    session = GameSession("2d-static-sparse", "eval", seed=3, max_steps=3)
    for key in ("space", "right", "space"):
        session.press(key)
    honest = session.records[0]
    one_brick = np.zeros((20, 20), int)
    one_brick[0, 0] = 1
    doctored = {
        "honest": {},
        "action-99": {"actions": [99, *honest.actions[1:]]},
        "too-many-actions": {"actions": honest.actions + [4, 4], "strides": honest.strides + [1, 1]},
        "design-shape": {"design": [[1]]},
        "one-brick-design": {
            "design": one_brick.tolist(),
            "iou": 1.0,
            "actions": [4],
            "strides": [1],
            "max_steps": 1,
            "total_reward": 5.0,
            "bricks_used": 1,
        },
        "bricks": {"bricks_used": honest.bricks_used + 3},
        "reward": {"total_reward": honest.total_reward + 50},
        "terminated": {"terminated": not honest.terminated},
    }
    for name, changes in doctored.items():  # written as they are (append_record would refuse most of them)
        (work / f"human-{name}.jsonl").write_text(EpisodeRecord(**{**vars(honest), **changes}).to_json() + "\n")
    text = (work / "human-honest.jsonl").read_text()
    (work / "human-torn.jsonl").write_text(text + text[: len(text) // 2])


def table_files(work: Path) -> None:
    """Runs directories for `snac table`: a finished cell made from the tiny run (its config and
    eval.json, a cell.json saying how it was scored), damaged copies of it, another run's files
    where a cell goes, links where a lock, a report or a README goes; and damaged run.json files."""
    from agents.table.readme import BEGIN, END
    from snac_jax.evaluation import TUNING_EVAL_SEED

    good = work / "good-runs" / "smoke" / "ppo" / "1d-static-sin"
    good.mkdir(parents=True)
    for name in ("config.json", "eval.json", "metrics.jsonl"):
        shutil.copyfile(work / "run" / name, good / name)
    (good / "cell.json").write_text(
        json.dumps(
            {
                "preset": "smoke",
                "algorithm": "ppo",
                "column": "1d-static",
                "task": "1d-static-sin",
                "budget": {"env_steps": 256, "requested": 256, "source": "robustness"},
                "eval_seed": TUNING_EVAL_SEED,
                "protocol": {"static_episodes": 2, "episodes_per_test_design": 1},
            }
        )
    )

    def damaged(name: str, file: str, edit) -> None:
        cell = work / f"{name}-runs" / "smoke" / "ppo" / "1d-static-sin"
        shutil.copytree(good, cell)
        (cell / file).write_text(edit((cell / file).read_text()))

    def edit_json(change):
        return lambda text: json.dumps(change(json.loads(text)))

    damaged("layout", "metrics.jsonl", lambda text: text)  # another run's finished files, without checkpoints
    damaged("iou", "eval.json", edit_json(lambda d: {k: {**v, "mean": 7.5, "min": -3.0} for k, v in d.items()}))
    damaged("nan", "eval.json", edit_json(lambda d: {k: {**v, "mean": float("nan")} for k, v in d.items()}))
    damaged("cut-eval", "eval.json", lambda text: text[: len(text) // 2])
    damaged("garbage-cell", "cell.json", lambda text: "garbage")
    damaged("list-cell", "cell.json", lambda text: "[]")
    damaged("no-protocol", "cell.json", edit_json(lambda d: {k: v for k, v in d.items() if k != "protocol"}))
    damaged("bad-task", "cell.json", edit_json(lambda d: {**d, "task": "1d-static-sine"}))
    damaged("string-seeds", "config.json", edit_json(lambda d: {**d, "seeds": "2"}))
    damaged("empty-config", "config.json", lambda text: "{}")
    impossible = {
        "min-above-mean": {"mean": 0.5, "min": 0.9, "ci95": [0.4, 0.6]},
        "no-brick": {"mean": 0.99, "min": 0.99, "ci95": [0.98, 1.0], "mean_bricks_used": 0.0},
    }
    for name, change in impossible.items():
        damaged(name, "eval.json", edit_json(lambda d, change=change: {k: {**v, **change} for k, v in d.items()}))
    huge = work / "huge-results" / "table" / "smoke" / "ppo" / "1d-static-gauss.json"
    huge.parent.mkdir(parents=True)
    with huge.open("wb") as f:  # sparse: 916 MB on paper, no disk
        f.truncate(916 * 10**6)
    (work / "table-runs" / "smoke").mkdir(parents=True)
    (work / "linklock").mkdir()
    (work / "precious.txt").write_text("a file outside the run\n")
    (work / "linklock" / ".lock").symlink_to(work / "precious.txt")
    (work / "link-results").mkdir()
    (work / "link-results" / "table.md").symlink_to(work / "precious.txt")
    (work / "readme.md").write_text(f"intro\n{BEGIN}\nold\n{END}\n")
    (work / "readme-link.md").symlink_to(work / "readme.md")
    for name, options in (
        ("runjson-string", '{"eval_episodes": 2, "no_eval": "false"}'),
        ("runjson-negative", '{"eval_episodes": -5, "no_eval": false}'),
    ):
        shutil.copytree(work / "run", work / name)
        (work / name / "run.json").write_text(options)


def snapshot(*paths: Path):
    """A check that `paths` still hold the bytes they hold now (a path absent now must stay
    absent). Taken when the cases are built; with no scratch folder (`cli_cases` called only to
    list the cases) every path is absent and nothing is read."""
    before = {path: path.read_bytes() if path.exists() else None for path in paths}
    return lambda: all((path.read_bytes() if path.exists() else None) == data for path, data in before.items())


def files_in(folder: Path) -> list[Path]:
    """The entries of `folder`; none where it does not exist (the cases only listed)."""
    return list(folder.iterdir()) if folder.is_dir() else []


def table_cases(work: Path) -> list[dict]:
    """`snac table`, its runs directory, `--report`, the lock and run.json (see `table_files`)."""

    def unchanged(*paths: Path):
        return snapshot(*paths)

    cell = ["--preset", "smoke", "--algorithms", "ppo", "--tasks", "1d-static-sin", "--no-progress"]
    report = ["table", "--preset", "smoke", "--report"]
    damaged = [
        ("cut-eval", "a truncated eval.json", "eval.json is not valid JSON"),
        ("nan", "a NaN mean in eval.json", "mean must be a finite number in [0, 1], got nan"),
        ("garbage-cell", "a garbage cell.json", "cell.json is not valid JSON"),
        ("list-cell", "cell.json = []", "cell.json must hold a JSON object, got list"),
        ("no-protocol", "a cell.json without protocol", "cell.json: protocol is missing"),
        ("bad-task", "a bad task id in cell.json", "cell.json: unknown task '1d-static-sine'"),
        ("string-seeds", 'config.json with "seeds": "2"', "config.json: seeds must be an int >= 1, got '2'"),
        ("empty-config", "config.json = {}", "config.json: algorithm is missing"),
    ]
    return [
        dict(
            what="table on a runs directory another table run holds",
            argv=["table", *cell, "--runs-dir", "table-runs"],
            refuse="is in use by",
            hold_lock=work / "table-runs" / "smoke",
            also=lambda: sorted(p.name for p in (work / "table-runs" / "smoke").iterdir()) == [".lock"],
        ),
        dict(
            what="table --runs-dir holding another run's cell files (the report's layout)",
            argv=["table", *cell, "--runs-dir", "layout-runs"],
            refuse="the table deletes nothing it did not make",
            also=unchanged(*files_in(work / "layout-runs" / "smoke" / "ppo" / "1d-static-sin")),
        ),
        dict(
            what="train --out DIR whose .lock is a link to a file outside",
            argv=["train", "ppo", *SHORT, "--out", "linklock"],
            refuse="is a symbolic link",
            also=unchanged(work / "precious.txt"),
        ),
        dict(
            what="table --report with an impossible IoU (mean 7.5, min -3)",
            argv=[*report, "--runs-dir", "iou-runs", "--results-dir", "iou-results"],
            refuse="mean must be a finite number in [0, 1], got 7.5",
            also=lambda: not (work / "iou-results").exists(),
        ),
        dict(
            what="table --algorithms ppo ppo --dry-run (a cell named twice)",
            argv=["table", *cell[:3], "ppo", *cell[3:], "--runs-dir", "dup-runs", "--dry-run"],
            check=lambda: not (work / "dup-runs").exists(),
            phrase_ok="1 cells,",
        ),
        dict(
            what="table --report --dry-run",
            argv=[*report, "--dry-run", "--runs-dir", "good-runs", "--results-dir", "dry-results"],
            check=lambda: not (work / "dry-results").exists(),
            phrase_ok="would write",
        ),
        dict(
            what="table --report --runs-dir DIR that does not exist",
            argv=[*report, "--runs-dir", "nowhere"],
            refuse="does not exist",
        ),
        dict(what="table --report --runs-dir FILE", argv=[*report, "--runs-dir", "file"], refuse="is a file"),
        *[
            dict(
                what=f"table --report: {what}",
                argv=[*report, "--runs-dir", f"{name}-runs", "--results-dir", f"{name}-results"],
                refuse=phrase,
                also=lambda name=name: not (work / f"{name}-results").exists(),
            )
            for name, what, phrase in damaged
        ],
        dict(
            what="table --report --readme LINK",
            argv=[*report, "--runs-dir", "good-runs", "--results-dir", "readme-results", "--readme", "readme-link.md"],
            refuse="is a symbolic link",
            also=lambda: (work / "readme-link.md").is_symlink() and not (work / "readme-results").exists(),
        ),
        dict(
            what="table --report where table.md is a link to a file outside",
            argv=[*report, "--runs-dir", "good-runs", "--results-dir", "link-results"],
            refuse="is a symbolic link inside",
            also=unchanged(work / "precious.txt"),
        ),
        dict(
            what="table --report on a good cell",
            argv=[*report, "--runs-dir", "good-runs", "--results-dir", "good-results"],
            check=lambda: (
                "eval"
                in json.loads((work / "good-results" / "table" / "smoke" / "ppo" / "1d-static-sin.json").read_text())
            ),
        ),
        dict(
            what='train --resume RUN whose run.json says "no_eval": "false"',
            argv=["train", "ppo", "--resume", "runjson-string"],
            refuse="no_eval must be true or false",
            also=unchanged(work / "runjson-string" / "metrics.jsonl"),
        ),
        dict(
            what="train --resume RUN whose run.json says eval_episodes -5",
            argv=["train", "ppo", "--resume", "runjson-negative"],
            refuse="eval_episodes must be an int >= 1",
            also=unchanged(work / "runjson-negative" / "metrics.jsonl"),
        ),
    ]


def cli_cases(work: Path) -> list[dict]:
    """(what, argv, phrase of the refusal) or (what, argv, check of a success) per case."""

    def file_unchanged(path: Path):
        return snapshot(path)

    def eval_json(name):
        return json.loads((work / name / "eval.json").read_text())["1d-static-sin"]

    def metrics_chunks(name):
        return [json.loads(line)["chunk"] for line in (work / name / "metrics.jsonl").read_text().splitlines() if line]

    return [
        # run directories
        dict(
            what="train --out DIR holding a finished run without checkpoints/",
            argv=["train", "ppo", *SHORT, "--out", "finished"],
            refuse="is not empty",
            also=file_unchanged(work / "finished" / "metrics.jsonl"),
        ),
        dict(
            what="train --out DIR holding an unrelated config.json",
            argv=["train", "ppo", *SHORT, "--out", "mine"],
            refuse="is not empty",
            also=file_unchanged(work / "mine" / "config.json"),
        ),
        dict(
            what="train --out DIR while another process holds DIR",
            argv=["train", "ppo", *SHORT, "--out", "locked"],
            refuse="is in use by",
            hold_lock=work / "locked",
        ),
        dict(
            what="train --out FILE/run (parent is a file)",
            argv=["train", "ppo", *SHORT, "--out", "file/run"],
            refuse="not a directory",
        ),
        dict(
            what="train --resume RUN --total-steps 512 (changing the run)",
            argv=["train", "ppo", "--resume", "run", "--total-steps", "512"],
            refuse="cannot change it",
        ),
        dict(
            what="train dqn --resume RUN (a ppo run)",
            argv=["train", "dqn", "--resume", "run"],
            refuse="holds a ppo run",
        ),
        dict(
            what="train --resume RUN keeps --eval-episodes 2 and --max-steps 40",
            argv=["train", "ppo", "--resume", "run"],
            check=lambda: (
                eval_json("run")["episodes"] == 2
                and eval_json("run")["mean_length"] <= 40
                and metrics_chunks("run") == [0, 1]
            ),
        ),
        dict(
            what="train --resume RUN whose metrics.jsonl ends in a torn line",
            argv=["train", "ppo", "--resume", "torn"],
            check=lambda: metrics_chunks("torn") == [0, 1],
        ),
        dict(
            what="train --resume RUN whose newest checkpoint is truncated",
            argv=["train", "ppo", "--resume", "damaged"],
            check=lambda: metrics_chunks("damaged") == [0, 1] and (work / "damaged" / "checkpoints" / "1").is_dir(),
            phrase_ok="resuming from an earlier checkpoint",
        ),
        dict(
            what="eval --checkpoint RUN whose newest checkpoint is truncated",
            argv=["eval", "--checkpoint", "damaged-eval"],
            refuse="is intact: `snac train ppo --resume",
        ),
        dict(
            what="train --resume RUN with an edited config.json (hidden_size)",
            argv=["train", "ppo", "--resume", "edited"],
            refuse="does not hold the state its config.json describes",
        ),
        dict(
            what="train --resume DIR with a corrupt config.json",
            argv=["train", "ppo", "--resume", "corrupt"],
            refuse="corrupt/config.json is not valid JSON",
        ),
        dict(
            what="train --resume RUN whose checkpoints/ is gone",
            argv=["train", "ppo", "--resume", "finished"],
            refuse="records 2 chunk(s) but there is no checkpoint",
        ),
        dict(
            what="train --total-steps 1 (banner) with --eval-episodes 10**12",
            argv=["train", "ppo", *TINY, "--total-steps", "1", "--eval-episodes", "1000000000000", "--out", "b1"],
            refuse="episodes at once needs about",
            also=lambda: True,
            banner="128 env steps (total_steps 1 rounded",
        ),
        dict(
            what="train --num-envs 1000000000",
            argv=["train", "ppo", "--num-envs", "1000000000", "--out", "big"],
            refuse="1,000,000,000 worlds needs about",
            memory=True,
        ),
        dict(
            what="train --total-steps 10**20",
            argv=["train", "ppo", "--total-steps", str(10**20), "--out", "long"],
            refuse="updates are counted in int32",
        ),
        dict(
            what="train --seed 4294967296",
            argv=["train", "ppo", "--seed", "4294967296"],
            refuse="seed: must be an int in",
        ),
        dict(what="train --task 4d-static", argv=["train", "ppo", "--task", "4d-static"], refuse="unknown task"),
        # human records
        *[
            dict(what=f"eval --human: {what}", argv=["eval", "--human", f"human-{name}.jsonl"], refuse=phrase)
            for name, what, phrase in [
                ("action-99", "an action out of range (99)", "actions must be in 0..4, got 99"),
                ("too-many-actions", "more actions than the step limit", "more than the step limit"),
                ("design-shape", "a 1x1 design on a 20x20 task", "design must be 20 x 20"),
                ("one-brick-design", "a one-brick design on a 20x20 task claiming IoU 1", "its design is not"),
                ("bricks", "more bricks claimed than used", "claims bricks used"),
                ("reward", "a larger reward claimed", "claims total reward"),
                ("terminated", "the termination flag flipped", "claims terminated"),
                ("torn", "a file whose last line is cut", "not a valid human record"),
                ("missing", "a file that does not exist", "no human record file"),
            ]
        ],
        dict(
            what="eval --human: an honest record",
            argv=["eval", "--human", "human-honest.jsonl"],
            check=lambda: True,
            phrase_ok="| 2d-static-sparse | 1 |",
        ),
        # play
        dict(
            what="play --record DIR",
            argv=["play", "--task", "1d-static-sin", "--record", "."],
            refuse="is a directory",
            timeout=120,
        ),
        dict(
            what="play --record FILE/h.jsonl",
            argv=["play", "--task", "1d-static-sin", "--record", "file/h.jsonl"],
            refuse="not a directory",
            timeout=120,
        ),
        # sizes
        dict(
            what="rollout --num-envs 1000000000",
            argv=["rollout", "--num-envs", "1000000000", "--steps", "2"],
            refuse="worlds needs about",
            memory=True,
        ),
        dict(
            what="eval --episodes 1000000000",
            argv=["eval", "--policy", "random", "--task", "1d-static-sin", "--episodes", "1000000000"],
            refuse="episodes at once needs about",
            memory=True,
        ),
        dict(
            what="render --cell 100000",
            argv=["render", "--task", "2d-static-dense", "--out", "x.gif", "--cell", "100000"],
            refuse="one frame at --cell 100000 needs about",
            memory=True,
        ),
        dict(
            what="render --cell 3",
            argv=["render", "--task", "2d-static-dense", "--out", "x.gif", "--cell", "3"],
            refuse="must be an int >= 4",
        ),
        # trained runs, rendered and evaluated
        dict(
            what="render --checkpoint RUN",
            argv=["render", "--task", "1d-static-sin", "--checkpoint", "run", "--out", "run.gif"],
            check=lambda: (work / "run.gif").stat().st_size > 0,
        ),
        dict(
            what="render --checkpoint RUN on another task",
            argv=["render", "--task", "1d-static-step", "--checkpoint", "run", "--out", "other.gif"],
            refuse="trained on '1d-static-sin'",
        ),
        dict(
            what="eval --checkpoint RUN (trained with --max-steps 40)",
            argv=["eval", "--checkpoint", "run", "--episodes", "3", "--json", "ev.json"],
            check=lambda: json.loads((work / "ev.json").read_text())["1d-static-sin"]["mean_length"] <= 40,
            phrase_ok="{'max_steps': 40}",
        ),
        dict(
            what="eval --checkpoint RUN --task 1d-static (other shapes)",
            argv=["eval", "--checkpoint", "run", "--task", "1d-static"],
            refuse="cannot be evaluated on 1d-static-gauss",
        ),
        dict(
            what="eval --checkpoint DIR that is not a run",
            argv=["eval", "--checkpoint", "mine"],
            refuse="mine/config.json",
        ),
        dict(
            what="eval --checkpoint DIR that does not exist",
            argv=["eval", "--checkpoint", "nowhere"],
            refuse="not a training run directory",
        ),
        # outputs checked first
        dict(
            what="eval --json DIR",
            argv=["eval", "--policy", "random", "--task", "1d-static-sin", "--json", "."],
            refuse="is a directory",
        ),
        dict(
            what="eval --json FILE/x.json",
            argv=["eval", "--policy", "random", "--task", "1d-static-sin", "--json", "file/x.json"],
            refuse="not a directory",
        ),
        dict(
            what="render --out FILE/x.gif",
            argv=["render", "--task", "1d-static-sin", "--out", "file/x.gif"],
            refuse="not a directory",
        ),
        dict(
            what="render --out x.png",
            argv=["render", "--task", "1d-static-sin", "--out", "x.png"],
            refuse="must name a .gif",
        ),
        dict(
            what="eval --paper-results (corrupt JSON)",
            argv=[
                "eval",
                "--policy",
                "random",
                "--task",
                "1d-static-sin",
                "--episodes",
                "2",
                "--paper-results",
                "bad_paper.json",
            ],
            refuse="bad_paper.json: not valid JSON",
        ),
        # numbers
        dict(
            what="rollout --seed 4294967296",
            argv=["rollout", "--seed", "4294967296"],
            refuse="must be an int in 0..4294967295",
        ),
        dict(
            what="eval --seed -1",
            argv=["eval", "--policy", "random", "--task", "1d-static-sin", "--episodes", "2", "--seed", "-1"],
            refuse="must be an int in 0..4294967295",
        ),
        dict(
            what="render --max-steps 2147483648",
            argv=["render", "--task", "1d-static-sin", "--out", "m.gif", "--max-steps", "2147483648"],
            refuse="max_steps must be an int in 1..2147483647",
        ),
        dict(what="rollout --steps 0", argv=["rollout", "--steps", "0"], refuse="must be an int >= 1"),
        dict(what="rollout --task 2d-static", argv=["rollout", "--task", "2d-static"], refuse="allowed: 1d-static-sin"),
        dict(what="eval --policy nope", argv=["eval", "--policy", "nope"], refuse="registered policies"),
        dict(
            what="eval with two sources",
            argv=["eval", "--policy", "random", "--human", "human-honest.jsonl"],
            refuse="exactly one of",
        ),
        *training_cases(work),
        *table_cases(work),
        *issue69_cases(work),
    ]


def issue69_cases(work: Path) -> list[dict]:
    """Sweep records edited by hand, the newest surfaces' rough edges (issue 69)."""

    def sweep_config(name: str) -> dict:
        return json.loads((work / name / "config.json").read_text())

    lr = "--sweep learning-rate="
    cases = [
        dict(
            what="train --resume SWEEP whose sweep.json sets learning_rate -1",
            argv=["train", "ppo", "--resume", "sweep-negative", "--no-progress"],
            refuse="sweep.json: learning_rate must be a number > 0, got -1.0",
            also=snapshot(work / "sweep-negative" / "metrics.jsonl"),
        ),
        dict(
            what="train --resume SWEEP whose sweep.json was validly edited (0.03 -> 0.02)",
            argv=["train", "ppo", "--resume", "sweep-valid-edit", "--no-progress"],
            refuse="arms/1/config.json disagrees with",
        ),
        dict(
            what="train --resume SWEEP whose sweep.json names an int setting",
            argv=["train", "ppo", "--resume", "sweep-int", "--no-progress"],
            refuse="num_envs cannot be swept in one program",
            one_line=1,
        ),
        dict(
            what="train --resume SWEEP whose sweep.json names an unknown setting",
            argv=["train", "ppo", "--resume", "sweep-unknown", "--no-progress"],
            refuse="ppo has no setting 'lr'",
            one_line=1,
        ),
        *(
            dict(
                what=f"train {lr}{values} ({why})",
                argv=["train", "ppo", *SHORT, "--sweep", f"learning-rate={values}", "--out", f"sweep-{why[:4]}"],
                refuse=phrase,
                also=lambda why=why: not (work / f"sweep-{why[:4]}").exists(),
            )
            for values, why, phrase in (
                ("1e39,0.1", "inf in float32", "is inf in float32"),
                ("1e-50,0.1", "0 in float32", "is 0 in float32"),
                ("0.1,0.1000000001", "two arms equal in float32", "are the same arm in float32"),
            )
        ),
        dict(
            what="a sweep's top-level config.json names its swept settings, not a default value",
            argv=["train", "ppo", "--resume", "sweep", "--no-progress", "--no-eval"],
            check=lambda: (
                "learning_rate" not in sweep_config("sweep") and sweep_config("sweep")["swept"] == ["learning_rate"]
            ),
        ),
        dict(
            what="eval --checkpoint SWEEP --seed-index 3 names arm 1 and its seed",
            argv=["eval", "--checkpoint", "sweep", "--seed-index", "3", "--episodes", "2", "--devices", "1"],
            phrase_ok="arm 1 (learning_rate=0.03), training seed index 1 (run index 3)",
        ),
        dict(
            what="train --resume SWEEP whose arms/0 is a link to a folder outside the run",
            argv=["train", "ppo", "--resume", "sweep-link", "--no-progress", "--no-eval"],
            refuse="is not the run's own folder",
            also=snapshot(work / "outside-arm" / "metrics.jsonl"),
        ),
        dict(
            what="train --resume SWEEP whose arms/1/config.json was deleted",
            argv=["train", "ppo", "--resume", "sweep-lost-arm", "--no-progress", "--no-eval"],
            phrase_ok="arms/1/config.json was missing; rewritten from",
            check=lambda: (
                json.loads((work / "sweep-lost-arm" / "arms" / "1" / "config.json").read_text())["learning_rate"]
                == 0.03
            ),
        ),
        dict(
            what="train's final table of a run scored with --max-steps 40 has no paper row",
            argv=["train", "ppo", "--resume", "run", "--no-progress"],
            phrase_ok="with {'max_steps': 40} (no paper row)",
        ),
        dict(
            what="eval --checkpoint RUN whose newest checkpoint has flipped bytes",
            argv=["eval", "--checkpoint", "bitflip", "--episodes", "2", "--devices", "1"],
            refuse="checkpoint 1 cannot be read",
            one_line=2,  # the run's settings, then the error
        ),
        dict(what="rollout --steps 2**31", argv=["rollout", "--steps", "2147483648"], refuse="1..2147483647"),
        *(
            dict(
                what=f"device_check.py {' '.join(args)}",
                argv=["--out", "dc", *args],
                script="bench/device_check.py",
                refuse=phrase,
                also=lambda: not (work / "dc").exists(),
            )
            for args, phrase in (
                (["--skip", "step", "learn", "readme", "gymnasium"], "leaves nothing to measure"),
                (["--budget-s", "0"], "--budget-s must be > 0 seconds, got 0"),
                (["--budget-s", "-5"], "--budget-s must be > 0 seconds, got -5"),
            )
        ),
        *(
            dict(
                what=f"robustness.py {' '.join(args)}",
                argv=args,
                script="bench/robustness.py",
                refuse=phrase,
                also=lambda: not (work / "probe").exists(),
            )
            for args, phrase in (
                (["--out", "probe", "--from-json", "garbage.json"], "--from-json garbage.json is not JSON"),
                (["--out", "probe", "--from-json", "missing.json"], "--from-json missing.json cannot be read"),
                (["--out", "probe", "--from-json", "run/config.json"], "is not a robustness.json"),
                (
                    ["--out", "probe", "--before", "garbage.json", "--from-json", "x"],
                    "--before garbage.json is not JSON",
                ),
                (["--out", "file"], "--out file is a file"),
            )
        ),
        *(
            dict(
                what=f"[69 also] table --report: {what}",
                argv=["table", "--preset", "smoke", "--report", "--runs-dir", runs, "--results-dir", results],
                refuse=phrase,
                also=lambda results=results: not (work / results / "table.md").exists(),
            )
            for what, runs, results, phrase in (
                (
                    "a 916 MB cell file in the results (sparse)",
                    "good-runs",
                    "huge-results",
                    "is 916,000,000 bytes, over the 8,388,608-byte limit",
                ),
                ("eval.json with min 0.9 above its mean 0.5", "min-above-mean-runs", "mab-results", "above its mean"),
                (
                    "eval.json with IoU 0.99 and no brick laid",
                    "no-brick-runs",
                    "nb-results",
                    "mean is 0.99 with mean_bricks_used 0",
                ),
            )
        ),
        dict(
            what="[69 also] train --switches landmark_action=\u0664 (an Arabic-Indic 4)",
            argv=["train", "ppo", *SHORT, "--task", "2d-static-sparse", "--switches", "landmark_action=\u0664"]
            + ["--out", "switch-digit"],
            refuse="ASCII only",
            also=lambda: not (work / "switch-digit").exists(),
        ),
        dict(
            what="[69 also] table --preset multi --dry-run in an empty runs directory: its total estimate",
            argv=["table", "--preset", "multi", "--dry-run", "--runs-dir", "multi-runs"],
            phrase_ok="total estimate: unknown (6 new",
            check=lambda: not (work / "multi-runs").exists(),
        ),
        dict(  # described without its phrase: a description holding it would match it, and run every case
            what="robustness.py --only with a phrase no case has",
            argv=["--out", "probe", "--only", "zz-none"],
            script="bench/robustness.py",
            refuse="matches no case",
            also=lambda: not (work / "probe").exists(),
        ),
    ]
    return [{**case, "group": "issue 69"} for case in cases]


def training_cases(work: Path) -> list[dict]:
    """Training that would learn nothing, diverge, or be interrupted; sweeps and reset strategies."""

    def strict_lines(path: Path) -> list[dict]:
        def refuse(constant):
            raise ValueError(f"not strict JSON: {constant}")

        return [json.loads(line, parse_constant=refuse) for line in path.read_text().splitlines() if line]

    small = ["--num-envs", "8", "--rollout-steps", "8", "--total-steps", "256", "--no-progress"]
    return [
        dict(
            what="train dqn --learning-starts beyond the whole budget",
            argv=["train", "dqn", *small, "--learning-starts", "100000", "--out", "late-dqn"],
            refuse="learning_starts must be at most 256",
            also=lambda: not (work / "late-dqn").exists(),
        ),
        dict(
            what="train sac --learning-starts one step past the budget",
            argv=["train", "sac", *small, "--learning-starts", "257", "--out", "late-sac"],
            refuse="learning_starts must be at most 256",
            also=lambda: not (work / "late-sac").exists(),
        ),
        dict(
            what="train dqn too short to fill one replay window",
            argv=[
                "train",
                "dqn",
                "--num-envs",
                "8",
                "--rollout-steps",
                "1",
                "--total-steps",
                "8",
                "--learning-starts",
                "0",
                "--no-progress",
                "--out",
                "short-replay",
            ],
            refuse="no gradient step would be taken",
        ),
        dict(
            what="train sac --reward-scale 1e38 (diverges)",
            argv=[
                "train",
                "sac",
                *small,
                "--batch-size",
                "16",
                "--hidden-sizes",
                "16,16",
                "--learning-starts",
                "0",
                "--chunks",
                "2",
                "--reward-scale",
                "1e38",
                "--max-steps",
                "40",
                "--eval-episodes",
                "2",
                "--out",
                "diverged",
            ],
            phrase_ok="note: training diverged",
            check=lambda: all(r.get("diverged") for r in strict_lines(work / "diverged" / "metrics.jsonl")),
        ),
        dict(
            what="Ctrl-C during train (SIGINT after the second checkpoint)",
            argv=[
                "train",
                "ppo",
                "--task",
                "1d-static-sin",
                *TINY,
                "--total-steps",
                "5120",
                "--chunks",
                "40",
                "--no-eval",
                "--out",
                "sigint",
            ],
            interrupt_when=work / "sigint" / "checkpoints" / "1",
            exit_code=130,
            phrase_ok="the run is resumable: snac train ppo --resume sigint",
        ),
        dict(
            what="train --sweep num-envs=8,16 (a shape)",
            argv=["train", "ppo", *SHORT, "--sweep", "num-envs=8,16", "--out", "sweep-shape"],
            refuse="num_envs cannot be swept in one program",
            also=lambda: not (work / "sweep-shape").exists(),
        ),
        dict(
            what="train --learning-rate X --sweep learning-rate=...",
            argv=[
                "train",
                "ppo",
                *SHORT,
                "--learning-rate",
                "0.001",
                "--sweep",
                "learning-rate=1e-3,2e-3",
                "--out",
                "sweep-twice",
            ],
            refuse="both set learning_rate",
        ),
        dict(
            what="train dqn --sweep exploration-fraction=0.1,0.5 (read outside the trace)",
            argv=[
                "train",
                "dqn",
                *small,
                "--learning-starts",
                "0",
                "--sweep",
                "exploration-fraction=0.1,0.5",
                "--out",
                "sweep-python",
            ],
            refuse="cannot be swept in one program",
        ),
        dict(
            what="train --resume RUN --sweep ...",
            argv=["train", "ppo", "--resume", "run", "--sweep", "learning-rate=1e-3,2e-3"],
            refuse="--sweep cannot change it",
        ),
        dict(what="rollout --reset vmap", argv=["rollout", "--reset", "vmap"], refuse="invalid choice: 'vmap'"),
    ]
