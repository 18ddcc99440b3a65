"""Lens file formats: project JSON (reader, writer, schema), pbrt .dat, Open Optical Designer JSON,
LensVisualizer JSON, format detection, bundled lenses.

Reference numbers (EFL/BFL/f-number) come from /work/shared/lens-data/FORMATS.md, where they were
computed by an independent y-nu trace and checked against optiland and rayoptics.  Tests that need
the shared lens data skip when it is absent; the bundled lenses and the inline samples below always run.
"""
from __future__ import annotations

import copy
import json
import math
import os
from pathlib import Path
import warnings

import pytest

import mi_neurallens as nl
from mi_neurallens.errors import GlassError, LensError
from mi_neurallens.optics import formats as F
from mi_neurallens.optics.formats import project_json as PJ
from mi_neurallens.optics.formats.lensvisualizer import LAMBDA_C_PRIME, LAMBDA_E, LAMBDA_F_PRIME
from mi_neurallens.optics.formats.pbrt import PbrtLayoutWarning
from mi_neurallens.optics.glass import AIR

from conftest import WIDE22, lens_from_rows

# the shared data lives beside the repository (../shared/lens-data), also in CI
SHARED = Path(os.environ.get("MI_NEURALLENS_LENS_DATA",
                             Path(__file__).resolve().parents[2] / "shared" / "lens-data"))
need_shared = pytest.mark.skipif(not SHARED.is_dir(), reason=f"shared lens data not found at {SHARED}")
SCHEMA = json.loads((Path(nl.__file__).parent / "data" / "lens.schema.json").read_text())
from mi_neurallens.constants import LAMBDA_D  # noqa: E402

# pbrt wide.22mm.dat, byte for byte (CRLF, trailing tabs, a stray '"' in a comment): 482 bytes.
WIDE22_DAT = (b'# Wide-angle (38-degree) lens. Nakamura.\t\t\t\r\n# MLD, p. 360"\t\t\t\r\n# Scaled to 22 mm from '
              b'100 mm\t\t\t\r\n# radius\tsep\tn\taperture\r\n35.98738\t1.21638\t1.54\t23.716\r\n11.69718\t9.9957\t1\t'
              b'17.996\r\n13.08714\t5.12622\t1.772\t12.364\r\n-22.63294\t1.76924\t1.617\t9.812\r\n71.05802\t0.8184\t1'
              b'\t9.152\r\n0\t2.27766\t0\t8.756\r\n-9.58584\t2.43254\t1.617\t8.184\r\n-11.28864\t0.11506\t1\t9.152\r\n'
              b'-166.7765\t3.09606\t1.713\t10.648\r\n-7.5911\t1.32682\t1.805\t11.44\r\n-16.7662\t3.98068\t1\t12.276'
              b'\r\n-7.70286\t1.21638\t1.617\t13.42\r\n-11.97328\t0\t1\t17.996\r\n')

# Open Optical Designer's built-in sample (src/data/default-sample-lens.js), as the app saves it.
OOD_SAMPLE = {
    "surfaces": [
        {"radius_of_curvature": 59, "aperture_radius": 25, "thickness": 8, "material": "PMMA", "conic_constant": 0},
        {"radius_of_curvature": 700, "aperture_radius": 25, "thickness": 0.5, "material": "Air", "conic_constant": 0},
        {"radius_of_curvature": 38, "aperture_radius": 25, "thickness": 10, "material": "PMMA", "conic_constant": -0.2},
        {"radius_of_curvature": 100, "aperture_radius": 25, "thickness": 1.2, "material": "Air", "conic_constant": 2},
        {"radius_of_curvature": 160, "aperture_radius": 21, "thickness": 2, "material": "PC", "conic_constant": 0},
        {"radius_of_curvature": 40, "aperture_radius": 20, "thickness": 12, "material": "Air", "conic_constant": 0},
        {"radius_of_curvature": -40, "aperture_radius": 20, "thickness": 2, "material": "PC", "conic_constant": 1.025},
        {"radius_of_curvature": "<INFINITY>", "aperture_radius": 21, "thickness": 5, "material": "PMMA",
         "conic_constant": 0},
        {"radius_of_curvature": -48, "aperture_radius": 21, "thickness": 0.5, "material": "Air", "conic_constant": 0.5},
        {"radius_of_curvature": -300, "aperture_radius": 23, "thickness": 6, "material": "PC", "conic_constant": 0},
        {"radius_of_curvature": -48, "aperture_radius": 23, "thickness": 0.5, "material": "Air",
         "conic_constant": -0.15},
        {"radius_of_curvature": 150, "aperture_radius": 23, "thickness": 4, "material": "PC", "conic_constant": -20},
        {"radius_of_curvature": -150, "aperture_radius": 23, "thickness": 37.95, "material": "Air",
         "conic_constant": -15}],
    "center_wavelength": 0.55, "short_wavelength": 0.44, "long_wavelength": 0.62, "env_beam_radius": 24,
    "env_rays_per_beam": 5, "env_fov_angle": 19, "env_beam_cross_distance": 30, "env_image_radius": 21.6,
    "env_initial_material": "Air"}

