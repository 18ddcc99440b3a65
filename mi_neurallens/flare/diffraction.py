"""The aperture's diffraction starburst: the far-field (Fraunhofer) pattern of the exit pupil, as a film kernel.

Physics
-------
A point light focused through a lens does not image to a point: the exit pupil's far-field diffraction pattern
spreads it, ``K_λ(x) = |P̂(x / (2 λ N_w))|² / (A (2 λ N_w)²)`` on the sensor plane (x in mm from the light's image),
where ``P̂`` is the Fourier transform of the pupil's shape with its inscribed radius scaled to 1 (frequencies in
cycles per that radius), ``A`` its area and ``N_w`` the working f-number on the image side.  By Parseval the kernel
integrates to 1: it redistributes light and adds none.  For a circle, ``P̂(f) = J1(2π|f|) / |f|``: the Airy
pattern, first dark ring at ``1.22 λ N_w``.  For the regular n-gon of an iris with n blades, the sum over its
edges (divergence theorem) ``P̂(q/2π) = (i/|q|²) Σ_e (q·n_e) L e^{−i q·m_e} sinc(q·t_e L/2)`` (edge normal n_e,
tangent t_e, midpoint m_e, length L = 2 tan(π/n)): each edge throws a streak along its normal whose intensity
falls as 1/|x|², so an even n gives n spikes (opposite edges share a streak) and an odd n gives 2n.

The pupil (a documented paraxial choice): the iris at the configured f-number and blade rotation as the exit pupil
presents it, i.e. scaled by the pupil magnification (:class:`~mi_neurallens.optics.paraxial.ParaxialSystem` at
587.56 nm: exit-pupil radius and position), its orientation kept (a negative magnification turns it by 180°,
which ``|P̂|²`` does not see).  ``N_w = (z_sensor − z_exit pupil) / (2 r_exit pupil)``: N at infinity focus,
``N (1 + |m| / m_p)`` when focused near.

On the film (pixels)
--------------------
The kernel is integrated over each pixel, on a canvas of twice the film's size (every offset between two film
pixels), per RGB channel: the wavelengths weighted by the sensor's own colour matching
(:func:`~mi_neurallens.sensors.wavelengths.rgb_weight`), i.e. spectrally for a light of flat spectrum within each
channel.  Near the centre (the square ``|fx|, |fy| ≤ NEAR_F``) the exact coherent pattern is sampled on a grid
fine enough for its fringes and for the pixels (``SUB_F`` in f units, at most half a pixel) at each of the
wavelengths, each sample binned into its pixel; beyond it, where the fringes are many and fine (the share of each
pixel outside the square), the fringe-averaged pattern is integrated over the pixel in closed form: for the polygon the incoherent
sum of the edges' streaks (their cross terms oscillate and average out), each streak's sinc² profile integrated
exactly across the pixel with the sine integral; for the circle the Airy envelope ``1 / (2π² |f|³)``.  That part
is evaluated once and scaled to each channel's mean wavelength (it is linear in λ where the streaks are narrower
than a pixel).  The canvas is not renormalised: the kernel integrates to 1 over the plane, and what falls beyond
the canvas falls beyond the film.
"""
from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
import math
import os

import numpy as np

from ..constants import LAMBDA_D
from ..errors import NeuralLensError

#: the exact (coherent) pattern within the square |fx|, |fy| ≤ NEAR_F, f units (cycles per inscribed radius; 8 ≈ 16
#: Airy rings); beyond it the fringe-averaged pattern
NEAR_F = 8.0
#: sample spacing of the exact pattern, f units (its fringes are ≈ 0.5 apart), at most half a pixel
SUB_F = 0.125
#: an aperture mask: the pupil sampled on MASK_SAMPLES² points, its pattern by FFT within |fx|, |fy| ≤ MASK_F (dust
#: specks a fiftieth of the pupil wide scatter to ≈ 25)
MASK_SAMPLES = 256
MASK_F = 32.0
#: the wavelengths (nm) a flare's kernel samples the exact pattern at, weighted by the sensor's colour matching
KERNEL_WAVELENGTHS_NM = tuple(390.0 + 20.0 * k for k in range(17))      # 390 … 710


