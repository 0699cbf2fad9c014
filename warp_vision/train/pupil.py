"""The pupil task: each eye's pupil net (:class:`warp_vision.nn.intraocular.PupilNet`) from (ONV,
current pupil) to Watson & Yellott's steady-state pupil of the scene's adapting luminance.

``python -m warp_vision.train pupil --eye left|right [--preset smoke|quick|default] [--flag value ...]``

The dataset is :func:`warp_vision.data.intraocular.synthesize_pupil` (v8 scenes through random pupils at
random light levels over ``luminance_decades`` decades). The loss is the squared error in mm. The best
epoch has the smallest validation median error; the summary reports the test split's and a held-out
set's (rooms training never sees) errors: median and 90th percentile in mm and relative to the teacher,
and the share within 5%.
"""

from __future__ import annotations

import numpy as np
import torch

from warp_vision.train import evaluation, harness
from warp_vision.train.config_intraocular import PupilTrainConfig
from warp_vision.train.intraocular import ShallowNetTask


def _errors(pred: torch.Tensor, true: torch.Tensor) -> dict:
    e = (pred - true).abs()
    rel = e / true
    return {"loss": float(torch.mean((pred - true) ** 2)), "median_error_mm": float(e.median()),
            "p90_error_mm": float(torch.quantile(e, 0.9)), "median_relative_error": float(rel.median()),
            "p90_relative_error": float(torch.quantile(rel, 0.9)), "within_5pct": float((rel <= 0.05).float().mean())}


class PupilTask(ShallowNetTask):
    name = "pupil"
    config_cls = PupilTrainConfig
    selection = {"median_error_mm": "min"}
    target = "teacher"

    def _render_set(self, dcfg, ddir, shard, progress, synthesize):
        from warp_vision.data.foveation import make_retina
        from warp_vision.data.intraocular import read_pupil_store, synthesize_pupil
        from warp_vision.data.store import ChunkedStore

        self.retina = make_retina(dcfg.scene_config())
        if synthesize:
            synthesize_pupil(ddir, dcfg, shard=shard, progress=progress, log=self.log)
        return read_pupil_store(ChunkedStore.open(ddir))

    def net_spec(self):
        c = self.cfg
        return {"kind": "pupil", "photoreceptor_xy": torch.from_numpy(np.asarray(self.retina.domain_xy, np.float64)),
                "hidden": c.hidden, "rings": c.rings, "sectors": c.sectors, "seed": c.seed}

    def loss(self, pred, true):
        return torch.mean((pred - true) ** 2)

    def errors(self, pred, true):
        return _errors(pred, true)

    def describe(self, model):
        return (f"pupil net ({self.cfg.eye} eye, {self.cfg.rings}x{self.cfg.sectors} regions, hidden "
                f"{self.cfg.hidden}): {sum(p.numel() for p in model.parameters()):,} parameters")

    def epoch_line(self, row):
        return (f"epoch {row['epoch']:3d}: train loss {row['train_loss']:.3e} mm^2  val median error "
                f"{row['val_median_error_mm']:.3f} mm ({100 * row['val_median_relative_error']:.1f}%)")

    def summary(self, test, history, model):
        lum = self.data["luminance"].numpy()
        return {**super().summary(test, history, model), "luminance_cd_m2_range": [float(lum.min()), float(lum.max())]}

    def figures(self, out, history, test, idx):
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        pred, true = self.heldout_pred
        lum, cur = self.heldout["luminance"].numpy(), self.heldout["pupil"].numpy()
        fig, ax = plt.subplots(1, 2, figsize=(10, 4))
        order = np.argsort(lum)
        ax[0].semilogx(lum[order], true[order], "k-", label="Watson & Yellott (teacher)")
        sc = ax[0].scatter(lum, pred, c=cur, s=8, cmap="viridis", label="net")
        fig.colorbar(sc, ax=ax[0], label="current pupil (mm)")
        ax[0].set(xlabel="adapting luminance (cd/m$^2$)", ylabel="commanded pupil (mm)",
                  title=f"{self.cfg.eye} eye, held-out rooms")
        ax[0].legend(loc="upper right")
        ax[1].hist(100 * (pred - true) / true, bins=40, color="C1")
        ax[1].set(xlabel="error relative to the teacher (%)", ylabel="held-out ONVs")
        self.save_figure(fig, out, "pupil.png")

    def eval_line(self, run_dir, split, n, ev):
        return (f"{run_dir} ({split}, {n:,} ONVs): median error {ev['median_error_mm']:.3f} mm "
                f"({100 * ev['median_relative_error']:.1f}%), p90 {ev['p90_error_mm']:.3f} mm, within 5%: "
                f"{100 * ev['within_5pct']:.1f}%")


def run(cfg: PupilTrainConfig | None = None, **kw) -> dict:
    """Train (or resume) one eye's pupil run: :func:`warp_vision.train.harness.run` for this task."""
    return harness.run(PupilTask, cfg, **kw)


def evaluate_run(run_dir: str, split: str = "test", log=print, checkpoint: str = "best") -> dict:
    """Re-evaluate a pupil run's ``checkpoint`` (best or latest) on its held-out ONVs."""
    return evaluation.evaluate_run(PupilTask, run_dir, split, log, checkpoint=checkpoint)
