"""``mi-neurallens lens``: inspect, list and draw lens prescriptions.

  lens info PATH [--json] [--wavelength NM] [--focal-length MM] [--focus-distance MM]
                                              the prescription and every paraxial number
  lens plot PATH [-o layout.png] [--fields DEG ...] [--wavelengths NM ...] [--rays N] [--dpi N]
                 [--focal-length MM] [--focus-distance MM]
  lens list [--json]                          the lenses (bundled and $MI_NEURALLENS_LENSES) with EFL, f-number, model
  lens convert IN OUT.json [--name NAME] [--glass NAME=SPEC ...] [--stop-radius MM]
                           [--focal-length MM] [--focus-distance MM]
                                              any readable lens file -> project JSON (atomic write); with the
                                              last two, one fixed configuration of a lens with moving groups

PATH is a lens file (project JSON, pbrt .dat, Open Optical Designer JSON, LensVisualizer JSON,
Zemax .zmx, CODE V .seq) or the name of a bundled lens (``lens list``).  Lengths are in mm; ``*_z`` are lens-space positions
(first vertex at z = 0, +z toward the sensor).  ``--focal-length`` (a zoom lens's) and ``--focus-distance`` (mm from
the sensor plane, or inf) show the lens as ``realistic_lens`` configures it: its moving groups set, or (a lens
without) the whole lens moved to focus.
"""
from __future__ import annotations

import json
import math
import os

from ..constants import FULL_FRAME_MM, LAMBDA_C, LAMBDA_D, LAMBDA_F



def add_parser(subparsers):
    p = subparsers.add_parser("lens", help="inspect, list and draw lens prescriptions",
                              description=__doc__.split("\n\n", 1)[1] if __doc__ else None,
                              formatter_class=_raw_formatter())
    sub = p.add_subparsers(dest="lens_command", metavar="SUBCOMMAND")

    pi = sub.add_parser("info", help="print the prescription and its paraxial numbers")
    pi.add_argument("path", metavar="PATH", help="lens file or bundled lens name")
    pi.add_argument("--json", action="store_true", help="print JSON instead of text")
    pi.add_argument("--wavelength", type=float, default=LAMBDA_D, metavar="NM",
                    help="wavelength of the paraxial numbers in nm (default 587.5618, the d line)")
    _configuration_args(pi)
    pi.set_defaults(func=run_info)

    pp = sub.add_parser("plot", help="draw the lens layout with traced ray fans (PNG/SVG/PDF)")
    pp.add_argument("path", metavar="PATH", help="lens file or bundled lens name")
    pp.add_argument("-o", "--output", help="output image (default: <lens name>-layout.png); the "
                                           "extension picks the format: .png, .svg, .pdf, ...")
    pp.add_argument("--fields", type=float, nargs="+", metavar="DEG",
                    help="field angles in degrees (default: 0, 0.7 and 1 x the half field of view)")
    pp.add_argument("--wavelengths", type=float, nargs="+", metavar="NM",
                    default=[LAMBDA_F, LAMBDA_D, LAMBDA_C], help="wavelengths in nm (default F, d, C lines)")
    pp.add_argument("--rays", type=int, default=11, metavar="N", help="rays per fan (default 11)")
    pp.add_argument("--title", help="extra first title line")
    pp.add_argument("--dpi", type=int, default=150, help="resolution of raster output (default 150)")
    _configuration_args(pp)
    pp.set_defaults(func=run_plot)

    pl = sub.add_parser("list", help="list the lenses (bundled, and those of $MI_NEURALLENS_LENSES) and where each comes from")
    pl.add_argument("--json", action="store_true", help="print JSON instead of text")
    pl.set_defaults(func=run_list)

    pc = sub.add_parser("convert", help="convert any readable lens file to project JSON",
                        description="Read IN in any supported format and write project JSON to OUT "
                                    "(atomically: a temporary file renamed over OUT), so that a converted "
                                    "lens can be checked into a scene's folder.")
    pc.add_argument("input", metavar="IN", help="lens file (any supported format) or bundled lens name")
    pc.add_argument("output", metavar="OUT", help="project JSON file to write")
    pc.add_argument("--name", help="lens name to store (default: the reader's, usually the file name)")
    pc.add_argument("--glass", action="append", default=[], metavar="NAME=SPEC",
                    help="Zemax/CODE V: replace the file's glass NAME by SPEC: a catalogue glass (N-BK7), a "
                         "constant index (1.5), nd/Vd of a model glass (1.5891/61.16) or a JSON medium "
                         "('{\"nd\": 1.5891, \"vd\": 61.16}'); repeatable")
    pc.add_argument("--stop-radius", type=float, metavar="MM",
                    help="Zemax/CODE V/Open Optical Designer: the stop radius in mm instead of the file's "
                         "aperture")
    _configuration_args(pc)
    pc.set_defaults(func=run_convert)

    p.set_defaults(func=lambda args: (p.print_help(), 2)[1])
    return p


