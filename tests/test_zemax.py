"""Zemax OpticStudio .zmx import (mi_neurallens.optics.formats.zemax) against ray-optics.

ray-optics (a dev/test dependency) ships .zmx files as its own test data; every one of them is either
read and compared with ray-optics' import of the same file, or refused with the keyword that puts it
outside what a rotationally symmetric refractive lens can be.  The comparison:

* paraxial EFL and BFL at the primary wavelength, and real rays (three fields, skew rays, three
  wavelengths) at the image plane, with ray-optics' media replaced by constant indices equal to ours
  at each wavelength, so the comparison isolates the reader's geometry (units, curvatures, thicknesses,
  conics, polynomial terms, the image distance, dropped dummy surfaces, the inserted stop);
* the glasses themselves where both resolve the same catalogue glass (indices to 1e-9), and EFL/BFL
  with ray-optics' own media where every glass is the same.

ray-optics writes a ``*_tmpl.smx`` next to a file with an unknown glass, so its imports run on copies in
a temporary folder, and its readers' log files are switched off.
"""
from __future__ import annotations

import contextlib
import json
import math
import os
from pathlib import Path
import shutil
import warnings

import numpy as np
import pytest

import mi_neurallens as nl
from mi_neurallens.errors import LensError
from mi_neurallens.optics import formats as F
from mi_neurallens.optics.glass import AIR, catalog_glass, constant, model_glass

rayoptics = pytest.importorskip("rayoptics")
RO = Path(rayoptics.__file__).resolve().parent

# file (relative to the rayoptics package) -> reader options.  Glass substitutions are what ray-optics
# substitutes itself, except B270: ray-optics falls back to n = 1.5, here a model glass close to
# Schott B 270.
ACCEPTED = {
    "zemax/tests/US00583336-2-scaled.zmx": {},
    "zemax/tests/US08427765-1.ZMX": {"glasses": {"L-TIM28_MOLD": {"glass": "S-TIM28", "catalog": "Ohara"}}},
    "zemax/tests/zmax_55278.zmx": {},
    "zemax/tests/354710-C-Zemax(ZMX).zmx": {"glasses": {"D-ZK3M": {"glass": "D-ZK3", "catalog": "CDGM"}}},
    "elem/tests/ACL3026U-Zemax(ZMX).zmx": {"glasses": {"B270": {"nd": 1.5230, "vd": 58.5}}},
    # CODE V
    "codev/tests/CODV_32327.seq": {},
    "codev/tests/CODV_49664.seq": {},
    "codev/tests/CODV_65564.seq": {},
    "codev/tests/CODV_65988_noDOE.seq": {},
    "codev/tests/ag_dblgauss.seq": {},
    "codev/tests/unfolded_lenses_w_ape.seq": {},
    "codev/tests/landscape_lens.seq": {"radius_mode": False},   # no RDM: curvatures, as ray-optics assumes
}
# file -> (keyword, surface number or None) of the first thing outside the supported subset
REFUSED = {
    "zemax/models/PhotoPrime/US05331467-1.zmx": ("OBSC", 2),   # central obscuration (a catadioptric)
    "zemax/tests/ASL5040-UV-Zemax(ZMX).zmx": ("TYPE", 1),       # QED_TYPE polynomial asphere
    "zemax/tests/HoO-V2C18Ex03.zmx": ("GLAS", 2),               # GLAS MIRROR
    "zemax/tests/HoO-V2C18Ex27.zmx": ("GLAS", 4),               # GLAS MIRROR
    "zemax/tests/HoO-V2C18Ex46.zmx": ("TYPE", 2),               # COORDBRK
    "zemax/tests/HoO-V2C18Ex66.zmx": ("TYPE", 2),               # COORDBRK
    "zemax/tests/HoO-V2C18Ex66NEW.zmx": ("TYPE", 2),            # COORDBRK
    "zemax/tests/US05831776-1.zmx": ("OBNA", None),             # object-space NA aperture
    "zemax/tests/US08011793-1.zmx": ("GLAS", 2),                # GLAS MIRROR
    "zemax/tests/zmax_37992.zmx": ("TYPE", 2),                  # COORDBRK
    # CODE V
    "codev/tests/CODV_65988.seq": ("DIF", 1),                   # diffractive surface
    "codev/tests/achroMangin.seq": ("REFL", 3),
    "codev/tests/achroMangin_ok.seq": ("REFL", 3),
    "codev/tests/dar_test.seq": ("ADE", 2),
    "codev/tests/dec_rev_tilt_test.seq": ("YDE", 2),
    "codev/tests/dec_test.seq": ("YDE", 2),
    "codev/tests/dec_tilt_test.seq": ("REFL", 2),
    "codev/tests/folded_lenses.seq": ("REFL", 2),
    "codev/tests/lens_reflection_test.seq": ("REFL", 2),
    "codev/tests/mangin.seq": ("REFL", 2),
    "codev/tests/paraboloid.seq": ("REFL", 1),
    "codev/tests/paraboloid_f8.seq": ("REFL", 1),
    "codev/tests/questar35.seq": ("CIR", 2),                    # CIR OBS: obscuration
    "codev/tests/rc_f16.seq": ("REFL", 1),
    "codev/tests/schmidt.seq": ("REFL", 3),
    "codev/tests/schmidt_sph.seq": ("REFL", 3),
    "codev/tests/singlet.seq": ("RDM", None),                   # and, with radius_mode=, no STO
    "codev/tests/test.seq": ("SI", None),                       # no image surface
    "codev/tests/threemir.seq": ("REFL", 2),
    "codev/tests/tilt_test.seq": ("ADE", 2),
    "codev/tests/asp46.seq": (None, None),                      # a flat aspheric plate: afocal
}
# without a substitution these name an unknown glass: file -> (surface, glass)
UNKNOWN_GLASS = {
    "zemax/tests/US08427765-1.ZMX": (3, "L-TIM28_MOLD"),
    "zemax/tests/354710-C-Zemax(ZMX).zmx": (1, "D-ZK3M"),
    "elem/tests/ACL3026U-Zemax(ZMX).zmx": (2, "B270"),
}
# every glass of these files is the same catalogue glass in both readers
SAME_GLASSES = ("zemax/tests/US00583336-2-scaled.zmx", "zemax/tests/US08427765-1.ZMX", "codev/tests/CODV_32327.seq",
                "codev/tests/CODV_65564.seq", "codev/tests/ag_dblgauss.seq")
WAVELENGTHS = (486.1327, 587.5618, 656.2725)


