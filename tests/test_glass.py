"""Optical media: catalog conversion against opticalglass, model / line / table glasses, the Open
Optical Designer materials, resolve_medium's errors, serialisation, and Dr.Jit evaluation."""
from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from mi_neurallens.errors import GlassError
from mi_neurallens.render_utils import default_variant
from mi_neurallens.optics import catalogs, glass as G
from mi_neurallens.optics.glass import (AIR, LAMBDA_C, LAMBDA_D, LAMBDA_E, LAMBDA_F, Medium,
                                        catalog_glass, constant, lines_glass, model_glass,
                                        ood_material, resolve_medium, table_glass)

LAMBDA_G = 435.8343
VIS = np.linspace(400.0, 800.0, 81)
WIDE = np.linspace(360.0, 830.0, 471)

gf = pytest.importorskip("opticalglass.glassfactory")


def _og_glasses(catalog):
    """(name, opticalglass glass) for every glass of a catalog opticalglass itself can create."""
    cat = gf.get_glass_catalog(catalog)
    out = []
    for n in cat.get_glass_names():
        try:
            out.append((str(n), cat.create_glass(n, catalog)))
        except ValueError:  # the two Hikari sheets with '-' coefficients, tested separately
            pass
    return out


# ------------------------------------------------------------------ catalog glasses
@pytest.mark.parametrize("catalog,formula", [("Schott", "sellmeier"), ("Ohara", "sellmeier"),
                                             ("Hoya", "power_n2"), ("CDGM", "power_n2"),
                                             ("Hikari", "power_n2"), ("Sumita", "power_n2")])
def test_every_catalog_glass_matches_opticalglass(catalog, formula):
    glasses = _og_glasses(catalog)
    assert len(glasses) > 100
    worst = 0.0
    for name, g in glasses:
        m = catalog_glass(name, catalog)
        assert m.formula == formula and m.source == {"catalog": catalog, "glass": name}
        worst = max(worst, float(np.max(np.abs(m.index(VIS) - g.calc_rindex(VIS)))))
        assert abs(m.nd - g.rindex("d")) < 1e-12
    assert worst < 1e-12, (catalog, worst)  # same formula, only the evaluation order differs


def test_known_values_and_coefficient_order():
    m = catalog_glass("S-LAL14", "Ohara")
    # opticalglass stores [B1, B2, B3, C1, C2, C3]; ours is (B1, C1, B2, C2, B3, C3)
    assert m.coefficients == pytest.approx((1.2372097, 0.015355132, 0.589722623, -0.00030789625,
                                            1.3192188, 93.7202947), abs=0, rel=1e-12)
    assert m.index([LAMBDA_D, LAMBDA_F, LAMBDA_C]) == pytest.approx(
        [1.696797, 1.705521, 1.692974], abs=1e-6)
    bk7 = catalog_glass("N-BK7", "Schott")
    assert bk7.nd == pytest.approx(1.5168, abs=1e-5) and bk7.vd == pytest.approx(64.17, abs=0.01)


@pytest.mark.parametrize("name", ["J-PSKH8", "J-KZFH9"])
def test_hikari_sheets_with_dash_coefficients(name):
    # opticalglass cannot create these ('-' in the coefficient cells); we read '-' as 0 and
    # check against the catalog's own measured line indices.
    with pytest.raises(ValueError):
        gf.create_glass(name, "Hikari")
    m = catalog_glass(name, "Hikari")
    ri = gf.get_glass_catalog("Hikari").df.loc[name]["refractive indices"]
    lines = {"d": LAMBDA_D, "F": LAMBDA_F, "C": LAMBDA_C, "g": LAMBDA_G, "e": LAMBDA_E}
    for k, lam in lines.items():
        assert m.index(lam) == pytest.approx(float(ri[k]), abs=3e-6), k


