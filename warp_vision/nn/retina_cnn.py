"""A standard CNN on the retina resampled to a foveated image: the ball-finder for ordinary scenes.

The liNet (:mod:`warp_vision.nn.linet`) gives every connection its own weight and, on generator v8's
ordinary balls among furniture, lamps and arms, memorises its training set; the stencil convolution on
the irregular layout (:mod:`warp_vision.nn.retina_conv`) shares its weights but stays shallow and coarse
(docs/RESULTS.md has both measurements). This module takes the route of image detectors instead:

- **Resampling** (fixed, no weights). The ONV is binned onto a ``size`` x ``size`` image whose pixel at
  (u, v) in [-1, 1]^2 shows the direction at eccentricity ``max_ecc * |(u, v)| ** power`` and polar
  angle ``atan2(v, u)`` in the eye frame (x right, y up, z the optical axis). ``power`` > 1 magnifies the
  centre as the retina does (about 0.55 deg a pixel at 2 deg, 1.5 deg at 45 deg for the defaults, where
  the photoreceptor spacing is 0.15 and 2.4 deg). Each pixel is the mean of the photoreceptors that fall
  in it; a pixel that none falls in takes the inverse-distance mean of its 4 nearest. Beyond the retina's
  rim the image is 0. The map is a sparse [pixels, P] matrix, applied as a CSR product (one product for
  all the views of a consensus: :meth:`RetinaImageCNN.view_images`).
- **Augmentation** (training only). The same binning with the pixel directions turned about the optical
  axis and mirrored (``transform``): the image of a rotated, mirrored world, whose target is turned the
  same way (:meth:`transform_targets`). A sphere stays a sphere, so the net sees every ball position,
  orientation and handedness from one rendered ONV.
- **Backbone**: a 4-stage CNN (3 x 3 convolutions, batch norm, ReLU; strides 2, 2, 2, 2) with a feature
  pyramid back up to half resolution: a heat map of the ball on a (size/2)^2 grid of cells, each cell
  with its visual direction.
- **Read-out**: the arg-max cell's ``window`` x ``window`` neighbourhood, with every cell within
  ``window_deg`` of it, soft-arg-maxed over the cells' unit direction vectors, gives the ball's direction
  as (yaw, pitch), standardised as the targets are. Local, not global: a lamp elsewhere on the map cannot
  pull the estimate toward it; the angular part covers a near ball at the magnified centre, whose heat
  is a plateau many cells wide. Training adds a cross-entropy of the heat map against the cell of the
  true direction (:meth:`heatmap_loss`).
- **Precision**: the image and the read-out are float32; in training the CNN (convolutions, batch norm,
  the pyramid) may run under bfloat16 autocast (``train_precision``, :func:`training_autocast`), where
  the hardware computes bfloat16 natively. Inference stays float32.
"""

from __future__ import annotations

import contextlib
import functools
import math
import warnings

import numpy as np
import torch
from scipy.spatial import cKDTree
from torch import Tensor, nn

from warp_vision.frames import gaze_angles, gaze_directions
from warp_vision.nn.standardise import StandardisedTargets

#: pixels: the foveated image is IMAGE_SIZE x IMAGE_SIZE
IMAGE_SIZE = 96
#: deg: the read-out's soft-arg-max also takes every cell within this angle of the heat map's peak
WINDOW_DEG = 6.0
#: transforms for augmentation: ROTATIONS angles about the optical axis, each plain and mirrored
ROTATIONS = 24
#: The foveation CNN's read-out at inference (eval mode): the ball's direction found in this many views
#: (:func:`consensus_transforms`) and mapped back, then the mean of the directions within CONSENSUS_DEG of
#: the view that most others agree with. Measured on held-out conditions (docs/RESULTS.md "Decoys"): every median
#: lower than one view's, and fewer balls missed (a view caught by a decoy is outvoted).
CONSENSUS_VIEWS = 8
CONSENSUS_DEG = 2.0
#: the ranging net's image (:class:`RetinaCNNRangeNet`): the central RANGE_ECC_DEG at a nearly uniform
#: scale (power 1.2: about 0.15 deg a pixel at 1-2 deg, where the photoreceptors lie 0.04-0.13 deg apart)
RANGE_IMAGE_SIZE = 96
RANGE_ECC_DEG = 8.0
RANGE_POWER = 1.2
#: deg: the ranging net reads balls within this angle of the line of sight (trained on those only; at
#: run time the foveation net's direction decides), so a near ball's disc stays inside its image
RANGE_GATE_DEG = 5.6


