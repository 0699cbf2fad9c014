"""Active face recognition (the paper's Section VI.B): the two-headed liNet on face ONVs.

``python -m warp_vision.train faces [--preset smoke|default|paper] [--flag value ...]``

The run itself (directory layout, ``--resume``, Ctrl-C, NaN checks, ``torchrun``) is
:mod:`warp_vision.train.harness`. As in the paper:

- The loss is cross-entropy(identity) + ``loss_lambda`` x MSE(pose standardised with the training set's
  mean and std), with lambda 6 and Adam (1e-3, betas 0.9/0.999), on a 70/10/20 split.
- ``best.pt`` is written only at an epoch that attains both the best validation pose MSE and the best
  validation accuracy so far (ties count).
- The run stops early after ``patience`` (30) epochs in which neither metric reaches a new best.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from warp_vision.nn.trained import fit_input_norm, net_input, set_input_standardisation
from warp_vision.train import evaluation, harness
from warp_vision.train.config import FaceTrainConfig, onv_dtype_name


def shuffled_labels(ident, pose, tr, seed: int):
    """Copies of the labels whose training entries are permuted among the training ONVs (val/test keep theirs)."""
    ident, pose = ident.clone(), pose.clone()
    src = torch.as_tensor(np.random.default_rng([seed, 104729]).permutation(tr))
    t = torch.as_tensor(tr)
    ident[t], pose[t] = ident[src], pose[src]
    return ident, pose


class FaceTask(harness.OnvTask):
    name = "faces"
    config_cls = FaceTrainConfig
    data_module = "warp_vision.data.faces"
    selection = {"mse": "min", "accuracy": "max"}

    def load(self, shard, progress, synthesize: bool = True):
        from warp_vision.data.faces import synthesize as render
        from warp_vision.data.store import ChunkedStore
        from warp_vision.eye.retina import Retina

        self.ddir = harness.dataset_dir(self.cfg, "faces", self.cfg.data_config())
        if synthesize:
            render(self.ddir, self.cfg.data_config(), shard=shard, progress=progress, log=self.log,
                   identities_path=self.cfg.identities_cache or None)
        data = ChunkedStore.open(self.ddir).load(["onv", "identity", "pose"])
        self.onv16, self.ident, self.pose = (torch.from_numpy(data[k]) for k in ("onv", "identity", "pose"))
        self.retina = Retina.load(self.ddir / "retina.npz")

    @classmethod
    def resolve_paths(cls, cfg):
        from warp_vision.data.faces import identities_cache
        from warp_vision.fileio import resolved

        super().resolve_paths(cfg)
        cache = cfg.identities_cache or identities_cache(cfg.identities, cfg.identity_seed)
        cfg.identities_cache = str(resolved(cache, "--identities-cache"))

    @classmethod
    def check_new_run(cls, cfg):
        """``--identities-cache``: a regular file (read where it holds the identities), or a path where one can be
        written; a device, a FIFO or a symbolic link there is refused before any work."""
        from warp_vision.fileio import require_output

        cache = Path(cfg.identities_cache)
        require_output(cache, "--identities-cache", kind="file", writable=not cache.is_file())

    def splits(self):
        c = self.cfg
        tr, va, te = harness.splits(len(self.ident), c.data_seed, c.val_fraction, c.test_fraction, min_test=1)
        self.labels = shuffled_labels(self.ident, self.pose, tr,
                                      c.seed) if c.shuffle_labels else (self.ident, self.pose)
        return tr, va, te

    def fit_norm(self, train):
        t = torch.as_tensor(train)
        return {**fit_input_norm(self.onv16, train), "pose_mean": self.pose[t].mean(0),
                "pose_std": self.pose[t].std(0).clamp_min(1e-6)}

    def net_spec(self):
        c = self.cfg
        return {"kind": "afr", "model": c.model, "identities": c.identities, "layers": c.layers,
                "receptive_field": c.receptive_field, "reduction": c.reduction, "seed": c.seed,
                "onv_dtype": onv_dtype_name(c),
                "photoreceptor_xy": torch.from_numpy(np.asarray(self.retina.domain_xy, np.float64))}

    def prepare(self, model, norm):
        model.set_pose_norm(norm["pose_mean"], norm["pose_std"])
        set_input_standardisation(model, norm)

    def describe(self, model):
        c = self.cfg
        return (f"AFR {c.model}: {sum(p.numel() for p in model.parameters()):,} parameters, layers "
                f"{getattr(model.backbone, 'layer_sizes', '?')}; {c.identities} identities"
                f"{'; TRAINING LABELS SHUFFLED (sanity check)' if c.shuffle_labels else ''}")

    def batch_loss(self, net, idx, norm, device):
        ident, pose = self.labels
        logits, z = net(net_input(self.onv16[idx], norm, device, self.onv_dtype))
        ce = F.cross_entropy(logits, ident[idx].to(device))
        mse = F.mse_loss(z, ((pose[idx] - norm["pose_mean"]) / norm["pose_std"]).to(device))
        acc = (logits.detach().argmax(1).cpu() == ident[idx]).float().mean().item()
        return ce + self.cfg.loss_lambda * mse, {"ce": ce.item(), "mse": mse.item(), "accuracy": acc}

    def evaluate(self, model, idx, norm, device, batch: int = 256):
        model.eval()
        logits, z = [], []
        with torch.no_grad():
            for s in range(0, len(idx), batch):
                a, b = model(net_input(self.onv16[torch.as_tensor(idx[s : s + batch])], norm, device, self.onv_dtype))
                logits.append(a.cpu())
                z.append(b.cpu())
        model.train()
        i = torch.as_tensor(idx)
        logits, z = torch.cat(logits), torch.cat(z)
        ce = float(F.cross_entropy(logits, self.ident[i]))
        mse = float(F.mse_loss(z, (self.pose[i] - norm["pose_mean"]) / norm["pose_std"]))
        pred_pose = model.pose_degrees(z.to(model.pose_std.device)).cpu()  # by the pose scale the net carries
        err = (pred_pose - self.pose[i]).abs()
        pred_id = logits.argmax(1)
        return {"ce": ce, "mse": mse, "loss": ce + self.cfg.loss_lambda * mse,
                "accuracy": float((pred_id == self.ident[i]).float().mean()), "pose_mae_deg": float(err.mean()),
                "yaw_mae_deg": float(err[:, 0].mean()), "pitch_mae_deg": float(err[:, 1].mean()),
                "pred_identity": pred_id, "pred_pose": pred_pose}

    def epoch_line(self, row):
        return (f"epoch {row['epoch']:3d}: train CE {row['train_ce']:.3f} MSE {row['train_mse']:.4f} acc "
                f"{row['train_accuracy']:.3f} | val CE {row['val_ce']:.3f} MSE {row['val_mse']:.4f} acc "
                f"{row['val_accuracy']:.3f} pose MAE {row['val_pose_mae_deg']:.2f} deg")

    def summary(self, test, history, model):
        from warp_vision.data.faces import FaceIdentities

        c = self.cfg
        nn_mm = FaceIdentities.load(self.ddir / "identities.npz").nearest_neighbour_mm()
        return {"model": c.model, "shuffle_labels": c.shuffle_labels, "identities": c.identities,
                "onvs": len(self.ident), "test_accuracy": test["accuracy"], "chance_accuracy": 1.0 / c.identities,
                "test_pose_mae_deg": test["pose_mae_deg"], "test_yaw_mae_deg": test["yaw_mae_deg"],
                "test_pitch_mae_deg": test["pitch_mae_deg"], "test_ce": test["ce"], "test_mse": test["mse"],
                "identity_nearest_neighbour_mm": {"min": float(nn_mm.min()), "median": float(np.median(nn_mm))},
                "dataset": str(self.ddir)}

    def figures(self, out, history, test, idx):
        from warp_vision.train.figures import write_face_figures

        write_face_figures(out, history, self.retina, self.onv16, self.ident, self.pose, idx, test, self.cfg)

    def eval_line(self, run_dir, split, n, ev):
        return (f"{run_dir} ({split}, {n:,} ONVs): identity accuracy {100 * ev['accuracy']:.2f}% (chance "
                f"{100 / self.cfg.identities:.1f}%); pose mean absolute error {ev['pose_mae_deg']:.3f} deg "
                f"(yaw {ev['yaw_mae_deg']:.3f}, pitch {ev['pitch_mae_deg']:.3f})")


def run(cfg: FaceTrainConfig | None = None, **kw) -> dict:
    """Train (or resume) an AFR run: :func:`warp_vision.train.harness.run` for this task."""
    return harness.run(FaceTask, cfg, **kw)


def evaluate_run(run_dir: str, split: str = "test", log=print, checkpoint: str = "best") -> dict:
    """Re-evaluate an AFR run's ``checkpoint`` (best or latest); prints accuracy and pose error."""
    return evaluation.evaluate_run(FaceTask, run_dir, split, log, checkpoint=checkpoint)
