"""Inputs that reach a node before its initial mesh, held until the mesh comes.

The schedulers of both nodes need the mesh, and a node may see its first tool poses, clouds or
prediction requests before it: `initial_mesh` is latched, but the discovery of its publisher
can come seconds after that of the streams (in one live run the simulation node got its mesh
2.5 s after the estimator and would have lost the first tool poses and requests). What arrives
first is good data, so it is kept and handed on when the mesh comes, in arrival order (an
estimate answers the request before it: handed on first, the simulator would ignore it). Each
kind has a capacity (a cloud or a mesh is large, a pose small); beyond it the oldest input of
that kind is dropped, and the nodes count what is held and dropped.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Mapping
from typing import Any

__all__ = ["HeldUntilMesh"]


class HeldUntilMesh:
    """Inputs in arrival order, each with the handler that takes it once the mesh is there;
    `capacities`: kind -> how many of that kind are kept at most."""

    def __init__(self, capacities: Mapping[str, int]) -> None:
        if any(capacity < 1 for capacity in capacities.values()):
            raise ValueError(f"every capacity must be >= 1, got {dict(capacities)}")
        self.capacities = dict(capacities)
        self._inputs: deque[tuple[str, Callable[[Any], object], Any]] = deque()
        self._counts = dict.fromkeys(self.capacities, 0)

    def hold(self, kind: str, handler: Callable[[Any], object], item: Any) -> str | None:
        """Keep `item` for `handler`; when that makes more of `kind` than its capacity, drop the
        oldest of that kind and say so."""
        self._inputs.append((kind, handler, item))
        self._counts[kind] += 1
        if self._counts[kind] <= self.capacities[kind]:
            return None
        oldest = next(index for index, (held_kind, _, _) in enumerate(self._inputs) if held_kind == kind)
        del self._inputs[oldest]  # O(held), only on overflow
        self._counts[kind] -= 1
        return f"{kind} dropped: {self.capacities[kind]} of them wait for the initial mesh"

    def release(self) -> None:
        """Hand every held input to its handler, oldest first."""
        while self._inputs:
            kind, handler, item = self._inputs.popleft()
            self._counts[kind] -= 1
            handler(item)
