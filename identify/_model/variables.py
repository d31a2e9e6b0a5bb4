"""The unconstrained variables of a least-squares fit over logs: shared and per-log.

A fit of `L` logs has variables every log's residuals depend on (the physical parameters,
in the transformed coordinates `z` of `parameters.py`) and nuisances that belong to one log
each: free initial-state entries (`Problem.y0_free` order) and free sensor offsets
(`Problem.offset_free` order). That split is what makes the Jacobian block-arrow shaped
(`residuals.log_blocked`, `identify._fit.block_lm`), so the solvers ask every variables
record for the three parts by name: `shared`, `y0`, `offset`.

The records are pytrees (equinox modules): optimistix, `jax.vmap` and `ravel_pytree` take
them as they are. Their leaves flatten in field order, so that order is the order of the
columns of every Jacobian and of the flat step; the fields are declared alphabetically.
A batch of variables (a vmapped fit) is the same record with a leading axis on every leaf
(`take` picks rows).
"""

from __future__ import annotations

import abc
from typing import Any, TypeVar

import equinox as eqx
import jax

_V = TypeVar("_V", bound="AbstractVariables")


class AbstractVariables(eqx.Module):
    """Variables of a fit of logs: the `shared` part (any pytree) and each log's nuisances
    `y0` (free initial-state entries, SI) and `offset` (free sensor offsets, in their
    channels' SI units), each a flat vector over all logs (or a batch of them)."""

    offset: eqx.AbstractVar[Any]
    y0: eqx.AbstractVar[Any]

    @property
    @abc.abstractmethod
    def shared(self) -> Any:
        """The variables every log depends on (a pytree)."""

    @abc.abstractmethod
    def with_parts(self: _V, shared, y0, offset) -> _V:
        """The same kind of record with these parts (`shared` in `self.shared`'s structure)."""

    def take(self: _V, index) -> _V:
        """Rows `index` of a batch of variables (an int drops the batch axis)."""
        return jax.tree_util.tree_map(lambda a: a[index], self)


class Variables(AbstractVariables):
    """The variables of `identify.fit`: `phys`, the transformed coordinates `z` of the free
    physical parameters (`parameters.x_from_z`: `x = x_from_z(problem, phys)`, then
    `theta_from_x`), shared by the logs; `y0` and `offset`, the per-log nuisances."""

    offset: Any
    phys: Any
    y0: Any

    @property
    def shared(self):
        return self.phys

    def with_parts(self, shared, y0, offset) -> Variables:
        return Variables(offset=offset, phys=shared, y0=y0)
