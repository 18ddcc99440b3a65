"""Anti-reflection coatings of lens surfaces: one quarter-wave layer, or a multilayer stack.

Two kinds, both immutable and hashable, both held in :attr:`Surface.coating`:

:class:`Coating`       one layer of index ``index``, a quarter wave thick at ``design_wavelength_nm`` (what
                       every version of the format had; its fingerprint and its formula are unchanged).
:class:`CoatingStack`  thin films listed **from the glass outward**, each a :class:`Layer` (a medium with its
                       n(λ) and a physical thickness in nm), with the design wavelength they were made for.

Reflectance (:func:`mi_neurallens.trace.interactions.interface_reflectance`, the one place it is computed, in
the tracer, the Taylor and ABCD baselines alike) is exact thin-film interference: for a stack, the
characteristic-matrix (transfer-matrix) method of Macleod, *Thin-Film Optical Filters* ch. 2, for s and p
with tilted admittances (η_s = n cos θ, η_p = n / cos θ), then averaged (unpolarised light); the layers'
indices at each ray's wavelength, their angles from Snell's invariant n sin θ.  Lossless layers: the
reflectance is the same from either side, so the tracer needs only know which side of the surface is the
"outward" (ambient) one: the medium of lower index at the design wavelength.  A layer in which the ray is
evanescent (only past the critical angle of the ambient, where the surface reflects totally anyway, or on a
glass–glass surface) has its cos θ clamped to 1e-6 (frustrated total reflection is not modelled).

Presets (:func:`preset`, also ``coating`` of ``lens_flare`` and ``{"preset": ...}`` in the project JSON):

``quarter_wave``  MgF2 (n = 1.38, constant), λ/4 at 550 nm: :class:`Coating` ``(1.38, 550)``.
``broadband``     the classic quarter-half-quarter AR, glass | Al2O3 λ/4 | ZrO2 λ/2 | MgF2 λ/4 | air at 550 nm,
                  with film indices at 550 nm of 1.63, 2.10 and 1.3785 (:data:`AL2O3`, :data:`ZRO2`,
                  :data:`MGF2`: published Sellmeier dispersions, the first two scaled to film density, see
                  :func:`film`).  On N-BK7 at normal incidence it reflects under 0.25 % from 460 to 700 nm (at
                  400 nm 6.6 %: the violet residue that makes coated lenses look purple), against 4.2 % bare and
                  1.3 % for the single MgF2 layer at 550 nm.
"""
from __future__ import annotations

from dataclasses import dataclass, field
import math

from .media import Medium

#: MgF2, ordinary ray, Dodge 1984 (Appl. Opt. 23, 1980), 0.2-7 µm, as on refractiveindex.info; evaporated
#: MgF2 films have about the bulk index (1.38)
MGF2 = Medium("MgF2", "sellmeier", (0.48755108, 0.04338408 ** 2, 0.39875031, 0.09461442 ** 2,
                                    2.3120353, 23.793604 ** 2),
              source={"reference": "Dodge 1984, ordinary ray (refractiveindex.info)"})
#: Al2O3 (sapphire), ordinary ray, Malitson & Dodge 1972 (J. Opt. Soc. Am. 62, 1405), 0.2-5 µm: the bulk crystal
AL2O3_BULK = Medium("Al2O3 (bulk)", "sellmeier", (1.4313493, 0.0726631 ** 2, 0.65054713, 0.1193242 ** 2,
                                                  5.3414021, 18.028251 ** 2),
                    source={"reference": "Malitson & Dodge 1972, ordinary ray (refractiveindex.info)"})
#: ZrO2 (cubic, Y2O3-stabilised), Wood & Nassau 1982 (Appl. Opt. 21, 2978), 0.36-5.1 µm: the bulk crystal
ZRO2_BULK = Medium("ZrO2 (bulk)", "sellmeier", (1.347091, 0.062543 ** 2, 2.117788, 0.166739 ** 2,
                                                9.452943, 24.320570 ** 2),
                   source={"reference": "Wood & Nassau 1982 (refractiveindex.info)"})


