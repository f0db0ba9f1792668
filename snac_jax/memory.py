"""Memory estimates checked before anything big is allocated.

Sizes that scale an allocation (worlds, episodes, designs, pixels) are free for the caller to
choose, and too large a one ends in the kernel killing the process (or a C++ abort that takes a
notebook kernel with it) after minutes. So each of them is estimated first, from shapes alone,
and compared with what the device can still take: too much is a `ValueError` that gives both
numbers. The estimates are upper bounds of the order of magnitude, not exact accounting.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np


def tree_bytes(tree: Any) -> int:
    """Bytes of every array (or `jax.ShapeDtypeStruct`) in a pytree."""
    import jax

    return int(sum(np.prod(x.shape, dtype=np.int64) * x.dtype.itemsize for x in jax.tree.leaves(tree)))


def _cgroup_room() -> int | None:
    """Bytes the process's cgroup (a container's limit) still allows, if it sets one."""
    limit, used = Path("/sys/fs/cgroup/memory.max"), Path("/sys/fs/cgroup/memory.current")
    try:
        text = limit.read_text().strip()
        return None if text == "max" else int(text) - int(used.read_text())
    except (OSError, ValueError):
        return None


def host_available() -> int:
    """Bytes of host memory available now: MemAvailable, capped by a container's limit."""
    available = None
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                available = int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    if available is None:  # not Linux: all of the physical memory
        available = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    room = _cgroup_room()
    return available if room is None else min(available, room)


def device_available(device=None) -> tuple[int, str]:
    """`(bytes, words)`: what `device` (default: JAX's first) can still allocate, and where."""
    import jax

    device = device or jax.devices()[0]
    stats = device.memory_stats() if device.platform != "cpu" else None
    if stats and "bytes_limit" in stats:
        free = int(stats["bytes_limit"]) - int(stats.get("bytes_in_use", 0))
        return free, f"the {gib(free)} free on {device.device_kind}"
    free = host_available()
    return free, f"the {gib(free)} of memory available on this machine"


def gib(size: float) -> str:
    return f"{size / 2**30:,.1f} GiB" if size >= 2**30 else f"{size / 2**20:,.1f} MiB"


def require(what: str, needed: int, advice: str = "", device=None) -> None:
    """`ValueError` if `what` would need more than `device` can still allocate."""
    free, where = device_available(device)
    if needed > free:
        raise ValueError(f"{what} needs about {gib(needed)}, more than {where}" + (f"; {advice}" if advice else ""))
