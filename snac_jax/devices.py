"""Use every CPU core: split the host into XLA devices and shard the env axis over them.

XLA on the CPU runs one device's elementwise work on few threads, so a batch of environments
on one device leaves cores idle. Splitting the host into one XLA device per core and giving
each device its own slice of the envs (`shard_map` over a one-axis mesh) keeps them all busy.

Usage (the device count is fixed when JAX's backend starts, i.e. at the first JAX operation):

    from snac_jax import devices
    devices.use_cpu_devices()            # before any JAX operation; None = one per core
    import jax
    mesh = devices.env_mesh()             # all local devices, axis name "envs"
    batch = devices.shard_envs(batch, mesh)   # leading axis split over the devices

    @jax.jit
    def run(keys, states):                # keys: one per device, states: (num_envs, ...)
        return jax.shard_map(per_device_fn, mesh=mesh, in_specs=devices.ENVS, out_specs=devices.ENVS)(keys, states)

`use_cpu_devices(1)` keeps a single device (the switch `--devices 1` of the CLI and benchmark).
On a GPU machine the CPU split is harmless and the mesh spans the GPUs.
"""

from __future__ import annotations

import os

ENV_AXIS = "envs"


def available_cores() -> int:
    """CPU cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


def use_cpu_devices(count: int | None = None, *, start: bool = True) -> int:
    """Expose `count` XLA CPU devices (default: one per available core); returns how many exist.

    Call it before the first JAX operation; importing jax or snac_jax first is fine (setting
    `XLA_FLAGS=--xla_force_host_platform_device_count=N` before Python starts does the same).
    Once JAX's backend has started the count is fixed: then the default (None) accepts whatever
    exists, and an explicit count raises `RuntimeError` if fewer devices exist (more is fine: a
    mesh can use the first `count`). A count < 1 raises `ValueError`. With `start=False` it only
    sets the count and returns it, leaving the backend unstarted (`jax.distributed.initialize`
    must come before it starts).
    """
    if count is not None and (isinstance(count, bool) or not isinstance(count, int) or count < 1):
        raise ValueError(f"the device count must be an int >= 1 or None (one per core), got {count!r}")
    import jax

    wanted = available_cores() if count is None else count
    if "xla_force_host_platform_device_count" not in os.environ.get("XLA_FLAGS", ""):
        try:
            jax.config.update("jax_num_cpu_devices", wanted)
        except RuntimeError:
            pass  # the backend already started: the count is what it is
    if not start:
        return wanted
    existing = len(jax.devices("cpu"))
    if count is not None and existing < count:
        raise RuntimeError(
            f"JAX started with {existing} CPU device(s), fewer than the {count} asked for; call "
            "snac_jax.devices.use_cpu_devices before the first JAX operation"
        )
    return existing


def env_mesh(num_devices: int | None = None, num_envs: int | None = None, *, global_devices: bool = False):
    """A one-axis mesh (axis `ENV_AXIS`) over the first `num_devices` devices of this process,
    or of every process with `global_devices` (training across hosts after
    `jax.distributed.initialize`; with one process the two are the same).

    By default all of them; given `num_envs`, the default is the most devices that split the
    envs evenly (a single env runs on one device). An explicit `num_devices` above the count
    raises `ValueError`.
    """
    import jax
    import numpy as np

    available = jax.devices() if global_devices else jax.local_devices()
    which = "devices of all processes" if global_devices else "local devices"
    if num_devices is None:
        num_devices = len(available)
        while num_envs is not None and num_envs % num_devices:
            num_devices -= 1
    if not 1 <= num_devices <= len(available):
        raise ValueError(f"num_devices must be in 1..{len(available)} (the {which}), got {num_devices}")
    return jax.sharding.Mesh(np.asarray(available[:num_devices]), (ENV_AXIS,))


def check_divisible(num_envs: int, mesh) -> None:
    """`ValueError` unless the envs split evenly over the mesh's devices."""
    num_devices = mesh.devices.size
    if num_envs % num_devices:
        raise ValueError(
            f"num_envs ({num_envs}) must be a multiple of the number of devices ({num_devices}); "
            f"use {num_devices * max(1, round(num_envs / num_devices))} envs or fewer devices"
        )


def env_sharding(mesh):
    """Sharding that splits an array's leading (env) axis over the mesh."""
    import jax

    return jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec(ENV_AXIS))


def shard_envs(tree, mesh):
    """Place every array of `tree` with its leading axis split over the mesh's devices."""
    import jax

    return jax.device_put(tree, env_sharding(mesh))


def __getattr__(name: str):
    # `ENVS` (the PartitionSpec of the env axis) is built on first use, so importing this module
    # does not import jax.
    if name == "ENVS":
        import jax

        return jax.sharding.PartitionSpec(ENV_AXIS)
    raise AttributeError(name)