def where_ok(excinfo, file, *, surface=None, field=None):
    e, msg = excinfo.value, str(excinfo.value)
    assert str(file) in msg, msg
    if surface is not None:
        assert e.surface == surface and f"surface {surface}" in msg, msg
    if field is not None:
        assert e.field == field and f"field '{field}'" in msg, msg
    return msg


def load(rel, **kw):
    return nl.Lens.load(RO / rel, **ACCEPTED.get(rel, {}), **kw)


def md_of(lens):
    """The reader's own metadata (Zemax or CODE V)."""
    return lens.metadata.get("zemax") or lens.metadata["codev"]


# ----------------------------------------------------------------------------------------- ray-optics
@contextlib.contextmanager
def _cwd(path):
    old = os.getcwd()
    os.chdir(path)
    try:
        yield
    finally:
        os.chdir(old)


@pytest.fixture(scope="module")
def ro_open(tmp_path_factory):
    """rel -> ray-optics OpticalModel of a copy of the file (cached per module)."""
    import logging
    from rayoptics.environment import open_model
    folder = tmp_path_factory.mktemp("rayoptics")
    cache = {}
    # ray-optics' readers log to a file named at import time in the then working folder: silence them
    loggers = [logging.getLogger(n) for n in ("rayoptics.zemax.zmxread", "rayoptics.codev.cmdproc")]
    saved = [lg.disabled for lg in loggers]
    for lg in loggers:
        lg.disabled = True

    def get(rel):
        if rel not in cache:
            src = RO / rel
            dst = folder / src.name
            shutil.copyfile(src, dst)
            with _cwd(folder), warnings.catch_warnings():
                warnings.simplefilter("ignore")
                opm = open_model(dst)
            # one on-axis field: the file's fields (image heights in some files) are not needed, and
            # ray-optics cannot re-solve them for the altered object distance used below
            from rayoptics.raytr.opticalspec import FieldSpec
            osp = opm["optical_spec"]
            osp["fov"] = FieldSpec(osp, key=("object", "angle"), value=0.0, flds=[0.0])
            opm.update_model()
            cache[rel] = opm
        return cache[rel]
    yield get
    for lg, d in zip(loggers, saved):
        lg.disabled = d


def _medium_after(lens, k):
    """Our medium after Zemax surface k (dropped dummies keep the medium before them)."""
    nums = md_of(lens)["surface_numbers"]
    m = lens.object_medium
    for j in range(1, k + 1):
        if j in nums:
            m = lens.surfaces[len(nums) - 1 - nums[::-1].index(j)].medium
    return m


@contextlib.contextmanager
def _ro_media(opm, lens, wavelength):
    """ray-optics' gaps set to constant indices equal to ours at ``wavelength``; restored after."""
    from opticalglass.opticalmedium import ConstantIndex
    sm = opm["seq_model"]
    saved = [g.medium for g in sm.gaps]
    for k, g in enumerate(sm.gaps):
        n = float(_medium_after(lens, k).index(wavelength))
        g.medium = ConstantIndex(n, f"n{k}")
    osp = opm["optical_spec"]
    wv = osp["wvls"]
    saved_wv = (list(wv.wavelengths), list(wv.spectral_wts), wv.reference_wvl)
    wv.set_from_list([[wavelength, 1.0]])
    wv.reference_wvl = 0
    opm.update_model()
    try:
        yield opm
    finally:
        for g, m in zip(sm.gaps, saved):
            g.medium = m
        wv.wavelengths, wv.spectral_wts, wv.reference_wvl = saved_wv
        wv.calc_colors()
        opm.update_model()


def _ro_first_order(opm):
    fod = opm["analysis_results"]["parax_data"].fod
    return fod.efl, fod.bfl


def _rays(lens, wavelength, rng, n_per_field=40):
    """Forward rays through the paraxial entrance pupil at fields 0, ½ and 1 × a maximum field, each
    at a random azimuth (skew rays), started on a plane in front of the first surface."""
    p = lens.paraxial(wavelength)
    s0 = lens.surfaces[0]
    r = np.linspace(0, s0.semi_diameter, 50)
    # in front of the first surface and of the dummy surfaces the reader dropped before it
    z0 = min(0.0, float(np.nanmin(s0.sag(r)))) - 5.0 - md_of(lens)["first_vertex_z_in_file"]
    tmax = min(math.radians(12.0), math.atan(0.35 * lens.surfaces[-1].semi_diameter / abs(p.efl)))
    o, d = [], []
    for f in (0.0, 0.5, 1.0):
        th = np.full(n_per_field, f * tmax)
        az = rng.uniform(0, 2 * np.pi, n_per_field)
        dirs = np.stack([np.sin(th) * np.cos(az), np.sin(th) * np.sin(az), np.cos(th)], 1)
        rr = 0.95 * p.entrance_pupil_radius * np.sqrt(rng.uniform(0, 1, n_per_field))
        a = rng.uniform(0, 2 * np.pi, n_per_field)
        ep = np.stack([rr * np.cos(a), rr * np.sin(a), np.full(n_per_field, p.entrance_pupil_z)], 1)
        o.append(ep + dirs * ((z0 - p.entrance_pupil_z) / dirs[:, 2:3]))
        d.append(dirs)
    return np.concatenate(o), np.concatenate(d), z0


def _ro_trace(opm, lens, o, d, z0, wavelength):
    """ray-optics' trace of our rays; returns positions and directions on OUR image plane."""
    from rayoptics.raytr.trace import trace
    sm = opm["seq_model"]
    zfirst = md_of(lens)["first_vertex_z_in_file"]
    T = -(z0 + zfirst)                    # object plane -> Zemax surface 1
    assert T > 0
    old = sm.gaps[0].thi
    sm.gaps[0].thi = T
    opm.update_model()
    pos, dirs = np.full((len(o), 3), np.nan), np.full((len(o), 3), np.nan)
    try:
        ro_image = sum(g.thi for g in sm.gaps[1:])   # Zemax surface 1 -> image surface
        for i in range(len(o)):
            try:
                ray = trace(sm, np.array([o[i, 0], o[i, 1], 0.0]), d[i], wavelength).ray
            except Exception:  # a ray that misses a surface in ray-optics
                continue
            pt, dr = np.asarray(ray[-1][0], float), np.asarray(ray[-1][1], float)
            # to our image plane (the same plane when the image distances agree, as they must)
            dz = (lens.image_z + zfirst) - ro_image - pt[2]
            pos[i] = pt + dr * dz / dr[2]
            pos[i, 2] = lens.image_z
            dirs[i] = dr
    finally:
        sm.gaps[0].thi = old
        opm.update_model()
    return pos, dirs, ro_image - zfirst


