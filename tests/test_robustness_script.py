"""`bench/robustness.py` without what its cases run (pytest, the train, play and render extras)
refuses in one line naming the dev extra, before it trains or writes anything."""

import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


@pytest.mark.parametrize("blocked", [["pytest"], ["distrax", "pygame"]])
def test_robustness_without_its_tools_refuses_in_one_line(tmp_path, blocked):
    out = tmp_path / "out"
    code = textwrap.dedent(f"""
        import runpy, sys
        for name in {blocked!r}:
            sys.modules[name] = None  # `import name` now fails as if it were not installed
        sys.argv = ["bench/robustness.py", "--out", {str(out)!r}]
        runpy.run_path("bench/robustness.py", run_name="__main__")
    """)
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert done.returncode == 2, done.stderr[-2000:]
    assert done.stderr.strip().splitlines() == [
        f'robustness.py: error: this needs the dev extra (missing: {", ".join(blocked)}): pip install -e ".[dev]"'
    ]
    assert not out.exists()
