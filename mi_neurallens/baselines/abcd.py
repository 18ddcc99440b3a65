"""ABCD (paraxial ray-transfer matrix) baseline: the linear limit of the lens transport map.

Per path, the matrix is built from per-step paraxial matrices along
:func:`~mi_neurallens.trace.paths.resolve_path` (reflections included), in **lens-space slopes**
``s = dy/dz`` (not unfolded; +z toward the sensor) so that free-space transfer between any two planes
is ``y' = y + (z₂ − z₁) s`` whatever the heading:

* transfer to the next vertex plane: ``[[1, Δz], [0, 1]]``;
* refraction at vertex curvature c from n₁ to n₂ (either heading): ``s' = (n₁/n₂) s − ((n₂ − n₁)/n₂) c y``;
* reflection (either heading): ``s' = −s − 2 c y``;
* the stop is a plane (transfer only); conics and aspheres enter with their vertex curvature.

Converting to :meth:`ParaxialSystem.abcd` (first → last vertex, reduced angle n·s) for the transmit
path: ``abcd = diag(1, n_out) · M · diag(1, 1/n_in)`` (tested).  The 4×4 matrix acting on
``(x, y, sx, sy)`` is block diagonal (rotational symmetry): :meth:`ABCDMap.matrix4`.

Wavelength: each matrix entry is computed exactly at Chebyshev nodes over the domain's λ range and
replaced by its least-squares polynomial in ``l = (λ − 550)/100`` (degree ≤ 6; constant for
dispersion-free lenses).  Throughput (``throughput=``): ``"normal"`` (default) — the product of the
Fresnel factors at normal incidence along the path (T = 1 − R, R for reflections; coatings at cos = 1),
the same λ polynomial; or ``"one"``.  Validity: every ray heading the right way (the paraxial model has
no occlusion); ``aperture="stop"`` adds the paraxial stop-plane height check (|(x, y)_stop| ≤ stop
radius).  Directions are rebuilt from the output slopes: ``(sx, sy, ±1)/‖·‖``.
"""
from __future__ import annotations

import numpy as np

from ..constants import VISIBLE_RANGE_NM
from .common import LAM0_NM, LAM_SCALE_NM, LensSpacePolyMap, fresnel_normal_R
from .poly import SparsePoly


def path_matrices(lens, spec, z_in: float, z_out: float, lam_nm: float):
    """(M, M_stop, T) at one wavelength: the 2×2 slope matrix z_in → z_out, the 2×2 z_in → stop
    plane (None if the path does not cross the stop) and the normal-incidence Fresnel product."""
    zv = lens.vertex_z
    z = float(z_in)
    M = np.eye(2)
    M_stop = None
    T = 1.0

    def transfer(M, dz):
        return np.array([[1.0, dz], [0.0, 1.0]]) @ M

    for st in spec.steps:
        zs = float(zv[st.surface])
        M = transfer(M, zs - z)
        z = zs
        if st.kind == "stop":
            if M_stop is None:
                M_stop = M.copy()
            continue
        surf = lens.surfaces[st.surface]
        m1, m2 = st.media
        n1, n2 = float(m1.index(lam_nm)), float(m2.index(lam_nm))
        c = surf.curvature
        if st.kind == "T":
            if m1 == m2:
                continue
            M = np.array([[1.0, 0.0], [-(n2 - n1) / n2 * c, n1 / n2]]) @ M
            T *= 1.0 - float(fresnel_normal_R(m1, m2, surf.coating, lam_nm))
        else:
            M = np.array([[1.0, 0.0], [-2.0 * c, -1.0]]) @ M
            T *= 0.0 if m1 == m2 else float(fresnel_normal_R(m1, m2, surf.coating, lam_nm))
    M = transfer(M, float(z_out) - z)
    return M, M_stop, T


def _fit_lambda(values, lams, max_degree=6, tol=1e-13):
    """Least-squares polynomial in l = (λ−550)/100 of ``values`` (K,), lowest degree reproducing them to
    ``tol`` relative (max_degree at most).  Returns coefficients (low → high)."""
    l = (np.asarray(lams) - LAM0_NM) / LAM_SCALE_NM
    v = np.asarray(values, np.float64)
    scale = max(np.abs(v).max(), 1e-300)
    for deg in range(0, max_degree + 1):
        c = np.polynomial.polynomial.polyfit(l, v, deg)
        if np.abs(np.polynomial.polynomial.polyval(l, c) - v).max() <= tol * scale:
            return c
    return c