@pytest.mark.parametrize("query,catalog,expect", [
    ("S-LAL14", None, ("Ohara", "S-LAL14")),
    ("s-lal14", None, ("Ohara", "S-LAL14")),
    ("LAL14", "Ohara", ("Ohara", "S-LAL14")),          # without the vendor prefix
    ("SLAL14", None, ("Ohara", "S-LAL14")),            # without the hyphen
    ("S-FSL5", None, ("Ohara", "S-FSL 5")),            # Ohara's sheet writes 'S-FSL 5'
    ("S-FSL 5", "ohara", ("Ohara", "S-FSL 5")),
    ("BK7", None, ("Schott", "N-BK7")),                # N- preferred over P-BK7
    ("F2", None, ("Schott", "F2")),                    # Schott before CDGM's F2
    ("F2", "CDGM", ("CDGM", "F2")),
    ("F1", None, ("CDGM", "F1")),                      # exact CDGM name beats Hoya E-F1
    ("H-BAK1", None, ("CDGM", "H-BaK1")),
    ("FDS20-W", "Hoya", ("Hoya", "FDS20-W ")),         # trailing blank in the Hoya sheet
    ("K-LASFN9", None, ("Sumita", "K-LaSFn9")),
    ("LASFN9", None, ("Sumita", "K-LaSFn9")),
    ("J-LASF016", None, ("Hikari", "J-LASF016")),
    ("FCD1", None, ("Hoya", "FCD1")),
])
def test_name_resolution(query, catalog, expect):
    m = catalog_glass(query, catalog)
    assert (m.source["catalog"], m.source["glass"]) == expect
    assert m.name == expect[1]


def test_catalog_order_for_names_in_several_catalogs():
    # A name in several catalogs resolves in the order Schott, Ohara, Hoya, CDGM, Hikari, Sumita.
    seen = {}
    for c in G.CATALOGS:
        for n in gf.get_glass_catalog(c).get_glass_names():
            seen.setdefault(catalogs._norm(n), []).append(c)
    multi = {k: v for k, v in seen.items() if len(v) > 1}
    assert multi  # e.g. F2 (Schott, CDGM)
    for k, cats in multi.items():
        assert catalog_glass(k).source["catalog"] == cats[0]


def test_unknown_glass_error_names_catalogs_and_suggestions():
    with pytest.raises(GlassError) as ei:
        catalog_glass("S-LAL1x4")
    msg = str(ei.value)
    assert "S-LAL1x4" in msg
    for c in G.CATALOGS:
        assert c in msg
    assert "close names" in msg and "(Ohara)" in msg
    assert msg.count("(Ohara)") + msg.count("(Schott)") + msg.count("(Hoya)") + \
        msg.count("(CDGM)") + msg.count("(Hikari)") + msg.count("(Sumita)") <= 3
    with pytest.raises(GlassError, match=r"unknown glass 'N-BK7'.*catalog Ohara"):
        catalog_glass("N-BK7", "Ohara")
    with pytest.raises(GlassError, match=r"unknown glass catalog 'Zeiss'.*Schott, Ohara, Hoya"):
        catalog_glass("N-BK7", "Zeiss")
    with pytest.raises(GlassError, match="non-empty string"):
        catalog_glass("  ")


def test_catalog_lookups_are_cached():
    catalog_glass("N-SF11", "Schott")
    before = catalogs._catalog_lookup.cache_info().hits
    a, b = catalog_glass("N-SF11", "Schott"), catalog_glass("N-SF11", "Schott")
    assert catalogs._catalog_lookup.cache_info().hits == before + 2
    assert a == b
    a.source["mutated"] = True  # each call gets its own source dict
    assert "mutated" not in catalog_glass("N-SF11", "Schott").source


def test_module_import_does_not_import_opticalglass():
    code = ("import sys, mi_neurallens.optics.glass as g; "
            "assert 'opticalglass' not in sys.modules, 'imported'; "
            "g.resolve_medium(1.5); g.resolve_medium({'nd': 1.5, 'vd': 60}); "
            "g.ood_material('PMMA'); assert 'opticalglass' not in sys.modules")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr


# ------------------------------------------------------------------ model glass
@pytest.mark.parametrize("nd,vd", [(1.4339, 94.99), (1.497, 81.61), (1.5168, 64.17),
                                   (1.696797, 55.53), (1.7552, 27.58), (1.92286, 18.9),
                                   (2.0, 15.0), (1.3, 200.0), (1.8, 5.0), (1.5, 1e6)])
def test_model_glass_exact_nd_vd_and_monotonic(nd, vd):
    m = model_glass(nd, vd)
    assert m.formula == "buchdahl"
    assert float(m.index(587.5618)) == nd                  # exactly
    assert float(m.index(LAMBDA_F) - m.index(LAMBDA_C)) == pytest.approx((nd - 1) / vd, abs=1e-12)
    n = m.index(WIDE)
    assert np.all(np.diff(n) < 0) and np.all(n > 1)


