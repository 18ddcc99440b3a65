"""Training configuration: dataclasses with defaults, read from TOML (``tomllib``).

A per-lens file ``training/<lens>.toml`` overrides any field; unknown keys are an error (typos must
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
    loss_weights: str = "goals"         # regressor, stop head: per-output MSE weights ∝ (output std / accuracy goal),
                                        # floored; or "uniform"
    odd_y: bool = True                  # regressor: y, dy = (ωy / s_max) × network: exactly odd in ωy, no mirror-plane seam
    input_box: bool = False             # regressor, stop head: train on inputs normalised over the valid rays' bounding
                                        # box, folded back into the first layer and skip (same file, same kernel;
                                        # training/input_box.py; on for the forward maps: FORWARD_REGRESSOR, FORWARD_STOP)
    exit_position: str = "auto"         # regressor: "plane" (the exit position on the output plane, the paper's), "cos"
                                        # (times |dz|: bounded for rays nearly parallel to the plane) or "auto" (cos
                                        # where the exit rays reach beyond 60° off axis: a fisheye's camera map;
                                        # outputs.wants_position_cos)
    target: str = "margin"              # classifier: "margin" (regress scale·(aperture margin) inside ±clip, one-sided
                                        # beyond: a sharper boundary) or "label" (BCE on blocked/passed, the paper's)
    margin_scale: float = 40.0          # classifier "margin" target: logit slope per unit margin at the boundary
    margin_clip: float = 3.0            # classifier "margin" target: |logit| it saturates at
    boundary_sigma: tuple = (1e-3, 5e-2)  # classifier: log-uniform width range of the boundary perturbations (unit cube)
    edge_weight: float = 0.0            # regressor: extra loss weight of rays near an aperture edge, where a ghost's
    edge_margin: float = 0.02           # sharp edge lands: w = 1 + edge_weight·exp(−margin / edge_margin) (0: off)
    stop_at_goals: bool = True          # a network stops as soon as a validation meets its goals (below)
    goal_position_um: tuple = (2.0, 20.0)       # regressor: exit-position error (median, p99), µm
    goal_direction_arcsec: tuple = (5.0, 40.0)  # regressor: exit-direction error (median, p99), arcsec
    goal_misclassification: float = 0.005       # classifier: held-out misclassification (natural mix)
    goal_stop_um: tuple = (2.0, 20.0)           # stop head: stop-plane crossing error (median, p99), µm
    goal_margin: float = 0.9            # stop when the validation is within goal × this (the held-out set differs)
    pool: int = 2_000_000               # samples held in memory per map; refreshed from the tracer
    refresh_every: int = 2000           # steps between pool refreshes (fresh tracer data)
    refresh_fraction: float = 0.25
    lm_minutes: float = 0.0             # Levenberg–Marquardt after Adam, per network of at most levenberg.MAX_PARAMS
                                        # weights, until its goals (0: Adam alone; training/levenberg.py)
    lm_iterations: int = 0              # at most this many Levenberg–Marquardt iterations (0: only lm_minutes
                                        # limits them; a count is what makes a run the same on every machine)
    lm_rows: int = 8192                 # fresh samples per Levenberg–Marquardt iteration
    lm_eval_every: int = 10             # Levenberg–Marquardt iterations between validations
    sizes: tuple = ()                   # regressor / classifier: architectures to try, smallest first, as "HxW"
                                        # (hidden layers × width); each map keeps the first that meets its goals,
                                        # the last when none does (empty: hidden × width alone; maps.train_sized)


#: Adam steps before a regressor's finish.  Adam only has to bring a network near the optimum the finish then
#: reaches in tens of iterations: on dgauss-50mm, this CPU, 4 000 steps reach the goals in 62 s (camera regressor)
#: and ≈ 135 s (a stack of four ghost regressors) where 12 000 took 109 and ≈ 270 s, at the same accuracy
#: (benchmarks/results/adam_steps/).  On a GPU, where the wall budgets would allow 3–4× the steps at launch-bound
#: speed, the cap is what keeps Adam from outlasting the finish (docs/results.md, "The third GPU session")
REGRESSOR_ADAM_STEPS = 4000


def regressor_defaults() -> NetConfig:
    """A 3×16 network: 1.5 min (at most :data:`REGRESSOR_ADAM_STEPS` steps) of Adam, then up to 4 min of the
    Levenberg–Marquardt finish, which takes it to the camera goals (the 27-surface RF 24 mm: 0.88 µm / 4.0″
    median in 2.8 min; a 5×32 network with Adam alone reached 1.75 µm / 7.2″ in 5.7 min and renders 3×
    slower — docs/results.md)."""
    return NetConfig(hidden=3, width=16, max_steps=REGRESSOR_ADAM_STEPS, max_minutes=1.5, lm_minutes=4.0)


def classifier_defaults() -> NetConfig:
    return NetConfig(hidden=2, width=16, lr=3e-3, max_steps=40000, max_minutes=1.0, lm_minutes=1.0,
                     residual="none", direction_loss="none", pool=1_500_000)


def stop_defaults() -> NetConfig:
    """The stop head (where rays cross the stop plane): smooth and nearly linear, so a small network, the
    regressor's 3×16 with :data:`REGRESSOR_ADAM_STEPS` of Adam and up to 1.5 min of the finish (it stops at the
    goal).  The camera heads were 2×32 until the finish showed what a 3×16 one reaches: 2 min of it took the paper
    lenses' camera heads to 0.012–0.11 µm median (the 2×32 ones: 0.73–1.40), with half the multiply-adds, so
    ``neural_lens`` below the widest f-number went from 20.5 to 25.5 M rays/s (docs/results.md, "What the iris
    costs").  Its loss weighs each crossing column by its spread (``loss_weights = "goals"``,
    :func:`~mi_neurallens.training.stop_head.stop_loss_weights`)."""
    return NetConfig(hidden=3, width=16, lr=3e-3, max_steps=REGRESSOR_ADAM_STEPS, max_minutes=0.5, lm_minutes=1.5,
                     patience=12, residual="linear", loss_weights="goals", direction_loss="none", odd_y=True,
                     pool=1_000_000)


#: the forward maps' Levenberg–Marquardt finish, at most this many iterations per network (besides its minutes).
#: On a CPU the networks finish one at a time and the minutes end it; on a GPU a lens's 28 forward networks of a
#: kind finish as one stack whose wall budget is 28 × the minutes, and the 28 classifiers, which rarely reach their
#: 0.05 % goal, ran 870 iterations in the 76 s before the call's deadline (docs/results.md, "The fourth GPU session").
#: The caps sit just above what the minutes give on the 2-core AVX-512 VM (Canon FD 24 mm's whole lens: a regressor
#: iteration 0.22 s, 1 min ≈ 270; a classifier's 0.024–0.030 s, 0.35 min ≈ 700–875; a stop head's 0.10–0.27 s,
#: 0.5 min ≈ 110–300), so they do not cut a CPU's finish but keep a GPU stack to about the iterations a CPU gives
#: each network.  (120 / 600 / 60, the numbers of an older, slower VM, cut 12 of that lens's regressors to half
#: their minute and left them above the flare goal.)
FORWARD_LM_ITERATIONS = {"regressor": 300, "classifier": 900, "stop": 300}
#: forward maps (ghosts, forward transmit) serve flares, so their goals are stated in film pixels at
#: ``TrainConfig.flare_resolution`` (:func:`flare_goals`: 3 / 30 µm at 2 K full frame) and are looser than a
#: camera ray's; the ghosts' edges are the flare error, so their classifier regresses the aperture margin
#: (docs/training.md).  The networks are the defaults' 3×16 / 2×16 with shorter Adam and finish budgets: the
#: Canon EF's ghosts reached 2.3–39 µm (median map 5.6) with ≤ 1 min of the finish (docs/results.md)
#: With ``input_box`` (trained on the valid rays' bounding box, folded back; training/input_box.py): back to back
#: with it off, dgauss-50mm's 28 ghost regressors all met their goals both ways, in 6.1 min against 6.8 (27 of 28
#: sooner, 17 of 28 lower at the median); the Canon EF's 278528, trained anew as 3×32 on its box, 4.68 µm where its
#: shipped map had 11.0 after three sessions of the finish (docs/results.md, "278528 on its box")
FORWARD_REGRESSOR = dict(max_minutes=1.0, max_steps=REGRESSOR_ADAM_STEPS, lm_minutes=1.0,
                         lm_iterations=FORWARD_LM_ITERATIONS["regressor"], input_box=True)
#: the forward regressor's goals at 2048 pixels across full frame (a 17.6 µm pixel): position (median, p99)
#: µm, 0.17 / 1.7 pixels; direction (median, p99) arcsec.  Both scale with the pixel (:func:`flare_goals`)
FLARE_GOAL_UM_2K = (3.0, 30.0)
FLARE_GOAL_ARCSEC_2K = (30.0, 200.0)
#: the forward classifier's Adam steps before its finish.  On this CPU the 0.4-min wall budget (a stack of four:
#: 1.6 min) ended Adam after 12 100–17 700 steps in the 42-min whole-lens run, where the validation had flattened
#: (ghost 2560: 0.24 % misclassified at 10 000 steps, 0.22 % at 15 376; the finish then took it to 0.05 %).  A GPU
#: trains a lens's 28 classifiers as one stack whose budget is 28 × 0.4 min, so without a step cap Adam ran to
#: 40 000 steps there — the step count, not the wall clock, is what makes a run the same on every machine.  On the
#: AVX-512 VM the cap ends Adam first (Canon FD 24 mm: stacks of four at 12 000 steps after 55–58 s of their 96 s),
#: which saved ≈ 6 of that lens's minutes; after the finish 31 of its 33 classifiers were within 0.05 %
FORWARD_CLASSIFIER_ADAM_STEPS = 12000
#: the forward classifier: 0.4 min of Adam before its 0.35-min finish.  With 1.25 min of Adam, dgauss-50mm's whole
#: lens spent half its 94 min on classifiers, each stack its whole budget; on eight of its ghosts 0.4 min of Adam
#: and the same finish gave flare errors within ±0.002 of the 1.25-min maps in 5.0 instead of ≈ 8 min a stack of
#: four (docs/results.md, "A whole new lens with the defaults on this CPU"); the whole lens then took 77.5 min, its
#: classifiers 27 instead of 46, its ghosts' verified flare errors no worse (median 0.0108 against 0.0127, 2^24
#: samples).  The finish was 0.75 min until its rows came from the tracer in chunks (levenberg.ROW_CHUNK): an
#: iteration then cost 0.042 s instead of 0.155, and 0.35 min left ghosts 1152, 16896, 4224 at 0.058–0.084 %
#: misclassified where 0.75 min had left them at 0.097–0.138 % (96: 0.045 % both).  The paper lenses' recipes keep
#: their own.  Adam also stops at :data:`FORWARD_CLASSIFIER_ADAM_STEPS`
FORWARD_CLASSIFIER = dict(target="margin", goal_misclassification=0.0005, max_minutes=0.4, lm_minutes=0.35,
                          max_steps=FORWARD_CLASSIFIER_ADAM_STEPS, patience=30,
                          lm_iterations=FORWARD_LM_ITERATIONS["classifier"])
#: a forward map's stop head (used only through an iris) gets at most this much of the finish unless
#: ``[forward_stop]`` says otherwise: 32 ghosts × the camera head's 1.5 min would add up to half an hour to a lens
FORWARD_STOP_LM_MINUTES = 0.5
#: a forward map's stop head: the regressor's recipe, a 3×16 network with :data:`REGRESSOR_ADAM_STEPS` of Adam and
#: the finish (the camera head is one too now; both were 2×32 with Adam to its budget).  A ghost crossing the stop
#: plane two or three times is as hard to place there as on the film: on dgauss-50mm's ghosts 96, 1152, 16896 and
#: 4224 the 3×16 heads reached 1.5–1.8 µm median, 7.1–8.9 µm p99 in 2.9 min for the four, the 2×32 ones
#: 2.7–5.2 / 12.5–24 µm in 4.7 (docs/results.md, "Stop heads as small as the regressor")
#: With ``input_box`` (the head trained on its valid rays' bounding box, folded back; training/input_box.py): back to back
#: with it off, dgauss-50mm's 28 heads met their goals in 3.8 min against 4.6, and the Canon EF's seven three-crossing
#: heads (its hardest) came out lower at the median, all seven, by 5–46 % (docs/results.md, "The last one, 278528").
FORWARD_STOP = dict(hidden=3, width=16, max_steps=REGRESSOR_ADAM_STEPS, lm_iterations=FORWARD_LM_ITERATIONS["stop"],
                    input_box=True)

PAPER = dict(schedule="paper", lr=1e-4, decay=0.95, decay_every=10000, batch=8192, warmup_steps=0,
             residual="none", direction_loss="cosine", loss_weights="uniform", odd_y=False, target="label")


@dataclass
class TrainConfig:
    lens: str = ""
    seed: int = 1
    backward: list = field(default_factory=lambda: ["transmit"])
    forward: list = field(default_factory=lambda: ["transmit", "ghosts"])
    max_ghosts: int = 32                # keep the top-K ghosts carrying energy_fraction of ghost energy…
    ghost_energy_fraction: float = 0.99
    ship_ghosts: int = 32               # …but train at most this many (CPU budget)
    close_focus_mm: float | str = DEFAULT_CLOSE_FOCUS_MM  # nearest object distance (mm from the first vertex) the maps support; 0:
                                        # infinity only; "auto": 300 mm, farther for a long lens (1:4 magnification at
                                        # most: plan.close_focus_mm)
    film_half_diagonal_mm: float = FULL_FRAME_HALF_DIAGONAL_MM
    flare_resolution: int = 2048        # pixels across the film's width the forward (flare) maps' goals are stated
                                        # for (flare_goals); fewer pixels: looser goals, smaller networks (sizes)
    field_margin: float = DEFAULT_FIELD_MARGIN
    film_reach: float = 1.5             # forward maps learn the rays landing within this × film_half_diagonal_mm of
                                        # the axis (at the nearest or farthest sensor plane); the rest count as
                                        # blocked (0: every ray that passes the lens; transport.planning.Reach)
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
    # after training: each ghost map trained verified against the tracer (flare.verify.record_flare_errors) and the
    # record kept in the model file, where the flare's mode auto reads it to choose, ghost by ghost, its learned map
    # (at the narrowest boundary band that passes) or the tracer.  Not part of what a map is trained with (digest)
    verify_flare: bool = True
    verify_flare_bands: list = field(default_factory=lambda: list(VERIFY_BANDS))  # band 0 (the learned edges)
                                        # for every ghost, each further band only for the ghosts the bands before
                                        # leave above the gate (auto_max_flare_error, 0.01); band 2 catches a fold's
                                        # edge (flare.verify.BANDS)
    verify_flare_samples: int = 24      # log2 samples of each render pair, per light position
    verify_flare_max_samples: int = 26  # at every band but the first a ghost above the gate is rendered again with
                                        # 4× the samples up to this (the protocol of `evaluate --flare`); the first
                                        # is not refined: a ghost it leaves above the gate goes to the next
    verify_flare_cost: bool = True      # then each ghost map auto may learn is timed against tracing the ghost
                                        # (flare.verify.record_flare_costs, this machine's backend): auto learns a
                                        # ghost only where that is faster (auto_max_cost)
    verify_flare_cost_samples: int = 22  # log2 samples of each timed render
    verify_flare_refine_minutes: float = 1.5  # a ghost the verification leaves above the gate at every band: its
                                        # regressor refined past its goals (the finish, this many minutes, from
                                        # the map as trained), verified again, and the better map kept (0: off;
                                        # whole_lens._finish_missed, docs/training.md)

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
        base, over = getattr(self, kind), getattr(self, f"forward_{kind}")
        if direction != "forward":
            return base
        if kind == "regressor":
            over = {**flare_goals(self.flare_resolution, self.film_half_diagonal_mm), **over}
        if kind == "stop" and "lm_minutes" not in over:
            over = {**over, "lm_minutes": min(base.lm_minutes, FORWARD_STOP_LM_MINUTES)}
        return _apply(base, over, f"forward_{kind}") if over else base


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
    network kind (:data:`NETWORK_KINDS`): Adam's ``max_minutes`` once per size it may try, plus the finish's
    ``lm_minutes`` (a stop head for every map).  An upper bound — each network leaves at its goals, Adam also
    at ``max_steps`` — without the data set-up and the held-out evaluation."""
    out = {}
    for kind in NETWORK_KINDS:
        nc = cfg.net(kind, direction)
        tries = max(len(nc.sizes), 1) if kind != "stop" else 1
        out[kind] = 0.0 if kind == "stop" and nc.max_minutes <= 0 else n_maps * (tries * nc.max_minutes + nc.lm_minutes)
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
        import tomllib
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
    """``training/<lens>.toml`` of the repository, when it exists
    (:func:`~mi_neurallens.transport.planes.recipe_path`)."""
    return recipe_path(lens_name)
