"""Write the figures of docs/performance.md and README.md's headline table from the benchmarks' JSON.

    python docs/make_performance.py                       # regenerate from docs/performance/
    python docs/make_performance.py --from out/bench      # first copy a fresh `make bench` run into docs/performance/
    python docs/make_performance.py --gpu-from DIR        # first copy a GPU run (benchmarks/gpu_suite.sh's results/)
    python docs/make_performance.py --check               # write nothing; exit 1 if a generated block differs

``docs/performance/`` holds one JSON file per benchmark run, exactly as the benchmark wrote it
(``bench_tracer.json``, ``mlp_<lens>.json`` and ``render_<lens>.json`` per lens, ``bench_flare.json``,
``equal_time.json``, ``bench_baselines.json``, ``accuracy_<lens>.json``, the flare's ``starburst_<lens>.json`` and
``coatings_<lens>.json``; GPU runs in ``gpu/``: ``render_<lens>.json``, ``mlp_<lens>.json``
and the suite's ``gpu.txt``), and ``sources.json``: for each file the command, the machine, the date and the
commit it was measured at.  ``--from`` / ``--gpu-from`` copy the files a run wrote and record their source (the
machine read from /proc/cpuinfo, or ``--machine TEXT``).  The learned maps' accuracy comes from the evaluation
records that ship with the models (``mi_neurallens/data/lenses/models/*.eval.json``).

Each table goes between ``<!-- generated: NAME -->`` and ``<!-- end generated -->`` (docs/generated_blocks.py);
the text around the tables is written by hand and states no figure of its own.  A file or a row a run did not
write leaves its table out or its row empty; nothing is made up.
"""
from __future__ import annotations

import argparse
import datetime
import glob
import json
import math
import os
import platform
import shutil
import subprocess
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from generated_blocks import ROOT, table, write_pages  # noqa: E402

if ROOT not in sys.path:            # this tree's package, not an installed one
    sys.path.insert(1, ROOT)

PERF = os.path.join(ROOT, "docs", "performance")
MODELS = os.path.join(ROOT, "mi_neurallens", "data", "lenses", "models")
#: the CPU benchmark files docs/performance/ takes from a run (``make bench`` writes them, and ``mlp_<lens>.json`` /
#: ``render_<lens>.json`` per lens)
CPU_FILES = ("bench_tracer.json", "bench_flare.json", "equal_time.json", "bench_baselines.json", "bench_zoom.json",
             "bench_zoom_640.json", "bench_focus.json")
#: how each file is made when its run did not record its own command (the Makefile's ``bench`` target)
DEFAULT_COMMANDS = {**{f: f"python benchmarks/{f[:-5]}.py" for f in CPU_FILES},
                    "bench_zoom_640.json": "python benchmarks/bench_zoom.py --focal 24.9,35,68.14 --focus inf "
                                           "--res 640x424 --reference-spp 64 --repeats 4",
                    "bench_focus.json": "python benchmarks/bench_zoom.py --lens canon-rf-24mm-f1.4l-vcm --focal none "
                                        "--focus inf,2,1,0.5,0.3,0.24"}
PERF_PAGE, README = "docs/performance.md", "README.md"
#: learned vs traced rows of bench_mlp / bench_render
EXACT_MLP, FUSED_MLP, COOP_MLP = "exact tracer", "neural, fused literals (default)", "neural, cooperative vectors"


# ------------------------------------------------------------------------------------------------ numbers
def num(v, sig: int = 3) -> str:
    """``v`` with ``sig`` significant digits in fixed notation (57.0, 2.02, 0.0286, 840)."""
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "—"
    v = float(v)
    if v == 0:
        return "0"
    d = max(sig - 1 - int(math.floor(math.log10(abs(v)))), 0)
    return f"{v:.{d}f}"


def ratio(v, sig: int = 3) -> str:
    """A ratio: two decimals near 1, ``sig`` significant digits elsewhere."""
    if v is None:
        return "—"
    return f"{v:.2f}×" if 0.995 <= v < 9.995 else f"{num(v, sig)}×"


def pct(v, sig: int = 2) -> str:
    return "—" if v is None else f"{num(100.0 * v, sig)} %"


def span(values, fmt=num, unit: str = "") -> str:
    """``lo–hi`` of the values (one value alone), or ``—``."""
    vs = sorted(v for v in values if v is not None)
    if not vs:
        return "—"
    lo, hi = fmt(vs[0]), fmt(vs[-1])
    return (lo if lo == hi else f"{lo}–{hi}") + unit


def div(a, b):
    return None if a is None or not b else a / b


