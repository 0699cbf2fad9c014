"""The intraocular shallow nets (the paper's SNNs 1-4): each eye's pupil net and lens net (:class:`LensNet`).

:class:`PupilNet`: (ONV [B, 3P], current pupil [B] mm) -> the commanded pupil [B] mm. The brightness of
an ONV is the scene's luminance times the pupil's area, so the net is given the pupil it looked through
(the efference copy of its last command, as the oculomotor nets are given their current activations).
Its first layer is fixed: the mean irradiance of each channel over ``rings`` x ``sectors`` regions of
the retina (rings of equal photoreceptor counts by eccentricity) and over the whole field, in log10 (one
decade is one unit, whatever the light level). The log pupil joins them, and a hidden layer of ``hidden``
tanh units maps them to the diameter, within 2-8 mm.
"""

from __future__ import annotations

import numpy as np
import torch

PUPIL_MM = (2.0, 8.0)
#: the accommodations (D) at which a lens net's calibration (:meth:`LensNet.calibrated`) is tabulated
LENS_BIAS_KNOTS_D = np.arange(0.0, 10.01, 0.5)
LOG_FLOOR = 1e-9  # irradiance floor under the log10 (far below any lit scene's)


def _check_onv(onv: torch.Tensor, P: int, name: str = "onv") -> None:
    if not torch.is_tensor(onv) or onv.dim() != 2 or onv.shape[1] != 3 * P:
        shape = tuple(onv.shape) if torch.is_tensor(onv) else type(onv).__name__
        raise ValueError(f"{name}: expected a tensor [B, {3 * P}] (3 channels of {P} photoreceptors), got {shape}")
    if not torch.isfinite(onv).all() or (onv < 0).any():
        raise ValueError(f"{name}: expected finite irradiances >= 0")


def _check_pupil(pupil_mm, onv: torch.Tensor) -> torch.Tensor:
    """``pupil_mm`` as a float32 [B] tensor on ``onv``'s device: one diameter in (0, 10] mm per ONV."""
    pupil_mm = torch.as_tensor(pupil_mm, dtype=torch.float32, device=onv.device).reshape(-1)
    if len(pupil_mm) != len(onv):
        raise ValueError(f"pupil_mm: expected one diameter per ONV ({len(onv)}), got {len(pupil_mm)}")
    if not torch.isfinite(pupil_mm).all() or (pupil_mm <= 0).any() or (pupil_mm > 10).any():
        raise ValueError(f"pupil_mm: expected diameters in (0, 10] mm, got {pupil_mm.tolist()[:5]}")
    return pupil_mm


def retina_regions(domain_xy: np.ndarray, rings: int, sectors: int) -> np.ndarray:
    """[P] region of each photoreceptor: ``rings`` eccentricity rings of equal counts times ``sectors``
    polar sectors, numbered ring-major."""
    xy = np.asarray(domain_xy, np.float64)
    rho, theta = np.hypot(xy[:, 0], xy[:, 1]), np.mod(np.arctan2(xy[:, 1], xy[:, 0]), 2 * np.pi)
    edges = np.quantile(rho, np.linspace(0, 1, rings + 1)[1:-1])
    ring = np.searchsorted(edges, rho, side="right")
    sector = np.minimum((theta / (2 * np.pi) * sectors).astype(int), sectors - 1)
    return ring * sectors + sector


class RegionLogMeans(torch.nn.Module):
    """ONV [B, 3P] -> [B, 3 (R + 1)]: log10 of each channel's mean irradiance over each region and over
    the whole retina. No weights."""

    def __init__(self, domain_xy: np.ndarray, rings: int, sectors: int):
        super().__init__()
        region = retina_regions(domain_xy, rings, sectors)
        R = rings * sectors
        A = np.zeros((len(region), R + 1), np.float32)
        A[np.arange(len(region)), region] = 1.0
        A[:, R] = 1.0
        A /= np.maximum(A.sum(axis=0, keepdims=True), 1.0)
        self.P = len(region)
        self.register_buffer("average", torch.from_numpy(A))

    @property
    def features(self) -> int:
        return 3 * self.average.shape[1]

    def forward(self, onv: torch.Tensor) -> torch.Tensor:
        x = onv.float().view(len(onv), self.P, 3)
        m = torch.einsum("bpc,pr->brc", x, self.average)
        return torch.log10(m.clamp_min(0) + LOG_FLOOR).flatten(1)


