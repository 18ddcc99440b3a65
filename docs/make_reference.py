"""Write the reference parts of the docs from the code and the package data, so that they cannot drift:

* each plugin's parameter table, from its docstring (the ``DOC`` string of ``mi_neurallens/sensors/realistic_lens.py``,
  ``mi_neurallens/sensors/neural_lens.py``, ``mi_neurallens/integrators/lens_flare.py``, in Mitsuba's
  ``.. pluginparameters::`` style), into docs/realistic_lens.md, docs/neural_lens.md and docs/flares.md;
* the table of bundled lenses (their JSON's ``description`` and ``source``, and ``Lens.paraxial()``) and the
  list of bundled models with their maps (the model files' metadata), into docs/lenses.md.

    python docs/make_reference.py            # rewrite the generated blocks
    python docs/make_reference.py --check    # exit 1 if a page's blocks are not what this script writes

Each block sits between ``<!-- generated: NAME -->`` and ``<!-- end generated -->`` (docs/generated_blocks.py);
``make docs`` runs this script and docs/make_performance.py.  Nothing here imports Mitsuba or Dr.Jit: the
docstrings are read from the source files, the models' metadata from the safetensors headers.
"""
from __future__ import annotations

import argparse
import ast
import json
import os
import re
import struct
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from generated_blocks import ROOT, table, write_pages  # noqa: E402

if ROOT not in sys.path:            # this tree's package, not an installed one
    sys.path.insert(1, ROOT)

#: plugin -> (source file of its DOC, the docs page that shows its parameters)
PLUGINS = {
    "realistic_lens": ("mi_neurallens/sensors/realistic_lens.py", "docs/realistic_lens.md"),
    "neural_lens": ("mi_neurallens/sensors/neural_lens.py", "docs/neural_lens.md"),
    "lens_flare": ("mi_neurallens/integrators/lens_flare.py", "docs/flares.md"),
}
#: Mitsuba's :ref: labels of the plugins -> the markdown link of their parameter table (relative to docs/)
REFS = {"sensor-realistic_lens": "realistic_lens.md#parameters", "sensor-neural_lens": "neural_lens.md#parameters",
        "integrator-lens_flare": "flares.md#parameters"}
#: the wavelength of the lens table's paraxial numbers (nm): the d line, Lens.paraxial()'s default
PARAXIAL_NM = 587.5618


# ------------------------------------------------------------------------------------------------ plugin parameters
def plugin_doc(source: str) -> str:
    """The ``DOC`` string of a plugin's source file (read with ``ast``: nothing is imported)."""
    with open(os.path.join(ROOT, source), encoding="utf-8") as f:
        tree = ast.parse(f.read())
    for node in tree.body:
        if isinstance(node, ast.Assign) and any(isinstance(t, ast.Name) and t.id == "DOC" for t in node.targets):
            return ast.literal_eval(node.value)
    raise ValueError(f"{source}: no DOC string")


def parse_parameters(doc: str) -> list:
    """The ``.. pluginparameters::`` list table of a docstring: ``[(name, type, description)]``, each cell's lines
    joined (RST markup kept)."""
    lines = doc.splitlines()
    try:
        i = next(k for k, ln in enumerate(lines) if ln.strip() == ".. pluginparameters::")
    except StopIteration:
        raise ValueError("no '.. pluginparameters::' table") from None
    rows, cell = [], None
    for ln in lines[i + 1:]:
        if not ln.strip():
            continue
        if not ln.startswith(" "):
            break                                   # the table ends at the first unindented line
        m = re.match(r"^ \* - ?(.*)$", ln)
        if m:
            rows.append([m.group(1).strip()])
            continue
        m = re.match(r"^   - ?(.*)$", ln)
        if m and rows:
            rows[-1].append(m.group(1).strip())
            continue
        if rows and ln.startswith("     "):
            rows[-1][-1] = (rows[-1][-1] + " " + ln.strip()).strip()
            continue
        raise ValueError(f"unexpected line in the parameter table: {ln!r}")
    bad = [r for r in rows if len(r) != 3]
    if bad:
        raise ValueError(f"parameter entries without name, type and description: {bad}")
    return [tuple(r) for r in rows]


def rst_to_md(text: str) -> str:
    """The RST inline markup of a docstring cell as markdown: literals, |true|, :ref:, docs/ page names."""
    text = re.sub(r":ref:`([^<`]+?)\s*<([^>]+)>`", lambda m: f"[`{m.group(1).strip()}`]({REFS[m.group(2)]})", text)
    text = re.sub(r"\|(true|false)\|", r"`\1`", text)
    text = re.sub(r"``(.+?)``", r"`\1`", text)

    def page(m):
        name, section = m.group(1), m.group(2)
        if section:
            slug = "".join(c for c in section.lower() if c.isalnum() or c in " -_").replace(" ", "-")
            return f"[{name}, “{section}”]({name}#{slug})"
        return f"[{name}]({name})"
    return re.sub(r"docs/([\w.-]+\.md)(?:, \"([^\"]+)\")?", page, text)


def split_default(desc: str) -> tuple:
    """``(description, default)``: the last ``(Default: …)`` of a description taken out of it."""
    k = desc.rfind("(Default:")
    if k < 0 or not desc.rstrip().endswith(")"):
        return desc, ""
    return desc[:k].rstrip(), desc[k + len("(Default:"):].rstrip()[:-1].strip()


def type_of(cell: str) -> str:
    return ", ".join(re.findall(r"\|(\w+)\|", cell))


def names_of(cell: str) -> str:
    if cell.startswith("("):
        return cell                                 # "(nested integrator)"
    return ", ".join(f"`{n.strip()}`" for n in cell.split(",") if n.strip())


