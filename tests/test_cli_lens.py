"""`mi-neurallens lens info | plot | list`, run in-process through mi_neurallens.cli.main."""
from __future__ import annotations

import json
import math
import struct

import pytest

from mi_neurallens import Lens
from mi_neurallens.cli import main

LENS = "wide-22mm"


def _bundled():
    from mi_neurallens.optics.formats import bundled_lenses
    return bundled_lenses()


def test_info_text_shows_paraxial_numbers(capsys):
    assert main(["lens", "info", LENS]) == 0
    out = capsys.readouterr().out
    lens = Lens.load(LENS)
    p = lens.paraxial()
    assert f"{lens.efl():.4f} mm" in out
    assert f"{lens.bfl():.4f} mm" in out
    assert f"f/{p.fnumber:.3f}" in out
    assert f"{p.entrance_pupil_radius:.4f} mm" in out
    assert "STOP" in out and lens.fingerprint() in out
    # one table row per surface
    assert sum(1 for line in out.splitlines() if line.strip().split(" ")[0].isdigit()) >= len(lens.surfaces)


@pytest.mark.parametrize("name", [LENS, "ood-59mm"])
def test_info_json_matches_api(capsys, name):
    assert main(["lens", "info", name, "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    lens = Lens.load(name)
    assert d["efl"] == lens.efl() and d["bfl"] == lens.bfl()
    assert d["name"] == lens.name and d["fingerprint"] == lens.fingerprint()
    assert len(d["surfaces"]) == len(lens.surfaces)
    assert [s["is_stop"] for s in d["surfaces"]].index(True) == lens.stop_index
    p = lens.paraxial()
    for k in ("entrance_pupil_z", "entrance_pupil_radius", "exit_pupil_z", "exit_pupil_radius", "fnumber"):
        assert d[k] == getattr(p, k)


def test_info_json_wavelength(capsys):
    assert main(["lens", "info", "canon-ef-24mm-f1.4l", "--json", "--wavelength", "486.1327"]) == 0
    d = json.loads(capsys.readouterr().out)
    lens = Lens.load("canon-ef-24mm-f1.4l")
    assert d["wavelength_nm"] == 486.1327
    assert d["efl"] == lens.efl(486.1327) != lens.efl()


def test_list(capsys):
    assert main(["lens", "list"]) == 0
    out = capsys.readouterr().out
    for name in _bundled():
        line = next(l for l in out.splitlines() if l.startswith(name + " "))
        lens = Lens.load(name)
        if lens.moving is not None and lens.moving.is_zoom:             # a zoom lens: its focal-length range
            from mi_neurallens.optics import moving as mv
            assert "{:.1f}-{:.1f}".format(*mv.focal_length_range(lens)) in line
        else:
            assert f"{lens.efl():.3f}" in line
    assert main(["lens", "list", "--json"]) == 0
    rows = json.loads(capsys.readouterr().out)
    assert {r["name"] for r in rows} == set(_bundled())
    assert all(math.isfinite(r["fnumber"]) and r["fnumber"] > 0 for r in rows)


def _png_size(path):
    with open(path, "rb") as f:
        head = f.read(24)
    assert head[:8] == b"\x89PNG\r\n\x1a\n"
    return struct.unpack(">II", head[16:24])


def test_plot_writes_png(tmp_path, capsys):
    out = tmp_path / "sub" / "layout.png"
    assert main(["lens", "plot", LENS, "-o", str(out), "--rays", "5"]) == 0
    assert "wrote" in capsys.readouterr().out
    w, h = _png_size(out)
    assert 800 <= w <= 4000 and 400 <= h <= 3000
    assert out.stat().st_size > 20_000
    assert [p.name for p in out.parent.iterdir()] == ["layout.png"]      # no temporary left over


def test_plot_fields_and_svg(tmp_path):
    out = tmp_path / "layout.svg"
    assert main(["lens", "plot", "telephoto-250mm", "-o", str(out), "--fields", "0", "3",
                 "--wavelengths", "550"]) == 0
    text = out.read_text()
    assert text.lstrip().startswith("<?xml") and "<svg" in text


@pytest.mark.parametrize("argv", [
    ["lens", "info", "/nonexistent/lens.json"],
    ["lens", "info", "no-such-bundled-lens", "--json"],
    ["lens", "plot", "no-such-bundled-lens", "-o", "x.png"],
])
def test_bad_path_one_line_error(capsys, argv):
    assert main(argv) == 1
    cap = capsys.readouterr()
    assert cap.out == ""
    lines = cap.err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("mi-neurallens: error:")


def test_bad_file_content(tmp_path, capsys):
    bad = tmp_path / "bad.dat"
    bad.write_text("# radius thickness eta aperture\n10 2 1.5\n")
    assert main(["lens", "info", str(bad)]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "bad.dat" in err[0]


def test_plot_bad_extension(tmp_path, capsys):
    assert main(["lens", "plot", LENS, "-o", str(tmp_path / "x.notanimage")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and ".png" in err[0]
    assert list(tmp_path.iterdir()) == []


def test_plot_into_axes_leaves_no_pyplot_state():
    import sys
    from matplotlib.figure import Figure
    from mi_neurallens.optics.plot import plot_lens
    before = sys.modules["matplotlib.pyplot"].get_fignums() if "matplotlib.pyplot" in sys.modules else []
    fig = Figure()
    ax = fig.add_subplot()
    assert plot_lens(Lens.load("dgauss-50mm"), ax, fields_deg=[0, 10], wavelengths_nm=[587.56],
                     rays_per_fan=3) is ax
    # 2 fields x 3 rays drawn, plus the lens outlines
    assert len(ax.lines) >= 6 and len(ax.patches) >= 4
    after = sys.modules["matplotlib.pyplot"].get_fignums() if "matplotlib.pyplot" in sys.modules else []
    assert after == before
