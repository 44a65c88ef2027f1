"""``RowBuffer``: float64 rows of one width appended one by one, for the long histories a run
records (poses, covariances, truth at 10-30 Hz over hours).

A kilometre traverse records ~10^5-10^6 poses; as lists of small arrays they cost several times
the numbers they hold (an EKF pose with its covariance: ~690 B as two arrays and a float, 424 B as a row),
and the lists grew ``fgslam run``'s memory by ~0.2 MB per metre. Rows are kept in blocks of
``block``; the buffer can be cut back to a length (a filter's rollback) and grown again.
"""

from __future__ import annotations

import numpy as np


class RowBuffer:
    """Float64 rows of ``width`` numbers, kept in blocks of ``block`` rows."""

    def __init__(self, width: int, block: int = 4096) -> None:
        if width < 1 or block < 1:
            raise ValueError(f"RowBuffer needs width and block >= 1, got {width}, {block}")
        self.width, self.block = int(width), int(block)
        self._full: list[np.ndarray] = []
        self._cur = np.empty((self.block, self.width))
        self._n = 0

    def __len__(self) -> int:
        return len(self._full) * self.block + self._n

    def append(self, row) -> None:
        if self._n == self.block:
            self._full.append(self._cur)
            self._cur, self._n = np.empty((self.block, self.width)), 0
        self._cur[self._n] = row
        self._n += 1

    def extend(self, rows: np.ndarray) -> None:
        for row in np.asarray(rows, dtype=float).reshape(-1, self.width):
            self.append(row)

    def row(self, i: int) -> np.ndarray:
        """Row ``i`` (a view: writing to it changes the buffer)."""
        if not 0 <= i < len(self):
            raise IndexError(f"row {i} of a RowBuffer of {len(self)} rows")
        k, r = divmod(i, self.block)
        return self._full[k][r] if k < len(self._full) else self._cur[r]

    def last(self) -> np.ndarray:
        """The newest row (a view: writing to it changes the buffer)."""
        if not len(self):
            raise IndexError("last() of an empty RowBuffer")
        return self.row(len(self) - 1)

    def truncate(self, n: int) -> None:
        """Keep the first ``n`` rows."""
        if not 0 <= n <= len(self):
            raise IndexError(f"cannot truncate a RowBuffer of {len(self)} rows to {n}")
        if n == len(self):  # nothing to cut (and the current block may be full: n // block
            return          # would then point one block past it)
        k, r = divmod(n, self.block)
        if k < len(self._full):
            self._cur = self._full[k]
            del self._full[k:]
            self._n = r
        else:
            self._n = r

    def blocks(self):
        """The rows block by block, oldest first (views, no copy)."""
        yield from self._full
        if self._n:
            yield self._cur[: self._n]

    def array(self, start: int = 0) -> np.ndarray:
        """The rows from index ``start`` on (all by default), (len - start, width), a copy."""
        if start >= len(self):
            return np.zeros((0, self.width))
        k, r = divmod(max(start, 0), self.block)
        parts = [*self._full[k:], self._cur[: self._n]]
        parts[0] = parts[0][r:]
        return np.concatenate(parts)
