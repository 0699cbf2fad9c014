"""The foveal verification net: an eye's central field -> "is the ball at my fovea, and how far off?".

Input: the photoreceptors within ``central_deg`` of the fovea (``central``, indices into the eye's
retina), standardised as every ONV net's input (:func:`warp_vision.nn.trained.net_input`). Output [B, 3]:
the logit that the ball's centre lies within :data:`warp_vision.data.verification.ACCEPT_DEG` of the
optical axis, and the ball's (yaw, pitch) in the eye frame, in degrees (the corrective saccade).

Two backbones (``model``):

- ``"linet"``: the paper's liNet (a weight of its own for every connection) on the central field's
  photoreceptor positions. At the fovea, where the candidate always sits, weights of their own are at
  home, as in face recognition.
- ``"cnn"``: the central field binned onto a nearly uniform image (``power`` 1.2) and the retina CNN's
  4-stage backbone with a dense read-out (:class:`warp_vision.nn.retina_cnn.RetinaImageRegression`).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor, nn

#: the verifier's backbones
VERIFY_MODELS = ("cnn", "linet")


class FovealVerifier(nn.Module):
    """Central field [B, 3N] -> [B, 3] (logit, yaw deg, pitch deg); see the module docstring. ``central``: the
    N photoreceptor indices of the eye's retina it reads (a buffer, so a checkpoint carries them)."""

    def __init__(self, model: str, central: np.ndarray, photoreceptor_angles: np.ndarray, photoreceptor_xy: np.ndarray,
                 central_deg: float, seed: int = 0, channels: int = 16, image_size: int = 48, layers: int = 3,
                 receptive_field: int = 20, reduction: int = 4):
        super().__init__()
        if model not in VERIFY_MODELS:
            raise ValueError(f"model: expected one of {VERIFY_MODELS}, got {model!r}")
        central = np.asarray(central, dtype=np.int64)
        if central.ndim != 1 or len(central) < 16:
            raise ValueError(f"central: expected at least 16 photoreceptor indices, got shape {central.shape}")
        self.model, self.central_deg = model, float(central_deg)
        self.register_buffer("central", torch.as_tensor(central))
        #: the logit above which the ball is accepted (training fits it to reject 1% of the balls)
        self.register_buffer("threshold", torch.tensor(0.0))
        torch.manual_seed(seed)
        if model == "cnn":
            from warp_vision.nn.retina_cnn import RetinaImageRegression

            self.backbone = RetinaImageRegression(np.asarray(photoreceptor_angles)[central], image_size, channels,
                                                  central_deg, 1.2, hidden=64, outputs=3)
        else:
            from warp_vision.nn.connectivity import onv_positions
            from warp_vision.nn.heads import foveation_net

            self.backbone = foveation_net("linet", onv_positions(np.asarray(photoreceptor_xy)[central]), layers,
                                          receptive_field, reduction, seed, outputs=3)

    @property
    def N(self) -> int:
        return int(self.central.numel())

    def forward(self, x: Tensor, transform=0) -> Tensor:
        """[B, 3]: the logit and the offset (deg). ``transform`` (the CNN, in training): the augmentation(s) of
        :meth:`warp_vision.nn.retina_cnn.RetinaImageCNN.image`, whose offsets are :func:`transform_offsets`'."""
        if x.ndim != 2 or x.shape[1] != 3 * self.N:
            raise ValueError(f"central field: expected [B, {3 * self.N}] (3 x {self.N:,} photoreceptors), got "
                             f"{tuple(x.shape)}")
        if self.model == "cnn":
            return self.backbone(x, transform)
        if transform != 0:
            raise ValueError("transform: the liNet verifier has no augmentation")
        return self.backbone(x)

    def verdict(self, x: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """(accepted [B] bool, probability [B], the ball's offset [B, 2] (yaw, pitch) rad) of central fields
        ``x`` (standardised as :meth:`forward`'s)."""
        out = self.forward(x)
        return out[:, 0] >= self.threshold, torch.sigmoid(out[:, 0]), torch.deg2rad(out[:, 1:])

    def field(self, onv: Tensor) -> Tensor:
        """The central field [B, 3N] of full ONVs [B, 3P] (photoreceptor-major, 3 channels each)."""
        idx = (3 * self.central[:, None] + torch.arange(3, device=self.central.device)).reshape(-1)
        return onv[:, idx.to(onv.device)]


def transform_offsets(offset: Tensor, k: int) -> Tensor:
    """Offsets (yaw, pitch) [B, 2] (any angle unit's radians) as seen in the image of augmentation ``k``."""
    from warp_vision.frames import gaze_angles, gaze_directions
    from warp_vision.nn.retina_cnn import transform_matrix

    m = torch.as_tensor(transform_matrix(k), dtype=torch.float64)
    return gaze_angles(torch.as_tensor(gaze_directions(offset.double().cpu().numpy())) @ m).to(offset)


def verify_net(spec: dict) -> FovealVerifier:
    """The untrained verifier a net spec describes (kind "verify")."""
    return FovealVerifier(spec["model"], _array(spec["central"]).astype(np.int64), _array(spec["photoreceptor_angles"]),
                          _array(spec["photoreceptor_xy"]), spec["central_deg"], spec["seed"], spec.get("channels", 16),
                          spec.get("image_size", 48), spec.get("layers", 3), spec.get("receptive_field", 20),
                          spec.get("reduction", 4))


def _array(x) -> np.ndarray:
    return x.numpy() if torch.is_tensor(x) else np.asarray(x)
