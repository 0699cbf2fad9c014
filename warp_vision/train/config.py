"""Training configuration: the foveation and face-recognition runs' dataclasses and presets, the checks
every task's config shares, and the command line generated from a dataclass. The body's nets' configs are in
:mod:`warp_vision.train.config_body` (oculomotor, arm, limb vision), the intraocular nets' in
:mod:`warp_vision.train.config_intraocular` (pupil, lens)."""

from __future__ import annotations

import argparse
import dataclasses
import math
from dataclasses import dataclass, fields
from typing import ClassVar

from warp_vision.data.faces import PRESET_DATA as FACE_DATA
from warp_vision.data.foveation import PRESET_DATA as FOVEATION_DATA
from warp_vision.data.foveation import FoveationDataConfig, generator_flag
from warp_vision.errors import field_help, field_sections, preset_defaults, require_positive, require_seeds

#: The allowed values of the fields that have a fixed set (argparse choices and validation).
CHOICES = {"loss": ["huber", "mse"], "model": ["linet", "fc", "conv", "cnn"], "eye": ["left", "right"],
           "onv_dtype": ["auto", "float16", "bfloat16", "float32"], "precision": ["auto", "float32", "bfloat16"],
           "lr_schedule": ["cosine", "plateau", "constant"], "head": ["auto", "softargmax", "linear"],
           "input_norm": ["auto", "sample", "dataset"], "generator": [7, 8, 9],
           "ball": ["ordinary", "glowing"]}


def check_net_sizes(cfg) -> None:
    """The hidden layers of ``cfg``'s net on its P photoreceptors, by arithmetic alone: a liNet or its fc twin
    (``layers`` of 1/``reduction`` the units, each reading ``receptive_field`` of the 3P inputs or the layer
    below) or the conv net (sites thinned by ``reduction`` per layer). The nets' builders refuse the same
    settings, but only once the dataset is rendered: ``--layers 8`` began by synthesising 6,112 ONVs."""
    from warp_vision.nn.connectivity import layer_sizes
    from warp_vision.nn.retina_conv import site_counts

    if cfg.model in ("linet", "fc"):
        layer_sizes(3 * cfg.photoreceptors, cfg.layers, cfg.receptive_field, cfg.reduction)
    elif cfg.model == "conv":
        if not cfg.reduction > 1:
            raise ValueError("reduction: the conv net's stride between its layers' sites, expected > 1, got "
                             f"{cfg.reduction}")
        site_counts(cfg.photoreceptors, cfg.layers, cfg.reduction)


def _check_common(cfg, presets: dict, positive: tuple = (), test_may_be_empty: bool = False) -> None:
    """The checks every training config shares: every number is finite, its preset, its fields with a
    fixed set of values, the network's and the optimisation's positive integers (and ``positive``), lr,
    device, the validation and test fractions (``test_may_be_empty``: a test fraction of 0 is allowed), and a
    task config's fixed ``task``. An empty ``out`` becomes the task's default, runs/<task>/<eye or side>."""
    for f in fields(cfg):
        v = getattr(cfg, f.name)
        if isinstance(v, float) and not math.isfinite(v):
            raise ValueError(f"{f.name}: expected a finite number, got {v}")
    if cfg.preset not in presets:
        raise ValueError(f"preset: expected one of {sorted(presets)}, got {cfg.preset!r}")
    for name, allowed in getattr(cfg, "CHOICES", CHOICES).items():
        if hasattr(cfg, name) and getattr(cfg, name) not in allowed:
            raise ValueError(f"{name}: expected one of {allowed}, got {getattr(cfg, name)!r}")
    require_positive(cfg,
                     [n for n in positive + ("layers", "receptive_field", "reduction", "batch", "epochs", "patience")
                      if hasattr(cfg, n)], flags=False)
    require_seeds(cfg)
    if not cfg.lr > 0:
        raise ValueError(f"lr: expected > 0, got {cfg.lr}")
    if not 0 < cfg.val_fraction < 1:  # (early stopping and the best checkpoint are chosen on it)
        raise ValueError(f"val_fraction: expected a fraction in (0, 1), got {cfg.val_fraction}")
    if not (0 <= cfg.test_fraction < 1 if test_may_be_empty else 0 < cfg.test_fraction < 1):
        interval = "[0, 1)" if test_may_be_empty else "(0, 1)"
        raise ValueError(f"test_fraction: expected a fraction in {interval}, got {cfg.test_fraction}")
    if not cfg.val_fraction + cfg.test_fraction < 1:
        raise ValueError(f"val_fraction and test_fraction: {cfg.val_fraction} + {cfg.test_fraction} leave no "
                         f"training data; expected a sum < 1")
    task = getattr(type(cfg), "task", None)  # the class's default: fixed per config class
    if task is not None and cfg.task != task:
        raise ValueError(f"task: expected {task!r}, got {cfg.task!r}")
    if task is not None and not cfg.out:
        cfg.out = f"runs/{task}/{getattr(cfg, 'side', None) or cfg.eye}"
    if cfg.device not in ("auto", "cpu", "cuda") and not cfg.device.startswith("cuda:"):
        raise ValueError(f"device: expected cpu, cuda or auto, got {cfg.device!r}")
    if hasattr(cfg, "onv_dtype") and cfg.model == "fc" and cfg.onv_dtype not in ("auto", "float32"):
        raise ValueError(f"onv_dtype: the fc baseline reads float32 ONVs, got {cfg.onv_dtype!r}")
    if hasattr(cfg, "precision") and cfg.precision == "bfloat16" and cfg.model not in ("cnn", "range"):
        raise ValueError(f"precision: bfloat16 training is the cnn and range nets'; the {cfg.model} net trains in "
                         "float32 (use --precision auto or float32)")