class ABCDMap(LensSpacePolyMap):
    """Paraxial 4×4 matrix map of one path; see the module docstring."""

    method = "abcd"
    angles = "slopes"

    def __init__(self, lens, path="transmit", direction="forward", z_in=None, z_out=None, *,
                 throughput: str = "normal", aperture: str = "none", lam_range=VISIBLE_RANGE_NM,
                 lam_nodes: int = 13):
        super().__init__(lens, path, direction, z_in, z_out)
        if throughput not in ("normal", "one"):
            raise ValueError(f"ABCD throughput must be 'normal' or 'one', got {throughput!r}")
        if aperture not in ("none", "stop"):
            raise ValueError(f"ABCD aperture must be 'none' or 'stop', got {aperture!r}")
        self.throughput_mode, self.aperture = throughput, aperture
        k = np.arange(lam_nodes)
        lo, hi = lam_range
        lams = 0.5 * (lo + hi) + 0.5 * (hi - lo) * np.cos(np.pi * (k + 0.5) / lam_nodes)
        Ms, Ss, Ts = [], [], []
        for lam in lams:
            M, Mst, T = path_matrices(lens, self.spec, self.z_in, self.z_out, lam)
            Ms.append(M)
            Ss.append(Mst if Mst is not None else np.full((2, 2), np.nan))
            Ts.append(T if throughput == "normal" else 1.0)
        Ms, Ss, Ts = np.array(Ms), np.array(Ss), np.array(Ts)
        self.M550, self.Mstop550, self.T550 = path_matrices(lens, self.spec, self.z_in, self.z_out, LAM0_NM)
        # SparsePoly in (x, y, sx, sy, l): outputs X, Y, SX, SY, T [, stop x, stop y]
        terms = {}

        def add(var, lam_coefs, out):
            for j, cj in enumerate(lam_coefs):
                if cj == 0.0:
                    continue
                e = [0, 0, 0, 0, j]
                if var is not None:
                    e[var] += 1
                terms.setdefault(tuple(e), {})[out] = terms.get(tuple(e), {}).get(out, 0.0) + cj

        for axis in (0, 1):                       # x block and y block share the 2×2
            pos, slo = axis, 2 + axis
            for r, out in ((0, axis), (1, 2 + axis)):
                add(pos, _fit_lambda(Ms[:, r, 0], lams), out)
                add(slo, _fit_lambda(Ms[:, r, 1], lams), out)
        add(None, _fit_lambda(Ts, lams), 4)
        n_out, radii = 5, []
        if aperture == "stop" and self.Mstop550 is not None:
            for axis in (0, 1):
                add(axis, _fit_lambda(Ss[:, 0, 0], lams), 5 + axis)
                add(2 + axis, _fit_lambda(Ss[:, 0, 1], lams), 5 + axis)
            n_out, radii = 7, [lens.stop.semi_diameter]
        exps = np.array(sorted(terms), dtype=np.int64)
        C = np.zeros((len(exps), n_out))
        for t, e in enumerate(map(tuple, exps)):
            for out, v in terms[e].items():
                C[t, out] = v
        core = SparsePoly(exps, C, center=[0, 0, 0, 0, LAM0_NM], scale=[1, 1, 1, 1, LAM_SCALE_NM])
        self._setup_core(core, radii)

    def matrix(self, lam_nm: float = LAM0_NM) -> np.ndarray:
        """The 2×2 slope matrix z_in → z_out at ``lam_nm`` (exact, not the λ polynomial)."""
        return path_matrices(self.lens, self.spec, self.z_in, self.z_out, lam_nm)[0]

    def matrix4(self, lam_nm: float = LAM0_NM) -> np.ndarray:
        """The 4×4 matrix acting on (x, y, sx, sy)."""
        m = self.matrix(lam_nm)
        M4 = np.zeros((4, 4))
        for a in (0, 1):
            M4[a, a], M4[a, 2 + a], M4[2 + a, a], M4[2 + a, 2 + a] = m[0, 0], m[0, 1], m[1, 0], m[1, 1]
        return M4

    def describe(self) -> dict:
        return {**super().describe(), "throughput": self.throughput_mode, "aperture": self.aperture,
                "matrix_550nm": self.M550.tolist()}
