"""Bad and edge inputs against the `snac` command line and the Python API, each judged against
what it should do (issue 18's re-measurement):

    python bench/robustness.py --out bench/results          # ~10 min on a busy 2-core CPU

Every case is an input a new, careless or hostile user might give, with the outcome it should
have: refused with a message naming the problem, or done right (a check of the result). Each is
judged

- `good`: the right outcome, delivered well (a refusal is one line, `snac CMD: error: ...` or
  argparse's usage error, exit status 2, or a `ValueError` from the API);
- `poor`: the right message, delivered poorly (a traceback, another exit status, another
  exception type);
- `bad`: silently wrong: accepted when it should be refused, or a wrong or lost result.

Writes only under `--out`: `robustness.json` (every case: command, exit status, the output's last
lines, verdict) and `robustness.md` (the table). Scratch runs live in a temporary folder there,
removed at the end. The cases are in `bench/robustness_cases.py` (command line) and
`bench/robustness_api.py` (Python API). `--only PHRASE` re-runs the command-line cases it names
(a phrase of their description, or their group, e.g. `issue 69`) and merges them into the record
under `--out`, noting the re-run; the record keeps the *before* rows it was written with.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.dont_write_bytecode = True  # nothing but the results is written

from bench.robustness_cases import TINY, cli_cases, setup  # noqa: E402

VERDICTS = ("good", "poor", "bad")
# What the cases run beyond the environment: pytest (the golden-trace case), `snac train` (the
# trained run every case starts from), `snac play` and `snac render`. The dev extra brings them all.
NEEDED_MODULES = ("pytest", "optax", "distrax", "flashbax", "pygame", "imageio")


def missing_modules() -> list[str]:
    """The modules of `NEEDED_MODULES` that cannot be imported here."""
    import importlib.util

    def found(name: str) -> bool:
        try:
            return importlib.util.find_spec(name) is not None
        except ValueError:  # a module set to None in sys.modules: blocked, as if not installed
            return False

    return [name for name in NEEDED_MODULES if not found(name)]


def snac(work: Path, *argv: str, timeout: float = 600, script: str | None = None) -> dict:
    """`python -m snac_jax.cli ARGV` (or `python SCRIPT ARGV`, a path under the repository) in
    `work`: exit status, stdout, stderr, seconds."""
    env = {
        **os.environ,
        "JAX_PLATFORMS": "cpu",
        "SDL_VIDEODRIVER": "dummy",
        "SDL_AUDIODRIVER": "dummy",
        "PYTHONPATH": str(ROOT),
    }
    env.pop("SNAC_TRACEBACK", None)
    start = time.perf_counter()
    try:
        done = subprocess.run(
            [sys.executable, *(["-m", "snac_jax.cli"] if script is None else [str(ROOT / script)]), *argv],
            cwd=work,
            env=env,
            capture_output=True,
            text=True,
            timeout=timeout,
        )
        code, out, err = done.returncode, done.stdout, done.stderr
    except subprocess.TimeoutExpired as expired:
        code, out, err = "timeout", expired.stdout or "", expired.stderr or ""
        out, err = (x.decode() if isinstance(x, bytes) else x for x in (out, err))
    return {"code": code, "out": out, "err": err, "seconds": round(time.perf_counter() - start, 1)}


def snac_interrupted(work: Path, argv, when: Path, timeout: float = 600) -> dict:
    """`snac ARGV` sent SIGINT (Ctrl-C) once `when` exists: exit status, stdout, stderr, seconds."""
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "PYTHONPATH": str(ROOT)}
    env.pop("SNAC_TRACEBACK", None)
    start = time.perf_counter()
    process = subprocess.Popen(
        [sys.executable, "-m", "snac_jax.cli", *argv],
        cwd=work,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    while not when.exists() and process.poll() is None and time.perf_counter() - start < timeout:
        time.sleep(0.05)
    if process.poll() is None:
        process.send_signal(signal.SIGINT)
    try:
        out, err = process.communicate(timeout=timeout)
        code = process.returncode
    except subprocess.TimeoutExpired:
        process.kill()
        out, err = process.communicate()
        code = "timeout"
    # the run's own progress lines are not the interruption's: keep what follows the last of them
    err = "\n".join(
        line for line in err.splitlines() if not line.startswith(("ppo on", "worlds split", "compiled a chunk"))
    )
    return {"code": code, "out": out, "err": err, "seconds": round(time.perf_counter() - start, 1)}


def judge_refusal(result: dict, phrase: str) -> tuple[str, str]:
    """A refusal: `phrase` (in any case) in one clean error line with status 2 is good; the
    phrase with a traceback or another status is poor; no phrase (accepted, or another error)
    is bad."""
    text = result["err"] + result["out"]
    lines = [line for line in result["err"].strip().splitlines() if line.strip()]
    last = lines[-1] if lines else ""
    if phrase.lower() not in text.lower():
        return "bad", f"exit {result['code']}: {last or result['out'].strip()[-200:]}"
    clean = result["code"] == 2 and "Traceback" not in text and ("error:" in last)
    return ("good" if clean else "poor"), f"exit {result['code']}: {last}"


def run_cli_case(work: Path, case: dict) -> dict:
    holder = None
    if "hold_lock" in case:
        holder = subprocess.Popen(
            [
                sys.executable,
                "-c",
                "import fcntl, sys, time; f = open(sys.argv[1], 'a+'); "
                "fcntl.flock(f, fcntl.LOCK_EX); print('locked', flush=True); time.sleep(600)",
                str(case["hold_lock"] / ".lock"),
            ],
            stdout=subprocess.PIPE,
            text=True,
        )
        holder.stdout.readline()
    try:
        if "interrupt_when" in case:
            result = snac_interrupted(work, case["argv"], case["interrupt_when"])
        else:
            result = snac(work, *case["argv"], timeout=case.get("timeout", 600), script=case.get("script"))
    finally:
        if holder is not None:
            holder.kill()
            holder.wait()
    if "refuse" in case:
        verdict, note = judge_refusal(result, case["refuse"])
        if verdict == "good" and case.get("one_line") and len(result["err"].strip().splitlines()) > case["one_line"]:
            verdict, note = "poor", f"{len(result['err'].strip().splitlines())} lines on stderr: {note}"
        if verdict == "good" and "also" in case and not case["also"]():
            verdict, note = "bad", "refused, but the files were changed"
        if "banner" in case and case["banner"] not in result["err"]:
            verdict, note = "bad", f"banner wrong: {result['err'].splitlines()[:1]}"
    else:
        ok = result["code"] == case.get("exit_code", 0) and case.get("phrase_ok", "") in result["err"] + result["out"]
        if "exit_code" in case:  # an interruption: one clean line, no traceback
            ok = ok and "Traceback" not in result["err"] and len(result["err"].strip().splitlines()) <= 3
        try:
            ok = ok and case.get("check", lambda: True)()
        except (OSError, ValueError, KeyError) as error:
            ok, result["err"] = False, result["err"] + f"\ncheck failed: {error}"
        lines = [line for line in (result["err"] + result["out"]).strip().splitlines() if line.strip()]
        verdict = "good" if ok else ("poor" if result["code"] == 0 else "bad")
        note = f"exit {result['code']}: {lines[-1] if lines else ''}"
    return {
        "what": case["what"],
        "input": command_line(case),
        "verdict": verdict,
        "note": note[:300],
        "seconds": result["seconds"],
    }


def selected(case: dict, only: str) -> bool:
    """Whether `--only ONLY` runs `case`: ONLY is in its description, or names its group."""
    return only in case["what"] or only == case.get("group")


def command_line(case: dict) -> str:
    return ("snac" if case.get("script") is None else f"python {case['script']}") + " " + " ".join(case["argv"])


def api_cases(work: Path, skip_memory: bool) -> list[dict]:
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "PYTHONPATH": str(ROOT)}
    done = subprocess.run(
        [sys.executable, str(ROOT / "bench" / "robustness_api.py"), str(work), "skip-memory" if skip_memory else "all"],
        capture_output=True,
        text=True,
        env=env,
        cwd=work,
        timeout=1200,
    )
    if done.returncode:
        raise RuntimeError(done.stderr[-3000:])
    return json.loads(done.stdout.strip().splitlines()[-1])


def other_cases(work: Path) -> list[dict]:
    """The run's files, the golden-trace tests, the throughput bench, and a SIGKILL."""
    results = []
    modes = {
        name: oct((work / "run" / name).stat().st_mode & 0o777)
        for name in ("config.json", "run.json", "metrics.jsonl", "curve.png", "eval.json")
        if (work / "run" / name).exists()
    }
    results.append(
        {
            "what": "file modes of a run (umask 022)",
            "input": "stat run/*",
            "note": json.dumps(modes),
            "verdict": "good" if set(modes.values()) == {"0o644"} else "bad",
        }
    )

    env = {**os.environ, "JAX_PLATFORMS": "cpu", "SNAC_GOLDEN_TRACES": str(work / "empty_traces.json")}
    tests = [
        "tests/test_conformance.py::test_replay_matches_golden_trace",
        "tests/test_numpy_engine.py::test_numpy_engine_replays_every_golden_trace",
    ]
    done = subprocess.run(
        [sys.executable, "-m", "pytest", "-n", "0", "-p", "no:cacheprovider", "-q", *tests],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    summary = done.stdout.strip().splitlines()[-1]
    results.append(
        {
            "what": "SNAC_GOLDEN_TRACES pointing at an empty file",
            "input": "pytest " + " ".join(tests),
            "note": summary,
            "verdict": "good" if done.returncode == 1 and "passed" not in summary else "bad",
        }
    )

    done = subprocess.run(
        [
            sys.executable,
            str(ROOT / "bench" / "throughput.py"),
            "--tasks",
            "1d-static-sin",
            "--num-envs",
            "1",
            "--steps",
            "10",
            "--numpy-steps",
            "100",
            "--no-e2e",
            "--json",
            str(work / "rows.json"),
        ],
        capture_output=True,
        text=True,
        cwd=work,
        env={**os.environ, "JAX_PLATFORMS": "cpu"},
    )
    results.append(
        {
            "what": "bench/throughput.py --json PATH (without --out)",
            "input": "python bench/throughput.py --json PATH",
            "note": ((done.stderr + done.stdout).strip().splitlines() or [""])[-1][:200],
            "verdict": "good" if done.returncode == 2 and not (work / "rows.json").exists() else "bad",
        }
    )

    results.append(sigkill_case(work))
    return results


def sigkill_case(work: Path) -> dict:
    """`snac train` SIGKILLed once its second chunk is logged, then resumed: its metrics equal
    those of a run never interrupted."""
    argv = ["train", "ppo", "--task", "1d-static-gauss", *TINY, "--total-steps", "1024", "--chunks", "8", "--no-eval"]
    snac(work, *argv, "--out", "straight")
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "PYTHONPATH": str(ROOT)}
    child = subprocess.Popen(
        [sys.executable, "-m", "snac_jax.cli", *argv, "--out", "killed"],
        cwd=work,
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    metrics = work / "killed" / "metrics.jsonl"
    while child.poll() is None and not (metrics.is_file() and metrics.read_text().count("\n") >= 2):
        time.sleep(0.02)
    child.send_signal(signal.SIGKILL)
    child.wait()
    resumed = snac(work, "train", "ppo", "--resume", "killed", "--no-progress")

    def lines(name):
        return [
            (r["chunk"], r["iou"], r["return"])
            for r in (json.loads(line) for line in (work / name / "metrics.jsonl").read_text().splitlines() if line)
        ]

    same = resumed["code"] == 0 and lines("killed") == lines("straight")
    return {
        "what": "SIGKILL after the second chunk is logged, then --resume",
        "input": "snac " + " ".join(argv),
        "verdict": "good" if same else "bad",
        "note": f"killed with exit {child.returncode}; resumed metrics equal the uninterrupted run's: {same}",
    }


def markdown(results: list[dict], seconds: float, before: dict | None = None, reruns: list | None = None) -> str:
    def count(rows):
        return ", ".join(
            f"{sum(r['verdict'] == v for r in rows)} {v}"
            for v in (*VERDICTS, "not run")
            if v != "not run" or any(r["verdict"] == v for r in rows)
        )

    lines = [
        "# Robustness: bad and edge inputs, re-measured",
        "",
        f"`python bench/robustness.py --out bench/results` ({len(results)} inputs, {seconds / 60:.0f} min). Each input is "
        "judged against what it should do: **good** = the right outcome, delivered well (a refusal is one line "
        "`snac CMD: error: ...` or argparse's usage error with exit status 2, or a `ValueError` from the API); "
        "**poor** = the right message, delivered poorly (a traceback, another status or exception type); "
        "**bad** = silently wrong (accepted when it should be refused, or a wrong or lost result). "
        "Paths are relative to a scratch folder holding a tiny trained run `run` (`--max-steps 40 --eval-episodes 2`) "
        "and damaged copies of it.",
        "",
        *(
            f"Re-run since with `--only {r['only']!r}` (merged into this record, the rest kept): {r['cases']} "
            f"case(s), {r['seconds'] / 60:.0f} min."
            for r in reruns or []
        ),
        "",
        f"**Now: {count(results)}.**"
        + ("" if before is None else f" Before the fixes: {count(list(before.values()))}."),
        "",
    ]
    if before is not None:
        lines += [
            "The *before* column is the same script run on the code before the fixes (`--skip-memory --out DIR` in a "
            "checkout of it, then `--before DIR/robustness.json` here). The oversized inputs were not run there (they "
            "exhaust the machine's memory; the issue reports what they did). A refusal there whose wording differs from "
            "today's (an `OverflowError` instead of the allowed range, a shape error deep in JAX) is judged by today's "
            "phrase, so it counts as bad where a reader might call it poor.",
            "",
        ]
    if before is None:
        lines += ["| # | input | command | verdict | what happened |", "|---:|---|---|---|---|"]
    else:
        lines += [
            "| # | input | command | before | what happened before | now | what happens now |",
            "|---:|---|---|---|---|---|---|",
        ]
    for i, r in enumerate(results, start=1):
        note = r["note"].replace("|", "\\|").replace("\n", " ")
        command = r["input"].replace("|", "\\|")
        old = (before or {}).get(r["what"], {"verdict": "—", "note": ""})
        old_note = old["note"][:160].replace("|", "\\|").replace("\n", " ")
        was = "" if before is None else f" {old['verdict']} | {old_note} |"
        lines.append(f"| {i} | {r['what']} | `{command}` |{was} {r['verdict']} | {note} |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, required=True, help="directory for robustness.json and robustness.md")
    parser.add_argument(
        "--only",
        default=None,
        help="run only the CLI cases whose description contains this (or whose group it names, e.g. 'issue 69'), "
        "merged into --out's record (the rest kept)",
    )
    parser.add_argument(
        "--skip-memory",
        action="store_true",
        help="leave out the oversized inputs (for code without the memory checks: they would exhaust memory)",
    )
    parser.add_argument(
        "--before",
        type=Path,
        default=None,
        metavar="JSON",
        help="robustness.json of the same cases on the code before the fixes: shown as a column",
    )
    parser.add_argument(
        "--from-json",
        type=Path,
        default=None,
        metavar="JSON",
        help="run nothing: rebuild robustness.md from an earlier robustness.json (and --before)",
    )
    args = parser.parse_args(argv)
    if args.from_json is None and (missing := missing_modules()):
        # Refused before anything runs: without them the cases would fail minutes in, writing nothing.
        parser.exit(
            2,
            f"{parser.prog}: error: this needs the dev extra (missing: {', '.join(missing)}): "
            'pip install -e ".[dev]"\n',
        )
    if args.out.exists() and not args.out.is_dir():
        parser.error(f"--out {args.out} is a file; give a directory for robustness.json and robustness.md")
    try:
        before = None if args.before is None else {r["what"]: r for r in load_results(args.before, "--before")[0]}
        if args.from_json is not None:
            results, seconds = load_results(args.from_json, "--from-json")
            kept = None
        else:
            kept = load_record(args.out / "robustness.json") if args.only else None
    except ValueError as error:
        parser.error(str(error))
    if args.only and not any(selected(case, args.only) for case in cli_cases(Path("/nonexistent"))):
        parser.error(f"--only {args.only!r} matches no case; the cases are listed in bench/robustness_cases.py")
    args.out.mkdir(parents=True, exist_ok=True)
    if args.from_json is not None:
        return write(args.out, results, seconds, before)
    start = time.perf_counter()
    with tempfile.TemporaryDirectory(dir=args.out, prefix=".robustness-") as scratch:
        work = Path(scratch).resolve()
        made = setup(work, snac)
        if made["run"]["code"] != 0:
            raise RuntimeError(made["run"]["err"][-3000:])
        results = []
        for case in cli_cases(work):
            if args.only and not selected(case, args.only):
                continue
            if case.get("memory") and args.skip_memory:
                results.append(
                    {
                        "what": case["what"],
                        "input": command_line(case),
                        "verdict": "not run",
                        "note": "memory case skipped (--skip-memory)",
                        "seconds": 0,
                    }
                )
                continue
            results.append(run_cli_case(work, case))
            print(f"{results[-1]['verdict']:5s} {results[-1]['what']} ({results[-1]['seconds']} s)", flush=True)
        if not args.only:
            results += api_cases(work, args.skip_memory)
            results += other_cases(work)
    seconds = time.perf_counter() - start
    if kept is None:
        return write(args.out, results, seconds, before)
    return write_merged(args.out, kept, results, args.only, seconds, before)


def load_record(path: Path) -> dict:
    """The record at `path` (a robustness.json) as `{"seconds", "results", ...}`; an empty
    record where there is none."""
    if not path.exists():
        return {"seconds": 0.0, "results": []}
    results, seconds = load_results(path, "the record")
    data = json.loads(path.read_text())
    return {**(data if isinstance(data, dict) else {}), "results": results, "seconds": seconds}


def load_results(path: Path, what: str = "--from-json") -> tuple[list[dict], float]:
    """`(results, seconds)` of a robustness.json; a one-line `ValueError` naming `what` and the
    file when it is missing, not JSON, or not such a record."""
    try:
        data = json.loads(Path(path).read_text())
    except OSError as error:
        raise ValueError(f"{what} {path} cannot be read: {error.strerror or error}") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
        raise ValueError(f"{what} {path} is not JSON: {error}") from None
    results, seconds = (
        (data, 0.0)
        if isinstance(data, list)
        else ((data.get("results"), data.get("seconds")) if isinstance(data, dict) else (None, None))
    )
    fields = ("what", "input", "verdict", "note")
    if not (
        isinstance(results, list)
        and all(isinstance(r, dict) and all(isinstance(r.get(k), str) for k in fields) for r in results)
        and isinstance(seconds, (int, float))
        and not isinstance(seconds, bool)
    ):
        raise ValueError(
            f"{what} {path} is not a robustness.json (an object with seconds and results, each result "
            f"with {', '.join(fields)} as strings)"
        )
    return results, float(seconds)


def write_merged(out: Path, kept: dict, rerun: list[dict], only: str, seconds: float, before: dict | None) -> int:
    """The record at `out` with the cases `--only ONLY` re-ran replaced (new ones appended), and
    that re-run noted: the rest of the record is the earlier whole run's, untouched."""
    fresh = {r["what"]: r for r in rerun}
    results = [fresh.pop(r["what"], r) for r in kept["results"]] + list(fresh.values())
    reruns = [*kept.get("reruns", []), {"only": only, "cases": len(rerun), "seconds": round(seconds, 1)}]
    return write(out, results, kept["seconds"], before, reruns)


def write(out: Path, results: list[dict], seconds: float, before: dict | None, reruns: list | None = None) -> int:
    """`robustness.json` and `robustness.md` under `out`. The *before* rows are kept in the
    record, so that rebuilding or merging into it keeps that column."""
    from snac_jax.atomic import atomic_write_json, atomic_write_text

    if before is None and (out / "robustness.json").is_file():
        before = load_record(out / "robustness.json").get("before")
    record = {"seconds": round(seconds, 1), "results": results}
    if reruns:
        record["reruns"] = reruns
    if before is not None:
        record["before"] = before
    atomic_write_json(out / "robustness.json", record)
    atomic_write_text(out / "robustness.md", markdown(results, seconds, before, reruns))
    counts = {v: sum(r["verdict"] == v for r in results) for v in VERDICTS}
    print(f"{counts}; wrote {out / 'robustness.md'}")
    return 0 if not counts["bad"] else 1


if __name__ == "__main__":
    sys.exit(main())