# ------------------------------------------------------------------------------------------------ the data
class Results:
    """The stored runs: ``cpu[name]`` (file name → JSON), ``gpu_render`` / ``gpu_mlp`` (lens → JSON), ``sources``
    (file → its command, machine, date, commit), ``evals`` (lens → the bundled model's evaluation record)."""

    def __init__(self, perf: str = PERF, models: str = MODELS):
        self.cpu = {}
        for p in sorted(glob.glob(os.path.join(perf, "*.json"))):
            if os.path.basename(p) != "sources.json" and not os.path.basename(p).startswith(("render_", "mlp_")):
                self.cpu[os.path.basename(p)] = _load(p)
        self.cpu_render = {_lens_of(p, "render_"): _load(p) for p in sorted(glob.glob(os.path.join(perf, "render_*.json")))}
        self.cpu_mlp = {_lens_of(p, "mlp_"): _load(p) for p in sorted(glob.glob(os.path.join(perf, "mlp_*.json")))}
        self.gpu_render = {_lens_of(p, "render_"): _load(p) for p in sorted(glob.glob(os.path.join(perf, "gpu", "render_*.json")))}
        self.gpu_mlp = {_lens_of(p, "mlp_"): _load(p) for p in sorted(glob.glob(os.path.join(perf, "gpu", "mlp_*.json")))}
        #: a GPU run's other files, by their key in sources.json ("gpu/bench_zoom.json")
        self.gpu = {f"gpu/{os.path.basename(p)}": _load(p) for p in sorted(glob.glob(os.path.join(perf, "gpu", "*.json")))
                    if not os.path.basename(p).startswith(("render_", "mlp_"))}
        src = os.path.join(perf, "sources.json")
        self.sources = _load(src).get("files", {}) if os.path.exists(src) else {}
        self.evals = {}
        for p in sorted(glob.glob(os.path.join(models, "*.model.safetensors.eval.json"))):
            d = _load(p)
            self.evals[d.get("lens") or os.path.basename(p).split(".model.")[0]] = d

    def source(self, name: str) -> str:
        """The line under a table: the command that made its file, the machine, when."""
        s = self.sources.get(name, {})
        cmd = s.get("command") or DEFAULT_COMMANDS.get(name, "")
        when = " ".join(x for x in (s.get("measured", ""), f"(commit {s['commit']})" if s.get("commit") else "") if x)
        parts = [f"`{cmd}`" if cmd else "", s.get("machine", "machine not recorded"), f"measured {when}" if when else ""]
        return "*" + "; ".join(p for p in parts if p) + ".*\n"

    def short(self, name: str) -> str:
        return self.sources.get(name, {}).get("machine_short", "")


def _load(path):
    with open(path, encoding="utf-8") as f:
        return json.load(f)


def _lens_of(path, prefix):
    return os.path.basename(path)[len(prefix):-len(".json")]


# ------------------------------------------------------------------------------------------------ tables
def tracer_table(r: Results) -> str:
    d = r.cpu.get("bench_tracer.json")
    if not d:
        return "*No tracer run stored.*\n"
    info = d.get("info", {})
    rows = []
    for x in d.get("rows", []):
        rows.append([f"`{x.get('lens', '')}`", x.get("surfaces", ""), x.get("path", ""), num(x.get("mrays_per_s")),
                     num(x.get("valid_fraction"), 2), num(x.get("optiland_mrays_per_s")) if "optiland_mrays_per_s" in x
                     else "no ghosts", ratio(x.get("speedup"), 2) if "speedup" in x else ""])
    head = ""
    if info.get("rays"):
        head = (f"{_pow2(info['rays'])} object-space rays ({_pow2(info.get('optiland_rays'))} for optiland), "
                f"{info.get('precision', '')}, Fresnel {'on' if info.get('fresnel') else 'off'}, wavelength "
                f"{info.get('wavelength', '')}.\n\n")
    return head + table(["lens", "optical surfaces", "path", "M rays/s", "valid", "optiland M rays/s",
                         "ours ÷ optiland"], rows) + "\n" + r.source("bench_tracer.json")


def _pow2(n):
    if not n:
        return "—"
    k = math.log2(n)
    return f"2^{int(k)}" if k == int(k) else f"{n:,}"


def mlp_table(r: Results) -> str:
    """The camera map alone against the tracer, per lens, on the CPU (``mlp_<lens>.json``)."""
    return lens_mlp_table(r, r.cpu_mlp, "", 1.0, "M")


def camera_record(ev: dict) -> dict:
    """A model's evaluation record of its camera map (the backward transmit map), {} where it has none."""
    return (ev.get("maps") or {}).get("backward.0") or {}


def tanh_table(r: Results) -> str:
    """What the float32 kernel (its tanh approximation, float32 arithmetic) adds to each camera map's own error: the
    default style's outputs against the float64 reference with the exact tanh (``mlp_<lens>.json``), beside the
    map's held-out error against the tracer (its evaluation record)."""
    rows, some, used = [], None, {}
    for lens, d in r.cpu_mlp.items():
        v = d.get("rows", {}).get(FUSED_MLP, {}).get("vs_float64_exact_tanh")
        if not v:               # a run before bench_mlp.py measured it
            continue
        some, used[lens] = some or v, d
        own = camera_record(r.evals.get(lens, {})).get("regressor", {})
        p, a = v["position_um"], v["direction_arcsec"]
        rows.append([f"`{lens}`", f"{num(p['median'], 2)} / {num(p['max'], 2)}", num(own.get("position_um_median")),
                     f"{num(a['median'], 2)} / {num(a['max'], 2)}", num(own.get("direction_arcsec_median")),
                     pct(v["validity_flips"])])
    if not rows:
        return "*No stored run of `benchmarks/bench_mlp.py` records it.*\n"
    return (f"The fused kernel's outputs on the first {_pow2(some['rays'])} rays of each camera-rays run against the "
            f"float64 evaluation with the exact tanh, on the rays the reference passes, beside each map's own error "
            f"against the tracer (held-out, median).\n\n"
            + table(["lens", "exit position µm: kernel − float64, median / max", "map − tracer, median",
                     "direction ″: kernel − float64, median / max", "map − tracer, median", "validity flips"],
                    rows)
            + "\n" + _each_lens(r, "mlp_", used))


def render_table(r: Results) -> str:
    """A whole frame through each sensor, per lens, on the CPU (``render_<lens>.json``)."""
    return lens_render_table(r, r.cpu_render, "")


def _scene(s):
    name = os.path.splitext(os.path.basename(str(s or "")))[0]
    return f"bundled scene `{name}`" if name else "scene"