# ----------------------------------------------------------------------------------------- the files
def test_every_shipped_file_is_classified():
    shipped = {str(p.relative_to(RO)) for p in RO.rglob("*") if p.suffix.lower() in (".zmx", ".seq")}
    assert shipped == set(ACCEPTED) | set(REFUSED), shipped ^ (set(ACCEPTED) | set(REFUSED))


@pytest.mark.parametrize("rel", sorted(REFUSED))
def test_refused_with_keyword(rel):
    keyword, surface = REFUSED[rel]
    with pytest.raises(LensError) as ei:
        nl.Lens.load(RO / rel)
    msg = where_ok(ei, RO / rel, surface=surface, field=keyword)
    if keyword is None:
        assert "afocal" in msg
    elif keyword not in ("RDM", "SI"):
        assert "not supported" in msg and "line " in msg


@pytest.mark.parametrize("rel", sorted(UNKNOWN_GLASS))
def test_unknown_glass_is_an_error_not_a_guess(rel):
    surface, glass = UNKNOWN_GLASS[rel]
    with pytest.raises(LensError) as ei:
        nl.Lens.load(RO / rel)
    msg = where_ok(ei, RO / rel, surface=surface, field="GLAS")
    assert f"unknown glass '{glass}'" in msg and "glasses=" in msg
    # the GLAS line's nd/Vd fields are named as unused (1.5/40 are OpticStudio's stale defaults)
    assert "nd " in msg and "not used" in msg


@pytest.mark.parametrize("rel", sorted(ACCEPTED))
def test_first_order_and_real_rays_match_rayoptics(rel, ro_open):
    lens = load(rel)
    md = md_of(lens)
    opm = ro_open(rel)
    primary = md["primary_wavelength_nm"]
    # the image distance is the file's last thickness (Zemax DISZ; CODE V: plus the SI defocus, which
    # ray-optics keeps aside as a focus shift)
    sm = opm["seq_model"]
    defocus = md.get("image_defocus_mm", 0.0)
    zfirst = md["first_vertex_z_in_file"]
    assert lens.image_z + zfirst == pytest.approx(sum(g.thi for g in sm.gaps[1:]) + defocus, rel=1e-12)
    if not md["dropped_surfaces"] or md["dropped_surfaces"][-1]["surface"] != md["surface_numbers"][-1] + 1:
        assert lens.surfaces[-1].thickness == pytest.approx(sm.gaps[-1].thi + defocus, rel=1e-12)
    with _ro_media(opm, lens, primary):
        efl, bfl = _ro_first_order(opm)
    assert lens.efl(primary) == pytest.approx(efl, rel=1e-4)
    # BFL from the last vertex; a trailing dummy surface, which the reader drops, moves that vertex
    shift = zfirst + float(lens.vertex_z[-1]) - sum(g.thi for g in sm.gaps[1:-1])
    assert lens.bfl(primary) + shift == pytest.approx(bfl, rel=1e-4)
    rng = np.random.default_rng(19)
    checked = 0
    for lam in WAVELENGTHS:
        o, d, z0 = _rays(lens, lam, rng)
        ours = lens.trace(o, d, lam, precision="float64")
        assert ours.valid.sum() >= 30, (rel, lam, ours.valid.sum())
        o, d = o[ours.valid], d[ours.valid]
        with _ro_media(opm, lens, lam):
            pos, dirs, ro_image = _ro_trace(opm, lens, o, d, z0, lam)
        assert ro_image + defocus == pytest.approx(lens.image_z, abs=1e-9)
        ok = np.isfinite(pos).all(1)
        assert ok.mean() > 0.95
        dp = np.abs(ours.position[ours.valid][ok] - pos[ok]).max()
        dd = np.abs(ours.direction[ours.valid][ok] - dirs[ok]).max()
        assert dp < 2e-3 and dd < 1e-5, (rel, lam, dp, dd)
        checked += ok.sum()
    assert checked >= 100


@pytest.mark.parametrize("rel", sorted(ACCEPTED))
def test_glasses_match_rayoptics_where_the_same(rel, ro_open):
    """Where both readers resolve the same catalogue glass, the indices agree (same vendor formula)."""
    lens = load(rel)
    sm = ro_open(rel)["seq_model"]
    same = 0
    for k, g in enumerate(sm.gaps):
        ours = _medium_after(lens, k)
        cat = getattr(g.medium, "catalog_name", lambda: None)()
        if ours.source.get("glass") == g.medium.name() and ours.source.get("catalog") == cat:
            for lam in WAVELENGTHS:
                assert float(ours.index(lam)) == pytest.approx(g.medium.rindex(lam), abs=1e-9)
            same += 1
        elif ours == AIR:
            assert g.medium.rindex(587.6) == 1.0
    if rel in SAME_GLASSES:
        assert same == sum(1 for s in lens.surfaces if s.medium != AIR)


@pytest.mark.parametrize("rel", SAME_GLASSES)
def test_first_order_with_rayoptics_own_glasses(rel, ro_open):
    lens = load(rel)
    opm = ro_open(rel)
    primary = md_of(lens)["primary_wavelength_nm"]
    wv = opm["optical_spec"]["wvls"]
    assert wv.wavelengths[wv.reference_wvl] == pytest.approx(primary)
    efl, bfl = _ro_first_order(opm)
    assert lens.efl(primary) == pytest.approx(efl, rel=1e-4)
    assert lens.bfl(primary) == pytest.approx(bfl, rel=1e-4)


def test_stop_radius_from_fnum_reproduces_opticstudio_stop():
    """FNUM 4.5: the stop radius gives a paraxial entrance pupil of EFL/4.5; the real marginal ray
    through that pupil edge meets the stop plane at the semi-diameter OpticStudio computed and saved
    on the stop surface (DIAM 4.215000499256, an automatic semi-diameter) — an independent check of
    geometry, glasses and the aperture rule."""
    lens = load("zemax/tests/US00583336-2-scaled.zmx")
    p = lens.paraxial(587.5618)
    assert p.fnumber == pytest.approx(4.5, rel=1e-12)
    assert lens.stop.label == "STO" and lens.metadata["zemax"]["surface_numbers"][lens.stop_index] == 7
    # the dummy SURF 1, 4.5 mm in front, is dropped; the first vertex is SURF 2
    md = lens.metadata["zemax"]
    assert md["dropped_surfaces"][0]["surface"] == 1 and md["first_vertex_z_in_file"] == 4.5
    res = lens.trace(np.array([[0.0, p.entrance_pupil_radius, -10.0]]), np.array([[0.0, 0.0, 1.0]]), 587.5618,
                     precision="float64", record=True)
    stop_hit = res.points[0][1 + lens.stop_index]
    assert stop_hit[2] == pytest.approx(lens.vertex_z[lens.stop_index])
    assert stop_hit[1] == pytest.approx(4.215000499256, abs=1e-6)


