"""snac-jax: the SNAC mobile-construction benchmark as pure-functional JAX environments.

The names below are imported on first use: importing `snac_jax` (or a light submodule such as
`snac_jax.devices`) must not start JAX's backend, because the number of CPU devices can only
be chosen before that (`snac_jax.devices.use_cpu_devices`), and gymnax starts it on import.
"""

import importlib

_EXPORTS = {
    "EnvConfig": "snac_jax.config",
    "EnvParams": "snac_jax.state",
    "EnvState": "snac_jax.state",
    "OVERRIDES": "snac_jax.tasks",
    "SNACEnv": "snac_jax.env",
    "TASKS": "snac_jax.tasks",
    "grid_iou": "snac_jax.metrics",
    "iou": "snac_jax.metrics",
    "make": "snac_jax.tasks",
    "test_design_names": "snac_jax.tasks",
}

# Subpackages reachable as attributes (`snac_jax.multi.make(...)` after `import snac_jax`), imported on
# first use like the names above.
_SUBPACKAGES = ("multi",)

__all__ = sorted(_EXPORTS)
__version__ = "0.1.0"


def __getattr__(name: str):
    if name in _EXPORTS:
        value = getattr(importlib.import_module(_EXPORTS[name]), name)
        globals()[name] = value
        return value
    if name in _SUBPACKAGES:
        return importlib.import_module(f"snac_jax.{name}")  # the import binds it in globals() too
    raise AttributeError(f"module 'snac_jax' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_EXPORTS) | set(_SUBPACKAGES))