def equal_time_table(r: Results) -> str:
    d = r.cpu.get("equal_time.json")
    if not d:
        return "*No run stored.*\n"
    rows = []
    for L in d.get("lenses", []):
        real = {x["spp"]: x for x in L.get("renders", {}).get("realistic_lens", [])}
        neur = {x["spp"]: x for x in L.get("renders", {}).get("neural_lens", [])}
        same_time = {x["spp_realistic"]: x for x in L.get("equal_time", [])}
        for spp in sorted(set(real) | set(neur)):
            a, b, t = real.get(spp, {}), neur.get(spp, {}), same_time.get(spp, {})
            rows.append([f"`{L.get('lens', '')}`", spp, num(a.get("seconds")), num(a.get("mape")),
                         num(b.get("seconds")), num(b.get("mape")), ratio(div(b.get("mape"), a.get("mape")), 3),
                         num(t.get("mape_neural")), ratio(div(t.get("mape_neural"), t.get("mape_realistic")), 3)])
    w, h = (d.get("resolution") or ["?", "?"])[:2]
    head = (f"The {_scene(d.get('scene'))} at {w}×{h}, {d.get('variant', '')}; MAPE against a "
            f"{d.get('reference_spp', '?')}-spp `realistic_lens` reference with its own seed (its noise is in both "
            f"columns); the last two columns interpolate `neural_lens`'s MAPE (log–log over its render times) at the time "
            f"`realistic_lens` took for that spp.\n\n")
    return head + table(["lens", "spp", "realistic_lens s", "MAPE", "neural_lens s", "MAPE",
                         "neural ÷ realistic, equal spp", "neural MAPE, equal time", "neural ÷ realistic, equal time"],
                        rows) + "\n" + r.source("equal_time.json")


def flare_table(r: Results) -> str:
    d = r.cpu.get("bench_flare.json")
    if not d:
        return "*No run stored.*\n"
    rows = []
    for x in d.get("rows", []):
        e, n, t = x.get("exact_pilot", {}), x.get("neural_pilot", {}), x.get("neural_equal_time", {})
        reach = (f"{num(e.get('fraction_before'), 2)} → {num(e.get('fraction_after'), 2)}"
                 if e.get("fraction_before") is not None else "—")
        rows.append([x.get("path_id", ""), num(div(e.get("samples_per_s"), 1e6)), num(div(n.get("samples_per_s"), 1e6)),
                     ratio(div(n.get("samples_per_s"), e.get("samples_per_s")), 2), reach,
                     num(t.get("exact_mape_vs_ref", e.get("mape_vs_ref"))), num(t.get("mape_vs_ref"))])
    head = (f"Lens `{d.get('lens', '')}`, one point light, 240×160, each ghost alone: {_pow2(d.get('samples'))} samples "
            f"(best of 3 after a compile run) and MAPE against a {_pow2(d.get('ref_samples'))}-sample exact render; "
            f"\"same time\": the learned ghost gets the wall time the traced one took.\n\n")
    return head + table(["ghost", "traced M samples/s", "learned M samples/s", "learned ÷ traced",
                         "samples reaching the film: whole disk → pilot cells", "MAPE traced",
                         "MAPE learned, same time"], rows) + "\n" + r.source("bench_flare.json")


def _runs(r: Results, prefix: str) -> list:
    """The stored CPU files whose names start with ``prefix`` (one per lens), sorted."""
    return sorted(n for n in r.cpu if n.startswith(prefix))


def starburst_table(r: Results) -> str:
    files = _runs(r, "starburst_")
    if not files:
        return "*No run stored.*\n"
    rows, srcs = [], []
    for n in files:
        d = r.cpu[n]
        rows.append([f"`{d.get('lens', '')}`", d.get("lights", ""), "×".join(str(v) for v in d.get("resolution", [])),
                     num(d.get("seconds_without")), num(d.get("seconds_with")), ratio(d.get("ratio"), 3),
                     num(d.get("kernel_build_seconds"), 2)])
        srcs.append(r.source(n))
    head = ("The bundled night scene's whole flare (its lights, the automatic ghost selection, mode auto, "
            f"{_pow2(r.cpu[files[0]].get('samples_per_light'))} samples per light), best of 11 renders, without and with "
            "the diffraction starburst; the film kernel is built once per aperture, focus and film.\n\n")
    return head + table(["lens", "lights", "film", "flare s, no starburst", "flare s, starburst", "ratio",
                         "kernel build s (once)"], rows) + "\n" + "".join(srcs)


def coatings_table(r: Results) -> str:
    files = _runs(r, "coatings_")
    if not files:
        return "*No run stored.*\n"
    rows, srcs, names = [], [], []
    for n in files:
        d = r.cpu[n]
        names = d.get("coatings", [])
        for x in d.get("rows", []):
            rows.append([f"`{d.get('lens', '')}`", SCENES[d.get("scene", "point")], x.get("path_id", "")]
                        + [f"{num(1e3 * x['seconds'][c])} ({ratio(x['ratio'][c], 3)})" for c in names])
        srcs.append(r.source(n))
    head = ("One ghost traced exactly (pilot bounds), best of 5 renders of each coating alternating, ms per render and "
            "its ratio to the first coating's: on one point light (the ghost's trace alone, the worst case) and on the "
            "bundled night scene.\n\n")
    return head + table(["lens", "scene", "ghost"] + [f"{c} ms" for c in names], rows) + "\n" + "".join(srcs)


SCENES = {"point": "one point light, 240×160", "night": "night, 4 lights, 960×640"}


def _gates():
    """``lens_flare``'s default gates of mode ``auto``: the verified flare error and the cost ratio."""
    from mi_neurallens.flare.options import FlareOptions
    return FlareOptions.auto_max_flare_error, FlareOptions.auto_max_cost


