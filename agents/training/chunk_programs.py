"""The compiled programs of a run's chunks, one per distinct chunk size (`driver.chunk_sizes` gives
at most two). The first is compiled when the driver asks for it. On an accelerator the others then
compile in one background thread while the first chunks train: a run's last, shorter chunk would
otherwise wait for a compile of its own after the training is nearly done, while the host's cores
sat idle. On a CPU the compile would take the cores the training runs on, and the chunks' timings
(the rates that plan `snac table`) would include it, so each program compiles when first needed.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any

import jax


def compiles_ahead() -> bool:
    """Whether the later programs compile in the background: on an accelerator, not on a CPU."""
    return jax.default_backend() != "cpu"


class ChunkPrograms:
    """`get(n)` is the compiled chunk of n updates; `lower(n)` lowers it (from abstract arguments,
    so the background thread never reads arrays the running chunks donate). `write` reports each
    compile once, when its program is first used, and a background compile that failed (then
    compiled again in the foreground, with the device idle)."""

    def __init__(
        self, lower: Callable[[int], Any], sizes: Iterable[int], write: Callable[[str], None], background: bool
    ):
        self._lower = lower
        self._needed = list(dict.fromkeys(sizes))  # distinct, in the order the run needs them
        self._write = write
        self._programs: dict[int, Any] = {}
        self._background: dict[int, Future] = {}
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="compile-chunk") if background else None

    def _compile(self, n: int) -> tuple[Any, float]:
        start = time.perf_counter()
        program = self._lower(n).compile()
        return program, time.perf_counter() - start

    def get(self, n: int) -> Any:
        if n not in self._programs:
            program, where = None, ""
            if n in self._background:
                try:
                    program, seconds = self._background.pop(n).result()
                    where = " (in the background)"
                except Exception as error:  # e.g. out of device memory beside the training: try again alone
                    self._write(
                        f"warning: compiling the chunk of {n} updates in the background failed "
                        f"({type(error).__name__}: {str(error).splitlines()[0] if str(error) else ''}); "
                        "compiling it now"
                    )
            if program is None:
                program, seconds = self._compile(n)
            self._write(f"compiled a chunk of {n} updates in {seconds:.1f} s{where}")
            self._programs[n] = program
            if self._pool is not None:
                for size in self._needed:
                    if size not in self._programs and size not in self._background:
                        self._background[size] = self._pool.submit(self._compile, size)
        return self._programs[n]

    def close(self) -> None:
        """Drops compiles not started and waits for one under way (XLA cannot stop it midway),
        saying so: an interrupted run may take a compile's time to exit."""
        if self._pool is None:
            return
        if any(f.running() for f in self._background.values()):
            self._write("waiting for a chunk's compile under way to finish (it cannot be stopped midway)")
        self._pool.shutdown(wait=True, cancel_futures=True)
