"""The training configurations of the intraocular nets (the paper's SNNs for the iris and the lens): the
pupil net and the lens net. Each is a dataclass with its presets; the command line and the checks they share
are :mod:`warp_vision.train.config`'s."""

from __future__ import annotations

from dataclasses import dataclass

from warp_vision.train.config import _check_common, check_splits


@dataclass
class PupilTrainConfig:
    """Everything a pupil-net run depends on (one eye; written to RUN_DIR/config.json)."""

    preset: str = "default"  # smoke | quick | default: sets the defaults of everything below
    task: str = "pupil"  # fixed: tells evaluate which kind of run a directory holds
    out: str = ""  # output directory; default: runs/pupil/<eye>
    data_dir: str = ""  # dataset directory; default: runs/datasets/pupil-<config hash>
    eye: str = "left"  # which eye's retina
    # the dataset (warp_vision.data.intraocular): v8 scenes through random pupils at random light levels
    samples: int = 3000  # training ONVs (validation and test split off them)
    heldout_samples: int = 500  # ONVs of held-out rooms (seeds offset by 1000), measured at the end
    photoreceptors: int = 14_400  # P: the foveation nets' retina
    samples_per_receptor: int = 4  # S rays per photoreceptor and channel
    luminance_decades: float = 5.0  # the adapting luminances span this many decades
    # the model
    hidden: int = 32  # tanh units
    rings: int = 4  # the fixed first layer's eccentricity rings
    sectors: int = 8  # and polar sectors
    # optimisation
    batch: int = 64
    lr: float = 3e-3  # Adam learning rate (of the first epoch)
    lr_schedule: str = "cosine"  # cosine (from lr to lr/20 over the epochs), plateau or constant
    epochs: int = 150  # at most
    patience: int = 150  # early stopping: epochs without a better validation error
    val_fraction: float = 0.1
    test_fraction: float = 0.1
    seed: int = 0  # data, initialisation and shuffling
    # the run
    device: str = "cpu"  # cpu, cuda, or auto (a small net: the CPU is as fast)

    def data_config(self):
        from warp_vision.data.intraocular import PupilDataConfig

        return PupilDataConfig(samples=self.samples, photoreceptors=self.photoreceptors, eye=self.eye,
                               samples_per_receptor=self.samples_per_receptor,
                               luminance_decades=self.luminance_decades, seed=self.seed)

    def validate(self) -> None:
        _check_common(self, PUPIL_PRESETS, ("samples", "heldout_samples", "photoreceptors", "samples_per_receptor",
                                            "hidden", "rings", "sectors"))
        check_splits(self.samples, self.val_fraction, self.test_fraction, min_test=2)
        self.data_config().validate()


PUPIL_PRESETS: dict[str, dict] = {
    # seconds, for tests
    "smoke": dict(samples=48, heldout_samples=16, photoreceptors=400, samples_per_receptor=1, hidden=8, epochs=2,
                  patience=2),
    # a first look (``python -m warp_vision.sim demo --quick``): a minute per eye on a 2-core CPU
    "quick": dict(samples=800, heldout_samples=200, epochs=100, patience=100),
    # 2-5 minutes per eye on a 2-core CPU (docs/RESULTS.md, "Figures behind the code's constants")
    "default": {},
}


@dataclass
class LensTrainConfig:
    """Everything a lens-net run depends on (one eye; written to RUN_DIR/config.json)."""

    preset: str = "default"  # smoke | quick | default: sets the defaults of everything below
    task: str = "lens"  # fixed: tells evaluate which kind of run a directory holds
    out: str = ""  # output directory; default: runs/lens/<eye>
    data_dir: str = ""  # dataset directory; default: runs/datasets/lens-<config hash>
    eye: str = "left"  # which eye's retina
    # the dataset (warp_vision.data.intraocular): textured cards at 0.2-5 m, the lens at random states near them
    samples: int = 16000  # training ONVs (validation and test split off them)
    heldout_samples: int = 1000  # ONVs of new textures, lamps and distances, measured at the end
    photoreceptors: int = 14_400  # P: the foveation nets' retina
    samples_per_receptor: int = 8  # S rays per photoreceptor and channel (the loop renders the net's field at this S)
    central_deg: float = 2.0  # the net reads the photoreceptors within this eccentricity
    defocus_range_D: float = 2.5  # |defocus| up to this
    card_vertices: int = 384  # per side of each textured card's grid
    # the model
    hidden: int = 64  # tanh units per hidden layer
    # optimisation
    batch: int = 64
    lr: float = 3e-3  # Adam learning rate (of the first epoch)
    lr_schedule: str = "cosine"  # cosine (from lr to lr/20 over the epochs), plateau or constant
    epochs: int = 120  # at most
    patience: int = 120  # early stopping: epochs without a better validation error
    val_fraction: float = 0.1
    test_fraction: float = 0.1
    seed: int = 0  # data, initialisation and shuffling
    # the run
    device: str = "cpu"  # cpu, cuda, or auto (a small net: the CPU is as fast)

    def data_config(self):
        from warp_vision.data.intraocular import LensDataConfig

        return LensDataConfig(samples=self.samples, photoreceptors=self.photoreceptors, eye=self.eye,
                              samples_per_receptor=self.samples_per_receptor, central_deg=self.central_deg,
                              defocus_range_D=self.defocus_range_D, card_vertices=self.card_vertices, seed=self.seed)

    def validate(self) -> None:
        _check_common(self, LENS_PRESETS,
                      ("samples", "heldout_samples", "photoreceptors", "samples_per_receptor", "hidden"))
        check_splits(self.samples, self.val_fraction, self.test_fraction, min_test=2)
        self.data_config().validate()


LENS_PRESETS: dict[str, dict] = {
    # seconds, for tests
    "smoke": dict(samples=48, heldout_samples=16, photoreceptors=1000, samples_per_receptor=1, card_vertices=48,
                  hidden=8, epochs=2, patience=2),
    # a first look (``python -m warp_vision.sim demo --quick``)
    "quick": dict(samples=2000, heldout_samples=400, epochs=80, patience=80),
    # 9-13 minutes per eye on a 2-core CPU, the cards' BVHs included (docs/RESULTS.md: the run, and why 16,000
    # ONVs rather than 6,000)
    "default": {},
}
