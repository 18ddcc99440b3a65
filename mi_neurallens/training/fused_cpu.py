"""The CPU training step of a :class:`~mi_neurallens.training.stacked.StackedMLP`, fused: forward and backward
of K tanh MLPs in one compiled C kernel (``fused_mlp.c``) instead of PyTorch's per-layer operations.

Why.  PyTorch's CPU products for these shapes (MKL's batched ``sgemm``) run its AVX2 code on AMD processors,
about 185 GFLOP/s on two Zen 5 cores whose AVX-512 units reach 517; and between the products, every
activation, its derivative and each layer's gradient is a separate pass over ``(K, B, width)`` arrays that
leave the cache.  Here one thread takes 128 rows of one map through every layer and back, in registers and
L1, with Eigen's rational tanh (:func:`~mi_neurallens.neural.mlp.tanh_eigen`) in between.  The losses
of the regressors and margin classifiers are there too, value and gradient in one pass
(:meth:`FusedKernel.loss_regressor`, :meth:`FusedKernel.loss_margin`; ``stacked.fused_step`` runs a step
with them and no autograd).

Layout (what :class:`StackedMLP` holds): ``params`` = [W₀ (K, in, w), b₀ (K, 1, w), …, W_H (K, w, out),
b_H (K, 1, out)], each contiguous float32; inputs ``(K, B, in)``.  :func:`fused_forward` is an autograd
function of the parameters (the inputs get no gradient: the trainers never need one).

The kernel is compiled once per network shape and machine with the C compiler that ``torch.compile`` uses
(``cc``, ``-O3 -march=native``, OpenMP) and cached under ``~/.cache/mi_neurallens/fused`` (or
``$MI_NEURALLENS_CACHE``).  Where there is no compiler, or with ``MI_NEURALLENS_FUSED=0``, :func:`kernel`
returns None and the trainers keep PyTorch's operations; the two agree to float32 rounding
(``tests/test_fused_cpu.py``).
"""
from __future__ import annotations

import ctypes
import hashlib
import math
import os
import platform
import shutil
import subprocess
import tempfile
from pathlib import Path

_SOURCE = Path(__file__).with_name("fused_mlp.c")
_KERNELS: dict = {}
#: floats a kernel vector holds (its widths are multiples of it)
VECTOR = 16
#: the widest hidden layer (and most outputs) the kernel takes: 16 vectors of sums are its registers' worth
MAX_WIDTH = 16 * VECTOR
#: why the last :func:`kernel` call returned None, in words (for the training log)
WHY_NOT = {}


def _cache_dir() -> Path:
    root = os.environ.get("MI_NEURALLENS_CACHE") or os.path.join(Path.home(), ".cache", "mi_neurallens")
    return Path(root) / "fused"


def _cpu_id() -> str:
    """What ``-march=native`` compiles for: the processor's model and feature flags."""
    try:
        text = Path("/proc/cpuinfo").read_text()
        keys = ("model name", "flags", "Features", "CPU implementer", "CPU part")
        lines = sorted({ln.split(":", 1)[0].strip() + ":" + ln.split(":", 1)[-1] for ln in text.splitlines()
                        if ln.startswith(keys)})
        return "\n".join([platform.machine()] + lines)
    except OSError:
        return platform.machine() + platform.processor()


def _compiler() -> str | None:
    for cc in (os.environ.get("CC"), "cc", "gcc", "clang"):
        if cc and shutil.which(cc):
            return cc
    return None


def _header(dims) -> str:
    from ..neural.mlp import TANH_CLAMP, TANH_P, TANH_Q

    n_in, width, n_out, hidden = dims[0], dims[1], dims[-1], len(dims) - 2
    nv, nvo = width // VECTOR, -(-n_out // VECTOR)

    def block(a, nv):      # input units summed at once in a gradient: a divisor of a, with a x nv ≤ 16 sums
        return next(b for b in (16, 8, 4, 2, 1) if a % b == 0 and b * nv <= 16 or b == 1)

    lines = [f"#define NIN {n_in}", f"#define NW {width}", f"#define NOUT {n_out}", f"#define NH {hidden}",
             f"#define NVO {nvo}", f"#define RB_H {16 // nv}", f"#define RB_O {16 // nvo}",
             f"#define IB_IN {block(n_in, nv)}", f"#define IB_HID {block(width, nv)}",
             f"#define IB_OUT {block(width, nvo)}", f"#define TANH_CLAMP {TANH_CLAMP!r}f"]
    lines += [f"#define TANH_P{i} {c!r}f" for i, c in enumerate(TANH_P)]
    lines += [f"#define TANH_Q{i} {c!r}f" for i, c in enumerate(TANH_Q)]
    return "\n".join(lines) + "\n"


