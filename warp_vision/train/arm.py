"""The arm task: one arm's posture net and voluntary net, trained on postures the body holds by itself.

``python -m warp_vision.train arm --side left|right [--preset smoke|quick|default] [--flag value ...]``

The dataset is :func:`warp_vision.sim.arm.synthesize_arm` (postures with the hand 0.2-0.6 m in front of
the shoulder and their least-effort holding activations, cached by config under
``runs/datasets/arm-<hash>``); postures whose holding residual exceeds ``max_residual`` are dropped. The
kept postures are split into train / validation / test; the samples are transitions among each split's
postures (:func:`warp_vision.sim.arm.reach_pairs`), so validation and test postures and their hand
positions are never trained on. Each sample is a pair (i, j), joint velocities v (zero for half the
samples, N(0, ``velocity_std``) rad/s for the others) and, for the voluntary net, the holding activations
of i (perturbed by 0.05 for half the samples; in the loop it reads the posture net's holding activations
at the current angles). Both nets
of :class:`warp_vision.nn.arm.ArmNets` are trained in torque, with posture i's balance ``A_i a = b_i`` from
the dataset:

- the voluntary net, (hand_j - hand_i, act_i, angles_i, v) -> a, so that ``A_i a`` supplies ``b_i`` plus
  :func:`warp_vision.sim.arm.demanded_torque` (angles_j - angles_i, v): a saturating spring of
  ``stiffness`` toward j's joints (saturating at ``saturation``) and a damper of ``damping``;
- the posture net, (angles_i, v) -> a, so that ``A_i a`` supplies ``b_i`` plus a damper of ``posture_damping``.

Each loss is ``torque_weight`` times a soft norm of the torque shortfall (quadratic below 0.1 N m, linear
above: a demand beyond what the muscles can give must not drown the rest) plus the mean squared departure
from act_i (the least-effort holding activations: among activations that give the torque, the nearest to
those that hold the arm where it is). The best epoch has the smallest validation loss. The test evaluation
ends on the body (:func:`warp_vision.sim.arm.evaluate_on_body`): held-out reaches after 0.3 and 0.6 s,
the posture net's hold after 0.3, 0.6 and 1 s, and the teachers (the exact holding activations, and the
exact static optimisation solved every 10 ms) as the floor.
"""

from __future__ import annotations

import numpy as np
import torch

from warp_vision.train import evaluation, harness
from warp_vision.train.config_body import ArmTrainConfig

FIELDS = ["angles", "qpos", "act", "hand", "residual", "torque_A", "torque_b"]


def _soft_norm(r: torch.Tensor, eps: float = 0.1) -> torch.Tensor:
    """A torque shortfall r (N m) as a loss: ~r^2 / (2 eps) below eps, ~r above (a demand beyond what the muscles
    can give must not drown the rest)."""
    return torch.sqrt(r**2 + eps**2) - eps


