"""Where a ghost map's flare error sits: inside the ghost or on its edge.

    python benchmarks/flare_edges.py wide-22mm 192 [--model FILE] [--samples 24]

Renders one ghost of ``scenes/night_point.xml`` exactly and with the neural map *with the same samples*
(``pilot_with = "exact"``, same seed: common random numbers, so Monte Carlo noise cancels), then splits
the pixels of the flare MAPE mask (luminance above 1 % of the exact image's peak) into the interior
(pixels at least 2 pixels inside the mask) and the edge (the rest), and prints the MAPE of each and the
share of the total error that comes from the edge.  An error that lives on the edge comes from rays near
the validity boundary (the classifier); an error inside comes from the regressor.
"""
from __future__ import annotations

import argparse
import os

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("lens")
    ap.add_argument("ghost", type=int)
    ap.add_argument("--model", help="model file (default: the bundled model of the lens)")
    ap.add_argument("--samples", type=int, default=24, help="log2 samples")
    a = ap.parse_args(argv)
    import mitsuba as mi
    mi.set_variant("llvm_ad_rgb")
    from scipy.ndimage import binary_erosion
    from mi_neurallens.commands.render import load_scene
    from mi_neurallens.flare.render import render_flare
    from mi_neurallens.metrics import FLARE_EPS_REL, FLARE_MASK_REL, LUMINANCE
    scene = load_scene(os.path.join(ROOT, "scenes", "night_point.xml"), variant="llvm_ad_rgb", lens=a.lens,
                       sensor_type="neural_lens", sets=[f"model={a.model or a.lens}"])
    n = 1 << a.samples
    ex = render_flare(scene, seed=1, ghosts=[a.ghost], samples=n, mode="exact").total
    ne = render_flare(scene, seed=1, ghosts=[a.ghost], samples=n, mode="neural", pilot_with="exact").total
    yn, ye = ne[..., :3] @ LUMINANCE, ex[..., :3] @ LUMINANCE
    mx = float(ye.max())
    mask = ye > FLARE_MASK_REL * mx
    rel = np.abs(yn - ye) / (np.abs(ye) + FLARE_EPS_REL * mx)
    inner = binary_erosion(mask, iterations=2) & mask
    edge = mask & ~inner
    print(f"{a.lens} ghost {a.ghost}, 2^{a.samples} samples, paired: MAPE {rel[mask].mean():.4f} over {mask.sum()} px; "
          f"interior {rel[inner].mean():.4f} ({inner.sum()} px), edge {rel[edge].mean():.4f} ({edge.sum()} px), "
          f"edge share of the error {rel[edge].sum() / rel[mask].sum():.2f}; flux ratio neural/exact "
          f"{yn.sum() / ye.sum():.4f}")


if __name__ == "__main__":
    main()
