"""``mi-neurallens accuracy LENS``: the baselines (ABCD, Taylor polynomial optics, fitted sparse
polynomials) and the neural maps against the exact tracer.

Per path and method: exit-position error (µm) and direction error (arcsec), median and p99, on rays valid
under both; relative throughput error; valid-mask IoU against the tracer; eval_dr rays/s on this CPU and a
FLOP estimate.  Then flare spot-diagram images of a point light per method and their MAPE against the
exact tracer (per ghost and for all evaluated ghosts combined; the transmit path's sharp spot is left
out, as in the paper's ghost comparison), beside the paper's numbers.  Writes
``accuracy_<lens>.json`` and ``accuracy_<lens>.md`` to ``--out`` and the figure to ``--figure``.
Ghost paths are always forward (they are flare paths); ``--direction`` applies to ``transmit``.
"""
from __future__ import annotations

import json
import os
import platform
import time


def add_parser(subparsers):
    p = subparsers.add_parser("accuracy", help="baselines vs neural vs exact: accuracy and cost tables",
                              description=__doc__.split("\n\n", 1)[1] if __doc__ else None)
    p.add_argument("lens", help="bundled lens name or prescription file")
    p.add_argument("--paths", default="transmit,ghosts",
                   help="comma list: transmit, ghosts (the top --ghosts by energy plus the shortest and longest "
                        "of the top ones), or integer path ids (default transmit,ghosts)")
    p.add_argument("--direction", choices=("backward", "forward"), default="backward",
                   help="direction of the transmit map (default backward, the camera map)")
    p.add_argument("--ghosts", type=int, default=2, help="number of most energetic ghosts (default 2)")
    p.add_argument("--methods", default=",".join(("abcd", "taylor3", "taylor5", "taylor5-ap", "fitted", "neural")),
                   help="comma list of abcd, taylor3, taylor5, taylor3-ap, taylor5-ap, fitted, neural")
    p.add_argument("--n", type=int, default=20000, help="rays per evaluation set (default 20000)")
    p.add_argument("--time-rays", type=int, default=1 << 18, help="rays for the eval_dr timing (default 262144)")
    p.add_argument("--flare-n", type=int, default=200_000, help="rays per wavelength for flare images (0: skip)")
    p.add_argument("--fitted-valid", default="auto", help="fitted validity: auto, classifier, aperture, all")
    p.add_argument("--seed", type=int, default=4242)
    p.add_argument("--out", default=os.path.join("out", "accuracy"), help="output folder (default out/accuracy)")
    p.add_argument("--figure", help="flare figure path (default <out>/baseline_flare_<lens>.png)")
    p.set_defaults(func=run)
    return p


def _paths(lens, spec, k, model):
    from ..baselines.accuracy import pick_ghosts
    out, short, long_ = [], None, None
    for w in [s.strip() for s in spec.split(",") if s.strip()]:
        if w == "transmit":
            out.append(("transmit", 0))
        elif w == "ghosts":
            g, short, long_ = pick_ghosts(lens, k, model)
            out += [("ghost", p) for p in g]
        else:
            out.append(("ghost" if int(w) else "transmit", int(w)))
    return out, short, long_


def run(args):
    from ..baselines.accuracy import PAPER_MAPE, evaluate_path, flare_images, save_flare_figure
    from ..baselines.common import bundled_model
    from ..optics.prescription import Lens
    from ..trace.paths import ghost_surfaces
    from ..fileio import atomic_write_text, jsonable
    lens = Lens.load(args.lens)
    model = bundled_model(lens)
    methods = tuple(m.strip() for m in args.methods.split(",") if m.strip())
    paths, short, long_ = _paths(lens, args.paths, args.ghosts, model)
    t0 = time.time()
    doc = {"lens": lens.name, "fingerprint": lens.fingerprint(), "command": "mi-neurallens accuracy " + " ".join(
        _argv(args)), "machine": f"{platform.machine()} {platform.processor() or ''} {os.cpu_count()} CPUs".strip(),
        "neural_model": None if model is None else sorted(model.maps), "paths": {}}
    print(f"{lens.name}: paths {[p for _, p in paths]} (short ghost {short}, long ghost {long_})", flush=True)
    fitted_opts = {"valid": args.fitted_valid}
    for kind, pid in paths:
        direction = args.direction if kind == "transmit" else "forward"
        r = evaluate_path(lens, pid, direction, methods, n=args.n, seed=args.seed, time_rays=args.time_rays,
                          model=model, fitted_opts=fitted_opts,
                          log=lambda s: print(s, flush=True))
        r["describe"] = "transmit" if pid == 0 else "ghost a={}, b={}".format(*ghost_surfaces(pid))
        doc["paths"][f"{direction}.{pid}"] = r
    flare = None
    ghost_ids = [p for k, p in paths if k == "ghost"]
    if args.flare_n > 0 and ghost_ids:
        fpaths = ghost_ids
        fm = tuple(m for m in methods if m != "taylor5-ap" and m != "taylor3-ap")
        flare = flare_images(lens, fpaths, fm, n=args.flare_n, model=model, fitted_opts=fitted_opts)
        doc["flare"] = {k: v for k, v in flare.items() if not k.startswith(("images", "all_images"))}
        doc["paper_mape"] = PAPER_MAPE.get(lens.name)
        if short is not None:
            fig = args.figure or os.path.join(args.out, f"baseline_flare_{lens.name}.png")
            save_flare_figure(flare, lens.name, short, long_, fig, fm)
            doc["figure"] = fig
            print(f"wrote {fig}")
    doc["seconds"] = time.time() - t0
    md = markdown(doc, short, long_)
    os.makedirs(args.out, exist_ok=True)
    jp = os.path.join(args.out, f"accuracy_{lens.name}.json")
    mp = os.path.join(args.out, f"accuracy_{lens.name}.md")
    atomic_write_text(jp, json.dumps(jsonable(doc), indent=1))
    atomic_write_text(mp, md)
    print(md)
    print(f"wrote {jp} and {mp}")
    return 0