def test_stop_on_a_lens_surface_becomes_a_flat_stop_at_its_vertex():
    lens = load("zemax/tests/354710-C-Zemax(ZMX).zmx")
    assert lens.stop_index == 0 and lens.stop.thickness == 0.0         # in front of the convex asphere
    assert lens.metadata["zemax"]["surface_numbers"][:2] == [None, 1]
    assert lens.stop.semi_diameter == pytest.approx(0.75)             # ENPD 1.5 at the first surface
    s1 = lens.surfaces[1]
    assert s1.conic == pytest.approx(-0.4776343430417) and len(s1.aspheric) == 5
    assert s1.aspheric[0] == pytest.approx(-6.313587842251e-3)        # PARM 2 -> A4


@pytest.mark.parametrize("rel", sorted(ACCEPTED))
def test_round_trip_through_project_json(rel, tmp_path):
    lens = load(rel)
    out = tmp_path / "lens.json"
    lens.save(out)
    back = nl.Lens.load(out)
    assert back.fingerprint() == lens.fingerprint() and back == lens
    assert md_of(back)["primary_wavelength_nm"] == md_of(lens)["primary_wavelength_nm"]


def test_utf16_and_utf8_read_the_same(tmp_path):
    src = RO / "zemax/tests/US00583336-2-scaled.zmx"     # UTF-8 in the package
    text = src.read_bytes().decode("utf-8")
    ref = nl.Lens.load(src)
    for enc, bom in (("utf-16-le", b"\xff\xfe"), ("utf-16-be", b"\xfe\xff"), ("utf-16-le", b"")):
        p = tmp_path / f"x-{enc}-{len(bom)}.zmx"
        p.write_bytes(bom + text.encode(enc))
        assert F.detect_format(p) == "zemax"
        lens = nl.Lens.load(p)
        assert lens.fingerprint() == ref.fingerprint()
        assert lens.metadata["zemax"]["encoding"].startswith("utf-16")
    assert ref.metadata["zemax"]["encoding"] == "utf-8"


def _same_or_none(a, b, rel: float = 1e-12) -> bool:
    """Equal to ``rel``, or both ``None`` (an optional field: pytest >= 9.2 refuses ``approx(None)`` with ``rel``)."""
    if a is None or b is None:
        return a is None and b is None
    return a == pytest.approx(b, rel=rel)


# ----------------------------------------------------------------------------------------- small files
def zmx(surfaces, header="UNIT MM X W X CM MR CPMM\nENPD 10\nWAVM 1 0.5875618 1\nPWAV 1\n", mode="SEQ"):
    """A small .zmx text: ``surfaces`` are lists of surface lines (object and image added)."""
    out = ["VERS 140730 73 26155", f"MODE {mode}", "NAME test lens", header.rstrip("\n"),
           "SURF 0", "  TYPE STANDARD", "  CURV 0.0 0 0 0 0 \"\"", "  DISZ INFINITY"]
    for i, lines in enumerate(surfaces, 1):
        out.append(f"SURF {i}")
        out += ["  " + ln for ln in lines]
    out += [f"SURF {len(surfaces) + 1}", "  TYPE STANDARD", "  CURV 0.0 0 0 0 0 \"\"", "  DISZ 0",
            "  DIAM 10 0 0 0 1 \"\""]
    return "\r\n".join(out) + "\r\n"


SINGLET = [
    ["STOP", "TYPE STANDARD", "CURV 0.0", "DISZ 5", "DIAM 6 1 0 0 1 \"\""],
    ["TYPE STANDARD", "CURV 0.02", "DISZ 6", "GLAS N-BK7 0 0 1.5168 64.17 0 0 0 0 0 0", "DIAM 12 1 0 0 1 \"\"",
     "MEMA 13 0 0 0 1 \"\""],
    ["TYPE EVENASPH", "CURV -0.005", "PARM 1 0", "PARM 2 1.0E-6", "PARM 3 -2.0E-9", "DISZ 90", "CONI -1.5",
     "DIAM 12 1 0 0 1 \"\"", "FLAP 0 11.5 0"],
]


def write(tmp_path, text, name="lens.zmx", encoding="utf-8"):
    p = tmp_path / name
    p.write_bytes(text.encode(encoding))
    return p


def test_small_file_maps_every_keyword(tmp_path):
    p = write(tmp_path, zmx(SINGLET))
    lens = nl.Lens.load(p)
    assert [s.label for s in lens.surfaces] == ["STO", "2", "3"]
    st, s2, s3 = lens.surfaces
    assert st.is_stop and st.thickness == 5 and st.semi_diameter == pytest.approx(5.0)   # ENPD 10, front stop
    assert s2.radius == pytest.approx(50.0) and s2.thickness == 6 and s2.semi_diameter == 12
    assert s2.housing_radius == 13                                                      # MEMA
    assert s2.medium == catalog_glass("N-BK7")
    assert s3.radius == pytest.approx(-200.0) and s3.conic == -1.5
    assert s3.aspheric == (1e-6, -2e-9) and s3.semi_diameter == 11.5                    # FLAP over DIAM
    assert s3.thickness == 90 and lens.image_z == 101                                   # last DISZ kept
    assert lens.metadata["zemax"]["primary_wavelength_nm"] == pytest.approx(587.5618)
    assert lens.metadata["description"] == "test lens"


@pytest.mark.parametrize("unit,scale", [("CM", 10.0), ("IN", 25.4), ("M", 1000.0)])
def test_units(tmp_path, unit, scale):
    ref = nl.Lens.load(write(tmp_path, zmx(SINGLET), "mm.zmx"))
    s = 1.0 / scale
    surfs = [
        ["STOP", "CURV 0.0", f"DISZ {5 * s!r}", f"DIAM {6 * s!r} 1 0 0 1 \"\""],
        [f"CURV {0.02 / s!r}", f"DISZ {6 * s!r}", "GLAS N-BK7", f"DIAM {12 * s!r} 1 0 0 1", f"MEMA {13 * s!r} 0"],
        ["TYPE EVENASPH", f"CURV {-0.005 / s!r}", f"PARM 2 {1e-6 / s ** 3!r}", f"PARM 3 {-2e-9 / s ** 5!r}",
         f"DISZ {90 * s!r}", "CONI -1.5", f"DIAM {12 * s!r} 1", f"FLAP 0 {11.5 * s!r} 0"],
    ]
    header = f"UNIT {unit} X W X CM MR CPMM\nENPD {10 * s!r}\nWAVM 1 0.5875618 1\nPWAV 1\n"
    lens = nl.Lens.load(write(tmp_path, zmx(surfs, header), f"{unit}.zmx"))
    assert lens.metadata["zemax"]["mm_per_unit"] == scale
    for a, b in zip(lens.surfaces, ref.surfaces):
        for f in ("radius", "thickness", "semi_diameter", "conic", "housing_radius"):
            assert _same_or_none(getattr(a, f), getattr(b, f)), (f, getattr(a, f), getattr(b, f))
        np.testing.assert_allclose(a.aspheric, b.aspheric, rtol=1e-12)
    assert lens.efl() == pytest.approx(ref.efl(), rel=1e-12)


