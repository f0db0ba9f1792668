"""Where a test run's time goes to XLA: a pytest plugin that counts, per test, the programs JAX
compiles and the seconds spent compiling (backend) and tracing/lowering them, from JAX's own
monitoring events; and a summary of what it wrote.

    JAX_COMPILATION_CACHE_DIR=$(mktemp -d) COMPILE_PROFILE_OUT=DIR \
        python -m pytest -p bench.compile_profile          # one JSON per xdist worker in DIR
    python bench/compile_profile.py DIR                    # per file, then the tests compiling most

Why: on a fresh clone the default suite's time is mostly XLA compiling the tests' programs (a
cold compilation cache), and no single test dominates; this says which files and tests compile
the most programs and seconds, so that sharing configurations or jitting eager checks is aimed
where it pays. "<collect>" is what compiles before a worker's first test (imports, module-level
set-up). Seconds include the machine's load: compare tests within one run.
"""

from __future__ import annotations

import collections
import json
import os
import sys
from pathlib import Path

COMPILE = "/jax/core/compile/backend_compile_duration"
TRACE = ("/jax/core/compile/jaxpr_trace_duration", "/jax/core/compile/jaxpr_to_mlir_module_duration")
FIELDS = ("compile_s", "programs", "trace_s")

_current = ["<collect>"]
_stats: dict[str, list[float]] = collections.defaultdict(lambda: [0.0, 0, 0.0])


def _listener(event: str, duration: float, **_) -> None:
    if event == COMPILE:
        _stats[_current[0]][0] += duration
        _stats[_current[0]][1] += 1
    elif event in TRACE:
        _stats[_current[0]][2] += duration


def pytest_configure(config) -> None:
    if not os.environ.get("COMPILE_PROFILE_OUT"):
        raise ValueError("bench.compile_profile needs COMPILE_PROFILE_OUT=DIR, the folder it writes its JSON to")
    import jax.monitoring

    jax.monitoring.register_event_duration_secs_listener(_listener)


def pytest_runtest_setup(item) -> None:
    _current[0] = item.nodeid


def pytest_sessionfinish(session) -> None:
    out = Path(os.environ["COMPILE_PROFILE_OUT"])
    out.mkdir(parents=True, exist_ok=True)
    worker = os.environ.get("PYTEST_XDIST_WORKER", "main")
    rows = {test: dict(zip(FIELDS, values)) for test, values in _stats.items()}
    (out / f"compile-{worker}.json").write_text(json.dumps(rows, indent=1) + "\n")


def summary(folder: Path, top: int = 30) -> str:
    """The per-file and per-test table of the JSON files in `folder`."""
    tests: dict[str, dict[str, float]] = {}
    for path in sorted(folder.glob("compile-*.json")):
        for test, row in json.loads(path.read_text()).items():
            total = tests.setdefault(test, dict.fromkeys(FIELDS, 0))
            for field in FIELDS:
                total[field] += row[field]
    if not tests:
        raise ValueError(f"no compile-*.json in {folder}: run pytest with -p bench.compile_profile first")
    files: dict[str, dict[str, float]] = {}
    for test, row in tests.items():
        total = files.setdefault(test.split("::")[0], dict.fromkeys(FIELDS, 0))
        for field in FIELDS:
            total[field] += row[field]
    whole = {field: sum(row[field] for row in tests.values()) for field in FIELDS}
    lines = [
        f"{whole['programs']:,} programs, {whole['compile_s']:,.0f} s compiling, {whole['trace_s']:,.0f} s tracing "
        "and lowering (all workers)",
        "",
        "| file | programs | compile s | trace s |",
        "|---|---:|---:|---:|",
    ]
    for name, row in sorted(files.items(), key=lambda item: -item[1]["compile_s"])[:top]:
        lines.append(f"| {name} | {row['programs']:,} | {row['compile_s']:.1f} | {row['trace_s']:.1f} |")
    lines += ["", "| test | programs | compile s |", "|---|---:|---:|"]
    for name, row in sorted(tests.items(), key=lambda item: -item[1]["compile_s"])[:top]:
        lines.append(f"| {name} | {row['programs']:,} | {row['compile_s']:.1f} |")
    return "\n".join(lines)


if __name__ == "__main__":
    if len(sys.argv) != 2:
        sys.exit("usage: python bench/compile_profile.py DIR (the COMPILE_PROFILE_OUT of a profiled pytest run)")
    print(summary(Path(sys.argv[1])))
