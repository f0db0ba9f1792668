"""`jax.random`'s Threefry-2x32 written as plain elementwise ops, bit for bit.

On the CPU, JAX lowers the Threefry hash as a rolled five-iteration `while` loop (it compiles
faster). Inside a vmapped step that loop cannot fuse with anything: each iteration is its own
pass over the batch with tuple copies, and the hashes then take most of a SNAC step. Written
out as 20 rounds of add/rotate/xor, XLA fuses the hash into the surrounding elementwise work.

The functions return exactly what the `jax.random` functions they name return for Threefry
keys (the default implementation; tests compare them bit for bit), so swapping them in changes
no random stream. Other key implementations (`rbg`, ...) fall back to `jax.random` itself.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

_ROTATIONS = ((13, 15, 26, 6), (17, 29, 16, 24))
_PARITY = np.uint32(0x1BD11BDA)


def _rotate_left(x: jax.Array, bits: int) -> jax.Array:
    return (x << np.uint32(bits)) | (x >> np.uint32(32 - bits))


def hash_2x32(key1: jax.Array, key2: jax.Array, x1: jax.Array, x2: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Threefry-2x32 (20 rounds) of the counter pair (x1, x2) under the key (key1, key2), uint32."""
    ks = (key1, key2, key1 ^ key2 ^ _PARITY)
    x1, x2 = x1 + ks[0], x2 + ks[1]
    for block in range(5):
        for rotation in _ROTATIONS[block % 2]:
            x1 = x1 + x2
            x2 = _rotate_left(x2, rotation) ^ x1
        x1 = x1 + ks[(block + 1) % 3]
        x2 = x2 + ks[(block + 2) % 3] + np.uint32(block + 1)
    return x1, x2


def _is_threefry(key: jax.Array) -> bool:
    return jax.dtypes.issubdtype(key.dtype, jax.dtypes.prng_key) and str(jax.random.key_impl(key)) == "threefry2x32"


def _fast(key: jax.Array) -> bool:
    # The counter layout below is that of the default `jax_threefry_partitionable=True`.
    return _is_threefry(key) and jax.config.jax_threefry_partitionable


def fold_in_words(key: jax.Array) -> tuple[jax.Array, jax.Array]:
    """`jax.random.key_data(jax.random.fold_in(key, 0))` as two uint32 words: one hash."""
    if not _fast(key):
        data = jax.random.key_data(jax.random.fold_in(key, 0))
        return data[..., 0], data[..., 1]
    data = jax.random.key_data(key)
    zero = jnp.zeros(data.shape[:-1], jnp.uint32)
    return hash_2x32(data[..., 0], data[..., 1], zero, zero)


def _counters(num: int) -> tuple[jax.Array, jax.Array]:
    """The 64-bit counters 0..num-1 as (high, low) uint32 words (num < 2**32)."""
    return jnp.zeros((num,), jnp.uint32), jnp.arange(num, dtype=jnp.uint32)


def split(key: jax.Array, num: int) -> jax.Array:
    """`jax.random.split(key, num)` for a single key."""
    if not _fast(key) or key.shape:
        return jax.random.split(key, num)
    data = jax.random.key_data(key)
    hi, lo = hash_2x32(data[0], data[1], *_counters(num))
    return jax.random.wrap_key_data(jnp.stack([hi, lo], axis=-1), impl="threefry2x32")


def bits(key: jax.Array, num: int) -> jax.Array:
    """`jax.random.bits(key, (num,))` (uint32) for a single key."""
    if not _fast(key) or key.shape:
        return jax.random.bits(key, (num,))
    data = jax.random.key_data(key)
    hi, lo = hash_2x32(data[0], data[1], *_counters(num))
    return hi ^ lo
