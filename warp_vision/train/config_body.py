"""The training configurations of the body's nets: the oculomotor nets (an eye's muscles), the arm motor
nets and the limb vision nets (ONV -> the hand-to-ball discrepancy or the ball's distance). Each is a
dataclass with its presets; the command line and the checks they share are :mod:`warp_vision.train.config`'s."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from warp_vision.train.config import CHOICES, _check_common, check_net_sizes, check_splits, epoch_lr


@dataclass
class OculomotorTrainConfig:
    """Everything an oculomotor-net run depends on (one eye; written to RUN_DIR/config.json)."""

    preset: str = "default"  # smoke | quick | default: sets the defaults of everything below
    task: str = "oculomotor"  # fixed: tells evaluate which kind of run a directory holds
    out: str = ""  # output directory; default: runs/oculomotor/<eye>
    data_dir: str = ""  # holding-activation dataset directory; default: runs/datasets/oculomotor-<config hash>
    eye: str = "left"  # which eye's muscles
    # the dataset: gazes and the activations that hold them, solved on the body
    gazes: int = 5000  # gazes whose holding activations are solved
    max_gaze_deg: float = 35.0  # the disc they are drawn from
    transitions: int = 120_000  # (current, next) gaze pairs drawn among the training gazes per run
    # the model
    hidden: int = 256  # units per hidden layer of the MLP
    # optimisation
    batch: int = 256
    lr: float = 3e-3  # Adam learning rate (of the first epoch)
    lr_schedule: str = "cosine"  # cosine (from lr to lr/20 over the epochs), plateau or constant
    epochs: int = 60  # at most
    patience: int = 60  # early stopping: epochs without a better validation activation RMSE
    val_fraction: float = 0.1  # of the gazes: transitions among them choose the best epoch
    test_fraction: float = 0.15  # of the gazes: transitions among them, and the body check, measure the net
    seed: int = 0  # gaze sampling, initialisation and shuffling
    body_checks: int = 100  # held-out saccades settled on the body to measure
                            # the net (and a quarter as many pursuit chains)
    # the run
    device: str = "cpu"  # cpu, cuda, or auto (a small MLP: the CPU is as fast)

    def data_config(self):
        from warp_vision.sim.oculomotor import HoldingDataConfig

        return HoldingDataConfig(eye=self.eye, gazes=self.gazes, max_gaze_deg=self.max_gaze_deg, seed=self.seed)

    def validate(self) -> None:
        _check_common(self, OCULOMOTOR_PRESETS, ("gazes", "transitions", "hidden", "body_checks"))
        self.data_config().validate()
        check_splits(self.gazes, self.val_fraction, self.test_fraction, min_test=2, name="gazes")


OCULOMOTOR_PRESETS: dict[str, dict] = {
    # seconds, for tests
    "smoke": dict(gazes=80, transitions=2000, hidden=32, epochs=2, patience=2, body_checks=8),
    # a first look (``python -m warp_vision.sim demo --quick``): both eyes in about 2 minutes on a 2-core CPU
    "quick": dict(gazes=1500, transitions=40_000, epochs=25, patience=25, body_checks=30),
    # both eyes in about 6 minutes on a 2-core CPU
    "default": {},
}


@dataclass
class ArmTrainConfig:
    """Everything an arm motor-net run depends on (one arm: its posture and voluntary nets; written to
    RUN_DIR/config.json)."""

    preset: str = "default"  # smoke | quick | default: sets the defaults of everything below
    task: str = "arm"  # fixed: tells evaluate which kind of run a directory holds
    out: str = ""  # output directory; default: runs/arm/<side>
    data_dir: str = ""  # holding-activation dataset directory; default: runs/datasets/arm-<config hash>
    side: str = "left"  # which arm: left or right
    # the dataset: postures with the hand 0.2-0.6 m in front of the shoulder and the activations that hold them
    postures: int = 4000  # postures whose holding activations are solved on the body
    max_residual: float = 0.05  # N m: postures whose holding residual exceeds
                                # this are dropped (the muscles cannot hold them)
    transitions: int = 100_000  # (current, next) posture pairs drawn among the training postures per run
    torque_weight: float = 1.0  # 1/(N m): weight of the torque the nets' activations
                                # fall short by (a soft norm) in the loss
    stiffness: float = 300.0  # N m/rad: the spring toward the goal posture the voluntary net learns
    saturation: float = 0.5  # rad: where that spring saturates (its torque at most stiffness x saturation)
    damping: float = 25.0  # N m s/rad: the damping the voluntary net learns (with the spring)
    posture_damping: float = 8.0  # N m s/rad: the damping the posture net learns (more asks the muscles for more than
                                  # they give when holding, and it drifts)
    velocity_std: float = 1.0  # rad/s: the joint velocities drawn for half the samples
    # the model
    hidden: int = 256  # units per hidden layer of both MLPs
    # optimisation
    batch: int = 256
    lr: float = 2e-3  # Adam learning rate (of the first epoch)
    lr_schedule: str = "cosine"  # cosine (from lr to lr/20 over the epochs), plateau or constant
    epochs: int = 40  # at most
    patience: int = 40  # early stopping: epochs without a better validation loss
    val_fraction: float = 0.1  # of the postures: transitions among them choose the best epoch
    test_fraction: float = 0.15  # of the postures: transitions among them, and the body checks, measure the nets
    seed: int = 0  # posture sampling, initialisation and shuffling
    body_checks: int = 60  # held-out reaches (and posture holds) simulated on the body to measure the nets
    skip_teacher_feedback: bool = False  # do not measure the exact static optimisation in
                                         # closed loop (the nets' teacher; the slowest check)
    # the run
    device: str = "cpu"  # cpu, cuda, or auto (small MLPs: the CPU is as fast)

    def data_config(self):
        from warp_vision.sim.arm import ArmDataConfig

        return ArmDataConfig(side=self.side, postures=self.postures, seed=self.seed)

    def validate(self) -> None:
        _check_common(self, ARM_PRESETS, ("postures", "transitions", "hidden", "body_checks"))
        if self.side not in ("left", "right"):
            raise ValueError(f"side: expected one of ['left', 'right'], got {self.side!r}")
        if not self.max_residual > 0:
            raise ValueError(f"max_residual: expected > 0 N m, got {self.max_residual}")
        if not self.saturation > 0:
            raise ValueError(f"saturation: expected > 0 rad, got {self.saturation}")
        for name in ("torque_weight", "stiffness", "damping", "posture_damping", "velocity_std"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name}: expected >= 0, got {getattr(self, name)}")
        self.data_config().validate()
        # the postures held are split: at most these
        check_splits(self.postures, self.val_fraction, self.test_fraction, min_test=2, name="postures")


ARM_PRESETS: dict[str, dict] = {
    # seconds, for tests
    "smoke": dict(postures=40, transitions=500, hidden=16, epochs=1, patience=1, body_checks=2),
    # a first look: one arm in about 1.5 minutes on a 2-core CPU
    "quick": dict(postures=1500, transitions=30_000, epochs=15, patience=15, body_checks=30),
    # one arm in about 6 minutes on a 2-core CPU shared with another job, 4.7 alone on 2026-12-06 (data
    # synthesis, about 35 s, and the body checks, about 2 minutes, included)
    "default": {},
}


@dataclass
class LimbTrainConfig:
    """Everything a limb vision run depends on (one eye's net: the ball's distance, or the hand-to-ball
    discrepancy of both arms; written to RUN_DIR/config.json)."""

    #: the allowed values where they are fewer than the foveation config's (argparse choices; validate checks them)
    CHOICES: ClassVar[dict] = {**CHOICES, "model": ["linet", "fc", "cnn", "range"]}

    preset: str = "default"  # smoke | quick | default: sets the defaults of everything below
    task: str = "limb"  # fixed: tells evaluate which kind of run a directory holds
    out: str = ""  # output directory; default: runs/limb/<eye>
    data_dir: str = ""  # dataset directory; default: runs/datasets/limb-<config hash>
    # the dataset (sim/limb.py): the loop's world, arms at random postures, the ball near a hand or on a shot's path
    samples: int = 10_000  # ONVs (train + validation + test)
    heldout_samples: int = 1000  # ONVs in rooms and of shots training never sees (the summary's held-out set)
    photoreceptors: int = 14_400  # P per retina: the foveation net's retina (the loop renders one ONV for both)
    eye: str = "left"  # left or right
    samples_per_receptor: int = 4  # S rays per photoreceptor and channel (the loop's)
    data_seed: int = 0  # seed of the dataset and of the train/val/test split
    ball: str = "ordinary"  # the cannon's ball as the loop shows it (sim --ball): ordinary (lit by the room's lamps) or
                            # glowing (v7's, the room dimmed)
    # the model
    model: str = "linet"  # linet, fc: the fully-connected twin with the same hidden sizes, cnn: a CNN on the ONV binned
                          # to a foveated image, trained with turned and mirrored copies (nn/retina_cnn.py), or range: a
                          # CNN on the central 8 deg to the ball's distance (the loop adds the foveation net's direction
                          # and the hand's proprioception)
    channels: int = 16  # cnn and range only: channels of its first stage (x1, 2, 4, 6 over its four stages)
    layers: int = 3  # liNet hidden layers H
    receptive_field: int = 20  # R, connections per unit
    reduction: int = 5  # f, each layer has 1/f of the previous layer's units
    onv_dtype: str = "auto"  # float16 (as stored), bfloat16, float32, or auto (float16
                             # for a liNet, float32 for the fc, cnn and range nets)
    precision: str = "auto"  # cnn and range only: their layers in training run in bfloat16 (autocast) or float32; auto:
                             # bfloat16 where the device computes it natively (a CPU with AVX512-BF16 or AMX, a GPU of
                             # compute capability 8 on), else float32. Evaluation is float32
    # optimisation
    near_weight_m: float = 0.25  # m: each arm's error is weighted by 1 / (this + its
                                 # true hand-ball distance): near balls count most
    batch: int = 64
    lr: float = 1e-3  # Adam learning rate (of the first epoch)
    lr_schedule: str = "cosine"  # cosine (from lr to lr/20 over the epochs), plateau or constant
    epochs: int = 30  # at most
    patience: int = 8  # early stopping: epochs without a better validation
                       # median error (near balls; ranging: of the distance)
    val_fraction: float = 0.1
    test_fraction: float = 0.1
    seed: int = 0  # initialisation and shuffling
    # the run
    device: str = "auto"  # cpu, cuda, or auto

    #: Fields added after runs were saved without them: a saved config that lacks one had this value.
    LEGACY_DEFAULTS = {"ball": "glowing", "precision": "float32", "channels": 16}  # (channels: read by models after it)
    #: the net settings only some models read (see :attr:`warp_vision.train.config.TrainConfig.MODEL_FIELDS`)
    MODEL_FIELDS: ClassVar[dict] = {"layers": ("linet", "fc"), "receptive_field": ("linet", "fc"),
                                    "reduction": ("linet", "fc"), "channels": ("cnn", "range")}

    def data_config(self):
        from warp_vision.sim.limb import LimbDataConfig

        return LimbDataConfig(eye=self.eye, samples=self.samples, photoreceptors=self.photoreceptors,
                              samples_per_receptor=self.samples_per_receptor, seed=self.data_seed, ball=self.ball)

    def heldout_config(self):
        from warp_vision.sim.limb import LimbDataConfig

        return LimbDataConfig(eye=self.eye, samples=self.heldout_samples, photoreceptors=self.photoreceptors,
                              samples_per_receptor=self.samples_per_receptor, seed=self.data_seed + 1,
                              rooms="heldout", shots="heldout", ball=self.ball)

    def epoch_lr(self, epoch: int) -> float:
        return epoch_lr(self, epoch)

    def validate(self) -> None:
        _check_common(self, LIMB_PRESETS, ("samples", "heldout_samples", "photoreceptors", "samples_per_receptor"))
        check_splits(self.samples, self.val_fraction, self.test_fraction, min_test=2)
        if not self.near_weight_m > 0:
            raise ValueError(f"near_weight_m: expected > 0 m, got {self.near_weight_m}")
        if self.model in ("cnn", "range") and self.onv_dtype not in ("auto", "float32"):
            raise ValueError(f"onv_dtype: the {self.model} net reads float32 ONVs, got {self.onv_dtype!r}")
        check_net_sizes(self)
        self.data_config().validate()
        self.heldout_config().validate()


LIMB_PRESETS: dict[str, dict] = {
    # seconds, for tests
    "smoke": dict(samples=64, heldout_samples=16, photoreceptors=400, samples_per_receptor=1, layers=2,
                  receptive_field=8, batch=16, epochs=2, patience=2),
    # a first look: about 2 minutes on a 2-core CPU, rendering included
    "quick": dict(samples=2000, heldout_samples=300, model="range", lr=2e-3, epochs=12, patience=12),
    # one eye in about 11 minutes on a 2-core CPU (rendering 11,000 ONVs, then about 4 minutes of training, less
    # with bfloat16; the runs: docs/RESULTS.md, "Figures behind the code's constants"):
    # the ranging net (the ONV-only nets find the ball but not the hands: docs/RESULTS.md)
    "default": dict(model="range", lr=2e-3, epochs=24, patience=24),
}