def ghost_counts(ev: dict, backend: str = "llvm") -> dict:
    """How the ghost maps of one evaluation record fare at ``auto``'s default gates: ``maps``, ``verified`` (a flare
    record), ``edges_learned`` (a record of the learned edges within the gate), ``edges_traced`` (within it only
    with the edges traced, ``boundary_band`` > 0), ``learned`` (of those, the ones whose recorded cost on
    ``backend`` is not above tracing them, or not recorded)."""
    gate, max_cost = _gates()
    out = dict(maps=0, verified=0, edges_learned=0, edges_traced=0, learned=0, cost_recorded=0)
    for key, m in (ev.get("maps") or {}).items():
        if not key.startswith("forward.") or key == "forward.0":
            continue
        out["maps"] += 1
        recs = ([m["flare"]] if m.get("flare") else []) + list((m.get("flare_bands") or {}).values())
        if not recs:
            continue
        out["verified"] += 1
        passing = sorted(float(x.get("boundary_band", 0.0)) for x in recs
                         if x.get("paired_mape") is not None and x["paired_mape"] <= gate)
        if not passing:
            continue
        band = passing[0]
        out["edges_learned" if band == 0.0 else "edges_traced"] += 1
        cost = (m.get("flare_cost") or {}).get(backend) or {}
        lu, eu = (cost.get("learned_us") or {}).get(f"{band:g}"), cost.get("exact_us")
        if lu is not None and eu:
            out["cost_recorded"] += 1
        if lu is None or not eu or lu / eu <= max_cost:
            out["learned"] += 1
    return out


def zoom_table(r: Results, name: str = "bench_zoom.json") -> str:
    """A lens's one camera map over its moving groups at configurations the training never drew (``bench_zoom.json``:
    the zoom lens; ``bench_focus.json``: an internally focused prime, no focal-length column;
    ``gpu/bench_zoom.json``: the zoom lens on a GPU, ``gpu_suite.sh zoom``): the map against the tracer on the same
    rays, neural_lens against realistic_lens on the still life."""
    d = r.gpu.get(name) if name.startswith("gpu/") else r.cpu.get(name)
    if not d:
        return ("*No GPU run stored: `bash benchmarks/gpu_suite.sh zoom` measures it, then `python docs/make_performance.py "
                "--gpu-from` its results.*\n" if name.startswith("gpu/") else "*No run stored.*\n")
    zoom = any(x.get("focal_length_mm") is not None for x in d.get("rows", []))
    rows = []
    for x in d.get("rows", []):
        m, rr = x.get("map", {}), x.get("render", {})
        focus = "∞" if math.isinf(float(x.get("focus_m", math.inf))) else f"{num(x.get('focus_m'))} m"
        rows.append(([f"{num(x.get('focal_length_mm'), 4)} mm"] if zoom else []) + [
            focus, f"{num(m.get('position_um_median'))} / {num(m.get('position_um_p99'))}",
            f"{num(m.get('direction_arcsec_median'))} / {num(m.get('direction_arcsec_p99'))}",
            pct(m.get("misclassification")), ratio(rr.get("mape_ratio")), ratio(rr.get("time_ratio")),
            ratio(rr.get("camera_time_ratio"))])
    res = "x".join(str(v) for v in d.get("resolution", []))
    note = (f"*`{d.get('lens')}`; render columns: the still life at {res}, {d.get('spp')} spp, MAPE against "
            f"realistic_lens at {d.get('reference_spp')} spp (neural ÷ realistic: 1 means the map adds nothing to "
            "the noise), render time neural ÷ realistic at equal spp, and the same for the camera rays alone (the "
            "sensors' `sample_ray` on the render's samples, no scene).*\n")
    return table((["focal length"] if zoom else []) + [
        "focus", "exit position µm, median / p99", "direction ″, median / p99", "misclassified", "MAPE ratio",
        "time ratio", "camera rays time ratio"], rows) + "\n" + note + r.source(name)


def maps_table(r: Results) -> str:
    gate, max_cost = _gates()
    rows = []
    for lens, ev in r.evals.items():
        cam = camera_record(ev)
        g, c = cam.get("regressor", {}), cam.get("classifier", {})
        k = ghost_counts(ev)
        rows.append([f"`{lens}`", f"{num(g.get('position_um_median'))} / {num(g.get('position_um_p99'))}",
                     f"{num(g.get('direction_arcsec_median'))} / {num(g.get('direction_arcsec_p99'))}",
                     pct(c.get("misclassification")), k["maps"], k["verified"],
                     f"{k['edges_learned']} / {k['edges_traced']}", f"{k['learned']} of {k['maps']}"])
    return (table(["model", "camera map: exit position µm, median / p99", "direction ″, median / p99", "misclassified",
                   "ghost maps", "verified", f"within {gate:g}: learned edges / edges traced",
                   "`auto` learns on a CPU"], rows)
            + f"\n*`mi-neurallens evaluate LENS --recorded` prints the same records (held-out rays traced in float64 at "
              f"training, the flare records and costs of `mi-neurallens evaluate --flare --flare-cost --write`); the "
              f"records ship beside each model in `mi_neurallens/data/lenses/models/`. `auto` at its defaults "
              f"(`auto_max_flare_error` {gate:g}, `auto_max_cost` {max_cost:g}) with the CPU (`llvm`) cost records, "
              f"on a film coarse enough for its position gate (`auto_max_error`: 0.1 px).*\n")


def baselines_speed_table(r: Results) -> str:
    d = r.cpu.get("bench_baselines.json")
    if not d:
        return "*No run stored.*\n"
    rows = [[x.get("path", ""), x.get("method", ""), num(div(x.get("rays_per_s"), 1e6)), ratio(x.get("speedup"), 2),
             x.get("flops_per_ray") if x.get("flops_per_ray") is not None else "—"] for x in d.get("rows", [])]
    head = (f"`eval_dr` of each method on the same {d.get('rays', '?'):,} rays of `{d.get('lens', '')}`, "
            f"{d.get('backend', '')}, {d.get('threads', '?')} threads.\n\n")
    return head + table(["path", "method", "M rays/s", "× exact", "FLOPs/ray"], rows) + "\n" \
        + r.source("bench_baselines.json")