#: what the CNNs can train in (the training configs' ``precision``): auto is bfloat16 where the device
#: computes it natively (:func:`native_bfloat16`), float32 elsewhere
PRECISIONS = ("auto", "float32", "bfloat16")


@functools.cache  # a property of the machine, asked on every training forward
def native_bfloat16(device_type: str) -> bool:
    """Whether ``device_type`` ("cpu", "cuda") runs bfloat16 convolutions in hardware: a CPU with AVX512-BF16
    or AMX tiles, a CUDA GPU that torch says supports bfloat16 without emulation (compute capability 8.0 on).
    Elsewhere torch would emulate bfloat16, so "auto" keeps float32 there."""
    if device_type == "cpu":
        probes = (getattr(torch.cpu, "_is_avx512_bf16_supported", None),
                  getattr(torch.cpu, "_is_amx_tile_supported", None))
        return any(bool(f()) for f in probes if f is not None)
    if device_type == "cuda" and torch.cuda.is_available():
        try:
            return bool(torch.cuda.is_bf16_supported(including_emulation=False))
        except TypeError:  # an older torch without the keyword
            return torch.cuda.get_device_capability()[0] >= 8
    return False


def training_autocast(precision: str, device_type: str) -> torch.dtype | None:
    """The autocast dtype a CNN trains in on ``device_type`` for ``precision`` (:data:`PRECISIONS`):
    torch.bfloat16, or None for float32 (no autocast)."""
    if precision not in PRECISIONS:
        raise ValueError(f"precision: expected one of {PRECISIONS}, got {precision!r}")
    if precision == "bfloat16" or (precision == "auto" and native_bfloat16(device_type)):
        return torch.bfloat16
    return None