def _configuration_args(p):
    p.add_argument("--focal-length", type=float, metavar="MM",
                   help="a zoom lens's focal length in mm (EFL at infinity focus, d line): its zoom groups move to it")
    p.add_argument("--focus-distance", type=float, metavar="MM",
                   help="focus on an object this many mm from the sensor plane (inf: infinity), by the lens's "
                        "focusing groups where it has them, else by moving the whole lens")


def _raw_formatter():
    import argparse
    return argparse.RawDescriptionHelpFormatter


# ------------------------------------------------------------------------------ helpers
def _load(path):
    from ..optics.prescription import Lens
    return Lens.load(path)


def _num(x):
    """JSON number: floats, with ±inf/NaN as None."""
    if x is None:
        return None
    x = float(x)
    return x if math.isfinite(x) else None


def _source(lens) -> str:
    src = (lens.metadata or {}).get("source")
    if isinstance(src, dict):
        parts = [src.get("reference"), src.get("repository")]
        return "; ".join(str(v) for v in parts if v)
    return str(src) if src else ""


def _surface_rows(lens, wavelength_nm):
    rows = []
    z = lens.vertex_z
    for i, s in enumerate(lens.surfaces):
        m = s.medium
        rows.append({
            "index": i,
            "label": s.label,
            "radius": _num(s.radius),                 # None = flat
            "thickness": s.thickness,
            "vertex_z": float(z[i]),
            "medium": m.name,
            "nd": m.nd,
            "vd": _num(m.vd),                         # None = no dispersion
            "n": float(m.index(wavelength_nm)),
            "semi_diameter": s.semi_diameter,
            "conic": s.conic,
            "aspheric": list(s.aspheric),
            "housing_radius": s.housing_radius,
            "is_stop": s.is_stop,
            "blades": s.blades,
        })
    return rows


def info_dict(lens, wavelength_nm=LAMBDA_D) -> dict:
    """Everything ``lens info --json`` prints: name, provenance, fingerprint, the paraxial numbers
    (:meth:`ParaxialSystem.to_dict`, at the top level), the 36×24 mm paraxial FOV and the surfaces."""
    p = lens.paraxial(wavelength_nm)
    d = {
        "name": lens.name,
        "path": lens.path,
        "description": (lens.metadata or {}).get("description", ""),
        "source": _source(lens),
        "fingerprint": lens.fingerprint(),
        "units": "mm",
    }
    d.update(p.to_dict())
    try:
        fov = p.fov_deg(*FULL_FRAME_MM)
        d["fov_36x24_deg"] = {"horizontal": fov.horizontal, "vertical": fov.vertical,
                              "diagonal": fov.diagonal, "model": "paraxial, tan-based"}
    except Exception:  # an object-space-telecentric lens has no chief-ray angle
        d["fov_36x24_deg"] = None
    d["surfaces"] = _surface_rows(lens, wavelength_nm)
    return d


def _fmt(x, nd=4, unit=" mm"):
    if x is None or (isinstance(x, float) and math.isinf(x)):
        return "infinity"
    if isinstance(x, float) and math.isnan(x):
        return "n/a"
    return f"{x:.{nd}f}{unit}"


