"""Training configuration: dataclasses with defaults, read from TOML (``tomllib``).

A lens's recipe, ``recipes/<lens>.toml`` of its lens library (the bundled ones in
``mi_neurallens/data/lenses/recipes/``), overrides any field; unknown keys are an error (typos must
not silently fall back to defaults).  ``schedule = "paper"`` in a ``[regressor]``/``[classifier]``
table selects the paper's schedule (Adam, lr 1e-4 × 0.95 every 10k batches, batch 8192, no residual,
cosine direction loss); the default ``"fast"`` schedule is what we measured to reach the paper's
accuracy within a CPU budget (docs/training.md).
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields, replace
import hashlib
import json

from ..constants import FULL_FRAME_HALF_DIAGONAL_MM
from ..errors import NeuralLensError
from ..flare.verify import BANDS as VERIFY_BANDS
from ..transport.planes import DEFAULT_CLOSE_FOCUS_MM, DEFAULT_FIELD_MARGIN, recipe_path


@dataclass
class NetConfig:
    """One network's settings (a ``[regressor]``, ``[classifier]`` or ``[stop]`` table).  Where the defaults' values
    came from: docs/training.md, "How the defaults were chosen"."""

    hidden: int = 5
    width: int = 32
    activation: str = "tanh"
    schedule: str = "fast"              # "fast" (cosine) or "paper" (exponential)
    lr: float = 3e-3
    lr_min: float = 1e-6
    warmup_steps: int = 200
    decay: float = 0.95                 # paper schedule: × decay every decay_every steps
    decay_every: int = 10000
    batch: int = 8192
    max_steps: int = 20000
    max_minutes: float = 10.0           # wall-clock cap per network (a stack of K networks: K × this)
    eval_every: int = 500
    patience: int = 8                   # evaluations without improvement before early stop
    residual: str = "linear"            # regressor: predict the residual of a least-squares linear guess
    direction_loss: str = "mse+cosine"  # or "cosine" (paper)
    cosine_weight: float = 1.0
    loss_weights: str = "goals"         # regressor, stop head: MSE weights ∝ std / goal, floored; or "uniform"
    direction_weight: float = 1.0       # regressor: its direction columns' loss weight × this (outputs.loss_weights)
    odd_y: bool = True                  # regressor: y, dy = (ωy / s_max) × network: odd in ωy, no mirror seam
    input_box: bool = False             # regressor, stop head: train on the valid rays' box (input_box.py)
    exit_position: str = "auto"         # regressor: "plane", "cos" (× |dz|) or "auto" (cos beyond 60°: outputs.py)
    target: str = "margin"              # classifier: "margin" (scale·aperture margin, a sharper edge) or "label" (BCE)
    margin_scale: float = 40.0          # classifier "margin" target: logit slope per unit margin at the boundary
    margin_clip: float = 3.0            # classifier "margin" target: |logit| it saturates at
    boundary_sigma: tuple = (1e-3, 5e-2)  # classifier: log-uniform widths of the boundary perturbations (unit cube)
    edge_weight: float = 0.0            # regressor: weight 1 + this·exp(−margin / edge_margin) near edges (0: off)
    edge_margin: float = 0.02           # regressor: the aperture margin over which that weight falls off
    stop_at_goals: bool = True          # a network stops as soon as a validation meets its goals (below)
    goal_position_um: tuple = (2.0, 20.0)       # regressor: exit-position error (median, p99), µm
    goal_direction_arcsec: tuple = (5.0, 40.0)  # regressor: exit-direction error (median, p99), arcsec
    goal_misclassification: float = 0.005       # classifier: held-out misclassification (natural mix)
    goal_stop_um: tuple = (2.0, 20.0)           # stop head: stop-plane crossing error (median, p99), µm
    goal_margin: float = 0.9            # stop when the validation is within goal × this (the held-out set differs)
    goal_corners: bool = False          # regressor over moving groups: its goals checked on the range's corners too
                                        # (configurations.CORNER_EDGES), not only on its cells (CELL_EDGES)
    pool: int = 2_000_000               # samples held in memory per map; refreshed from the tracer
    refresh_every: int = 2000           # steps between pool refreshes (fresh tracer data)
    refresh_fraction: float = 0.25
    lm_minutes: float = 0.0             # Levenberg–Marquardt finish per network after Adam (0: none; levenberg.py)
    lm_iterations: int = 0              # at most this many finish iterations (0: lm_minutes alone; a count: any machine)
    lm_rows: int = 8192                 # fresh samples per Levenberg–Marquardt iteration
    lm_eval_every: int = 10             # Levenberg–Marquardt iterations between validations
    lm_max_weights: int = 2500          # larger networks are left to Adam (levenberg.MAX_PARAMS, the same)
    lm_huber: float = 0.0               # regressor's finish: Huber loss, δ = this × its start's median |residual| (0: squares)
    lm_huber_refix: float = 0.0         # ... and δ fixed anew whenever a column's median |residual| has fallen this many
                                        # times since it was (0: once, at the finish's start; regressor.RegressorFit.lm_refix)
    lm_cell_weight: float = 0.0         # regressor's finish over moving groups: rows weighted by their configuration cell's
                                        # error over the cells' median, to this power, best weights by the worst cell (0: off)
    widen_width: int = 0                # after the finish: the hidden layers widened to this width (the same function)
    widen_minutes: float = 0.0          # and finished this many minutes more, to that budget, not stopping at the goals
                                        # (0: not; levenberg.widened_finish)
    widen_iterations: int = 0           # ... and at most this many iterations (0: as lm_iterations; a count: any machine)
    sizes: tuple = ()                   # "HxW" to try, smallest first; a map keeps the first at its goals (maps.py)


#: Adam's steps before a regressor's finish: enough to come near the optimum the finish reaches, the same on any machine
REGRESSOR_ADAM_STEPS = 4000


def regressor_defaults() -> NetConfig:
    """A 3×16 regressor, 1.5 min of Adam then up to 4 of the finish: the camera goals, rendering 3× faster than 5×32."""
    return NetConfig(hidden=3, width=16, max_steps=REGRESSOR_ADAM_STEPS, max_minutes=1.5, lm_minutes=4.0)


def classifier_defaults() -> NetConfig:
    """A 2×16 margin classifier, 1 min of Adam then up to 1 of the finish, to its patience rather than its goals:
    stopped at the first validation within 0.5 %, fresh camera maps of five lenses were left at 0.27–0.47 %
    misclassified; to patience, at 0.05–0.35 % for 0.1–0.4 min more (docs/training.md).  Forward maps' classifiers
    stop at their goals (:data:`FORWARD_CLASSIFIER`)."""
    return NetConfig(hidden=2, width=16, lr=3e-3, max_steps=40000, max_minutes=1.0, lm_minutes=1.0,
                     residual="none", direction_loss="none", pool=1_500_000, stop_at_goals=False)


def stop_defaults() -> NetConfig:
    """The stop head: the regressor's 3×16 recipe, up to 1.5 min of the finish: more precise than 2×32, half the cost."""
    return NetConfig(hidden=3, width=16, lr=3e-3, max_steps=REGRESSOR_ADAM_STEPS, max_minutes=0.5, lm_minutes=1.5,
                     patience=12, residual="linear", loss_weights="goals", direction_loss="none", odd_y=True,
                     pool=1_000_000)


