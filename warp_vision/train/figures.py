"""Figures of a foveation run: loss curves (Fig. 6), predicted vs true angles, retina images."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from matplotlib.figure import Figure


def retinal_image_point_deg(yaw_pitch: np.ndarray, eye) -> np.ndarray:
    """Where a point seen in direction (yaw, pitch) [N, 2] (rad, eye frame) images on the retina:
    retinal-domain (x, y) in degrees (the optics invert the image)."""
    from warp_vision.train.loop import directions

    u = directions(torch.as_tensor(yaw_pitch, dtype=torch.float64)).numpy()
    field = np.degrees(np.arccos(np.clip(u[:, 2], -1, 1)))
    ecc = np.linspace(0.0, np.radians(95.0), 400)
    ang = eye.field_angle_deg(ecc)
    ok = np.isfinite(ang)
    rho = np.degrees(np.interp(field, ang[ok], ecc[ok]))
    phi = np.arctan2(u[:, 1], u[:, 0]) + np.pi
    return np.stack([rho * np.cos(phi), rho * np.sin(phi)], axis=1)


def plot_curves(histories: dict, title: str = "foveation training") -> Figure:
    """Training and validation MSE per epoch for one or more runs ({label: history})."""
    fig = Figure(figsize=(6.5, 4.2))
    ax = fig.add_subplot(1, 1, 1)
    for i, (label, hist) in enumerate(histories.items()):
        ep = [h["epoch"] for h in hist]
        c = f"C{i}"
        ax.plot(ep, [h["train_mse"] for h in hist], "-", color=c, label=f"{label} train")
        ax.plot(ep, [h["val_mse"] for h in hist], "--", color=c, label=f"{label} validation")
    ax.axhline(0.01, color="0.6", lw=0.8, ls=":")
    ax.set_yscale("log")
    ax.set_xlabel("epoch")
    ax.set_ylabel("MSE (standardised targets)")
    ax.set_title(title)
    ax.legend()
    return fig


def write_figures(out: Path, history, retina, onv16, target, idx, pred, cfg) -> None:
    from warp_vision import viz
    from warp_vision.data.foveation import make_eye

    figdir = Path(out) / "figures"
    figdir.mkdir(exist_ok=True)
    plot_curves({cfg.model: history}).savefig(figdir / "loss_curves.png", dpi=120, bbox_inches="tight")
    true = target[torch.as_tensor(idx)].numpy()
    p = pred.numpy()
    fig = Figure(figsize=(9, 4.2))
    for k, name in enumerate(("yaw", "pitch")):
        ax = fig.add_subplot(1, 2, k + 1)
        ax.scatter(np.degrees(true[:, k]), np.degrees(p[:, k]), s=4, alpha=0.6)
        lim = np.degrees(np.abs(true[:, k]).max()) * 1.05 if len(true) else 1
        ax.plot([-lim, lim], [-lim, lim], color="0.5", lw=0.8)
        ax.set_xlabel(f"true {name} (deg)")
        ax.set_ylabel(f"predicted {name} (deg)")
        ax.set_aspect("equal")
    fig.suptitle("held-out ONVs: predicted vs true eye rotation")
    fig.savefig(figdir / "predicted_vs_true.png", dpi=120, bbox_inches="tight")
    eye = make_eye(cfg.data_config())
    n = min(4, len(idx))
    fig = Figure(figsize=(4.2 * n, 4.4))
    tp = retinal_image_point_deg(true[:n], eye)
    pp = retinal_image_point_deg(p[:n], eye)
    for k in range(n):
        ax = fig.add_subplot(1, n, k + 1)
        viz.plot_onv(retina, onv16[int(idx[k])].float(), ax=ax, mark=[tuple(tp[k]), tuple(pp[k])],
                     title="ball image: + true, x predicted")
    fig.savefig(figdir / "retina_images.png", dpi=110, bbox_inches="tight")