class PupilNet(torch.nn.Module):
    """(ONV [B, 3P], current pupil [B] mm) -> commanded pupil [B] mm (module docstring)."""

    def __init__(self, domain_xy: np.ndarray, hidden: int = 32, rings: int = 4, sectors: int = 8):
        super().__init__()
        self.pool = RegionLogMeans(domain_xy, rings, sectors)
        n = self.pool.features + 1
        self.register_buffer("feature_mean", torch.zeros(n))
        self.register_buffer("feature_std", torch.ones(n))
        self.hidden = torch.nn.Linear(n, hidden)
        self.out = torch.nn.Linear(hidden, 1)

    def raw_features(self, onv: torch.Tensor, pupil_mm: torch.Tensor) -> torch.Tensor:
        """The fixed first layer's outputs [B, 3 (R + 1) + 1] (region log-means and the log pupil), before
        standardisation."""
        _check_onv(onv, self.pool.P)
        return torch.cat([self.pool(onv), torch.log10(_check_pupil(pupil_mm, onv))[:, None]], dim=1)

    def head(self, raw: torch.Tensor) -> torch.Tensor:
        """The learned part: :meth:`raw_features` -> the commanded pupil [B] mm."""
        z = self.out(torch.tanh(self.hidden((raw - self.feature_mean) / self.feature_std)))[:, 0]
        lo, hi = PUPIL_MM
        return lo + (hi - lo) * torch.sigmoid(z)

    def forward(self, onv: torch.Tensor | None = None, pupil_mm: torch.Tensor | None = None,
                raw: torch.Tensor | None = None) -> torch.Tensor:
        """The commanded pupil [B] mm of (``onv``, ``pupil_mm``), or of precomputed :meth:`raw_features`."""
        if raw is None:
            if onv is None or pupil_mm is None:
                raise ValueError("PupilNet: expected onv and pupil_mm, or raw features")
            raw = self.raw_features(onv, pupil_mm)
        return self.head(raw)


#: :class:`BandEnergies`' neighbourhood sizes: the image averaged over each photoreceptor and this many of
#: its nearest neighbours, finest first; successive averages differ by one octave of spatial frequency.
LENS_NEIGHBOURHOODS = (3, 6, 12, 24, 48, 96)
#: The colour-channel pairs whose band responses :class:`BandEnergies` correlates: (R, B), (R, G), (G, B).
CHANNEL_PAIRS = ((0, 2), (0, 1), (1, 2))


