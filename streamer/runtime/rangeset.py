"""Sets of segment indices kept as ranges (:class:`RangeSet`).

The stages' and the launcher's bookkeeping of indices (done, failed, gaps, conflicts) is in
ranges, never per index: an index of 2^40 costs one range, not 2^40 entries.
"""

from __future__ import annotations

import bisect
from collections.abc import Iterable


class RangeSet:
    """A set of non-negative integers kept as sorted disjoint ``[first, last]`` ranges.

    Memory is O(number of ranges), whatever the indices: adding 2^40 costs one range.
    """

    def __init__(self, items: Iterable[int] = ()):
        self._starts: list[int] = []
        self._ends: list[int] = []
        for i in items:
            self.add(i)

    @classmethod
    def from_ranges(cls, ranges, limit: int | None = None) -> RangeSet:
        """From ``[[first, last], ...]``, malformed entries ignored, clipped to ``[0, limit)``."""
        out = cls()
        for r in ranges or ():
            try:
                a, b = int(r[0]), int(r[1])
            except (TypeError, ValueError, IndexError, OverflowError):
                continue
            if limit is not None:
                b = min(b, limit - 1)
            a = max(a, 0)
            if a <= b:
                out.add_range(a, b)
        return out

    def add(self, i: int) -> None:
        self.add_range(i, i)

    def add_range(self, a: int, b: int) -> None:
        """Add ``a .. b`` (inclusive)."""
        k = bisect.bisect_left(self._ends, a - 1)  # first range that ends at or after a - 1
        j = k
        while j < len(self._starts) and self._starts[j] <= b + 1:
            a, b = min(a, self._starts[j]), max(b, self._ends[j])
            j += 1
        self._starts[k:j] = [a]
        self._ends[k:j] = [b]

    def discard(self, i: int) -> None:
        k = bisect.bisect_right(self._starts, i) - 1
        if k < 0 or self._ends[k] < i:
            return
        a, b = self._starts[k], self._ends[k]
        new = [(x, y) for x, y in ((a, i - 1), (i + 1, b)) if x <= y]
        self._starts[k : k + 1] = [x for x, _ in new]
        self._ends[k : k + 1] = [y for _, y in new]

    def __contains__(self, i) -> bool:
        k = bisect.bisect_right(self._starts, i) - 1
        return k >= 0 and self._ends[k] >= i

    def __len__(self) -> int:
        return sum(b - a + 1 for a, b in zip(self._starts, self._ends))

    def __bool__(self) -> bool:
        return bool(self._starts)

    def __iter__(self):
        for a, b in zip(self._starts, self._ends):
            yield from range(a, b + 1)

    def ranges(self) -> list[list[int]]:
        return [[a, b] for a, b in zip(self._starts, self._ends)]

    @property
    def n_ranges(self) -> int:
        return len(self._starts)

    def max(self, default: int = -1) -> int:
        return self._ends[-1] if self._ends else default

    def covers(self, a: int, b: int) -> bool:
        """True when every index ``a .. b`` is in the set."""
        k = bisect.bisect_right(self._starts, a) - 1
        return k >= 0 and self._ends[k] >= b

    def missing(self, a: int, b: int) -> list[list[int]]:
        """The ranges of ``a .. b`` not in the set."""
        out, pos = [], a
        k = max(0, bisect.bisect_right(self._starts, a) - 1)
        for s, e in zip(self._starts[k:], self._ends[k:]):
            if s > b:
                break
            if e < pos:
                continue
            if s > pos:
                out.append([pos, s - 1])
            pos = e + 1
        if pos <= b:
            out.append([pos, b])
        return out

    def update(self, items: Iterable[int]) -> None:
        """Add every index of ``items`` (a :class:`RangeSet` range by range)."""
        if isinstance(items, RangeSet):
            for a, b in zip(items._starts, items._ends):
                self.add_range(a, b)
        else:
            for i in items:
                self.add(i)

    def copy(self) -> RangeSet:
        out = RangeSet()
        out._starts, out._ends = list(self._starts), list(self._ends)
        return out

    def __or__(self, other) -> RangeSet:
        out = self.copy()
        out.update(other)
        return out

    __ror__ = __or__

    def __ior__(self, other) -> RangeSet:
        self.update(other)
        return self

    def __sub__(self, other) -> RangeSet:
        """The indices of this set not in ``other`` (a RangeSet or any container)."""
        if isinstance(other, RangeSet):
            out = RangeSet()
            for a, b in zip(self._starts, self._ends):
                for x, y in other.missing(a, b):
                    out.add_range(x, y)
            return out
        out = self.copy()
        for i in other:
            out.discard(i)
        return out

    def __rsub__(self, other) -> set:
        """``other - self`` for a plain set (or any iterable): a set."""
        return {i for i in other if i not in self}

    def issuperset(self, items) -> bool:
        """True when every index of ``items`` is in the set (a ``range`` of step 1: in one look-up)."""
        if isinstance(items, range) and items.step == 1:
            return len(items) == 0 or self.covers(items.start, items.stop - 1)
        if isinstance(items, RangeSet):
            return all(self.covers(a, b) for a, b in zip(items._starts, items._ends))
        return all(i in self for i in items)

    def __eq__(self, other) -> bool:
        if isinstance(other, RangeSet):
            return self._starts == other._starts and self._ends == other._ends
        if isinstance(other, (set, frozenset)):
            return len(self) == len(other) and all(i in self for i in other)
        return NotImplemented

    # unhashable (mutable): a class that defines __eq__ and not __hash__ has __hash__ = None

    def __repr__(self) -> str:
        return f"RangeSet({self.ranges()})"