# FORMATS.md: name -> (wavelength nm, EFL, BFL, f-number at the file's stop)
PBRT_REF = {
    "wide.22mm.dat": (22.0235, 14.3183, 2.68), "dgauss.50mm.dat": (50.3582, 36.1059, 2.03),
    "fisheye.10mm.dat": (9.9914, 23.1605, 3.95), "telephoto.250mm.dat": (249.5666, 105.0704, 5.42),
    "wide.dat": (100.1068, 65.0830, 2.68), "dgauss.dat": (100.7163, 72.2118, 2.03),
    "fisheye.dat": (99.9142, 231.6054, 3.95), "telephoto.dat": (99.8266, 42.0282, 5.42),
}
LV_REF = {  # file -> (wavelength, EFL, BFL, f-number)
    "CanonEF24mmf14L.json": (LAMBDA_D, 24.8151, 38.2150, 1.45),
    "CanonEF24mmf14LII.json": (LAMBDA_D, 24.5386, 38.4759, 1.42),
    "CanonFD24mmf28SSC.json": (LAMBDA_D, 24.0000, 35.7996, 2.80),
    "CanonRF24mmF14LVCM.json": (LAMBDA_D, 24.7131, 15.1677, 1.46),
    "CanonEF2470mmf28L.json": (LAMBDA_D, 24.8968, 38.4639, 2.38),
    "LeicaSummicronR50mmf2.json": (LAMBDA_E, 52.5061, 37.6999, 2.00),   # e-line indices
    "NikonAFFisheyeNikkor16mmf28D.json": (LAMBDA_D, 15.6685, 40.2718, 2.90),
    "CanonFD300mmf4SSC.json": (LAMBDA_D, 299.5288, 116.2785, 4.00),
}
BUNDLED_REF = {  # name -> (wavelength, EFL, BFL, f-number)
    "wide-22mm": (LAMBDA_D, 22.0235, 14.3183, 2.68),
    "dgauss-50mm": (LAMBDA_D, 50.3582, 36.1059, 2.03),
    "fisheye-10mm": (LAMBDA_D, 9.9914, 23.1605, 3.95),
    "telephoto-250mm": (LAMBDA_D, 249.5666, 105.0704, 5.42),
    "canon-ef-24mm-f1.4l": (LAMBDA_D, 24.8151, 38.2150, 1.45),
    "canon-rf-24mm-f1.4l-vcm": (LAMBDA_D, 24.7131, 15.1677, 1.46),
}


def where_ok(excinfo, file, *, surface=None, field=None):
    """The error names the file, the surface index and the field (both in the text and as attributes)."""
    e, msg = excinfo.value, str(excinfo.value)
    assert str(file) in msg, msg
    if surface is not None:
        assert e.surface == surface and f"surface {surface}" in msg, msg
    if field is not None:
        assert e.field == field and f"field '{field}'" in msg, msg
    return msg


def write(tmp_path, name, content) -> Path:
    p = tmp_path / name
    if isinstance(content, bytes):
        p.write_bytes(content)
    elif isinstance(content, str):
        p.write_text(content)
    else:
        p.write_text(json.dumps(content))
    return p


def small_doc():
    """A valid project-JSON document: a singlet and a rear stop."""
    return {"format": "mi-neurallens-lens", "version": 1, "name": "singlet", "surfaces": [
        {"label": "1", "radius": 50.0, "thickness": 5.0, "medium": 1.5, "semi_diameter": 10.0},
        {"label": "2", "radius": -50.0, "thickness": 2.0, "medium": "air", "semi_diameter": 10.0},
        {"label": "STO", "radius": "inf", "thickness": 45.0, "medium": "air", "semi_diameter": 5.0, "stop": True}]}


def schema_ok(doc) -> bool:
    import jsonschema
    return jsonschema.Draft202012Validator(SCHEMA).is_valid(doc)


# ============================================================================ bundled lenses
def test_bundled_names():
    assert set(F.bundled_lenses()) == {"wide-22mm", "ood-59mm", "canon-ef-24mm-f1.4l", "dgauss-50mm",
                                       "fisheye-10mm", "telephoto-250mm", "canon-rf-24mm-f1.4l-vcm",
                                       "canon-ef-24-70mm-f2.8l"}


@pytest.mark.parametrize("name", sorted(BUNDLED_REF))
def test_bundled_paraxial_matches_formats_md(name):
    wl, efl, bfl, fno = BUNDLED_REF[name]
    lens = nl.Lens.load(name)
    p = lens.paraxial(wl)
    assert p.efl == pytest.approx(efl, abs=1.5e-4)
    assert p.bfl == pytest.approx(bfl, abs=1.5e-4)
    assert p.fnumber == pytest.approx(fno, abs=6e-3)
    # the image plane sits at the BFL: pbrt files are focused at infinity, the Canon files keep the
    # patents' last d (EF: 36.467, not the paraxial BFL; RF: 15.18, focused at 49.7 m)
    last = lens.surfaces[-1].thickness
    if name.startswith("canon"):
        assert last == {"canon-ef-24mm-f1.4l": 36.467, "canon-rf-24mm-f1.4l-vcm": 15.18}[name]
    else:
        assert last == pytest.approx(bfl, abs=1.5e-4)


def test_bundled_ood_59mm():
    lens = nl.Lens.load("ood-59mm")
    p = lens.paraxial(550.0)
    # FORMATS.md: 59.5274 with object space n = 1 and air gaps 1.000278 (rayoptics ConstantIndex) ...
    assert lens.replace(object_medium=AIR).efl(550.0) == pytest.approx(59.5274, abs=1e-4)
    # ... the app's displayed 1/Φ ≈ 59.52 (it starts in its own air), 59.53 with the image-side index
    assert 1.0 / p.power == pytest.approx(59.52, abs=5e-3)
    assert p.efl == pytest.approx(59.53, abs=5e-3)
    assert p.object_index == pytest.approx(1.000278, abs=1e-6)
    assert p.bfl == pytest.approx(38.03, abs=5e-3)
    assert lens.surfaces[-1].thickness == 37.95                     # kept as written
    assert lens.stop.label == "STO" and lens.vertex_z[lens.stop_index] == pytest.approx(30.0)
    st = lens.metadata["ood"]["stop"]
    assert st["clipped"] and lens.stop.semi_diameter == pytest.approx(st["limit_mm"])
    assert p.entrance_pupil_radius < 24.0


@pytest.mark.parametrize("name", ["wide-22mm", "ood-59mm", "canon-ef-24mm-f1.4l", "dgauss-50mm",
                                  "fisheye-10mm", "telephoto-250mm", "canon-rf-24mm-f1.4l-vcm",
                                  "canon-ef-24-70mm-f2.8l"])
