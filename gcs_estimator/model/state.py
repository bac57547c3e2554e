"""The augmented state vector, declared as named blocks.

The filters estimate one vector x_a assembled from blocks: the flight states
[V, alpha, theta, q], the aerodynamic coefficients of the configured structure, and
further blocks (sensor biases, gust states) as the model grows. Blocks with dynamics
come first: the filter kernels use that the rows of F below them are zero (constant
blocks have no dynamics, d(beta)/dt = w_beta).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple


class Block(NamedTuple):
    """A contiguous slice of the augmented state."""

    name: str
    names: tuple[str, ...]
    start: int
    dynamic: bool
    """True when the block has dynamics (rows of F not all zero)."""

    @property
    def stop(self) -> int:
        return self.start + len(self.names)

    @property
    def slice(self) -> slice:
        return slice(self.start, self.stop)


@dataclass(frozen=True)
class StateLayout:
    """The blocks of one augmented state, in order."""

    blocks: tuple[Block, ...]

    @staticmethod
    def assemble(blocks: Sequence[tuple[str, Sequence[str], bool]]) -> StateLayout:
        """Lay out (name, element names, dynamic) blocks one after another; dynamic
        blocks must come first."""
        out: list[Block] = []
        start = 0
        seen_constant = False
        for name, names, dynamic in blocks:
            if dynamic and seen_constant:
                raise ValueError(f"state block {name!r} has dynamics but follows a constant one")
            seen_constant = seen_constant or not dynamic
            if any(b.name == name for b in out):
                raise ValueError(f"state block {name!r} declared twice")
            out.append(Block(name, tuple(names), start, dynamic))
            start += len(names)
        return StateLayout(tuple(out))

    @property
    def n(self) -> int:
        """Dimension of the augmented state."""
        return self.blocks[-1].stop if self.blocks else 0

    @property
    def n_dynamic(self) -> int:
        """Leading elements with dynamics; F is zero below them."""
        return sum(len(b.names) for b in self.blocks if b.dynamic)

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(n for b in self.blocks for n in b.names)

    def block(self, name: str) -> Block:
        for b in self.blocks:
            if b.name == name:
                return b
        raise KeyError(f"no state block {name!r}; blocks: {[b.name for b in self.blocks]}")