def test_model_glass_infinite_vd_is_flat_and_errors():
    m = model_glass(1.5, math.inf)
    assert np.all(m.index(WIDE) == 1.5)
    for nd, vd, what in [(1.0, 50, "nd must be > 1"), (0.9, 50, "nd must be > 1"),
                         (1.5, 0, "Vd must be > 0"), (1.5, -3, "Vd must be > 0"),
                         (float("nan"), 50, "must be finite"), (1.5, float("nan"), "Vd must be"),
                         (True, 50, "must be a number"), ("1.5", 50, "must be a number")]:
        with pytest.raises(GlassError, match=what):
            model_glass(nd, vd)


def test_model_glass_against_opticalglass_modelglass():
    from opticalglass.modelglass import ModelGlass
    lam = np.linspace(400.0, 700.0, 61)
    # model="opticalglass" is opticalglass' ModelGlass, to rounding
    for nd, vd in [(1.5168, 64.17), (1.696797, 55.53), (1.92286, 18.9), (1.45, 90.0)]:
        ref = ModelGlass(nd, vd, "x").calc_rindex(lam)
        assert np.max(np.abs(model_glass(nd, vd, model="opticalglass").index(lam) - ref)) < 1e-13
    # ModelGlass keeps nd but not Vd: opticalglass' Buchdahl2.update solves with
    # (m*dw - dw2) where the constraint needs (m*dw + dw2).  Ours keeps both exactly.
    ref = ModelGlass(1.5, 30.0, "x")
    assert 0.5 / (ref.rindex("F") - ref.rindex("C")) == pytest.approx(29.27, abs=0.01)
    # The default (normal-line) model vs ModelGlass over 400-700 nm, ordinary glasses:
    # measured gap max 4.9e-3 (nd 1.8, Vd 20), median 1.3e-3.
    gaps = []
    for nd in (1.50, 1.60, 1.70, 1.80):
        for vd in (20.0, 30.0, 40.0, 50.0, 60.0, 70.0, 80.0):
            ours = model_glass(nd, vd)
            ref = ModelGlass(nd, vd, "x")
            assert float(ours.index(LAMBDA_D)) == ref.rindex("d") == nd
            assert float(ours.index(LAMBDA_F) - ours.index(LAMBDA_C)) == pytest.approx(
                (nd - 1) / vd, abs=1e-12)
            gaps.append(float(np.max(np.abs(ours.index(lam) - ref.calc_rindex(lam)))))
    assert 1e-4 < max(gaps) < 6e-3 and np.median(gaps) < 2e-3
    # ... and ModelGlass is not monotonic for fluorite-like glass, ours is.
    og = ModelGlass(1.4339, 94.99, "x").calc_rindex(WIDE)
    assert np.any(np.diff(og) >= 0)
    assert np.all(np.diff(model_glass(1.4339, 94.99).index(WIDE)) < 0)


def test_model_glass_closer_to_real_glasses_than_modelglass():
    from opticalglass.modelglass import ModelGlass
    lam = np.linspace(400.0, 700.0, 31)
    ours, theirs = [], []
    for c in G.CATALOGS:
        for _, g in _og_glasses(c)[::6]:
            nd, nF, nC = g.calc_rindex(np.array([LAMBDA_D, LAMBDA_F, LAMBDA_C]))
            vd = (nd - 1) / (nF - nC)
            real = g.calc_rindex(lam)
            ours.append(np.max(np.abs(model_glass(nd, vd).index(lam) - real)))
            theirs.append(np.max(np.abs(ModelGlass(nd, vd, "x").calc_rindex(lam) - real)))
    assert len(ours) > 150
    assert np.median(ours) < 3e-4 and np.median(ours) < 0.3 * np.median(theirs)


# ------------------------------------------------------------------ line glasses
def _lines_of(g):
    return dict(zip("dCFge", g.calc_rindex(np.array([LAMBDA_D, LAMBDA_C, LAMBDA_F, LAMBDA_G,
                                                     LAMBDA_E]))))