def check_splits(n: int, val_fraction: float, test_fraction: float, min_test: int = 0, name: str = "samples",
                 of: str = "") -> tuple[int, int, int]:
    """(train, validation, test) counts of ``n`` samples split by the fractions: at least one to validate and
    ``min_test`` to test. Fewer than 2 left to train is a ValueError beginning with the setting ``name`` (``of``:
    what the count is made of, after it), as one sample's targets have no spread to standardise by. The harness
    splits by these counts (``harness.splits``); each config's validate checks its count before any data is
    rendered."""
    n_test = max(min_test, int(round(n * test_fraction)))
    n_val = max(1, int(round(n * val_fraction)))
    if n - n_val - n_test < 2:
        raise ValueError(f"{name}: {n:,}{of} leave {max(0, n - n_val - n_test)} to train after {n_val} to validate and "
                         f"{n_test} to test: expected at least 2 (more {name}, or a smaller --val-fraction or "
                         f"--test-fraction)")
    return n - n_val - n_test, n_val, n_test


def onv_dtype_name(cfg) -> str:
    """The dtype ``cfg``'s net reads its ONVs in: ``cfg.onv_dtype``, with "auto" meaning float16 (the
    store's) for a liNet and float32 for the fc, conv, cnn and range nets."""
    if cfg.onv_dtype != "auto":
        return cfg.onv_dtype
    return "float32" if cfg.model in ("fc", "conv", "cnn", "range") else "float16"


def epoch_lr(cfg, epoch: int) -> float:
    """The learning rate of epoch ``epoch`` (0-based) of a run with config ``cfg``: a function of the epoch
    alone, so a resumed run continues the schedule exactly. ``cfg.lr_schedule`` (constant when the config
    has none) "cosine" falls from lr to lr/20 over the epochs; "constant" and "plateau" (which the
    training loop lowers) keep lr."""
    schedule = getattr(cfg, "lr_schedule", "constant")
    if schedule in ("constant", "plateau") or cfg.epochs == 1:
        return cfg.lr
    t = min(epoch, cfg.epochs - 1) / (cfg.epochs - 1)
    return cfg.lr * (0.05 + 0.95 * 0.5 * (1.0 + math.cos(math.pi * t)))