def test_bundled_files_validate_and_round_trip(name, tmp_path):
    import jsonschema
    path = F.bundled_lens_path(name)
    doc = json.loads(path.read_text())
    jsonschema.validate(doc, SCHEMA, cls=jsonschema.Draft202012Validator)
    src = doc["source"]
    for k in ("file", "repository", "commit", "path", "sha256", "conversion"):
        assert src.get(k), (name, k)
    lens = F.load_lens(name)
    assert lens.name == name and lens.path == str(path)
    out = tmp_path / f"{name}.json"
    lens.save(out)
    back = F.load_lens(out)
    assert back == lens and back.fingerprint() == lens.fingerprint()
    assert back.metadata == lens.metadata
    assert PJ.lens_to_dict(back) == PJ.lens_to_dict(lens) == doc     # the bundled file is the writer's output
    assert out.read_text() == path.read_text()


@need_shared
def test_convert_bundled_reproduces_committed_files(tmp_path):
    with warnings.catch_warnings():
        warnings.simplefilter("error")   # none of the bundled sources needs the axpos conversion
        written = F.convert_bundled(SHARED, tmp_path)
    assert set(written) == set(F.bundled_lenses())
    for name, p in written.items():
        new, old = F.load_lens(p), F.load_lens(name)
        # the same document, numbers to 1e-9 relative: glass models fitted to catalog data (least squares)
        # differ in their last bits between numpy/BLAS builds, which would change the exact fingerprint
        _assert_same_document(PJ.lens_to_dict(new), PJ.lens_to_dict(old), name)
        assert new.metadata["source"] == old.metadata["source"], name
    assert not [p for p in tmp_path.iterdir() if p.suffix != ".json"]  # no temp files left behind


def _assert_same_document(a, b, where):
    """``a == b`` for JSON-like documents, floats compared to 1e-9 relative (1e-15 absolute)."""
    if isinstance(a, dict) and isinstance(b, dict):
        assert set(a) == set(b), (where, sorted(set(a) ^ set(b)))
        for k in a:
            _assert_same_document(a[k], b[k], f"{where}/{k}")
    elif isinstance(a, list) and isinstance(b, list):
        assert len(a) == len(b), where
        for i, (u, v) in enumerate(zip(a, b)):
            _assert_same_document(u, v, f"{where}[{i}]")
    elif isinstance(a, float) or isinstance(b, float):
        assert a == pytest.approx(b, rel=1e-9, abs=1e-15), where
    else:
        assert a == b, where


def test_user_lens_libraries_come_before_the_bundled_one(tmp_path, monkeypatch):
    """$MI_NEURALLENS_LENSES (a path list) is searched before the library inside the package: its lenses join
    the bundled ones, and its copy of a bundled name wins; a name nowhere is an error listing the names."""
    a, b = tmp_path / "a", tmp_path / "b"
    a.mkdir(), b.mkdir()
    (a / "mine.json").write_text(json.dumps(small_doc()))
    (b / "wide-22mm.json").write_text(json.dumps(small_doc()))
    monkeypatch.setenv(F.LENSES_ENV, os.pathsep.join([str(a), str(b)]))
    assert "mine" in F.bundled_lenses() and "ood-59mm" in F.bundled_lenses()
    assert F.load_lens("mine").name == "singlet"
    assert F.load_lens("wide-22mm").name == "singlet"          # the user's copy, not the bundled lens
    with pytest.raises(LensError, match="lenses: .*mine"):
        F.load_lens("no-such-lens")
    monkeypatch.delenv(F.LENSES_ENV)
    assert F.load_lens("wide-22mm").name == "wide-22mm"


def test_unknown_bundled_name_lists_names_and_formats():
    with pytest.raises(LensError) as e:
        F.load_lens("no-such-lens")
    msg = str(e.value)
    assert "no-such-lens" in msg and "wide-22mm" in msg and "ood-59mm" in msg and "pbrt" in msg
    with pytest.raises(LensError, match="file not found.*wide-22mm"):
        F.load_lens("some/dir/missing.dat")


# ============================================================================ format detection
def test_detection_by_content_not_extension(tmp_path):
    pb = write(tmp_path, "lens.json", WIDE22_DAT)                 # pbrt text with a .json name
    ood = write(tmp_path, "lens.dat", OOD_SAMPLE)                 # OOD JSON with a .dat name
    prj = write(tmp_path, "lens.txt", small_doc())
    assert F.detect_format(pb) == "pbrt"
    assert F.detect_format(ood) == "ood"
    assert F.detect_format(prj) == "project"
    assert F.load_lens(pb).efl() == pytest.approx(22.0235, abs=1e-4)
    assert F.load_lens(ood).num_surfaces == 14
    assert F.load_lens(prj).name == "singlet"
    # a dict is read as a parsed document
    assert F.load_lens(small_doc()).name == "singlet"


def test_detection_lensvisualizer(tmp_path):
    p = write(tmp_path, "x.json", lv_doc())
    assert F.detect_format(p) == "lensvisualizer"


@pytest.mark.parametrize("content, match", [
    ({"hello": 1}, "not a lens format"),
    ({"format": "zemax", "surfaces": []}, "unknown format 'zemax'"),
    ("SURF 1\nCURV 0.1\n", "not a recognised lens file"),
    ({"0001": {"optical-elements-patent": []}}, "lentil lens database"),
    (b"\x00\x01\x02binary", "binary file"),
    ("{not json", "not valid JSON"),
])
def test_unsupported_content_lists_formats(tmp_path, content, match):
    p = write(tmp_path, "x.json", content)
    with pytest.raises(LensError, match=match) as e:
        F.load_lens(p)
    assert str(p) in str(e.value)
    if match not in ("not valid JSON",):
        assert "pbrt" in str(e.value) and "Open Optical Designer" in str(e.value)


def test_reader_option_for_wrong_format(tmp_path):
    p = write(tmp_path, "x.json", small_doc())
    with pytest.raises(LensError) as e:
        F.load_lens(p, layout="axpos")
    where_ok(e, p, field="layout")
    with pytest.raises(LensError, match="unknown format"):
        F.load_lens(p, format="oslo")