@pytest.mark.parametrize("keys", ["dCF", "dCFg", "dCFe", "dCFge"])
def test_lines_glass_interpolates_given_lines(keys):
    lam = {"d": LAMBDA_D, "C": LAMBDA_C, "F": LAMBDA_F, "g": LAMBDA_G, "e": LAMBDA_E}
    for name, cat in [("S-LAL14", "Ohara"), ("N-SF11", "Schott"), ("FCD1", "Hoya"),
                      ("H-ZF88", "CDGM"), ("J-LASF016", "Hikari"), ("K-CaFK95", "Sumita")]:
        n = {k: round(float(v), 5) for k, v in _lines_of(gf.create_glass(name, cat)).items()}
        kw = {"n" + k: n[k] for k in keys}
        m = lines_glass(**kw)
        assert m.formula == "power_n2"
        for k in keys:
            assert abs(float(m.index(lam[k])) - n[k]) < 1e-7, (name, k)
        assert np.all(np.diff(m.index(WIDE)) < 0)


def test_lines_glass_close_to_catalog_s_lal14():
    g = gf.create_glass("S-LAL14", "Ohara")
    n = _lines_of(g)
    m = lines_glass(n["d"], n["C"], n["F"], ng=n["g"])
    lam = np.linspace(400.0, 700.0, 301)
    assert np.max(np.abs(m.index(lam) - g.calc_rindex(lam))) < 2e-4
    m5 = lines_glass(n["d"], n["C"], n["F"], ng=n["g"], ne=n["e"])
    assert np.max(np.abs(m5.index(lam) - g.calc_rindex(lam))) < 2e-5
    m3 = lines_glass(n["d"], n["C"], n["F"])  # g imputed from the normal line
    assert "g" in m3.source["imputed"]
    assert np.max(np.abs(m3.index(lam) - g.calc_rindex(lam))) < 5e-4


def test_lines_glass_rejects_abnormal_dispersion():
    with pytest.raises(GlassError, match="nF > nd > nC"):
        lines_glass(1.5, 1.51, 1.49)
    with pytest.raises(GlassError, match="not strictly decreasing|do not describe"):
        lines_glass(1.5168, 1.51432, 1.52238, ng=1.5200)   # ng < nF
    with pytest.raises(GlassError, match="must be a number"):
        lines_glass(1.5168, None, 1.52238)
    with pytest.raises(GlassError, match="≥ 1"):
        lines_glass(0.5, 0.4, 0.6)


# ------------------------------------------------------------------ tables and OOD
def test_table_interpolation_and_extrapolation_by_hand():
    m = table_glass([(400.0, 1.53), (500.0, 1.52), (700.0, 1.51)], "t")
    assert m.index(450.0) == pytest.approx(1.525, abs=1e-15)
    assert m.index(600.0) == pytest.approx(1.515, abs=1e-15)
    assert m.index(300.0) == pytest.approx(1.53 + 100 * 1e-4, abs=1e-14)      # first segment
    assert m.index(900.0) == pytest.approx(1.51 - 200 * 0.5e-4, abs=1e-14)    # last segment
    assert np.all(table_glass([(550.0, 1.7)], "one").index(WIDE) == 1.7)


def test_table_validation():
    cases = [([], "at least one"), ([(500, 1.5), (500, 1.6)], "strictly increasing"),
             ([(600, 1.5), (500, 1.6)], "strictly increasing"), ([(500, float("nan"))], "finite"),
             ([(500, 0.0)], "index must be > 0"), ([(-5, 1.5)], "wavelength must be > 0"),
             ([(500, 1.5, 0.1)], "pair"), ("abc", "list of"), ([(500, True)], "number")]
    for pairs, what in cases:
        with pytest.raises(GlassError, match=what):
            table_glass(pairs, "x")


def test_ood_pmma_and_air():
    pmma = ood_material("PMMA")
    assert pmma.formula == "table"
    assert pmma.index([425.0, 589.0, 635.0]) == pytest.approx([1.5026, 1.4921, 1.4905], abs=1e-12)
    assert pmma.index(500.0) == pytest.approx(1.5026 + (75 / 164) * (1.4921 - 1.5026), abs=1e-12)
    air = ood_material("Air")
    assert air.index(550.0) == pytest.approx(1.000278, abs=2e-6) and air.index(550.0) > 1.0002
    assert air != AIR
    assert ood_material("GERM").name == "Germanium"          # alternate_name
    assert ood_material("pmma") == pmma                       # case-insensitive fallback
    bk7 = ood_material("N-BK7")                               # [λ, n, k] rows: k ignored
    assert bk7.index(550.0) == pytest.approx(1.5185, abs=1e-12)
    with pytest.raises(GlassError) as ei:
        ood_material("Unobtainium")
    assert "Unobtainium" in str(ei.value) and "PMMA" in str(ei.value) and "Air" in str(ei.value)