@dataclass
class TrainConfig:
    """Everything a foveation training run depends on (written to RUN_DIR/config.json)."""

    preset: str = "default"  # smoke | quick | default | paper: sets the defaults of everything below
    out: str = "runs/foveation"  # output directory (config, checkpoints, metrics, figures)
    data_dir: str = ""  # dataset directory; default: runs/datasets/foveation-<config hash>
    # the dataset
    samples: int = 8000  # ONVs in the dataset (train + validation + test)
    photoreceptors: int = 14_400  # P per retina
    eye: str = "left"  # left or right: each eye has its own retina, hence its own net
    samples_per_receptor: int = 4  # S rays per photoreceptor and channel
    max_field_deg: float = 45.0  # the ball lies within this angle of the optical axis
    data_seed: int = 0  # seed of the dataset (scenes) and of the train/val/test split
    generator: int = 7  # the scene generator: 7 (a glowing ball in one dim room), 8 (ordinary balls in a family of
                        # everyday rooms, distractors, the body's arms) or 9 (v8 plus decoys, round things that are not
                        # the ball, such as a cannon's muzzle; the quick, default and paper presets' choice)
    # the model
    input_norm: str = "auto"  # the photoreceptors' adaptation: log(1 + irradiance / scale) with scale each ONV's own
                              # mean irradiance (sample: a brighter room reads the same) or the training set's
                              # (dataset); auto: sample for generators 8 and 9, dataset for 7
    model: str = "linet"  # linet (the smoke and paper presets'); fc: the fully-connected baseline with the same hidden
                          # sizes; conv: weights shared across the retina (nn/retina_conv.py: stencil layers, reduction
                          # = the sites' stride, a soft-argmax of a saliency channel); cnn: a CNN on the ONV resampled
                          # to a foveated image, trained with turned and mirrored copies (nn/retina_cnn.py; the
                          # ball-finder for generators 8 and 9, the quick and default presets')
    head: str = "auto"  # read-out: softargmax (layers vote for a gaze direction; liNet only), linear (the paper's Fig.
                        # 5), or auto (softargmax for a liNet, linear for fc)
    layers: int = 4  # liNet hidden layers H
    receptive_field: int = 20  # R, connections per unit
    reduction: int = 5  # f, each layer has 1/f of the previous layer's units (conv: of its sites)
    channels: int = 16  # conv and cnn only: channels of the first layer (conv: doubling
                        # per layer up to 64; cnn: x1, 2, 4, 6 over its four stages)
    no_augment: bool = False  # cnn only: train on the plain image alone, without the turned and
                              # mirrored copies (an ablation: the net then memorises its training
                              # set, docs/RESULTS.md "Where the paper's MSE goal stands")
    plain_epochs: int = 0  # cnn only: the last N epochs (of the epoch cap) train on the plain image alone, after the
                           # turned and mirrored copies (an ablation between the copies throughout and no_augment:
                           # docs/RESULTS.md "Copies first, the plain image last"); 0: copies throughout
    views: int = 8  # cnn only: its read-out at inference (the test, evaluate, the simulation; the epochs' validation
                    # reads one view) is the consensus of this many turned and mirrored views (nn/retina_cnn.py:
                    # CONSENSUS_VIEWS); 1: the plain image alone (8x less inference)
    # optimisation
    init: str = ""  # a foveation run directory (or its best.pt) whose best weights start this run (the same model and
                    # sizes, e.g. the other eye's cnn); empty: the seed's initialisation
    loss: str = "huber"  # huber (quadratic within 0.1 std of the target, ~2 deg, linear beyond: robust to the few balls
                         # too small or hidden to localise) or mse (the paper's)
    batch: int = 64
    lr: float = 1e-3  # Adam learning rate (of the first epoch)
    lr_schedule: str = "cosine"  # cosine (the epoch's rate falls from lr to lr/20 over the epochs), plateau (x0.3 after
                                 # every 3 epochs without a better validation loss) or constant
    onv_dtype: str = "auto"  # the dtype the net reads ONVs in: float16 (as stored; standardised in the first layer),
                             # bfloat16, float32 (a standardised float32 copy of each batch), or auto (float16 for a
                             # liNet, float32 for the fc, conv, cnn and range nets)
    precision: str = "auto"  # cnn only: the CNN's layers in training run in bfloat16 (autocast; the
                             # image, loss and read-out stay float32) or float32; auto: bfloat16
                             # where the device computes it natively (a CPU with AVX512-BF16 or AMX,
                             # a GPU of compute capability 8 on), else float32. Evaluation is float32
    epochs: int = 40  # at most
    patience: int = 8  # early stopping: epochs without a better validation loss
    val_fraction: float = 0.1
    test_fraction: float = 0.1
    seed: int = 0  # initialisation and shuffling
    # the run
    device: str = "auto"  # cpu, cuda, or auto (cuda when Warp and torch see one)

    #: Fields added after runs were saved without them: a saved config that lacks one had this value (ONVs read
    #: in float32; channels, views, no_augment and plain_epochs are read by models that came with them or after).
    #: Any other setting missing from a saved config is refused (rundir.config_from_saved).
    LEGACY_DEFAULTS = {"generator": 7, "input_norm": "dataset", "precision": "float32", "onv_dtype": "float32",
                       "channels": 16, "init": "", "views": 8, "no_augment": False, "plain_epochs": 0}
    #: the net settings only some models read: {field: those models} (a flag given for another is refused)
    MODEL_FIELDS: ClassVar[dict] = {"layers": ("linet", "fc", "conv"), "receptive_field": ("linet", "fc"),
                                    "reduction": ("linet", "fc", "conv"), "channels": ("conv", "cnn"),
                                    "views": ("cnn",)}

    def per_sample_input(self) -> bool:
        """Whether the net's input is scaled by each ONV's own mean irradiance (``input_norm``, "auto" resolved)."""
        return self.input_norm == "sample" or (self.input_norm == "auto" and self.generator >= 8)

    def head_kind(self) -> str:
        """The read-out this config builds ("auto" resolved)."""
        if self.head == "auto":
            return "linear" if self.model == "fc" else "softargmax"
        return self.head

    def epoch_lr(self, epoch: int) -> float:
        """Adam's learning rate in epoch ``epoch`` (0-based): :func:`epoch_lr`."""
        return epoch_lr(self, epoch)

    def data_config(self) -> FoveationDataConfig:
        return FoveationDataConfig(
            samples=self.samples,
            photoreceptors=self.photoreceptors,
            eye=self.eye,
            samples_per_receptor=self.samples_per_receptor,
            max_field_deg=self.max_field_deg,
            seed=self.data_seed,
            generator=self.generator,
        )

    def validate(self) -> None:
        _check_common(self, PRESETS, ("samples", "photoreceptors", "samples_per_receptor"), test_may_be_empty=True)
        check_splits(self.samples, self.val_fraction, self.test_fraction)
        if self.model == "fc" and self.head == "softargmax":
            raise ValueError("head: the fc baseline has no unit positions to vote with; use --head linear")
        if self.model in ("conv", "cnn") and self.head == "linear":
            raise ValueError(f"head: the {self.model} net reads out by a soft-argmax of its heat map; use --head auto "
                             "or softargmax")
        if self.model in ("conv", "cnn") and self.onv_dtype not in ("auto", "float32"):
            raise ValueError(f"onv_dtype: the {self.model} net reads float32 ONVs, got {self.onv_dtype!r}")
        if self.channels < 1:
            raise ValueError(f"channels: expected a positive integer, got {self.channels}")
        if self.no_augment and self.model != "cnn":
            raise ValueError(f"no_augment: the turned and mirrored copies are the cnn's; the {self.model} net trains "
                             "without them")
        if self.no_augment and self.views != 1:
            raise ValueError("views: a net trained without the turned and mirrored copies reads the plain image "
                             f"alone; use --views 1 with --no-augment (got {self.views})")
        if self.plain_epochs and self.model != "cnn":
            raise ValueError(f"plain_epochs: the turned and mirrored copies are the cnn's; the {self.model} net trains "
                             "without them")
        if not 0 <= self.plain_epochs <= self.epochs:
            raise ValueError(f"plain_epochs: expected 0 to the {self.epochs} epochs, got {self.plain_epochs}")
        if self.plain_epochs == self.epochs and not self.no_augment:
            raise ValueError("plain_epochs: every epoch on the plain image is --no-augment (with --views 1)")
        from warp_vision.nn.retina_cnn import consensus_transforms

        consensus_transforms(self.views)  # (validates: 1 to 48, the turns plain and mirrored)
        check_net_sizes(self)
        self.data_config().validate()


