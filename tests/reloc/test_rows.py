"""RowBuffer against a plain list of rows under random appends, truncations and reads."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from reloc.rows import RowBuffer

ops = st.lists(st.one_of(st.tuples(st.just("append"), st.integers(1, 9)),
                         st.tuples(st.just("truncate"), st.floats(0.0, 1.0)),
                         st.tuples(st.just("set_last"), st.integers(0, 3))), max_size=80)


@settings(max_examples=60, deadline=None)
@given(ops, st.integers(1, 5))
def test_row_buffer_behaves_like_a_list_of_rows(program, block):
    buf, model, k = RowBuffer(3, block=block), [], 0
    for op, arg in program:
        if op == "append":
            for _ in range(arg):
                k += 1
                row = np.array([k, -k, 0.5 * k])
                buf.append(row)
                model.append(row)
        elif op == "truncate":
            n = int(arg * len(model))
            tail = buf.array(n)
            np.testing.assert_array_equal(tail, np.array(model[n:]).reshape(-1, 3))
            buf.truncate(n)
            del model[n:]
        elif model:
            buf.last()[:] = arg
            model[-1] = np.full(3, float(arg))
        assert len(buf) == len(model)
        np.testing.assert_array_equal(buf.array(), np.array(model).reshape(-1, 3))
    buf.extend(np.arange(6.0).reshape(2, 3))
    assert len(buf) == len(model) + 2 and buf.last().tolist() == [3.0, 4.0, 5.0]


def test_row_buffer_refuses_bad_lengths():
    buf = RowBuffer(2)
    with pytest.raises(IndexError):
        buf.last()
    with pytest.raises(IndexError):
        buf.truncate(1)
    with pytest.raises(ValueError):
        RowBuffer(0)


@pytest.mark.parametrize("block", [1, 2, 4])
def test_truncating_to_the_whole_length_keeps_every_row(block):
    """A buffer whose current block is full, cut to its own length (a rollback with nothing after
    the restored step), keeps all its rows."""
    buf = RowBuffer(2, block=block)
    rows = np.arange(2.0 * 2 * block).reshape(-1, 2)
    buf.extend(rows)
    buf.truncate(len(buf))
    np.testing.assert_array_equal(buf.array(), rows)
    buf.append([-1.0, -2.0])
    assert len(buf) == len(rows) + 1 and buf.last().tolist() == [-1.0, -2.0]


@pytest.mark.parametrize("block", [1, 3, 8])
def test_row_reads_every_row_across_blocks_and_after_a_cut(block):
    buf = RowBuffer(2, block=block)
    rows = np.arange(2.0 * 11).reshape(-1, 2)
    buf.extend(rows)
    for i in range(len(rows)):
        np.testing.assert_array_equal(buf.row(i), rows[i])
    buf.truncate(5)
    buf.append([-1.0, -2.0])
    assert buf.row(5).tolist() == [-1.0, -2.0] and buf.row(4).tolist() == rows[4].tolist()
    for i in (-1, 6):
        with pytest.raises(IndexError):
            buf.row(i)