@dataclass(frozen=True)
class Pupil:
    """The exit pupil's shape: ``blades`` (0: a circle, else a regular polygon) with inscribed radius 1, its first
    blade's normal at ``rotation_deg`` from +x (the :class:`~mi_neurallens.trace.iris.Iris` convention)."""

    blades: int = 0
    rotation_deg: float = 0.0

    @property
    def area(self) -> float:
        n = self.blades
        return math.pi if n == 0 else n * math.tan(math.pi / n)

    def edges(self):
        """(normal angle (rad), length) of each edge; empty for the circle."""
        n = self.blades
        if n == 0:
            return []
        a0 = math.radians(self.rotation_deg)
        return [(a0 + 2.0 * math.pi * k / n, 2.0 * math.tan(math.pi / n)) for k in range(n)]


def working_fnumber_and_pupil(lens, wavelength_nm: float = LAMBDA_D):
    """``(N_w, Pupil)`` of ``lens`` as configured (its stop radius and blades, its sensor distance), paraxially at
    ``wavelength_nm``: see the module docstring."""
    from ..trace.iris import Iris
    p = lens.paraxial(wavelength_nm)
    z_sensor = float(lens.image_z)
    r_xp, z_xp = float(p.exit_pupil_radius), float(p.exit_pupil_z)
    if not (math.isfinite(r_xp) and math.isfinite(z_xp)) or r_xp <= 0:
        raise NeuralLensError(f"lens '{lens.name}' has no finite exit pupil (image-side telecentric?): its diffraction "
                              f"starburst is not defined here; render the flare with diffraction off")
    iris = Iris.of_lens(lens)
    return abs(z_sensor - z_xp) / (2.0 * r_xp), Pupil(iris.blades, iris.rotation_deg)


# ------------------------------------------------------------------------------------------ special functions
def bessel_j1(x):
    """J1(x) for float64 arrays: the rational and asymptotic forms of Numerical Recipes (bessj1), |error| < 1e-8."""
    x = np.asarray(x, np.float64)
    ax = np.abs(x)
    y = x * x
    small = x * (72362614232.0 + y * (-7895059235.0 + y * (242396853.1 + y * (-2972611.439 + y * (
        15704.48260 + y * (-30.16036606)))))) / (144725228442.0 + y * (2300535178.0 + y * (18583304.74 + y * (
            99447.43394 + y * (376.9991397 + y)))))
    axs = np.maximum(ax, 8.0)
    z = 8.0 / axs
    zz = z * z
    xx = axs - 2.356194491
    p1 = 1.0 + zz * (0.183105e-2 + zz * (-0.3516396496e-4 + zz * (0.2457520174e-5 + zz * (-0.240337019e-6))))
    p2 = 0.04687499995 + zz * (-0.2002690873e-3 + zz * (0.8449199096e-5 + zz * (-0.88228987e-6 + zz * 0.105787412e-6)))
    large = np.sqrt(0.636619772 / axs) * (np.cos(xx) * p1 - z * np.sin(xx) * p2) * np.sign(x)
    return np.where(ax < 8.0, small, large)


def sine_integral(x):
    """Si(x) = ∫₀ˣ sin t / t dt for float64 arrays: its power series for |x| ≤ 20 (41 terms), beyond it
    π/2 − f cos x − g sin x with the auxiliary functions' asymptotic series (|error| < 1e-9 against scipy's)."""
    x = np.asarray(x, np.float64)
    ax = np.abs(x)
    xs = np.minimum(ax, 20.0)
    term, total = xs.copy(), xs.copy()
    x2 = xs * xs
    for k in range(1, 41):                                      # Σ (−1)^k x^(2k+1) / ((2k+1)(2k+1)!)
        term = -term * x2 / ((2 * k) * (2 * k + 1))
        total = total + term / (2 * k + 1)
    xl = np.maximum(ax, 20.0)
    inv2 = 1.0 / (xl * xl)
    f, g, tf, tg = np.ones_like(xl), np.ones_like(xl), np.ones_like(xl), np.ones_like(xl)
    for k in range(1, 10):                                      # f ~ (1/x) Σ (−1)^k (2k)!/x^2k, g ~ (1/x²) Σ (−1)^k (2k+1)!/x^2k
        tf = -tf * (2 * k - 1) * (2 * k) * inv2
        tg = -tg * (2 * k) * (2 * k + 1) * inv2
        f, g = f + tf, g + tg
    large = 0.5 * math.pi - (f / xl) * np.cos(xl) - (g * inv2) * np.sin(xl)
    return np.sign(x) * np.where(ax <= 20.0, total, large)


