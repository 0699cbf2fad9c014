"""The limb vision task: one eye's net from its ONV to each arm's hand-to-ball discrepancy, or (``--model
range``, the default preset's) to the ball's distance.

``python -m warp_vision.train limb --eye left|right [--preset smoke|quick|default] [--flag value ...]``

The dataset is :mod:`warp_vision.sim.limb` (the closed loop's world: the body's arms at random postures,
the cannon's ball near a hand or on a shot's path, the eye tracking it). The net
(:func:`warp_vision.nn.heads.limb_vision_net`, or with ``--model cnn``
:class:`warp_vision.nn.retina_cnn.RetinaCNNLimbNet`, trained on turned and mirrored copies) reads the ONV as the
foveation net does and outputs six values: ``ball - hand`` of the left and of the right arm, in the eye frame (m; the
loop turns them into the head and world frames with the eye's orientation, which the oculomotor system knows). The loss
is a Huber loss on the standardised targets, each arm's weighted by ``1 / (near_weight_m + distance)`` so the
balls near a hand, the ones that matter for striking, count most. The best epoch has the smallest
validation median error on balls within 0.6 m of the hand; the summary gives that error (median and 90th
percentile, cm, and relative to the true distance) on the test split and on the held-out set (rooms and
shots training never saw), and by distance.

``--model range`` (:class:`warp_vision.nn.retina_cnn.RetinaCNNRangeNet`): the net reads the ball's
distance from the eye (log m) on the same ONVs, those whose ball lies within
:data:`~warp_vision.nn.retina_cnn.RANGE_GATE_DEG` of the line of sight. The nets above find the ball but
not the hands (docs/RESULTS.md: the hands are dim, thin and peripheral, and every ONV-only net stays at chance on
them), so the loop's limb vision (:class:`warp_vision.sim.limb.LimbVision`) puts the discrepancy
together: the ball's direction from the eye's foveation net, its distance from this net, the hand from
proprioception. The loss is a Huber loss on the standardised log distance; the best epoch has the
smallest validation median relative error; the summary gives the relative and absolute errors by
distance, on the test split and held out.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from warp_vision.nn.trained import fit_input_norm, net_input, set_input_standardisation
from warp_vision.sim.limb import NEAR_M
from warp_vision.sim.limb_errors import discrepancy_errors, range_errors
from warp_vision.train import evaluation, harness
from warp_vision.train.config import onv_dtype_name
from warp_vision.train.config_body import LimbTrainConfig

#: Huber threshold in standardised target units
HUBER_DELTA = 0.1
#: Huber threshold of the ranging loss (standardised log distance)
RANGE_HUBER_DELTA = 0.5


class LimbTask(harness.OnvTask):
    name = "limb"
    config_cls = LimbTrainConfig
    data_module = "warp_vision.sim.limb"
    selection = {"near_median_cm": "min"}

    def __init__(self, cfg, log=print):
        super().__init__(cfg, log)
        self.ranging = cfg.model == "range"
        if self.ranging:
            self.selection = {"depth_median_relative": "min"}

    def dataset_dirs(self):
        """The training set's store and the held-out set's (rooms and shots training never sees) beside it."""
        ddir = Path(self.cfg.data_dir)
        return [ddir, ddir.parent / f"limb-{self.cfg.heldout_config().key()}"]

    def render(self, shard, progress):
        from warp_vision.sim.limb import synthesize

        for d, dcfg in zip(self.dataset_dirs(), (self.cfg.data_config(), self.cfg.heldout_config())):
            synthesize(d, dcfg, shard=shard, progress=progress, log=self.log)

    def load(self, shard, progress, synthesize: bool = True):
        from warp_vision.data.store import ChunkedStore
        from warp_vision.eye.retina import Retina

        self.ddir, self.heldout_dir = self.dataset_dirs()
        if synthesize:
            self.render(shard, progress)
        fields = ["onv", "target", "meta"]
        d = ChunkedStore.open(self.ddir).load(fields)
        self.onv16, self.target, self.meta = (torch.from_numpy(d[k]) for k in fields)
        h = ChunkedStore.open(self.heldout_dir).load(fields)
        self.h_onv16, self.h_target, self.h_meta = (torch.from_numpy(h[k]) for k in fields)
        self.retina = Retina.load(self.ddir / "retina.npz")
        if self.ranging:  # the ball's log distance from the eye [N, 1]
            self.target, self.h_target = (torch.log(m[:, :1].double()).float() for m in (self.meta, self.h_meta))

    def _gated(self, meta: torch.Tensor) -> np.ndarray:
        """Ranging: the samples whose ball lies within RANGE_GATE_DEG of the line of sight."""
        from warp_vision.nn.retina_cnn import RANGE_GATE_DEG

        return meta[:, 3].numpy() < RANGE_GATE_DEG

    def splits(self):
        c = self.cfg
        parts = harness.splits(len(self.target), c.data_seed, c.val_fraction, c.test_fraction, min_test=2)
        if self.ranging:
            keep = self._gated(self.meta)
            parts = tuple(p[keep[p]] for p in parts)
        return parts

    def fit_norm(self, train):
        t = self.target[torch.as_tensor(train)]
        return {**fit_input_norm(self.onv16, train, per_sample=True), "target_mean": t.mean(0),
                "target_std": t.std(0).clamp_min(1e-6)}

    def net_spec(self):
        from warp_vision.eye.optics import NavarroEye
        from warp_vision.nn.retina_cnn import IMAGE_SIZE

        c = self.cfg
        spec = {"kind": "limb", "model": c.model, "layers": c.layers, "receptive_field": c.receptive_field,
                "reduction": c.reduction, "seed": c.seed, "onv_dtype": onv_dtype_name(c),
                "photoreceptor_xy": torch.from_numpy(np.asarray(self.retina.domain_xy, np.float64))}
        if c.model in ("cnn", "range"):  # its image's warp: the directions the photoreceptors see at the default optics
            angles = np.asarray(self.retina.visual_angles(NavarroEye()), np.float64)
            spec.update(channels=c.channels, image_size=IMAGE_SIZE, photoreceptor_angles=torch.from_numpy(angles))
        if c.model == "range":
            from warp_vision.nn.retina_cnn import RANGE_ECC_DEG, RANGE_IMAGE_SIZE, RANGE_POWER

            spec.update(image_size=RANGE_IMAGE_SIZE, max_ecc_deg=RANGE_ECC_DEG, power=RANGE_POWER)
        return spec

    def prepare(self, model, norm):
        model.set_target_norm(norm["target_mean"], norm["target_std"])
        set_input_standardisation(model, norm)

    def describe(self, model):
        if self.ranging:
            return (f"limb vision ranging cnn ({model.warp.size} x {model.warp.size} image of the central "
                    f"{math.degrees(model.warp.max_ecc):g} deg): {sum(p.numel() for p in model.parameters()):,} "
                    "parameters")
        if self.cfg.model == "cnn":
            return (f"limb vision cnn ({model.warp.size} x {model.warp.size} foveated image): "
                    f"{sum(p.numel() for p in model.parameters()):,} parameters")
        b = model.backbone
        return (f"limb vision {self.cfg.model}: {sum(p.numel() for p in model.parameters()):,} parameters, "
                f"layers {getattr(b, 'layer_sizes', '?')}")

    def _weights(self, y: torch.Tensor) -> torch.Tensor:
        """[N, 6] loss weights: each arm's three components by 1 / (near_weight_m + its distance), mean 1."""
        d = y.reshape(len(y), 2, 3).norm(dim=-1)
        w = 1.0 / (self.cfg.near_weight_m + d)
        w = w / w.mean()
        return w.repeat_interleave(3, dim=1)

    def batch_loss(self, net, idx, norm, device):
        y = self.target[idx]
        x = net_input(self.onv16[idx], norm, device, self.onv_dtype)
        if self.ranging:  # any turn or mirror of the world: the distance stays
            from warp_vision.nn.retina_cnn import ROTATIONS

            z = ((y - norm["target_mean"]) / norm["target_std"]).to(device)
            loss = torch.nn.functional.huber_loss(net(x, transform=int(torch.randint(2 * ROTATIONS, ()))), z,
                                                  delta=RANGE_HUBER_DELTA)
            return loss, {"loss": float(loss.detach())}
        if self.cfg.model == "cnn":  # a turned and mirrored copy of the world, its discrepancies turned alike
            from warp_vision.nn.retina_cnn import ROTATIONS, RetinaCNNLimbNet

            k = int(torch.randint(2 * ROTATIONS, ()))
            y = RetinaCNNLimbNet.transform_targets(y, k)
            pred = net(x, transform=k)
        else:
            pred = net(x)
        w = self._weights(y).to(device)
        z = ((y - norm["target_mean"]) / norm["target_std"]).to(device)
        loss = (torch.nn.functional.huber_loss(pred, z, delta=HUBER_DELTA, reduction="none") * w).mean()
        return loss, {"loss": float(loss.detach())}

    def _predict(self, model, onv16, idx, norm, device, batch: int = 256) -> torch.Tensor:
        model.eval()
        out = []
        with torch.no_grad():
            for s in range(0, len(idx), batch):
                z = model(net_input(onv16[torch.as_tensor(idx[s:s + batch])], norm, device, self.onv_dtype)).cpu()
                out.append(z * norm["target_std"] + norm["target_mean"])
        model.train()
        return torch.cat(out) if out else torch.zeros(0, self.target.shape[1])

    @staticmethod
    def _hand_m(meta: torch.Tensor) -> np.ndarray:
        return meta[:, 1:3].min(1).values.numpy()

    def evaluate(self, model, idx, norm, device):
        self._norm = norm
        idx = np.asarray(idx)
        pred = self._predict(model, self.onv16, idx, norm, device)
        true = self.target[torch.as_tensor(idx)]
        if self.ranging:
            ev = range_errors(pred.numpy(), true.numpy(), self._hand_m(self.meta[torch.as_tensor(idx)]))
            z, zp = ((t - norm["target_mean"]) / norm["target_std"] for t in (true, pred))
            ev["loss"] = float(torch.nn.functional.huber_loss(zp, z,
                                                              delta=RANGE_HUBER_DELTA)) if len(idx) else float("nan")
            return {**ev, "pred": pred}
        ev = discrepancy_errors(pred.numpy(), true.numpy())
        y = true
        w = self._weights(y)
        z = (y - norm["target_mean"]) / norm["target_std"]
        zp = (pred - norm["target_mean"]) / norm["target_std"]
        ev["loss"] = float((torch.nn.functional.huber_loss(zp, z, delta=HUBER_DELTA,
                                                           reduction="none") * w).mean()) if len(idx) else float("nan")
        return {**ev, "pred": pred}

    def epoch_line(self, row):
        if self.ranging:
            return (f"epoch {row['epoch']:3d}: train loss {row['train_loss']:.4f}  val loss {row['val_loss']:.4f}  "
                    f"val distance error median {100 * row['val_depth_median_relative']:.2f}%, "
                    f"p90 {100 * row['val_depth_p90_relative']:.2f}%")
        return (f"epoch {row['epoch']:3d}: train loss {row['train_loss']:.4f}  val loss {row['val_loss']:.4f}  "
                f"val near-ball error median {row['val_near_median_cm']:.2f} cm, p90 {row['val_near_p90_cm']:.2f} cm")

    def summary(self, test, history, model):
        norm = self._norm  # the test evaluation's, just before
        if self.ranging:
            return self._range_summary(test, model, norm)
        pred = self._predict(model.cpu(), self.h_onv16, np.arange(len(self.h_target)), norm, "cpu")
        self.heldout_pred = pred.numpy()
        held = discrepancy_errors(self.heldout_pred, self.h_target.numpy())
        tracked = self.h_meta[:, 3].numpy() < 2.0  # the ball within 2 deg of the line of sight
        held["tracked_within_2deg"] = discrepancy_errors(self.heldout_pred[tracked], self.h_target.numpy()[tracked])
        return {"eye": self.cfg.eye, "frame": "eye (x right, y up, z along the line of sight); m",
                "test": {k: v for k, v in test.items() if k != "pred"}, "heldout": held,
                "dataset": str(self.ddir), "heldout_dataset": str(self.heldout_dir)}

    def _range_summary(self, test, model, norm):
        idx = np.flatnonzero(self._gated(self.h_meta))
        pred = self._predict(model.cpu(), self.h_onv16, idx, norm, "cpu").numpy()
        self.heldout_idx, self.heldout_pred = idx, pred
        true, meta = self.h_target[torch.as_tensor(idx)].numpy(), self.h_meta[torch.as_tensor(idx)]
        held = range_errors(pred, true, self._hand_m(meta))
        tracked = meta[:, 3].numpy() < 2.0
        held["tracked_within_2deg"] = range_errors(pred[tracked], true[tracked], self._hand_m(meta)[tracked])
        return {"eye": self.cfg.eye, "target": "log distance (m) from the eye's centre to the ball, balls within "
                f"{self._gate_deg()} deg of the line of sight", "test": {k: v for k, v in test.items() if k != "pred"},
                "heldout": held, "heldout_samples_in_gate": int(len(idx)),
                "dataset": str(self.ddir), "heldout_dataset": str(self.heldout_dir)}

    @staticmethod
    def _gate_deg() -> float:
        from warp_vision.nn.retina_cnn import RANGE_GATE_DEG

        return RANGE_GATE_DEG

    def _range_figures(self, out, plt):
        true = np.exp(self.h_target[torch.as_tensor(self.heldout_idx)].numpy().ravel())
        pred = np.exp(self.heldout_pred.ravel())
        fig, axs = plt.subplots(1, 2, figsize=(10, 4))
        axs[0].scatter(true, pred, s=3, alpha=0.4)
        axs[0].plot([0, true.max()], [0, true.max()], "k", lw=0.8)
        axs[0].set(xlabel="true distance (m)", ylabel="estimated (m)",
                   title=f"held-out ({self.cfg.eye} eye): the ball's distance")
        axs[1].scatter(true, 100 * np.abs(pred / true - 1), s=3, alpha=0.4)
        axs[1].axhline(5.0, color="r", lw=0.8, ls="--")
        axs[1].set(xlabel="true distance (m)", ylabel="|relative error| (%)", yscale="log", title="relative error")
        fig.tight_layout()
        (Path(out) / "figures").mkdir(parents=True, exist_ok=True)
        fig.savefig(Path(out) / "figures" / "range_errors.png", dpi=110)
        plt.close(fig)

    def figures(self, out, history, test, idx):
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        if self.ranging:
            self._range_figures(out, plt)
            return

        true = self.h_target.numpy().reshape(-1, 3)
        pred = self.heldout_pred.reshape(-1, 3)
        dist = np.linalg.norm(true, axis=1)
        err = np.linalg.norm(pred - true, axis=1)
        fig, axs = plt.subplots(1, 2, figsize=(10, 4))
        axs[0].scatter(dist, err * 100, s=3, alpha=0.4)
        axs[0].axvline(NEAR_M, color="k", lw=0.8, ls="--")
        axs[0].axhline(3.0, color="r", lw=0.8, ls="--")
        axs[0].set(xlabel="true hand-ball distance (m)", ylabel="error (cm)", yscale="log",
                   title=f"held-out ({self.cfg.eye} eye): error against distance")
        near = dist < NEAR_M
        for k, name in enumerate("xyz"):
            axs[1].scatter(true[near, k], pred[near, k], s=3, alpha=0.4, label=name)
        lim = NEAR_M
        axs[1].plot([-lim, lim], [-lim, lim], "k", lw=0.8)
        axs[1].set(xlabel="true component (m)", ylabel="estimated (m)", title="held-out, balls within 0.6 m")
        axs[1].legend()
        fig.tight_layout()
        (Path(out) / "figures").mkdir(parents=True, exist_ok=True)
        fig.savefig(Path(out) / "figures" / "limb_errors.png", dpi=110)
        plt.close(fig)

    def eval_line(self, run_dir, split, n, ev):
        if self.ranging:
            return (f"{run_dir} ({split}, {n:,} ONVs): ball distance error median "
                    f"{100 * ev['depth_median_relative']:.2f}%, 90th percentile {100 * ev['depth_p90_relative']:.2f}%, "
                    f"median {ev['depth_median_cm']:.2f} cm")
        return (f"{run_dir} ({split}, {n:,} ONVs): hand-ball error within {NEAR_M} m: median "
                f"{ev['near_median_cm']:.2f} cm, 90th percentile {ev['near_p90_cm']:.2f} cm, relative "
                f"{ev['near_median_relative']:.3f}")


def run(cfg: LimbTrainConfig | None = None, **kw) -> dict:
    """Train (or resume) a limb vision run: :func:`warp_vision.train.harness.run` for this task."""
    return harness.run(LimbTask, cfg, **kw)


def evaluate_run(run_dir: str, split: str = "test", log=print, checkpoint: str = "best") -> dict:
    return evaluation.evaluate_run(LimbTask, run_dir, split, log, checkpoint=checkpoint)