def transform_matrix(k: int) -> np.ndarray:
    """The 3 x 3 map of augmentation ``k`` in [0, 2 * ROTATIONS): a turn of 2 pi (k // 2) / ROTATIONS about
    the optical axis, mirrored in x when k is odd. k = 0 is the identity."""
    a = 2 * math.pi * (k // 2) / ROTATIONS
    c, s = math.cos(a), math.sin(a)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return rot @ np.diag([-1.0 if k % 2 else 1.0, 1.0, 1.0])


def consensus_transforms(n: int) -> list[int]:
    """The ``n`` augmentations (1 <= n <= 2 * ROTATIONS) the consensus read-out uses: turns spread evenly
    over the circle, alternately plain and mirrored; ``[0]`` (the plain image) for n = 1."""
    if not (isinstance(n, (int, np.integer)) and 1 <= n <= 2 * ROTATIONS):
        raise ValueError(f"views: expected an int in [1, {2 * ROTATIONS}], got {n!r}")
    return [2 * ((i * ROTATIONS) // n) + (i % 2) for i in range(n)]


def consensus_of(d: Tensor) -> Tensor:
    """(yaw, pitch) [B, 2] rad from V directions per sample [B, V, 3] (eye frame, any length): the mean
    of the unit directions within :data:`CONSENSUS_DEG` of the one that has the most such neighbours
    (itself included; the first on a tie)."""
    d = d / d.norm(dim=2, keepdim=True)
    near = (d @ d.transpose(1, 2)) >= math.cos(math.radians(CONSENSUS_DEG))
    best = near.sum(2).argmax(1)
    w = near[torch.arange(len(d), device=d.device), best].to(d.dtype)
    return gaze_angles((w[:, :, None] * d).sum(1))


class FoveatedImage:
    """The warp between image coordinates (u, v) in [-1, 1]^2 and eye-frame directions."""

    def __init__(self, size: int, max_ecc_deg: float, power: float):
        if not (isinstance(size, int) and size >= 16 and size % 16 == 0):
            raise ValueError(f"size: expected a multiple of 16, at least 16, got {size!r}")
        if not (0 < max_ecc_deg < 90 and power >= 1):
            raise ValueError(f"max_ecc_deg in (0, 90) and power >= 1 expected, got {max_ecc_deg!r}, {power!r}")
        self.size, self.max_ecc, self.power = size, math.radians(max_ecc_deg), float(power)

    def uv_to_dirs(self, uv: np.ndarray) -> np.ndarray:
        rho = np.hypot(uv[..., 0], uv[..., 1])
        ecc = self.max_ecc * rho ** self.power
        phi = np.arctan2(uv[..., 1], uv[..., 0])
        s = np.sin(ecc)
        return np.stack([s * np.cos(phi), s * np.sin(phi), np.cos(ecc)], -1)

    def dirs_to_uv(self, d: np.ndarray) -> np.ndarray:
        ecc = np.arccos(np.clip(d[..., 2], -1.0, 1.0))
        rho = (ecc / self.max_ecc) ** (1.0 / self.power)
        phi = np.arctan2(d[..., 1], d[..., 0])
        return np.stack([rho * np.cos(phi), rho * np.sin(phi)], -1)

    def grid_uv(self, n: int) -> np.ndarray:
        """[n * n, 2] centres of an n x n grid over [-1, 1]^2, row-major with v falling down the rows."""
        c = (np.arange(n) + 0.5) / n * 2 - 1
        u, v = np.meshgrid(c, -c)
        return np.stack([u.ravel(), v.ravel()], -1)

    def binning(self, photoreceptor_dirs: np.ndarray, m: np.ndarray) -> tuple[Tensor, Tensor, Tensor]:
        """(pixel, photoreceptor, weight): the entries of the sparse [size^2, P] matrix that bins the ONV of
        photoreceptors at ``photoreceptor_dirs`` into the image whose pixel directions are mapped by ``m``
        (3 x 3) before looking them up."""
        n = self.size
        # photoreceptor p lands in the pixel of m^-1 d_p (the pixel whose turned direction is d_p)
        uv = self.dirs_to_uv(photoreceptor_dirs @ m)  # rows: (m^T d)^T, m orthogonal
        col = np.floor((uv[:, 0] + 1) / 2 * n).astype(np.int64)
        row = np.floor((1 - uv[:, 1]) / 2 * n).astype(np.int64)
        inside = (col >= 0) & (col < n) & (row >= 0) & (row < n)
        pix, pr = row[inside] * n + col[inside], np.flatnonzero(inside)
        counts = np.bincount(pix, minlength=n * n)
        rows, cols, vals = [pix], [pr], [1.0 / counts[pix]]
        empty = np.flatnonzero(counts == 0)
        if len(empty):
            tree = cKDTree(photoreceptor_dirs)
            want = self.uv_to_dirs(self.grid_uv(n)[empty]) @ m.T
            dist, nn_idx = tree.query(want, k=4)
            spacing = np.median(tree.query(photoreceptor_dirs[:: max(1, len(photoreceptor_dirs) // 500)], k=2)[0][:, 1])
            w = 1.0 / np.maximum(dist, 1e-9)
            w /= w.sum(1, keepdims=True)
            # beyond the rim (nearest photoreceptor far beyond the local spacing there): black
            rim = dist[:, 0] > max(0.1, 20 * spacing)
            w[rim] = 0.0
            rows.append(np.repeat(empty, 4))
            cols.append(nn_idx.ravel())
            vals.append(w.ravel())
        return (torch.as_tensor(np.concatenate(rows)), torch.as_tensor(np.concatenate(cols)),
                torch.as_tensor(np.concatenate(vals), dtype=torch.float32))


class _Rebuilt(dict):
    """A cache of values rebuilt on demand: ``copy.deepcopy`` starts it empty. It holds sparse CSR tensors,
    which deepcopy cannot copy (they have no storage)."""

    def __deepcopy__(self, memo):
        return type(self)()


def _cbr(i: int, o: int, stride: int = 1) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(i, o, 3, stride, 1, bias=False), nn.BatchNorm2d(o), nn.ReLU(inplace=True))


class RetinaImageCNN(StandardisedTargets):
    """What the foveation and limb vision CNNs share: the ONV's foveated image (and its augmentations),
    a 4-stage CNN over it, and the targets' standardisation buffers (``outputs`` values)."""

    def __init__(self, photoreceptor_angles: np.ndarray, size: int, channels: int, max_ecc_deg: float, power: float,
                 outputs: int):
        super().__init__()
        a = np.asarray(photoreceptor_angles, dtype=np.float64)
        if a.ndim != 2 or a.shape[1] != 2 or len(a) < 16 or not np.isfinite(a).all():
            raise ValueError(f"photoreceptor_angles: expected finite values of shape (P >= 16, 2), got {a.shape}")
        if not (isinstance(channels, int) and channels >= 1):
            raise ValueError(f"channels: expected a positive int, got {channels!r}")
        self.warp = FoveatedImage(size, max_ecc_deg, power)
        self.P = len(a)
        self._dirs = gaze_directions(a)
        self._binnings: dict[int, tuple] = {0: self.warp.binning(self._dirs, np.eye(3))}
        self._matrices = _Rebuilt()  # :meth:`binning_matrix`'s, per (augmentations, device)
        self.stage_channels = [channels, 2 * channels, 4 * channels, 6 * channels]
        c = self.stage_channels
        self.stem = nn.Sequential(_cbr(3, c[0], 2), _cbr(c[0], c[0]))
        self.down = nn.ModuleList([nn.Sequential(_cbr(c[i], c[i + 1], 2), _cbr(c[i + 1], c[i + 1])) for i in range(3)])
        self.init_target_norm(outputs)
        #: the precision of the CNN in training (:data:`PRECISIONS`; set by the training task from its config's
        #: ``precision``); evaluation and inference are always float32
        self.train_precision = "float32"

    def compute(self, device: torch.device):
        """The context the CNN's layers run in: bfloat16 autocast while training at a ``train_precision`` that
        resolves to it on ``device`` (:func:`training_autocast`), else nothing (float32)."""
        dt = training_autocast(self.train_precision, device.type) if self.training else None
        return torch.autocast(device.type, dtype=dt) if dt is not None else contextlib.nullcontext()

    def binning(self, k: int) -> tuple[Tensor, Tensor, Tensor]:
        if k not in self._binnings:
            self._binnings[k] = self.warp.binning(self._dirs, transform_matrix(k))
        return self._binnings[k]

    def binning_matrix(self, ks: tuple[int, ...], device: torch.device) -> Tensor:
        """The sparse (CSR) [len(ks) * size^2, P] matrix that bins an ONV channel into the images of the
        augmentations ``ks``, one below the other (rows v * size^2 to (v + 1) * size^2 - 1: ``ks[v]``'s
        :meth:`binning`); built once per tuple and device. A CSR product sums each pixel's photoreceptors in a
        row of its own: on this project's 2-core CPU 5.6x faster than an ``index_add_`` of the entries for the
        8 views of one ONV, 2.1-2.5x for 64 ONVs (``bench readout``)."""
        key = (tuple(int(k) for k in ks), str(device))
        if key not in self._matrices:
            parts = [self.binning(k) for k in key[0]]
            n2 = self.warp.size ** 2
            idx = torch.stack([torch.cat([pix + v * n2 for v, (pix, _, _) in enumerate(parts)]),
                               torch.cat([pr for _, pr, _ in parts])])
            coo = torch.sparse_coo_tensor(idx, torch.cat([w for _, _, w in parts]), (len(parts) * n2, self.P),
                                          check_invariants=True).coalesce()
            with warnings.catch_warnings():  # "sparse CSR support is in beta": used here for sparse @ dense only
                warnings.simplefilter("ignore", UserWarning)
                self._matrices[key] = coo.to_sparse_csr().to(device)
        return self._matrices[key]

    def image(self, x: Tensor, k=0) -> Tensor:
        """ONV inputs [B, 3P] -> the foveated image [B, 3, size, size] of augmentation ``k`` (an int), or
        with a list of ints, the batch split into that many consecutive groups (``torch.tensor_split``),
        group g binned through augmentation ``k[g]``. channels_last."""
        if not isinstance(k, (int, np.integer)):
            img = torch.cat([self.image(part, kk) for part, kk in zip(torch.tensor_split(x, len(k)), k)])
            return img.contiguous(memory_format=torch.channels_last)  # (cat of batches of 1 may return NCHW)
        return self.view_images(x, [int(k)])

    def view_images(self, x: Tensor, ks: list[int]) -> Tensor:
        """ONV inputs [B, 3P] -> the foveated images of every augmentation in ``ks``, view by view: [len(ks) * B,
        3, size, size], rows v * B to (v + 1) * B - 1 the images of ``ks[v]``, binned by one sparse product
        (:meth:`binning_matrix`), channels_last."""
        if x.ndim != 2 or x.shape[1] != 3 * self.P:
            raise ValueError(f"onv: expected [B, {3 * self.P}], got {tuple(x.shape)}")
        b, n, v = x.shape[0], self.warp.size, len(ks)
        cols = x.reshape(b, self.P, 3).permute(1, 0, 2).reshape(self.P, b * 3).float()
        # float32 under any caller's autocast (no bfloat16 CSR product)
        with torch.autocast(x.device.type, enabled=False):
            img = self.binning_matrix(tuple(ks), x.device) @ cols  # [V n^2, B*3]
        # [V, n, n, B, 3] -> [V, B, n, n, 3] (the one copy) -> [V B, 3, n, n] with channels_last strides
        return img.reshape(v, n, n, b, 3).permute(0, 3, 1, 2, 4).reshape(v * b, n, n, 3).permute(0, 3, 1, 2)

    def features(self, img: Tensor) -> list[Tensor]:
        """The four stages' feature maps (1/2, 1/4, 1/8, 1/16 of the image's size)."""
        feats = [self.stem(img)]
        for d in self.down:
            feats.append(d(feats[-1]))
        return feats


class RetinaCNNFoveationNet(RetinaImageCNN):
    """ONV [B, 3P] (standardised log responses, :func:`warp_vision.nn.trained.net_input`) -> standardised
    (yaw, pitch) [B, 2] of the ball: resampling to a foveated image, a CNN with a feature pyramid, a
    heat map and a local soft-arg-max (module docstring)."""

    def __init__(self, photoreceptor_angles: np.ndarray, size: int = IMAGE_SIZE, channels: int = 16,
                 max_ecc_deg: float = 50.0, power: float = 1.5, window: int = 5, window_deg: float = WINDOW_DEG,
                 views: int = 1):
        consensus_transforms(views)  # (validates)
        if not (isinstance(window, int) and window >= 1 and window % 2 == 1):
            raise ValueError(f"window: expected an odd positive int, got {window!r}")
        if not 0 <= window_deg < 90:
            raise ValueError(f"window_deg: expected degrees in [0, 90), got {window_deg!r}")
        super().__init__(photoreceptor_angles, size, channels, max_ecc_deg, power, outputs=2)
        self.window, self.window_deg, self.views = window, float(window_deg), int(views)
        lat = 2 * channels
        self.lateral = nn.ModuleList(nn.Conv2d(ch, lat, 1) for ch in self.stage_channels)
        self.smooth = _cbr(lat, lat)
        self.heat = nn.Conv2d(lat, 1, 1)
        cells = size // 2
        self.register_buffer("cell_dirs",
                             torch.as_tensor(self.warp.uv_to_dirs(self.warp.grid_uv(cells)), dtype=torch.float32),
                             persistent=False)

    def logits(self, img: Tensor) -> Tensor:
        """Heat-map logits [B, cells^2] (float32) of a foveated image."""
        with self.compute(img.device):
            feats = self.features(img)
            p = self.lateral[-1](feats[-1])
            for i in range(len(feats) - 2, -1, -1):
                p = self.lateral[i](feats[i]) + nn.functional.interpolate(p, size=feats[i].shape[-2:], mode="nearest")
            return self.heat(self.smooth(p)).flatten(1).float()

    def read_out(self, logits: Tensor) -> Tensor:
        """(yaw, pitch) [B, 2] rad: the soft-arg-max of the heat map over the cells near its peak: within
        ``window`` cells of it (the coarse periphery) or within ``window_deg`` degrees of its direction
        (the magnified centre, where a near ball spans many cells and its heat is a plateau)."""
        return gaze_angles(self._peak_weights(logits, logits.detach().argmax(1)) @ self.cell_dirs)

    def _near_peak(self, peak: Tensor) -> Tensor:
        """[B, cells] bool: the cells of :meth:`read_out`'s window around each of the cells ``peak`` [B]."""
        m = self.warp.size // 2
        r = self.window // 2
        cell = torch.arange(m * m, device=peak.device)
        rows = (cell[None] // m - (peak // m)[:, None]).abs() <= r
        near_cells = rows & ((cell[None] % m - (peak % m)[:, None]).abs() <= r)
        return near_cells | (self.cell_dirs[peak] @ self.cell_dirs.T >= math.cos(math.radians(self.window_deg)))

    def _peak_weights(self, logits: Tensor, peak: Tensor) -> Tensor:
        return logits.masked_fill(~self._near_peak(peak), float("-inf")).softmax(1)

    def candidates(self, x: Tensor, k: int = 4, min_sep_deg: float = 4.0) -> tuple[Tensor, Tensor]:
        """The ``k`` strongest peaks of the plain image's heat map for ONV inputs ``x`` [B, 3P] (as
        :meth:`forward` reads them): (directions [B, k, 2] (yaw, pitch) rad, each the soft-arg-max around its
        peak as :meth:`read_out`'s; scores [B, k], the share of the map's softmax within the peak's window).
        Each peak after the first is the highest cell farther than ``min_sep_deg`` from every earlier peak;
        where none is left, the direction is NaN and the score 0."""
        if not (isinstance(k, (int, np.integer)) and k >= 1):
            raise ValueError(f"k: expected a positive int, got {k!r}")
        logits = self.logits(self.image(x, 0)).detach()
        prob = logits.softmax(1)
        free = torch.ones_like(logits, dtype=torch.bool)
        cos_sep = math.cos(math.radians(min_sep_deg))
        dirs, scores = [], []
        for _ in range(int(k)):
            masked = logits.masked_fill(~free, float("-inf"))
            peak = masked.argmax(1)
            alive = torch.isfinite(masked.max(1).values)
            near = self._near_peak(peak)
            d = gaze_angles(self._peak_weights(logits, peak) @ self.cell_dirs)
            dirs.append(torch.where(alive[:, None], d, torch.full_like(d, float("nan"))))
            scores.append(torch.where(alive, (prob * near).sum(1), torch.zeros_like(alive, dtype=prob.dtype)))
            free &= (self.cell_dirs[peak] @ self.cell_dirs.T) < cos_sep
        return torch.stack(dirs, 1), torch.stack(scores, 1)

    def forward(self, x: Tensor, transform=0, with_logits: bool = False):
        """Standardised (yaw, pitch) [B, 2] of the ball in the image of augmentation ``transform`` (an int,
        or a list of ints for consecutive groups: :meth:`image`); with ``with_logits`` also the heat map's
        logits (for :meth:`heatmap_loss`)."""
        if not self.training and self.views > 1 and not with_logits and isinstance(transform, int) and transform == 0:
            return (self.consensus(x) - self.target_mean) / self.target_std
        logits = self.logits(self.image(x, transform))
        out = (self.read_out(logits) - self.target_mean) / self.target_std
        return (out, logits) if with_logits else out

    def consensus(self, x: Tensor, max_images: int = 256) -> Tensor:
        """(yaw, pitch) [B, 2] rad of the ball by the consensus of ``self.views`` views (:data:`CONSENSUS_VIEWS`):
        each view's direction mapped back to the eye frame; the view with the most others within
        :data:`CONSENSUS_DEG` (the first on a tie, the plain image) and those others are averaged. At most
        ``max_images`` images go through the CNN at once."""
        ks = consensus_transforms(self.views)
        b = x.shape[0]
        per = max(1, max_images // max(b, 1))
        dirs = []
        for g in range(0, len(ks), per):
            group = ks[g : g + per]
            ang = self.read_out(self.logits(self.view_images(x, group)))  # each view's frame
            m = torch.as_tensor(np.stack([transform_matrix(k) for k in group]), dtype=ang.dtype, device=ang.device)
            d = gaze_directions(ang).reshape(len(group), b, 3)
            dirs.append(torch.einsum("vbj,vij->vbi", d, m))  # back to the eye frame: m @ d
        return consensus_of(torch.cat(dirs).permute(1, 0, 2))

    def transform_targets(self, target: Tensor, k: int) -> Tensor:
        """(yaw, pitch) [B, 2] rad as seen in the image of augmentation ``k`` (the world mapped by m^-1)."""
        m = torch.as_tensor(transform_matrix(k), dtype=torch.float64)
        d = torch.as_tensor(gaze_directions(target.double().cpu().numpy())) @ m  # rows (m^T d)^T
        return gaze_angles(d).to(target)

    def heatmap_loss(self, logits: Tensor, target: Tensor) -> Tensor:
        """Cross-entropy of the heat map against the cell nearest each true direction ``target`` [B, 2] rad."""
        d = torch.as_tensor(gaze_directions(target.double().cpu().numpy()), dtype=torch.float32, device=logits.device)
        nearest = (d @ self.cell_dirs.T).argmax(1)
        return nn.functional.cross_entropy(logits, nearest)


class RetinaImageRegression(RetinaImageCNN):
    """The foveated image and CNN of :class:`RetinaImageCNN`, its last stage's map flattened (where things
    are matters) into a hidden layer of ``hidden`` units and a linear read-out of ``outputs`` values."""

    def __init__(self, photoreceptor_angles: np.ndarray, size: int, channels: int, max_ecc_deg: float, power: float,
                 hidden: int, outputs: int):
        super().__init__(photoreceptor_angles, size, channels, max_ecc_deg, power, outputs=outputs)
        last = self.stage_channels[-1] * (size // 16) ** 2
        self.head = nn.Sequential(nn.Flatten(), nn.Linear(last, hidden), nn.ReLU(inplace=True),
                                  nn.Linear(hidden, outputs))

    def forward(self, x: Tensor, transform=0) -> Tensor:
        img = self.image(x, transform)
        with self.compute(img.device):
            return self.head(self.features(img)[-1]).float()


class RetinaCNNLimbNet(RetinaImageRegression):
    """ONV [B, 3P] -> standardised hand-to-ball discrepancies [B, 6] (``ball - hand`` of the left and of
    the right arm, eye frame; the limb vision task, :mod:`warp_vision.train.limb`): a
    :class:`RetinaImageRegression` of the whole foveated image."""

    def __init__(self, photoreceptor_angles: np.ndarray, size: int = IMAGE_SIZE, channels: int = 16,
                 max_ecc_deg: float = 50.0, power: float = 1.5, hidden: int = 128):
        super().__init__(photoreceptor_angles, size, channels, max_ecc_deg, power, hidden, outputs=6)

    @staticmethod
    def transform_targets(target: Tensor, k: int) -> Tensor:
        """Discrepancies [B, 6] as seen in the image of augmentation ``k``: each arm's vector mapped by
        m^-1; a mirrored image shows the left arm where the right one was, so the arms swap."""
        m = torch.as_tensor(transform_matrix(k), dtype=target.dtype, device=target.device)
        t = target.reshape(-1, 2, 3) @ m  # rows (m^T t)^T
        if k % 2:
            t = t.flip(1)
        return t.reshape(-1, 6)


class RetinaCNNRangeNet(RetinaImageRegression):
    """ONV [B, 3P] -> the standardised log distance (m) [B, 1] from the eye to a ball near the line of
    sight (within :data:`RANGE_GATE_DEG`): the limb vision nets' depth. The image is the foveal
    :data:`RANGE_ECC_DEG` at nearly uniform scale, where a ball of known size shows its distance by its
    apparent size (0.76 deg across at 3 m for the cannon's 4 cm ball, 4.6 deg at 0.5 m); a
    :class:`RetinaImageRegression` with one output. A turn or mirror of the world leaves a distance as it
    is, so every augmentation keeps the target."""

    def __init__(self, photoreceptor_angles: np.ndarray, size: int = RANGE_IMAGE_SIZE, channels: int = 16,
                 max_ecc_deg: float = RANGE_ECC_DEG, power: float = RANGE_POWER, hidden: int = 128):
        super().__init__(photoreceptor_angles, size, channels, max_ecc_deg, power, hidden, outputs=1)

    @staticmethod
    def transform_targets(target: Tensor, k: int) -> Tensor:
        """A distance is the same in a turned or mirrored world."""
        return target