def _text_info(lens, wavelength_nm) -> str:
    p = lens.paraxial(wavelength_nm)
    out = []
    md = lens.metadata or {}
    out.append(f"{lens.name}  (fingerprint {lens.fingerprint()})")
    if md.get("description"):
        out.append(f"  {md['description']}")
    if lens.path:
        out.append(f"  file:   {lens.path}")
    if _source(lens):
        out.append(f"  source: {_source(lens)}")
    out.append(f"  {len(lens.surfaces)} surfaces, stop at surface {lens.stop_index}, "
               f"track {lens.total_track:.4f} mm (first to last vertex), image plane at z = {lens.image_z:.4f} mm")
    out.append("")
    show_n = abs(wavelength_nm - LAMBDA_D) > 1e-6
    head = (f"  {'#':>3} {'label':<6} {'radius':>12} {'thickness':>10} {'medium after':<18} {'nd':>8} {'Vd':>7}"
            + (f" {'n(λ)':>9}" if show_n else "") + f" {'semi-diam':>9}  notes")
    out.append("Surfaces (mm; radius > 0: centre toward the sensor; medium listed AFTER the surface)")
    out.append(head)
    out.append("  " + "-" * (len(head) - 2))
    for i, s in enumerate(lens.surfaces):
        m = s.medium
        vd = m.vd
        notes = []
        if s.is_stop:
            notes.append("STOP" + (f" ({s.blades} blades)" if s.blades else ""))
        if s.conic:
            notes.append(f"conic K={s.conic:g}")
        if s.is_aspheric:
            notes.append("asphere " + ", ".join(f"A{4 + 2 * k}={a:.4g}" for k, a in enumerate(s.aspheric) if a))
        if s.housing_radius is not None:
            notes.append(f"housing r={s.housing_radius:g}")
        if s.coating is not None:
            notes.append(f"coated n={s.coating.index:g}" if not hasattr(s.coating, "layers") else
                         f"coated {s.coating.name or 'stack'} ({len(s.coating.layers)} layers)")
        rad = "flat" if math.isinf(s.radius) else f"{s.radius:.5f}"
        line = (f"  {i:>3} {s.label[:6]:<6} {rad:>12} {s.thickness:>10.5f} {m.name[:18]:<18} {m.nd:>8.5f} "
                f"{('-' if math.isinf(vd) else f'{vd:.2f}'):>7}"
                + (f" {float(m.index(wavelength_nm)):>9.6f}" if show_n else "")
                + f" {s.semi_diameter:>9.4f}  {'; '.join(notes)}")
        out.append(line.rstrip())
    out.append("")
    out.append(f"Paraxial optics at {wavelength_nm:g} nm (object space n = {p.object_index:.6f}, "
               f"image space n = {p.image_index:.6f}); z = lens-space position, first vertex at 0")
    try:
        focus = p.focus_distance_for(p.sensor_distance)
        focus_s = _fmt(focus, 2)
    except Exception:
        focus_s = "beyond infinity (sensor closer than the rear focal point)"
    rows = [
        ("EFL (rear focal length n'/Φ, H' to F')", _fmt(p.efl)),
        ("front focal length (n/Φ, F to H)", _fmt(p.front_focal_length)),
        ("power Φ", f"{p.power:.6g} 1/mm"),
        ("BFL (last vertex to F')", _fmt(p.bfl)),
        ("FFL (F to first vertex, > 0: F in front)", _fmt(p.ffl)),
        ("front focal point F, z", _fmt(p.front_focal_z)),
        ("rear focal point F', z", _fmt(p.rear_focal_z)),
        ("front principal plane H, z", _fmt(p.front_principal_z)),
        ("rear principal plane H', z", _fmt(p.rear_principal_z)),
        ("aperture stop, z / radius", f"{_fmt(p.stop_z)} / {_fmt(p.stop_radius)}"),
        ("entrance pupil, z / radius", f"{_fmt(p.entrance_pupil_z)} / {_fmt(p.entrance_pupil_radius)}"),
        ("exit pupil, z / radius", f"{_fmt(p.exit_pupil_z)} / {_fmt(p.exit_pupil_radius)}"),
        ("pupil magnification (XP/EP radius)", _fmt(p.pupil_magnification, 4, "")),
        ("f-number (EFL / entrance pupil diameter)", f"f/{p.fnumber:.3f}"),
        ("sensor distance (last vertex to image plane)", _fmt(p.sensor_distance)),
        ("in focus on the image plane (from first vertex)", focus_s),
    ]
    try:
        fov = p.fov_deg(*FULL_FRAME_MM)
        rows.append(("FOV on 36x24 mm, paraxial tan (h / v / diag)",
                     f"{fov.horizontal:.2f}° / {fov.vertical:.2f}° / {fov.diagonal:.2f}°"))
    except Exception:
        pass
    w = max(len(k) for k, _ in rows)
    out += [f"  {k:<{w}}  {v}" for k, v in rows]
    (A, B), (C, D) = p.abcd()
    out.append(f"  {'ABCD, (y, n·u) first vertex → last vertex':<{w}}  [[{A:.6g}, {B:.6g} mm], [{C:.6g} 1/mm, {D:.6g}]]")
    return "\n".join(out)