# ------------------------------------------------------------------------------------------ the pattern
def power_spectrum(fx, fy, pupil: Pupil):
    """``|P̂(f)|²`` of ``pupil`` (inscribed radius 1) at frequencies (``fx``, ``fy``) in cycles per unit: the exact,
    coherent pattern (float64 numpy).  Its integral over the plane is the pupil's area."""
    fx, fy = np.asarray(fx, np.float64), np.asarray(fy, np.float64)
    rho = np.hypot(fx, fy)
    if pupil.blades == 0:
        r = np.maximum(rho, 1e-12)
        amp = np.where(rho < 1e-6, math.pi, bessel_j1(2.0 * math.pi * r) / r)
        return amp * amp
    qx, qy = 2.0 * math.pi * fx, 2.0 * math.pi * fy
    re = np.zeros_like(qx)
    im = np.zeros_like(qx)
    for phi, L in pupil.edges():
        nx, ny = math.cos(phi), math.sin(phi)               # the edge's outward normal; its midpoint is (nx, ny)
        qn = qx * nx + qy * ny
        qt = -qx * ny + qy * nx
        a = 0.5 * L * qt
        sinc = np.where(np.abs(a) < 1e-8, 1.0, np.sin(a) / np.where(np.abs(a) < 1e-8, 1.0, a))
        c = qn * L * sinc
        re += c * np.cos(qn)                                 # e^{−i q·m} with m = n: q·m = qn
        im -= c * np.sin(qn)
    q2 = qx * qx + qy * qy
    small = q2 < 1e-10
    q2s = np.where(small, 1.0, q2)
    val = (re * re + im * im) / (q2s * q2s)
    return np.where(small, pupil.area ** 2, val)


def _streak_integral(v1, v2, L):
    """∫_{v1}^{v2} sinc²(π L v) dv (sinc(x) = sin x / x), exactly, with the sine integral; for an interval on one
    side of the streak and many fringes away from it, the fringe average 1 / (2 (π L v)²) integrated."""
    a = math.pi * L

    def antider(v):
        av = a * v
        safe = np.where(np.abs(av) < 1e-9, 1.0, av)
        return (sine_integral(2.0 * av) - np.where(np.abs(av) < 1e-9, 0.0, np.sin(av) ** 2 / safe)) / a

    lo, hi = np.minimum(v1, v2), np.maximum(v1, v2)
    far = (lo * hi > 0) & (np.minimum(np.abs(lo), np.abs(hi)) * a > 6.0)
    out = np.zeros_like(lo)
    if far.any():
        l, h = lo[far], hi[far]
        out[far] = (1.0 / l - 1.0 / h) / (2.0 * a * a)
    near = ~far
    if near.any():
        out[near] = antider(hi[near]) - antider(lo[near])
    return out


def far_density(fx, fy, pupil: Pupil):
    """The fringe-averaged ``|P̂(f)|²`` at points: the Airy envelope ``1 / (2π² |f|³)`` for the circle, the incoherent
    sum of the edges' terms ``(q·n_e)² L² sinc²(q·t_e L / 2) / |q|⁴`` for the polygon (their cross terms dropped)."""
    fx, fy = np.asarray(fx, np.float64), np.asarray(fy, np.float64)
    rho2 = np.maximum(fx * fx + fy * fy, 1e-12)
    if pupil.blades == 0:
        return 1.0 / (2.0 * math.pi ** 2 * rho2 ** 1.5)
    out = np.zeros_like(fx)
    for phi, L in pupil.edges():
        nx, ny = math.cos(phi), math.sin(phi)
        a = math.pi * L * (-fx * ny + fy * nx)
        sinc2 = np.where(np.abs(a) < 1e-8, 1.0, np.sin(a) ** 2 / np.maximum(a * a, 1e-300))
        out += L * L * (fx * nx + fy * ny) ** 2 / (4.0 * math.pi ** 2 * rho2 * rho2) * sinc2
    return out