#: ONVs per held-out condition of ``evaluate --conditions`` (:func:`warp_vision.train.conditions.evaluate_conditions`).
CONDITION_SAMPLES = 400

#: Each preset: its dataset (``data.foveation.PRESET_DATA``, which ``python -m warp_vision.data foveation
#: --preset`` builds too) and the net and training settings over it.
PRESETS: dict[str, dict] = {
    # end to end in well under a minute (tests)
    "smoke": dict(**FOVEATION_DATA["smoke"], layers=3, receptive_field=8, batch=16, epochs=3, patience=3),
    # a first look (``python -m warp_vision.sim demo --quick`` trains these): about 2 minutes on a 2-core CPU,
    # synthesis included
    "quick": dict(**FOVEATION_DATA["quick"], epochs=12, patience=12, model="cnn", lr=2e-3),
    # the default run: the retina CNN on generator v9, about 12-14 minutes on a 2-core CPU that trains it in
    # bfloat16, about 15 in float32 (12,000 ONVs of P=14,400, S=4 rendered by two processes, then 20 epochs,
    # which miss fewer balls than 12: docs/RESULTS.md "20 epochs" and "bfloat16 training"). v7's liNet:
    # --generator 7 --model linet --lr 0.001 --epochs 40 --samples 8000
    "default": dict(**FOVEATION_DATA["default"], model="cnn", lr=2e-3, epochs=20),
    # the paper's set-up on v9: 20K training ONVs of P=14,400, liNet H=4, R=20, f=5, batch 64
    "paper": dict(**FOVEATION_DATA["paper"], epochs=60, patience=10),
}


