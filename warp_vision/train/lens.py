"""The lens task: each eye's lens net (:class:`warp_vision.nn.intraocular.LensNet`) from (ONV, current
pupil) to the signed defocus of the current accommodation (accommodation minus the fixated object's
vergence, dioptres).

``python -m warp_vision.train lens --eye left|right [--preset smoke|quick|default] [--flag value ...]``

The dataset is :func:`warp_vision.data.intraocular.synthesize_lens`: textured cards at 0.2-5 m filling
the central field, the lens at random states within ``defocus_range_D`` of them (half the samples near
focus). The loss is Huber (1 D) on the defocus. The best epoch has the smallest validation median error;
the summary reports the test split's and a held-out set's (new textures, lamps and distances) median and
90th percentile absolute error (D) and the share of samples beyond 0.5 D whose sign is right. After
training the net's bias near focus is tabulated against the lens state on the training split
(:func:`fit_bias`, :meth:`LensTask.calibrate`, stored in best.pt); the loop subtracts it
(:meth:`warp_vision.nn.intraocular.LensNet.calibrated`), and the summary's ``heldout_calibrated`` scores
the held-out set so.
"""

from __future__ import annotations

import numpy as np
import torch

from warp_vision.nn.intraocular import LENS_BIAS_KNOTS_D
from warp_vision.train import evaluation, harness
from warp_vision.train.config_intraocular import LensTrainConfig
from warp_vision.train.intraocular import ShallowNetTask

#: The sign of the defocus is scored on samples whose defocus exceeds this (D).
SIGN_ABOVE_D = 0.5
#: The calibration's median error is taken over training samples this near focus (D) ...
CALIBRATE_WITHIN_D = 0.6
#: ... at least this many of them within half a knot spacing of an accommodation knot (else interpolated).
CALIBRATE_MIN_SAMPLES = 20


def fit_bias(pred: np.ndarray, defocus: np.ndarray, accommodation: np.ndarray) -> np.ndarray:
    """The lens net's bias table (:attr:`warp_vision.nn.intraocular.LensNet.bias_D`): at each accommodation
    knot the median of estimate minus truth over samples near focus (where the loop's lens comes to rest)
    whose accommodation is within half a knot spacing of it. Knots with too few samples take their nearest fitted
    neighbours' values (linear interpolation, held flat beyond the ends); none fitted: zeros."""
    pred, defocus, accommodation = (np.asarray(a, np.float64).reshape(-1) for a in (pred, defocus, accommodation))
    if not (len(pred) == len(defocus) == len(accommodation)):
        raise ValueError("fit_bias: expected as many estimates, defocuses and accommodations")
    near = np.abs(defocus) < CALIBRATE_WITHIN_D
    half = (LENS_BIAS_KNOTS_D[1] - LENS_BIAS_KNOTS_D[0]) / 2
    fitted, values = [], []
    for k in LENS_BIAS_KNOTS_D:
        m = near & (np.abs(accommodation - k) <= half)
        if m.sum() >= CALIBRATE_MIN_SAMPLES:
            fitted.append(k)
            values.append(np.median(pred[m] - defocus[m]))
    if not fitted:
        return np.zeros(len(LENS_BIAS_KNOTS_D))
    return np.interp(LENS_BIAS_KNOTS_D, fitted, values)


def _errors(pred: torch.Tensor, true: torch.Tensor) -> dict:
    e = (pred - true).abs()
    big = true.abs() > SIGN_ABOVE_D
    return {
        "loss": float(torch.nn.functional.huber_loss(pred, true)),
        "median_error_D": float(e.median()),
        "p90_error_D": float(torch.quantile(e, 0.9)),
        "sign_correct_above_0.5D": float((torch.sign(pred[big]) == torch.sign(true[big])).float().mean())
        if big.any()
        else float("nan"),
        "median_error_D_within_0.5D": float(e[~big].median()) if (~big).any() else float("nan"),
    }