class FusedKernel:
    """The compiled forward and backward of one network shape ``dims`` = [in, w, …, w, out]."""

    def __init__(self, lib, dims, threads: int):
        self.lib, self.dims = lib, list(dims)
        lib.fused_forward.argtypes = [ctypes.c_int, ctypes.c_int, ctypes.c_void_p, ctypes.c_void_p,
                                      ctypes.c_void_p, ctypes.c_void_p]
        lib.fused_backward.argtypes = [ctypes.c_int, ctypes.c_int, ctypes.c_void_p, ctypes.c_void_p,
                                       ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p]
        lib.fused_set_threads.argtypes = [ctypes.c_int]
        P, L, I, F = ctypes.c_void_p, ctypes.c_long, ctypes.c_int, ctypes.c_float
        lib.loss_regressor.argtypes = [I, I, P, P, L, L, P, L, L, P, L, L, P, L, L, P, P, P, P, P, P, P, P,
                                       I, I, F, F, P, P]
        lib.loss_margin.argtypes = [I, I, P, P, L, L, F, P, P]
        lib.fused_set_threads(int(threads))

    @staticmethod
    def _ptrs(tensors):
        return (ctypes.c_void_p * len(tensors))(*[t.data_ptr() for t in tensors])

    def _padded_out(self, torch, params):
        """The parameters with the output layer's W and b zero-padded to whole vectors (the kernel's layout)."""
        pad = -self.dims[-1] % VECTOR
        ps = [p.detach().contiguous() for p in params]
        if pad:
            ps[-2] = torch.nn.functional.pad(ps[-2], (0, pad)).contiguous()
            ps[-1] = torch.nn.functional.pad(ps[-1], (0, pad)).contiguous()
        return ps

    def _check(self, torch, x, params):
        """What the kernel reads through raw pointers, checked: float32 CPU tensors of this network's shapes."""
        K = x.shape[0]
        want = []
        for a, b in zip(self.dims[:-1], self.dims[1:]):
            want += [(K, a, b), (K, 1, b)]
        if x.dim() != 3 or x.shape[2] != self.dims[0] or len(params) != len(want) or any(
                tuple(p.shape) != w for p, w in zip(params, want)) or any(
                t.dtype != torch.float32 or t.device.type != "cpu" for t in (x, *params)):
            raise ValueError(f"fused kernel {self.dims}: inputs {tuple(x.shape)} {x.dtype} and parameters "
                             f"{[tuple(p.shape) for p in params]} are not its float32 CPU shapes")

    def forward(self, torch, x, params):
        """x (K, B, in) float32 → (out (K, B, out), acts (K, H, B, w): the hidden layers' outputs)."""
        self._check(torch, x, params)
        K, B = x.shape[0], x.shape[1]
        x = x.contiguous()
        ps = self._padded_out(torch, params)
        acts = torch.empty((K, len(self.dims) - 2, B, self.dims[1]), dtype=torch.float32)
        out = torch.empty((K, B, self.dims[-1]), dtype=torch.float32)
        self.lib.fused_forward(K, B, x.data_ptr(), self._ptrs(ps), acts.data_ptr(), out.data_ptr())
        return out, acts

    def backward(self, torch, x, params, acts, gout):
        """Gradients of ``sum(gout · out)`` for every parameter, shaped as ``params``."""
        self._check(torch, x, params)
        K, B = x.shape[0], x.shape[1]
        if tuple(gout.shape) != (K, B, self.dims[-1]) or gout.dtype != torch.float32 or \
                tuple(acts.shape) != (K, len(self.dims) - 2, B, self.dims[1]):
            raise ValueError(f"fused kernel {self.dims}: gout {tuple(gout.shape)} or acts {tuple(acts.shape)}")
        x, gout, acts = x.contiguous(), gout.contiguous(), acts.contiguous()
        trans = [w.detach().transpose(1, 2).contiguous() for w in params[0::2]]
        grads = [torch.full_like(p, math.nan, memory_format=torch.contiguous_format) for p in params]
        self.lib.fused_backward(K, B, x.data_ptr(), self._ptrs(trans), acts.data_ptr(), gout.data_ptr(),
                                self._ptrs(grads))
        if math.isnan(float(grads[0].reshape(-1)[0])):       # its scratch could not be allocated
            raise MemoryError(f"fused kernel {self.dims}: no memory for {K} maps' gradient sums")
        return grads


    # -- the losses, value and gradient in one pass (fused_mlp.c, "The losses of training/regressor.py") -------
    @staticmethod
    def _check_rows(torch, out, n_out, *rows):
        """A loss's outputs (K, B, n_out) and its batch's arrays (K, B, ·): float32 on the CPU."""
        K, B = out.shape[0], out.shape[1]
        if out.dim() != 3 or out.shape[2] != n_out or any(
                r is not None and (tuple(r.shape[:2]) != (K, B) or r.dtype != torch.float32 or r.device.type != "cpu")
                for r in (out, *rows)):
            raise ValueError(f"fused loss: outputs {tuple(out.shape)} and rows "
                             f"{[None if r is None else (tuple(r.shape), r.dtype) for r in rows]}")

    @staticmethod
    def _rows(a):
        """(pointer, map stride, row stride) of a (K, B, c) batch view whose rows are contiguous."""
        if a.stride(-1) != 1:
            a = a.contiguous()
        return a, a.data_ptr(), a.stride(0), a.stride(1)

    def loss_regressor(self, torch, out, batch, const, *, odd: bool, cos_mode: int, cosine_weight: float,
                       heading: float):
        """(loss (K,) float32, ∂ΣK loss / ∂out (K, B, 5)) of :meth:`RegressorFit.rows_loss
        <mi_neurallens.training.regressor.RegressorFit.rows_loss>`; ``cos_mode`` 0: MSE, 1: cosine, 2: both."""
        K, B = out.shape[0], out.shape[1]
        self._check_rows(torch, out, 5, batch["X"], batch["Y"], batch["Yraw"], batch.get("W"))
        if batch["X"].shape[-1] != self.dims[0] or const["skip"].shape[-1] != self.dims[0]:
            raise ValueError(f"fused regressor loss: inputs {tuple(batch['X'].shape)}, skip {tuple(const['skip'].shape)}"
                             f", not (K, B, {self.dims[0]}) and (K, 5, {self.dims[0]})")
        out = out.detach().contiguous()
        keep = []
        rows = []
        for name in ("X", "Y", "Yraw"):
            a, ptr, ks, rs = self._rows(batch[name])
            keep.append(a)
            rows += [ptr, ks, rs]
        w = batch.get("W")
        if w is not None:
            a, ptr, ks, rs = self._rows(w)
            keep.append(a)
            rows += [ptr, ks, rs]
        else:
            rows += [None, 0, 0]
        c = {n: const[n].detach().to(torch.float32).contiguous() for n in
             ("W", "shift", "skip", "scale", "sig_d2", "wy_c", "wy_s", "odd_s")}
        loss = torch.empty(K, dtype=torch.float64)
        gout = torch.empty((K, B, 5), dtype=torch.float32)
        self.lib.loss_regressor(K, B, out.data_ptr(), *rows, *[c[n].data_ptr() for n in
                                ("W", "shift", "skip", "scale", "sig_d2", "wy_c", "wy_s", "odd_s")],
                                int(odd), int(cos_mode), float(cosine_weight), float(heading),
                                loss.data_ptr(), gout.data_ptr())
        return loss.to(torch.float32), gout

    def loss_margin(self, torch, out, target, clip: float):
        """(loss (K,) float32, ∂ΣK loss / ∂out (K, B, 1)) of :meth:`ClassifierFit.margin_loss
        <mi_neurallens.training.classifier.ClassifierFit.margin_loss>`."""
        K, B = out.shape[0], out.shape[1]
        self._check_rows(torch, out, 1, target)
        out = out.detach().contiguous()
        t = target if target.stride(-1) == 1 else target.contiguous()
        loss = torch.empty(K, dtype=torch.float64)
        gout = torch.empty((K, B, 1), dtype=torch.float32)
        self.lib.loss_margin(K, B, out.data_ptr(), t.data_ptr(), t.stride(0), t.stride(1), float(clip),
                             loss.data_ptr(), gout.data_ptr())
        return loss.to(torch.float32), gout