#: the forward maps' finish iterations per network: about what its minutes give on a CPU, so a GPU stack gets no more
FORWARD_LM_ITERATIONS = {"regressor": 300, "classifier": 900, "stop": 300}
#: forward (flare) regressors: 3×16 with 1 min of Adam and 1 of the finish, on their input box: the flare goals sooner
FORWARD_REGRESSOR = dict(max_minutes=1.0, max_steps=REGRESSOR_ADAM_STEPS, lm_minutes=1.0,
                         lm_iterations=FORWARD_LM_ITERATIONS["regressor"], input_box=True)
#: the forward regressor's position goals (median, p99), µm, at 2048 pixels across full frame: 0.17 / 1.7 pixels
FLARE_GOAL_UM_2K = (3.0, 30.0)
#: the forward regressor's direction goals (median, p99), arcsec, at 2048 pixels (both scale: flare_goals)
FLARE_GOAL_ARCSEC_2K = (30.0, 200.0)
#: the forward classifier's Adam steps: where its validation has flattened, and a count is the same on every machine
FORWARD_CLASSIFIER_ADAM_STEPS = 12000
#: forward classifiers: margin target, 0.4 min of Adam + 0.35 of the finish: 1.25 min of Adam's flares, sooner;
#: stopping at their goals (a lens has up to 32 ghosts), whatever the camera map's classifier does
FORWARD_CLASSIFIER = dict(target="margin", goal_misclassification=0.0005, max_minutes=0.4, lm_minutes=0.35,
                          max_steps=FORWARD_CLASSIFIER_ADAM_STEPS, patience=30, stop_at_goals=True,
                          lm_iterations=FORWARD_LM_ITERATIONS["classifier"])
