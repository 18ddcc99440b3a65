"""Pure-numpy optics (no Mitsuba, no Dr.Jit at import): prescriptions, glass, file formats, paraxial."""