class ArmTask(harness.Task):
    name = "arm"
    config_cls = ArmTrainConfig
    #: the loss (activation error plus the torque residual) picks the best epoch
    selection = {"loss": "min"}

    def load(self, shard, progress, synthesize: bool = True):
        from warp_vision.data.store import ChunkedStore
        from warp_vision.sim.arm import synthesize_arm

        self.ddir = harness.dataset_dir(self.cfg, "arm", self.cfg.data_config())
        self.body = None
        if synthesize:
            from warp_vision.body import Body

            self.body = Body()
            synthesize_arm(self.ddir, self.cfg.data_config(), shard=shard, progress=progress, log=self.log,
                           body=self.body)
        self.data = ChunkedStore.open(self.ddir).load(FIELDS)
        self.kept = np.nonzero(self.data["residual"] <= self.cfg.max_residual)[0]
        if len(self.kept) < 8:
            raise ValueError(f"only {len(self.kept)} of {len(self.data['residual'])} postures are held within "
                             f"{self.cfg.max_residual} N m: raise postures or max_residual")
        self.t = {k: torch.as_tensor(self.data[k],
                                     dtype=torch.float32) for k in ("angles", "act", "hand", "torque_A", "torque_b")}

    def splits(self):
        """Kept postures split into train / validation / test; the samples are transitions among each split's
        postures."""
        from warp_vision.sim.arm import reach_pairs

        c = self.cfg
        ptr, pva, pte = (self.kept[s] for s in harness.splits(len(self.kept), c.seed, c.val_fraction, c.test_fraction,
                                                              min_test=2))
        rng = np.random.default_rng([c.seed, 1])
        hand, angles = self.data["hand"], self.data["angles"]
        pairs = [reach_pairs(ptr, c.transitions, rng, hand, angles)]
        for p in (pva, pte):
            pairs.append(reach_pairs(p, max(500, 4 * len(p)), rng, hand, angles))
        self.pairs = tuple(np.concatenate(p) for p in zip(*pairs))  # sample s is the pair (i[s], j[s])
        n = len(self.pairs[0])
        noisy = rng.uniform(size=(n, 1)) < 0.5
        a_in = self.data["act"][self.pairs[0]] + noisy * rng.normal(0, 0.05, (n, 63))
        self.act_in = torch.as_tensor(np.clip(a_in, 0, 1), dtype=torch.float32)
        self.test_postures = pte
        # joint velocities (rad/s) the nets are asked to damp: none for half the samples; and the voluntary
        # net's "current activations": the holding ones, perturbed for half the samples (in the loop they
        # are the muscles' true state, which differs)
        moving = rng.uniform(size=(n, 1)) < 0.5
        self.vel = torch.as_tensor(moving * rng.normal(0, c.velocity_std, (n, 7)), dtype=torch.float32)
        edges = np.cumsum([0] + [len(p[0]) for p in pairs])
        return tuple(np.arange(edges[k], edges[k + 1]) for k in range(3))

    def net_spec(self):
        return {"kind": "arm", "hidden": self.cfg.hidden, "seed": self.cfg.seed, "side": self.cfg.side}

    def data_config(self):
        from dataclasses import asdict

        return asdict(self.cfg.data_config())

    def _predict(self, net, idx, device):
        from warp_vision.sim.arm import demanded_torque

        model = net.module if hasattr(net, "module") else net
        idx = np.asarray(idx)
        i, j = (torch.as_tensor(p[idx]) for p in self.pairs)
        t, c = self.t, self.cfg
        v = self.vel[idx].to(device)
        angles, a_i = t["angles"][i].to(device), t["act"][i].to(device)
        A, b = t["torque_A"][i].to(device), t["torque_b"][i].to(device)
        vol = model.voluntary((t["hand"][j] - t["hand"][i]).to(device), self.act_in[idx].to(device), angles, v)
        pos = model.posture(angles, v)

        def residual(a, tau):  # the torque (N m) activations a leave short of holding posture i plus tau
            return ((A @ a.unsqueeze(-1)).squeeze(-1) - b - tau).norm(dim=-1)

        dq = t["angles"][j].to(device) - angles
        return {"vol": vol, "pos": pos, "a_i": a_i,
                "vtorque": residual(vol, demanded_torque(dq, v, c.stiffness, c.damping, c.saturation, xp=torch)),
                "ptorque": residual(pos, demanded_torque(torch.zeros_like(v), v, c.stiffness, c.posture_damping,
                                                         c.saturation, xp=torch))}

    def _losses(self, p):
        tw = self.cfg.torque_weight
        lv = torch.mean(torch.mean((p["vol"] - p["a_i"]) ** 2, -1) + tw * _soft_norm(p["vtorque"]))
        lp = torch.mean(torch.mean((p["pos"] - p["a_i"]) ** 2, -1) + tw * _soft_norm(p["ptorque"]))
        return lv, lp

    def batch_loss(self, net, idx, norm, device):
        lv, lp = self._losses(self._predict(net, idx, device))
        loss = lv + lp
        return loss, {"loss": loss.item(), "voluntary_loss": lv.item(), "posture_loss": lp.item()}

    def evaluate(self, model, idx, norm, device):
        with torch.no_grad():
            p = self._predict(model, idx, device)
            lv, lp = self._losses(p)
        rest = (self.vel[np.asarray(idx)].abs().sum(-1) == 0).to(p["pos"].device)
        return {"loss": float(lv + lp), "voluntary_loss": float(lv), "posture_loss": float(lp),
                "posture_rmse_at_rest": float(torch.sqrt(torch.mean((p["pos"][rest] - p["a_i"][rest]) ** 2))),
                "voluntary_torque_Nm_median": float(p["vtorque"].median()),
                "posture_torque_Nm_median": float(p["ptorque"].median())}

    def describe(self, model):
        return (f"arm nets ({self.cfg.side} arm, posture + voluntary MLPs, hidden {self.cfg.hidden}): "
                f"{sum(p.numel() for p in model.parameters()):,} parameters; {len(self.kept):,} of "
                f"{len(self.data['residual']):,} postures held within {self.cfg.max_residual} N m")

    def epoch_line(self, row):
        return (f"epoch {row['epoch']:3d}: train loss {row['train_loss']:.3e}  val loss {row['val_loss']:.3e} "
                f"torque short (median): voluntary {row['val_voluntary_torque_Nm_median']:.3f} N m, posture "
                f"{row['val_posture_torque_Nm_median']:.3f} N m; posture RMSE at rest "
                f"{row['val_posture_rmse_at_rest']:.4f}")

    def summary(self, test, history, model):
        from warp_vision.body import Body
        from warp_vision.sim.arm import HAND_SITE, evaluate_on_body

        self.log("checking the nets on the body (held-out postures and reaches)")
        body = self.body if getattr(self, "body", None) is not None else Body()
        on_body = evaluate_on_body(model.cpu().eval(), body, self.cfg.side, self.data, self.test_postures,
                                   n=self.cfg.body_checks, teacher_feedback=not self.cfg.skip_teacher_feedback,
                                   torque={"stiffness": self.cfg.stiffness, "damping": self.cfg.damping,
                                           "saturation": self.cfg.saturation})
        r = self.data["residual"]
        return {"side": self.cfg.side, "hand_point": f"{HAND_SITE}_{self.cfg.side[0]} (world = torso frame)",
                "reach_mode": "closed loop: the voluntary net every 10 ms on the remaining displacement from the true "
                              "hand, the true joint angles and velocities and the posture net's holding activations at "
                              "the current angles; open loop: its first output (from the start's holding activations) "
                              "applied throughout",
                "test_loss": test["loss"], "test_posture_rmse_at_rest": test["posture_rmse_at_rest"],
                "test_voluntary_torque_Nm_median": test["voluntary_torque_Nm_median"],
                "test_posture_torque_Nm_median": test["posture_torque_Nm_median"], **on_body,
                "postures": int(len(r)), "postures_held": int(len(self.kept)),
                "holding_residual_Nm_median": float(np.median(r)), "dataset": str(self.ddir)}

    def eval_line(self, run_dir, split, n, ev):
        return (f"{run_dir} ({split}, {n:,} transitions): loss {ev['loss']:.3e}, torque short (median) voluntary "
                f"{ev['voluntary_torque_Nm_median']:.3f} N m, posture {ev['posture_torque_Nm_median']:.3f} N m")


def run(cfg: ArmTrainConfig | None = None, **kw) -> dict:
    """Train (or resume) one arm's run: :func:`warp_vision.train.harness.run` for this task."""
    return harness.run(ArmTask, cfg, **kw)


def evaluate_run(run_dir: str, split: str = "test", log=print, checkpoint: str = "best") -> dict:
    """Re-evaluate an arm run's ``checkpoint`` (best or latest) on its held-out transitions."""
    return evaluation.evaluate_run(ArmTask, run_dir, split, log, checkpoint=checkpoint)
