"""Dr.Jit conventions shared by every kernel of the package.

Numpy arrays handed to Dr.Jit on the LLVM backend are wrapped without a copy, and the kernel that reads
them is compiled with the alignment of that memory (``load … align 32`` for an aligned buffer, ``align 1``
otherwise).  Numpy's allocations are only 16-byte aligned, so the same kernel got a different source text,
and Dr.Jit compiled it again, whenever an input happened to land on another alignment: a neural flare
recompiled a few of its ghost kernels (seconds each) on each of its first renders, and a new process missed
the disk cache.  :func:`from_numpy` gives every array the same, 64-byte, alignment.
"""
from __future__ import annotations

import numpy as np

#: byte alignment of the buffers :func:`from_numpy` hands to Dr.Jit (a cache line, ≥ any vector width)
ALIGNMENT = 64


def aligned_copy(a, dtype) -> np.ndarray:
    """A C-contiguous copy of ``a`` as ``dtype`` whose data starts on an :data:`ALIGNMENT`-byte boundary (one
    pass: strided input and the type conversion are handled by the assignment)."""
    a = np.asarray(a)
    dtype = np.dtype(dtype)
    raw = np.empty(a.size * dtype.itemsize + ALIGNMENT, dtype=np.uint8)
    off = (-raw.ctypes.data) % ALIGNMENT
    out = raw[off:off + a.size * dtype.itemsize].view(dtype).reshape(a.shape)
    out[...] = a
    return out


def numpy_dtype(T):
    """The numpy dtype of the elements of the Dr.Jit array type ``T`` (e.g. ``mi.Float`` → float32)."""
    import drjit as dr
    vt = dr.type_v(T)
    table = {dr.VarType.Float16: np.float16, dr.VarType.Float32: np.float32, dr.VarType.Float64: np.float64,
             dr.VarType.Int32: np.int32, dr.VarType.UInt32: np.uint32, dr.VarType.Int64: np.int64,
             dr.VarType.UInt64: np.uint64, dr.VarType.Bool: np.bool_}
    return table[vt]


def from_numpy(T, a):
    """The 1-D Dr.Jit array ``T(a)`` over an aligned copy of ``a`` (converted to ``T``'s element type), so
    kernels reading it compile to the same code whatever numpy's allocation.  One copy, like
    ``T(np.ascontiguousarray(a, dtype))``, which it replaces."""
    a = np.asarray(a)
    return T(aligned_copy(a if a.ndim == 1 else a.reshape(-1), numpy_dtype(T)))
