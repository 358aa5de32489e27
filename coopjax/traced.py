"""Whether JAX is tracing a value, and for what: the one place that asks.

A check that needs concrete values (a step-size limit, a parameter's sign) runs only on concrete
ones; a traced value gets the check's mark instead (`coopjax.status`). A derivative rule needs to
know whether it is pushed forward (`jvp`, `jacfwd`) or pulled back (`grad`, `vjp`, `linearize`).
"""

from __future__ import annotations

import jax


def is_tracer(x) -> bool:
    """`x` is traced (under jit, vmap, grad, ...), so its value is not known here."""
    return isinstance(x, jax.core.Tracer)


def is_traced(tree) -> bool:
    """Some leaf of `tree` is traced."""
    return any(is_tracer(x) for x in jax.tree_util.tree_leaves(tree))


def differentiated(tree) -> bool:
    """`jvp`, `grad` or `linearize` is tracing some leaf of `tree` (jit and vmap alone are not)."""
    return any(any(s in type(x).__name__ for s in ("JVP", "Linearize")) for x in jax.tree_util.tree_leaves(tree))


def pulled_back(tangents) -> bool:
    """Inside a `custom_jvp` rule: reverse mode (`grad`, `vjp`, `linearize`) is tracing it. JAX then
    evaluates the rule partially, and its tangents are the unknowns of that trace; under forward
    mode they are concrete or batched values. Either answer is exact: a miss only costs time."""
    return any(type(d).__name__ == "JaxprTracer" for d in tangents)