def kernel(torch, dims) -> FusedKernel | None:
    """The fused kernel for networks of shape ``dims`` on this CPU, compiled on first use (≈ 1 s) and cached
    on disk; None (and the reason in :data:`WHY_NOT`) when disabled or no C compiler works."""
    key = tuple(int(d) for d in dims)
    if key in _KERNELS:
        return _KERNELS[key]
    got = None
    if os.environ.get("MI_NEURALLENS_FUSED", "1") == "0":
        WHY_NOT[key] = "MI_NEURALLENS_FUSED=0"
    elif len(key) < 3 or len(set(key[1:-1])) != 1 or key[1] % VECTOR or not 0 < key[1] <= MAX_WIDTH \
            or not 0 < key[-1] <= MAX_WIDTH or key[0] < 1:
        WHY_NOT[key] = f"hidden layers {key[1:-1]}: one width, a multiple of {VECTOR} up to {MAX_WIDTH}"
    else:
        try:
            got = FusedKernel(ctypes.CDLL(str(_build(key))), key, torch.get_num_threads())
        except (OSError, subprocess.SubprocessError, RuntimeError) as e:
            WHY_NOT[key] = f"no compiled kernel ({str(e).strip().splitlines()[-1] if str(e).strip() else e})"
    _KERNELS[key] = got
    return got


