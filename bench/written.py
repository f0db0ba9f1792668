"""What a benchmark writes beside its numbers: the machine it measured on, and its JSON and
markdown pair, each written atomically under the `--out` it was given and nowhere else."""

from __future__ import annotations

import json
import platform
from pathlib import Path

from snac_jax.atomic import atomic_write


def device_context() -> dict:
    """The processor, JAX backend, device kind and JAX version: what a rate needs beside it to mean anything."""
    import jax

    device = jax.devices()[0]
    return {
        "machine": platform.processor() or platform.machine(),
        "backend": jax.default_backend(),
        "device": getattr(device, "device_kind", str(device)),
        "jax": jax.__version__,
    }


def write_pair(out: Path, stem: str, payload: dict, table: str) -> None:
    """`out/<stem>.json` (the payload) and `out/<stem>.md` (the table), each atomically."""
    text = json.dumps(payload, indent=1) + "\n"
    atomic_write(Path(out) / f"{stem}.json", lambda f: f.write(text.encode()))
    atomic_write(Path(out) / f"{stem}.md", lambda f: f.write(table.encode()))