def far_pixel_integral(fx, fy, sx, sy, pupil: Pupil):
    """``∫ |P̂|² df`` over the pixels centred at (``fx``, ``fy``) of size ``sx`` × ``sy`` (f units), fringe-averaged
    (see the module docstring): valid where a pixel spans many fringes and ``|f|`` is large."""
    fx, fy = np.asarray(fx, np.float64), np.asarray(fy, np.float64)
    rho2 = np.maximum(fx * fx + fy * fy, 1e-12)
    if pupil.blades == 0:
        return sx * sy / (2.0 * math.pi ** 2 * rho2 ** 1.5)
    out = np.zeros_like(fx)
    seen = {}
    for phi, L in pupil.edges():
        # opposite edges of an even polygon throw the same streak: evaluate it once, count it twice
        key = round(math.remainder(phi, math.pi), 9)
        if key in seen:
            out += seen[key]
            continue
        nx, ny = math.cos(phi), math.sin(phi)
        v = -fx * ny + fy * nx                                 # across the streak
        cos2 = (fx * nx + fy * ny) ** 2 / rho2
        w = sx * abs(ny) + sy * abs(nx)                        # the pixel's width across the streak
        term = (L * L * cos2 / (4.0 * math.pi ** 2 * rho2)) * (sx * sy / w) * _streak_integral(v - 0.5 * w,
                                                                                               v + 0.5 * w, L)
        seen[key] = term
        out += term
    return out