#: a forward stop head's finish, at most (used only through an iris): 32 ghosts × the camera head's 1.5 min is too long
FORWARD_STOP_LM_MINUTES = 0.5
#: forward stop heads: the regressor's 3×16 recipe on their input box, which places a ghost's crossings best
FORWARD_STOP = dict(hidden=3, width=16, max_steps=REGRESSOR_ADAM_STEPS, lm_iterations=FORWARD_LM_ITERATIONS["stop"],
                    input_box=True)

PAPER = dict(schedule="paper", lr=1e-4, decay=0.95, decay_every=10000, batch=8192, warmup_steps=0,
             residual="none", direction_loss="cosine", loss_weights="uniform", odd_y=False, target="label")


@dataclass
class TrainConfig:
    """A lens's training recipe (``recipes/<lens>.toml`` of its lens library); the defaults' histories:
    docs/training.md, "How the defaults were chosen"."""

    lens: str = ""
    seed: int = 1
    backward: list = field(default_factory=lambda: ["transmit"])
    forward: list = field(default_factory=lambda: ["transmit", "ghosts"])
    max_ghosts: int = 32                # keep the top-K ghosts carrying energy_fraction of ghost energy…
    ghost_energy_fraction: float = 0.99
    ship_ghosts: int = 32               # …but train at most this many (CPU budget)
    close_focus_mm: float | str = DEFAULT_CLOSE_FOCUS_MM  # nearest object the maps serve (mm; 0: infinity; planes.py)
    zoom_end_weight: float | None = None    # a lens with moving groups: its training rays' configurations drawn
    focus_end_weight: float | None = None   # a range's ends 1/(1-a) times as densely as uniform, 0 <= a < 1
    #                                         (transport/configurations.py end_warp; None: ZOOM_/FOCUS_END_WEIGHT)
    zoom_margin: float | None = None        # ...and drawn this fraction of the zoom range beyond each of its ends
    #                                         (the cam curves continued; None: configurations.ZOOM_MARGIN)
    zoom_dense_at: str = "ends"             # ...the zoom drawn densest at the range's "ends" or at every listed
    #                                         zoom position ("positions": also where the cam curves' cubics join)
    film_half_diagonal_mm: float = FULL_FRAME_HALF_DIAGONAL_MM
    flare_resolution: int = 2048        # pixels across the film the flare maps' goals are stated for (flare_goals)
    field_margin: float = DEFAULT_FIELD_MARGIN
    film_reach: float = 1.5             # forward maps learn rays landing within this × the film half diagonal (0: all)
    mcmc_threshold: float = 0.02        # valid fraction below which regressor data comes from MCMC
    mcmc_chains: int = 1 << 16
    mcmc_p_large: float = 0.3
    mcmc_sigma: float = 0.02
    heldout: int = 200_000
    fresnel: bool = True
    threads: int = 2
    device: str = "auto"                # "auto": CUDA if available, else CPU
    regressor: NetConfig = field(default_factory=regressor_defaults)
    classifier: NetConfig = field(default_factory=classifier_defaults)
    stop: NetConfig = field(default_factory=stop_defaults)  # the stop head (max_minutes = 0: none)
    # overrides for forward maps (flares); a recipe's [forward_*] table is merged into these
    forward_regressor: dict = field(default_factory=lambda: dict(FORWARD_REGRESSOR))
    forward_classifier: dict = field(default_factory=lambda: dict(FORWARD_CLASSIFIER))
    forward_stop: dict = field(default_factory=lambda: dict(FORWARD_STOP))
    # after training, each ghost map verified against the tracer for the flare's mode auto (not in the digest)
    verify_flare: bool = True
    verify_flare_bands: list = field(default_factory=lambda: list(VERIFY_BANDS))  # each further band only for
                                        # the ghosts the bands before leave above the gate (flare.verify.BANDS)
    verify_flare_samples: int = 24      # log2 samples of each render pair, per light position
    verify_flare_max_samples: int = 26  # a later band renders a ghost above the gate again, 4× the samples up to this
    verify_flare_cost: bool = True      # then each ghost map auto may learn timed against tracing it (auto_max_cost)
    verify_flare_cost_samples: int = 22  # log2 samples of each timed render
    verify_flare_refine_minutes: float = 1.5  # a ghost above the gate at every band: its finish again (0: off)

    def to_dict(self) -> dict:
        return asdict(self)

    def digest(self) -> str:
        """What a map was trained with, as 12 hex digits (the ``verify_flare*`` settings, which change no map, left
        out): a resumed run keeps the maps of an earlier one whose digest is its own."""
        d = {k: v for k, v in self.to_dict().items() if not k.startswith("verify_flare")}
        return hashlib.sha256(json.dumps(d, sort_keys=True).encode()).hexdigest()[:12]

    def net(self, kind: str, direction: str) -> NetConfig:
        """The network settings of ``kind`` (``regressor``, ``classifier`` or ``stop``) for maps in
        ``direction`` (forward maps apply the ``forward_<kind>`` overrides)."""
        base, over = getattr(self, kind), getattr(self, table_name(kind, "forward"))
        if direction != "forward":
            return base
        if kind == "regressor":
            over = {**flare_goals(self.flare_resolution, self.film_half_diagonal_mm), **over}
        if kind == "stop" and "lm_minutes" not in over:
            over = {**over, "lm_minutes": min(base.lm_minutes, FORWARD_STOP_LM_MINUTES)}
        return _apply(base, over, f"forward_{kind}") if over else base


