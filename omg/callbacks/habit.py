"""``HabitEvalCallback``: the paper's evaluation of habit transfer at ``omg test`` on a HabitPriorModule.

Validation clips are cut into fixed-length crops. Each crop is reconstructed through the VQ-VAE
with a habit latent drawn from its own category's prior (FID, per-category Intra-FID, Diversity,
1-NNA and MPJPE against the real crops), and transferred to every other category with at least
``min_samples`` real crops (the cross-category downstream task: the FID of the motions transferred
into a category against its real motions, averaged). Features are those of a motion evaluator
trained on the same representation (``configs/mini/habit_evaluator.yaml``). Each replication
draws new prior samples and codes; the table row is the VQ-VAE's quantizer (EMA or EMA-reset),
and rows of earlier runs written to the same ``table`` file are printed with it.
"""

from __future__ import annotations

import json
from pathlib import Path

import lightning as L
import numpy as np
import torch
from lightning.pytorch.callbacks import Callback
from lightning.pytorch.utilities import rank_zero_info, rank_zero_only
from torch import Tensor, nn

from omg.callbacks.run import run_dir
from omg.errors import UsageError
from omg.evaluation import build_evaluator, check_evaluator_spec, protocol, write_report
from omg.files import atomic_write, write_json
from omg.metrics import FID, MPJPE, CrossCategoryFID, Diversity, IntraFID, OneNNA

COLUMNS = {  # summary key -> the paper's column
    "fid": "FID", "intra_fid": "Intra-FID", "cross_category_fid": "downstream FID", "diversity": "Diversity",
    "one_nna": "1-NNA", "mpjpe": "MPJPE (m)",
}  # fmt: skip


def crops(samples: list[dict], length: int, stride: int | None = None) -> list[dict]:
    """``length``-frame crops of every clip every ``stride`` frames (default ``length``: not overlapping;
    a shorter clip whole): {motion (T, D), category, offsets (J, 3)}."""
    out = []
    for sample in samples:
        motion, meta = sample["motion"], sample["meta"]
        starts = range(0, max(1, len(motion) - length + 1), stride or length)
        for start in starts:
            out.append({"motion": motion[start:start + length], "category": meta.get("category") or "",
                        "offsets": np.asarray(meta["offsets"], np.float32)})
    return out


def _batches(items: list, size: int):
    for i in range(0, len(items), size):
        yield items[i:i + size]


def _stack(items: list[dict]) -> tuple[Tensor, Tensor, Tensor]:
    """(motion (B, T, D), mask (B, T), offsets (B, J, 3)) of crops, padded."""
    T = max(len(it["motion"]) for it in items)
    motion = torch.zeros(len(items), T, items[0]["motion"].shape[1])
    mask = torch.zeros(len(items), T, dtype=torch.bool)
    for b, it in enumerate(items):
        motion[b, : len(it["motion"])] = torch.from_numpy(np.asarray(it["motion"]))
        mask[b, : len(it["motion"])] = True
    return motion, mask, torch.from_numpy(np.stack([it["offsets"] for it in items]))


