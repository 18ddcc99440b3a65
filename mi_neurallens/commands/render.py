"""``mi-neurallens render``: render a Mitsuba XML scene that uses the lens sensors.

Overrides (``--lens``, ``--set key=value``, ``--resolution``, ``--spp``) edit the scene's first
``<sensor>`` element in the XML before loading (``film.key=value``/``sampler.key=value`` reach the
sensor's film/sampler), so they work on any scene, with or without ``$parameters``.  XML parameters
(``<default name="..."/>`` / ``$name``) are set with ``-D name=value``.

The image is rendered in passes (``--passes``, each with its own seed) with a progress bar, averaged,
and written as an OpenEXR (``-o out.exr``, atomically) plus a tone-mapped sRGB PNG next to it.
"""
from __future__ import annotations

import math
import os
import sys
import time

from ..render_utils import add_variant_argument


def add_parser(subparsers):
    p = subparsers.add_parser("render", help="render a Mitsuba XML scene (EXR + PNG)",
                              description=__doc__.split("\n\n", 1)[1] if __doc__ else None)
    p.add_argument("scene", help="Mitsuba XML scene file, or a bundled scene's name (still_life, chart, bokeh, night, "
                                    "night_point)")
    p.add_argument("-o", "--output", help="output EXR (default: <scene name>.exr in the current directory)")
    p.add_argument("--spp", type=int, help="samples per pixel (overrides the scene's sampler)")
    add_variant_argument(p)
    p.add_argument("--lens", help="lens of the sensor: bundled name or file (sets the sensor's 'lens')")
    p.add_argument("--set", dest="sets", action="append", default=[], metavar="KEY=VALUE",
                   help="set a sensor property (repeatable), e.g. --set fstop=8 --set focus_distance=2; "
                        "film.KEY=VALUE / sampler.KEY=VALUE for the film/sampler")
    p.add_argument("-D", dest="params", action="append", default=[], metavar="NAME=VALUE",
                   help="XML parameter ($NAME) value (repeatable)")
    p.add_argument("--resolution", help="film size WxH, e.g. 640x480")
    p.add_argument("--passes", type=int, help="number of passes (default: spp/16, at least 1)")
    p.add_argument("--exposure", type=float, default=0.0, help="PNG exposure in stops (default 0)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run)
    return p


def _resolution(text):
    from ..errors import NeuralLensError
    try:
        w, h = text.lower().split("x")
        w, h = int(w), int(h)
        if w <= 0 or h <= 0:
            raise ValueError
        return w, h
    except ValueError:
        raise NeuralLensError(f"--resolution expects WxH with positive integers (e.g. 640x480), got {text!r}") \
            from None


def load_scene(path, *, variant=None, sets=(), lens=None, resolution=None, spp=None, params=(),
               sensor_type=None):
    """Load the scene ``path`` (a file, or the name of a bundled scene: :func:`mi_neurallens.resources.scene_path`)
    with the overrides applied (see the module docstring); returns the scene."""
    import mitsuba as mi
    from ..errors import NeuralLensError
    from ..resources import scene_path
    from ..render_utils import apply_sensor_overrides
    if variant is not None and mi.variant() != variant:
        if variant not in mi.variants():
            raise NeuralLensError(f"unknown Mitsuba variant {variant!r}; available: {', '.join(mi.variants())}")
        mi.set_variant(variant)
    import mi_neurallens
    mi_neurallens.register()
    path = str(scene_path(path))
    with open(path, encoding="utf-8") as f:
        text = f.read()
    text = apply_sensor_overrides(text, sets=sets, lens=lens, resolution=resolution, spp=spp, source=path,
                                  sensor_type=sensor_type)
    kw = {}
    for kv in params:
        if "=" not in kv:
            raise NeuralLensError(f"-D expects NAME=VALUE, got {kv!r}")
        k, v = kv.split("=", 1)
        kw[k.strip()] = v
    fr = mi.file_resolver() if hasattr(mi, "file_resolver") else mi.Thread.thread().file_resolver()
    fr.prepend(os.path.dirname(os.path.abspath(path)))
    try:
        return mi.load_string(text, **kw)
    except Exception as e:   # Mitsuba wraps plugin errors; show the root cause first
        cause = e
        while cause.__cause__ is not None:
            cause = cause.__cause__
        raise NeuralLensError(f"{path}: cannot load the scene: {_strip_traceback(str(cause))}") from e


def _strip_traceback(msg: str) -> str:
    """Mitsuba embeds a plugin's Python traceback in its error; keep the location and the message."""
    lines = msg.splitlines()
    if not any(l.startswith("Traceback") or l.endswith("Traceback (most recent call last):") for l in lines):
        return msg
    head = lines[0].split("Traceback (most recent call last):")[0].rstrip()
    last = max(i for i, l in enumerate(lines) if l.lstrip().startswith("File ") or l.startswith("Traceback")
               or l.endswith("Traceback (most recent call last):"))
    tail = "\n".join(lines[last + 1:]).strip()
    return f"{head} {tail}".strip()


def render_passes(scene, spp: int, passes: int, show_progress=True, seed: int = 0, desc: str = "render"):
    """Render ``spp`` samples per pixel in ``passes`` passes (different seeds) and average; returns
    (numpy image, seconds)."""
    import drjit as dr
    import mitsuba as mi
    import numpy as np
    from ..render_utils import progress
    passes = max(1, min(int(passes), int(spp)))
    base, extra = divmod(int(spp), passes)
    acc = None
    t0 = time.perf_counter()
    for i in progress(range(passes), total=passes, desc=desc, enable=show_progress):
        k = base + (1 if i < extra else 0)
        img = mi.render(scene, spp=k, seed=seed + i)
        a = np.array(img, dtype=np.float64) * k
        acc = a if acc is None else acc + a
    dr.sync_thread()
    return (acc / spp).astype(np.float32), time.perf_counter() - t0


def run(args) -> int:
    from ..render_utils import write_exr, write_png
    res = _resolution(args.resolution) if args.resolution else None
    scene = load_scene(args.scene, variant=args.variant, sets=args.sets, lens=args.lens,
                       resolution=res, spp=args.spp, params=args.params)
    sensor = scene.sensors()[0]
    spp = sensor.sampler().sample_count()   # after --spp; samplers may round it (ldsampler: square power of 2)
    passes = args.passes or max(1, math.ceil(spp / 16))
    out = args.output or os.path.splitext(os.path.basename(args.scene))[0] + ".exr"
    if not out.lower().endswith(".exr"):
        out += ".exr"
    size = sensor.film().size()
    print(f"rendering {args.scene}: {size[0]}x{size[1]}, {spp} spp in {passes} pass(es), "
          f"variant {args.variant}\n  sensor: {sensor}", file=sys.stderr)
    img, secs = render_passes(scene, spp, passes, show_progress=not args.no_progress)
    write_exr(out, img)
    png = os.path.splitext(out)[0] + ".png"
    write_png(png, img, args.exposure)
    print(f"render time {secs:.2f} s; wrote {out} and {png}")
    return 0
