"""Where the package's data is found: lenses, their models and training recipes, and the demo scenes.

Everything a user gets from ``pip install`` ships inside the package, under ``mi_neurallens/data/``, and this
module is the one place that knows where.  Lenses, models and recipes live in *lens libraries*, folders laid
out as::

    <name>.json                          a prescription (project JSON, docs/lens-format.md)
    models/<name>.model.safetensors      its learned maps, with the evaluation record beside it
                                         (<name>.model.safetensors.eval.json / .eval.md)
    recipes/<name>.toml                  its training recipe (docs/training.md)

The search path is every folder of ``$MI_NEURALLENS_LENSES`` (a path list, separated like ``PATH``), then the
library inside the package (``mi_neurallens/data/lenses``).  The first library that has a file wins, so a
user's copy of a lens, a model or a recipe is found before the bundled one, and a library of one's own lenses
is added by naming its folder.  Each of the three kinds is looked up on its own: a user's library may hold a
retrained model for a bundled lens without a copy of the prescription.

Scenes are found by name in ``mi_neurallens/data/scenes`` (``still_life``, ``night_point``, ...), or used as
given when the name is a path to an existing file.

This module imports nothing of the package but :mod:`.errors`, so every folder may use it.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from .errors import LensError

#: environment variable: lens libraries searched before the bundled one (os.pathsep-separated)
LENSES_ENV = "MI_NEURALLENS_LENSES"

#: the origin label of the library inside the package
BUNDLED = "bundled"

MODEL_SUFFIX = ".model.safetensors"

_DATA = Path(__file__).resolve().parent / "data"


@dataclass(frozen=True)
class Library:
    """One folder of lenses (``path``) and where it came from (``origin``: ``"bundled"`` or
    ``"$MI_NEURALLENS_LENSES"``)."""
    path: Path
    origin: str

    def lens(self, name: str) -> Path:
        return self.path / f"{name}.json"

    def model(self, name: str) -> Path:
        return self.path / "models" / f"{name}{MODEL_SUFFIX}"

    def recipe(self, name: str) -> Path:
        return self.path / "recipes" / f"{name}.toml"


def bundled_library() -> Library:
    """The library that ships inside the package (``mi_neurallens/data/lenses``)."""
    return Library(_DATA / "lenses", BUNDLED)


def libraries() -> list[Library]:
    """The search path: ``$MI_NEURALLENS_LENSES``'s folders in order, then the bundled library."""
    env = os.environ.get(LENSES_ENV, "")
    user = [Library(Path(p).expanduser(), f"${LENSES_ENV}") for p in env.split(os.pathsep) if p.strip()]
    return user + [bundled_library()]


def _first(kind: str, name: str) -> Path | None:
    for lib in libraries():
        p = getattr(lib, kind)(name)
        if p.is_file():
            return p
    return None


# ------------------------------------------------------------------------------------------ lenses
def lens_names() -> list[str]:
    """Names of every lens on the search path, sorted (a name in two libraries is listed once)."""
    names: set[str] = set()
    for lib in libraries():
        if lib.path.is_dir():
            names.update(p.stem for p in lib.path.glob("*.json") if not p.name.startswith("."))
    return sorted(names)


def find_lens(name: str) -> Path | None:
    """The prescription of the lens ``name`` on the search path, or ``None``."""
    return _first("lens", name)


def lens_path(name: str) -> Path:
    """The prescription of the lens ``name``; a :class:`~mi_neurallens.errors.LensError` that lists the lenses
    there are when there is none."""
    p = find_lens(name)
    if p is None:
        raise LensError(f"no lens named '{name}' in {search_path_text()}; lenses: {', '.join(lens_names()) or '(none)'}")
    return p


def lens_origin(name: str) -> Library | None:
    """The library the lens ``name`` is found in (the first on the search path)."""
    for lib in libraries():
        if lib.lens(name).is_file():
            return lib
    return None


def search_path_text() -> str:
    """The search path in words, for error messages."""
    return " then ".join(f"{lib.path} ({lib.origin})" for lib in libraries())


# ------------------------------------------------------------------------------------------ models, recipes
def find_model(name: str) -> Path | None:
    """The model file of the lens ``name`` on the search path (``models/<name>.model.safetensors``), or
    ``None``."""
    return _first("model", name)


def model_names() -> list[str]:
    """Names of the lenses with a model on the search path, sorted."""
    names: set[str] = set()
    for lib in libraries():
        d = lib.path / "models"
        if d.is_dir():
            names.update(p.name[:-len(MODEL_SUFFIX)] for p in d.glob(f"*{MODEL_SUFFIX}"))
    return sorted(names)


def find_recipe(name: str) -> Path | None:
    """The training recipe of the lens ``name`` on the search path (``recipes/<name>.toml``), or ``None``."""
    return _first("recipe", name)


# ------------------------------------------------------------------------------------------ scenes
def scenes_dir() -> Path:
    """The folder of the bundled demo scenes."""
    return _DATA / "scenes"


def scene_names() -> list[str]:
    """Names of the bundled scenes (file names without ``.xml``), sorted."""
    return sorted(p.stem for p in scenes_dir().glob("*.xml"))


def scene_path(spec: str | os.PathLike) -> Path:
    """A scene file: ``spec`` itself when it names an existing file, else the bundled scene of that name
    (``still_life`` or ``still_life.xml``); a :class:`~mi_neurallens.errors.LensError` naming the bundled
    scenes otherwise."""
    p = Path(spec).expanduser()
    if p.is_file():
        return p
    name = p.name[:-4] if p.name.endswith(".xml") else p.name
    q = scenes_dir() / f"{name}.xml"
    if q.is_file() and str(p.parent) in ("", ".", "scenes"):
        return q
    raise LensError(f"scene file not found: {str(spec)!r}; or a bundled scene: {', '.join(scene_names())} "
                    f"(in {scenes_dir()})")