@torch.no_grad()
def evaluate_habits(prior, evaluator: nn.Module, items: list[dict], seed: int, min_samples: int = 5,
                    batch_size: int = 64, diversity_pairs: int = 300) -> dict[str, float]:
    """One replication of the paper's metrics for a HabitPriorModule on real crops ``items``."""
    vq = prior.vq
    cats = vq.categories
    known = [it for it in items if it["category"] in cats]
    if len(known) < 2:
        raise UsageError(f"the evaluation needs at least 2 validation crops of the model's categories {cats}")
    E = evaluator.encode_motion(torch.from_numpy(np.asarray(known[0]["motion"]))[None]).shape[-1]
    fid, intra, cross = FID(E), IntraFID(E, cats), CrossCategoryFID(E, cats, min_samples=min_samples)
    pairs = min(diversity_pairs, len(known))
    diversity, real_diversity, one_nna, mpjpe = Diversity(pairs, seed), Diversity(pairs, seed), OneNNA(), MPJPE()
    counts = {c: sum(it["category"] == c for it in known) for c in cats}
    targets = [k for k, c in enumerate(cats) if counts[c] >= min_samples]
    gen = torch.Generator().manual_seed(seed)
    rep = vq.representation
    for part in _batches(known, batch_size):
        motion, mask, offsets = (t.to(vq.device) for t in _stack(part))
        category = torch.tensor([cats.index(it["category"]) for it in part], device=vq.device)
        real = evaluator.encode_motion(motion, mask)
        recon = torch.empty_like(motion)
        for k in category.unique().tolist():
            rows = category == k
            z = prior.flows.sample(k, int(rows.sum()), gen)
            recon[rows] = vq.transfer(motion[rows], k, z, seed=int(torch.randint(2**31, (1,), generator=gen)))
        fake = evaluator.encode_motion(recon, mask)
        fid.update(real, real=True)
        fid.update(fake, real=False)
        intra.update(real, category, real=True)
        intra.update(fake, category, real=False)
        cross.update(real, category, real=True)
        one_nna.update(real, real=True)
        one_nna.update(fake, real=False)
        diversity.update(fake)
        real_diversity.update(real)
        mpjpe.update(rep.decode(recon, offsets), rep.decode(motion, offsets), mask)
        for k in targets:  # the downstream task: every crop of another category into category k
            rows = category != k
            if not rows.any():
                continue
            z = prior.flows.sample(k, int(rows.sum()), gen)
            moved = vq.transfer(motion[rows], k, z, seed=int(torch.randint(2**31, (1,), generator=gen)))
            into = torch.full((int(rows.sum()),), k, device=vq.device)
            cross.update(evaluator.encode_motion(moved, mask[rows]), into, real=False)
    return {"fid": float(fid.compute()), "intra_fid": float(intra.compute()["intra_fid"]),
            "cross_category_fid": float(cross.compute()["cross_category_fid"]),
            "diversity": float(diversity.compute()), "real_diversity": float(real_diversity.compute()),
            "one_nna": float(one_nna.compute()), "mpjpe": float(mpjpe.compute())}


def paper_table(rows: dict[str, dict[str, dict]]) -> str:
    """The paper's table: one row per quantizer (EMA, EMA-reset), mean ± 95% CI; real motion's Diversity last."""
    lines = ["| quantizer | " + " | ".join(COLUMNS.values()) + " |", "|---|" + "---:|" * len(COLUMNS)]
    for label, summary in rows.items():
        cells = [f"{summary[k]['mean']:.4f} ± {summary[k]['ci95']:.4f}" if k in summary else "–" for k in COLUMNS]
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    real = next((s["real_diversity"] for s in rows.values() if "real_diversity" in s), None)
    if real is not None:
        cells = ["–"] * len(COLUMNS)
        cells[list(COLUMNS).index("diversity")] = f"{real['mean']:.4f}"
        lines.append("| real motion | " + " | ".join(cells) + " |")
    return "\n".join(lines)


