"""Exception types.  Every error names where it came from (file, surface, field) and what is valid."""
from __future__ import annotations


class NeuralLensError(Exception):
    """Base class of every error raised by mi-neurallens."""


class LensError(NeuralLensError, ValueError):
    """An invalid lens prescription (bad file, impossible geometry, unknown glass, ...).

    The message is built from ``where`` (file name, surface index/label, field) and ``what``
    so a user can find the offending line without reading our code.
    """

    def __init__(self, what: str, *, file: str | None = None, surface: int | None = None,
                 label: str | None = None, field: str | None = None):
        self.file, self.surface, self.label, self.field, self.what = file, surface, label, field, what
        parts = []
        if file:
            parts.append(str(file))
        if surface is not None:
            parts.append(f"surface {surface}" + (f" ({label})" if label else ""))
        if field:
            parts.append(f"field '{field}'")
        super().__init__((": ".join(parts) + ": " if parts else "") + what)


class GlassError(LensError):
    """A medium that cannot be resolved (unknown catalog glass, bad dispersion data)."""


class ModelError(NeuralLensError, ValueError):
    """An invalid or mismatched neural lens model file."""
