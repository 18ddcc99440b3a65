"""Training the stop head of a learned map: where its rays cross the aperture-stop plane.

Stopping down changes only *which* rays pass, never where a passing ray goes, so a map learned with
the iris at the lens's widest opening renders every smaller (or bladed) iris exactly if it also knows
where each ray crosses the stop plane (:mod:`mi_neurallens.trace.iris`).  The stop head
(:class:`~mi_neurallens.neural.model.StopHead`) is that prediction: an MLP on the map's normalised
inputs, on top of a least-squares linear guess (the skip connection), with the sy outputs exactly odd in
ωy (as the regressor's y).  It is trained apart from the classifier and regressor, on valid rays of the
widest-open lens (the same sampler, :class:`~mi_neurallens.training.data.RegressorStream`), so adding it
to a shipped map leaves that map's other outputs bit for bit unchanged.

Loss: mean squared error of the standardised crossing coordinates.  Validation: held-out float64 rays,
the per-ray largest crossing error (µm); the best weights by its median are kept.
"""
from __future__ import annotations

import math
import time

import numpy as np

from ..errors import NeuralLensError
from .config import NetConfig, table_name
from ..transport.sampling import PathSampler, heldout_valid
from .data import RegressorStream
from .evaluate import stop_errors
from .input_box import fold_input_box, input_box, is_box
from .levenberg import check_finishable, check_widenable, finish_results, widen_as_configured, widened_finish
from .nets import load_torch, new_state, pick_device
from .outputs import fit_output_transform
from .stacked import Problem


def stop_loss_weights(mode: str, oscale) -> np.ndarray:
    """Per-column weights (2k,) of the stop head's standardised MSE.  ``goals``: ∝ the column's spread
    ``oscale`` (mm) over its goal, which is the same µm for every column — the regressor's rule
    (:func:`~mi_neurallens.training.outputs.loss_weights`), normalised to mean 1 and floored at 0.05.  It
    moves the network's effort from the narrow columns (sy, whose spread the odd-y factor makes small) to the
    wide ones, where the µm error is: on the Canon EF's two worst three-crossing heads it gave 8.8 and 4.2 µm
    median where ``uniform`` gave 12.5 and 7.6 (and the physical MSE, ∝ ``oscale``², 12.5 and 5.1).
    ``uniform``: all 1 (each column's error relative to its own spread)."""
    oscale = np.asarray(oscale, np.float64)
    if mode == "uniform":
        return np.ones(len(oscale))
    if mode != "goals":
        raise NeuralLensError(f"unknown loss_weights {mode!r}: use 'goals' or 'uniform'")
    return np.maximum(oscale / oscale.mean(), 0.05)


def odd_columns(x_wy: np.ndarray, s_max: float, k: int) -> np.ndarray:
    """(N, 2k) multiplier M of the stop outputs: ωy/s_max on the sy columns, 1 on the sx columns."""
    M = np.ones((len(x_wy), 2 * k))
    M[:, 1::2] = np.asarray(x_wy, np.float64)[:, None] / float(s_max)
    return M


