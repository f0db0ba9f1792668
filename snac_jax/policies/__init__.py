"""Policies that the evaluator and the CLI can run, by name.

Every policy implements the one interface of `snac_jax.policy.Policy`. The registry maps a
name to a *builder* `builder(env, **options) -> Policy` (for `env`'s task), named as
"module:function" so that listing the names imports nothing heavy.

Learned agents are not registered by name: a trained run is its checkpoint directory, and
`snac eval --checkpoint DIR` takes its builder from the installed checkpoint loader
(`snac_jax.plugins.checkpoint_loader()`, which the agents package provides as
`agents.training.trained.checkpoint_builder`). That builder has the same `builder(env, **options)` form,
so the evaluator runs a checkpoint exactly as it runs the policies listed here.
"""

from __future__ import annotations

import dataclasses
import importlib
from collections.abc import Callable
from typing import Any

from snac_jax.policy import Policy

PolicyBuilder = Callable[..., Policy]


@dataclasses.dataclass(frozen=True)
class PolicyEntry:
    builder: str  # "module:function", called as builder(env, **options)
    paper_method: str | None  # key of the paper's table (`paper_results.json` "methods"), if any
    help: str


POLICIES: dict[str, PolicyEntry] = {
    "handcrafted": PolicyEntry(
        builder="snac_jax.policies.handcrafted:handcrafted_policy",
        paper_method="handcrafted",
        help="the paper's handcrafted baseline (1D: the variant without a brick map, as the paper's table)",
    ),
    "handcrafted-map": PolicyEntry(
        builder="snac_jax.policies.handcrafted:handcrafted_policy_map",
        paper_method="handcrafted",
        help="the handcrafted baseline, 1D variant with its own brick map (2D/3D unchanged)",
    ),
    "random": PolicyEntry(
        builder="snac_jax.policies.random:random_policy", paper_method=None, help="uniformly random actions"
    ),
}


def policy_builder(name: str) -> PolicyBuilder:
    """The builder registered as `name`; `ValueError` naming the registered ones otherwise."""
    if name not in POLICIES:
        raise ValueError(f"unknown policy {name!r}; registered policies: {', '.join(POLICIES)}")
    module, function = POLICIES[name].builder.split(":")
    return getattr(importlib.import_module(module), function)


def build_policy(name: str, env: Any, **options: Any) -> Policy:
    return policy_builder(name)(env, **options)


__all__ = ["POLICIES", "Policy", "PolicyBuilder", "PolicyEntry", "build_policy", "policy_builder"]