# ------------------------------------------------------------------------------------------ the film kernel
def film_kernel(pupil: Pupil, fnumber: float, pixel_mm: tuple, size: tuple, wavelengths_nm, weights, mask=None):
    """The starburst kernel on a film of ``size`` = (W, H) pixels of ``pixel_mm`` = (width, height) mm: an array
    (2H, 2W, C) whose entry [H + j, W + i] is the share of a light's energy that lands i pixels right of and j
    pixels below the pixel its image falls on, per channel (each channel sums to 1 less what falls beyond the
    canvas).  ``wavelengths_nm`` (k,) and ``weights`` (k, C): the wavelengths the exact part is sampled at and each
    channel's weight of each (the sensor's colour matching, or ones for one wavelength).  ``fnumber``: the working
    f-number N_w.

    Per pixel: the exact pattern integrated over its part inside the square |fx|, |fy| ≤ ``NEAR_F`` (a grid of
    spacing at most ``SUB_F`` and half a pixel, each sample binned into its pixel), plus the fringe-averaged
    pattern's closed-form pixel integral times the share of the pixel outside that square.

    ``mask``: an optional transmission image (2-D array, 0-1) over the pupil's circumscribed square (first row at
    +y): the pupil times it, its pattern by FFT (:func:`masked_spectrum`) within |fx|, |fy| ≤ ``MASK_F`` instead of
    the closed form within ``NEAR_F``; beyond, the iris's fringe-averaged pattern times the mask's share of the
    pupil's light.  What the mask blocks is taken from the starburst (it sums to that share)."""
    W, H = (int(v) for v in size)
    px, py = (float(v) for v in pixel_mm)
    lams = np.asarray(wavelengths_nm, np.float64).ravel()
    wts = np.asarray(weights, np.float64).reshape(len(lams), -1)
    C = wts.shape[1]
    norm = wts.sum(0)
    norm = np.where(np.abs(norm) > 0, norm, 1.0)
    lam_c = (wts * lams[:, None]).sum(0) / norm                  # each channel's mean wavelength
    j, i = np.meshgrid(np.arange(-H, H, dtype=np.float64), np.arange(-W, W, dtype=np.float64), indexing="ij")
    out = np.zeros((2 * H, 2 * W, C))
    near, table, far_scale = NEAR_F, None, 1.0
    if mask is not None:
        s_min = 2.0 * lams.min() * 1e-6 * fnumber
        table = masked_spectrum(pupil, mask, max_spacing=min(SUB_F, 0.5 * px / s_min, 0.5 * py / s_min))
        near, far_scale = MASK_F, table[2] / pupil.area
    # outside the square: the fringe-averaged pattern at the channels' mean wavelength, scaled to each channel's
    # (it is linear in λ where the streaks are narrower than a pixel, and the Airy envelope is everywhere)
    lam0 = float(np.mean(lam_c))
    s0 = 2.0 * lam0 * 1e-6 * fnumber                            # mm per f unit
    sx, sy = px / s0, py / s0
    inside = _inside_share(i, sx, near) * _inside_share(j, sy, near)
    far = np.where(inside > 0.0, 0.0, far_pixel_integral(i * sx, j * sy, sx, sy, pupil))
    # the pixels the square cuts: their part outside it sampled (at most SUB_F * 2 apart) with the point density
    cut = (inside > 0.0) & (inside < 1.0)
    if cut.any():
        far[cut] = _outside_square(i[cut], j[cut], sx, sy, pupil, near)
    out += far[..., None] * (far_scale * lam_c / lam0)[None, None, :]
    # inside: the exact pattern, at every wavelength
    for k, lam in enumerate(lams):
        s = 2.0 * lam * 1e-6 * fnumber
        sx, sy = px / s, py / s
        if table is None:
            d = min(SUB_F, 0.5 * sx, 0.5 * sy)
            n = int(math.ceil(2.0 * NEAR_F / d))
            g = (np.arange(n) + 0.5) * (2.0 * NEAR_F / n) - NEAR_F
            fx, fy = np.meshgrid(g, g)
            val = power_spectrum(fx, fy, pupil) * (2.0 * NEAR_F / n) ** 2
        else:
            fx, fy, _, val = table[0], table[1], table[2], table[3]
        ii = np.floor(fx / sx + 0.5).astype(np.int64) + W
        jj = np.floor(fy / sy + 0.5).astype(np.int64) + H
        ok = (ii >= 0) & (ii < 2 * W) & (jj >= 0) & (jj < 2 * H)
        binned = np.bincount((jj[ok] * (2 * W) + ii[ok]).ravel(), weights=val[ok].ravel(),
                             minlength=4 * H * W).reshape(2 * H, 2 * W)
        out += binned[..., None] * (wts[k] / norm)[None, None, :]
    # the pattern integrates to the pupil's area (Parseval): the kernel to 1 over the plane.  Not renormalised on
    # the canvas: what falls beyond it falls beyond the film
    return out / pupil.area


def _outside_square(i, j, sx, sy, pupil, near=NEAR_F):
    """∫ of the fringe-averaged density over the part of each pixel (``i``, ``j``) outside the exact square, by a
    midpoint grid of spacing ≤ 2 SUB_F (the streaks' sinc² profile across, ≈ 1 f unit wide, resolved)."""
    mx = max(1, int(math.ceil(sx / (2.0 * SUB_F))))
    my = max(1, int(math.ceil(sy / (2.0 * SUB_F))))
    ox = ((np.arange(mx) + 0.5) / mx - 0.5) * sx
    oy = ((np.arange(my) + 0.5) / my - 0.5) * sy
    out = np.zeros(len(i))
    for k in range(len(i)):
        fx, fy = np.meshgrid(i[k] * sx + ox, j[k] * sy + oy)
        keep = (np.abs(fx) > near) | (np.abs(fy) > near)
        out[k] = far_density(fx[keep], fy[keep], pupil).sum() * (sx * sy / (mx * my))
    return out


def _inside_share(i, s, near=NEAR_F):
    """The share of pixel ``i`` (width ``s`` f units, centred at ``i s``) inside [−near, near]."""
    lo, hi = (i - 0.5) * s, (i + 0.5) * s
    return np.clip(np.minimum(hi, near) - np.maximum(lo, -near), 0.0, None) / s