class BandEnergies(torch.nn.Module):
    """Central ONV [B, N, 3] -> [B, bands x (3 + 3) x rings] fixed band-pass features of each colour channel.

    Each channel is divided by its mean over the field (so the scene's light level and tint drop out), then
    split into band-pass images (differences of Gaussians on the irregular retina, the receptive fields of
    retinal ganglion cells): band 0 is each photoreceptor minus the mean of its ``neighbourhoods[0]``
    nearest neighbours, band i the mean over ``neighbourhoods[i - 1]`` neighbours minus the mean over
    ``neighbourhoods[i]``. Per band and per eccentricity ring (``rings`` of equal photoreceptor counts):
    the log10 mean energy of each channel (how much contrast the blur leaves at that scale), then the
    correlation of the band's responses between the channel pairs of :data:`CHANNEL_PAIRS` (1 where two
    channels are blurred alike; the eye's chromatic aberration blurs them unequally, in an order set by
    the sign of the defocus). No weights."""

    def __init__(self, domain_xy: np.ndarray, neighbourhoods=LENS_NEIGHBOURHOODS, rings: int = 3):
        super().__init__()
        from scipy.spatial import cKDTree

        ks = tuple(int(k) for k in neighbourhoods)
        if len(ks) < 1 or ks[0] < 1 or any(b <= a for a, b in zip(ks, ks[1:])):
            raise ValueError(f"neighbourhoods: expected increasing positive counts, got {neighbourhoods}")
        xy = np.asarray(domain_xy, np.float64)
        if len(xy) <= ks[-1]:
            raise ValueError(f"domain_xy: expected more than {ks[-1]} photoreceptors, got {len(xy)}")
        _d, nbr = cKDTree(xy).query(xy, ks[-1] + 1)
        self.neighbourhoods = ks
        self.register_buffer("neighbours", torch.from_numpy(nbr[:, 1:].astype(np.int64)))
        rho = np.hypot(xy[:, 0], xy[:, 1])
        ring = np.searchsorted(np.quantile(rho, np.linspace(0, 1, rings + 1)[1:-1]), rho, side="right")
        A = np.zeros((len(xy), rings), np.float32)
        A[np.arange(len(xy)), ring] = 1.0
        self.register_buffer("ring_average", torch.from_numpy(A / A.sum(0, keepdims=True)))

    @property
    def rings(self) -> int:
        return self.ring_average.shape[1]

    @property
    def features(self) -> int:
        return len(self.neighbourhoods) * (3 + len(CHANNEL_PAIRS)) * self.rings

    def bands(self, x: torch.Tensor) -> list[torch.Tensor]:
        """The band-pass images [B, N, 3] of ``x`` (finest first), after each channel's normalisation."""
        x = x / x.mean(dim=1, keepdim=True).clamp_min(1e-12)
        out, level, total, done = [], x, torch.zeros_like(x), 0
        for k in self.neighbourhoods:  # the neighbour sums grow by the next nearest ones only
            total = total + x[:, self.neighbours[:, done:k]].sum(dim=2)
            done = k
            coarser = total / k
            out.append(level - coarser)
            level = coarser
        return out

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = []
        for b in self.bands(x):
            e = torch.einsum("bnc,nr->bcr", b * b, self.ring_average)  # [B, 3, rings]
            out.append(torch.log10(e + 1e-8).flatten(1))
            for i, j in CHANNEL_PAIRS:
                cross = torch.einsum("bn,nr->br", b[..., i] * b[..., j], self.ring_average)
                out.append(cross / torch.sqrt(e[:, i] * e[:, j]).clamp_min(1e-12))
        return torch.cat(out, dim=1)


