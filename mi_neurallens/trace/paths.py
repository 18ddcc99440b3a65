"""Light-path types through a sequential lens and their binary ids (paper §3, "path type").

A *path* is the sequence of transmit (T) / reflect (R) decisions a ray makes at the optical
surfaces it hits.  The aperture stop is **not** an interaction (it only occludes), so interactions
are counted on ``lens.optical_indices`` only.

**Path id (bit order).**  Bit ``m`` of the id (``1 << m``) is 1 when the ``m``-th interaction along
the ray (0-based, in the order the ray meets the surfaces, starting at the first surface it hits)
is a reflection.  Decisions after the highest set bit are all T, so every id is finite and:

* ``0`` is the transmit path (``"transmit"``) in either direction;
* a forward ghost that reflects first at optical surface ``a`` and then at optical surface ``b``
  (``b < a``; indices into ``lens.optical_indices``, front to back) has id
  ``(1 << a) | (1 << (2*a - b))``: T through surfaces 0…a−1 (a interactions), R at a (interaction
  a), T back through a−1…b+1 (a−b−1 interactions), R at b (interaction 2a−b), then T to the sensor.

For backward paths (sensor → object) the first interaction is at the rear-most optical surface.
A forward path must leave through the rear (toward the sensor) and a backward path through the
front; ids that do not are rejected with a clear error.
"""
from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations
import math

from ..errors import NeuralLensError

FORWARD, BACKWARD = "forward", "backward"


@dataclass(frozen=True)
class Step:
    """One static step of a traced path, with the facts every consumer of the path needs resolved once
    (the tracer, Taylor and ABCD optics, the fitted baseline's aperture fits).

    ``kind``: ``"T"``/``"R"`` (an interaction at optical surface ``surface``), or ``"stop"``
    (crossing the aperture-stop plane).  ``heading`` is +1 when the ray travels toward +z when it
    reaches this step, −1 otherwise.  ``surface`` indexes ``lens.surfaces``.
    """

    kind: str
    surface: int
    heading: int
    #: the media on either side of the surface in the ray's order: (the one the ray arrives in, the
    #: one across the surface); ``(None, None)`` for the stop, which only occludes
    media: tuple = (None, None)
    #: the radius (mm) a ray's hit point must not exceed: the surface's clear semi-diameter tightened by
    #: the housing of every gap this step borders (a reflection borders only the gap it arrives from);
    #: for the stop, its semi-diameter (a bladed stop is tested as a polygon by the tracer)
    clear_radius: float = math.inf


@dataclass(frozen=True)
class PathSpec:
    """A path type resolved against a lens: its id, direction and static step sequence."""

    id: int
    direction: str
    steps: tuple[Step, ...]

    @property
    def num_reflections(self) -> int:
        return sum(1 for s in self.steps if s.kind == "R")

    @property
    def interactions(self) -> tuple[Step, ...]:
        return tuple(s for s in self.steps if s.kind != "stop")

    def describe(self) -> str:
        return " ".join(f"{s.kind}{s.surface}" for s in self.steps)


def ghost_id(a: int, b: int) -> int:
    """Id of the forward ghost reflecting at optical surface ``a`` then ``b`` (``b < a``)."""
    if not (0 <= b < a):
        raise NeuralLensError(f"ghost ({a}, {b}): need 0 <= b < a (optical-surface indices)")
    return (1 << a) | (1 << (2 * a - b))


def ghost_surfaces(path_id: int) -> tuple[int, int]:
    """Inverse of :func:`ghost_id`: (a, b) for a forward two-reflection id."""
    bits = [m for m in range(path_id.bit_length()) if path_id >> m & 1]
    if len(bits) != 2:
        raise NeuralLensError(f"path id {path_id} is not a ghost (it has {len(bits)} reflections, need 2)")
    a = bits[0]
    b = 2 * a - bits[1]
    if not 0 <= b < a:
        raise NeuralLensError(f"path id {path_id} is not a forward two-reflection path")
    return a, b


def all_ghosts(lens) -> list[tuple[int, int, int]]:
    """Every forward two-reflection path of ``lens`` as ``(id, a, b)``; C(n, 2) of them for n
    optical surfaces.  Whether light can actually reach the sensor along each one is a question
    for the tracer (:func:`mi_neurallens.trace.api.ghost_reachability`)."""
    n = len(lens.optical_indices)
    return [(ghost_id(a, b), a, b) for b, a in combinations(range(n), 2)]


