"""What the pupil and lens tasks share (:mod:`warp_vision.train.pupil`, :mod:`warp_vision.train.lens`).

Their nets have a fixed first layer (``raw_features``: region log-means, contrast energies) and a small
learned head. The first layer is computed once per dataset, in batches, and training runs the head on it
(``net(raw=...)``); the standardisation of the raw features (and any other norm entry named like one of
the net's buffers) is fitted on the training split and copied into the net. Each task has a training set
(split into train / validation / test) and a held-out set that training never sees, evaluated at the end.
"""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch

from warp_vision.train import harness


class ShallowNetTask(harness.Task):
    """Subclasses set ``name``, ``config_cls``, ``selection``, ``target`` (the data field the net learns)
    and implement ``_render_set`` (synthesise if missing, load, and return a dict of tensors with
    ``onv`` and ``pupil``), ``net_spec``, ``loss``, ``errors`` and the lines and figures."""

    target = ""
    #: raw_features' keyword arguments for the stored ONVs (the lens data store the central field only)
    raw_kwargs: dict = {}

    def _render_set(self, dcfg, ddir: str, shard, progress: bool, synthesize: bool) -> dict:
        raise NotImplementedError

    def loss(self, pred: torch.Tensor, true: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError

    def errors(self, pred: torch.Tensor, true: torch.Tensor) -> dict:
        raise NotImplementedError

    def _load_set(self, dcfg, ddir: str, shard, progress: bool, synthesize: bool) -> dict:
        """A dataset with its ONVs replaced by the net's fixed first layer (``raw``)."""
        d = self._render_set(dcfg, ddir, shard, progress, synthesize)
        net = self._net()
        with torch.no_grad():
            d["raw"] = torch.cat([net.raw_features(d["onv"][s:s + 256].float(), d["pupil"][s:s + 256],
                                                   **self.raw_kwargs)
                                  for s in range(0, len(d["onv"]), 256)])
        del d["onv"]
        return d

    def load(self, shard, progress, synthesize: bool = True):
        dcfg = self.cfg.data_config()
        self.data = self._load_set(dcfg, self.cfg.data_dir, shard, progress, synthesize)
        hcfg = dcfg.heldout(self.cfg.heldout_samples)
        # beside the training set; its seed is offset by 1000 (new rooms or textures, lamps, distances)
        self.heldout_dir = str(Path(self.cfg.data_dir).parent / f"{self.name}-{hcfg.key()}")
        self.heldout = self._load_set(hcfg, self.heldout_dir, shard, progress, synthesize)

    def _net(self):
        from warp_vision.nn.trained import build_net

        return build_net(self.net_spec())

    def splits(self):
        c = self.cfg
        return harness.splits(len(self.data["raw"]), c.seed, c.val_fraction, c.test_fraction, min_test=2)

    def fit_norm(self, train):
        f = self.data["raw"][torch.as_tensor(train)]
        return {"feature_mean": f.mean(0), "feature_std": f.std(0).clamp_min(1e-3)}

    def prepare(self, model, norm):
        with torch.no_grad():
            for k, v in norm.items():
                getattr(model, k).copy_(v)

    def data_config(self):
        return asdict(self.cfg.data_config())

    def _predict(self, net, data: dict, idx, device):
        i = torch.as_tensor(np.asarray(idx))
        return net(raw=data["raw"][i].to(device)), data[self.target][i].to(device)

    def batch_loss(self, net, idx, norm, device):
        pred, true = self._predict(net, self.data, idx, device)
        loss = self.loss(pred, true)
        return loss, {"loss": loss.item()}

    def evaluate(self, model, idx, norm, device):
        with torch.no_grad():
            pred, true = self._predict(model, self.data, idx, device)
        return self.errors(pred.cpu(), true.cpu())

    def summary(self, test, history, model):
        """The test split's and the held-out set's errors (the held-out predictions are kept for the figures)."""
        with torch.no_grad():
            pred, true = self._predict(model.cpu(), self.heldout, np.arange(len(self.heldout["raw"])), "cpu")
        self.heldout_pred = (pred.numpy(), true.numpy())
        return {"eye": self.cfg.eye, "test": test, "heldout": self.errors(pred, true), "dataset": self.cfg.data_dir,
                "heldout_dataset": self.heldout_dir}

    @staticmethod
    def save_figure(fig, out: Path, name: str) -> None:
        import matplotlib.pyplot as plt

        fig.tight_layout()
        (out / "figures").mkdir(parents=True, exist_ok=True)
        fig.savefig(out / "figures" / name, dpi=110)
        plt.close(fig)
