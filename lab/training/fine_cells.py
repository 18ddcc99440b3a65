"""Run ``mi-neurallens`` with a zoom lens's configuration cells split finer along the zoom: six bins of the zoom
parameter (edges at 0.1, 0.3, 0.5, 0.7, 0.9 of its range) times the focus band's three, instead of wide / mid / tele
(transport/configurations.py, ``Configurations.cells``).  The cells are what the per-cell goals and the regressor's
``lm_cell_weight`` look at; a band as wide as the zoom's middle hides one bad focal length inside it.

Written for issue 55.  Measured once (12-min finishes of one fresh EF 24-70 map, on the Huber loss): with
``lm_cell_weight=2`` on these cells bench_zoom's ten configurations reached 2.64-6.03 arcsec, against 2.49-6.75
unweighted (45 mm at infinity 6.75 -> 6.03, the others 0.05-0.2 arcsec worse).

    python lab/training/fine_cells.py train canon-ef-24-70mm-f2.8l --finish-only maps --base MODEL --out DIR \
        --set regressor.lm_cell_weight=2 --set regressor.lm_huber=0.5 --set regressor.lm_minutes=12 \
        --set regressor.stop_at_goals=false --set classifier.lm_minutes=0.5
"""
import sys
import numpy as np
from mi_neurallens.transport import configurations as C

#: inner edges of the zoom bins, as fractions of the zoom range (rays beyond either end fall in the end bins)
ZOOM_EDGES = [0.1, 0.3, 0.5, 0.7, 0.9]
orig = C.Configurations.cells

def cells(self, x, min_rays=C.CELL_MIN_RAYS):
    base = orig(self, x, min_rays=0)
    if "zoom" not in self.names:
        return {k: m for k, m in base.items() if m.sum() >= min_rays}
    x = np.asarray(x, dtype=np.float64)
    t, f = self.split([x[:, 4 + j] for j in range(self.dims)])
    t = np.broadcast_to(np.asarray(t, np.float64), (len(x),))
    t0, t1 = self.zoom_range
    a = (t - t0) / max(t1 - t0, 1e-30)
    focus = {}
    for k, m in base.items():
        fk = k.split(", ")[-1] if "focus" in self.names else ""
        focus[fk] = focus.get(fk, np.zeros(len(x), bool)) | m
    zbin = np.digitize(a, ZOOM_EDGES)
    out = {f"z{i}" + (f", {fk}" if fk else ""): (zbin == i) & fm
           for i in range(len(ZOOM_EDGES) + 1) for fk, fm in focus.items()}
    return {k: m for k, m in out.items() if m.sum() >= min_rays}

C.Configurations.cells = cells
from mi_neurallens.cli import main
sys.exit(main(sys.argv[1:]))
