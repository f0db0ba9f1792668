"""The compiled programs of a run's chunks, one per distinct chunk size (`driver.chunk_sizes` gives
at most two). The first is compiled when the driver asks for it; the others then compile in one
background thread while the first chunks train. A run's last, shorter chunk otherwise waits for a
compile of its own after the training is nearly done, which on a GPU can be a large share of a
short run.
"""

from __future__ import annotations

import time
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any, Callable, Iterable


class ChunkPrograms:
    """`get(n)` is the compiled chunk of n updates; `lower(n)` lowers it (from abstract arguments,
    so the background thread never reads arrays the running chunks donate). `write` reports each
    compile once, when its program is first used."""

    def __init__(self, lower: Callable[[int], Any], sizes: Iterable[int], write: Callable[[str], None]):
        self._lower = lower
        self._needed = list(dict.fromkeys(sizes))  # distinct, in the order the run needs them
        self._write = write
        self._programs: dict[int, Any] = {}
        self._background: dict[int, Future] = {}
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="compile-chunk")

    def _compile(self, n: int) -> tuple[Any, float]:
        start = time.perf_counter()
        program = self._lower(n).compile()
        return program, time.perf_counter() - start

    def get(self, n: int) -> Any:
        if n not in self._programs:
            if n in self._background:
                program, seconds = self._background.pop(n).result()
                self._write(f"compiled a chunk of {n} updates in {seconds:.1f} s (in the background)")
            else:
                program, seconds = self._compile(n)
                self._write(f"compiled a chunk of {n} updates in {seconds:.1f} s")
            self._programs[n] = program
            for size in self._needed:
                if size not in self._programs and size not in self._background:
                    self._background[size] = self._pool.submit(self._compile, size)
        return self._programs[n]

    def close(self) -> None:
        """Drops compiles not started and waits for one under way (XLA cannot stop it midway)."""
        self._pool.shutdown(wait=True, cancel_futures=True)