# ============================================================================ project JSON
def test_project_json_medium_specs_and_defaults(tmp_path):
    d = small_doc()
    specs = ["N-BK7", 1.5, {"n": 1.6}, {"glass": "S-LAL14", "catalog": "Ohara"}, {"nd": 1.6968, "vd": 55.53},
             {"nd": 1.696797, "nC": 1.692973, "nF": 1.705521, "ng": 1.712337}, {"table": [[400, 1.53], [700, 1.51]]},
             {"ood": "PMMA"}, {"name": "x", "formula": "constant", "coefficients": [1.7]}]
    for spec in specs:
        d["surfaces"][0]["medium"] = spec
        assert schema_ok(d), spec
        lens = F.load_lens(write(tmp_path, "m.json", d))
        assert lens.surfaces[0].medium.nd > 1.4
    s = lens.surfaces[0]
    assert (s.conic, s.aspheric, s.housing_radius, s.is_stop, s.blades, s.coating) == (0.0, (), None, False, 0, None)
    assert lens.object_medium == AIR and lens.metadata["description"] == "" and lens.metadata["source"] == {}
    # radius null == "inf"
    d["surfaces"][2]["radius"] = None
    assert F.load_lens(write(tmp_path, "n.json", d)).stop.radius == math.inf


def test_writer_writes_full_media_and_reads_without_catalog(tmp_path, monkeypatch):
    d = small_doc()
    d["surfaces"][0]["medium"] = {"glass": "S-LAL14", "catalog": "Ohara"}
    d["surfaces"][0]["coating"] = {"index": 1.38}
    d["surfaces"][2].update(blades=7, blade_rotation_deg=12.5)
    d["surfaces"][1].update(conic=-0.5, aspheric=[1e-6, -2e-9], housing_radius=11.0)
    d["description"] = "test"
    d["source"] = {"file": "x", "conversion": ["a", "b"]}
    d["metadata"] = {"anything": {"nested": [1, 2]}}
    lens = F.load_lens(write(tmp_path, "a.json", d))
    out = tmp_path / "b.json"
    F.save_lens(lens, out)
    written = json.loads(out.read_text())
    assert written["surfaces"][0]["medium"]["formula"] == "sellmeier"
    assert written["surfaces"][0]["medium"]["source"] == {"catalog": "Ohara", "glass": "S-LAL14"}
    assert written["surfaces"][0]["coating"] == {"index": 1.38, "design_wavelength_nm": 550}
    assert schema_ok(written)
    import mi_neurallens.optics.glass as G
    monkeypatch.setattr(G, "catalog_glass", lambda *a, **k: pytest.fail("catalog lookup on load"))
    back = F.load_lens(out)
    assert back == lens and back.fingerprint() == lens.fingerprint()
    assert back.metadata == {"description": "test", "source": {"file": "x", "conversion": ["a", "b"]},
                             "anything": {"nested": [1, 2]}}
    assert back.stop.blades == 7 and back.surfaces[1].aspheric == (1e-6, -2e-9)


def test_save_is_atomic(tmp_path):
    lens = F.load_lens(small_doc())
    out = tmp_path / "l.json"
    lens.save(out)
    before = out.read_text()
    bad = lens.replace(metadata={**lens.metadata, "oops": object()})
    with pytest.raises(LensError) as e:
        F.save_lens(bad, out)
    where_ok(e, out, field="metadata")
    assert out.read_text() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["l.json"]


def _bad(mutate):
    d = small_doc()
    mutate(d)
    return d


# (mutation, exception type, surface, field, text in the message, schema also rejects?)
BAD_PROJECT = [
    ("unknown glass", lambda d: d["surfaces"][0].update(medium="S-NOSUCHGLASS"), GlassError, 0, "medium",
     "unknown glass", "accept"),
    ("bad medium dict", lambda d: d["surfaces"][0].update(medium={"glas": "N-BK7"}), GlassError, 0, "medium",
     "cannot resolve", "reject"),
    ("negative thickness", lambda d: d["surfaces"][1].update(thickness=-1.0), LensError, 1, "thickness", "≥ 0", "reject"),
    ("zero thickness", lambda d: d["surfaces"][0].update(thickness=0.0), LensError, 0, "thickness", "> 0", "accept"),
    ("semi-diameter too large", lambda d: d["surfaces"][0].update(radius=8.0, semi_diameter=9.0), LensError, 0,
     "semi_diameter", "larger than the surface allows", "accept"),
    ("negative semi-diameter", lambda d: d["surfaces"][1].update(semi_diameter=-3), LensError, 1, "semi_diameter",
     "> 0", "reject"),
    ("sags cross", lambda d: d["surfaces"][0].update(radius=20.0, thickness=1.0) or d["surfaces"][1].update(
        radius=-20.0), LensError, 0, "thickness", "cross", "accept"),
    ("missing stop", lambda d: d["surfaces"][2].pop("stop"), LensError, None, "stop", "no surface is marked", "reject"),
    ("second stop", lambda d: d["surfaces"].append({"radius": "inf", "thickness": 1.0, "medium": "air",
                                                    "semi_diameter": 5.0, "stop": True}),
     LensError, 3, "stop", "second aperture stop", "reject"),
    ("NaN", lambda d: d["surfaces"][1].update(thickness=float("nan")), LensError, 1, "thickness", "finite", None),
    ("Infinity radius", lambda d: d["surfaces"][1].update(radius=float("inf")), LensError, 1, "radius", "finite", None),
    ("string number", lambda d: d["surfaces"][1].update(thickness="5"), LensError, 1, "thickness",
     "must be a number", "reject"),
    ("bool number", lambda d: d["surfaces"][0].update(semi_diameter=True), LensError, 0, "semi_diameter",
     "got boolean", "reject"),
    ("radius word", lambda d: d["surfaces"][0].update(radius="flat"), LensError, 0, "radius", "inf", "reject"),
    ("radius zero", lambda d: d["surfaces"][0].update(radius=0), LensError, 0, "radius", "radius 0", "reject"),
    ("stop string", lambda d: d["surfaces"][2].update(stop="yes"), LensError, 2, "stop", "true or false", "reject"),
    ("blades fraction", lambda d: d["surfaces"][2].update(blades=6.5), LensError, 2, "blades", "integer", "reject"),
    ("blades two", lambda d: d["surfaces"][2].update(blades=2), LensError, 2, "blades", "≥ 3", "reject"),
    ("aspheric too long", lambda d: d["surfaces"][0].update(aspheric=[0.0] * 8), LensError, 0, "aspheric",
     "at most 7", "reject"),
    ("aspheric string", lambda d: d["surfaces"][0].update(aspheric=[1e-5, "x"]), LensError, 0, "aspheric[1]",
     "must be a number", "reject"),
    ("housing negative", lambda d: d["surfaces"][0].update(housing_radius=-1), LensError, 0, "housing_radius",
     "> 0", "reject"),
    ("unknown surface key", lambda d: d["surfaces"][1].update(thicknes=3), LensError, 1, "thicknes",
     "did you mean 'thickness'", "reject"),
    ("unknown coating key", lambda d: d["surfaces"][1].update(coating={"idx": 1.38}), LensError, 1, "coating.idx",
     "unknown key", "reject"),
    ("missing semi-diameter", lambda d: d["surfaces"][1].pop("semi_diameter"), LensError, 1, "semi_diameter",
     "missing", "reject"),
    ("surface not object", lambda d: d["surfaces"].__setitem__(1, [1, 2, 3]), LensError, 1, None,
     "must be a JSON object", "reject"),
    ("label type", lambda d: d["surfaces"][1].update(label=2), LensError, 1, "label", "string", "reject"),
]
BAD_TOP = [
    ("unknown top key", lambda d: d.update(nmae="x"), "nmae", "did you mean 'name'"),
    ("wrong format", lambda d: d.update(format="mi-neurallens-lense"), "format", 'must be "mi-neurallens-lens"'),
    ("version 2", lambda d: d.update(version=2), "version", "not supported"),
    ("units", lambda d: d.update(units="m"), "units", "only \"mm\""),
    ("missing name", lambda d: d.pop("name"), "name", "missing"),
    ("unknown source key", lambda d: d.update(source={"comit": "x"}), "source.comit", "did you mean 'commit'"),
    ("reserved metadata key", lambda d: d.update(metadata={"source": {}}), "metadata.source", "top-level"),
    ("surfaces not a list", lambda d: d.update(surfaces={}), "surfaces", "array"),
    ("bad object medium", lambda d: d.update(object_medium="unobtainium"), "object_medium", "unknown glass"),
]