def parameter_table(plugin: str) -> str:
    """The markdown parameter table of ``plugin``, from its DOC."""
    source = PLUGINS[plugin][0]
    rows = []
    for name, typ, desc in parse_parameters(plugin_doc(source)):
        d, default = split_default(desc)
        rows.append([names_of(name), type_of(typ), rst_to_md(default), rst_to_md(d)])
    return (f"*Generated by docs/make_reference.py from the plugin's docstring (`DOC` in `{source}`).*\n\n"
            + table(["parameter", "type", "default", "description"], rows))


# ------------------------------------------------------------------------------------------------ lenses and models
def _bundled():
    from mi_neurallens import resources
    return resources.bundled_library()


def model_header(path: str) -> dict:
    """The ``model`` metadata of a model file (the JSON of its safetensors header; the tensors are not read)."""
    with open(path, "rb") as f:
        n = struct.unpack("<Q", f.read(8))[0]
        header = json.loads(f.read(n))
    return json.loads(header["__metadata__"]["model"])


def size_of(layers) -> str:
    """``[4, 16, 16, 16, 5]`` → ``3×16`` (hidden layers × width; ``3×16/32`` where the widths differ)."""
    hidden = list(layers)[1:-1]
    widths = sorted(set(hidden))
    return f"{len(hidden)}×{'/'.join(str(w) for w in widths)}"


def count_sizes(sizes: list) -> str:
    """``["3×16", "3×16", "3×32"]`` → ``3×16 (2), 3×32 (1)``; one size alone without its count."""
    uniq = sorted(set(sizes), key=lambda s: (sizes.count(s) * -1, s))
    if len(uniq) == 1:
        return uniq[0]
    return ", ".join(f"{s} ({sizes.count(s)})" for s in uniq)


def lens_table() -> str:
    """The bundled lenses: name, description, surfaces, paraxial EFL and f-number, whether a model ships, source."""
    from mi_neurallens.optics.prescription import Lens
    lib = _bundled()
    rows = []
    for path in sorted(lib.path.glob("*.json")):
        name = path.stem
        with open(path, encoding="utf-8") as f:
            data = json.load(f)
        lens = Lens.load(str(path))
        p = lens.paraxial(PARAXIAL_NM)
        src = data.get("source") or {}
        where = f"[{src.get('file', name)}]({src['url']})" if src.get("url") else src.get("file", "")
        if src.get("repository"):
            where += f" ({src['repository']})"
        if src.get("reference"):
            where += f"; {src['reference']}"
        model = "yes" if lib.model(name).is_file() else "—"
        efl = f"{p.efl:.2f}"
        if lens.moving is not None and lens.moving.is_zoom:
            from mi_neurallens.optics import moving as mv
            efl = "{:.2f}–{:.2f}".format(*mv.focal_length_range(lens))
        rows.append([f"`{name}`", data.get("description", ""), len(lens.surfaces), efl,
                     f"f/{p.fnumber:.3g}", model, where])
    return (f"*Generated by docs/make_reference.py from the files in `mi_neurallens/data/lenses/`: EFL and f-number "
            f"paraxial at {PARAXIAL_NM:.2f} nm (`Lens.paraxial()`), the stop at its bundled size; surfaces count the "
            f"stop.*\n\n"
            + table(["name", "description", "surfaces", "EFL (mm)", "f-number", "model", "source"], rows))


def model_table() -> str:
    """The bundled models: which maps each holds and their networks (hidden layers × width)."""
    lib = _bundled()
    rows = []
    for path in sorted((lib.path / "models").glob("*.model.safetensors")):
        m = model_header(str(path))
        maps = {e["key"]: e for e in m["maps"]}
        cam = maps.get("backward.0")
        camera = "—"
        if cam is not None:
            camera = f"{size_of(cam['regressor']['layers'])} + {size_of(cam['classifier']['layers'])}"
            if cam.get("stop"):
                camera += f", stop head {size_of(cam['stop']['layers'])}"
        fwd = "yes" if "forward.0" in maps else "—"
        ghosts = [e for k, e in maps.items() if k.startswith("forward.") and e["path_id"] != 0]
        if ghosts:
            g = (f"{len(ghosts)}: regressors {count_sizes([size_of(e['regressor']['layers']) for e in ghosts])}; "
                 f"classifiers {count_sizes([size_of(e['classifier']['layers']) for e in ghosts])}")
        else:
            g = "—"
        lo, hi = m.get("sensor_distance_mm", [None, None])
        sd = f"{lo:.2f}–{hi:.2f}" if lo is not None else ""
        rows.append([f"`{m['lens']['name']}`", camera, fwd, g, sd, f"{os.path.getsize(path) / 1e6:.2f} MB"])
    return ("*Generated by docs/make_reference.py from the model files in `mi_neurallens/data/lenses/models/`; "
            "networks as hidden layers × width, the camera map's as regressor + classifier.*\n\n"
            + table(["model (lens)", "camera map (backward)", "forward transmit map", "ghost maps",
                     "sensor distance (mm)", "file"], rows))


# ------------------------------------------------------------------------------------------------ pages
def pages() -> dict:
    """{page: {block name: body}}: every block this script writes."""
    out = {}
    for plugin, (_, page) in PLUGINS.items():
        out.setdefault(page, {})[f"{plugin}-parameters"] = parameter_table(plugin)
    out.setdefault("docs/lenses.md", {}).update({"bundled-lenses": lens_table(), "bundled-models": model_table()})
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--check", action="store_true", help="write nothing; exit 1 if a generated block differs")
    a = ap.parse_args(argv)
    changed = write_pages(pages(), check=a.check)
    for p in changed:
        print(("differs: " if a.check else "wrote ") + p)
    return 1 if a.check and changed else 0


if __name__ == "__main__":
    sys.exit(main())