def pupil_function(pupil: Pupil, n: int = MASK_SAMPLES, supersample: int = 4):
    """The pupil's transmission (1 inside, 0 outside, edges area-averaged over ``supersample``² points) on an
    ``n`` × ``n`` grid over its circumscribed square (half-width ``circumradius``; first row at +y), and that
    half-width."""
    rc = 1.0 if pupil.blades == 0 else 1.0 / math.cos(math.pi / pupil.blades)
    m = n * supersample
    c = ((np.arange(m) + 0.5) / m * 2.0 - 1.0) * rc
    ux, uy = np.meshgrid(c, c[::-1])
    if pupil.blades == 0:
        inside = ux * ux + uy * uy <= 1.0
    else:
        inside = np.ones_like(ux, bool)
        for phi, _ in pupil.edges():
            inside &= ux * math.cos(phi) + uy * math.sin(phi) <= 1.0
    return inside.reshape(n, supersample, n, supersample).mean(axis=(1, 3)), rc


def resample_mask(image, n: int):
    """A transmission image (2-D, any size, first row at +y) resampled bilinearly to ``n`` × ``n`` (values 0-1)."""
    img = np.clip(np.asarray(image, np.float64), 0.0, 1.0)
    h, w = img.shape
    y = np.clip((np.arange(n) + 0.5) / n * h - 0.5, 0.0, h - 1.0)
    x = np.clip((np.arange(n) + 0.5) / n * w - 0.5, 0.0, w - 1.0)
    y0, x0 = np.floor(y).astype(int), np.floor(x).astype(int)
    y1, x1 = np.minimum(y0 + 1, h - 1), np.minimum(x0 + 1, w - 1)
    ty, tx = (y - y0)[:, None], (x - x0)[None, :]
    top = img[y0][:, x0] * (1 - tx) + img[y0][:, x1] * tx
    bot = img[y1][:, x0] * (1 - tx) + img[y1][:, x1] * tx
    return top * (1 - ty) + bot * ty