def test_model_glass_and_constant_index(tmp_path):
    surfs = [list(s) for s in SINGLET]
    surfs[1][3] = "GLAS ___BLANK 1 0 1.6968 55.53 0 0 0 0 0 0"
    lens = nl.Lens.load(write(tmp_path, zmx(surfs)))
    m = model_glass(1.6968, 55.53)
    assert (lens.surfaces[1].medium.formula, lens.surfaces[1].medium.coefficients) == (m.formula, m.coefficients)
    assert lens.surfaces[1].medium.nd == pytest.approx(1.6968, abs=1e-12)
    surfs[1][3] = "GLAS ___BLANK 1 0 1.6 0 0 0 0 0 0 0"               # Vd 0: no dispersion
    lens = nl.Lens.load(write(tmp_path, zmx(surfs), "c.zmx"))
    assert lens.surfaces[1].medium.coefficients == constant(1.6).coefficients == (1.6,)


def test_unknown_glass_substitution_and_no_nd_vd_fallback(tmp_path):
    surfs = [list(s) for s in SINGLET]
    surfs[1][3] = "GLAS NOSUCHGLASS 0 0 1.6968 55.53 0 0 0 0 0 0"
    p = write(tmp_path, zmx(surfs))
    with pytest.raises(LensError) as ei:
        nl.Lens.load(p)
    msg = where_ok(ei, p, surface=2, field="GLAS")
    assert "NOSUCHGLASS" in msg and "1.6968" in msg
    lens = nl.Lens.load(p, glasses={"nosuchglass": {"nd": 1.6968, "vd": 55.53}})
    assert lens.surfaces[1].medium.nd == pytest.approx(1.6968)
    assert lens.metadata["zemax"]["glasses"]["NOSUCHGLASS"]["from"] == "glasses= option"
    with pytest.raises(LensError) as ei:
        nl.Lens.load(p, glasses={"NOSUCHGLASS": "N-BK7", "TYPO": "N-SF5"})
    assert "TYPO" in where_ok(ei, p, field="glasses")


def test_gcat_order_picks_the_catalogue(tmp_path):
    surfs = [list(s) for s in SINGLET]
    surfs[1][3] = "GLAS SF5"                      # Schott's lead SF5, not N-SF5
    lens = nl.Lens.load(write(tmp_path, zmx(surfs, "GCAT SCHOTT\nENPD 10\n")))
    assert lens.surfaces[1].medium.source == {"catalog": "Schott", "glass": "SF5"}


