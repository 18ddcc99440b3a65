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

#: the oldest LLVM whose code generation Dr.Jit 1.5's kernels survive (LLVM 15 aborts the process with
#: "Cannot select: ... fmaximum/fminimum" on the first kernel that uses dr.minimum/dr.maximum)
MIN_LLVM = 16


def check_llvm() -> None:
    """Raise a :class:`~mi_neurallens.errors.NeuralLensError` that says what to install when the LLVM library
    Dr.Jit loaded is older than :data:`MIN_LLVM`: LLVM 15 does not fail cleanly, it aborts the whole Python
    process inside the first kernel compilation.  Nothing happens when Dr.Jit found no LLVM at all (its own
    error says so when an LLVM variant is used) or found a recent one."""
    import drjit as dr
    major = dr.detail.llvm_version()[0]
    if 0 < major < MIN_LLVM:
        from .errors import NeuralLensError
        found = ".".join(str(v) for v in dr.detail.llvm_version())
        raise NeuralLensError(
            f"Dr.Jit loaded LLVM {found}, which aborts the process while compiling its kernels; mi-neurallens "
            f"needs LLVM >= {MIN_LLVM} for Mitsuba's llvm_* variants. On Debian or Ubuntu: `sudo apt-get install "
            f"libllvm19`, then `export DRJIT_LIBLLVM_PATH=/usr/lib/$(uname -m)-linux-gnu/libLLVM.so.19.1` if "
            f"Dr.Jit still finds the old one (elsewhere: any LLVM >= {MIN_LLVM} shared library, named by "
            f"DRJIT_LIBLLVM_PATH). A cuda_* variant needs no LLVM.")


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


class untraversed:
    """A data descriptor for Python attributes of Mitsuba plugins that Dr.Jit's traversal must not visit.

    Dr.Jit traverses a Python plugin (a subclass of a Mitsuba class) through every value of its ``__dict__``,
    descending into lists, dicts and dataclasses: for a frozen function (``dr.freeze``) that takes a scene,
    once per call.  Our sensors hold the lens, its set-up and a whole neural model there — thousands of numpy
    layers and no Dr.Jit variable the sensor's kernels need from them as inputs — and a call that took the
    scene spent 16 ms (``realistic_lens``) to 340 ms (``neural_lens``) on that walk alone.  The value is kept
    in a plain holder object, which the traversal does not enter; reading and assigning work as usual::

        class MySensor(mi.Sensor):
            setup = untraversed()
    """

    class _Box:
        __slots__ = ("value",)

        def __init__(self, value):
            self.value = value

    def __set_name__(self, owner, name):
        self.name, self.key = name, "_untraversed_" + name

    def __get__(self, obj, objtype=None):
        if obj is None:
            return self
        try:
            return obj.__dict__[self.key].value
        except KeyError:
            raise AttributeError(f"{type(obj).__name__!r} object has no attribute {self.name!r}") from None

    def __set__(self, obj, value):
        obj.__dict__[self.key] = untraversed._Box(value)
