"""The history on disk: rows beyond a chunk go to a temporary file and come back equal."""

from __future__ import annotations

import numpy as np

from gcs_estimator.estimation.history import HISTORY_CHUNK, Rows


def test_rows_spill_to_disk_and_read_back_equal() -> None:
    rng = np.random.default_rng(1)
    data = rng.normal(size=(3 * HISTORY_CHUNK + 17, 5))
    rows = Rows(5)
    for k, row in enumerate(data):
        rows.append(row)
        if k % 1000 == 999:
            data[k] = row * 2  # the newest row replaced (a restart's swap)
            rows.last()[:] = data[k]
    assert rows.n == len(data)
    got = rows.array()
    assert isinstance(got, np.memmap)  # mapped from the file, not held in memory
    np.testing.assert_array_equal(got, data)
    # More rows after a read: the file goes on where it was.
    extra = rng.normal(size=(HISTORY_CHUNK, 5))
    for row in extra:
        rows.append(row)
    np.testing.assert_array_equal(rows.array(), np.vstack([data, extra]))


def test_a_short_history_stays_in_memory() -> None:
    rows = Rows(3)
    for k in range(10):
        rows.append((k, k, k))
    got = rows.array()
    assert not isinstance(got, np.memmap) and got.shape == (10, 3)


def test_column_groups_come_back_apart_each_from_its_own_file() -> None:
    """A row written at once, read back as groups (mapped from disk past a chunk)."""
    rng = np.random.default_rng(2)
    data = rng.normal(size=(2 * HISTORY_CHUNK + 5, 6))
    rows = Rows((2, 3, 1))
    for row in data:
        rows.claim()[:] = row
    rows.last()[:] = data[-1] = 7.0
    a, b, c = rows.arrays()
    assert all(isinstance(g, np.memmap) for g in (a, b, c))
    assert [g.shape[1] for g in (a, b, c)] == [2, 3, 1]
    np.testing.assert_array_equal(np.hstack([a, b, c]), data)