@pytest.mark.parametrize("case", BAD_PROJECT, ids=[c[0] for c in BAD_PROJECT])
def test_project_json_bad_surface(tmp_path, case):
    _, mutate, exc, surface, field, text, schema = case
    d = _bad(mutate)
    p = tmp_path / "bad-lens.json"
    p.write_text(json.dumps(d))              # NaN / Infinity are written as the JSON extensions NaN, Infinity
    with pytest.raises(exc) as e:
        F.load_lens(p)
    msg = where_ok(e, p, surface=surface, field=field)
    assert text in msg
    # the schema rejects every structural error; geometry (sags, sphere limits, zero gaps) and glass names
    # are beyond JSON Schema: it accepts those and only the reader rejects them.  NaN is not JSON at all.
    if schema is not None:
        assert schema_ok(d) is (schema == "accept"), case[0]


@pytest.mark.parametrize("case", BAD_TOP, ids=[c[0] for c in BAD_TOP])
def test_project_json_bad_top_level(tmp_path, case):
    _, mutate, field, text = case
    d = _bad(mutate)
    p = write(tmp_path, "bad-top.json", d)
    with pytest.raises(LensError) as e:
        F.load_lens(p, format="project")
    assert text in where_ok(e, p, field=field)


def test_reader_and_schema_agree():
    """Structural errors: the schema and the reader both reject; valid documents: both accept."""
    cases = [(c[0], c[1]) for c in BAD_PROJECT if c[6] == "reject"]
    cases += [(c[0], c[1]) for c in BAD_TOP if c[0] != "bad object medium"]
    assert len(cases) > 25
    for name, mutate in cases:
        d = _bad(mutate)
        assert not schema_ok(d), name
        with pytest.raises(LensError):
            F.load_lens(d, format="project")
    # and the other way round: every optional field at an explicit value, accepted by both
    d = small_doc()
    d["surfaces"][2].update(blades=0, blade_rotation_deg=0, coating=None, housing_radius=None, conic=0, aspheric=[])
    d["surfaces"][0].update(coating={}, housing_radius=10.5)
    d.update(description="", units="mm", object_medium="air", source={}, metadata={})
    assert schema_ok(d)
    F.load_lens(d)


def test_json_syntax_and_duplicate_keys(tmp_path):
    p = write(tmp_path, "dup.json", '{"format": "mi-neurallens-lens", "version": 1, "version": 1}')
    with pytest.raises(LensError) as e:
        F.load_lens(p)
    where_ok(e, p, field="version")
    p = write(tmp_path, "syn.json", '{"format": "mi-neurallens-lens",\n "version": 1,,}')
    with pytest.raises(LensError, match="line 2, column"):
        F.load_lens(p)


# ============================================================================ pbrt
def test_pbrt_wide22_matches_hand_built(tmp_path, wide22):
    p = write(tmp_path, "wide.22mm.dat", WIDE22_DAT)
    assert p.stat().st_size == 482
    lens = F.load_lens(p)
    assert lens.name == "wide.22mm" and lens.num_surfaces == 13 and lens.stop_index == 5
    ref = lens_from_rows(WIDE22)
    for s, r in zip(lens.surfaces[:-1], ref.surfaces[:-1]):
        assert (s.radius, s.thickness, s.semi_diameter, s.is_stop, s.medium) == (
            r.radius, r.thickness, r.semi_diameter, r.is_stop, r.medium)
        assert s.medium.is_constant
    bfl = lens.metadata["pbrt"]["image_distance_mm"]
    assert lens.surfaces[-1].thickness == bfl == pytest.approx(14.3183, abs=1e-4)
    assert lens.efl() == pytest.approx(22.0235, abs=1e-4)
    md = lens.metadata["pbrt"]
    assert md["layout"] == "thickness" and "constant" in md["dispersion"] and md["file_last_thickness"] == 0
    assert lens.metadata["description"] == "Wide-angle (38-degree) lens. Nakamura."