ACC_METHODS = ("abcd", "taylor3", "taylor5", "taylor5-ap", "fitted", "neural")


def baselines_accuracy_table(r: Results) -> str:
    names = _runs(r, "accuracy_")
    if not names:
        return "*No run stored.*\n"
    rows, flare = [], []
    for n in names:
        d = r.cpu[n]
        for key, p in (d.get("paths") or {}).items():
            ms = p.get("methods", {})
            cells = []
            for m in ACC_METHODS:
                x = ms.get(m)
                cells.append("—" if not x or x.get("position_um_median") is None else
                             f"{num(x['position_um_median'])} / {num(x.get('position_um_p99'))} ({num(x.get('iou'), 2)})")
            rows.append([f"`{d.get('lens', '')}`", key, p.get("steps", "")] + cells)
        allm = (d.get("flare") or {}).get("all") or {}
        if allm:
            flare.append([f"`{d.get('lens', '')}`"] + [num(allm.get(m)) if m in allm else "—" for m in ACC_METHODS])
    out = ("Exit position error in µm, median / p99, on rays valid under both the method and the tracer, and in "
           "brackets the IoU of the two valid masks (rays uniform over the map's domain); `neural` is the bundled "
           "model of the run's date.\n\n" + table(["lens", "map", "steps", *ACC_METHODS], rows))
    if flare:
        out += ("\nFlare spot diagrams of the same ghosts (a point light, the evaluated ghosts combined), MAPE against "
                "the tracer's:\n\n" + table(["lens", *ACC_METHODS], flare))
    return out + "\n" + "\n".join(r.source(n) for n in names)


def gpu_render_table(r: Results) -> str:
    return lens_render_table(r, r.gpu_render, "gpu/")


def lens_render_table(r: Results, runs: dict, folder: str) -> str:
    """One row per lens of ``runs`` (lens → bench_render.py's JSON, stored as ``<folder>render_<lens>.json``):
    thinlens, realistic_lens and neural_lens render times at each ``ray_kernel`` measured, their ratio."""
    if not runs:
        return "*No run stored.*\n"
    rows, some = [], None
    for lens, d in runs.items():
        some = some or d
        res = d.get("results", {})
        kernels = d.get("ray_kernels") or ["auto"]
        tag = lambda s, k: s if k == kernels[0] else f"{s}[{k}]"          # bench_render's row names
        cells = [f"`{lens}`", num(res.get("thinlens", {}).get("render_s"))]
        for s in ("realistic_lens", "neural_lens"):
            cells.append(" / ".join(num(res.get(tag(s, k), {}).get("render_s")) for k in kernels))
        for k in kernels:
            cells.append(ratio(div(res.get(tag("neural_lens", k), {}).get("render_s"),
                                   res.get(tag("realistic_lens", k), {}).get("render_s")), 3))
        fast = d.get("fastest", {})
        cells.append(ratio(div(res.get(fast.get("neural_lens"), {}).get("render_s"),
                               res.get(fast.get("realistic_lens"), {}).get("render_s")), 3))
        rows.append(cells)
    kernels = some.get("ray_kernels") or ["auto"]
    w, h = (some.get("resolution") or ["?", "?"])[:2]
    ks = " / ".join(kernels)
    head = (f"The {_scene(some.get('scene'))} at {w}×{h}, {some.get('spp', '?')} spp, {some.get('variant', '')}; each lens "
            f"sensor with `ray_kernel` {ks}; best of {some.get('repeats', '?')} renders after a warm-up.\n\n")
    header = ["lens", "thinlens s", f"realistic_lens s ({ks})", f"neural_lens s ({ks})"] + \
        [f"neural ÷ realistic, {k}" for k in kernels] + ["neural ÷ realistic, each at its faster"]
    return head + table(header, rows) + "\n" + _each_lens(r, f"{folder}render_", runs)


def _each_lens(r: Results, prefix: str, runs: dict) -> str:
    """The source line of a table with one run per lens: the first run's, its lens named as each lens in turn."""
    first = next(iter(runs))
    line = r.source(f"{prefix}{first}.json").replace(f"--lens {first}", "--lens LENS", 1)
    if line.startswith("*`"):
        end = line.index("`", 2) + 1              # after the command's code span
        line = line[:end] + " for each LENS of the table" + line[end:]
    return line


def gpu_mlp_table(r: Results) -> str:
    return lens_mlp_table(r, r.gpu_mlp, "gpu/", 1e3, "G")


def lens_mlp_table(r: Results, runs: dict, folder: str, scale: float, unit: str) -> str:
    """One row per lens of ``runs`` (lens → bench_mlp.py's JSON, stored as ``<folder>mlp_<lens>.json``): the exact
    tracer, the fused network and cooperative vectors in ``unit`` rays/s (M rays/s ÷ ``scale``); on CUDA (fp16
    cooperative vectors) their exit position x error against the fp32 network's."""
    if not runs:
        return "*No run stored.*\n"
    rows, some, fp16 = [], None, False
    for lens, d in runs.items():
        some = some or d
        rows_in = d.get("rows", {})
        ex = rows_in.get(EXACT_MLP, {}).get("mrays_per_s")
        fu = rows_in.get(FUSED_MLP, {}).get("mrays_per_s")
        co = rows_in.get(COOP_MLP, {})
        x = (co.get("diff_vs_cpu_style_per_output") or {}).get("x", {})
        fp16 = fp16 or (x.get("p99") is not None and folder == "gpu/")
        rows.append([f"`{lens}`", num(div(ex, scale)), num(div(fu, scale)), ratio(div(fu, ex), 2),
                     num(div(co.get("mrays_per_s"), scale)), ratio(div(co.get("mrays_per_s"), ex), 2),
                     num(1e3 * x["p99"], 2) if x.get("p99") is not None else "—"])
    head = (f"Each bundled camera map alone on {_pow2(some.get('rays'))} backward rays, "
            f"{some.get('variant') or 'llvm_ad_rgb'}, {some.get('threads', '?')} threads, best of 5")
    header = ["lens", f"exact tracer {unit} rays/s", f"learned, fused {unit} rays/s", "fused ÷ tracer",
              f"cooperative vectors {unit} rays/s", "coopvec ÷ tracer"]
    if fp16:
        head += ("; cooperative vectors run in fp16 on CUDA: their exit position x against the fp32 network's, in µm "
                 "(p99 over the rays that pass)")
        header.append("coopvec x error µm p99")
    else:
        rows = [row[:-1] for row in rows]
    return head + ".\n\n" + table(header, rows) + "\n" + _each_lens(r, f"{folder}mlp_", runs)


