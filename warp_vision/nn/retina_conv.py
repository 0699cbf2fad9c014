"""A convolution on the irregular, foveated retina: units that share their weights across the retina.

A liNet (:mod:`warp_vision.nn.linet`) gives every connection its own weight. That is what makes it
cheap, and what makes it learn "where is the brightest blob" from a few thousand ONVs; but a target that
is defined by its *shape* (an ordinary ball among furniture, lamps and arms, generator v8) must then be
learnt anew at every place on the retina, and a liNet trained on 8,000 v8 ONVs memorises its training
set without generalising (docs/RESULTS.md has the measurement). This module is the weight-shared alternative:

- **Sites.** Layer 0's sites are the photoreceptors (3 channels each: the ONV's element 3p + c). Layer
  h's sites are every ``stride``-th of layer h - 1's, drawn with a seeded generator, so each layer keeps
  the retina's foveated density; a site keeps its photoreceptor's position and visual direction.
- **Stencil.** Each site of layer h reads 9 sites of layer h - 1: its own place and 8 points around it at
  one local spacing (the distance to its 6th nearest site of layer h - 1) in the 8 compass directions of
  the retinal domain, each the layer h - 1 site nearest that point. On the foveated layout the stencil
  shrinks toward the fovea like the photoreceptor spacing, as a 3 x 3 convolution of stride 2 would on
  a log-polar image.
- **Channels.** Layer h has C_h channels per site; unit (site, c) = ReLU(bias_c + sum over the 9 stencil
  points and the C_{h-1} input channels of W_h[c, point, channel] x): one 3 x 3 x C_{h-1} kernel per
  output channel, shared by every site.

The forward pass is an ``index_select`` of the stencil and one matrix product per layer (torch; no
custom kernel). :class:`RetinaConvFoveationNet` reads it out with a learnt saliency channel per layer
whose spatial soft-argmax over the sites' visual directions votes for the gaze.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from scipy.spatial import cKDTree
from torch import Tensor, nn

from warp_vision.frames import check_positions
from warp_vision.nn.standardise import StandardisedTargets

STENCIL = 9  # the site itself and 8 compass points


def site_counts(n_sites: int, layers: int, stride: float) -> list[int]:
    """[N_0 = n_sites, N_1, ..., N_H]: each layer keeps floor(N_(h-1) / stride) sites of the layer below,
    which needs 7 sites at least (a site's spacing is its 6th neighbour's distance). A ValueError names
    the first layer left without sites (checked by the training configs before any data is rendered)."""
    if not (isinstance(stride, (int, float, np.integer, np.floating)) and math.isfinite(stride) and stride > 1):
        raise ValueError(f"stride: expected a number > 1, got {stride!r}")
    counts = [int(n_sites)]
    for h in range(1, layers + 1):
        n = int(counts[-1] // stride)
        if n < 1 or counts[-1] < 7:
            raise ValueError(f"layers: layer {h} would have no sites ({counts[-1]} sites in layer {h - 1}, stride "
                             f"{stride})")
        counts.append(n)
    return counts


def stencil_layers(site_xy: np.ndarray, layers: int, stride: float, seed: int = 0) -> list[dict]:
    """The sites and stencils of layers 1..H over photoreceptors at ``site_xy`` [P, 2] (retinal domain).

    Returns per layer {"sites": [N_h] indices into layer h - 1's sites, "stencil": [N_h, 9] indices into
    layer h - 1's sites, "photoreceptor": [N_h] the photoreceptor each site sits on}."""
    xy = check_positions("site_xy", site_xy)
    if isinstance(layers, bool) or not isinstance(layers, (int, np.integer)) or layers < 1:
        raise ValueError(f"layers: expected an int >= 1, got {layers!r}")
    counts = site_counts(len(xy), layers, stride)
    rng = np.random.default_rng(int(seed))
    ang = np.linspace(0, 2 * np.pi, 8, endpoint=False)
    compass = np.stack([np.cos(ang), np.sin(ang)], 1)
    prev_xy, prev_pr = xy, np.arange(len(xy))
    out = []
    for n in counts[1:]:
        sites = np.sort(rng.choice(len(prev_xy), size=n, replace=False))
        tree = cKDTree(prev_xy)
        dist, _ = tree.query(prev_xy[sites], k=7)
        spacing = np.maximum(dist[:, 6], 1e-9)
        points = prev_xy[sites][:, None, :] + spacing[:, None, None] * compass[None]  # [n, 8, 2]
        _, around = tree.query(points.reshape(-1, 2), k=1)
        stencil = np.concatenate([sites[:, None], around.reshape(n, 8)], axis=1)
        out.append({"sites": sites, "stencil": stencil.astype(np.int64), "photoreceptor": prev_pr[sites]})
        prev_xy, prev_pr = prev_xy[sites], prev_pr[sites]
    return out


def channel_plan(first: int, layers: int, cap: int = 64) -> list[int]:
    """C_1..C_H: ``first`` channels, doubling per layer up to ``cap``."""
    return [min(cap, first * 2**h) for h in range(layers)]


class RetinaConv(nn.Module):
    """The backbone: H weight-shared stencil layers (ReLU) over an ONV [B, 3P] -> each layer's maps
    [B, N_h, C_h]. Buffers ``stencil_h`` (long) and ``photoreceptor_h`` are in ``state_dict``."""

    def __init__(self, site_xy: np.ndarray, layers: int = 4, stride: float = 4, channels: int = 16, seed: int = 0,
                 in_channels: int = 3):
        super().__init__()
        plan = stencil_layers(site_xy, layers, stride, seed)
        self.in_channels = int(in_channels)
        self.sites = len(site_xy)
        self.channels = channel_plan(int(channels), layers)
        self.layer_sites = [len(site_xy)] + [len(p["sites"]) for p in plan]
        for h, p in enumerate(plan, start=1):
            self.register_buffer(f"stencil_{h}", torch.from_numpy(p["stencil"]))
            self.register_buffer(f"photoreceptor_{h}", torch.from_numpy(p["photoreceptor"].astype(np.int64)))
        c_in = [self.in_channels] + self.channels[:-1]
        self.convs = nn.ModuleList(nn.Linear(STENCIL * a, b) for a, b in zip(c_in, self.channels))
        # batch normalisation of each channel over the batch and the sites, before the ReLU
        self.norms = nn.ModuleList(nn.BatchNorm1d(c) for c in self.channels)
        for conv in self.convs:  # He initialisation for ReLU
            nn.init.normal_(conv.weight, 0.0, math.sqrt(2.0 / conv.in_features))
            nn.init.zeros_(conv.bias)

    @property
    def num_layers(self) -> int:
        return len(self.convs)

    def forward(self, onv: Tensor) -> list[Tensor]:
        B = onv.shape[0]
        if onv.dim() != 2 or onv.shape[1] != self.in_channels * self.sites:
            raise ValueError(f"onv: expected shape [B, {self.in_channels * self.sites}], got {tuple(onv.shape)}")
        x = onv.reshape(B, self.sites, self.in_channels)
        maps = []
        for h, (conv, norm) in enumerate(zip(self.convs, self.norms), start=1):
            st = getattr(self, f"stencil_{h}")
            g = x.index_select(1, st.reshape(-1)).reshape(B, st.shape[0], -1)  # [B, N_h, 9 C_{h-1}]
            y = conv(g)
            x = torch.relu(norm(y.reshape(-1, y.shape[-1])).reshape(y.shape))
            maps.append(x)
        return maps


class RetinaConvFoveationNet(StandardisedTargets):
    """ONV [B, 3P] -> standardised (yaw, pitch): a :class:`RetinaConv` backbone whose layers h >= 2 each
    have a saliency channel (a learnt 1 x 1 mix of their channels); each layer's soft-argmax of its
    saliency over its sites' visual directions is a vote, and a linear layer (starting as the votes'
    mean) combines the votes, standardised like the targets."""

    def __init__(self, backbone: RetinaConv, photoreceptor_angles: np.ndarray, first_vote: int = 2):
        super().__init__()
        a = torch.as_tensor(np.asarray(photoreceptor_angles, dtype=np.float32))
        if a.shape != (backbone.sites, 2) or not torch.isfinite(a).all():
            raise ValueError(f"photoreceptor_angles: expected finite values of shape ({backbone.sites}, 2), got "
                             f"{tuple(a.shape)}")
        self.backbone = backbone
        self.voting = list(range(max(1, first_vote), backbone.num_layers + 1))
        self.init_target_norm(2)
        self.saliency = nn.ModuleList(nn.Linear(backbone.channels[h - 1], 1) for h in self.voting)
        self.log_temperature = nn.Parameter(torch.zeros(len(self.voting)))
        for k, h in enumerate(self.voting):
            self.register_buffer(f"directions_{k}", a[getattr(backbone, f"photoreceptor_{h}")].clone())
        self.head = nn.Linear(2 * len(self.voting), 2)
        with torch.no_grad():
            self.head.weight.zero_()
            self.head.bias.zero_()
            for k in range(len(self.voting)):
                self.head.weight[:, 2 * k:2 * k + 2] = torch.eye(2) / len(self.voting)

    def saliency_logits(self, onv: Tensor) -> list[Tensor]:
        """Each voting layer's saliency over its sites [B, N_h] (the soft-argmax's logits)."""
        maps = self.backbone(onv)
        return [self.saliency[k](maps[h - 1]).squeeze(-1) * self.log_temperature[k].exp() for k,
                h in enumerate(self.voting)]

    def votes(self, onv: Tensor, logits: list[Tensor] | None = None) -> list[Tensor]:
        """Each voting layer's gaze vote [B, 2] (radians)."""
        logits = self.saliency_logits(onv) if logits is None else logits
        return [torch.softmax(s, dim=1) @ getattr(self, f"directions_{k}") for k, s in enumerate(logits)]

    def forward(self, onv: Tensor, with_logits: bool = False):
        """Standardised (yaw, pitch) [B, 2]; with ``with_logits``, also the saliency logits (for
        :meth:`heatmap_loss`)."""
        logits = self.saliency_logits(onv)
        z = [(v - self.target_mean) / self.target_std for v in self.votes(onv, logits)]
        out = self.head(torch.cat(z, dim=1))
        return (out, logits) if with_logits else out

    def heatmap_loss(self, logits: list[Tensor], target: Tensor) -> Tensor:
        """Cross-entropy of each voting layer's saliency against the site nearest the true direction
        ``target`` [B, 2] (radians), averaged over the layers: dense supervision of where the ball is, as
        keypoint detectors train their heat maps, beside the soft-argmax's regression."""
        loss = 0.0
        for k, s in enumerate(logits):
            d = getattr(self, f"directions_{k}")
            nearest = torch.cdist(target.to(d), d).argmin(dim=1)
            loss = loss + torch.nn.functional.cross_entropy(s, nearest)
        return loss / len(logits)
