"""Small helpers for rendering scripts: atomic EXR/PNG output, tone mapping, progress, XML overrides, the bokeh
scene.

Nothing here sets a Mitsuba variant; functions that need Mitsuba import it lazily.
"""
from __future__ import annotations

import os
import xml.etree.ElementTree as ET

import numpy as np

from .fileio import atomic_write

from .errors import NeuralLensError


#: environment variable naming the Mitsuba variant of the command line, the benchmarks and the tests
VARIANT_ENV = "MI_NEURALLENS_VARIANT"


def default_variant(kind: str = "rgb") -> str:
    """The Mitsuba variant the command line, the benchmarks and the tests use unless told otherwise:
    ``$MI_NEURALLENS_VARIANT`` or ``llvm_ad_rgb``.  ``kind="spectral"``: its spectral sibling
    (``cuda_ad_rgb`` → ``cuda_ad_spectral``).  ``MI_NEURALLENS_VARIANT=cuda_ad_rgb`` runs them on a GPU."""
    v = os.environ.get(VARIANT_ENV, "").strip() or "llvm_ad_rgb"
    if kind == "rgb":
        return v
    if kind == "spectral":
        return v.replace("_rgb", "_spectral").replace("_mono", "_spectral")
    raise NeuralLensError(f"default_variant(kind={kind!r}): use 'rgb' or 'spectral'")


def add_variant_argument(parser) -> None:
    """``--variant`` for an argparse parser (commands and benchmarks), defaulting to :func:`default_variant`."""
    parser.add_argument("--variant", default=default_variant(),
                        help=f"Mitsuba variant (default: ${VARIANT_ENV} or llvm_ad_rgb; now {default_variant()})")


# ----------------------------------------------------------------------------- output
def write_exr(path: str, image) -> None:
    """Write a float image (H, W, C) as OpenEXR, atomically."""
    import mitsuba as mi
    arr = np.ascontiguousarray(np.asarray(image, dtype=np.float32))
    atomic_write(path, lambda tmp: mi.Bitmap(arr).write(tmp))


def tonemap(image, exposure_ev: float = 0.0) -> np.ndarray:
    """Linear RGB → 8-bit sRGB (exposure in stops, clamp, sRGB OETF).  Returns (H, W, 3) uint8."""
    a = np.asarray(image, dtype=np.float64)
    if a.ndim == 2:
        a = a[..., None]
    if a.shape[2] == 1:
        a = np.repeat(a, 3, axis=2)
    a = np.clip(np.nan_to_num(a[..., :3] * (2.0 ** exposure_ev)), 0.0, 1.0)
    s = np.where(a <= 0.0031308, 12.92 * a, 1.055 * np.power(a, 1 / 2.4) - 0.055)
    return (s * 255.0 + 0.5).astype(np.uint8)


def write_png(path: str, image, exposure_ev: float = 0.0) -> None:
    """Tone-map (see :func:`tonemap`) and write a PNG, atomically."""
    from PIL import Image
    img = Image.fromarray(tonemap(image, exposure_ev))
    atomic_write(path, lambda tmp: img.save(tmp, format="PNG"))


# ----------------------------------------------------------------------------- progress
def progress(iterable, total=None, desc=None, enable=True):
    """tqdm if available (and enabled), otherwise a plain iterator printing nothing."""
    if not enable:
        return iterable
    try:
        from tqdm import tqdm
        return tqdm(iterable, total=total, desc=desc, unit="pass")
    except ImportError:  # pragma: no cover
        return iterable


def progress_bar(total: int, desc: str, unit: str = "step"):
    """A tqdm bar on standard error to ``update(k)`` by hand (gone when closed), or None where tqdm is missing."""
    try:
        from tqdm import tqdm
    except ImportError:  # pragma: no cover
        return None
    return tqdm(total=total, desc=desc, unit=unit, leave=False)


# ----------------------------------------------------------------------------- XML overrides
def parse_value(text: str):
    """'4' -> ('integer', '4'), '2.5' -> ('float', ...), 'true' -> ('boolean', ...), else string."""
    t = text.strip()
    if t.lower() in ("true", "false"):
        return "boolean", t.lower()
    try:
        int(t)
        return "integer", t
    except ValueError:
        pass
    try:
        float(t)
        return "float", t
    except ValueError:
        return "string", text


def _set_child(elem, name: str, text: str, float_ok=True):
    tag, value = parse_value(text)
    if tag == "integer" and float_ok:
        tag = "float"           # sensor properties are floats; integers only where asked
    for ch in list(elem):
        if ch.get("name") == name:
            elem.remove(ch)
    ET.SubElement(elem, tag, {"name": name, "value": value})


def apply_sensor_overrides(xml_text: str, *, sets=(), lens=None, resolution=None, spp=None,
                           source="scene", sensor_type=None) -> str:
    """Edit a scene's XML text: set properties of its (first) ``<sensor>``.

    ``sets``: ``key=value`` strings; ``film.key=value`` / ``sampler.key=value`` go to the sensor's
    film / sampler (``film.width=640``).  ``lens``: shorthand for ``lens=...``.  ``resolution``:
    (w, h) for the film.  ``spp``: the sampler's ``sample_count``.  ``sensor_type``: replace the
    sensor plugin (e.g. ``neural_lens`` for a scene written for ``realistic_lens``; the two share
    their properties).  Values are typed as boolean (true/false), float (numbers; integers for
    film/sampler) or string.
    """
    try:
        root = ET.fromstring(xml_text)
    except ET.ParseError as e:
        raise NeuralLensError(f"{source}: not valid XML: {e}") from None
    sensor = root.find(".//sensor")
    if sensor is None:
        raise NeuralLensError(f"{source}: the scene has no <sensor> to apply --set/--lens/--resolution to")

    def child(kind, default_type):
        e = sensor.find(kind)
        if e is None:
            e = ET.SubElement(sensor, kind, {"type": default_type})
        return e

    if sensor_type is not None:
        sensor.set("type", sensor_type)
    items = list(sets)
    if lens is not None:
        items.append(f"lens={lens}")
    for kv in items:
        if "=" not in kv:
            raise NeuralLensError(f"--set expects key=value, got {kv!r}")
        k, v = kv.split("=", 1)
        k = k.strip()
        if k.startswith("film."):
            _set_child(child("film", "hdrfilm"), k[5:], v, float_ok=False)
        elif k.startswith("sampler."):
            _set_child(child("sampler", "independent"), k[8:], v, float_ok=False)
        elif k in ("lens", "pupil_sampling", "model"):
            for ch in list(sensor):
                if ch.get("name") == k:
                    sensor.remove(ch)
            ET.SubElement(sensor, "string", {"name": k, "value": v})
        else:
            # focus_distance and sensor_distance are exclusive: the one being set replaces the other
            rival = {"focus_distance": "sensor_distance", "sensor_distance": "focus_distance"}.get(k)
            if rival:
                for ch in list(sensor):
                    if ch.get("name") == rival:
                        sensor.remove(ch)
            _set_child(sensor, k, v)
    if resolution is not None:
        f = child("film", "hdrfilm")
        _set_child(f, "width", str(int(resolution[0])), float_ok=False)
        _set_child(f, "height", str(int(resolution[1])), float_ok=False)
    if spp is not None:
        _set_child(child("sampler", "independent"), "sample_count", str(int(spp)), float_ok=False)
    return ET.tostring(root, encoding="unicode")