class HabitEvalCallback(Callback):
    """The habit-transfer evaluation at ``omg test`` (a HabitPriorModule checkpoint, data.val the real motion).

    Args:
        evaluator: a motion evaluator checkpoint trained on the same representation (EvaluatorModule).
        replications: passes with new prior samples and codes; mean ± 95% CI.
        crop_len: frames per evaluated crop (default: data.max_len).
        crop_stride: frames between crop starts (default: crop_len, crops that do not overlap); a small
            validation set gives more crops with overlapping ones, but then a real crop's nearest
            neighbour is often its overlapping twin, which biases 1-NNA upwards.
        min_samples: a category is a downstream target when it has this many real crops (paper: 5).
        diversity_pairs: Diversity's pairs (paper: 300; fewer when there are fewer crops).
        seed: seeds every replication.
        table: a JSON file that collects the rows (EMA, EMA-reset) of the runs that wrote to it; the
            whole table is printed and written beside it as markdown.
    """

    def __init__(self, evaluator: str, replications: int = 5, crop_len: int | None = None,
                 crop_stride: int | None = None, min_samples: int = 5, diversity_pairs: int = 300, seed: int = 0,
                 table: str | None = None):
        if not Path(evaluator).exists():
            raise UsageError(f"HabitEvalCallback.evaluator: no evaluator checkpoint at {evaluator}; train one with "
                             "`omg fit --config configs/mini/habit_evaluator.yaml`")
        if replications < 1 or min_samples < 2 or diversity_pairs < 2 or (crop_stride is not None and crop_stride < 1):
            raise UsageError("HabitEvalCallback: replications >= 1, min_samples >= 2, diversity_pairs >= 2 and "
                             f"crop_stride >= 1, got {replications}, {min_samples}, {diversity_pairs}, {crop_stride}")
        self.evaluator_path, self.replications, self.crop_len = evaluator, replications, crop_len
        self.crop_stride = crop_stride
        self.min_samples, self.diversity_pairs, self.seed = min_samples, diversity_pairs, seed
        self.table = Path(table) if table else None
        self.evaluator: nn.Module | None = None

    def preflight(self, model: L.LightningModule, data: L.LightningDataModule | None = None) -> None:
        """The checks that need no trainer: ``omg.tools.lightning`` runs them before the run creates its
        folder, ``setup`` again for a Trainer used without the CLI."""
        if not hasattr(model, "flows") or not hasattr(model, "vq"):
            raise UsageError(f"HabitEvalCallback evaluates a HabitPriorModule, not a {type(model).__name__}")
        if self.evaluator is None:
            self.evaluator = build_evaluator(self.evaluator_path, key="HabitEvalCallback.evaluator")
        check_evaluator_spec(self.evaluator, model.spec, key="HabitEvalCallback.evaluator")

    def setup(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        self.preflight(pl_module, trainer.datamodule)

    def on_test_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        data = trainer.datamodule
        if data is None or not getattr(data, "val_urls", None):
            raise UsageError("HabitEvalCallback evaluates on the validation set: set data.val")
        length = self.crop_len or data.hparams.max_len
        items = crops(data.val_clips().samples, length, self.crop_stride)
        evaluator = self.evaluator.to(pl_module.device)
        pl_module.eval()
        label = pl_module.vq.row_label

        def replication(r: int) -> dict[str, float]:
            values = evaluate_habits(pl_module, evaluator, items, self.seed + r, self.min_samples,
                                     diversity_pairs=self.diversity_pairs)
            rank_zero_info(f"omg: habit evaluation replication {r + 1}/{self.replications} ({label}): "
                           + ", ".join(f"{k} {v:.4f}" for k, v in values.items()))
            return values

        summary = protocol(replication, self.replications)
        for key, s in summary.items():
            pl_module.log(f"eval/{key}", s["mean"])
        settings = {"checkpoint": str(trainer.ckpt_path) if trainer.ckpt_path else None, "row": label,
                    "evaluator": self.evaluator_path, "replications": self.replications, "crops": len(items),
                    "crop_len": length, "crop_stride": self.crop_stride or length, "min_samples": self.min_samples,
                    "seed": self.seed}
        self._report(run_dir(trainer), label, summary, settings)

    @rank_zero_only
    def _report(self, directory: Path, label: str, summary: dict, settings: dict) -> None:
        write_report(directory, summary, settings, name="habit_eval")
        rows = {}
        if self.table is not None and self.table.is_file():
            rows = json.loads(self.table.read_text())
        rows[label] = {k: {"mean": v["mean"], "ci95": v["ci95"]} for k, v in summary.items()}
        rows = {k: rows[k] for k in sorted(rows, key=lambda r: (r != "EMA", r))}  # the paper's order
        table = paper_table(rows)
        if self.table is not None:
            self.table.parent.mkdir(parents=True, exist_ok=True)
            write_json(self.table, rows)
            atomic_write(self.table.with_suffix(".md"), (table + "\n").encode())
        print(f"\n{table}\n\n({settings['crops']} validation crops of {settings['crop_len']} frames every "
              f"{settings['crop_stride']}, "
              f"{self.replications} replications; written to {directory / 'habit_eval.md'})")
