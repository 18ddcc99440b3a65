"""``mi-neurallens demo``: the side-by-side demo on the bundled defaults, from the installed package.

The 22 mm lens (``wide-22mm``): its paraxial data, its layout drawn with traced ray fans, and the bundled
still life rendered three times — a converged exact reference (``realistic_lens``), the exact tracer and the
learned map (``neural_lens``) at equal samples — side by side with their error against the reference (MAPE,
relMSE) and their render times.  Writes into ``--out`` (default ``out/demo``): ``wide-22mm-layout.png``,
``compare.png``, ``compare.md`` / ``compare.json`` and the three images as EXR and PNG.  About 2–3 minutes on
two CPU cores at the defaults, most of it the reference.
"""
from __future__ import annotations

import os
import sys

from ..render_utils import add_variant_argument


def add_parser(subparsers):
    p = subparsers.add_parser("demo", help="the side-by-side demo (exact vs learned lens) on the bundled defaults",
                              description=__doc__.split("\n\n", 1)[1])
    p.add_argument("--out", "-o", default=os.path.join("out", "demo"), help="output folder (default: out/demo)")
    p.add_argument("--lens", default="wide-22mm", help="a lens with a model (default: wide-22mm)")
    p.add_argument("--spp", type=int, default=64, help="samples per pixel of the two test renders (64)")
    p.add_argument("--reference-spp", type=int, default=1024, help="samples per pixel of the reference (1024)")
    p.add_argument("--resolution", help="film size WxH (default: the scene's, 320x240)")
    add_variant_argument(p)
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.set_defaults(func=run)
    return p


def run(args) -> int:
    from ..cli import main
    os.makedirs(args.out, exist_ok=True)
    steps = [
        ["lens", "info", args.lens],
        ["lens", "plot", args.lens, "-o", os.path.join(args.out, f"{args.lens}-layout.png")],
        ["compare", "still_life", "--lens", args.lens, "--spp", str(args.spp), "--reference-spp",
         str(args.reference_spp), "--out", args.out, "--variant", args.variant]
        + (["--resolution", args.resolution] if args.resolution else [])
        + (["--no-progress"] if args.no_progress else []),
    ]
    for step in steps:
        print(f"$ mi-neurallens {' '.join(step)}", file=sys.stderr, flush=True)
        rc = main(step)
        if rc:
            return rc
    print(f"side by side: {os.path.join(args.out, 'compare.png')} (table: {os.path.join(args.out, 'compare.md')})")
    return 0
