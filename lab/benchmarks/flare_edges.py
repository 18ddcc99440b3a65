"""Where a ghost map's flare error sits: inside the ghost or on its edge.

    python benchmarks/flare_edges.py wide-22mm 192 [288 ...|all] [--model FILE] [--samples 24]
                                     [--reference 28] [--json OUT] [--set fstop=5.4 --set blades=6]
                                     [--boundary-band B] [--light X,Y] [--attribute]

Renders each ghost of ``scenes/night_point.xml`` alone, exactly and with its neural map *with the same samples*
(``pilot_with = "exact"``, same seed: common random numbers, so Monte Carlo noise cancels), then splits
the pixels of the flare MAPE mask (luminance above 1 % of the exact image's peak) into the interior
(pixels at least 2 pixels inside the mask) and the edge (the rest), and prints the MAPE of each and the
share of the total error that comes from the edge.  An error that lives on the edge comes from rays near
the validity boundary (the classifier); an error inside comes from the regressor.

Because the noise cancels, the paired MAPE converges to the map's own error as the sample count grows:
it is the per-ghost number of the goal "each shipped ghost ≤ 0.01 against a converged exact reference"
once it no longer falls with 4× the samples.  ``--reference K`` also renders an exact reference with
2^K samples (another seed) and reports the plain (independent) MAPE of the neural and of the exact
render against it: the exact one is the test budget's noise floor.  ``--set KEY=VALUE`` sets a property
of the scene's ``neural_lens`` (e.g. ``fstop``, ``blades``: the learned ghosts then test the iris on
their predicted stop crossings).  ``--combined`` adds one row with every listed ghost at once
(``--combined-only``: just that row).  ``--boundary-band B``: the learned renders trace their samples within ±B of
a classifier's decision (the flare's ``boundary_band``).
"""
from __future__ import annotations