def _axpos_text(header=True, first=0.0):
    """wide.22mm in the 'axpos' layout: column 2 = distance from the previous surface."""
    lines = ["# Wide-angle, axpos layout"] + (["# radius\taxpos\tN\taperture"] if header else [])
    prev = first
    for r, t, n, a in WIDE22:
        lines.append(f"  {r}\t{prev}\t{n}\t{a}")
        prev = t
    return "\r\n".join(lines) + "\r\n"


def test_pbrt_axpos_detected_and_converted(tmp_path):
    p = write(tmp_path, "wide-axpos.dat", _axpos_text())
    with pytest.warns(PbrtLayoutWarning, match="axpos"):
        lens = F.load_lens(p)
    assert lens.metadata["pbrt"]["layout"] == "axpos" and "axpos" in lens.metadata["pbrt"]["layout_reason"]
    thick = F.load_lens(write(tmp_path, "wide.dat", WIDE22_DAT))
    assert lens.fingerprint() == thick.fingerprint()


def test_pbrt_axpos_ambiguous_is_refused(tmp_path):
    p = write(tmp_path, "noheader.dat", _axpos_text(header=False))
    with pytest.raises(LensError) as e:
        F.load_lens(p)
    msg = where_ok(e, p, surface=0, field="thickness")
    assert "layout='axpos'" in msg and "layout='thickness'" in msg
    with pytest.warns(PbrtLayoutWarning):
        lens = F.load_lens(p, layout="axpos")
    assert lens.efl() == pytest.approx(22.0235, abs=1e-4)


def test_pbrt_axpos_header_with_thicknesses(tmp_path):
    # dgauss.50mm.dat's situation: header left over from the original, numbers already thicknesses
    text = WIDE22_DAT.decode().replace("# radius\tsep\tn\taperture", "#    radius\t axpos\tN\taperture")
    lens = F.load_lens(write(tmp_path, "w.dat", text))
    assert lens.metadata["pbrt"]["layout"] == "thickness"
    assert "header" in lens.metadata["pbrt"]["layout_reason"]


@need_shared
@pytest.mark.parametrize("fname", sorted(PBRT_REF))
def test_pbrt_shared_files(fname):
    efl, bfl, fno = PBRT_REF[fname]
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        lens = F.load_lens(SHARED / "pbrt" / fname)
    axpos = "." not in fname[:-4]
    assert lens.metadata["pbrt"]["layout"] == ("axpos" if axpos else "thickness")
    assert any(issubclass(x.category, PbrtLayoutWarning) for x in w) == axpos
    p = lens.paraxial(LAMBDA_D)
    assert p.efl == pytest.approx(efl, abs=1.5e-4) and p.bfl == pytest.approx(bfl, abs=1.5e-4)
    assert p.fnumber == pytest.approx(fno, abs=6e-3)


def _dat_lines():
    return WIDE22_DAT.decode().split("\r\n")


@pytest.mark.parametrize("case", ["truncated", "text", "two stops", "no stop", "bad aperture", "bad eta",
                                  "negative thickness", "nan"])
def test_pbrt_bad_rows(tmp_path, case):
    lines = _dat_lines()          # data rows start on line 5 (index 4): row k is on line 5 + k
    if case == "truncated":
        lines[6] = lines[6].rsplit("\t", 1)[0]                    # row 2 loses its aperture
        surface, field, text = 2, "aperture", "line 7: truncated row"
    elif case == "text":
        lines[7] = lines[7].replace("1.617", "1.6l7")
        surface, field, text = 3, "eta", "line 8: '1.6l7' is not a number"
    elif case == "two stops":
        lines[10] = "0\t2.43254\t0\t8.184"
        surface, field, text = 6, "radius", "second aperture stop"
    elif case == "no stop":
        lines[9] = "1e9\t2.27766\t0\t8.756"
        surface, field, text = None, "radius", "no aperture stop"
    elif case == "bad aperture":
        lines[5] = "11.69718\t9.9957\t1\t0"
        surface, field, text = 1, "aperture", "aperture diameter must be > 0"
    elif case == "bad eta":
        lines[4] = "35.98738\t1.21638\t0.54\t23.716"
        surface, field, text = 0, "eta", "eta must be ≥ 1"
    elif case == "negative thickness":
        lines[5] = "11.69718\t-9.9957\t1\t17.996"
        surface, field, text = 1, "thickness", "thickness must be ≥ 0"
    else:
        lines[5] = "11.69718\tnan\t1\t17.996"
        surface, field, text = 1, "thickness", "is not a number"
    p = write(tmp_path, "bad.dat", "\r\n".join(lines))
    with pytest.raises(LensError) as e:
        F.load_lens(p)
    assert text in where_ok(e, p, surface=surface, field=field)


def test_pbrt_impossible_geometry_names_row(tmp_path):
    lines = _dat_lines()
    lines[4] = "35.98738\t1.21638\t1.54\t80"                       # 40 mm semi-diameter on R = 36
    p = write(tmp_path, "big.dat", "\r\n".join(lines))
    with pytest.raises(LensError) as e:
        F.load_lens(p)
    where_ok(e, p, surface=0, field="semi_diameter")


# ============================================================================ Open Optical Designer
def test_ood_sample(tmp_path):
    p = write(tmp_path, "lens-design.json", OOD_SAMPLE)
    lens = F.load_lens(p)
    bundled = F.load_lens("ood-59mm")
    assert lens.fingerprint() == bundled.fingerprint()
    assert [s.label for s in lens.surfaces][5:8] == ["6", "STO", "7"]
    assert lens.surfaces[5].thickness == 8.3 and lens.stop.thickness == 3.7
    assert lens.surfaces[8].radius == math.inf and lens.surfaces[3].conic == 2.0     # "<INFINITY>", conic
    assert lens.object_medium.index(550.0) == pytest.approx(1.000278, abs=2e-6)
    assert lens.surfaces[0].medium.index(589.0) == pytest.approx(1.4921, abs=1e-12)  # PMMA table
    # the stop radius is the largest the neighbours allow: surface 7 (R -40, K 1.025) reaches z = 30
    r = lens.stop.semi_diameter
    s7 = lens.surfaces[7]
    assert lens.vertex_z[7] + s7.sag(r) == pytest.approx(30.0, abs=1e-9)