def test_ood_data_file_is_a_faithful_copy():
    pkg = Path(G.__file__).resolve().parents[1] / "data" / "ood-materials.json"
    data = json.loads(pkg.read_text())
    shared = Path(__file__).resolve().parents[2] / "shared/lens-data/open-optical-designer/material-data.json"
    if shared.exists():
        assert data == json.loads(shared.read_text())
    names = [m["name"] for m in data]
    assert {"Air", "PMMA", "PC", "N-BK7", "Germanium"} <= set(names)
    for m in data:
        pairs = [(r[0] * 1000.0, r[1]) for r in m["refractive_index"]]
        assert ood_material(m["name"]).index(pairs[0][0]) == pytest.approx(pairs[0][1], abs=1e-12)


# ------------------------------------------------------------------ resolve_medium
def test_resolve_valid_forms():
    assert resolve_medium("air") is AIR and resolve_medium(" AIR ") is AIR
    assert resolve_medium(1) is AIR and resolve_medium(1.0) is AIR
    assert resolve_medium(1.5) == constant(1.5)
    assert resolve_medium(np.float64(1.6)).coefficients == (1.6,)
    assert resolve_medium({"n": 1.7, "name": "oil"}) == constant(1.7, "oil")
    assert resolve_medium({"n": 1}) is AIR
    assert resolve_medium("S-LAL14") == catalog_glass("S-LAL14", "Ohara")
    m = resolve_medium({"glass": "LAL14", "catalog": "Ohara", "name": "front"})
    assert m.name == "front" and m.source["glass"] == "S-LAL14"
    assert m.coefficients == catalog_glass("S-LAL14").coefficients
    assert resolve_medium({"nd": 1.6, "vd": 40}) == model_glass(1.6, 40)
    assert resolve_medium({"nd": 1.6, "vd": 40, "model": "opticalglass"}) == \
        model_glass(1.6, 40, model="opticalglass")
    lm = resolve_medium({"nd": 1.5168, "nC": 1.51432, "nF": 1.52238, "ng": 1.52668, "name": "L"})
    assert lm.name == "L" and lm.index(LAMBDA_D) == pytest.approx(1.5168, abs=1e-9)
    t = resolve_medium({"table": [[400, 1.5], [700, 1.4]]})
    assert t.formula == "table" and t.index(550.0) == pytest.approx(1.45)
    assert resolve_medium({"ood": "PMMA"}) == ood_material("PMMA")


def _err(spec, *parts, **where):
    with pytest.raises(GlassError) as ei:
        resolve_medium(spec, **where)
    msg = str(ei.value)
    for p in parts:
        assert p in msg, (p, msg)
    return ei.value


