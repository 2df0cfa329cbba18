"""Shared helpers for map-store tests."""

import numpy as np
import zarr



def store_arrays(path) -> dict:
    """Every array of a zarr store, by path."""
    out = {}

    def visit(group, prefix):
        for name, array in group.arrays():
            out[prefix + name] = array[:]
        for name, sub in group.groups():
            visit(sub, prefix + name + "/")
    visit(zarr.open_group(str(path), mode="r"), "")
    return out


def assert_same_store(a, b) -> None:
    A, B = store_arrays(a), store_arrays(b)
    assert sorted(A) == sorted(B)
    for key in A:
        x, y = A[key], B[key]
        if x.dtype.kind == "f":
            assert np.array_equal(x, y, equal_nan=True), key
        else:
            assert np.array_equal(x, y), key