class StopFit(Problem):
    """One stop head's training problem (pool, targets, loss, validation, fresh data) for
    :func:`~mi_neurallens.training.stacked.train_stack`.

    The network's output ``p`` times ``M`` relates to the crossings ``s`` (N, 2k) by
    ``s = M·(shift + skip·xn) + oscale·(M·p)``."""

    POOL = {"X": "X", "Y": "Y"}         # normalised inputs, standardised crossings

    def __init__(self, torch, dev, net, stream, val, pool0, *, center, scale_in, s_max, k, transform,
                 state, nc: NetConfig, log=None, desc="stop head"):
        self.torch, self.dev, self.net, self.stream, self.nc = torch, dev, net, stream, nc
        self.center, self.scale_in, self.s_max, self.k = center, scale_in, float(s_max), int(k)
        self.skip, self.shift, self.oscale = transform
        self.state, self.log, self.desc = state, log, desc
        x0, s0 = pool0
        self.X, self.Y = self._pair(x0, s0)
        self.xv, self.sv = val
        self.Xv, self.Yv = self._pair(self.xv, self.sv)
        self.wy_c, self.wy_s = float(center[2]), float(scale_in[2])
        self.W = self.f32(stop_loss_weights(nc.loss_weights, self.oscale))

    def f32(self, a):
        return self.torch.as_tensor(np.ascontiguousarray(a, dtype=np.float32), device=self.dev)

    def _pair(self, x, s):
        xn = (x - self.center) / self.scale_in
        t = (s - odd_columns(x[:, 2], self.s_max, self.k) * (self.shift + xn @ self.skip.T)) / self.oscale
        return self.f32(xn), self.f32(t)

    def M_of(self, xb, const=None):
        """The odd-y factor of a batch (…, B, 4): ωy/s_max on the sy columns, 1 on the sx ones; with a stack's
        ``const``, each map's ωy from its own input normalisation (:meth:`constants`)."""
        M = self.torch.ones(xb.shape[:-1] + (2 * self.k,), device=xb.device, dtype=xb.dtype)
        c, sc = (self.wy_c, self.wy_s) if const is None else (const["WY"][..., 0], const["WY"][..., 1])
        M[..., 1::2] = ((c + sc * xb[..., 2]) / self.s_max)[..., None]
        return M

    def predict(self, xb):
        return self.net(xb) * self.M_of(xb)

    def crossings(self, x, p):
        """Crossings (N, 2k) from inputs and the network's output times M (numpy)."""
        xn = (x - self.center) / self.scale_in
        return p * self.oscale + odd_columns(x[:, 2], self.s_max, self.k) * (self.shift + xn @ self.skip.T)

    # -- the pieces :func:`~mi_neurallens.training.stacked.train_stack` runs --------------------------
    def constants(self):
        """This map's column weights, (1, 2k), and the (centre, scale) of its ωy input, (1, 2) (stacked: (K, 1, ·)):
        the maps of one stack may normalise their inputs differently (``input_box``)."""
        return {"W": self.W[None], "WY": self.f32([[self.wy_c, self.wy_s]])}

    def rows_loss(self, out, batch, const):
        """Weighted mean squared error of the standardised crossings (:func:`stop_loss_weights`), reduced over
        the samples ((B,) or (K, B)).  The maps of one stack share the domain (the ωy scale of M)."""
        return (((out * self.M_of(batch["X"], const) - batch["Y"]) ** 2) * const["W"]).mean(-1).mean(-1)

    def lm_residual(self, z, batch):
        """Levenberg–Marquardt's residuals (the weighted standardised crossing errors of :meth:`rows_loss`) and
        ∂r/∂z."""
        w = self.torch.sqrt(self.W).to(z.dtype)
        M = self.M_of(batch["X"]).to(z.dtype)
        return w * (z * M - batch["Y"].to(z.dtype)), w * M

    def fresh_rows(self, n):
        _, x, y = self.stream.sample(n)
        X, Y = self._pair(x, y[:, 5:])
        return {"X": X, "Y": Y}

    def goals_met(self) -> bool:
        """The last validation meets ``nc.goal_stop_um`` (median, p99 of the largest crossing error)."""
        h = self.state["history"]
        g = self.nc.goal_margin
        med, p99 = self.nc.goal_stop_um
        return bool(h) and h[-1]["stop_um_med"] <= g * med and h[-1]["stop_um_p99"] <= g * p99

    def validate(self, step, loss, seconds):
        with self.torch.no_grad():
            p = self.predict(self.Xv).double().cpu().numpy()
        e = stop_errors(self.crossings(self.xv, p), self.sv)
        rec = {"step": step, "loss": loss.item() if loss is not None else math.nan, "seconds": seconds,
               "stop_um_med": e["stop_um_median"], "stop_um_p99": e["stop_um_p99"]}
        self.state["history"].append(rec)
        if self.log:
            self.log(self.desc, rec)
        # the goals are on the median and the p99: score both, relative to them (2 µm, 20 µm)
        score = e["stop_um_median"] / 2.0 + e["stop_um_p99"] / 20.0
        return score, dict(med=f"{e['stop_um_median']:.2f}µm", p99=f"{e['stop_um_p99']:.1f}µm")


def train_stop_head(lens, tm, nc: NetConfig, *, seed: int, fresnel: bool = True, mcmc_threshold: float = 0.02,
                    n_val: int = 20_000, threads: int = 2, device: str = "auto", progress: bool = True,
                    log=None, stream=None):
    """Train the stop head of the learned map ``tm`` (a :class:`~mi_neurallens.neural.model.NeuralMap`
    of ``lens`` as it was trained, i.e. wide open) and return it as a
    :class:`~mi_neurallens.neural.model.StopHead` (``tm`` is not changed).  ``stream``: an existing
    :class:`~mi_neurallens.training.data.RegressorStream` of the same map built with ``stops=True``."""
    return train_stop_heads(lens, [tm], nc, seeds=[seed], fresnel=fresnel, mcmc_threshold=mcmc_threshold,
                            n_val=n_val, threads=threads, device=device, progress=progress, log=log,
                            streams=None if stream is None else [stream])[0]


