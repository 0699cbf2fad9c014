"""The oculomotor task: each eye's net from (desired change of gaze, current activations) to the next
six extraocular activations, trained on holding activations the body solves for itself.

``python -m warp_vision.train oculomotor --eye left|right [--preset smoke|quick|default] [--flag value ...]``

The dataset is :func:`warp_vision.sim.oculomotor.synthesize_holding` (gazes in a disc and their
least-effort holding activations, cached by config). The samples are transitions between gazes
(:func:`warp_vision.sim.oculomotor.transition_pairs`): ``transitions`` pairs among the training gazes,
and pairs among the validation and test gazes, which training never sees. The loss weighs each
activation error by the inverse square of (1 deg + the change asked for): the loop asks for sub-degree
corrections every period, whose activation changes are tiny next to a saccade's. The test evaluation
ends on the body: the gaze the eye settles at under the net's activations
(:func:`warp_vision.sim.oculomotor.evaluate_on_body`).
"""

from __future__ import annotations

import numpy as np
import torch

from warp_vision.train import evaluation, harness
from warp_vision.train.config_body import OculomotorTrainConfig


class OculomotorTask(harness.Task):
    name = "oculomotor"
    config_cls = OculomotorTrainConfig
    #: the unweighted activation error picks the best epoch: the weighted loss of a few hundred held-out
    #: gazes rests on their rare close neighbours (a "near" transition mostly draws the gaze itself), too
    #: few to rank epochs by
    selection = {"activation_rmse": "min"}

    def load(self, shard, progress, synthesize: bool = True):
        from warp_vision.data.store import ChunkedStore
        from warp_vision.sim.oculomotor import synthesize_holding

        self.ddir = harness.dataset_dir(self.cfg, "oculomotor", self.cfg.data_config())
        if synthesize:
            synthesize_holding(self.ddir, self.cfg.data_config(), shard=shard, progress=progress, log=self.log)
        data = ChunkedStore.open(self.ddir).load(["gaze", "act", "residual"])
        self.gaze_np, self.act_np, self.residual = data["gaze"], data["act"], data["residual"]
        self.gaze = torch.as_tensor(self.gaze_np, dtype=torch.float32)
        self.act = torch.as_tensor(self.act_np, dtype=torch.float32)

    def splits(self):
        """Gazes split into train / validation / test; the samples are transitions among each split's gazes."""
        from warp_vision.sim.oculomotor import transition_pairs

        c = self.cfg
        gtr, gva, gte = harness.splits(len(self.gaze_np), c.seed, c.val_fraction, c.test_fraction, min_test=2)
        rng = np.random.default_rng([c.seed, 1])
        pairs = [transition_pairs(gtr, c.transitions, rng, self.gaze_np)]
        for g in (gva, gte):
            pairs.append(transition_pairs(g, max(2000, 4 * len(g)), rng, self.gaze_np))
        self.test_gazes = gte
        self.pairs = tuple(np.concatenate(p) for p in zip(*pairs))  # sample s is the pair (i[s], j[s])
        edges = np.cumsum([0] + [len(p[0]) for p in pairs])
        return tuple(np.arange(edges[k], edges[k + 1]) for k in range(3))

    def net_spec(self):
        return {"kind": "oculomotor", "hidden": self.cfg.hidden, "seed": self.cfg.seed}

    def data_config(self):
        from dataclasses import asdict

        from warp_vision.sim.oculomotor import HOLDING_VERSION

        # the generator's version travels with the net: load_oculomotor refuses nets of an older eye plant
        return {**asdict(self.cfg.data_config()), "generator_version": HOLDING_VERSION}

    def _errors(self, net, idx, device):
        i, j = (torch.as_tensor(p[np.asarray(idx)]) for p in self.pairs)
        change = self.gaze[j] - self.gaze[i]
        pred = net(change.to(device), self.act[i].to(device))
        w = 1.0 / (torch.rad2deg(change.norm(dim=-1, keepdim=True)) + 1.0) ** 2
        return pred, self.act[j].to(device), w.to(device)

    def batch_loss(self, net, idx, norm, device):
        pred, true, w = self._errors(net, idx, device)
        loss = torch.mean(w * (pred - true) ** 2)
        return loss, {"loss": loss.item()}

    def evaluate(self, model, idx, norm, device):
        with torch.no_grad():
            pred, true, w = self._errors(model, idx, device)
        return {"loss": float(torch.mean(w * (pred - true) ** 2)),
                "activation_rmse": float(torch.sqrt(torch.mean((pred - true) ** 2)))}

    def describe(self, model):
        return (f"oculomotor MLP ({self.cfg.eye} eye, hidden {self.cfg.hidden}): "
                f"{sum(p.numel() for p in model.parameters()):,} parameters")

    def epoch_line(self, row):
        return (f"epoch {row['epoch']:3d}: train loss {row['train_loss']:.3e}  val loss {row['val_loss']:.3e} "
                f"activation RMSE {row['val_activation_rmse']:.4f}")

    def summary(self, test, history, model):
        from warp_vision.body import Body, BodyConfig
        from warp_vision.sim.oculomotor import evaluate_on_body

        self.log("checking the net on the body (held-out gazes)")
        on_body = evaluate_on_body(model.cpu(), Body(BodyConfig(arms=False)), self.cfg.eye, self.gaze_np, self.act_np,
                                   self.test_gazes, n=self.cfg.body_checks)
        return {"eye": self.cfg.eye, "test_loss": test["loss"], "test_activation_rmse": test["activation_rmse"],
                **on_body, "holding_residual_Nm_max": float(self.residual.max()), "dataset": str(self.ddir)}

    def eval_line(self, run_dir, split, n, ev):
        return (f"{run_dir} ({split}, {n:,} transitions): loss {ev['loss']:.3e}, activation RMSE "
                f"{ev['activation_rmse']:.4f}")


def run(cfg: OculomotorTrainConfig | None = None, **kw) -> dict:
    """Train (or resume) one eye's oculomotor run: :func:`warp_vision.train.harness.run` for this task."""
    return harness.run(OculomotorTask, cfg, **kw)


def evaluate_run(run_dir: str, split: str = "test", log=print, checkpoint: str = "best") -> dict:
    """Re-evaluate an oculomotor run's ``checkpoint`` (best or latest) on its held-out transitions."""
    return evaluation.evaluate_run(OculomotorTask, run_dir, split, log, checkpoint=checkpoint)
