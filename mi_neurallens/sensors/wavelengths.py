"""One wavelength per camera ray: sampling and the spectral/RGB weight (shared by the lens sensors).

A lens bends each wavelength differently, so a traced ray is valid for ONE wavelength only.  Each ray
therefore carries a single λ, importance-sampled with Mitsuba's ``sample_rgb_spectrum`` (a smooth
fit to the sum of the CIE 1931 colour-matching functions on [360, 830] nm):

* spectral variants: ``ray.wavelengths`` = λ on every lane, weight = 1/pdf(λ) (Mitsuba's film then
  applies the colour-matching functions);
* RGB variants: weight = ``xyz_to_srgb(cie1931_xyz(λ)) · D65(λ) · MI_CIE_Y_NORMALIZATION / pdf(λ)``,
  whose expectation over λ is (1, 1, 1): an achromatic lens renders white as white, a dispersive lens
  gets its colour fringes.

**Stratified λ.**  The 1-D sample must come from the sampler so that ``ldsampler``/``multijitter``
stratify it (a hashed number is as noisy as ``independent``).  Spectral integrators pass it as
``sample1``.  RGB integrators pass ``sample1 = 0``; there the sensor asks for a 1-D *time* sample
instead: when the user gave no shutter interval, the sensor sets ``shutter_close = shutter_open + 1``
before Mitsuba reads it, uses ``(time − shutter_open)/shutter_open_time`` as the λ sample and gives the
ray ``time = shutter_open`` (no motion blur is lost: there was none).  With a real shutter interval
(motion blur) in an RGB variant, time is kept and λ falls back to a TEA hash of the film and pupil
samples (unbiased, but colour noise as with ``independent``).

**λ-independent lenses** (all media constant index, no coatings): λ does not matter, so RGB variants
use weight 1 (no colour noise at all) and spectral variants use Mitsuba's standard 4 hero wavelengths.
"""
from __future__ import annotations

#: wavelength used for tracing when the lens does not depend on λ (nm)
NEUTRAL_WAVELENGTH_NM = 550.0

LAMBDA_FROM_TIME, LAMBDA_HASH, LAMBDA_SAMPLE1, LAMBDA_NONE = "time", "hash", "sample1", "none"


def prepare_shutter(mi, props, lambda_dependent: bool) -> str:
    """Decide where the λ sample comes from; in RGB variants possibly enable a unit shutter so the
    integrator draws a stratified 1-D sample.  Call BEFORE ``mi.Sensor.__init__(props)``."""
    if not lambda_dependent:
        return LAMBDA_NONE
    if mi.is_spectral:
        return LAMBDA_SAMPLE1
    so = props.get("shutter_open", 0.0) if "shutter_open" in props else 0.0
    sc = props.get("shutter_close", so) if "shutter_close" in props else so
    if float(sc) == float(so):
        props["shutter_close"] = float(so) + 1.0
        return LAMBDA_FROM_TIME
    return LAMBDA_HASH


def sample_wavelength(mi, dr, sensor, mode: str, time, sample1, sample2, sample3, active=True, deferred=False):
    """Returns ``(lam_nm, wavelengths_for_ray, weight, ray_time)``.

    ``lam_nm``: mi.Float (or a Python float for λ-independent lenses) used to trace the lens;
    ``wavelengths_for_ray``: the ray's ``wavelengths`` (spectral) or None; ``weight``: mi.Spectrum
    (or a Python float 1.0) to multiply the lens weight with; ``ray_time``.  ``deferred`` (RGB variants, a
    sampled λ): ``weight`` is the sampling's 1/pdf alone, the caller multiplies by :func:`rgb_weight` of λ.
    """
    if mode == LAMBDA_NONE:
        if mi.is_spectral:
            wav, w = sensor.sample_wavelengths(dr.zeros(mi.SurfaceInteraction3f), sample1, active)
            return NEUTRAL_WAVELENGTH_NM, wav, w, time
        return NEUTRAL_WAVELENGTH_NM, None, 1.0, time
    if mode == LAMBDA_SAMPLE1:
        u = sample1
    elif mode == LAMBDA_FROM_TIME:
        so, st = sensor.shutter_open(), sensor.shutter_open_time()
        u = dr.clip((time - so) * (1.0 / st), 0.0, 0.99999994)
        time = dr.zeros(mi.Float, dr.width(u)) + so
    else:  # LAMBDA_HASH
        b = lambda v: dr.reinterpret_array(mi.UInt32, v)
        u = mi.sample_tea_float32(b(sample2.x) ^ b(sample3.y), b(sample2.y) ^ (b(sample3.x) * 0x9E3779B9))
    lam, inv_pdf = mi.sample_rgb_spectrum(u)
    if mi.is_spectral:
        return lam, mi.Spectrum(lam), mi.Spectrum(inv_pdf), time
    if deferred:
        return lam, None, inv_pdf, time
    return lam, None, mi.Spectrum(rgb_weight(mi, lam) * inv_pdf), time


def rgb_weight(mi, lam):
    """The sRGB weight of the wavelength ``lam`` (nm) in RGB variants without its sampling pdf: the factor
    :func:`sample_wavelength` with ``deferred = True`` leaves to the caller (it reads Mitsuba's CIE tables,
    which a frozen kernel, ``dr.freeze``, cannot take as inputs)."""
    return mi.xyz_to_srgb(mi.cie1931_xyz(lam)) * (mi.cie_d65(lam) * mi.MI_CIE_Y_NORMALIZATION)
