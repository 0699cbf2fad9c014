"""The verification task: each eye's foveal verification net (:class:`warp_vision.nn.verify.FovealVerifier`).

``python -m warp_vision.train verify --eye left|right [--preset smoke|quick|default] [--model cnn|linet]``

The dataset is :func:`warp_vision.data.verification.synthesize_verify`: the central field fixating the
ball or a look-alike (0 to ``max_offset_deg`` off) in generator-v9 scenes. The loss is the binary
cross-entropy of "the ball is at the fovea" plus ``offset_weight`` times the Huber loss (1 degree) of the
ball's direction on ball samples. The best epoch has the smallest validation loss. The summary reports the
test split's and a held-out set's (rooms of the held-out family) ROC area, the threshold that rejects 1% of
the balls (fitted on the validation split, stored in best.pt), the false accepts per look-alike class at that
threshold, and the offset's median error; a figure draws the held-out ROC per class.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from warp_vision.train import evaluation, harness
from warp_vision.train.config_verify import VerifyTrainConfig

#: the false-reject rate the accept threshold is set at
FALSE_REJECTS = 0.01
HUBER_DEG = 1.0
#: a sample whose ball is not at the fovea but within this angle of it (or hidden there) is left out of the
#: classification and its scores: the eye is as good as on the ball (the offset brings it there), neither a
#: right nor a wrong accept
IGNORE_DEG = 4.5
#: the CNN's training batches are split into this many groups, each seen through a random turn or mirror
AUGMENT_GROUPS = 4


def roc_auc(score: np.ndarray, label: np.ndarray) -> float:
    """The area under the ROC curve: the chance a ball sample scores above a look-alike (ties half), by the
    Mann-Whitney rank sum."""
    from scipy.stats import rankdata

    pos, neg = score[label > 0.5], score[label <= 0.5]
    if not len(pos) or not len(neg):
        return float("nan")
    ranks = rankdata(np.concatenate([pos, neg]))  # ties take their mean rank
    return float((ranks[: len(pos)].sum() - len(pos) * (len(pos) + 1) / 2) / (len(pos) * len(neg)))


def accept_threshold(score: np.ndarray, label: np.ndarray, false_rejects: float = FALSE_REJECTS) -> float:
    """The logit above which a sample is accepted so that ``false_rejects`` of the ball samples fall below it."""
    pos = np.sort(score[label > 0.5])
    if not len(pos):
        return float("inf")
    return float(np.quantile(pos, false_rejects))


def verdicts(score: np.ndarray, label: np.ndarray, cls: np.ndarray, threshold: float) -> dict:
    """False rejects of the balls and false accepts per look-alike class at ``threshold``."""
    from warp_vision.data.verification import CLASSES

    acc = score >= threshold
    out = {"false_rejects": float(np.mean(~acc[label > 0.5])) if (label > 0.5).any() else float("nan"),
           "false_accepts": {}}
    for k, name in enumerate(CLASSES):
        m = (cls == k) & (label <= 0.5)
        if k and m.any():
            out["false_accepts"][name] = {"rate": float(acc[m].mean()), "n": int(m.sum())}
    neg = label <= 0.5
    out["false_accepts_all"] = float(acc[neg].mean()) if neg.any() else float("nan")
    return out


class VerifyTask(harness.Task):
    name = "verify"
    config_cls = VerifyTrainConfig
    selection = {"loss": "min"}

    def render(self, shard, progress):
        from warp_vision.data.verification import synthesize_verify

        synthesize_verify(self.cfg.data_dir, self.cfg.data_config(), shard=shard, progress=progress, log=self.log)
        synthesize_verify(self._heldout_dir(), self._heldout_config(), shard=shard, progress=progress, log=self.log)

    def dataset_dirs(self):
        return [Path(self.cfg.data_dir), Path(self._heldout_dir())]

    def _heldout_config(self):
        return self.cfg.data_config().heldout(self.cfg.heldout_samples)

    def _heldout_dir(self) -> str:
        return str(Path(self.cfg.data_dir).parent / f"verify-{self._heldout_config().key()}")

    def dataset_bytes(self):
        from warp_vision.data.store import dataset_bytes
        from warp_vision.data.verification import dataset_fields

        dc, hc = self.cfg.data_config(), self._heldout_config()
        return dataset_bytes(dataset_fields(dc), dc.samples) + dataset_bytes(dataset_fields(hc), hc.samples)

    def load(self, shard, progress, synthesize: bool = True):
        from warp_vision.data.store import ChunkedStore
        from warp_vision.eye.retina import Retina

        if synthesize:
            self.render(shard, progress)
        keys = ["onv", "label", "offset", "cls", "ball_ecc_deg"]
        self.data, self.heldout = ({k.replace("ball_ecc_deg", "ecc"): torch.from_numpy(v)
                                    for k, v in ChunkedStore.open(d).load(keys).items()}
                                   for d in (self.cfg.data_dir, self._heldout_dir()))
        self.retina = Retina.load(Path(self.cfg.data_dir) / "retina.npz")

    def splits(self):
        c = self.cfg
        return harness.splits(len(self.data["label"]), c.seed, c.val_fraction, c.test_fraction, min_test=2)

    def fit_norm(self, train):
        from warp_vision.nn.trained import fit_input_norm

        return fit_input_norm(self.data["onv"], train, per_sample=True)

    def data_config(self):
        from dataclasses import asdict

        return asdict(self.cfg.data_config())

    def net_spec(self):
        from warp_vision.data.foveation import make_eye
        from warp_vision.data.verification import central_photoreceptors

        c = self.cfg
        central = central_photoreceptors(self.retina, c.central_deg)
        angles = np.asarray(self.retina.visual_angles(make_eye(c.data_config().scene_config())), np.float64)
        return {"kind": "verify", "model": c.model, "central_deg": c.central_deg, "seed": c.seed,
                "channels": c.channels, "layers": c.layers, "receptive_field": c.receptive_field,
                "reduction": c.reduction, "central": torch.from_numpy(central.astype(np.int64)),
                "photoreceptor_angles": torch.from_numpy(np.nan_to_num(angles)),
                "photoreceptor_xy": torch.from_numpy(np.asarray(self.retina.domain_xy, np.float64))}

    def _outputs(self, net, data: dict, idx, norm: dict, device, augment: bool = False):
        from warp_vision.nn.trained import net_input
        from warp_vision.nn.verify import transform_offsets

        i = torch.as_tensor(np.asarray(idx))
        offset, ks = data["offset"][i], 0
        if augment and self.cfg.model == "cnn":
            from warp_vision.nn.retina_cnn import ROTATIONS

            ks = [int(k) for k in torch.randint(2 * ROTATIONS, (AUGMENT_GROUPS,))]
            offset = torch.cat([transform_offsets(o, k) for o,
                                k in zip(torch.tensor_split(offset, AUGMENT_GROUPS), ks)])
        out = net(net_input(data["onv"][i], norm, device), transform=ks)
        label = data["label"][i].to(device)
        weight = ((label > 0.5) | (data["ecc"][i].to(device) > IGNORE_DEG)).float()
        return out, torch.stack([label, weight], 1), torch.rad2deg(offset).to(device)

    def _loss(self, out, label_weight, offset_deg):
        label, weight = label_weight[:, 0], label_weight[:, 1]
        bce = (torch.nn.functional.binary_cross_entropy_with_logits(out[:, 0], label,
                                                                    reduction="none") * weight).sum() \
            / weight.sum().clamp_min(1)
        pos = label > 0.5
        off = (torch.nn.functional.huber_loss(out[pos, 1:], offset_deg[pos], delta=HUBER_DEG) if pos.any()
               else out.sum() * 0)
        return bce + self.cfg.offset_weight * off, bce, off

    def batch_loss(self, net, idx, norm, device):
        out, label, offset = self._outputs(net, self.data, idx, norm, device, augment=True)
        loss, bce, off = self._loss(out, label, offset)
        return loss, {"loss": loss.item(), "bce": bce.item()}

    def _scores(self, model, data, idx, norm, device):
        """(outputs, (label, weight), offset deg) of samples ``idx`` in eval mode (batch norm's running statistics)."""
        outs = []
        was = model.training
        model.eval()
        with torch.no_grad():
            for s in range(0, len(idx), 256):
                outs.append(torch.cat([t.cpu()[:, None] if t.ndim == 1 else t.cpu()
                                       for t in self._outputs(model, data, idx[s:s + 256], norm, device)], 1))
        model.train(was)
        o = torch.cat(outs) if outs else torch.zeros(0, 7)
        return o[:, :3], o[:, 3:5], o[:, 5:]  # (outputs, (label, weight), offset deg)

    def _metrics(self, out, label_weight, offset, cls, threshold=None) -> dict:
        loss, bce, _ = self._loss(out, label_weight, offset)
        keep = label_weight[:, 1] > 0  # the samples scored (IGNORE_DEG)
        out, offset, cls, label = out[keep], offset[keep], cls[keep], label_weight[keep, 0]
        s, y = out[:, 0].numpy(), label.numpy()
        pos = y > 0.5
        err = (out[pos, 1:] - offset[pos]).norm(dim=1).numpy()
        th = accept_threshold(s, y) if threshold is None else threshold
        return {"loss": float(loss), "bce": float(bce), "auc": roc_auc(s, y), "threshold": th,
                "median_offset_error_deg": float(np.median(err)) if len(err) else float("nan"),
                "p90_offset_error_deg": float(np.quantile(err, 0.9)) if len(err) else float("nan"),
                **verdicts(s, y, cls.numpy(), th)}

    def evaluate(self, model, idx, norm, device):
        out, label, offset = self._scores(model, self.data, np.asarray(idx), norm, device)
        return self._metrics(out, label, offset, self.data["cls"][torch.as_tensor(np.asarray(idx))])

    def calibrate(self, model, train_ids, device):
        """The accept threshold (1% false rejects), fitted on the validation split, into the net's buffer."""
        _, val, _ = self.splits()
        out, label, _ = self._scores(model, self.data, val, self._norm, device)
        keep = label[:, 1] > 0
        model.threshold.fill_(accept_threshold(out[keep, 0].numpy(), label[keep, 0].numpy()))
        return True

    def prepare(self, model, norm):
        self._norm = norm

    def summary(self, test, history, model):
        model = model.cpu()
        th = float(model.threshold)
        n = len(self.heldout["label"])
        out, label, offset = self._scores(model, self.heldout, np.arange(n), self._norm, "cpu")
        keep = label[:, 1] > 0
        self.heldout_scores = (out[keep, 0].numpy(), label[keep, 0].numpy(), self.heldout["cls"][keep].numpy())
        return {"eye": self.cfg.eye, "model": self.cfg.model, "threshold": th, "test": test,
                "heldout": self._metrics(out, label, offset, self.heldout["cls"], th), "dataset": self.cfg.data_dir,
                "heldout_dataset": self._heldout_dir()}

    def describe(self, model):
        return (f"verification net ({self.cfg.eye} eye, {self.cfg.model}, {model.N:,} photoreceptors within "
                f"{self.cfg.central_deg:g} deg): {sum(p.numel() for p in model.parameters()):,} parameters")

    def epoch_line(self, row):
        return (f"epoch {row['epoch']:3d}: train loss {row['train_loss']:.4f}  val loss {row['val_loss']:.4f}  "
                f"AUC {row['val_auc']:.4f}  false accepts at 1% false rejects "
                f"{100 * row['val_false_accepts_all']:.1f}%")

    def figures(self, out, history, test, idx):
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        from warp_vision.data.verification import CLASSES

        s, y, cls = self.heldout_scores
        pos = np.sort(s[y > 0.5])
        fig, ax = plt.subplots(figsize=(6, 5))
        for k, name in enumerate(CLASSES[1:], start=1):
            neg = s[(cls == k) & (y <= 0.5)]
            if len(neg) < 5:
                continue
            th = np.concatenate([pos, [np.inf]])
            fr = np.searchsorted(pos, th, side="left") / max(len(pos), 1)  # balls below each threshold
            fa = np.array([(neg >= t).mean() for t in th])
            ax.plot(fa, fr, label=f"{name} ({len(neg)})")
        ax.axhline(FALSE_REJECTS, color="k", lw=0.7, ls="--")
        ax.set(xscale="symlog", xlabel="false accepts (look-alikes accepted)", ylabel="false rejects (balls rejected)",
               title=f"{self.cfg.eye} eye's {self.cfg.model} verifier, held-out rooms", ylim=(0, 0.2))
        ax.set_xscale("symlog", linthresh=0.01)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=7)
        fig.tight_layout()
        (out / "figures").mkdir(parents=True, exist_ok=True)
        fig.savefig(out / "figures" / "verify_roc.png", dpi=110)
        plt.close(fig)

    def eval_line(self, run_dir, split, n, ev):
        fa = ", ".join(f"{k} {100 * v['rate']:.1f}%" for k, v in ev["false_accepts"].items())
        return (f"{run_dir} ({split}, {n:,} ONVs): AUC {ev['auc']:.4f}, false rejects "
                f"{100 * ev['false_rejects']:.1f}%, false accepts {100 * ev['false_accepts_all']:.1f}% ({fa}); offset "
                f"median {ev['median_offset_error_deg']:.2f} deg")


def run(cfg: VerifyTrainConfig | None = None, **kw) -> dict:
    """Train (or resume) one eye's verification run: :func:`warp_vision.train.harness.run` for this task."""
    return harness.run(VerifyTask, cfg, **kw)


def evaluate_run(run_dir: str, split: str = "test", log=print, checkpoint: str = "best") -> dict:
    """Re-evaluate a verification run's ``checkpoint`` (best or latest) on its held-out ONVs."""
    return evaluation.evaluate_run(VerifyTask, run_dir, split, log, checkpoint=checkpoint)
