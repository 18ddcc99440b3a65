"""``python -m mi_neurallens.optics.formats`` — convert lens files and regenerate the bundled lenses.

    python -m mi_neurallens.optics.formats convert-bundled /path/to/lens-data [--out DIR]
    python -m mi_neurallens.optics.formats convert INPUT OUTPUT.json [--name NAME]
    python -m mi_neurallens.optics.formats list
"""
from __future__ import annotations

import argparse
import sys

from ...errors import LensError
from ... import resources
from . import BUNDLED, bundled_lenses, convert_bundled, convert_file


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m mi_neurallens.optics.formats", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    b = sub.add_parser("convert-bundled", help="regenerate the bundled lenses' JSON from the shared lens data folder")
    b.add_argument("source_dir", help="folder holding pbrt/, open-optical-designer/, other/")
    b.add_argument("--out", default=None, help=f"output folder (default: {resources.bundled_library().path})")
    c = sub.add_parser("convert", help="convert one file (any supported format) to project JSON")
    c.add_argument("input")
    c.add_argument("output")
    c.add_argument("--name", default=None)
    sub.add_parser("list", help="list the bundled lenses")
    a = ap.parse_args(argv)
    try:
        if a.cmd == "convert-bundled":
            for name, path in convert_bundled(a.source_dir, a.out).items():
                print(f"{name:22s} <- {BUNDLED[name]['file']:48s} -> {path}")
        elif a.cmd == "convert":
            convert_file(a.input, a.output, name=a.name)
            print(f"wrote {a.output}")
        else:
            print("\n".join(bundled_lenses()))
    except LensError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