def film(bulk: Medium, n_550: float, name: str) -> Medium:
    """An evaporated film of a bulk material: less dense, so a lower index.  Modelled as the bulk Sellmeier terms
    scaled by one factor, ``n_f² − 1 = s (n_b² − 1)``, with ``s`` chosen so that ``n_f(550 nm) = n_550``: the
    bulk dispersion's shape at the film's index."""
    nb = float(bulk.index(550.0))
    s = (n_550 * n_550 - 1.0) / (nb * nb - 1.0)
    c = list(bulk.coefficients)
    c[0::2] = [b * s for b in c[0::2]]
    return Medium(name, "sellmeier", tuple(c),
                  source={"reference": f"{bulk.source.get('reference', bulk.name)}, scaled to n(550 nm) = {n_550}"})


#: evaporated Al2O3 and ZrO2 films at the indices the classic quarter-half-quarter designs use
AL2O3 = film(AL2O3_BULK, 1.63, "Al2O3")
ZRO2 = film(ZRO2_BULK, 2.10, "ZrO2")

#: the materials a project JSON may name by string in a stack's layer
COATING_MATERIALS = {"MgF2": MGF2, "Al2O3": AL2O3, "ZrO2": ZRO2, "Al2O3 (bulk)": AL2O3_BULK,
                     "ZrO2 (bulk)": ZRO2_BULK}


@dataclass(frozen=True)
class Coating:
    """A single-layer anti-reflection coating, a quarter wave thick at ``design_wavelength_nm``.

    ``index`` is the layer's refractive index (MgF2: 1.38), constant in λ.  The reflectance is the exact
    thin-film (Airy) result for each polarisation, averaged; see :mod:`mi_neurallens.trace.interactions`.
    """

    index: float = 1.38
    design_wavelength_nm: float = 550.0

    @property
    def thickness_nm(self) -> float:
        return self.design_wavelength_nm / (4.0 * self.index)


@dataclass(frozen=True)
class Layer:
    """One thin film: its medium (n(λ)) and its physical thickness in nm."""

    medium: Medium
    thickness_nm: float

    def __post_init__(self):
        t = float(self.thickness_nm)
        if not (math.isfinite(t) and t > 0.0):
            raise ValueError(f"coating layer '{self.medium.name}': thickness must be > 0 nm, got {t}")
        object.__setattr__(self, "thickness_nm", t)


@dataclass(frozen=True)
class CoatingStack:
    """Thin films on a surface, ``layers`` listed from the glass outward, designed for
    ``design_wavelength_nm`` (which also decides, with the two media's indices there, which side of the
    surface is the glass).  ``name`` is informative (a preset's name) and not part of the fingerprint."""

    layers: tuple[Layer, ...]
    design_wavelength_nm: float = 550.0
    name: str = field(default="", compare=False)

    def __post_init__(self):
        if not self.layers:
            raise ValueError("a coating stack needs at least one layer")
        object.__setattr__(self, "layers", tuple(self.layers))

    @classmethod
    def from_waves(cls, spec, design_wavelength_nm: float = 550.0, name: str = "") -> "CoatingStack":
        """A stack from (medium, optical thickness in waves at the design wavelength) pairs, glass outward:
        ``0.25`` is a quarter wave, physical thickness ``0.25 λ / n(λ)``."""
        lam = float(design_wavelength_nm)
        return cls(tuple(Layer(m, float(w) * lam / float(m.index(lam))) for m, w in spec), lam, name)

    def ambient_is_first(self, m1: Medium, m2: Medium) -> bool:
        """True when ``m1`` (the medium the ray comes from) is the outward side: the lower index at the design
        wavelength (ties: ``m1``)."""
        lam = self.design_wavelength_nm
        return float(m1.index(lam)) <= float(m2.index(lam))


PRESETS = ("quarter_wave", "broadband")


def preset(name: str):
    """A named coating (see the module docstring): ``quarter_wave`` or ``broadband``."""
    if name == "quarter_wave":
        return Coating(1.38, 550.0)
    if name == "broadband":
        return CoatingStack.from_waves(((AL2O3, 0.25), (ZRO2, 0.5), (MGF2, 0.25)), 550.0, name="broadband")
    raise ValueError(f"unknown coating preset {name!r}; presets: {', '.join(PRESETS)}")

