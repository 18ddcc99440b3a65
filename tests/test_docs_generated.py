"""The generated parts of the docs are what their generators make of the stored data, byte for byte, so that
text and measurement cannot drift: docs/performance.md's tables and README.md's headline table (from the
benchmarks' JSON in docs/performance/ and the models' evaluation records, docs/make_performance.py), the
plugins' parameter tables (from their DOC strings) and the lists of bundled lenses and models
(docs/make_reference.py).  After a change to a DOC string, a lens, a model or a stored run: ``make docs``."""
from __future__ import annotations

import ast
import copy
import glob
import os
import re
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(ROOT, "docs"))

import generated_blocks  # noqa: E402
import make_performance  # noqa: E402
import make_reference  # noqa: E402
import pytest  # noqa: E402

HINT = "the docs' generated blocks are stale: run `make docs` (python docs/make_performance.py; python docs/make_reference.py)"


def page_blocks(rel: str) -> dict:
    with open(os.path.join(ROOT, rel), encoding="utf-8") as f:
        return generated_blocks.blocks(f.read())


def assert_pages(pages: dict):
    for rel, bodies in pages.items():
        found = page_blocks(rel)
        for name, body in bodies.items():
            assert name in found, f"{rel}: no generated block '{name}'"
            assert found[name] == generated_blocks.normalised(body), f"{rel}, block '{name}': {HINT}"


@pytest.fixture(scope="module")
def performance():
    return make_performance.pages()


@pytest.fixture(scope="module")
def reference():
    return make_reference.pages()


def test_performance_and_headline_are_what_the_stored_runs_give(performance):
    assert_pages(performance)


def test_reference_pages_are_what_the_docstrings_and_package_data_give(reference):
    assert_pages(reference)


def test_every_marker_in_the_docs_has_a_generator(performance, reference):
    made = {(rel, name) for gen in (performance, reference) for rel, bodies in gen.items() for name in bodies}
    pages = ["README.md"] + [os.path.relpath(p, ROOT) for p in sorted(glob.glob(os.path.join(ROOT, "docs", "*.md")))]
    found = {(rel, name) for rel in pages for name in page_blocks(rel)}
    assert found == made, f"markers without a generator: {sorted(found - made)}; blocks without markers: {sorted(made - found)}"


def test_readme_headline_comes_from_the_same_json_as_performance_md():
    """A value changed in a stored run moves both README's headline and performance.md's table."""
    r = make_performance.Results()
    assert r.cpu.get("bench_tracer.json"), "no stored tracer run"
    changed = copy.copy(r)
    changed.cpu = copy.deepcopy(r.cpu)
    row = next(x for x in changed.cpu["bench_tracer.json"]["rows"] if x.get("path") == "transmit")
    row["mrays_per_s"] = 12345.6
    pages = make_performance.pages(changed)
    assert "12346" in pages["docs/performance.md"]["tracer"]
    assert "12346" in pages["README.md"]["headline"]
    # and every comparison in the headline is one of the verdicts of performance.md
    for c in make_performance.comparisons(r):
        assert c["what"] in pages["README.md"]["headline"] and c["what"] in pages["docs/performance.md"]["verdicts"]


def test_missing_runs_leave_tables_out_not_made_up(tmp_path):
    empty = make_performance.Results(perf=str(tmp_path), models=str(tmp_path))
    pages = make_performance.pages(empty)
    assert all("No " in body or body.strip() == "" or body.startswith("|")
               for body in pages["docs/performance.md"].values())
    assert re.search(r"\d", pages["README.md"]["headline"].split("\n", 2)[2]) is None     # a table with no rows


def test_tanh_table_names_the_runs_that_measured_it():
    """The render-time tanh's table takes its rows from the camera-rays runs that recorded the deviation, and its
    source line from one of those, not from a run before the measure."""
    r = make_performance.Results()
    assert r.cpu_mlp, "no stored camera-rays run"
    changed = copy.copy(r)
    changed.cpu_mlp = copy.deepcopy(r.cpu_mlp)
    first, *rest = changed.cpu_mlp
    changed.cpu_mlp[first]["rows"][make_performance.FUSED_MLP].pop("vs_float64_exact_tanh", None)
    body = make_performance.tanh_table(changed)
    assert f"`{first}`" not in body and all(f"`{lens}`" in body for lens in rest)
    for d in changed.cpu_mlp.values():
        d["rows"][make_performance.FUSED_MLP].pop("vs_float64_exact_tanh", None)
    assert "No stored run" in make_performance.tanh_table(changed)


def test_amd_generation_from_cpuid_family_and_model():
    gen = make_performance.amd_generation
    assert (gen(26, 2), gen(25, 0x11), gen(25, 0x61), gen(25, 0x01), gen(25, 0x21)) == (
        "Zen 5", "Zen 4", "Zen 4", "Zen 3", "Zen 3")
    assert (gen(23, 0x31), gen(23, 0x01), gen(6, 85)) == ("Zen 2", "Zen/Zen+", "")


def _read_properties(source: str) -> set:
    with open(os.path.join(ROOT, source), encoding="utf-8") as f:
        return set(re.findall(r"rd\.(?:string|float|int|bool)\(\"(\w+)\"", f.read()))


def _documented(plugin: str) -> set:
    names = set()
    for name, _, _ in make_reference.parse_parameters(make_reference.plugin_doc(make_reference.PLUGINS[plugin][0])):
        names.update(n.strip() for n in name.split(","))
    return names


def test_every_plugin_parameter_is_in_its_docstring():
    base = _read_properties("mi_neurallens/sensors/base.py")
    for plugin in ("realistic_lens", "neural_lens"):
        read = base | _read_properties(make_reference.PLUGINS[plugin][0])
        missing = read - _documented(plugin)
        assert not missing, f"{plugin} reads properties its DOC does not describe: {sorted(missing)}"
    with open(os.path.join(ROOT, "mi_neurallens/integrators/lens_flare.py"), encoding="utf-8") as f:
        tree = ast.parse(f.read())
    props = next(node.value for node in tree.body if isinstance(node, ast.Assign)
                 and any(isinstance(t, ast.Name) and t.id == "_PROPS" for t in node.targets))
    read = {ast.literal_eval(k) for k in props.keys}
    missing = read - _documented("lens_flare")
    assert not missing, f"lens_flare reads properties its DOC does not describe: {sorted(missing)}"


def test_docstrings_quote_no_lab_notebook():
    for plugin, (source, _) in make_reference.PLUGINS.items():
        doc = make_reference.plugin_doc(source)
        assert "results.md" not in doc and "lab/" not in doc, plugin