def configured(lens, focal_length_mm=None, focus_distance_mm=None):
    """``lens`` as ``realistic_lens`` configures it: ``(configured lens, configuration dict or None)``.  With moving
    groups: at the focal length (None: the first listed position) focused on ``focus_distance_mm`` (from the
    sensor plane; None: infinity); without: ``focal_length_mm`` refused, the whole lens moved to focus."""
    from ..errors import LensError
    from ..optics import moving as mv
    if lens.moving is None:
        if focal_length_mm is not None:
            raise LensError(f"lens '{lens.name}' is not a zoom lens (its focal length is {lens.efl():.4g} mm): "
                            "leave --focal-length out", file=lens.path)
        if focus_distance_mm is None:
            return lens, None
        from ..sensors.common import solve_sensor_distance
        s = solve_sensor_distance(lens, float(focus_distance_mm))
        return lens.with_sensor_distance(s), {"focusing": "unit (the whole lens moves)",
                                              "focus_distance_mm": _num(focus_distance_mm), "sensor_distance_mm": s}
    focus = math.inf if focus_distance_mm is None else float(focus_distance_mm)
    L, t, f = mv.configure(lens, focal_length_mm, focus)
    mg = lens.moving
    lo, hi = mv.focal_length_range(lens) if mg.is_zoom else (None, None)
    conf = {"focusing": "moving groups", "focal_length_mm": mv.focal_length(lens, t) if mg.is_zoom else None,
            "focal_length_range_mm": [lo, hi] if mg.is_zoom else None,
            "focus_distance_mm": _num(focus), "zoom": t, "focus": f,
            "gaps_mm": {str(i): float(L.surfaces[i].thickness) for i in mg.gaps},
            "positions": mg.positions, "zoom_focal_lengths_mm": list(mg.zoom_efl_mm) if mg.zoom_efl_mm else None,
            "close_focus_mm": mg.close_focus_mm, "close_gaps": mg.close_gaps}
    return L, conf


def _configuration_text(lens, conf) -> list:
    """The lines ``lens info`` adds for a configured lens."""
    if conf is None:
        return []
    if conf["focusing"].startswith("unit"):
        return [f"  focused on {_fmt(conf['focus_distance_mm'], 1)} from the sensor by moving the whole lens: sensor "
                f"distance {conf['sensor_distance_mm']:.4f} mm", ""]
    out = ["Moving groups (docs/lens-format.md, 'Moving groups')"]
    if conf["focal_length_range_mm"]:
        lo, hi = conf["focal_length_range_mm"]
        zl = ", ".join(f"{z:g}" for z in conf["zoom_focal_lengths_mm"] or [])
        out.append(f"  zoom: {conf['positions']} listed positions ({zl} mm), focal length {lo:.4f}-{hi:.4f} mm at "
                   "infinity focus")
        out.append(f"  this configuration: focal length {conf['focal_length_mm']:.4f} mm (zoom parameter "
                   f"{conf['zoom']:.4f})")
    if conf["close_focus_mm"]:
        out.append(f"  focusing groups: infinity to {conf['close_focus_mm'] / 1000:g} m (close gaps "
                   f"{conf['close_gaps']})")
    out.append(f"  focused on {_fmt(conf['focus_distance_mm'], 1)} from the sensor (focus parameter "
               f"{conf['focus']:.4f}; 0 = the listed infinity gaps, 1 = the close ones)")
    out.append("  variable gaps: " + ", ".join(f"after {i}: {d:.4f}" for i, d in conf["gaps_mm"].items()) + " mm")
    out.append("")
    return out


# ------------------------------------------------------------------------------ commands
def run_info(args) -> int:
    base = _load(args.path)
    lens, conf = configured(base, args.focal_length, args.focus_distance)
    if args.json:
        d = info_dict(lens, args.wavelength)
        d["fingerprint"] = base.fingerprint()
        d["configuration"] = conf
        print(json.dumps(d, indent=2, allow_nan=False))
    else:
        text = _text_info(lens, args.wavelength).splitlines()
        text[0] = f"{base.name}  (fingerprint {base.fingerprint()})"
        k = next((i for i, line in enumerate(text) if line.startswith("Surfaces")), len(text))
        print("\n".join(text[:k] + _configuration_text(base, conf) + text[k:]))
    return 0


def run_plot(args) -> int:
    from ..optics.plot import plot_lens
    lens, _ = configured(_load(args.path), args.focal_length, args.focus_distance)
    out = args.output or f"{lens.name}-layout.png"
    path = plot_lens(lens, out, fields_deg=args.fields, wavelengths_nm=tuple(args.wavelengths),
                     rays_per_fan=args.rays, title=args.title, dpi=args.dpi)
    print(f"wrote {path} ({os.path.getsize(path)} bytes)")
    return 0