@dataclass
class FaceTrainConfig:
    """Everything an active-face-recognition run depends on (written to RUN_DIR/config.json)."""

    #: the allowed values where they are fewer than the foveation config's (argparse choices; validate checks them)
    CHOICES: ClassVar[dict] = {**CHOICES, "model": ["linet", "fc"]}

    preset: str = "default"  # smoke | default | paper: sets the defaults of everything below
    task: str = "faces"  # fixed: tells evaluate which kind of run a directory holds
    out: str = "runs/faces"  # output directory (config, checkpoints, metrics, figures)
    data_dir: str = ""  # dataset directory; default: runs/datasets/faces-<config hash>
    identities_cache: str = ""  # the identity meshes' cache file; default: runs/faces/identities-<n>-<seed>-...npz
    # the dataset
    identities: int = 50  # distinct people (classes)
    pose_step_deg: float = 4.0  # yaw and pitch step (the paper: 2)
    max_pose_deg: float = 30.0  # poses span -max to +max degrees in yaw and pitch
    photoreceptors: int = 14_400  # P per retina
    eye: str = "left"  # which eye's retina
    samples_per_receptor: int = 4  # S rays per photoreceptor and channel
    distance_m: float = 0.5  # eye to the face's centre
    identity_seed: int = 0  # seed of the identities' shapes and colours
    data_seed: int = 0  # seed of the train/val/test split (and of the rays)
    # the model
    model: str = "linet"  # linet, or fc: the fully-connected twin with the same hidden sizes
    layers: int = 5  # liNet hidden layers H
    receptive_field: int = 20  # R, connections per unit
    reduction: int = 2  # f, each layer has 1/f of the previous layer's units
    # optimisation
    loss_lambda: float = 6.0  # loss = cross-entropy + loss_lambda * MSE(standardised pose)
    onv_dtype: str = "auto"  # the dtype the net reads ONVs in: float16 (as stored), bfloat16,
                             # float32, or auto (float16 for a liNet, float32 for fc)
    batch: int = 64
    lr: float = 1e-3  # Adam learning rate (betas 0.9, 0.999)
    epochs: int = 60  # at most
    patience: int = 30  # early stopping: epochs in which neither validation metric reaches a new best
    val_fraction: float = 0.1
    test_fraction: float = 0.2
    shuffle_labels: bool = False  # sanity check: train on identities and poses shuffled across the training ONVs
    seed: int = 0  # initialisation and shuffling
    # the run
    device: str = "auto"  # cpu, cuda, or auto (cuda when Warp and torch see one)

    #: Fields added after runs were saved without them: a saved config that lacks one had this value.
    LEGACY_DEFAULTS = {"onv_dtype": "float32"}

    def data_config(self):
        from warp_vision.data.faces import FaceDataConfig

        return FaceDataConfig(identities=self.identities, pose_step_deg=self.pose_step_deg,
                              max_pose_deg=self.max_pose_deg, photoreceptors=self.photoreceptors, eye=self.eye,
                              samples_per_receptor=self.samples_per_receptor, distance_m=self.distance_m,
                              identity_seed=self.identity_seed, seed=self.data_seed)

    def validate(self) -> None:
        _check_common(self, FACE_PRESETS)
        if self.identities < 2:
            raise ValueError(f"identities: expected at least 2 (a classifier needs classes), got {self.identities}")
        if not self.loss_lambda >= 0:
            raise ValueError(f"loss_lambda: expected >= 0, got {self.loss_lambda}")
        check_net_sizes(self)
        data = self.data_config()
        data.validate()
        check_splits(data.samples, self.val_fraction, self.test_fraction, min_test=1, name="identities",
                     of=f" samples ({self.identities} identities x {data.poses} poses)")