def train_stop_heads(lens, tms, nc: NetConfig, *, seeds, fresnel: bool = True, mcmc_threshold: float = 0.02,
                     n_val: int = 20_000, threads: int = 2, device: str = "auto", progress: bool = True,
                     log=None, streams=None, start=None, like_streams=None):
    """The stop heads of the maps ``tms`` (all crossing the stop plane the same number of times, on one
    domain), trained as one stack (:func:`~mi_neurallens.training.stacked.train_stack`); a list of
    :class:`~mi_neurallens.neural.model.StopHead` in the order of ``tms``.  ``streams``: each map's
    :class:`~mi_neurallens.training.data.RegressorStream` with ``stops=True`` (default: built here);
    ``like_streams``: streams of the same maps without the crossings (the regressors'), whose valid fractions
    and pilot bounds the streams built here take instead of tracing them again.

    ``start``: one :class:`~mi_neurallens.neural.model.StopHead` per map to finish instead — no Adam, only the
    Levenberg–Marquardt finish (``nc.lm_minutes``, which must be > 0) from its weights and output transform, its
    hidden layers first widened to ``nc.width`` where that is wider and the layer count is ``nc.hidden``
    (:func:`~mi_neurallens.training.levenberg.widen`: the same function, with room)."""
    if start is not None:
        table = table_name("stop", tms[0].direction)
        check_finishable([(f"{tm.key} stop head", h.layers) for tm, h in zip(tms, start)], nc, "the stop heads'",
                         table, f"--keep networks --set {table}.hidden=3 --set {table}.width=32",
                         what="--finish-only stop-heads: ")
    from .stacked import train_stack
    torch = load_torch(threads)
    dev = pick_device(torch, device)
    torch.manual_seed(int(seeds[0]))
    t0 = time.perf_counter()
    fits, transforms, boxes = [], [], []
    ks = set()
    for j, tm in enumerate(tms):
        stream = streams[j] if streams is not None else None
        if stream is None:
            ps = PathSampler(lens, tm.path_id, tm.direction, tm.z_in, tm.z_out, tm.domain, fresnel=fresnel, stops=True)
            stream = RegressorStream(ps, seeds[j], mcmc_threshold, like=None if like_streams is None else like_streams[j])
        fit, k, tr, box = _stop_fit(torch, dev, lens, tm, nc, stream, seeds[j], len(tms),
                                    None if start is None else start[j], fresnel, mcmc_threshold, n_val, log)
        ks.add(k)
        fits.append(fit)
        transforms.append(tr)
        boxes.append(box)
    if len(ks) != 1:
        raise NeuralLensError(f"train_stop_heads: one stack needs one crossing count, got {sorted(ks)}")
    k = ks.pop()
    keys = [tm.key for tm in tms]
    check_widenable(nc, len(tms[0].input_center), 2 * k, table_name("stop", tms[0].direction))
    if start is None:
        res = train_stack(torch, dev, fits, nc, seeds=seeds, n_in=len(tms[0].input_center), n_out=2 * k, keys=keys,
                          progress=progress,
                          desc=f"stop heads ×{len(tms)}" if len(tms) > 1 else f"{keys[0]} stop head", log=log)
    else:
        res = [_finish_start(tm, head, f, nc, log) for tm, head, f in zip(tms, start, fits)]
    finish_results(torch, fits, res, nc, keys, log=log, progress=progress)
    widened_finish(torch, fits, res, nc, keys, log=log, progress=progress)
    return [_stop_head(r, tr, box, tm, nc, k, seed, None if start is None else start[j], t0, len(tms))
            for j, (r, tr, seed, box, tm) in enumerate(zip(res, transforms, seeds, boxes, tms))]


