"""Factorised noisy layers (Fortunato et al. 2018, NoisyNet): exploration through learned
parameter noise, for Rainbow's Q-network (`agents.common.networks.QNetwork` with `noisy`)."""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np


class NoisyDense(nn.Module):
    """Dense layer with learned factorised Gaussian noise (Fortunato et al., NoisyNet): kernel
    mu + sigma * f(e_in) f(e_out)^T, bias mu_b + sigma_b * f(e_out), f(e) = sign(e) sqrt|e|; at
    init mu ~ U(+-1/sqrt(fan_in)), sigma = sigma0 / sqrt(fan_in). With `noise`, fresh noise from
    the "noise" rng (`apply(..., rngs={"noise": key})`) on every call; without it, the mean (mu
    only).

    `per_row`: one draw for each (time step, world), the first two axes of the input, instead of
    one for the whole batch. Acting needs it: one draw shared by all worlds perturbs them alike, so
    they all take the same action. It costs a second matrix product, not a kernel per row:
    x (mu + sigma * e_in e_out^T) = x mu + ((x * e_in) sigma) * e_out. Learning keeps one draw per
    batch, as NoisyNet does."""

    features: int
    sigma0: float = 0.1
    noise: bool = False
    per_row: bool = False

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        fan_in = x.shape[-1]
        bound = 1.0 / np.sqrt(fan_in)
        uniform = lambda key, shape: jax.random.uniform(key, shape, jnp.float32, -bound, bound)
        sigma = nn.initializers.constant(self.sigma0 / np.sqrt(fan_in))
        kernel = self.param("kernel", uniform, (fan_in, self.features))
        bias = self.param("bias", uniform, (self.features,))
        sigma_kernel = self.param("sigma_kernel", sigma, (fan_in, self.features))
        sigma_bias = self.param("sigma_bias", sigma, (self.features,))
        if not self.noise:
            return x @ kernel + bias
        if self.per_row and x.ndim < 3:
            raise ValueError(f"per_row noise needs inputs (time, batch, ..., features), got shape {x.shape}")
        key_in, key_out = jax.random.split(self.make_rng("noise"))
        scale = lambda e: jnp.sign(e) * jnp.sqrt(jnp.abs(e))
        rows = x.shape[:2] + (1,) * (x.ndim - 3) if self.per_row else ()  # broadcast over any axes between
        noise_in = scale(jax.random.normal(key_in, rows + (fan_in,)))
        noise_out = scale(jax.random.normal(key_out, rows + (self.features,)))
        if self.per_row:
            return x @ kernel + bias + ((x * noise_in) @ sigma_kernel + sigma_bias) * noise_out
        return x @ (kernel + sigma_kernel * jnp.outer(noise_in, noise_out)) + bias + sigma_bias * noise_out


def noisy_dense(sigma0: float, noise: bool, per_row: bool = False):
    """A `agents.common.networks.Layer` of noisy layers: `(features, gain) -> NoisyDense` (its own init, no gain)."""
    return lambda features, gain: NoisyDense(features, sigma0=sigma0, noise=noise, per_row=per_row)