def table_name(kind: str, direction: str) -> str:
    """The recipe table (and ``--set`` prefix) of the ``kind`` networks (``regressor``, ``classifier`` or ``stop``)
    of maps in ``direction``: ``forward_<kind>`` for forward maps, else ``<kind>``."""
    return f"forward_{kind}" if direction == "forward" else kind


def flare_goals(resolution: int, film_half_diagonal_mm: float = FULL_FRAME_HALF_DIAGONAL_MM) -> dict:
    """The forward regressor's goals for flares rendered ``resolution`` pixels across a 3:2 film of this
    half diagonal (mm): :data:`FLARE_GOAL_UM_2K` (µm) and :data:`FLARE_GOAL_ARCSEC_2K` (arcsec), both scaled
    by the pixel's size against a 2048-pixel full-frame one (17.6 µm): the same fraction of a pixel at any
    resolution.  ``flare_resolution = 1024`` doubles them."""
    if not isinstance(resolution, int) or resolution <= 0:
        raise NeuralLensError(f"training config: flare_resolution = {resolution!r}; give pixels across the film (> 0)")
    scale = (2048.0 / resolution) * (film_half_diagonal_mm / FULL_FRAME_HALF_DIAGONAL_MM)
    return dict(goal_position_um=tuple(g * scale for g in FLARE_GOAL_UM_2K),
                goal_direction_arcsec=tuple(g * scale for g in FLARE_GOAL_ARCSEC_2K))


#: the networks of one map, in the order a direction trains them (``TrainConfig.net`` kinds)
NETWORK_KINDS = ("regressor", "classifier", "stop")