class LensTask(ShallowNetTask):
    name = "lens"
    config_cls = LensTrainConfig
    selection = {"median_error_D": "min"}
    target = "defocus"
    raw_kwargs = {"central_only": True}

    def _render_set(self, dcfg, ddir, shard, progress, synthesize):
        from warp_vision.data.foveation import FoveationDataConfig, make_retina
        from warp_vision.data.intraocular import central_photoreceptors, synthesize_lens
        from warp_vision.data.store import ChunkedStore

        self.retina = make_retina(FoveationDataConfig(photoreceptors=self.cfg.photoreceptors, eye=self.cfg.eye))
        self.central = central_photoreceptors(self.retina, self.cfg.central_deg)
        if synthesize:
            synthesize_lens(ddir, dcfg, shard=shard, progress=progress, log=self.log)
        d = ChunkedStore.open(ddir).load(["onv", "defocus", "pupil", "distance", "accommodation"])
        return {k: torch.as_tensor(v) for k, v in d.items()}

    def net_spec(self):
        c = self.cfg
        return {"kind": "lens", "photoreceptor_xy": torch.from_numpy(np.asarray(self.retina.domain_xy, np.float64)),
                "central": torch.from_numpy(self.central.astype(np.int64)), "photoreceptors": c.photoreceptors,
                "hidden": c.hidden, "samples_per_receptor": c.samples_per_receptor, "seed": c.seed}

    def fit_norm(self, train):
        # the contrast floor: a decade of energy under the faintest 1% of the training images
        f = self.data["raw"][torch.as_tensor(train)]
        return {**super().fit_norm(train), "contrast_floor": torch.quantile(self._net().contrast(f), 0.01) - 1.0}

    def loss(self, pred, true):
        return torch.nn.functional.huber_loss(pred, true)

    def calibrate(self, model, train_ids, device):
        with torch.no_grad():
            pred, true = self._predict(model, self.data, train_ids, device)
        acc = self.data["accommodation"][torch.as_tensor(np.asarray(train_ids))]
        bias = fit_bias(pred.cpu().numpy(), true.cpu().numpy(), acc.numpy())
        with torch.no_grad():
            model.bias_D.copy_(torch.as_tensor(bias, dtype=model.bias_D.dtype))
        if not np.any(bias):  # (no knot had its samples: a smoke-sized run)
            self.log(f"lens net's bias near focus: not fitted, no accommodation has {CALIBRATE_MIN_SAMPLES} training "
                     f"samples within {CALIBRATE_WITHIN_D:g} D of focus; none is subtracted")
        else:
            self.log("lens net's bias near focus (D) at accommodations "
                     + ", ".join(f"{k:g}: {b:+.3f}" for k, b in zip(LENS_BIAS_KNOTS_D[::2], bias[::2])))
        return True

    def summary(self, test, history, model):
        out = super().summary(test, history, model)
        # the same held-out ONVs, the estimate calibrated by the lens state it was seen with (what the loop uses)
        pred, true = (torch.as_tensor(a) for a in self.heldout_pred)
        out["heldout_calibrated"] = self.errors(model.calibrated(pred, self.heldout["accommodation"]), true)
        out["bias_D"] = model.bias_D.tolist()
        return out

    def errors(self, pred, true):
        return _errors(pred, true)

    def describe(self, model):
        return (f"lens net ({self.cfg.eye} eye, {len(self.central):,} central photoreceptors, hidden "
                f"{self.cfg.hidden}): {sum(p.numel() for p in model.parameters()):,} parameters")

    def epoch_line(self, row):
        return (f"epoch {row['epoch']:3d}: train loss {row['train_loss']:.3e}  val median error "
                f"{row['val_median_error_D']:.3f} D, sign right beyond 0.5 D: "
                f"{100 * row['val_sign_correct_above_0.5D']:.1f}%")

    def figures(self, out, history, test, idx):
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        pred, true = self.heldout_pred
        dist = self.heldout["distance"].numpy()
        fig, ax = plt.subplots(1, 2, figsize=(10, 4))
        sc = ax[0].scatter(true, pred, c=np.log10(dist), s=6, cmap="viridis")
        fig.colorbar(sc, ax=ax[0], label="log10 card distance (m)")
        lim = [float(min(true.min(), pred.min())), float(max(true.max(), pred.max()))]
        ax[0].plot(lim, lim, "k-", lw=0.8)
        ax[0].set(xlabel="true defocus (D)", ylabel="lens net's estimate (D)",
                  title=f"{self.cfg.eye} eye, held-out cards")
        ax[1].hist(pred - true, bins=60, color="C1")
        ax[1].set(xlabel="error (D)", ylabel="held-out ONVs")
        self.save_figure(fig, out, "lens.png")

    def eval_line(self, run_dir, split, n, ev):
        return (f"{run_dir} ({split}, {n:,} ONVs): median error {ev['median_error_D']:.3f} D, p90 "
                f"{ev['p90_error_D']:.3f} D, sign right beyond 0.5 D: {100 * ev['sign_correct_above_0.5D']:.1f}%")


def run(cfg: LensTrainConfig | None = None, **kw) -> dict:
    """Train (or resume) one eye's lens run: :func:`warp_vision.train.harness.run` for this task."""
    return harness.run(LensTask, cfg, **kw)


def evaluate_run(run_dir: str, split: str = "test", log=print, checkpoint: str = "best") -> dict:
    """Re-evaluate a lens run's ``checkpoint`` (best or latest) on its held-out ONVs."""
    return evaluation.evaluate_run(LensTask, run_dir, split, log, checkpoint=checkpoint)