def resolve_path(lens, path, direction: str = FORWARD) -> PathSpec:
    """Turn ``path`` (``"transmit"``, an int id, a ``(a, b)`` ghost pair, or a PathSpec) into the
    static step list for ``lens`` in ``direction``."""
    if isinstance(path, PathSpec):
        if path.direction != direction:
            raise NeuralLensError(f"path {path.id} was resolved for {path.direction}, not {direction}")
        return path
    if direction not in (FORWARD, BACKWARD):
        raise NeuralLensError(f"direction must be 'forward' or 'backward', got {direction!r}")
    if isinstance(path, str):
        if path != "transmit":
            raise NeuralLensError(f"unknown path {path!r}: use 'transmit', an integer path id or a ghost (a, b)")
        pid = 0
    elif isinstance(path, tuple):
        pid = ghost_id(*path)
    elif isinstance(path, int) and not isinstance(path, bool) and path >= 0:
        pid = int(path)
    else:
        raise NeuralLensError(f"invalid path {path!r}: use 'transmit', a non-negative integer id or (a, b)")

    opt = lens.optical_indices
    n = len(opt)
    stop = lens.stop_index
    heading = +1 if direction == FORWARD else -1
    k = 0 if direction == FORWARD else n - 1
    steps: list[Step] = []

    def stops_between(s_from: float, s_to: float, h: int):
        lo, hi = min(s_from, s_to), max(s_from, s_to)
        if lo < stop < hi:
            steps.append(Step("stop", stop, h, clear_radius=float(lens.stop.semi_diameter)))

    prev = -0.5 if direction == FORWARD else len(lens.surfaces) - 0.5  # virtual input position
    m = 0
    max_steps = 4 * n + 2 * pid.bit_length() + 8
    while 0 <= k < n:
        if m > max_steps:  # pragma: no cover - cannot happen for finite ids
            raise NeuralLensError(f"path id {pid} does not terminate")
        s = opt[k]
        stops_between(prev, s, heading)
        kind = "R" if (pid >> m) & 1 else "T"
        steps.append(interaction_step(lens, kind, s, heading))
        prev = s
        if kind == "R":
            heading = -heading
        k += heading
        m += 1
    if m <= pid.bit_length() - 1:
        raise NeuralLensError(f"path id {pid} ({bin(pid)}) has reflections after the ray has left the lens "
                              f"({m} interactions)")
    exit_pos = len(lens.surfaces) - 0.5 if k >= n else -0.5
    stops_between(prev, exit_pos, heading)
    if (direction == FORWARD) != (k >= n):
        side = "front (object side)" if k < 0 else "rear (sensor side)"
        raise NeuralLensError(f"path id {pid} leaves the lens through the {side}; a {direction} path must "
                              f"leave through the {'rear' if direction == FORWARD else 'front'}")
    return PathSpec(pid, direction, tuple(steps))


def interaction_step(lens, kind: str, i: int, h: int) -> Step:
    """The T/R step at surface ``i`` with heading ``h``, its media and clear radius resolved."""
    surfs = lens.surfaces
    mb, ma = lens.medium_before(i), surfs[i].medium
    r = surfs[i].semi_diameter
    gap_in = i - 1 if h > 0 else i
    gaps = (gap_in,) if kind == "R" else (gap_in, i if h > 0 else i - 1)
    for g in gaps:
        if 0 <= g < len(surfs) and surfs[g].housing_radius is not None:
            r = min(r, surfs[g].housing_radius)
    return Step(kind, i, h, (mb, ma) if h > 0 else (ma, mb), float(r))


def rank_ghosts_by_energy(lens, energy, ghost_ids=None, skip=None) -> list[dict]:
    """Rank the forward ghosts of ``lens`` by the energy they carry, largest first.

    ``energy(path_id) -> (energy, valid_fraction)`` is the caller's estimator (flares and training
    sample the field differently); it is also called with ``0`` for the transmit path, which scales
    ``relative_to_transmit``.  ``ghost_ids``: only these ids; ``skip(a, b) -> bool``: ghosts known to
    carry nothing (energy 0 without tracing).  A ghost whose path cannot be traced (an error from
    :func:`resolve_path`) gets energy 0.  Each entry: ``path_id``, ``surfaces`` [a, b], ``energy``,
    ``valid_fraction``, ``share`` of the total ghost energy, ``cumulative_share``,
    ``relative_to_transmit``.
    """
    e_t, _ = energy(0)
    out = []
    for pid, a, b in all_ghosts(lens):
        if ghost_ids is not None and pid not in ghost_ids:
            continue
        e, f = 0.0, 0.0
        if skip is None or not skip(a, b):
            try:
                e, f = energy(pid)
            except NeuralLensError:
                pass
        out.append({"path_id": pid, "surfaces": [a, b], "energy": float(e), "valid_fraction": float(f)})
    out.sort(key=lambda d: -d["energy"])
    total = sum(d["energy"] for d in out) or 1.0
    c = 0.0
    for d in out:
        d["share"] = d["energy"] / total
        c += d["share"]
        d["cumulative_share"] = c
        d["relative_to_transmit"] = d["energy"] / e_t if e_t > 0 else 0.0
    return out