def budget_minutes(cfg: TrainConfig, direction: str, n_maps: int) -> dict:
    """The most wall-clock minutes the networks of ``n_maps`` maps of ``direction`` may train with ``cfg``, per
    network kind (:data:`NETWORK_KINDS`): per size it may try (``sizes``, each trained whole), Adam's
    ``max_minutes``, the finish's ``lm_minutes`` and the widened finish's ``widen_minutes`` (a stop head for every
    map, at one size).  An upper bound — each
    network leaves at its goals, Adam also at ``max_steps`` — without the data set-up and the held-out
    evaluation."""
    out = {}
    for kind in NETWORK_KINDS:
        nc = cfg.net(kind, direction)
        tries = max(len(nc.sizes), 1) if kind != "stop" else 1
        widen = nc.widen_minutes if nc.widen_width > 0 else 0.0
        out[kind] = (0.0 if kind == "stop" and nc.max_minutes <= 0
                     else n_maps * tries * (nc.max_minutes + nc.lm_minutes + widen))
    return out


def minutes_text(minutes: float) -> str:
    """``95.2`` → ``"1 h 35 min"``; under an hour ``"12.5 min"``."""
    if minutes < 60:
        return f"{minutes:.1f} min"
    h, m = divmod(int(round(minutes)), 60)
    return f"{h} h {m:02d} min"


def parse_size(size) -> tuple:
    """``"3x16"`` → (3, 16): hidden layers × width, as ``NetConfig.sizes`` lists them."""
    try:
        h, w = (int(v) for v in str(size).lower().split("x"))
        if h >= 1 and w >= 1:
            return h, w
    except ValueError:
        pass
    raise NeuralLensError(f"training config: size {size!r}; write hidden layers x width, e.g. \"3x16\"")


#: the allowed values of NetConfig's string options
CHOICES = {"schedule": ("fast", "paper"), "target": ("margin", "label"), "residual": ("linear", "none"),
           "loss_weights": ("goals", "uniform"), "exit_position": ("auto", "plane", "cos")}


def _apply(nc: NetConfig, d: dict, where: str) -> NetConfig:
    d = dict(d)
    if d.get("schedule") == "paper":
        d = {**PAPER, **d}
    names = {f.name for f in fields(NetConfig)}
    bad = sorted(set(d) - names)
    if bad:
        raise NeuralLensError(f"training config [{where}]: unknown key(s) {bad}; known: {sorted(names)}")
    for k, allowed in CHOICES.items():
        if k in d and d[k] not in allowed:
            raise NeuralLensError(f"training config [{where}]: {k} = {d[k]!r}; choose one of {list(allowed)}")
    for size in d.get("sizes", ()):
        parse_size(size)
    if "sizes" in d:
        d["sizes"] = tuple(d["sizes"])
    return replace(nc, **d)


def load_config(path: str | None = None, lens: str | None = None, overrides: dict | None = None) -> TrainConfig:
    """Defaults, then the TOML file ``path`` (if any), then ``overrides``."""
    data = {}
    if path:
        try:
            import tomllib
        except ImportError:         # Python 3.10: the same parser as the tomli package
            import tomli as tomllib
        try:
            with open(path, "rb") as f:
                data = tomllib.load(f)
        except FileNotFoundError:
            raise NeuralLensError(f"training config {path}: file not found") from None
        except tomllib.TOMLDecodeError as e:
            raise NeuralLensError(f"training config {path}: {e}") from None
    for k, v in (overrides or {}).items():       # a table is merged key by key: --set regressor.x=1 keeps the
        if isinstance(v, dict) and isinstance(data.get(k), dict):   # recipe's other [regressor] keys
            data[k] = {**data[k], **v}
        else:
            data[k] = v
    cfg = TrainConfig()
    names = {f.name for f in fields(TrainConfig)}
    bad = sorted(set(data) - names)
    if bad:
        raise NeuralLensError(f"training config {path or ''}: unknown key(s) {bad}; known: {sorted(names)}")
    for k, v in data.items():
        if k in ("regressor", "classifier", "stop"):
            setattr(cfg, k, _apply(getattr(cfg, k), v, k))
        elif k.startswith("forward_"):
            setattr(cfg, k, {**getattr(cfg, k), **v})
        else:
            setattr(cfg, k, v)
    if lens:
        cfg.lens = lens
    return cfg


def default_config_path(lens_name: str) -> str | None:
    """The lens's recipe, ``recipes/<lens>.toml`` of the first lens library that has one, or ``None``: the
    defaults (:func:`~mi_neurallens.transport.planes.recipe_path`)."""
    return recipe_path(lens_name)