def run_list(args) -> int:
    from .. import resources
    rows = []
    for name in resources.lens_names():
        lens = _load(name)
        p = lens.paraxial()
        lib = resources.lens_origin(name)
        model, recipe = resources.find_model(name), resources.find_recipe(name)
        zoom = None
        if lens.moving is not None and lens.moving.is_zoom:
            from ..optics import moving as mv
            zoom = list(mv.focal_length_range(lens))
        rows.append({"name": name, "efl": p.efl, "bfl": p.bfl, "fnumber": p.fnumber, "focal_length_range_mm": zoom,
                     "surfaces": len(lens.surfaces),
                     "description": (lens.metadata or {}).get("description", ""),
                     "origin": lib.origin, "path": str(lib.lens(name)),
                     "model": str(model) if model else None, "recipe": str(recipe) if recipe else None})
    if args.json:
        print(json.dumps(rows, indent=2, allow_nan=False))
        return 0
    w = max([len(r["name"]) for r in rows] + [4])
    print(f"{'name':<{w}}  {'EFL mm':>9}  {'f/#':>6}  {'surf':>4}  {'model':>5}  {'from':<9}  description")
    for r in rows:
        desc = r["description"]
        desc = desc if len(desc) <= 60 else desc[:59] + "…"
        origin = "bundled" if r["origin"] == resources.BUNDLED else "user"
        efl = f"{r['efl']:.3f}" if not r["focal_length_range_mm"] else "{:.1f}-{:.1f}".format(*r["focal_length_range_mm"])
        print(f"{r['name']:<{w}}  {efl:>9}  {r['fnumber']:>6.2f}  {r['surfaces']:>4}  "
              f"{'yes' if r['model'] else '-':>5}  {origin:<9}  {desc}")
    print("(paraxial at 587.56 nm, stop fully open, a zoom lens's range and its f-number at the first position; "
          "`mi-neurallens lens info NAME` for details)")
    print(f"lens libraries, first wins: {resources.search_path_text()}")
    return 0


def glass_spec(text: str):
    """``--glass NAME=SPEC`` -> (NAME, medium spec for ``resolve_medium``)."""
    from ..errors import LensError
    name, sep, spec = text.partition("=")
    name, spec = name.strip(), spec.strip()
    if not sep or not name or not spec:
        raise LensError(f"--glass {text!r}: expected NAME=SPEC, e.g. D-ZK3M=D-ZK3 or B270=1.5231/58.5",
                        field="--glass")
    if spec.startswith("{"):
        try:
            return name, json.loads(spec)
        except json.JSONDecodeError as e:
            raise LensError(f"--glass {text!r}: not valid JSON: {e.msg}", field="--glass") from None
    parts = spec.split("/")
    try:
        nums = [float(x) for x in parts]
    except ValueError:
        return name, spec
    if len(nums) == 1:
        return name, nums[0]
    if len(nums) == 2:
        return name, {"nd": nums[0], "vd": nums[1]}
    raise LensError(f"--glass {text!r}: SPEC is a glass name, a number, nd/Vd or a JSON object", field="--glass")


def run_convert(args) -> int:
    from ..optics.formats import convert_file
    opts = {}
    if args.glass:
        opts["glasses"] = dict(glass_spec(g) for g in args.glass)
    if args.stop_radius is not None:
        opts["stop_radius"] = args.stop_radius
    configure = args.focal_length is not None or args.focus_distance is not None
    if configure:
        from ..optics.formats import load_lens
        if load_lens(args.input, **opts).moving is None:
            raise SystemExit(f"mi-neurallens: error: {args.input} has no moving groups: --focal-length and "
                             "--focus-distance configure a lens that zooms or focuses by moving groups")
    lens = convert_file(args.input, args.output, name=args.name, **opts)
    if configure:
        # one fixed configuration: what a lens without moving groups is (neural_lens can learn it)
        from ..optics.formats import save_lens
        fixed, conf = configured(lens, args.focal_length, args.focus_distance)
        md = dict(fixed.metadata)
        src = dict(md.get("source", {}))
        src["conversion"] = list(src.get("conversion", [])) + [
            f"one configuration of the moving groups: focal length {conf['focal_length_mm'] or fixed.efl():.6g} mm, "
            f"focused on {'infinity' if conf['focus_distance_mm'] is None else format(conf['focus_distance_mm'], 'g') + ' mm'}"
            f" (zoom parameter {conf['zoom']:.6g}, focus parameter {conf['focus']:.6g})"]
        md["source"] = src
        lens = fixed.replace(metadata=md, path=None)
        save_lens(lens, args.output)
    p = lens.paraxial()
    print(f"wrote {args.output}: {lens.name}, {len(lens.surfaces)} surfaces, EFL {p.efl:.4f} mm, f/{p.fnumber:.3f} "
          f"(fingerprint {lens.fingerprint()})")
    return 0
