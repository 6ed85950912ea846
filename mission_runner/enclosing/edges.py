"""Directed edges from the computing rows to slots, for swarms whose graph is sparse.

:func:`.step.enclosing_step` relates every row to every slot on ``(..., R, S)`` planes: the
complete graph's layout, and one vehicle's (a single row). On a sparse graph almost all of a
plane is masked out (1000 vehicles with 6 neighbours each: 7000 edges of 1 001 000 entries), so
with an :class:`EdgeIndex` the step keeps its estimators, errors and weights on ``(..., E)``
arrays, one entry per directed edge (row i, slot j), and sums them by row.

Edges are fixed for a run (the union of every graph the run will have, e.g. a ring closing over
a loss); which of them are graph edges at step k is a mask ``(..., E)``. An edge outside the
graph at step k is left as the dense planes leave an entry masked out: not ranged, not updated,
not in the sums.
"""

from dataclasses import dataclass
from typing import Self, TypeVar

import numpy as np
from numpy.typing import NDArray

Item = TypeVar("Item", bound=np.generic)


@dataclass(frozen=True)
class EdgeIndex:
    """Directed edges (row, slot), sorted by row then slot; no self edge.

    row: ``(E,)`` the computing row (0..R-1). slot: ``(E,)`` the slot (0 the target).
    reverse: ``(E,)`` the edge from the slot's row back to this row's slot, -1 where there is
    none (the target, a slot that is not a row, a one-way edge). starts: ``(R,)`` each row's
    first edge (clipped to E - 1). empty: ``(R,)`` bool, rows without an edge.
    n_rows, n_slots: R and S.
    """

    row: NDArray[np.intp]
    slot: NDArray[np.intp]
    reverse: NDArray[np.intp]
    starts: NDArray[np.intp]
    empty: NDArray[np.bool_]
    n_rows: int
    n_slots: int

    @classmethod
    def of_mask(cls, mask: NDArray[np.bool_], row_slots: NDArray[np.intp]) -> Self:
        """The edges of a boolean ``(R, S)`` mask, for rows at slots ``row_slots`` ``(R,)``
        (self entries dropped)."""
        n_rows, n_slots = mask.shape
        not_self = np.arange(n_slots) != row_slots[:, None]
        row, slot = np.nonzero(mask & not_self)  # row-major: sorted by row, then slot
        row_of_slot = np.full(n_slots, -1)
        row_of_slot[row_slots] = np.arange(n_rows)
        key = row * n_slots + slot
        back_row = row_of_slot[slot]
        back_key = back_row * n_slots + row_slots[row]
        found = np.minimum(np.searchsorted(key, back_key), max(key.size - 1, 0))
        has_reverse = (back_row >= 0) & (key.size > 0) & (key[found] == back_key)
        counts = np.bincount(row, minlength=n_rows)
        starts = np.cumsum(counts) - counts
        return cls(
            row=row,
            slot=slot,
            reverse=np.where(has_reverse, found, -1),
            starts=np.minimum(starts, max(row.size - 1, 0)),
            empty=counts == 0,
            n_rows=n_rows,
            n_slots=n_slots,
        )

    @property
    def size(self) -> int:
        """E, the number of edges."""
        return int(self.row.size)

    def gather(self, plane: NDArray[Item]) -> NDArray[Item]:
        """``(..., R, S)`` -> the entries of the edges ``(..., E)``."""
        return plane[..., self.row, self.slot]

    def scatter(self, values: NDArray[Item], fill: object) -> NDArray[Item]:
        """``(..., E)`` -> ``(..., R, S)`` planes, ``fill`` off the edges."""
        plane = np.full((*values.shape[:-1], self.n_rows, self.n_slots), fill, dtype=values.dtype)
        plane[..., self.row, self.slot] = values
        return plane

    def difference(
        self, row_values: NDArray[np.float64], slot_values: NDArray[np.float64]
    ) -> NDArray[np.float64]:
        """``row_values[row] - slot_values[slot]`` ``(..., E)`` for values by row ``(..., R)``
        and by slot ``(..., S)``."""
        return row_values[..., self.row] - slot_values[..., self.slot]

    def reversed(self, values: NDArray[np.float64]) -> NDArray[np.float64]:
        """Each edge's reverse edge's value ``(..., E)``; NaN where there is none."""
        return np.where(self.reverse >= 0, values[..., self.reverse], np.nan)

    def row_sums(self, values: NDArray[np.generic]) -> NDArray[np.float64]:
        """The sum of ``values`` ``(..., E)`` over each row's edges ``(..., R)`` (0 for a row
        without edges), in edge order."""
        if self.size == 0:
            return np.zeros((*values.shape[:-1], self.n_rows))
        sums = np.add.reduceat(values.astype(float, copy=False), self.starts, axis=-1)
        return np.where(self.empty, 0.0, sums)