def test_ood_stop_radius_rule(tmp_path):
    doc = copy.deepcopy(OOD_SAMPLE)
    doc["env_beam_radius"] = 10.0                    # small enough not to be clipped
    lens = F.load_lens(write(tmp_path, "a.json", doc))
    p = lens.paraxial(550.0)
    assert p.entrance_pupil_radius == pytest.approx(10.0, rel=1e-12)
    assert not lens.metadata["ood"]["stop"]["clipped"]
    doc["center_wavelength"] = 0.44                  # the rule uses center_wavelength
    lens44 = F.load_lens(write(tmp_path, "b.json", doc))
    assert lens44.paraxial(440.0).entrance_pupil_radius == pytest.approx(10.0, rel=1e-12)
    assert lens44.stop.semi_diameter != lens.stop.semi_diameter
    fixed = F.load_lens(write(tmp_path, "c.json", doc), stop_radius=5.0)
    assert fixed.stop.semi_diameter == 5.0


@pytest.mark.parametrize("case", ["inside glass", "outside", "unknown material", "bad radius", "missing distance",
                                  "too big stop"])
def test_ood_bad(tmp_path, case):
    doc = copy.deepcopy(OOD_SAMPLE)
    kw = {}
    if case == "inside glass":
        doc["env_beam_cross_distance"] = 4.0         # inside the first PMMA element
        surface, field, text = 0, "env_beam_cross_distance", "falls inside PMMA"
    elif case == "outside":
        doc["env_beam_cross_distance"] = 60.0
        surface, field, text = None, "env_beam_cross_distance", "outside the lens"
    elif case == "unknown material":
        doc["surfaces"][4]["material"] = "Unobtainium"
        surface, field, text = 4, "material", "unknown Open Optical Designer material"
    elif case == "bad radius":
        doc["surfaces"][2]["radius_of_curvature"] = "INF"
        surface, field, text = 2, "radius_of_curvature", "<INFINITY>"
    elif case == "missing distance":
        del doc["env_beam_cross_distance"]
        surface, field, text = None, "env_beam_cross_distance", "missing"
    else:
        kw = {"stop_radius": 19.0}
        surface, field, text = 6, "stop_radius", "larger than the neighbouring surfaces allow"
    p = write(tmp_path, "bad-ood.json", doc)
    with pytest.raises(LensError) as e:
        F.load_lens(p, **kw)
    assert text in where_ok(e, p, surface=surface, field=field)


# ============================================================================ LensVisualizer
def lv_doc():
    return {"key": "test-singlet", "name": "TEST", "asph": {"2A": {"K": 0.0}}, "var": {},
            "elements": [{"id": 1, "name": "L1", "nd": 1.5168, "vd": 64.17, "glass": "N-BK7 class"}],
            "surfaces": [{"label": "1", "R": 50, "d": 5, "nd": 1.5168, "elemId": 1, "sd": 10},
                         {"label": "2A", "R": -50, "d": 2, "nd": 1, "elemId": 0, "sd": 10},
                         {"label": "STO", "R": 1e15, "d": 45, "nd": 1, "elemId": 0, "sd": 5}]}


def test_lensvisualizer_small(tmp_path):
    d = lv_doc()
    d["asph"] = {"2A": {"K": -0.5, "A4": 1e-6, "A6": 0, "A8": 2e-12, "A10": 0, "A20": 0, "A3": 0}}
    lens = F.load_lens(write(tmp_path, "t.json", d))
    s = lens.surfaces[1]
    assert s.conic == -0.5 and s.aspheric == (1e-6, 0.0, 2e-12)
    assert lens.stop_index == 2 and lens.stop.radius == math.inf and lens.surfaces[-1].thickness == 45
    m = lens.surfaces[0].medium
    assert m.nd == pytest.approx(1.5168, abs=1e-12) and m.vd == pytest.approx(64.17, rel=1e-9)   # model glass
    assert lens.name == "test-singlet"


def test_lensvisualizer_e_line_model_glass(tmp_path):
    d = lv_doc()
    d["elements"][0].update(indexReference="e", nd=1.62286, vd=60.08)
    d["surfaces"][0]["nd"] = 1.62286
    m = F.load_lens(write(tmp_path, "e.json", d)).surfaces[0].medium
    ne = m.index(LAMBDA_E)
    ve = (ne - 1) / (m.index(LAMBDA_F_PRIME) - m.index(LAMBDA_C_PRIME))
    assert ne == pytest.approx(1.62286, abs=1e-12) and ve == pytest.approx(60.08, rel=1e-9)
    assert m.nd < ne                                   # d (587.6 nm) is redder than e (546.1 nm)


def test_lensvisualizer_line_glass_and_e_lines(tmp_path):
    d = lv_doc()
    lines = dict(nC=1.692973, nF=1.705521, ng=1.712337)
    d["elements"][0].update(nd=1.696797, **lines)
    d["surfaces"][0]["nd"] = 1.696797
    m = F.load_lens(write(tmp_path, "l.json", d)).surfaces[0].medium
    for lam, n in ((656.2725, lines["nC"]), (LAMBDA_D, 1.696797), (486.1327, lines["nF"]), (435.8343, lines["ng"])):
        assert m.index(lam) == pytest.approx(n, abs=1e-9)
    d["elements"][0].update(indexReference="e", nd=1.700, nC=1.6930, nF=1.7055, ng=1.7123)   # ne with C, F, g
    d["surfaces"][0]["nd"] = 1.700
    m = F.load_lens(write(tmp_path, "le.json", d)).surfaces[0].medium
    for lam, n in ((LAMBDA_E, 1.700), (656.2725, 1.6930), (486.1327, 1.7055), (435.8343, 1.7123)):
        assert m.index(lam) == pytest.approx(n, abs=1e-9)