BAD = {  # name -> (surface index in SINGLET (0-based), line to add or (old, new) replacement, keyword)
    "coordinate break": (1, ("TYPE STANDARD", "TYPE COORDBRK"), "TYPE"),
    "odd asphere": (2, ("TYPE EVENASPH", "TYPE ODDASPHE"), "TYPE"),
    "gradient index": (1, ("TYPE STANDARD", "TYPE GRINSUR1"), "TYPE"),
    "mirror": (1, ("GLAS N-BK7 0 0 1.5168 64.17 0 0 0 0 0 0", "GLAS MIRROR 0 0 1.5 40"), "GLAS"),
    "tilt": (1, "SCBD 1 0 0 0 0 2.5 0 0", "SCBD"),
    "decenter": (2, "SCBD 1 0 0 0.1 0 0 0 0", "SCBD"),
    "r2 term": (2, ("PARM 2 1.0E-6", "PARM 1 1.0E-3\r\n  PARM 2 1.0E-6"), "PARM"),
    "obscuration": (1, "OBSC 0 2 0", "OBSC"),
    "annular aperture": (1, "CLAP 1 12 0", "CLAP"),
    "rectangular aperture": (1, "SQAP 5 5 0", "SQAP"),
    "decentered aperture": (1, "OBDC 1.0 0", "OBDC"),
    "diam too large": (1, ("DIAM 12 1 0 0 1 \"\"", "DIAM 55 1 0 0 1 \"\""), "DIAM"),
    "no diam": (1, ("DIAM 12 1 0 0 1 \"\"", "COMM no diam"), "DIAM"),
    "bad number": (1, ("DISZ 6", "DISZ 6.0E"), "DISZ"),
    "unknown glass": (1, ("GLAS N-BK7 0 0 1.5168 64.17 0 0 0 0 0 0", "GLAS N-BK77"), "GLAS"),
    "negative thickness": (1, ("DISZ 6", "DISZ -6"), "DISZ"),
    "thickness too small": (1, ("DISZ 6", "DISZ 0.1"), "DISZ"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_surface_named(tmp_path, case):
    i, change, keyword = BAD[case]
    surfs = [list(s) for s in SINGLET]
    if isinstance(change, tuple):
        k = surfs[i].index(change[0])
        surfs[i][k] = change[1]
    else:
        surfs[i].append(change)
    p = write(tmp_path, zmx(surfs))
    with pytest.raises(LensError) as ei:
        nl.Lens.load(p)
    msg = where_ok(ei, p, surface=i + 1, field=keyword)
    assert "line " in msg or case in ("thickness too small", "diam too large")
    if case == "diam too large":
        assert "larger than the surface allows" in msg and "50 mm" in msg


def test_missing_stop(tmp_path):
    surfs = [list(s) for s in SINGLET]
    surfs[0].remove("STOP")
    p = write(tmp_path, zmx(surfs))
    with pytest.raises(LensError) as ei:
        nl.Lens.load(p)
    assert "no aperture stop" in where_ok(ei, p, field="STOP")


@pytest.mark.parametrize("header,keyword", [
    ("MODE NSC", "MODE"), ("OBNA 0.1 0", "OBNA"), ("UNIT FT", "UNIT"), ("PWAV 3", "PWAV")])
def test_bad_header(tmp_path, header, keyword):
    if header.startswith("MODE"):
        text = zmx(SINGLET, mode="NSC")
    else:
        text = zmx(SINGLET, f"UNIT MM\nENPD 10\nWAVM 1 0.5875618 1\n{header}\n")
    p = write(tmp_path, text)
    with pytest.raises(LensError) as ei:
        nl.Lens.load(p)
    where_ok(ei, p, field=keyword)


def test_obna_with_stop_radius(tmp_path):
    p = write(tmp_path, zmx(SINGLET, "UNIT MM\nOBNA 0.1 0\nWAVM 1 0.5875618 1\n"))
    lens = nl.Lens.load(p, stop_radius=4.0)
    assert lens.stop.semi_diameter == 4.0


def test_curved_image_surface(tmp_path):
    text = zmx(SINGLET).replace("SURF 4\r\n  TYPE STANDARD\r\n  CURV 0.0", "SURF 4\r\n  TYPE STANDARD\r\n  CURV 0.01")
    p = write(tmp_path, text)
    with pytest.raises(LensError) as ei:
        nl.Lens.load(p)
    assert "curved image surface" in where_ok(ei, p, surface=4, field="CURV")


@pytest.mark.parametrize("rel", ["zemax/tests/US00583336-2-scaled.zmx", "zemax/tests/zmax_55278.zmx"])
def test_truncated_files(tmp_path, rel):
    raw = (RO / rel).read_bytes()
    text, enc = F.zemax.decode(F.Ctx(None), raw)
    lines = text.splitlines()
    # cut the file after each line of the last two SURF blocks, up to the image surface's DISZ (after
    # it the lens is complete), and mid-file: never a lens, always an error
    last = max(i for i, ln in enumerate(lines) if ln.startswith("SURF"))
    prev = max(i for i, ln in enumerate(lines[:last]) if ln.startswith("SURF"))
    image_disz = next(i for i in range(last, len(lines)) if lines[i].split()[:1] == ["DISZ"])
    cuts = list(range(prev + 1, image_disz + 1)) + [len(lines) // 3]
    checked = 0
    for c in cuts:
        body = "\r\n".join(lines[:c]) + "\r\n"
        p = tmp_path / f"cut{c}.zmx"
        p.write_bytes(body.encode(enc))
        with pytest.raises(LensError) as ei:
            nl.Lens.load(p)
        msg = str(ei.value)
        assert str(p) in msg and ei.value.field is not None, msg
        checked += 1
    assert checked >= 5
    if enc.startswith("utf-16"):                  # an odd number of bytes
        p = tmp_path / "odd.zmx"
        p.write_bytes(raw[:len(raw) // 2 | 1])
        with pytest.raises(LensError, match="truncated"):
            nl.Lens.load(p)


# ----------------------------------------------------------------------------------------- CLI
def test_cli_convert(tmp_path, capsys):
    from mi_neurallens.cli import main
    src = RO / "zemax/tests/US08427765-1.ZMX"
    out = tmp_path / "scene" / "lens.json"
    assert main(["lens", "convert", str(src), str(out)]) == 1          # unknown glass: nothing written
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "L-TIM28_MOLD" in err[0] and "--glass" in err[0]
    assert not out.exists()
    assert main(["lens", "convert", str(src), str(out), "--glass", "L-TIM28_MOLD=S-TIM28", "--name", "us8427765"]) == 0
    assert "wrote" in capsys.readouterr().out
    back = nl.Lens.load(out)
    ref = load("zemax/tests/US08427765-1.ZMX")
    assert back.fingerprint() == ref.fingerprint() and back.name == "us8427765"
    doc = json.loads(out.read_text())
    assert doc["source"]["format"] == "Zemax OpticStudio .zmx" and len(doc["source"]["sha256"]) == 64
    assert [p.name for p in out.parent.iterdir()] == ["lens.json"]       # no temporary left over
    # any readable format converts: a bundled pbrt lens
    out2 = tmp_path / "wide.json"
    assert main(["lens", "convert", "wide-22mm", str(out2)]) == 0
    assert nl.Lens.load(out2).fingerprint() == nl.Lens.load("wide-22mm").fingerprint()


def test_cli_info_and_plot_read_design_files(tmp_path, capsys):
    from mi_neurallens.cli import main
    src = RO / "codev/tests/ag_dblgauss.seq"
    assert main(["lens", "info", str(src), "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    lens = nl.Lens.load(src)
    assert d["efl"] == lens.efl() and d["fingerprint"] == lens.fingerprint()
    assert d["fnumber"] == pytest.approx(2.0, rel=1e-3)                       # EPD 50, EFL 100
    out = tmp_path / "layout.png"
    assert main(["lens", "plot", str(RO / "zemax/tests/zmax_55278.zmx"), "-o", str(out), "--rays", "3",
                 "--fields", "0", "--wavelengths", "587.6", "--dpi", "50"]) == 0
    with open(out, "rb") as f:
        head = f.read(24)
    assert head[:8] == b"\x89PNG\r\n\x1a\n" and int.from_bytes(head[16:20], "big") < 700   # 50 dpi


@pytest.mark.parametrize("spec,expect", [
    ("X=N-BK7", "N-BK7"), ("X=1.5", 1.5), ("X=1.5891/61.16", {"nd": 1.5891, "vd": 61.16}),
    ('X={"glass": "S-TIM28", "catalog": "Ohara"}', {"glass": "S-TIM28", "catalog": "Ohara"})])
def test_glass_option_parsing(spec, expect):
    from mi_neurallens.commands.lens import glass_spec
    assert glass_spec(spec) == ("X", expect)
    with pytest.raises(LensError):
        glass_spec("no-equals-sign")


# ----------------------------------------------------------------------------------------- CODE V
SEQ = """RDM;LEN "a test"
TITLE 'singlet & stop' ! a comment; not a command
EPD 10.0; DIM M
WL 656.2725 587.5618 486.1327; REF 2
YAN 0.0 10.0
SO 0.0 1e10
S 0.0 5.0
  STO
S 50.0 6.0 NBK7_SCHOTT
  CIR 12.0; CIR EDG 13.0
S -200.0 &
   90.0
  ASP; K -1.5
  A 1.0e-6; B -2.0e-9
SI 0.0 0.5
"""


def test_codev_small_file(tmp_path):
    p = write(tmp_path, SEQ, "lens.seq")
    assert F.detect_format(p) == "codev"
    lens = nl.Lens.load(p)
    md = lens.metadata["codev"]
    st, s2, s3 = lens.surfaces
    assert st.is_stop and st.thickness == 5.0 and st.semi_diameter == pytest.approx(5.0)
    assert s2.radius == 50.0 and s2.medium == catalog_glass("N-BK7") and s2.semi_diameter == 12.0
    assert s2.housing_radius == 13.0
    assert s3.radius == -200.0 and s3.conic == -1.5 and s3.aspheric == (1e-6, -2e-9)
    assert s3.thickness == 90.5 and md["image_defocus_mm"] == 0.5          # SI thickness = defocus
    assert list(md["estimated_semi_diameters"]) == ["3"]                  # no CIR on surface 3
    assert md["primary_wavelength_nm"] == 587.5618
    assert lens.metadata["description"] == "singlet & stop"
    # the same lens in curvatures and centimetres
    cv = (SEQ.replace("RDM;LEN", "RDM N;LEN").replace("DIM M", "DIM C").replace("EPD 10.0", "EPD 1.0")
          .replace("S 0.0 5.0", "S 0.0 0.5").replace("S 50.0 6.0", "S 0.2 0.6").replace("CIR 12.0; CIR EDG 13.0",
          "CIR 1.2; CIR EDG 1.3").replace("S -200.0 &\n   90.0", "S -0.05 9.0").replace("A 1.0e-6; B -2.0e-9",
          "A 1.0e-3; B -2.0e-4").replace("SI 0.0 0.5", "SI 0.0 0.05"))
    other = nl.Lens.load(write(tmp_path, cv, "cm.seq"))
    for a, b in zip(other.surfaces, lens.surfaces):
        for f in ("radius", "thickness", "semi_diameter", "conic", "housing_radius"):
            assert _same_or_none(getattr(a, f), getattr(b, f)), (f, getattr(a, f), getattr(b, f))
        np.testing.assert_allclose(a.aspheric, b.aspheric, rtol=1e-12)


@pytest.mark.parametrize("glass,nd,vd", [("517000.520000", 1.517, 52.0), ("500.700", 1.5, 70.0),
                                         ("1.6968:55.53", None, None)])
def test_codev_glass_codes(tmp_path, glass, nd, vd):
    p = write(tmp_path, SEQ.replace("NBK7_SCHOTT", glass), "g.seq")
    if nd is None:
        with pytest.raises(LensError) as ei:
            nl.Lens.load(p)
        where_ok(ei, p, surface=2, field="S")
        return
    m = nl.Lens.load(p).surfaces[1].medium
    assert m.nd == pytest.approx(nd, abs=1e-12) and m.vd == pytest.approx(vd, rel=1e-9)


def test_codev_private_glass(tmp_path):
    text = SEQ.replace("SO 0.0 1e10", "PRV\n PWL 656.3 587.6 486.1\n 'E48' 1.527 1.5306 1.5378\nEND\nSO 0.0 1e10")
    lens = nl.Lens.load(write(tmp_path, text.replace("NBK7_SCHOTT", "'E48'"), "p.seq"))
    m = lens.surfaces[1].medium
    assert m.formula == "table" and float(m.index(587.6)) == pytest.approx(1.5306)


@pytest.mark.parametrize("change,keyword,surface", [
    (("NBK7_SCHOTT", "NBK7_SCHOTT REFL"), "S", 2),
    (("NBK7_SCHOTT", "REFL"), "REFL", 2),
    (("  STO\n", "  STO\n  ADE 2.0\n"), "ADE", 1),
    (("  STO\n", "  STO\n  YDE 0.1\n"), "YDE", 1),
    (("  CIR 12.0;", "  CIR OBS 2.0; CIR 12.0;"), "CIR", 2),
    (("  STO\n", ""), "STO", None),
    (("RDM;LEN", "LEN"), "RDM", None),
    (("EPD 10.0", "NAO 0.1"), "NAO", None),
    (("NBK7_SCHOTT", "NBK77_SCHOTT"), "S", 2),
    (("NBK7_SCHOTT", "NBK7_NOSUCHCAT"), "S", 2),
    (("CIR 12.0;", "CIR 55.0;"), "CIR", 2),
    (("SI 0.0 0.5\n", ""), "SI", None),
    (("S -200.0 &\n   90.0", "S -200.0 9x0"), "S", 3),
    (("  ASP; K -1.5", "  ASP; K -1.5; CIR S2 3.0"), "CIR", 3),
    (("SI 0.0 0.5", "SI -100.0 0.5"), "SI", 4),
    (("EPD 10.0; DIM M", "EPD 10.0; DIM M; ZOO RDY S2 50 60"), "ZOO", None),  # a zoomed radius (only gaps move)
])
def test_codev_refusals(tmp_path, change, keyword, surface):
    text = SEQ.replace(*change)
    assert text != SEQ
    p = write(tmp_path, text, "bad.seq")
    with pytest.raises(LensError) as ei:
        nl.Lens.load(p)
    where_ok(ei, p, surface=surface, field=keyword)


def test_codev_truncated(tmp_path):
    lines = SEQ.splitlines()
    for c in range(7, len(lines)):                                   # from the first S line on
        p = write(tmp_path, "\n".join(lines[:c]) + "\n", f"cut{c}.seq")
        with pytest.raises(LensError) as ei:
            nl.Lens.load(p)
        assert str(p) in str(ei.value) and ei.value.field is not None
    p = write(tmp_path, SEQ.split("   90.0")[0], "amp.seq")        # ends with '&'
    with pytest.raises(LensError, match="truncated"):
        nl.Lens.load(p)


def test_codev_stop_on_a_lens_surface_without_cir(tmp_path):
    text = "RDM\nEPD 10; WL 587.56\nSO 0 1e10\nS 50 6 NBK7_SCHOTT\n  STO\nS -50 45\nSI 0 0\n"
    lens = nl.Lens.load(write(tmp_path, text, "s.seq"))
    assert [s.label for s in lens.surfaces] == ["STO", "1", "2"] and lens.stop.semi_diameter == pytest.approx(5.0)
    est = lens.metadata["codev"]["estimated_semi_diameters"]
    assert set(est) == {"1", "2"} and est["1"] == pytest.approx(1.02 * 5.0)    # on axis: the marginal ray


def test_codev_radius_mode_option():
    rel = "codev/tests/singlet.seq"
    with pytest.raises(LensError) as ei:                            # curvatures given, but no stop
        nl.Lens.load(RO / rel, radius_mode=False)
    where_ok(ei, RO / rel, field="STO")
    with pytest.raises(LensError) as ei:                            # the file says RDM: no override
        nl.Lens.load(RO / "codev/tests/ag_dblgauss.seq", radius_mode=True)
    where_ok(ei, RO / "codev/tests/ag_dblgauss.seq", field="RDM")


# ----------------------------------------------------------------------------------------- the table
if __name__ == "__main__":  # `PYTHONPATH=. python3 tests/test_zemax.py`: the table in docs/lens-format.md
    import tempfile

    class _Factory:
        def mktemp(self, name):
            return Path(tempfile.mkdtemp(prefix=name))

    warnings.simplefilter("ignore")
    gen = ro_open._get_wrapped_function()(_Factory())
    get = next(gen)
    print("| file | primary nm | EFL mm | EFL rel. diff | BFL mm | BFL rel. diff | rays | max Δpos mm | max Δdir |")
    print("|---|---|---|---|---|---|---|---|---|")
    for rel in sorted(ACCEPTED, key=lambda r: (not r.endswith((".zmx", ".ZMX")), r.lower())):
        lens, opm = load(rel), get(rel)
        md = md_of(lens)
        pw = md["primary_wavelength_nm"]
        sm = opm["seq_model"]
        shift = md["first_vertex_z_in_file"] + float(lens.vertex_z[-1]) - sum(g.thi for g in sm.gaps[1:-1])
        with _ro_media(opm, lens, pw):
            efl, bfl = _ro_first_order(opm)
        rng = np.random.default_rng(19)
        dp = dd = 0.0
        n = 0
        for lam in WAVELENGTHS:
            o, d, z0 = _rays(lens, lam, rng)
            ours = lens.trace(o, d, lam, precision="float64")
            o, d = o[ours.valid], d[ours.valid]
            with _ro_media(opm, lens, lam):
                pos, dirs, _ = _ro_trace(opm, lens, o, d, z0, lam)
            ok = np.isfinite(pos).all(1)
            n += int(ok.sum())
            dp = max(dp, float(np.abs(ours.position[ours.valid][ok] - pos[ok]).max()))
            dd = max(dd, float(np.abs(ours.direction[ours.valid][ok] - dirs[ok]).max()))
        b = lens.bfl(pw) + shift
        print(f"| {Path(rel).name} | {pw:g} | {lens.efl(pw):.6f} | {abs(lens.efl(pw) / efl - 1):.0e} | {b:.6f} | "
              f"{abs(b / bfl - 1):.0e} | {n} | {dp:.0e} | {dd:.0e} |")


# ----------------------------------------------------------------------------------------- configurations
#: a two-group lens whose gap after surface 2 and image distance change between configurations (Zemax's
#: multi-configuration lines as OpticStudio writes them: operand, surface, configuration, value, …)
ZOOM_SURFS = [
    ["TYPE STANDARD", "CURV 0.02", "DISZ 4", "GLAS N-BK7 0 0 1.5168 64.17 0 0 0 0 0 0", "DIAM 12 1 0 0 1 \"\""],
    ["TYPE STANDARD", "CURV 0.0", "DISZ 20", "DIAM 12 1 0 0 1 \"\""],
    ["STOP", "TYPE STANDARD", "CURV 0.0", "DISZ 5", "DIAM 6 1 0 0 1 \"\""],
    ["TYPE STANDARD", "CURV 0.03", "DISZ 4", "GLAS N-BK7 0 0 1.5168 64.17 0 0 0 0 0 0", "DIAM 10 1 0 0 1 \"\""],
    ["TYPE STANDARD", "CURV -0.01", "DISZ 40", "DIAM 10 1 0 0 1 \"\""],
]


def _mce(rows):
    return "".join(f"{op} {a} {c} {v} 0 0 0 1 1 1 0 0 \"\" 0\r\n" for op, a, c, v in rows)


def test_zemax_configurations_are_zoom_positions(tmp_path):
    """MNUM 3 with THIC rows: three zoom positions (ordered by focal length), the gaps that change are the moving
    groups, each configuration's lens is the one the file describes in that configuration; with ENPD the stop's
    radius follows each position's entrance pupil."""
    from mi_neurallens.optics import moving as mv
    head = "UNIT MM X W X CM MR CPMM\nENPD 8\nWAVM 1 0.5875618 1\nPWAV 1\nMNUM 3 1\n"
    rows = [("THIC", 2, 1, 20), ("THIC", 2, 2, 12), ("THIC", 2, 3, 5), ("THIC", 5, 1, 40), ("THIC", 5, 2, 45),
            ("THIC", 5, 3, 52)]
    lens = nl.Lens.load(write(tmp_path, zmx(ZOOM_SURFS, header=head) + _mce(rows)))
    mg = lens.moving
    assert mg.positions == 3 and set(mg.gaps) == {1, 4}
    assert [g[0] for g in mg.gaps[1]] == [5.0, 12.0, 20.0] and [g[0] for g in mg.gaps[4]] == [52.0, 45.0, 40.0]
    assert list(mg.zoom_efl_mm) == sorted(mg.zoom_efl_mm)
    for k, c in enumerate((3, 2, 1)):           # configuration c as a lens of its own: the same EFL and pupil
        single = nl.Lens.load(write(tmp_path, zmx([
            [ln.replace("DISZ 20", f"DISZ {dict(rows[i][2:] for i in range(3))[c]}") for ln in s] if j == 1 else
            ([ln.replace("DISZ 40", f"DISZ {dict(r[2:] for r in rows[3:])[c]}") for ln in s] if j == 4 else s)
            for j, s in enumerate(ZOOM_SURFS)], header=head.replace("MNUM 3 1\n", "")), f"c{c}.zmx"))
        conf = mv.at(lens, float(k), 0.0)
        assert conf.efl() == pytest.approx(single.efl(), rel=1e-12)
        assert conf.stop.semi_diameter == pytest.approx(single.stop.semi_diameter, rel=1e-9)


def test_zemax_configurations_with_a_close_focus(tmp_path):
    """A configuration with the object at a finite distance (THIC 0) is the close focus of the one at infinity; the
    close-focus distance is measured from the sensor.  An operand that changes a curvature is refused."""
    head = "UNIT MM X W X CM MR CPMM\nENPD 8\nWAVM 1 0.5875618 1\nPWAV 1\nMNUM 2 1\n"
    rows = [("THIC", 0, 1, "INFINITY"), ("THIC", 0, 2, 500), ("THIC", 5, 1, 40), ("THIC", 5, 2, 44)]
    lens = nl.Lens.load(write(tmp_path, zmx(ZOOM_SURFS, header=head) + _mce(rows)))
    mg = lens.moving
    assert mg.positions == 1 and mg.gaps == {4: ((40.0, 44.0),)} and mg.close_gaps == "published"
    assert mg.close_focus_mm == pytest.approx(500 + 4 + 20 + 5 + 4 + 44)
    bad = _mce(rows + [("CRVT", 4, 2, 0.031)])
    with pytest.raises(LensError) as ei:
        nl.Lens.load(write(tmp_path, zmx(ZOOM_SURFS, header=head) + bad, "bad.zmx"))
    assert "CRVT" in str(ei.value) and "only gaps" in str(ei.value)