def _argv(args):
    out = [args.lens, "--paths", args.paths, "--direction", args.direction, "--ghosts", str(args.ghosts),
           "--n", str(args.n), "--flare-n", str(args.flare_n)]
    if args.methods != ",".join(("abcd", "taylor3", "taylor5", "taylor5-ap", "fitted", "neural")):
        out += ["--methods", args.methods]
    if args.fitted_valid != "auto":
        out += ["--fitted-valid", args.fitted_valid]
    return out


def _g(v, fmt="{:.3g}"):
    return "—" if v is None else fmt.format(v)


def markdown(doc, short=None, long_=None) -> str:
    lines = [f"# Baseline accuracy: `{doc['lens']}`", "", f"`{doc['command']}` ({doc['machine']})", "",
             "Errors on rays valid under both the method and the tracer; IoU of the valid masks on rays uniform "
             "over the map's domain; rays/s of `eval_dr` (LLVM, float32).", "",
             "| path | steps | valid frac | method | pos µm med | pos µm p99 | dir ″ med | dir ″ p99 | T rel med | "
             "T rel p99 | IoU | Mrays/s | FLOPs/ray |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for key, r in doc["paths"].items():
        first = True
        for name, m in r["methods"].items():
            lab = f"{key} ({r['describe']})" if first else ""
            st = str(r["steps"]) if first else ""
            vf = f"{r['valid_fraction']:.3f}" if first else ""
            first = False
            if name == "exact":
                lines.append(f"| {lab} | {st} | {vf} | exact | 0 | 0 | 0 | 0 | 0 | 0 | 1 | "
                             f"{m['rays_per_s'] / 1e6:.2f} | — |")
                continue
            lines.append(f"| {lab} | {st} | {vf} | {name} | {_g(m['position_um_median'])} | {_g(m['position_um_p99'])} | "
                         f"{_g(m['direction_arcsec_median'])} | {_g(m['direction_arcsec_p99'])} | "
                         f"{_g(m['throughput_rel_median'])} | {_g(m['throughput_rel_p99'])} | {m['iou']:.3f} | "
                         f"{m['rays_per_s'] / 1e6:.2f} | {_g(m['flops_per_ray'], '{:d}')} |")
    fl = doc.get("flare")
    if fl:
        names = sorted({n for d in fl["mape"].values() for n in d}, key=lambda s: (s != "abcd", s))
        lines += ["", f"## Flare spot-diagram image MAPE vs exact (point light {fl['field_deg']:.1f}° off axis, "
                  f"{fl['n_rays']} rays per wavelength at {', '.join(str(int(w)) for w in fl['wavelengths'])} nm, "
                  f"{fl['half_extent_mm']:.1f} mm half extent)", "",
                  "Weights: Fresnel throughput / 1 (geometric: the paper's protocol, Fresnel off).  MAPE: "
                  "`metrics.mape_masked` (luminance over the pixels above 1 % of the reference's peak); every "
                  "method sees the same rays, so this is map error, not noise.", "",
                  "| image | " + " | ".join(names) + " |", "|---|" + "---|" * len(names)]
        for pid in fl["paths"]:
            tag = " (short)" if pid == short else (" (long)" if pid == long_ else "")
            lines.append(f"| path {pid}{tag} | " + " | ".join(
                f"{_g(fl['mape'][pid].get(n))} / {_g(fl['mape_geometric'][pid].get(n))}" for n in names) + " |")
        lines.append("| all evaluated ghosts (sum) | " + " | ".join(
            f"{_g(fl['all'].get(n))} / {_g(fl['all_geometric'].get(n))}" for n in names) + " |")
        pp = doc.get("paper_mape")
        if pp:
            lines += ["", "Paper (flare renders, Fresnel off): all paths Poly {} vs neural {}; single path {} Poly {} vs "
                      "neural {}.".format(pp["all paths"]["poly"], pp["all paths"]["neural"], pp["single path"]["path"],
                                          pp["single path"]["poly"], pp["single path"]["neural"])]
    lines += ["", f"({doc['seconds']:.0f} s)"]
    return "\n".join(lines) + "\n"