# ------------------------------------------------------------------------------------------------ comparisons
#: the sections of docs/performance.md the verdicts and README's headline link to (anchor -> heading)
SECTIONS = {"the-exact-tracer": "The exact tracer", "camera-rays": "Camera rays", "render-time": "Render time",
            "equal-samples-and-equal-time": "Equal samples and equal time", "lens-flare": "Lens flare",
            "the-learned-maps-accuracy": "The learned maps' accuracy", "baselines": "Baselines", "on-a-gpu": "On a GPU"}
#: a learned / exact ratio within this of 1 is "level": the benchmarks' run-to-run noise is of this order
LEVEL = 0.03


def comparisons(r: Results) -> list:
    """Every learned-against-exact figure the tables hold, one dict each: ``what``, ``value`` (learned ÷ exact: a
    number, or ``(lo, hi)`` over lenses or ghosts), ``higher`` (whether higher is better for the learned path),
    ``machine``, ``anchor`` (its table in docs/performance.md).  The verdicts and README's headline read these."""
    out = []

    def add(what, value, higher, name, anchor):
        if value is not None:
            out.append(dict(what=what, value=value, higher=higher, machine=r.short(name), anchor=anchor))

    if r.cpu_mlp:
        add("camera rays per second, the learned map ÷ the tracer", _mlp_ratios(r.cpu_mlp), True,
            f"mlp_{next(iter(r.cpu_mlp))}.json", "camera-rays")
    if r.cpu_render:
        add("render time, `neural_lens` ÷ `realistic_lens`", _render_ratios(r.cpu_render), False,
            f"render_{next(iter(r.cpu_render))}.json", "render-time")
    d = r.cpu.get("equal_time.json")
    if d:
        eq_spp, eq_t = [], []
        for L in d.get("lenses", []):
            real = {x["spp"]: x for x in L.get("renders", {}).get("realistic_lens", [])}
            for x in L.get("renders", {}).get("neural_lens", []):
                eq_spp.append(div(x.get("mape"), real.get(x["spp"], {}).get("mape")))
            eq_t += [div(t.get("mape_neural"), t.get("mape_realistic")) for t in L.get("equal_time", [])]
        add("image error (MAPE) at equal samples, `neural_lens` ÷ `realistic_lens`", _range(eq_spp), False,
            "equal_time.json", "equal-samples-and-equal-time")
        add("image error (MAPE) at equal render time, `neural_lens` ÷ `realistic_lens`", _range(eq_t), False,
            "equal_time.json", "equal-samples-and-equal-time")
    d = r.cpu.get("bench_flare.json")
    if d:
        add("flare samples per second, a learned ghost ÷ a traced one",
            _range([div(x.get("neural_pilot", {}).get("samples_per_s"), x.get("exact_pilot", {}).get("samples_per_s"))
                    for x in d.get("rows", [])]), True, "bench_flare.json", "lens-flare")
    if r.gpu_mlp:
        add("camera rays per second, the learned map ÷ the tracer", _mlp_ratios(r.gpu_mlp), True,
            f"gpu/mlp_{next(iter(r.gpu_mlp))}.json", "on-a-gpu")
    if r.gpu_render:
        add("render time, `neural_lens` ÷ `realistic_lens` (each at its faster `ray_kernel`)",
            _render_ratios(r.gpu_render), False, f"gpu/render_{next(iter(r.gpu_render))}.json", "on-a-gpu")
    return out


def _mlp_ratios(runs: dict):
    """The fused camera map's rate ÷ the tracer's, over the lenses of ``runs`` (lens → bench_mlp.py's JSON)."""
    return _range([div(x.get("rows", {}).get(FUSED_MLP, {}).get("mrays_per_s"),
                       x.get("rows", {}).get(EXACT_MLP, {}).get("mrays_per_s")) for x in runs.values()])


def _render_ratios(runs: dict):
    """neural_lens's render time ÷ realistic_lens's, each at its faster ``ray_kernel``, over the lenses of ``runs``
    (lens → bench_render.py's JSON)."""
    v = []
    for x in runs.values():
        res, fast = x.get("results", {}), x.get("fastest", {})
        v.append(div(res.get(fast.get("neural_lens", "neural_lens"), {}).get("render_s"),
                     res.get(fast.get("realistic_lens", "realistic_lens"), {}).get("render_s")))
    return _range(v)


def _range(values):
    vs = sorted(v for v in values if v is not None)
    return (vs[0], vs[-1]) if vs else None


def rnum(v) -> str:
    """A ratio for reading: two decimals near 1, two significant digits elsewhere (0.19, 1.37, 840)."""
    return f"{v:.2f}" if 0.995 <= v < 9.995 else num(v, 2)


def rspan(value) -> str:
    lo, hi = value if isinstance(value, tuple) else (value, value)
    a, b = rnum(lo), rnum(hi)
    return f"{a}×" if a == b else f"{a}–{b}×"


