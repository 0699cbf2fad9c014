"""The training configuration of the foveal verification nets (:mod:`warp_vision.train.verify`): a dataclass
with its presets; the command line and the checks it shares with the others are
:mod:`warp_vision.train.config`'s."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from warp_vision.train.config import CHOICES, _check_common, check_splits


@dataclass
class VerifyTrainConfig:
    """Everything a verification-net run depends on (one eye; written to RUN_DIR/config.json)."""

    CHOICES: ClassVar[dict] = {**CHOICES, "model": ["cnn", "linet"]}

    preset: str = "default"  # smoke | quick | default: sets the defaults of everything below
    task: str = "verify"  # fixed: tells evaluate which kind of run a directory holds
    out: str = ""  # output directory; default: runs/verify/<eye>
    data_dir: str = ""  # dataset directory; default: runs/datasets/verify-<config hash>
    eye: str = "left"  # which eye's retina
    # the dataset (warp_vision.data.verification): the central field fixating the ball or a look-alike
    samples: int = 20000  # training ONVs (validation and test split off them)
    heldout_samples: int = 3000  # ONVs of held-out rooms, measured at the end
    photoreceptors: int = 14_400  # P: the foveation nets' retina
    samples_per_receptor: int = 4  # S: the foveation ONV's (the loop reads the field out of it)
    central_deg: float = 5.0  # the field the net reads
    max_offset_deg: float = 2.0  # the fixation error after a saccade: 0 to this
    # the model
    model: str = "cnn"  # cnn (the default: the better on held-out rooms, docs/RESULTS.md) or linet (the paper's)
    channels: int = 16  # cnn: the first stage's channels
    layers: int = 3  # linet: locally-connected layers
    receptive_field: int = 20  # linet: K nearest inputs per unit
    reduction: int = 4  # linet: units shrink by this factor per layer
    offset_weight: float = 0.5  # the offset's share of the loss (on ball samples only)
    # optimisation
    batch: int = 64
    lr: float = 2e-3  # Adam learning rate (of the first epoch)
    lr_schedule: str = "cosine"  # cosine (from lr to lr/20 over the epochs), plateau or constant
    epochs: int = 20  # at most
    patience: int = 20  # early stopping: epochs without a better validation loss
    val_fraction: float = 0.1
    test_fraction: float = 0.1
    seed: int = 0  # data, initialisation and shuffling
    # the run
    device: str = "cpu"  # cpu, cuda, or auto

    def data_config(self):
        from warp_vision.data.verification import VerifyDataConfig

        return VerifyDataConfig(samples=self.samples, photoreceptors=self.photoreceptors, eye=self.eye,
                                samples_per_receptor=self.samples_per_receptor, central_deg=self.central_deg,
                                max_offset_deg=self.max_offset_deg, seed=self.seed)

    def validate(self) -> None:
        _check_common(self, VERIFY_PRESETS, ("samples", "heldout_samples", "photoreceptors", "samples_per_receptor",
                                             "channels"))
        if not 0 <= self.offset_weight <= 10:
            raise ValueError(f"offset_weight: expected 0 to 10, got {self.offset_weight}")
        check_splits(self.samples, self.val_fraction, self.test_fraction, min_test=2)
        self.data_config().validate()


VERIFY_PRESETS: dict[str, dict] = {
    # seconds, for tests
    "smoke": dict(samples=48, heldout_samples=16, photoreceptors=1000, samples_per_receptor=1, channels=4, epochs=2,
                  patience=2),
    # a first look
    "quick": dict(samples=3000, heldout_samples=600, epochs=12, patience=12),
    "default": {},
}