def _build(dims) -> Path:
    """Compile ``fused_mlp.c`` for ``dims`` on this machine into the cache (once); returns the library."""
    cc = _compiler()
    if cc is None:
        raise RuntimeError("no C compiler (cc, gcc or clang) on PATH")
    header = _header(dims)
    source = _SOURCE.read_text()
    flags = ["-O3", "-march=native", "-ffp-contract=fast", "-fno-math-errno", "-fopenmp", "-shared", "-fPIC"]
    if "avx512f" in _cpu_id():
        flags.append("-mprefer-vector-width=512")
    tag = hashlib.sha1("\n".join([header, source, " ".join(flags), cc, _cpu_id()]).encode()).hexdigest()[:16]
    out = _cache_dir() / f"fused_mlp_{'x'.join(map(str, dims))}_{tag}.so"
    if out.exists():
        return out
    out.parent.mkdir(parents=True, exist_ok=True)
    # built beside its final name and renamed into place: another process sees the whole library or none
    with tempfile.TemporaryDirectory(dir=out.parent) as tmp:
        src = Path(tmp) / "fused_mlp.c"
        src.write_text(header + source)
        lib = Path(tmp) / out.name
        proc = subprocess.run([cc, *flags, str(src), "-o", str(lib)], capture_output=True, text=True, timeout=120)
        if proc.returncode != 0:
            raise RuntimeError(f"{cc} failed: {proc.stderr.strip()[-400:]}")
        os.replace(lib, out)
    return out


def fused_forward(torch, kern: FusedKernel, x, params):
    """``StackedMLP.forward`` of ``params`` on ``x`` through the fused kernel, differentiable in ``params``."""
    return _function(torch).apply(kern, x, *params)


_FN = {}


def _function(torch):
    if "fn" not in _FN:
        class Fused(torch.autograd.Function):
            @staticmethod
            def forward(ctx, kern, x, *params):
                out, acts = kern.forward(torch, x.detach(), params)
                ctx.kern = kern
                ctx.save_for_backward(x.detach(), acts, *[p.detach() for p in params])
                return out

            @staticmethod
            def backward(ctx, gout):
                x, acts, *params = ctx.saved_tensors
                grads = ctx.kern.backward(torch, x, params, acts, gout)
                return (None, None, *grads)

        _FN["fn"] = Fused
    return _FN["fn"]