def verdict(c) -> str:
    lo, hi = c["value"] if isinstance(c["value"], tuple) else (c["value"], c["value"])
    if 1 - LEVEL <= lo and hi <= 1 + LEVEL:
        return f"level (within {LEVEL:.0%})"
    good = (lambda v: v > 1 + LEVEL) if c["higher"] else (lambda v: v < 1 - LEVEL)
    bad = (lambda v: v < 1 - LEVEL) if c["higher"] else (lambda v: v > 1 + LEVEL)
    if good(lo) and good(hi):
        return "**the learned path is better**"
    if bad(lo) and bad(hi):
        return "**the tracer is better**"
    return "mixed"


def verdicts(r: Results) -> str:
    """One line per comparison: where the learned path is faster or more accurate than the tracer, where not."""
    lines = [f"* {c['machine']}: {c['what']}: **{rspan(c['value'])}** ({'higher' if c['higher'] else 'lower'} is "
             f"better for the learned path): {verdict(c)}. [{SECTIONS[c['anchor']]}](#{c['anchor']})"
             for c in comparisons(r)]
    gate, _ = _gates()
    tot = {k: sum(ghost_counts(ev)[k] for ev in r.evals.values()) for k in ("maps", "edges_learned", "edges_traced", "learned")}
    if tot["maps"]:
        within = tot["edges_learned"] + tot["edges_traced"]
        lines.append(f"* Bundled models: {within} of their {tot['maps']} ghost maps are within {gate:g} of the tracer "
                     f"(verified flare error); on a CPU `auto` learns {tot['learned']}, and traces the "
                     f"{within - tot['learned']} that cost more learned than traced"
                     + (f" and the {tot['maps'] - within} outside the gate" if tot["maps"] > within else "")
                     + ". [The learned maps' accuracy](#the-learned-maps-accuracy)")
    return "\n".join(lines) + "\n"


def headline(r: Results) -> str:
    """README's table: the figures a user asks first, each from the same JSON as docs/performance.md."""
    rows = []
    d = r.cpu.get("bench_tracer.json")
    if d:
        tr = [x.get("mrays_per_s") for x in d.get("rows", []) if x.get("path") == "transmit"]
        sp = [x.get("speedup") for x in d.get("rows", []) if "speedup" in x]
        rows.append(["the exact tracer, camera rays", f"{span(tr)} M rays/s, {rspan(_range(sp))} optiland's",
                     r.short("bench_tracer.json"), "the-exact-tracer"])
    for c in comparisons(r):
        rows.append([c["what"], rspan(c["value"]), c["machine"], c["anchor"]])
    cams = [camera_record(ev).get("regressor", {}).get("position_um_median")
            for ev in r.evals.values()]
    if any(v is not None for v in cams):
        rows.append(["the bundled camera maps' exit position error, held-out median", span(cams, unit=" µm"),
                     "bundled models", "the-learned-maps-accuracy"])
    return table(["", "figure", "machine", "details"],
                 [[w, v, m, f"[{SECTIONS[a]}](docs/performance.md#{a})"] for w, v, m, a in rows])


def pages(r: Results | None = None) -> dict:
    """{page: {block name: body}}: every block this script writes."""
    r = r or Results()
    return {PERF_PAGE: {"verdicts": verdicts(r), "tracer": tracer_table(r), "camera-rays": mlp_table(r),
                        "tanh": tanh_table(r),
                        "render": render_table(r), "equal-time": equal_time_table(r), "flare": flare_table(r),
                        "starburst": starburst_table(r), "coatings": coatings_table(r),
                        "maps": maps_table(r), "zoom": zoom_table(r), "zoom-640": zoom_table(r, "bench_zoom_640.json"),
                        "zoom-gpu": zoom_table(r, "gpu/bench_zoom.json"),
                        "focus": zoom_table(r, "bench_focus.json"), "baselines-speed": baselines_speed_table(r),
                        "baselines-accuracy": baselines_accuracy_table(r), "gpu-render": gpu_render_table(r),
                        "gpu-camera-rays": gpu_mlp_table(r)},
            README: {"headline": headline(r)}}


# ------------------------------------------------------------------------------------------------ taking a run
def amd_generation(family: int, model: int) -> str:
    """The Zen generation of an AMD CPU from its cpuid family and model (``cpu family``, ``model`` in
    /proc/cpuinfo), which a virtual machine's bare "AMD EPYC" model name leaves out and the maps' speed against the
    tracer depends on (Zen 4 runs AVX-512 on 256-bit units, Zen 5 on 512-bit ones): family 26 is Zen 5; family 25
    Zen 4 at models 0x10-0x1f, 0x60-0x7f and 0xa0-0xaf, else Zen 3; family 23 Zen 2 from model 0x30, else Zen or
    Zen+; "" for any other family."""
    if family == 26:
        return "Zen 5"
    if family == 25:
        return "Zen 4" if 0x10 <= model <= 0x1f or 0x60 <= model <= 0x7f or 0xa0 <= model <= 0xaf else "Zen 3"
    if family == 23:
        return "Zen 2" if model >= 0x30 else "Zen/Zen+"
    return ""


def detect_machine() -> tuple:
    """(long, short) words for this machine: CPU model (with its Zen generation on AMD), cores, AVX-512 or AVX2,
    OS."""
    model, flags, ids = platform.processor() or platform.machine(), "", {}
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as f:
            for line in f:
                key, _, value = (part.strip() for part in line.partition(":"))
                if key == "model name" and model in ("", platform.machine(), platform.processor()):
                    model = value
                elif key == "flags" and not flags:
                    flags = " " + value
                elif key in ("cpu family", "model") and key not in ids and value.isdigit():
                    ids[key] = int(value)
    except OSError:
        pass
    simd = "AVX-512" if " avx512f" in flags else "AVX2" if " avx2" in flags else ""
    zen = amd_generation(ids["cpu family"], ids["model"]) if "AMD" in model and len(ids) == 2 else ""
    if zen and "Zen" not in model:
        model = f"{model} {zen}"
    n = os.cpu_count() or 0
    long = f"{n}-core {model}" + (f" ({simd})" if simd else "") + f", {platform.system()}"
    return long, f"{n}-core CPU"