class LensNet(torch.nn.Module):
    """(central ONV, current pupil [B] mm) -> the signed defocus [B] in dioptres: the accommodation minus
    the fixated object's vergence (positive: focused too near).

    It reads the photoreceptors ``central`` (indices into the retina of ``photoreceptors``) through the fixed
    :class:`BandEnergies` of each colour channel: how much contrast the blur leaves in each octave, and how
    alike the channels are blurred (the eye's longitudinal chromatic aberration, about 1.6 D from blue to
    red, blurs them unequally, and the order of their sharpness gives the sign). The log pupil joins them,
    and two hidden layers of ``hidden`` tanh units map them to the defocus.

    The central field is rendered for this net with ``samples_per_receptor`` rays per photoreceptor and
    channel (the lens data's, more than the foveation ONV's 4: with 4 pupil points a blurred image is
    sampled too sparsely to tell its blur apart, docs/RESULTS.md), so it is usually given just those photoreceptors
    (``central_only``)."""

    def __init__(self, domain_xy: np.ndarray, central: np.ndarray, photoreceptors: int, hidden: int = 64,
                 samples_per_receptor: int = 16):
        super().__init__()
        central = np.asarray(central, np.int64)
        need = LENS_NEIGHBOURHOODS[-1] + 1
        if central.ndim != 1 or len(central) < need or central.min() < 0 or central.max() >= photoreceptors:
            raise ValueError(f"central: expected at least {need} photoreceptor indices below {photoreceptors}")
        self.P = int(photoreceptors)
        #: S of the central render this net reads (its training data's)
        if isinstance(samples_per_receptor, bool) or int(samples_per_receptor) < 1:
            raise ValueError(f"samples_per_receptor: expected a positive integer, got {samples_per_receptor!r}")
        self.samples_per_receptor = int(samples_per_receptor)
        self.register_buffer("central", torch.from_numpy(central))
        self.bands = BandEnergies(np.asarray(domain_xy)[central])
        n = self.bands.features + 1
        self.register_buffer("feature_mean", torch.zeros(n))
        self.register_buffer("feature_std", torch.ones(n))
        #: below this :meth:`contrast` the image holds no defocus cue (set from the training data)
        self.register_buffer("contrast_floor", torch.tensor(-np.inf))
        #: the net's median error near focus at each accommodation of LENS_BIAS_KNOTS_D (D), fitted on the
        #: training split after training (:meth:`warp_vision.train.lens.LensTask.calibrate`); zeros: none
        self.register_buffer("bias_D", torch.zeros(len(LENS_BIAS_KNOTS_D)))
        self.register_load_state_dict_pre_hook(_no_bias_is_zero_bias)
        self.mlp = torch.nn.Sequential(torch.nn.Linear(n, hidden), torch.nn.Tanh(), torch.nn.Linear(hidden, hidden),
                                       torch.nn.Tanh(), torch.nn.Linear(hidden, 1))

    def calibrated(self, defocus: torch.Tensor, accommodation_D) -> torch.Tensor:
        """The estimate ``defocus`` [B] of ONVs seen with the lens at ``accommodation_D`` (the efference copy
        of the lens command; a float or [B]) less the net's bias at that accommodation (``bias_D``,
        interpolated): near focus, where the loop's lens settles, the estimate reads the defocus without
        the net's systematic offset (near cards read as slightly less defocused than they are). The bias is
        a smooth function of the lens state alone, a few hundredths of a dioptre, so it cannot carry the
        defocus itself."""
        acc = torch.as_tensor(accommodation_D, dtype=torch.float64).reshape(-1).cpu().numpy()
        if not np.isfinite(acc).all():
            raise ValueError(f"accommodation_D: expected finite dioptres, got {acc.tolist()[:5]}")
        b = np.interp(acc, LENS_BIAS_KNOTS_D, self.bias_D.detach().cpu().double().numpy())
        return defocus - torch.as_tensor(b, dtype=defocus.dtype, device=defocus.device)

    def raw_features(self, onv: torch.Tensor, pupil_mm: torch.Tensor, central_only: bool = False) -> torch.Tensor:
        """The fixed first layer's outputs [B, features] (the energies and the log pupil), before
        standardisation. ``central_only``: ``onv`` holds only the central photoreceptors ([B, 3
        len(central)], as the lens datasets store them)."""
        N = len(self.central)
        _check_onv(onv, N if central_only else self.P)
        pupil_mm = _check_pupil(pupil_mm, onv)
        x = onv.float().view(len(onv), -1, 3)
        if not central_only:
            x = x[:, self.central]
        return torch.cat([self.bands(x), torch.log10(pupil_mm)[:, None]], dim=1)

    def contrast(self, raw: torch.Tensor) -> torch.Tensor:
        """[B] the image's fine contrast: the mean log10 energy of the finest band over
        channels and rings. A uniform field (a glowing ball filling the fovea) has none: compare with
        ``contrast_floor``, under which the net's estimate means nothing."""
        return raw[:, : 3 * self.bands.rings].mean(dim=1)

    def head(self, raw: torch.Tensor) -> torch.Tensor:
        """The learned part: :meth:`raw_features` [B, features] -> defocus [B] (D)."""
        return self.mlp((raw - self.feature_mean) / self.feature_std)[:, 0]

    def forward(self, onv: torch.Tensor | None = None, pupil_mm: torch.Tensor | None = None, central_only: bool = False,
                raw: torch.Tensor | None = None) -> torch.Tensor:
        """The defocus [B] (D) of (``onv``, ``pupil_mm``), or of precomputed :meth:`raw_features` ``raw``."""
        if raw is None:
            if onv is None or pupil_mm is None:
                raise ValueError("LensNet: expected onv and pupil_mm, or raw features")
            raw = self.raw_features(onv, pupil_mm, central_only)
        return self.head(raw)


def _no_bias_is_zero_bias(module, state_dict, prefix, *args) -> None:
    """Checkpoints of lens nets written before the calibration existed load with none (zeros)."""
    state_dict.setdefault(prefix + "bias_D", torch.zeros(len(LENS_BIAS_KNOTS_D)))