#: Each face preset: its dataset (``data.faces.PRESET_DATA``, which ``python -m warp_vision.data faces --preset``
#: builds too) and the net and training settings over it.
FACE_PRESETS: dict[str, dict] = {
    # seconds, for tests: 3 identities x 4 x 4 poses on a small retina
    "smoke": dict(**FACE_DATA["smoke"], layers=3, receptive_field=8, batch=8, epochs=3, patience=3),
    # 50 identities x 15 x 15 poses (4-degree steps): 11,250 ONVs
    "default": dict(**FACE_DATA["default"]),
    # the paper's protocol: 50 identities x 30 x 30 poses (2-degree steps): 45,000 ONVs
    "paper": dict(**FACE_DATA["paper"], epochs=200),
}


def resolve(preset: str, overrides: dict, cls=None, presets: dict | None = None):
    """The preset's config (of ``cls``, TrainConfig by default) with ``overrides`` (only keys whose value
    is not None) applied."""
    cls = cls or TrainConfig
    presets = PRESETS if presets is None else presets
    if preset not in presets:
        raise ValueError(f"preset: expected one of {sorted(presets)}, got {preset!r}")
    cfg = cls(preset=preset, **presets[preset])
    for k, v in overrides.items():
        if v is not None and k != "preset":
            setattr(cfg, k, v)
    cfg.validate()
    return cfg


def add_arguments(p: argparse.ArgumentParser, cls=None, presets: dict | None = None) -> dict:
    """One ``--flag`` per field of ``cls`` (TrainConfig by default; default None: the preset decides), in
    groups by the config's sections (:func:`warp_vision.errors.field_sections`: "the run", "the dataset", "the
    model", "optimisation"). Returns {section title: its argument group}."""
    cls = cls or TrainConfig
    presets = PRESETS if presets is None else presets
    defaults = cls()
    sections, groups = field_sections(cls), {}

    def group(name: str):
        title, _, about = sections.get(name, "the run").partition(": ")
        if title not in groups:
            groups[title] = p.add_argument_group(title, about or None)
        return groups[title]

    for f in fields(cls):
        if f.name == "task":  # fixed per config class, not a choice
            continue
        if f.name == "preset":
            group(f.name).add_argument("--preset", choices=sorted(presets), default="default",
                                       help=field_help(cls, f.name))
            continue
        value = getattr(defaults, f.name)
        choices = getattr(cls, "CHOICES", CHOICES)
        extra = {"choices": choices[f.name]} if f.name in choices else {}
        if isinstance(value, bool):
            group(f.name).add_argument(f"--{f.name.replace('_', '-')}", action="store_const", const=True,
                                       default=None, help=f"{field_help(cls, f.name)} (default: off)")
            continue
        group(f.name).add_argument(
            f"--{f.name.replace('_', '-')}",
            type=generator_flag if f.name == "generator" else type(value),
            default=None,
            help=f"{field_help(cls, f.name)} ({preset_defaults(presets, f.name, value)})",
            **extra,
        )
    return groups


def from_args(args: argparse.Namespace, cls=None, presets: dict | None = None):
    """The config of a command line: its preset with the flags given over it. A flag of a net setting the
    chosen model does not read (``cls.MODEL_FIELDS``: ``--model cnn --receptive-field 30``) is a ValueError
    rather than a setting left unread."""
    cls = cls or TrainConfig
    cfg = resolve(args.preset, {f.name: getattr(args, f.name, None) for f in fields(cls)}, cls, presets)
    for name, models in getattr(cls, "MODEL_FIELDS", {}).items():
        if getattr(args, name, None) is not None and cfg.model not in models:
            which = (
                f"the {models[0]} net does"
                if len(models) == 1
                else f"the {', '.join(models[:-1])} and {models[-1]} nets do"
            )
            raise ValueError(f"--{name.replace('_', '-')}: the {cfg.model} net does not read it ({which}); leave it "
                             f"out, or choose {'that' if len(models) == 1 else 'one of those'} with --model")
    return cfg


def asdict(cfg) -> dict:
    return dataclasses.asdict(cfg)