def masked_spectrum(pupil: Pupil, mask, max_spacing: float = SUB_F, n: int = MASK_SAMPLES):
    """``|P̂|²`` of the pupil times the transmission image ``mask`` (over its circumscribed square), by FFT: the
    frequencies within |fx|, |fy| ≤ MASK_F at a spacing of at most ``max_spacing`` (f units) and each sample's
    share of the integral: ``(fx, fy, ∫|P M|², value × cell area)``."""
    P, rc = pupil_function(pupil, n)
    field = P * resample_mask(mask, n)
    du = 2.0 * rc / n
    L = 1 << int(math.ceil(math.log2(max(1.0 / (du * max_spacing), 2.0 * n))))
    spec = np.abs(np.fft.fftshift(np.fft.fft2(field, s=(L, L)))) ** 2 * du ** 4     # |P̂|² at f = k / (L du)
    df = 1.0 / (L * du)
    f = (np.arange(L) - L // 2) * df
    keep = np.abs(f) <= MASK_F
    fx, fy = np.meshgrid(f[keep], -f[keep])          # row 0 of the field is +y: its transform's rows run the same way
    val = spec[np.ix_(keep, keep)] * df * df
    return fx, fy, float((field ** 2).sum() * du * du), val


#: convolve by summing shifted kernels while the image has at most this many lit pixels (point lights in focus
#: light a few each; a shifted kernel costs ≈ 1/40 of the FFT at 960×640), else by FFT
SPARSE_MAX = 32


class FilmKernel:
    """A :func:`film_kernel` ``array`` (2H, 2W, C) and what it was made of (``pupil``, ``fnumber``, ``pixel_mm``,
    the channels' mean wavelengths ``lam_c`` in nm), its FFT kept once computed."""

    def __init__(self, array, pupil: Pupil | None = None, fnumber: float = 0.0, pixel_mm=(0.0, 0.0), lam_c=()):
        self.array = np.asarray(array, np.float64)
        self.pupil, self.fnumber, self.pixel_mm = pupil, float(fnumber), tuple(pixel_mm)
        self.lam_c = np.asarray(lam_c, np.float64)
        self._fft = None
        self._f32 = None

    def convolve(self, image):
        """``image`` (H, W, C) convolved with the kernel (light beyond the film dropped): (H, W, C).  Sums a shifted
        kernel per lit pixel when few are lit (exact, and cheap for lights in focus), else by FFT."""
        image = np.asarray(image, np.float64)
        H, W = image.shape[:2]
        lit = np.argwhere(np.any(image != 0.0, axis=2))
        if len(lit) <= SPARSE_MAX:
            if self._f32 is None:                      # channels first: a scalar times a plane is 5x faster
                self._f32 = np.ascontiguousarray(self.array.transpose(2, 0, 1), np.float32)
            out = np.zeros((image.shape[2], H, W), np.float32)
            for y, x in lit:
                for c in range(image.shape[2]):
                    if image[y, x, c] != 0.0:
                        out[c] += np.float32(image[y, x, c]) * self._f32[c, H - y:2 * H - y, W - x:2 * W - x]
            return out.transpose(1, 2, 0).astype(np.float64)
        # by FFT in float32, channels first (contiguous transforms), separably: the rows' transforms only of the
        # rows that hold light, the inverse rows' only of the film's H rows (the rest is padding)
        if self._fft is None:
            k = np.fft.ifftshift(self.array, axes=(0, 1)).transpose(2, 0, 1)      # offset 0 at [0, 0]
            self._fft = np.fft.rfft2(np.ascontiguousarray(k, np.float32))
        rows = np.unique(lit[:, 0])

        def channel(c):
            spec = np.zeros((2 * H, W + 1), np.complex64)
            spec[rows] = np.fft.rfft(np.ascontiguousarray(image[rows, :, c], np.float32), n=2 * W)
            spec = np.fft.fft(spec, axis=0) * self._fft[c]
            return np.fft.irfft(np.fft.ifft(spec, axis=0)[:H], n=2 * W)[:, :W]

        # the channels on threads: numpy's FFT releases the GIL, and a machine has cores to spare here
        with ThreadPoolExecutor(max(1, min(image.shape[2], os.cpu_count() or 1))) as pool:
            out = list(pool.map(channel, range(image.shape[2])))
        return np.stack(out, axis=2).astype(np.float64)


def channel_wavelengths(wavelengths_nm, weights):
    """Each channel's mean wavelength (nm) under ``weights`` (k, C), as :func:`film_kernel` uses them."""
    lams = np.asarray(wavelengths_nm, np.float64).ravel()
    wts = np.asarray(weights, np.float64).reshape(len(lams), -1)
    norm = wts.sum(0)
    return (wts * lams[:, None]).sum(0) / np.where(np.abs(norm) > 0, norm, 1.0)


def offset_kernel(fk: FilmKernel, centre):
    """The fringe-averaged pattern of ``fk``'s pupil integrated over each pixel of the film (H, W, C), centred at
    ``centre`` = (x, y) in pixels from the first pixel's centre (anywhere, the film's outside too): for a light
    whose own image misses the film, so that only its far field, the spikes, reaches it."""
    H, W = fk.array.shape[0] // 2, fk.array.shape[1] // 2
    j, i = np.meshgrid(np.arange(H, dtype=np.float64) - centre[1], np.arange(W, dtype=np.float64) - centre[0],
                       indexing="ij")
    lam0 = float(np.mean(fk.lam_c))
    s0 = 2.0 * lam0 * 1e-6 * fk.fnumber
    sx, sy = fk.pixel_mm[0] / s0, fk.pixel_mm[1] / s0
    far = far_pixel_integral(i * sx, j * sy, sx, sy, fk.pupil) / fk.pupil.area
    return far[..., None] * (fk.lam_c / lam0)[None, None, :]


def convolve(image, kernel):
    """``image`` (H, W, C) convolved with a :func:`film_kernel` (2H, 2W, C) of the same film: (H, W, C)."""
    return FilmKernel(kernel).convolve(image)