def _software(d: dict) -> str:
    """What a benchmark's JSON says of its software: Mitsuba / Dr.Jit versions, variant, threads."""
    m = d.get("machine") if isinstance(d.get("machine"), dict) else {}
    parts = []
    if m.get("python"):
        parts.append(f"Python {m['python']}")
    if m.get("mitsuba") or m.get("drjit"):
        parts.append(f"Mitsuba {m.get('mitsuba', '?')} / Dr.Jit {m.get('drjit', '?')}")
    if d.get("variant"):
        parts.append(str(d["variant"]))
    threads = d.get("threads") or (d.get("info") or {}).get("drjit_threads")
    if threads:
        parts.append(f"{threads} Dr.Jit threads")
    return "".join(f", {p}" for p in parts)


def _commit() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True,
                              check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return ""


def take_run(src: str, names: list, dest: str, machine: tuple, command_of) -> list:
    """Copy ``names`` found in ``src`` into ``dest`` (as written) and record their source; returns those copied."""
    os.makedirs(dest, exist_ok=True)
    spath = os.path.join(PERF, "sources.json")
    sources = _load(spath) if os.path.exists(spath) else {"files": {}}
    today, commit, took = datetime.date.today().isoformat(), _commit(), []
    for n in names:
        p = os.path.join(src, n)
        if not os.path.isfile(p):
            continue
        shutil.copyfile(p, os.path.join(dest, n))
        key = os.path.relpath(os.path.join(dest, n), PERF).replace(os.sep, "/")
        d = _load(p)
        sources["files"][key] = {"command": command_of(n, d), "machine": machine[0] + _software(d),
                                 "machine_short": machine[1], "measured": today, "commit": commit}
        took.append(key)
    with open(spath + ".tmp", "w", encoding="utf-8") as f:
        json.dump(sources, f, indent=1, ensure_ascii=False)
        f.write("\n")
    os.replace(spath + ".tmp", spath)
    return took


def _cpu_command(name, d):
    for prefix, script in (("mlp_", "bench_mlp"), ("render_", "bench_render")):
        if name.startswith(prefix):          # the Makefile's per-lens runs: the command line without --out
            cmd = d.get("command") if isinstance(d.get("command"), str) else ""
            return cmd.split(" --out ")[0] or f"python benchmarks/{script}.py --lens {name[len(prefix):-5]}"
    if isinstance(d.get("command"), str) and d["command"].strip():
        cmd = d["command"].split(" --out ")[0]
        return cmd if not name.startswith("accuracy_") else cmd + " --out out/bench"
    return DEFAULT_COMMANDS.get(name, "")


def _gpu_machine(src: str) -> tuple:
    """The GPU of a gpu_suite.sh run, from its gpu.txt (nvidia-smi's name and driver); the JSON adds the rest."""
    gpu, driver = "GPU", ""
    p = os.path.join(src, "gpu.txt")
    if os.path.exists(p):
        lines = [ln for ln in open(p, encoding="utf-8").read().splitlines() if ln.strip()]
        if len(lines) > 1:
            cells = [c.strip() for c in lines[1].split(",")]
            gpu, driver = cells[0], cells[2] if len(cells) > 2 else ""
    return gpu + (f" (driver {driver})" if driver else ""), gpu


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--from", dest="src", help="copy a CPU run's JSON from this folder first (make bench: out/bench)")
    ap.add_argument("--gpu-from", help="copy a GPU run's render_*.json, mlp_*.json, bench_zoom.json and gpu.txt from "
                                       "this folder first")
    ap.add_argument("--machine", help="the machine of the run taken, in words (default: read from this machine)")
    ap.add_argument("--check", action="store_true", help="write nothing; exit 1 if a generated block differs")
    a = ap.parse_args(argv)
    if a.src:
        names = list(CPU_FILES) + sorted(os.path.basename(p) for p in glob.glob(os.path.join(a.src, "*.json"))
                                         if os.path.basename(p).startswith(("accuracy_", "mlp_", "render_",
                                                                            "starburst_", "coatings_")))
        m = (a.machine, a.machine.split(",")[0]) if a.machine else detect_machine()
        print("took", ", ".join(take_run(a.src, names, PERF, m, _cpu_command)) or "nothing")
    if a.gpu_from:
        names = sorted(os.path.basename(p) for p in glob.glob(os.path.join(a.gpu_from, "*.json"))
                       if os.path.basename(p).startswith(("render_", "mlp_")) or os.path.basename(p) == "bench_zoom.json")
        m = (a.machine, a.machine.split(",")[0]) if a.machine else _gpu_machine(a.gpu_from)
        took = take_run(a.gpu_from, names, os.path.join(PERF, "gpu"), m,
                        lambda n, d: d.get("command", "").split(" --out ")[0] or "bash benchmarks/gpu_suite.sh bench")
        for extra in ("gpu.txt", "setup.txt"):
            if os.path.isfile(os.path.join(a.gpu_from, extra)):
                shutil.copyfile(os.path.join(a.gpu_from, extra), os.path.join(PERF, "gpu", extra))
        print("took", ", ".join(took) or "nothing")
    changed = write_pages(pages(), check=a.check)
    for p in changed:
        print(("differs: " if a.check else "wrote ") + p)
    return 1 if a.check and changed else 0


if __name__ == "__main__":
    sys.exit(main())