def _stop_fit(torch, dev, lens, tm, nc: NetConfig, stream, seed: int, n_maps: int, s0, fresnel: bool,
              mcmc_threshold: float, n_val: int, log):
    """One map's stop-head problem for :func:`train_stop_heads`: (its :class:`StopFit`, the path's stop-plane
    crossings, its output transform (skip, shift, oscale), the input normalisation (center, scale) it trains on).
    Validated on ``n_val`` held-out float64 rays traced with ``seed + 7``; its first pool from ``stream``; the
    transform fitted to that pool, or with ``s0`` (a stop head to finish) that head's."""
    from .stacked import pool_rows
    k = stream.ps.map.stop_crossings
    if k == 0 or stream.ps.n_out != 5 + 2 * k:
        raise NeuralLensError(f"map {tm.key} of '{lens.name}': its path never crosses the stop plane, or the "
                              "sampler was built without stops=True")
    center, scale_in, s_max = np.asarray(tm.input_center), np.asarray(tm.input_scale), tm.domain.s_max
    xv, yv = heldout_valid(lens, (tm.path_id, tm.direction, tm.z_in, tm.z_out), tm.domain, n_val, seed + 7,
                           mcmc_threshold, fresnel, stops=True)
    _, x0, y0 = stream.sample(pool_rows(nc, n_maps, 4 * (len(center) + 2 * k)))
    c0 = y0[:, 5:]
    if nc.input_box and s0 is None:
        center, scale_in = input_box(x0, center, scale_in)
    xn0 = (x0 - center) / scale_in
    if s0 is None:
        tr = fit_output_transform(xn0, c0, "linear", odd_columns(x0[:, 2], s_max, k))
    else:
        if s0.crossings != k:
            raise NeuralLensError(f"map {tm.key}: the stop head to finish has {s0.crossings} crossings, the path {k}")
        tr = tuple(np.asarray(v, np.float64) for v in (s0.skip, s0.out_shift, s0.out_scale))
    state = new_state()
    if s0 is not None:        # "refined": a finish-only run's mark in the state, as it has been written
        state.update(step=int(s0.training.get("steps", 0)), refined=True)
    fit = StopFit(torch, dev, None, stream, (xv, yv[:, 5:]), (x0, c0), center=center, scale_in=scale_in,
                  s_max=s_max, k=k, transform=tr, state=state, nc=nc, log=log, desc=f"{tm.key} stop head")
    return fit, k, tr, (center, scale_in)


def _finish_start(tm, head, fit, nc: NetConfig, log) -> dict:
    """What the finish of ``head`` (the map ``tm``'s stop head) starts from: its layers, widened as configured
    (:func:`~mi_neurallens.training.levenberg.widen_as_configured`; noted in ``fit.state`` and the log), and the
    fit's state."""
    layers = [(np.asarray(W, np.float64), np.asarray(b, np.float64)) for W, b in head.layers]
    layers, hidden = widen_as_configured(layers, nc.hidden, nc.width, [int(tm.path_id), int(nc.width), 7])
    if hidden is not None:
        fit.state["widened_from"] = hidden
        if log:
            log(f"{tm.key} stop head widened", {"from": "x".join(map(str, hidden)), "to": f"{nc.hidden}x{nc.width}"})
    return {"layers": layers, "state": fit.state}


def _stop_head(r: dict, transform, trained_box, tm, nc: NetConfig, k: int, seed: int, s0, t0: float, n_maps: int):
    """The :class:`~mi_neurallens.neural.model.StopHead` of one trained (or finished) result ``r``: its input box
    folded back into the map's normalisation (:func:`~mi_neurallens.training.input_box.fold_input_box`), its
    training record (configuration, steps, seconds, stop reason, samples, seed, history, the finish's, the box,
    and with ``s0`` — the head it was finished from — that head's steps, seconds and configuration)."""
    from ..neural.model import StopHead
    skip, shift, oscale = transform
    st = r["state"]
    cb, sb = trained_box
    box = None
    if is_box((cb, sb), tm.input_center, tm.input_scale):
        r["layers"], skip, shift = fold_input_box(r["layers"], skip, shift, (cb, sb),
                                                  (tm.input_center, tm.input_scale))
        box = {"center": [float(v) for v in cb], "scale": [float(v) for v in sb]}
    training = {"config": dict(nc.__dict__), "steps": st["step"], "seconds": st["seconds"],
                "stop_reason": st.get("stop_reason"), "samples": st["samples"], "seed": int(seed),
                "wall_seconds": time.perf_counter() - t0, "stacked_with": n_maps, "history": st["history"]}
    if st.get("lm"):
        training["lm"] = st["lm"]
    if st.get("widened"):           # widened after its finish and finished again (levenberg.widened_finish)
        training["widened"] = st["widened"]
    if box is not None:
        training["input_box"] = box
    if s0 is not None:          # "refined_from": the record's name in the model files written before "finish"
        training["refined_from"] = {k_: s0.training.get(k_) for k_ in ("steps", "seconds", "config")}
        if st.get("widened_from"):
            training["widened_from"] = st["widened_from"]
    return StopHead(crossings=k, layers=r["layers"], skip=skip, out_scale=oscale, out_shift=shift,
                    activation=nc.activation, odd_y=True, training=training)
