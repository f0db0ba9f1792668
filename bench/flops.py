"""The matrix arithmetic a JAX function does, counted from its jaxpr: the multiply-adds of every
`dot_general` and convolution, times the trips of the scans around them.

Why from the jaxpr rather than from a parameter count: a count of weights says nothing of a
convolution's reuse of its kernel, of a design encoded once per episode rather than per step, or
of a replayed batch's size; the traced program holds all of it. XLA's own cost analysis counts a
loop's body once, whatever its trip count, so it undercounts every learner (each is a scan of
scans). A `while_loop`'s trips are unknown before it runs: its body counts once; a `cond`
counts its costliest branch; either way the result says it is not exact.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import jax
from jax.extend import core


@dataclass(frozen=True)
class Flops:
    total: float  # multiply-adds x 2
    exact: bool  # False: a while loop's body was counted once


def count(fn, *args, **kwargs) -> Flops:
    """The matrix FLOPs of one call `fn(*args, **kwargs)` (traced, not run)."""
    return _jaxpr_flops(jax.make_jaxpr(fn)(*args, **kwargs).jaxpr)


def _jaxpr_flops(jaxpr) -> Flops:
    total, exact = 0.0, True
    for eqn in jaxpr.eqns:
        name = eqn.primitive.name
        if name == "dot_general":
            total += _dot_flops(eqn)
        elif name == "conv_general_dilated":
            total += _conv_flops(eqn)
        elif name == "cond":
            branches = [_jaxpr_flops(b.jaxpr) for b in eqn.params["branches"]]
            total += max(b.total for b in branches)  # which runs is known only at run time: an upper bound
            exact &= all(b.exact for b in branches) and len({b.total for b in branches}) == 1
        else:
            inner = [_jaxpr_flops(j) for j in _sub_jaxprs(eqn.params)]
            trips = eqn.params["length"] if name == "scan" else 1
            total += trips * sum(f.total for f in inner)
            exact &= all(f.exact for f in inner) and name != "while"
    return Flops(total, exact)


def _sub_jaxprs(params: dict):
    for value in params.values():
        for item in value if isinstance(value, (tuple, list)) else (value,):
            if isinstance(item, core.ClosedJaxpr):
                yield item.jaxpr
            elif isinstance(item, core.Jaxpr):
                yield item


def _dot_flops(eqn) -> float:
    (lhs_contract, _), _ = eqn.params["dimension_numbers"]
    lhs = eqn.invars[0].aval.shape
    return 2.0 * math.prod(eqn.outvars[0].aval.shape) * math.prod(lhs[d] for d in lhs_contract)


def _conv_flops(eqn) -> float:
    rhs = eqn.invars[1].aval.shape
    spec = eqn.params["dimension_numbers"].rhs_spec  # (out features, in features, *spatial)
    per_output = math.prod(rhs[d] for d in spec[1:])  # in features (per group) x kernel
    return 2.0 * math.prod(eqn.outvars[0].aval.shape) * per_output