import argparse
import os
import sys


ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("lens")
    ap.add_argument("ghosts", nargs="+", help="ghost path ids, or 'all' (every ghost the model has a map for)")
    ap.add_argument("--model", help="model file (default: the bundled model of the lens)")
    ap.add_argument("--samples", type=int, default=24, help="log2 samples")
    ap.add_argument("--reference", type=int, default=0, help="log2 samples of an independent exact reference (0: none)")
    ap.add_argument("--json", help="write the rows here")
    ap.add_argument("--set", dest="sets", action="append", default=[], metavar="KEY=VALUE",
                    help="neural_lens property (repeatable), e.g. --set fstop=5.4 --set blades=6")
    ap.add_argument("--combined", action="store_true", help="also render all listed ghosts together")
    ap.add_argument("--combined-only", action="store_true", help="only the row with all listed ghosts together")
    ap.add_argument("--boundary-band", type=float, default=0.0,
                    help="the learned renders' boundary_band (samples at a classifier's edge traced exactly)")
    ap.add_argument("--iris-band", type=float, default=None,
                    help="the learned renders' iris_band (samples at the iris's edge traced exactly; default: "
                         "--boundary-band)")
    ap.add_argument("--light", metavar="X,Y",
                    help="the point light's position (m, at z = 5 m; default: the scene's, 0.9,0.45)")
    ap.add_argument("--attribute", action="store_true",
                    help="also render the two hybrids (exact validity + learned exit rays, learned validity + exact "
                         "exit rays) that split the error between the regressor and the classifier")
    a = ap.parse_args(argv)
    import mitsuba as mi
    sys.path.insert(0, ROOT)
    from mi_neurallens.render_utils import default_variant
    mi.set_variant(default_variant())
    from scipy.ndimage import binary_erosion
    from mi_neurallens.commands.render import load_scene
    from mi_neurallens.fileio import atomic_write_json
    from mi_neurallens.flare.render import FlareOptions, render_flare
    from mi_neurallens.flare.verify import paired_renders
    from mi_neurallens.metrics import LUMINANCE, flare_error_map, mape_masked
    from mi_neurallens.neural.model import bundled_model_path, load_model
    HybridFlare = _hybrid_renderer()
    model = a.model or bundled_model_path(a.lens)
    ghosts = load_model(model).ghost_ids if a.ghosts == ["all"] else [int(g) for g in a.ghosts]
    scene = load_scene(os.path.join(ROOT, "scenes", "night_point.xml"), variant=default_variant(), lens=a.lens,
                       sensor_type="neural_lens", sets=[f"model={model}"] + a.sets,
                       params=[] if not a.light else [f"light_x={a.light.split(',')[0]}",
                                                      f"light_y={a.light.split(',')[1]}"])
    n = 1 << a.samples
    rows = []
    for g in ([] if a.combined_only else ghosts) + (["all"] if a.combined or a.combined_only else []):
        gl = ghosts if g == "all" else [g]
        ex, ne, _ = paired_renders(scene, gl, n, seed=1, boundary_band=a.boundary_band,
                                   iris_band=a.iris_band)   # `evaluate --flare`'s protocol
        rel, mask = flare_error_map(ne, ex)
        if not mask.any():      # the stop blocks this ghost entirely (or it leaves the film): nothing to compare
            rows.append(dict(ghost=g, log2_samples=a.samples, pixels=0,
                             exact_flux=float(ex[..., :3].sum()), neural_flux=float(ne[..., :3].sum())))
            print(f"{a.lens} ghost {g}{' '.join([''] + a.sets)}: no pixel above the threshold in the exact "
                  f"render (flux exact {rows[-1]['exact_flux']:.3g}, neural {rows[-1]['neural_flux']:.3g})", flush=True)
            continue
        yn, ye = ne[..., :3] @ LUMINANCE, ex[..., :3] @ LUMINANCE
        inner = binary_erosion(mask, iterations=2) & mask
        edge = mask & ~inner
        row = dict(ghost=g, log2_samples=a.samples, mape=float(rel[mask].mean()), pixels=int(mask.sum()),
                   interior=float(rel[inner].mean()), interior_pixels=int(inner.sum()),
                   edge=float(rel[edge].mean()), edge_pixels=int(edge.sum()),
                   edge_share=float(rel[edge].sum() / rel[mask].sum()), flux_ratio=float(yn.sum() / ye.sum()))
        attribution = ""
        if a.attribute:
            for which, label in (("regressor", "learned exit rays"), ("classifier", "learned validity")):
                hy = HybridFlare(scene, 0, FlareOptions(ghosts=gl, samples=n, mode="neural", pilot_with="exact"),
                                 learned=which).render(seed=1).total
                r2, m2 = flare_error_map(hy, ex)
                row[which] = dict(mape=float(r2[m2].mean()), interior=float(r2[inner & m2].mean()),
                                  edge=float(r2[edge & m2].mean()))
                attribution += (f"; {label} only: MAPE {row[which]['mape']:.4f} (interior {row[which]['interior']:.4f}, "
                                f"edge {row[which]['edge']:.4f})")
        line = attribution
        if a.reference:
            ref = render_flare(scene, seed=101, ghosts=gl, samples=1 << a.reference, mode="exact").total
            row.update(reference_log2_samples=a.reference, independent=float(mape_masked(ne, ref)),
                       exact_floor=float(mape_masked(ex, ref)))
            line += (f"; independent vs a 2^{a.reference} exact reference: neural {row['independent']:.4f}, "
                    f"exact (noise floor) {row['exact_floor']:.4f}")
        row["boundary_band"] = a.boundary_band
        row["iris_band"] = a.boundary_band if a.iris_band is None else a.iris_band
        rows.append(row)
        print(f"{a.lens} ghost {g}{' '.join([''] + a.sets)}, 2^{a.samples} samples, paired: MAPE {row['mape']:.4f} over {row['pixels']} px; "
              f"interior {row['interior']:.4f} ({row['interior_pixels']} px), edge {row['edge']:.4f} "
              f"({row['edge_pixels']} px), edge share of the error {row['edge_share']:.2f}; flux ratio "
              f"neural/exact {row['flux_ratio']:.4f}" + line, flush=True)
    if a.json:
        atomic_write_json(a.json, dict(lens=a.lens, model=os.path.relpath(model, ROOT), rows=rows,
                                       command="python " + " ".join([os.path.relpath(__file__, ROOT)] + (argv or sys.argv[1:]))))


def _hybrid_renderer():
    """A :class:`FlareRenderer` whose learned evaluators take one half from the tracer (see ``--attribute``)."""
    import drjit as dr
    from mi_neurallens.flare.render import FlareRenderer

    class Hybrid:
        """A ghost evaluator that keeps one learned ``part`` ("regressor" or "classifier") and takes the
        other from the tracer, on the same rays."""
        kind = "neural"
        band = 0.0                                  # no boundary_band: both halves are whole (GhostStats.band)

        def __init__(self, exact, learned, part):
            self.exact, self.learned, self.part, self.map, self.pid = exact, learned, part, learned.map, learned.pid

        def __call__(self, o, d, lam, active):
            ve, xe, ye, te, _ = self.exact(o, d, lam, active)
            vn, xn, yn, tn, _ = self.learned(o, d, lam, active)   # the learned half without boundary_band
            if self.part == "regressor":            # the tracer decides validity, the regressor where rays go
                return ve, xn, yn, tn, None
            # the classifier decides validity; where the tracer has an exit ray (valid rays), it is used
            return vn, dr.select(ve, xe, xn), dr.select(ve, ye, yn), dr.select(ve, te, tn), None

    class HybridFlare(FlareRenderer):
        def __init__(self, scene, sensor, opts, learned):
            super().__init__(scene, sensor, opts)
            self.learned = learned

        def evaluator(self, pid):
            ev = super().evaluator(pid)
            return Hybrid(self.exact_evaluator(pid), ev, self.learned) if ev.kind == "neural" else ev

    return HybridFlare


if __name__ == "__main__":
    main()
