"""Inputs that reach a node before its initial mesh, held until the mesh comes.

The schedulers of both nodes need the mesh, and a node may see its first tool poses, clouds or
prediction requests before it: `initial_mesh` is latched, but the discovery of its publisher
can come seconds after that of the streams (in one live run the simulation node got its mesh
2.5 s after the estimator and would have lost the first tool poses and requests). What arrives
first is good data, so it is kept, in arrival order, and handed to the scheduler when the mesh
comes. Beyond `capacity` inputs of one kind the oldest is dropped: the nodes count both.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from typing import Any

__all__ = ["HeldUntilMesh"]


class HeldUntilMesh:
    """At most `capacity` inputs of one kind (`what`, for messages), oldest first."""

    def __init__(self, what: str, capacity: int) -> None:
        if capacity < 1:
            raise ValueError(f"capacity must be >= 1, got {capacity}")
        self.what = what
        self.capacity = int(capacity)
        self._inputs: deque = deque()

    def __len__(self) -> int:
        return len(self._inputs)

    def hold(self, item: Any) -> str | None:
        """Keep `item`; when that overflows the capacity, drop the oldest and say why."""
        self._inputs.append(item)
        if len(self._inputs) <= self.capacity:
            return None
        self._inputs.popleft()
        return f"{self.what} dropped: {self.capacity} of them wait for the initial mesh"

    def release(self, handler: Callable[[Any], object]) -> int:
        """Hand every held input to `handler`, oldest first; how many there were."""
        count = 0
        while self._inputs:
            handler(self._inputs.popleft())
            count += 1
        return count