@pytest.mark.parametrize("case", ["odd term", "A18", "A2", "no STO", "two STO", "elem missing", "nd mismatch",
                                  "asph label", "asph missing", "bad sd", "curved STO", "air nd"])
def test_lensvisualizer_bad(tmp_path, case):
    d = lv_doc()
    if case == "odd term":
        d["asph"] = {"2A": {"K": 0, "A4": 1e-6, "A5": 3e-9}}
        surface, field, text = 1, "asph.2A.A5", "odd aspheric term A5"
    elif case == "A18":
        d["asph"] = {"2A": {"K": 0, "A4": 1e-6, "A18": 1e-25}}
        surface, field, text = 1, "asph.2A.A18", "A4 … A16 only"
    elif case == "A2":
        d["asph"] = {"2A": {"K": 0, "A2": 1e-3}}
        surface, field, text = 1, "asph.2A.A2", "A4 … A16 only"
    elif case == "no STO":
        d["surfaces"][2]["label"] = "3"
        surface, field, text = None, "label", "no surface is labelled 'STO'"
    elif case == "two STO":
        d["surfaces"].append({"label": "STO", "R": 1e15, "d": 1, "nd": 1, "elemId": 0, "sd": 5})
        surface, field, text = 3, "label", "second surface labelled 'STO'"
    elif case == "elem missing":
        d["surfaces"][0]["elemId"] = 7
        surface, field, text = 0, "elemId", "element 7 is not in elements[]"
    elif case == "nd mismatch":
        d["surfaces"][0]["nd"] = 1.6
        surface, field, text = 0, "nd", "disagrees"
    elif case == "asph label":
        d["asph"]["9A"] = {"K": 0, "A4": 1e-6}
        surface, field, text = None, "asph.9A", "no surface has that label"
    elif case == "asph missing":
        d["asph"] = {}
        surface, field, text = 1, "asph", "marks an aspheric surface"
    elif case == "bad sd":
        d["surfaces"][1]["sd"] = "10"
        surface, field, text = 1, "sd", "must be a number"
    elif case == "curved STO":
        d["surfaces"][2]["R"] = 100
        surface, field, text = 2, "R", "must be flat"
    else:
        d["surfaces"][1]["nd"] = 1.2
        surface, field, text = 1, "nd", "elemId 0 means air"
    p = write(tmp_path, "bad-lv.json", d)
    with pytest.raises(LensError) as e:
        F.load_lens(p)
    assert text in where_ok(e, p, surface=surface, field=field)


@need_shared
@pytest.mark.parametrize("fname", sorted(LV_REF))
def test_lensvisualizer_shared_files(fname):
    wl, efl, bfl, fno = LV_REF[fname]
    lens = F.load_lens(SHARED / "other" / fname)
    doc = json.loads((SHARED / "other" / fname).read_text())
    p = lens.paraxial(wl)
    assert p.efl == pytest.approx(efl, abs=1.5e-4) and p.bfl == pytest.approx(bfl, abs=1.5e-4)
    assert p.fnumber == pytest.approx(fno, abs=6e-3)
    assert lens.surfaces[-1].thickness == doc["surfaces"][-1]["d"]          # the file's last d is kept
    assert lens.surfaces[lens.stop_index].label == "STO"
    for s, row in zip(lens.surfaces, doc["surfaces"]):                       # indices at the reference line
        assert s.medium.index(wl) == pytest.approx(row["nd"], abs=1e-9)
    assert sum(s.is_aspheric for s in lens.surfaces) == len(doc["asph"])


@need_shared
def test_lensvisualizer_zoom_and_focus():
    f = SHARED / "other" / "CanonEF2470mmf28L.json"
    tele = F.load_lens(f, zoom=2)
    assert tele.efl() == pytest.approx(68.1207, abs=1.5e-4)                  # FORMATS.md, tele position
    assert F.load_lens(f, zoom=1).efl() == pytest.approx(35.1182, abs=1.5e-4)
    close = F.load_lens(SHARED / "other" / "CanonFD300mmf4SSC.json", focus="close")
    assert close.surfaces[-1].thickness == pytest.approx(91.262918)
    with pytest.raises(LensError) as e:
        F.load_lens(f, zoom=3)
    where_ok(e, f, field="zoom")


# ============================================================================ command line
def test_module_entry_point(tmp_path, capsys):
    from mi_neurallens.optics.formats.__main__ import main
    src = write(tmp_path, "w.dat", WIDE22_DAT)
    out = tmp_path / "w.json"
    assert main(["convert", str(src), str(out), "--name", "w22"]) == 0
    assert F.load_lens(out).name == "w22" and schema_ok(json.loads(out.read_text()))
    assert main(["convert", str(tmp_path / "nope.dat"), str(out)]) == 2
    assert "file not found" in capsys.readouterr().err


def test_docs_example():
    """The complete example in docs/lens-format.md validates against the schema and loads as described; so does
    its coating-stack example, on a surface."""
    import re
    text = (Path(nl.__file__).parents[1] / "docs" / "lens-format.md").read_text()
    blocks = re.findall(r"```json\n(.*?)```", text, re.S)
    stack = json.loads([b for b in blocks if '"layers"' in b][0])
    d = small_doc()
    d["surfaces"][0]["coating"] = stack
    assert schema_ok(d) and len(F.load_lens(d).surfaces[0].coating.layers) == 3
    doc = json.loads([b for b in blocks if '"surfaces"' in b][0])
    assert schema_ok(doc)
    lens = F.load_lens(doc)
    p = lens.paraxial(LAMBDA_D)
    assert p.efl == pytest.approx(99.93, abs=5e-3) and p.bfl == pytest.approx(95.967, abs=5e-4)
    assert p.fnumber == pytest.approx(5.0, abs=5e-3)
    assert lens.stop.blades == 6 and lens.surfaces[3].housing_radius == 13.5
    assert lens.surfaces[3].coating == nl.Coating() and lens.surfaces[1].medium.name == "N-BK7"
