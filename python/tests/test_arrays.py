"""numpy input: every dtype, C and Fortran order, non-contiguous slices;
C-ordered stacks are read in place (zero copy), the rest copied once."""

import resource
import subprocess
import sys
import textwrap

import numpy as np
import pytest

import scanloc


@pytest.fixture(scope="module")
def frames():
    m = scanloc.Microscope(height=36, width=40, emitters=3, brightness=50)
    data, _ = scanloc.simulate(8, seed=5, microscope=m, progress=False)
    assert data.dtype == np.uint16 and data.flags.c_contiguous
    return data


def same(a, b):
    a = a.sort_values(["frame", "x", "y"]).reset_index(drop=True)
    b = b.sort_values(["frame", "x", "y"]).reset_index(drop=True)
    assert len(a) == len(b) > 0
    for column in a.columns:
        np.testing.assert_array_equal(a[column].to_numpy(), b[column].to_numpy(), err_msg=column)


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.uint32, np.float32, np.float64])
def test_c_order_is_zero_copy_and_fortran_order_gives_the_same_features(frames, dtype):
    data = np.clip(frames, 0, 255).astype(dtype) if dtype == np.uint8 else frames.astype(dtype)
    assert scanloc.is_zero_copy(data)
    fortran = np.asfortranarray(data)
    assert not fortran.flags.c_contiguous and not scanloc.is_zero_copy(fortran)
    same(scanloc.locate(data, 7, progress=False), scanloc.locate(fortran, 7, progress=False))


def test_non_contiguous_slices_equal_their_copies(frames):
    for view in (frames[::2], frames[:, 2:-3, 1:-1], frames[:, ::-1]):
        assert not scanloc.is_zero_copy(view)
        same(scanloc.locate(view, 7, progress=False), scanloc.locate(np.ascontiguousarray(view), 7, progress=False))


def test_other_integer_dtypes_are_converted(frames):
    assert not scanloc.is_zero_copy(frames.astype(np.int64))
    same(scanloc.locate(frames.astype(np.int64), 7, progress=False),
         scanloc.locate(frames.astype(np.uint32), 7, progress=False))
    big_endian = frames.astype(">u2")
    same(scanloc.locate(big_endian, 7, progress=False), scanloc.locate(frames, 7, progress=False))


def test_the_input_is_left_unchanged(frames):
    before = frames.copy()
    scanloc.locate(frames, 7, progress=False)
    np.testing.assert_array_equal(frames, before)


def test_an_empty_stack_gives_an_empty_table():
    table = scanloc.locate(np.zeros((0, 20, 20), np.uint16), 7, progress=False)
    assert len(table) == 0 and list(table.columns) == scanloc.FEATURE_COLUMNS


def peak_growth(order):
    """The peak memory a locate adds over a 128 MB uint16 stack, in a
    fresh interpreter, over the stack's size."""
    code = textwrap.dedent(f"""
        import resource, numpy as np, scanloc
        stack = np.ones((250, 512, 512), np.uint16, order={order!r})
        stack[:, ::37, ::41] = 40
        before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        scanloc.locate(stack, 7, progress=False)
        after = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        print((after - before) * 1024 / stack.nbytes)
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return float(out.stdout.strip())


def test_a_c_ordered_stack_is_not_copied():
    # Zero copy: what locate adds is its per-thread buffers and features,
    # far below the stack; a copy of it would add at least 1.0.
    assert peak_growth("C") < 0.5
    # A Fortran-ordered one is copied once, in C order.
    assert peak_growth("F") >= 0.9
