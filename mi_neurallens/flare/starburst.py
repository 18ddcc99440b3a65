"""The diffraction starburst in a flare render (``lens_flare``'s ``diffraction``): which light gets which kernel.

The physics, the film kernel and the convolution live in :mod:`mi_neurallens.flare.diffraction`; this module
applies them to a :class:`~mi_neurallens.flare.render.FlareRenderer`'s render:

* point, spot and directional lights (the backward render does not see them): their own images, traced forward
  into a block of their own (the transmit path), convolved with the kernel;
* area emitters the backward render shows (``small_emitters``): the kernel minus a delta;
* a light whose own image misses the film: :func:`offframe_starburst`, so that its spikes still reach in.
"""
from __future__ import annotations

import math
import os
import zlib

import numpy as np

from ..jit import from_numpy
from .kernels import rgb
from .options import FlareError


def film_kernel_of(fr):
    """The :class:`~mi_neurallens.flare.diffraction.FilmKernel` of renderer ``fr``'s lens as configured (iris,
    blades, focus, its ``aperture_mask``) on its film, per channel with the sensor's colour matching
    (:func:`~mi_neurallens.sensors.wavelengths.rgb_weight` at ``KERNEL_WAVELENGTHS_NM``); kept on ``fr`` while
    those stay."""
    import mitsuba as mi
    from ..sensors.wavelengths import rgb_weight
    from .diffraction import (KERNEL_WAVELENGTHS_NM, FilmKernel, channel_wavelengths, film_kernel,
                              working_fnumber_and_pupil)
    N_w, pupil = working_fnumber_and_pupil(fr.lens)
    pix = (fr.setup.sensor_width_mm / fr.size[0], fr.setup.sensor_height_mm / fr.size[1])
    key = (N_w, pupil, pix, fr.crop_size, fr.opts.aperture_mask)
    cached = getattr(fr, "_film_kernel", None)
    if cached is None or cached[0] != key:
        lam = np.asarray(KERNEL_WAVELENGTHS_NM, np.float64)
        w = rgb_weight(mi, mi.Float(lam.astype(np.float32)))
        weights = np.stack([np.asarray(w[c], np.float64) for c in range(3)], 1)
        mask = load_aperture_mask(fr.opts.aperture_mask) if fr.opts.aperture_mask else None
        kernel = film_kernel(pupil, N_w, pix, fr.crop_size, lam, weights, mask=mask)
        fr._film_kernel = cached = (key, FilmKernel(kernel, pupil, N_w, pix, channel_wavelengths(lam, weights)))
    return cached[1]


def starburst_image(fr, direct: dict, offframe: list, seed: int = 0):
    """What diffraction adds to renderer ``fr``'s flare image (H, W, 3), or None when no light contributes:
    ``direct`` = {"unseen": image block of the point, spot and directional lights' own images, "seen": of the area
    emitters'}, convolved with the kernel (the seen ones with the kernel minus a delta: their image is in the
    backward render already, and with include_transmit in the flare too); and the spikes of the lights in
    ``offframe`` (their images missed the film)."""
    out = None
    if direct:
        K = film_kernel_of(fr)
        out = 0.0
        for kind, blk in direct.items():
            img = np.asarray(blk.tensor().numpy(), np.float64)
            out = out + K.convolve(img)
            if kind == "seen" and not fr.opts.include_transmit:
                out = out - img
    for light in offframe:
        spikes = offframe_starburst(fr, light, seed)
        if spikes is not None:
            out = spikes if out is None else out + spikes
    return None if out is None else np.asarray(out, np.float32)


def offframe_starburst(fr, light, seed: int = 0, n: int = 1 << 18):
    """The starburst (H, W, 3) of a point, spot or directional ``light`` whose own image falls beside renderer
    ``fr``'s film: that image traced (``n`` random samples of the transmit path over the light's input disk, kept
    wherever they land on the sensor plane) and taken as a point at its centroid with its energy, spread by the
    fringe-averaged pattern (:func:`~mi_neurallens.flare.diffraction.offset_kernel`).  None when no light passes."""
    import mitsuba as mi
    import drjit as dr
    from .diffraction import offset_kernel
    R = fr._region_radius(light)
    rng = np.random.default_rng([seed, zlib.crc32(light.name.encode()) & 0xFFFF])
    u = rng.random((5, n))
    r, t = R * np.sqrt(u[0]), 2.0 * math.pi * u[1]
    F = lambda a: from_numpy(mi.Float, a)                      # noqa: E731
    xf = fr.xf()
    scene = fr.scene if fr.opts.visibility else None
    fr.kernels.crop_test = False                               # keep the samples that miss the film
    try:
        hit, px, py, val, lam, _ = fr.kernels.contrib(fr.exact_evaluator(0), light.emitter, scene, xf,
                                                      F(r * np.cos(t)), F(r * np.sin(t)), F(u[2]),
                                                      mi.Point2f(F(u[3]), F(u[4])))
        rgb_, lum = rgb(hit, val, lam)
        dr.eval(rgb_, lum, px, py)
    finally:
        fr.kernels.crop_test = True
    w = lum.numpy().astype(np.float64)
    if not w.sum() > 0:
        return None
    energy = np.array([c.numpy().astype(np.float64).sum() for c in rgb_]) * (math.pi * R * R / n)
    cx = float((px.numpy() * w).sum() / w.sum()) - fr.crop_offset[0] - 0.5
    cy = float((py.numpy() * w).sum() / w.sum()) - fr.crop_offset[1] - 0.5
    return np.asarray(offset_kernel(film_kernel_of(fr), (cx, cy)) * energy[None, None, :], np.float32)


def load_aperture_mask(path):
    """The transmission image ``path`` (any format Mitsuba reads: PNG, JPEG, EXR, ...) as linear grey values, a 2-D
    numpy array, its first row the top (+y)."""
    import mitsuba as mi
    if not os.path.isfile(path):
        raise FlareError(f"lens_flare: 'aperture_mask': no such image: {path}")
    try:
        bmp = mi.Bitmap(path).convert(mi.Bitmap.PixelFormat.Y, mi.Struct.Type.Float32, srgb_gamma=False)
    except Exception as e:                                   # Mitsuba's reader raises RuntimeError on a bad file
        raise FlareError(f"lens_flare: 'aperture_mask': cannot read {path}: {e}") from None
    return np.array(bmp, np.float64).reshape(bmp.height(), bmp.width())
