"""The foveation task: from an ONV, the eye rotation (yaw, pitch) that brings the ball onto the fovea.

``python -m warp_vision.train [--preset smoke|quick|default|paper] [--flag value ...]``

The dataset is :mod:`warp_vision.data.foveation` (self-synthesised ONVs of a ball in a room, cached by its
config). The net is a liNet (or its fully-connected baseline) with a linear or soft-argmax read-out
(:mod:`warp_vision.nn.heads`), or with ``--model conv|cnn`` a weight-shared net with a heat map
(:mod:`warp_vision.nn.retina_conv`, :mod:`warp_vision.nn.retina_cnn`: turned and mirrored copies in
training), trained on standardised targets with a Huber loss (or the paper's MSE).
The run itself (directories, resume, DDP, checkpoints, early stopping) is :mod:`warp_vision.train.harness`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from warp_vision.frames import gaze_directions
from warp_vision.nn.retina_cnn import IMAGE_SIZE
from warp_vision.nn.trained import fit_input_norm, net_input, set_input_standardisation
from warp_vision.train import evaluation, harness
from warp_vision.train.config import TrainConfig, onv_dtype_name

#: Weight of the conv net's heat-map cross-entropy beside its regression loss (a cross-entropy of a few
#: nats against a Huber loss of about 0.05: the heat map leads early, the regression refines).
HEATMAP_WEIGHT = 0.02
#: The cnn's heat-map cross-entropy weight: its heat map is its read-out, so the cross-entropy leads.
CNN_HEATMAP_WEIGHT = 0.1
#: Huber loss threshold in standardised target units (the targets' std is about 20 degrees, so ~2 degrees).
HUBER_DELTA = 0.1


def angular_error_deg(pred: torch.Tensor, true: torch.Tensor) -> torch.Tensor:
    """Angle (degrees) between the gaze directions of predicted and true (yaw, pitch) [N, 2]."""
    c = (gaze_directions(pred.double()) * gaze_directions(true.double())).sum(1).clamp(-1.0, 1.0)
    return torch.rad2deg(torch.arccos(c)).float()


def train_loss(kind: str, pred: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """The training loss on standardised targets: "mse" (the paper's) or "huber" (quadratic within
    HUBER_DELTA of the target, linear beyond: a few balls too small or too hidden to localise do not
    dominate the gradient and the choice of the best epoch)."""
    if kind == "mse":
        return torch.nn.functional.mse_loss(pred, y)
    return torch.nn.functional.huber_loss(pred, y, delta=HUBER_DELTA)


#: deg: an estimate this far off has found another object than the ball.
OFF_DEG = 5.0


def mse_parts(se: torch.Tensor, err_deg: torch.Tensor) -> dict:
    """Where a foveation MSE comes from: the share of samples more than :data:`OFF_DEG` off
    (``over_5deg``), the share of the summed squared error they hold (``mse_share_off``), and the MSE of
    the others (``mse_within_5deg``). ``se``: each sample's squared standardised error (mean over yaw
    and pitch). A training MSE below some goal needs the missed share times their mean error below it:
    the misses, not the precision on the balls found, set the floor."""
    nan = float("nan")
    if len(se) == 0:
        return {"over_5deg": nan, "mse_share_off": nan, "mse_within_5deg": nan}
    off = err_deg > OFF_DEG
    total = float(se.sum())
    return {"over_5deg": float(off.float().mean()),
            "mse_share_off": float(se[off].sum()) / total if total > 0 else 0.0,
            "mse_within_5deg": float(se[~off].mean()) if bool((~off).any()) else nan}


#: The bands :func:`miss_breakdown` groups the balls by: eccentricity of the ball's direction and its
#: apparent radius (degrees, lower edges).
ECC_BANDS_DEG = (0.0, 10.0, 20.0, 30.0, 40.0)
RADIUS_BANDS_DEG = (0.0, 1.0, 2.0, 4.0, 6.0, 8.0, 11.0, 15.0)
#: The dataset's meta columns that flag what else is in the scene (those the generator writes).
SCENE_FLAGS = ("occluded", "glow", "distractor", "arm", "decoy")
#: :func:`miss_breakdown`'s bands of the ball's signal (:func:`warp_vision.data.foveation.ball_signal`):
#: the photoreceptors that see it and its contrast with its surround (lower edges).
RECEPTOR_BANDS = (0, 5, 10, 20, 40, 80, 160, 320)
CONTRAST_BANDS = (0.0, 0.05, 0.1, 0.2, 0.4, 0.8, 1.6, 10.0)
#: A ball "barely seen" (:func:`barely_seen`): fewer photoreceptors on it, or a lower contrast, than these.
BARELY_RECEPTORS = 5
BARELY_CONTRAST = 0.05


def barely_seen(err_deg, signal: dict) -> dict:
    """The balls the ONV barely holds (fewer than :data:`BARELY_RECEPTORS` photoreceptors see them, or their
    contrast is under :data:`BARELY_CONTRAST`, or NaN: no ring around them seen): their share of the balls
    (``share``), the share of them more than :data:`OFF_DEG` off (``off``), their share of all the misses
    (``of_misses``), and the misses among the other balls as a share of all balls (``others_off``): the
    least a net must find of the rest."""
    err = np.asarray(err_deg, np.float64)
    contrast = np.nan_to_num(np.asarray(signal["contrast"], np.float64), nan=0.0)
    weak = (np.asarray(signal["receptors"]) < BARELY_RECEPTORS) | (contrast < BARELY_CONTRAST)
    off = err > OFF_DEG
    n = max(len(err), 1)
    return {"share": float(weak.sum()) / n, "off": float(off[weak].mean()) if weak.any() else float("nan"),
            "of_misses": float((off & weak).sum()) / max(int(off.sum()), 1),
            "others_off": float((off & ~weak).sum()) / n}


def miss_breakdown(err_deg, target, meta, columns, signal: dict | None = None) -> list[dict]:
    """Where the balls more than :data:`OFF_DEG` off lie: one row per eccentricity band, apparent-radius
    band and scene flag (on and off) with its samples ``n``, the share of them off (``off``) and their
    share of all the misses (``of_misses``). ``err_deg`` [N], ``target`` [N, 2] (yaw, pitch, rad),
    ``meta`` [N, C] with ``columns`` its names (:func:`warp_vision.data.foveation.meta_columns`; v7's
    three have no scene flag but occluded). ``signal``: the samples' :func:`~warp_vision.data.foveation.
    ball_signal` (with the estimates as ``directions``), which adds rows per band of photoreceptors on the
    ball and of its contrast, and per class of what the estimate lands on; with ``chance_landed_on`` as well,
    those rows carry ``chance``: the share of the chance directions landing on that class."""
    err, meta = np.asarray(err_deg, dtype=np.float64), np.asarray(meta, dtype=np.float64)
    off = err > OFF_DEG
    misses = max(int(off.sum()), 1)
    axis = gaze_directions(torch.zeros(1, 2, dtype=torch.float64))
    d = gaze_directions(torch.as_tensor(np.asarray(target), dtype=torch.float64))
    ecc = np.degrees(np.arccos(np.clip((d * axis).sum(1).numpy(), -1.0, 1.0)))
    col = {c: k for k, c in enumerate(columns)}
    radius = np.degrees(np.arcsin(np.clip(meta[:, col["radius_m"]] / meta[:, col["distance_m"]], 0.0, 1.0)))

    def row(group, label, m):
        n = int(m.sum())
        return {"group": group, "bin": label, "n": n, "off": float(off[m].mean()) if n else float("nan"),
                "of_misses": float(off[m].sum()) / misses}

    rows = []
    for group, v, edges in (("eccentricity (deg)", ecc, ECC_BANDS_DEG),
                            ("apparent radius (deg)", radius, RADIUS_BANDS_DEG)):
        for lo, hi in zip(edges, edges[1:] + (np.inf,)):
            rows.append(row(group, f"{lo:g}-{hi:g}" if np.isfinite(hi) else f">= {lo:g}", (v >= lo) & (v < hi)))
    for flag in SCENE_FLAGS:
        if flag in col:
            on = meta[:, col[flag]] > 0.5
            rows += [row(flag, "yes", on), row(flag, "no", ~on)]
    if signal is not None:
        from warp_vision.data.foveation import LANDED_ON

        bands = (("photoreceptors on the ball", np.asarray(signal["receptors"], np.float64), RECEPTOR_BANDS),
                 ("ball's contrast", np.nan_to_num(np.asarray(signal["contrast"], np.float64), nan=0.0),
                  CONTRAST_BANDS))
        for group, v, edges in bands:
            for lo, hi in zip(edges, edges[1:] + (np.inf,)):
                rows.append(row(group, f"{lo:g}-{hi:g}" if np.isfinite(hi) else f">= {lo:g}", (v >= lo) & (v < hi)))
        if "landed_on" in signal:
            landed = np.asarray(signal["landed_on"], dtype=object)
            chance = np.asarray(signal["chance_landed_on"], dtype=object) if "chance_landed_on" in signal else None
            for c in LANDED_ON:
                rows.append(row("estimate lands on", c, landed == c))
                if chance is not None:
                    rows[-1]["chance"] = float((chance == c).mean()) if len(chance) else float("nan")
    return [r for r in rows if r["n"]]


def miss_table(rows: list[dict]) -> str:
    """:func:`miss_breakdown`'s rows as a markdown table."""
    lines = [f"| group | bin | ONVs | > {OFF_DEG:g} deg off | share of the misses |", "|---|---|---|---|---|"]
    lines += [f"| {r['group']} | {r['bin']} | {r['n']:,} | {100 * r['off']:.1f}% | {100 * r['of_misses']:.1f}%"
              + (f" (chance {100 * r['chance']:.1f}%)" if "chance" in r else "") + " |" for r in rows]
    return "\n".join(lines)


def miss_agreement(names, preds, target) -> dict:
    """Whether several nets miss the same balls: ``preds`` [K] of [N, 2] (yaw, pitch, rad), each net's
    estimates for the same ``target`` [N, 2]. Returns ``off`` (each net's share more than :data:`OFF_DEG`
    off), ``pairs`` (per pair: ``both`` off as a share of all, ``independent``, the product of the two shares,
    what two nets missing independently would give, ``shared``, the share of the first's misses the second
    also misses, ``same_wrong``, the share of all where both are off and within :data:`OFF_DEG` of each
    other: the same wrong thing) and ``best_of`` (the share off when, for every ball, the best of the nets
    is taken: what no way of choosing among them can beat)."""
    if len(names) != len(preds) or len(names) < 2:
        raise ValueError(f"miss_agreement: two or more nets, one name each; got {len(names)} names, {len(preds)} "
                         "estimates")
    true = torch.as_tensor(np.asarray(target), dtype=torch.float64)
    pred = [torch.as_tensor(np.asarray(p), dtype=torch.float64) for p in preds]
    if any(p.shape != true.shape for p in pred):
        raise ValueError(f"miss_agreement: every net's estimates must be shaped like the targets {tuple(true.shape)}")
    err = [angular_error_deg(p, true).double().numpy() for p in pred]
    off = [e > OFF_DEG for e in err]
    pairs = []
    for a in range(len(names)):
        for b in range(a + 1, len(names)):
            near = angular_error_deg(pred[a], pred[b]).double().numpy() <= OFF_DEG
            both = off[a] & off[b]
            pairs.append({"a": names[a], "b": names[b], "both": float(both.mean()),
                          "independent": float(off[a].mean() * off[b].mean()),
                          "shared": float(both.sum() / off[a].sum()) if off[a].any() else float("nan"),
                          "same_wrong": float((both & near).mean())})
    return {"names": list(names), "n": len(true), "off": [float(o.mean()) for o in off], "pairs": pairs,
            "best_of": float((np.min(err, axis=0) > OFF_DEG).mean())}


def agreement_table(r: dict) -> str:
    """:func:`miss_agreement`'s pairs as a markdown table, its best-of line below."""
    lines = ["| net A | net B | A off | B off | both off | if independent | A's misses B shares | the same wrong thing "
             "|",
             "|---|---|---|---|---|---|---|---|"]
    off = dict(zip(r["names"], r["off"]))
    for q in r["pairs"]:
        lines.append(f"| {q['a']} | {q['b']} | {100 * off[q['a']]:.1f}% | {100 * off[q['b']]:.1f}% | "
                     f"{100 * q['both']:.1f}% | {100 * q['independent']:.1f}% | {100 * q['shared']:.0f}% | "
                     f"{100 * q['same_wrong']:.1f}% |")
    lines.append(f"the best of the {len(r['names'])} nets for every ball (an oracle): {100 * r['best_of']:.1f}% of the "
                 f"{r['n']:,} balls more than {OFF_DEG:g} deg off")
    return "\n".join(lines)


#: The settings that fix the shapes of a foveation net's weights, per model: a warm start (``--init``)
#: needs them equal (the cnn reads a resampled image of fixed size, whatever the retina).
SHAPE_SETTINGS = {"linet": ("photoreceptors", "layers", "receptive_field", "reduction"),
                  "fc": ("photoreceptors", "layers", "receptive_field", "reduction"),
                  "conv": ("photoreceptors", "layers", "reduction", "channels"),
                  "cnn": ("channels",)}
#: The models whose weights are shared across the retina: a warm start from the other eye's net is meaningful
INIT_ACROSS_EYES = ("cnn", "conv")


class FoveationTask(harness.OnvTask):
    name = "foveation"
    config_cls = TrainConfig
    data_module = "warp_vision.data.foveation"

    @classmethod
    def check_new_run(cls, cfg):
        """``--init``: a foveation net's checkpoint of this run's model and sizes, refused before any data is
        rendered. The other eye's net is a meaningful start only for a net whose weights are shared across the
        retina (:data:`INIT_ACROSS_EYES`): a liNet's or fc net's weights belong to one eye's photoreceptors."""
        if not cfg.init:
            return
        import errno

        from warp_vision.nn.trained import (
            binding,
            describe_binding,
            read_checkpoint,
            read_run_config,
            run_identity,
            saved_task,
        )
        from warp_vision.train.rundir import a_run, init_checkpoint

        best = init_checkpoint(cfg.init)
        if not best.is_file():
            raise FileNotFoundError(errno.ENOENT,
                                    "no such checkpoint (--init takes a foveation run directory or its best.pt)",
                                    str(best))
        run = best.parent
        saved = read_run_config(run)
        if saved is not None:
            if (task := saved_task(run, saved)) != cls.name:
                raise ValueError(f"init: {run} is {a_run(task)}; --init takes a foveation run of the net this run "
                                 "trains")
            there = run_identity(cls.name, saved)
        else:  # a checkpoint on its own: what it belongs to is in it
            there = binding(read_checkpoint(best))
            if there["task"] != cls.name:
                raise ValueError(f"init: {best} is {a_run(there['task'])}'s; --init takes a foveation run of the net "
                                 f"this run trains")
        if there.get("eye") not in (None, cfg.eye):
            if cfg.model not in INIT_ACROSS_EYES:
                raise ValueError(f"init: {best} belongs to {describe_binding(there)}; a {cfg.model} net's weights "
                                 f"belong to its own eye's photoreceptors, so --init across eyes is refused (it is "
                                 f"meaningful for --model {' or '.join(INIT_ACROSS_EYES)}, whose weights are shared "
                                 "across the retina)")
            print(f"init: starting the {cfg.eye} eye's net from {describe_binding(there)} ({best}): --model "
                  f"{cfg.model} shares its weights across the retina, so they carry over to this eye's")
        if saved is None:
            return  # a checkpoint on its own: its weights are checked as they load
        there = {"model": "linet", **saved}  # (a config older than its model)
        keys = ("model",) if there["model"] != cfg.model else SHAPE_SETTINGS[cfg.model]
        differ = [k for k in keys if k in there and there[k] != getattr(cfg, k)]
        if differ:
            raise ValueError(
                f"init: {run} trained another net than this run's: "
                + ", ".join(f"--{k.replace('_', '-')} {there[k]} there, {getattr(cfg, k)} here" for k in differ)
            )

    def dataset_dirs(self):
        return [harness.dataset_dir(self.cfg, "foveation", self.cfg.data_config())]

    def render(self, shard, progress):
        from warp_vision.data.foveation import synthesize

        synthesize(self.dataset_dirs()[0], self.cfg.data_config(), shard=shard, progress=progress, log=self.log)

    def load(self, shard, progress, synthesize: bool = True):
        from warp_vision.data.store import ChunkedStore
        from warp_vision.eye.retina import Retina

        self.ddir = self.dataset_dirs()[0]
        if synthesize:
            self.render(shard, progress)
        data = ChunkedStore.open(self.ddir).load(["onv", "target"])
        self.onv16, self.target = torch.from_numpy(data["onv"]), torch.from_numpy(data["target"])
        self.retina = Retina.load(self.ddir / "retina.npz")

    def splits(self):
        c = self.cfg
        return harness.splits(len(self.target), c.data_seed, c.val_fraction, c.test_fraction)

    def fit_norm(self, train):
        t = self.target[torch.as_tensor(train)]
        return {**fit_input_norm(self.onv16, train, per_sample=self.cfg.per_sample_input()), "target_mean": t.mean(0),
                "target_std": t.std(0).clamp_min(1e-6)}

    def net_spec(self):
        from warp_vision.data.foveation import make_eye

        c = self.cfg
        angles = self.retina.visual_angles(make_eye(c.data_config())) if c.head_kind() == "softargmax" else None
        return {"kind": "foveation", "model": c.model, "head": c.head_kind(), "layers": c.layers,
                "channels": c.channels, "receptive_field": c.receptive_field, "reduction": c.reduction, "seed": c.seed,
                "onv_dtype": onv_dtype_name(c),
                "photoreceptor_xy": torch.from_numpy(np.asarray(self.retina.domain_xy, np.float64)),
                "photoreceptor_angles": None if angles is None else torch.from_numpy(np.asarray(angles, np.float64)),
                **({"image_size": IMAGE_SIZE, "views": c.views} if c.model == "cnn" else {})}

    def prepare(self, model, norm):
        model.set_target_norm(norm["target_mean"], norm["target_std"])
        set_input_standardisation(model, norm)

    def describe(self, model):
        if self.cfg.model == "cnn":
            return (f"cnn ({model.warp.size} x {model.warp.size} foveated image, heat map read-out): "
                    f"{sum(p.numel() for p in model.parameters()):,} parameters")
        b = model.backbone
        layers = getattr(b, "layer_sizes", None) or [
            f"{n}x{c}" for n, c in zip(getattr(b, "layer_sites", [])[1:], getattr(b, "channels", []))]
        return (f"{self.cfg.model} ({self.cfg.head_kind()} head): {sum(p.numel() for p in model.parameters()):,} "
                f"parameters, layers {layers}")

    def batch_loss(self, net, idx, norm, device):
        if self.cfg.model == "cnn":  # turned and mirrored copies, four groups a batch
            return self._cnn_batch_loss(net, idx, norm, device)
        y = ((self.target[idx] - norm["target_mean"]) / norm["target_std"]).to(device)
        x = net_input(self.onv16[idx], norm, device, self.onv_dtype)
        if self.cfg.model == "conv":  # the saliency maps also learn where the ball is, site by site
            pred, logits = net(x, with_logits=True)
            inner = getattr(net, "module", net)  # under DDP
            loss = train_loss(self.cfg.loss, pred,
                              y) + HEATMAP_WEIGHT * inner.heatmap_loss(logits, self.target[idx].to(device))
        else:
            pred = net(x)
            loss = train_loss(self.cfg.loss, pred, y)
        return loss, {"loss": float(loss.detach()), "mse": float(torch.nn.functional.mse_loss(pred.detach(), y))}

    def _cnn_batch_loss(self, net, idx, norm, device, groups: int = 4):
        """The cnn's loss: the batch in ``groups`` consecutive groups, each binned through a random
        augmentation with its targets turned alike (``cfg.no_augment``, and in the last ``cfg.plain_epochs`` epochs:
        every group the plain image), in one forward pass (one pass under DDP, and batch norm sees the whole batch)."""
        from warp_vision.nn.retina_cnn import ROTATIONS

        inner = getattr(net, "module", net)  # under DDP
        if self.cfg.no_augment or self.epoch >= self.cfg.epochs - self.cfg.plain_epochs:
            ks = [0] * groups
        else:
            ks = [int(k) for k in torch.randint(2 * ROTATIONS, (groups,))]
        target = self.target[idx]
        true = torch.cat([inner.transform_targets(t, k) for t, k in zip(torch.tensor_split(target, groups), ks)])
        y = ((true - norm["target_mean"]) / norm["target_std"]).to(device)
        pred, logits = net(net_input(self.onv16[idx], norm, device, self.onv_dtype), transform=ks, with_logits=True)
        loss = train_loss(self.cfg.loss, pred, y) + CNN_HEATMAP_WEIGHT * inner.heatmap_loss(logits, true.to(device))
        return loss, {"loss": float(loss.detach()), "mse": float(torch.nn.functional.mse_loss(pred.detach(), y))}

    def evaluate(self, model, idx, norm, device, batch: int = 256):
        model.eval()
        preds = []
        with torch.no_grad():
            for s in range(0, len(idx), batch):
                preds.append(model(net_input(self.onv16[torch.as_tensor(idx[s : s + batch])], norm, device,
                                             self.onv_dtype)).cpu())
        model.train()
        z = torch.cat(preds) if preds else torch.zeros(0, 2)
        true = self.target[torch.as_tensor(idx)]
        zt = (true - norm["target_mean"]) / norm["target_std"]
        pred = z * norm["target_std"] + norm["target_mean"]
        err = angular_error_deg(pred, true)
        some = len(idx) > 0
        nan = float("nan")
        se = ((z - zt) ** 2).mean(1) if some else torch.zeros(0)
        return {"mse": float(se.mean()) if some else nan,
                "loss": float(train_loss(self.cfg.loss, z, zt)) if some else nan,
                "median_deg": float(err.median()) if some else nan,
                "p90_deg": float(torch.quantile(err, 0.9)) if some else nan,
                **mse_parts(se, err), "pred": pred, "err_deg": err}

    def validate(self, model, idx, norm, device):
        """One view per epoch (the plain image, as the net trains), not the consensus of ``views`` that the
        test, ``evaluate`` and the simulation read: 8 views cost 8 times the inference, a large share of a
        default epoch (docs/RESULTS.md, "The consensus read-out, and 32,000 ONVs")."""
        if not hasattr(model, "views"):
            return self.evaluate(model, idx, norm, device)
        views, model.views = model.views, 1
        try:
            return self.evaluate(model, idx, norm, device)
        finally:
            model.views = views

    def epoch_line(self, row):
        k = self.cfg.loss
        return (f"epoch {row['epoch']:3d}: train {k} {row['train_loss']:.4f} MSE {row['train_mse']:.4f}  val {k} "
                f"{row['val_loss']:.4f} MSE {row['val_mse']:.4f}  val median {row['val_median_deg']:.2f} deg")

    def summary(self, test, history, model):
        c = self.cfg
        best = min(history, key=lambda r: r["val_loss"]) if history else {}
        return {"model": c.model, "head": c.head_kind(), "loss": c.loss, "best_val_mse": best.get("val_mse"),
                "first_epoch_train_mse_below_0.01": next((h["epoch"] for h in history if h["train_mse"] < 0.01), None),
                "test_mse": test["mse"], "test_median_deg": test["median_deg"], "test_p90_deg": test["p90_deg"],
                "test_over_5deg": test["over_5deg"], "test_mse_within_5deg": test["mse_within_5deg"],
                "dataset": str(self.ddir)}

    def figures(self, out, history, test, idx):
        from warp_vision.train.figures import write_figures

        write_figures(out, history, self.retina, self.onv16, self.target, idx, test["pred"], self.cfg)

    def eval_line(self, run_dir, split, n, ev):
        return (f"{run_dir} ({split}, {n:,} ONVs): MSE {ev['mse']:.4f}; angular error median {ev['median_deg']:.3f} "
                f"deg, 90th percentile {ev['p90_deg']:.3f} deg; {100 * ev['over_5deg']:.1f}% more than {OFF_DEG:g} deg "
                f"off (another object found) hold {100 * ev['mse_share_off']:.1f}% of the MSE; the rest's MSE "
                + (f"{ev['mse_within_5deg']:.4f}" if ev["over_5deg"] != 1 else "none: every one is off"))


def run(cfg: TrainConfig | None = None, **kw) -> dict:
    """Train (or resume) a foveation run: :func:`warp_vision.train.harness.run` for this task."""
    return harness.run(FoveationTask, cfg, **kw)


def evaluate_run(run_dir: str, split: str = "test", log=print, misses: bool = False, signal: bool = False,
                 progress: bool = True, checkpoint: str = "best", views: int | None = None) -> dict:
    """Re-evaluate a foveation run's ``checkpoint`` (best or latest: :func:`evaluation.evaluate_run`, as ``views``);
    prints the angular error. ``misses``: also where the
    balls more than :data:`OFF_DEG` off lie (:func:`miss_breakdown`), printed as a table and returned as
    ``"misses"``, and drawn in ``RUN/figures/misses_<split>.png``. ``signal`` (with ``misses``; v8 and v9
    runs): the split is rendered again with and without its balls
    (:func:`warp_vision.data.foveation.ball_signal`; about 0.1 s an ONV here), which adds the bands of the
    ball's signal, what the estimates land on and the :func:`barely_seen` summary (``"barely_seen"``)."""
    if signal and not misses:
        raise ValueError("signal: a part of the misses' breakdown; pass misses=True too")
    detail = (lambda task, idx, ev,
              log: _misses(task, idx, ev, log, run_dir, split, signal, progress)) if misses else None
    return evaluation.evaluate_run(FoveationTask, run_dir, split, log, detail=detail, checkpoint=checkpoint,
                                   views=views,
                                progress=progress)


def evaluate_agreement(run_dirs, split: str = "test", log=print) -> dict:
    """Whether foveation runs trained on one dataset miss the same balls of its ``split``
    (:func:`miss_agreement`; each run's best checkpoint, read out as it is for its test)."""
    if len(run_dirs) < 2:
        raise ValueError("agreement: give two or more runs")
    got = []

    def keep(task, idx, ev, log):
        got.append((str(Path(task.ddir).resolve()), np.asarray(idx), ev["pred"].numpy(),
                    task.target[torch.as_tensor(np.asarray(idx))].numpy()))
        return {}

    for run_dir in run_dirs:
        evaluation.evaluate_run(FoveationTask, run_dir, split, log, detail=keep)
    for run_dir, (ddir, idx, _, _) in zip(run_dirs[1:], got[1:]):
        if ddir != got[0][0] or not np.array_equal(idx, got[0][1]):
            raise ValueError(f"agreement: {run_dir} does not share {run_dirs[0]}'s dataset and {split} split "
                             f"({ddir} against {got[0][0]}): the nets must see the same balls")
    short = [Path(r).name for r in run_dirs]
    names = short if len(set(short)) == len(short) else [str(r) for r in run_dirs]
    r = miss_agreement(names, [g[2] for g in got], got[0][3])
    log(f"whether the nets miss the same balls ({split}, {r['n']:,} ONVs; more than {OFF_DEG:g} deg "
        f"off):\n{agreement_table(r)}")
    return r


def write_miss_figure(run_dir, split: str, rows: list[dict], n: int) -> Path:
    """``RUN/figures/misses_<split>.png``: :func:`warp_vision.train.figures.plot_misses` of ``rows``."""
    from warp_vision.fileio import atomic_write
    from warp_vision.train.figures import plot_misses

    path = Path(run_dir) / "figures" / f"misses_{split}.png"
    path.parent.mkdir(parents=True, exist_ok=True)
    fig = plot_misses(rows,
                      f"{Path(run_dir).name}: where the balls more than {OFF_DEG:g} deg off lie ({split}, {n:,} ONVs)")
    atomic_write(path, lambda f: fig.savefig(f, format="png", dpi=110, bbox_inches="tight"))
    return path


def _misses(task: FoveationTask, idx, ev, log, run_dir, split: str, signal: bool = False,
            progress: bool = True) -> dict:
    from warp_vision.data.foveation import ball_signal, make_eye, meta_columns
    from warp_vision.data.store import ChunkedStore

    idx = np.asarray(idx)
    meta = ChunkedStore.open(task.ddir).load(["meta"])["meta"][idx]
    sig = None
    if signal:
        cfg = task.cfg.data_config()
        if cfg.generator < 8:
            raise ValueError(
                f"signal: generator {cfg.generator}: v8 and v9 runs only (v7's ball glows in a fixed room)"
            )
        # chance: each scene probed along the next sample's ball direction, drawn as the targets are
        chance = task.target[torch.as_tensor(np.roll(idx, -1))].numpy()
        sig = ball_signal(cfg, idx, task.retina, make_eye(cfg), directions=ev["pred"].numpy(), progress=progress,
                          chance_directions=chance)
    rows = miss_breakdown(ev["err_deg"].numpy(), task.target[torch.as_tensor(idx)].numpy(), meta,
                          meta_columns(task.cfg.generator), signal=sig)
    log(f"where the balls more than {OFF_DEG:g} deg off lie:\n{miss_table(rows)}")
    fig = write_miss_figure(run_dir, split, rows, len(idx))
    log(f"wrote {fig}")
    if sig is None:
        return {"misses": rows}
    b = barely_seen(ev["err_deg"].numpy(), sig)
    log(f"barely seen (fewer than {BARELY_RECEPTORS} photoreceptors on the ball, or contrast under "
        f"{BARELY_CONTRAST:g}): {100 * b['share']:.1f}% of the balls, {100 * b['off']:.0f}% of them off, "
        f"{100 * b['of_misses']:.1f}% of the misses; the balls seen better are missed in {100 * b['others_off']:.1f}% "
        "of all samples")
    return {"misses": rows, "barely_seen": b}
