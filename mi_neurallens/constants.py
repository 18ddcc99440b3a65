"""Constants used across the package, each defined once (units in the names or the comments).

Only plain numbers: importing this module imports nothing else, so every layer (``optics`` included)
may use it.
"""

#: Fraunhofer spectral lines (nm): d (helium, 587.5618) is the reference wavelength of nd, Vd, the
#: paraxial numbers and the layout plots; F and C (hydrogen) give the Abbe number; e (mercury).
LAMBDA_D = 587.5618
LAMBDA_F = 486.1327
LAMBDA_C = 656.2725
LAMBDA_E = 546.0740

#: width and height of the 35 mm full-frame film (mm): the default sensor of the cameras
FULL_FRAME_MM = (36.0, 24.0)

#: half diagonal of the 36 × 24 mm full-frame film, √(18² + 12²) = 21.63331 mm, as used for fields of
#: view, ghost ranking and spot-diagram extents (mm)
FULL_FRAME_HALF_DIAGONAL_MM = 21.6333

#: Rec. 709 / sRGB luminance weights of linear (R, G, B)
LUMINANCE_WEIGHTS = (0.2126, 0.7152, 0.0722)

#: arcseconds per radian (180 · 3600 / π)
ARCSEC_PER_RAD = 180.0 * 3600.0 / 3.141592653589793

#: the visible range (nm) over which wavelengths are sampled (CIE 1931 observer tabulation) and glass
#: indices are checked; spectral quantities outside it are never asked for
VISIBLE_RANGE_NM = (360.0, 830.0)
