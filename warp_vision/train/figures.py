"""Figures of training runs: foveation (Fig. 6 curves, predicted vs true angles, retina images) and face recognition
(Figs. 11 and 12)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from matplotlib.figure import Figure

from warp_vision.frames import gaze_directions


def retinal_image_point_deg(yaw_pitch: np.ndarray, eye) -> np.ndarray:
    """Where a point seen in direction (yaw, pitch) [N, 2] (rad, eye frame) images on the retina:
    retinal-domain (x, y) in degrees (the optics invert the image)."""
    u = gaze_directions(np.asarray(yaw_pitch, dtype=np.float64))
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
    ax.axhline(0.01, color="0.6", lw=0.8, ls=":", label="0.01 (the paper's foveation nets' training MSE)")
    ax.set_yscale("log")
    ax.set_xlabel("epoch")
    ax.set_ylabel("MSE (standardised targets)")
    ax.set_title(title)
    # below the axes, where it hides no curve (a run's validation curve may lie anywhere)
    ax.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.14), ncol=2, frameon=False)
    return fig


def plot_misses(rows: list[dict], title: str) -> Figure:
    """:func:`warp_vision.train.foveation.miss_breakdown`'s rows, a panel per group (the scene flags' yes and
    no rows together in one): the share of each bin's balls more than 5 degrees off, on one scale, with
    the share of all the balls dotted; the group "estimate lands on" as each class's share of the misses, with
    the share landing there by chance marked where the rows carry it."""
    panels: dict[str, list] = {}
    for r in rows:
        flag = r["bin"] in ("yes", "no")
        label = f"{r['group']}: {r['bin']} ({r['n']:,})" if flag else f"{r['bin']} ({r['n']:,})"
        panels.setdefault("in the scene" if flag else r["group"], []).append((label, r))
    cols = 2 if len(panels) > 1 else 1
    nrows = (len(panels) + cols - 1) // cols
    tallest = max(len(v) for v in panels.values())
    fig = Figure(figsize=(5.4 * cols, nrows * (0.8 + 0.22 * tallest) + 0.6))
    top = max(100 * r["off"] for r in rows if r["group"] != "estimate lands on")
    first = [r for r in rows if r["group"] == rows[0]["group"]]  # every group covers all the balls
    overall = 100 * sum(r["n"] * r["off"] for r in first) / max(sum(r["n"] for r in first), 1)
    for k, (g, items) in enumerate(panels.items()):
        ax = fig.add_subplot(nrows, cols, k + 1)
        landing = g == "estimate lands on"
        v = [100 * (r["of_misses"] if landing else r["off"]) for _, r in items]
        y = np.arange(len(items))
        ax.barh(y, v, color="C3" if landing else "C0", height=0.7)
        if not landing:
            ax.axvline(overall, color="0.3", lw=0.8, ls=":", label=f"all balls: {overall:.1f}%")
            ax.legend(fontsize=7, loc="lower right")
        elif any("chance" in r for _, r in items):
            ax.scatter([100 * r.get("chance", np.nan) for _, r in items], y, marker="|", s=120, color="k", zorder=3,
                       label="by chance (another ball's direction)")
            ax.legend(fontsize=7, loc="upper right")  # the first rows' bars (the ball) are short
        ax.set_yticks(y, [label for label, _ in items], fontsize=8)
        ax.invert_yaxis()
        ax.set_xlim(0, 100 if landing else 1.05 * max(top, 1.0))
        ax.set_title(g, fontsize=9)
        ax.set_xlabel("share of the misses (%)" if landing else "balls > 5 deg off (%)", fontsize=8)
        ax.tick_params(axis="x", labelsize=8)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout(rect=(0, 0, 1, 0.98))
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


# --------------------------------------------------------------------------------------------------
# active face recognition (the paper's Figs. 11 and 12)


def plot_face_curves(history) -> Figure:
    """Classification (cross-entropy, accuracy) and regression (pose MSE) curves of an AFR run (Fig. 12)."""
    fig = Figure(figsize=(12, 4.2))
    fig.subplots_adjust(wspace=0.45)  # room for the accuracy axis between the panels
    ep = [h["epoch"] for h in history]
    ax = fig.add_subplot(1, 2, 1)
    ax.plot(ep, [h["train_ce"] for h in history], "-", color="C0", label="train cross-entropy")
    ax.plot(ep, [h["val_ce"] for h in history], "--", color="C0", label="validation cross-entropy")
    ax.set_yscale("log")
    ax.set_xlabel("epoch")
    ax.set_ylabel("classification loss")
    acc = ax.twinx()
    acc.plot(ep, [100 * h["val_accuracy"] for h in history], ":", color="C3", label="validation accuracy")
    acc.set_ylabel("validation accuracy (%)", color="C3")
    acc.set_ylim(0, 100)
    ax.legend(loc="center right")
    ax.set_title("identity (FC1)")
    ax = fig.add_subplot(1, 2, 2)
    ax.plot(ep, [h["train_mse"] for h in history], "-", color="C1", label="train")
    ax.plot(ep, [h["val_mse"] for h in history], "--", color="C1", label="validation")
    ax.set_yscale("log")
    ax.set_xlabel("epoch")
    ax.set_ylabel("pose MSE (standardised)")
    ax.set_title("pose (FC2)")
    ax.legend()
    return fig


def write_face_figures(out: Path, history, retina, onv16, ident, pose, idx, test: dict, cfg) -> None:
    """loss_curves.png, confusion_matrix.png, retina_grid.png, pose_error.png in ``out/figures``."""
    from warp_vision import viz

    figdir = Path(out) / "figures"
    figdir.mkdir(exist_ok=True)
    plot_face_curves(history).savefig(figdir / "loss_curves.png", dpi=120, bbox_inches="tight")
    i = torch.as_tensor(idx)
    true_id, pred_id = ident[i].numpy(), test["pred_identity"].numpy()
    n = cfg.identities
    cm = np.zeros((n, n))
    np.add.at(cm, (true_id, pred_id), 1)
    cm /= np.maximum(cm.sum(1, keepdims=True), 1)
    fig = Figure(figsize=(6, 5.2))
    ax = fig.add_subplot(1, 1, 1)
    im = ax.imshow(cm, cmap="viridis", vmin=0, vmax=1)
    fig.colorbar(im, ax=ax, label="share of the true identity's test ONVs")
    ax.set_xlabel("predicted identity")
    ax.set_ylabel("true identity")
    ax.set_title(f"test confusion matrix (accuracy {100 * test['accuracy']:.1f}%)")
    fig.savefig(figdir / "confusion_matrix.png", dpi=120, bbox_inches="tight")
    # retina images across poses (columns) and identities (rows), as in Fig. 11
    data = cfg.data_config()
    values = data.pose_values()
    cols = sorted({int(round(k)) for k in np.linspace(0, len(values) - 1, min(5, len(values)))})
    rows = list(range(min(4, n)))
    mid = len(values) // 2
    fig = Figure(figsize=(3.0 * len(cols), 3.1 * len(rows)))
    for r, who in enumerate(rows):
        for c, k in enumerate(cols):
            s = who * data.poses + k * len(values) + mid
            ax = fig.add_subplot(len(rows), len(cols), r * len(cols) + c + 1)
            viz.plot_onv(retina, onv16[s].float(), ax=ax,
                         title=f"id {who}, yaw {values[k]:+.0f}, pitch {values[mid]:+.0f}")
            lim = 1.5 * np.degrees(np.arctan(0.12 / data.distance_m)) + 5
            ax.set_xlim(-lim, lim)
            ax.set_ylim(-lim, lim)
            ax.set_xlabel("")
            ax.set_ylabel("")
    fig.suptitle("retina images (optical image inverted, as on a retina) across poses and identities")
    fig.savefig(figdir / "retina_grid.png", dpi=90, bbox_inches="tight")
    # pose error as a function of pose
    err = (test["pred_pose"] - pose[i]).abs().mean(1).numpy()
    yaw_k = np.searchsorted(values, pose[i][:, 0].numpy() - 1e-3)
    pit_k = np.searchsorted(values, pose[i][:, 1].numpy() - 1e-3)
    grid = np.full((len(values), len(values)), np.nan)
    tot = np.zeros_like(grid)
    cnt = np.zeros_like(grid)
    np.add.at(tot, (pit_k, yaw_k), err)
    np.add.at(cnt, (pit_k, yaw_k), 1)
    grid[cnt > 0] = tot[cnt > 0] / cnt[cnt > 0]
    fig = Figure(figsize=(6, 5.2))
    ax = fig.add_subplot(1, 1, 1)
    half = (values[1] - values[0]) / 2 if len(values) > 1 else 1
    im = ax.imshow(grid, origin="lower",
                   extent=(values[0] - half, values[-1] + half, values[0] - half, values[-1] + half), cmap="magma")
    fig.colorbar(im, ax=ax, label="mean absolute pose error (deg)")
    ax.set_xlabel("yaw (deg)")
    ax.set_ylabel("pitch (deg)")
    ax.set_title(f"test pose error by pose (mean {test['pose_mae_deg']:.2f} deg)")
    fig.savefig(figdir / "pose_error.png", dpi=120, bbox_inches="tight")