@pytest.mark.parametrize("spec,parts", [
    (float("nan"), ["nan", "n ≥ 1"]),
    (float("inf"), ["inf", "n ≥ 1"]),
    (True, ["True", "boolean", "'air'"]),
    (0, ["0", "n ≥ 1"]),
    (-1.5, ["-1.5", "n ≥ 1"]),
    (0.8, ["0.8", "n ≥ 1"]),
    ("", ["empty", "'air'"]),
    ("Unobtainium", ["Unobtainium", "Schott", "Sumita"]),
    (None, ["None", "'air'", "catalog glass"]),
    ([1.5], ["[1.5]", "expected"]),
    ({}, ["{}", "expected", "'nd', 'vd'"]),
    ({"n": 0.9}, ["0.9", "≥ 1"]),
    ({"n": "1.5"}, ["'1.5'", "must be a number"]),
    ({"n": True}, ["True", "must be a number"]),
    ({"n": float("nan")}, ["finite"]),
    ({"n": 1.5, "colour": "red"}, ["'colour'", "valid keys: n, name"]),
    ({"n": 1.5, "glass": "F2"}, ["mixes", "catalog", "constant"]),
    ({"nd": 1.5}, ["'nd' without 'vd'", "'nC' and 'nF'"]),
    ({"nd": 1.5, "nC": 1.49}, ["missing", "'nF'"]),
    ({"vd": 60}, ["missing", "'nd'"]),
    ({"nd": 1.5, "vd": 60, "nC": 1.49}, ["mixes", "model", "lines"]),
    ({"nd": 1.5, "vd": -1}, ["Vd must be > 0"]),
    ({"nd": 1.5, "vd": 60, "name": 3}, ["'name' must be a non-empty string"]),
    ({"glass": "N-BK7", "catalog": "Zeiss"}, ["Zeiss", "Schott, Ohara"]),
    ({"glass": 7}, ["non-empty string", "7"]),
    ({"glass": "N-BK8"}, ["N-BK8", "close names", "N-BK7 (Schott)"]),
    ({"table": []}, ["at least one"]),
    ({"table": [[500, 1.5], [400, 1.6]]}, ["strictly increasing"]),
    ({"ood": "Glass"}, ["Glass", "available", "PMMA"]),
    ({"formula": "cauchy", "coefficients": [1.5]}, ["cauchy", "valid", "sellmeier"]),
    ({"formula": "sellmeier", "coefficients": [1.0, 0.1, 2.0]}, ["pairs (B_i, C_i)"]),
    ({"formula": "power_n2", "coefficients": [0.5, 2.0]}, ["integer powers"]),
    ({"formula": "buchdahl", "coefficients": [0.5876, 1.5]}, ["5 values"]),
    ({"formula": "constant", "coefficients": [1.5], "source": "x"}, ["'source' must be a dict"]),
    ({"formula": "constant", "coefficients": "1.5"}, ["list of numbers"]),
    ({"formula": "constant", "coefficients": [float("nan")]}, ["finite"]),
    ({"formula": "table", "coefficients": [500, 1.5, 400, 1.6]}, ["strictly increasing"]),
    ({1: 2}, ["keys must be strings"]),
])
def test_resolve_errors(spec, parts):
    e = _err(spec, *parts, file="lens.json", surface=4, label="L2 front")
    assert str(e).startswith("lens.json: surface 4 (L2 front): field 'medium': ")
    assert e.file == "lens.json" and e.surface == 4 and e.field == "medium"


def test_resolve_error_field_is_configurable():
    e = _err("nope-glass", "nope-glass", field="env_initial_material")
    assert "field 'env_initial_material'" in str(e)


# ------------------------------------------------------------------ serialisation
def _one_of_each():
    return [AIR, constant(1.33, "water"), catalog_glass("N-BK7"), catalog_glass("S-LAL14"),
            catalog_glass("FCD1"), catalog_glass("H-ZF88"), catalog_glass("J-LASF016"),
            catalog_glass("K-LaSFn9"), model_glass(1.7, 30), model_glass(1.5, 60, model="opticalglass"),
            lines_glass(1.5168, 1.51432, 1.52238), lines_glass(1.5168, 1.51432, 1.52238, ng=1.52668),
            table_glass([(500.0, 1.5)], "one"), ood_material("Air"), ood_material("Fluorite")]


def test_to_dict_from_dict_round_trip_every_formula():
    media = _one_of_each()
    assert {m.formula for m in media} == set(G.FORMULAS)
    for m in media:
        d = json.loads(json.dumps(m.to_dict()))
        back = Medium.from_dict(d)
        assert back == m and back.coefficients == m.coefficients and back.source == m.source
        assert np.array_equal(back.index(WIDE), m.index(WIDE))
        fast = resolve_medium(d)  # the project-JSON fast path
        assert fast == m and fast.source == m.source


# ------------------------------------------------------------------ Dr.Jit evaluation
def test_dr_index_matches_index_for_every_formula():
    mi = pytest.importorskip("mitsuba")
    mi.set_variant(default_variant())
    lam = np.linspace(300.0, 900.0, 241)  # includes table extrapolation
    lam32 = np.asarray(mi.Float(lam), dtype=np.float64)
    media = _one_of_each()
    assert {m.formula for m in media} == set(G.FORMULAS)
    for m in media:
        ref = m.index(lam)
        d64 = np.asarray(m.dr_index(mi.Float64(lam)), dtype=np.float64)
        assert d64.shape == lam.shape
        assert np.max(np.abs(d64 - ref)) < 1e-12, m
        d32 = np.asarray(m.dr_index(mi.Float(lam)), dtype=np.float64)
        assert np.max(np.abs(d32 - m.index(lam32))) < 1e-6, m
