"""``HabitEvalCallback``: the paper's table of habit transfer at ``omg test``, on a HabitVQModule of the
paper's order (its own flows) or a HabitPriorModule.

Validation clips are cut into fixed-length crops. ``mode="paper"`` (default: "Behave Your Motion"
Sec. 4.4.1, one table of six columns): FID, Intra-FID, Diversity and 1-NNA of the model's
*own-category* output (each crop through the VQ-VAE with a habit latent of its own category's
prior, against the real crops: the paper notes that a pure reconstruction model "naturally
achieves low FID and Intra-FID", so these are the model's output in the crop's own category);
Downstream, the per-category FID of every crop transferred to every other category with at least
``min_samples`` real crops against that category's real crops (``cross_category_fid``); and MPJPE of
those transfers against their sources. ``mode="transfer_distribution"`` (a named diagnostic, omg's
figures before): FID, Intra-FID, Diversity and 1-NNA of the transferred crops against the target
category's real crops, MPJPE against the source; pooled over the targets, untransferred crops are
the real mixture again, so there Intra-FID is the figure that sees whether habits moved.
Features are those of a motion evaluator trained on the same representation
(``configs/mini/habit_evaluator.yaml``). Each replication draws new prior samples and codes; the
table row is the VQ-VAE's quantizer (EMA or EMA-reset), and rows of earlier runs written to the
same ``table`` file are printed with it.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Callable

import lightning as L
import numpy as np
import torch
from lightning.pytorch.callbacks import Callback
from lightning.pytorch.utilities import rank_zero_info, rank_zero_only
from torch import Tensor, nn

from omg.callbacks.run import run_dir, stop_if_signalled
from omg.errors import UsageError
from omg.evaluation import build_evaluator, build_metric, check_evaluator_spec, parse_metrics, protocol, write_report
from omg.files import atomic_write, write_json
from omg.metrics import EvalBatch
from omg.registry import METRICS

COLUMNS = {  # summary key -> the paper's column (Behave Your Motion, Sec. 4.4.1: its six)
    "fid": "FID", "intra_fid": "Intra-FID", "cross_category_fid": "Downstream", "diversity": "Diversity",
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


MODES = ("paper", "transfer_distribution")
HABIT_METRICS = ("fid", "intra_fid", "cross_category_fid", "diversity", "one_nna", "mpjpe")  # the paper's table
# mode "paper": these are fed the transfers (every crop onto every other target category); the others the
# model's own-category output, as the paper computes FID, Intra-FID, Diversity and 1-NNA (Sec. 4.4.1)
ON_TRANSFERS = frozenset({"cross_category_fid", "mpjpe"})
# mode "transfer_distribution": every metric is fed the transfers, against the target's real crops; its
# Intra-FID is the per-target FID that cross_category_fid would repeat
DISTRIBUTION_METRICS = ("fid", "intra_fid", "diversity", "one_nna", "mpjpe")


def check_mode(mode: str) -> None:
    if mode not in MODES:
        raise UsageError(f"HabitEvalCallback.mode: one of {', '.join(MODES)} (paper: the paper's table; "
                         f"transfer_distribution: the diagnostic of transferred crops against the target's), "
                         f"got {mode!r}")


def default_metrics(mode: str) -> tuple[str, ...]:
    return HABIT_METRICS if mode == "paper" else DISTRIBUTION_METRICS


def habit_parts(model) -> tuple[nn.Module, nn.Module]:
    """(the VQ-VAE, the flow priors) a habit evaluation transfers with: a HabitPriorModule's VQ-VAE and its
    flows, or a HabitVQModule of the paper's order (``flow_prior``) and the flows it holds."""
    if hasattr(model, "vq") and hasattr(model, "flows"):  # HabitPriorModule
        return model.vq, model.flows
    if not hasattr(model, "vqvae") or not hasattr(model, "flows"):
        raise UsageError(f"HabitEvalCallback evaluates a HabitVQModule or HabitPriorModule, not a "
                         f"{type(model).__name__}")
    if model.flows is None:
        raise UsageError("HabitEvalCallback: this VQ-VAE was trained in omg's earlier order (kl_then_flows) and "
                         "holds no flow priors; test its stage-2 prior: omg test --config "
                         "configs/mini/habit_prior.yaml --config configs/mini/habit_eval.yaml --ckpt_path PRIOR.ckpt")
    return model, model.flows


def prior_move(model) -> Callable[[Tensor, int, torch.Generator], Tensor]:
    """The transfer the evaluation scores: ``motion`` (B, T, D) onto category ``k`` with habit latents
    drawn from k's flow prior (the code sampling seeded from ``gen``)."""
    vq, flows = habit_parts(model)

    def move(motion: Tensor, k: int, gen: torch.Generator) -> Tensor:
        z = flows.sample(k, len(motion), gen)
        return vq.transfer(motion, k, z, seed=int(torch.randint(2**31, (1,), generator=gen)))
    return move


@torch.no_grad()
def evaluate_habits(model, evaluator: nn.Module, items: list[dict], seed: int, min_samples: int = 5,
                    batch_size: int = 64, diversity_pairs: int = 300, mode: str = "paper",
                    move: Callable[[Tensor, int, torch.Generator], Tensor] | None = None,
                    metrics: dict[str, dict] | None = None) -> dict[str, float]:
    """One replication of the habit evaluation of ``model`` (a HabitVQModule of the paper's order or a
    HabitPriorModule) on real crops ``items``.

    The transfers: every crop of another category onto each category c with at least ``min_samples`` real
    crops. ``mode="paper"`` (the paper's table): FID, Intra-FID, Diversity and 1-NNA of the model's
    own-category output (each crop onto its own category) against the real crops; Downstream
    (``cross_category_fid``: per target, the transfers against its real crops) and MPJPE of the transfers
    against their sources (``ON_TRANSFERS``). ``mode="transfer_distribution"`` (a diagnostic): every metric
    on the transfers, against the target's real crops (MPJPE against the source).
    ``move(motion, k, gen)``: the transfer scored (default: the model's, ``prior_move``). ``metrics``: registered
    metrics by name with their options (``parse_metrics``; default ``default_metrics(mode)``), each fed through
    ``eval_update`` (a reference metric, Diversity, also for the real crops as ``real_<name>``)."""
    check_mode(mode)
    vq, _ = habit_parts(model)
    move = move or prior_move(model)
    cats = vq.categories
    known = [it for it in items if it["category"] in cats]
    counts = {c: sum(it["category"] == c for it in known) for c in cats}
    targets = [k for k, c in enumerate(cats) if counts[c] >= min_samples]
    if not targets or not any(len(known) > counts[cats[k]] for k in targets):
        raise UsageError(f"the habit evaluation needs validation crops of the model's categories {cats}, "
                         f"{min_samples} of a target category and others to transfer onto it; got {counts}")
    E = evaluator.encode_motion(torch.from_numpy(np.asarray(known[0]["motion"]))[None]).shape[-1]
    real_count = len(known) if mode == "paper" else sum(counts[cats[k]] for k in targets)
    pairs = min(diversity_pairs, real_count)
    chosen = dict(metrics if metrics is not None else parse_metrics(None, defaults=default_metrics(mode),
                                                                    from_prompts=False))
    context = {"num_features": E, "categories": cats, "num_pairs": pairs, "seed": seed, "min_samples": min_samples,
               "skeleton": vq.spec.skeleton, "fps": vq.spec.fps}
    metrics = {}
    for name, options in chosen.items():
        metrics[name] = build_metric(name, options, context, key="HabitEvalCallback.metrics")
        if getattr(METRICS.get(name), "reference", False):  # also described for the real crops
            metrics[f"real_{name}"] = build_metric(name, options, context, key="HabitEvalCallback.metrics")
    # which metrics read which motion: in the paper's table the transfers feed ON_TRANSFERS, the own-category
    # output the rest; the diagnostic feeds every metric the transfers
    on_transfers = {n: m for n, m in metrics.items() if mode != "paper" or n.removeprefix("real_") in ON_TRANSFERS}
    on_own = {n: m for n, m in metrics.items() if n not in on_transfers}
    gen = torch.Generator().manual_seed(seed)
    rep = vq.representation
    for part in _batches(known, batch_size):
        motion, mask, offsets = (t.to(vq.device) for t in _stack(part))
        category = torch.tensor([cats.index(it["category"]) for it in part], device=vq.device)
        real = evaluator.encode_motion(motion, mask)
        source = rep.decode(motion, offsets)
        if on_own:  # each crop onto its own category, against all the real crops
            own = torch.empty_like(motion)
            for k in category.unique().tolist():
                rows = category == k
                own[rows] = move(motion[rows], k, gen)
            batch = EvalBatch(real=real, gen=evaluator.encode_motion(own, mask), category=category, mask=mask,
                              real_joints=source, gen_joints=rep.decode(own, offsets))
            for name, metric in on_own.items():
                metric.eval_update(batch, real=name.startswith("real_"))
        if not on_transfers:
            continue
        for k in targets:  # every crop of another category onto category k, against k's real crops
            rows = category != k
            if not rows.any():
                continue
            moved = move(motion[rows], k, gen)
            into = torch.full((int(rows.sum()),), k, device=vq.device)
            target = category == k
            batch = EvalBatch(real=real[target], gen=evaluator.encode_motion(moved, mask[rows]),
                              category=category[target], gen_category=into, mask=mask[rows],
                              real_joints=source[rows], gen_joints=rep.decode(moved, offsets[rows]))
            for name, metric in on_transfers.items():
                metric.eval_update(batch, real=name.startswith("real_"))
    out = {name: metric.compute() for name, metric in metrics.items()}
    return {name: float(v[name.removeprefix("real_")] if isinstance(v, dict) else v) for name, v in out.items()}


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
    """The habit-transfer evaluation at ``omg test`` (a HabitVQModule checkpoint of the paper's order, or a
    HabitPriorModule one; data.val the real motion).

    Args:
        evaluator: a motion evaluator checkpoint trained on the same representation (EvaluatorModule).
        mode: ``paper`` (the paper's table: FID, Intra-FID, Diversity, 1-NNA of the own-category output,
            Downstream and MPJPE of the transfers) or ``transfer_distribution`` (the diagnostic of the
            transfers against the target's real crops; its row is labelled "<quantizer> (transfer
            distribution)").
        replications: passes with new prior samples and codes; mean ± 95% CI.
        crop_len: frames per evaluated crop (default: data.max_len).
        crop_stride: frames between crop starts (default: crop_len, crops that do not overlap); a small
            validation set gives more crops with overlapping ones, but then a real crop's nearest
            neighbour is often its overlapping twin, which biases 1-NNA upwards.
        min_samples: a category is a transfer target when it has this many real crops (paper: 5).
        diversity_pairs: Diversity's pairs (paper: 300; fewer when there are fewer crops).
        seed: seeds every replication.
        table: a JSON file that collects the rows (EMA, EMA-reset) of the runs that wrote to it; the
            whole table is printed and written beside it as markdown.
        metrics: registered metrics by name, as ``EvalCallback.metrics`` (default: the paper's FID,
            Intra-FID, Downstream, Diversity, 1-NNA and MPJPE; a plugin's metric is fed the own-category
            output in ``paper`` mode, the transfers in ``transfer_distribution``).
    """

    def __init__(self, evaluator: str, replications: int = 5, crop_len: int | None = None,
                 crop_stride: int | None = None, min_samples: int = 5, diversity_pairs: int = 300, seed: int = 0,
                 table: str | None = None, mode: str = "paper", metrics: list[str | dict] | None = None):
        check_mode(mode)
        if not Path(evaluator).exists():
            raise UsageError(f"HabitEvalCallback.evaluator: no evaluator checkpoint at {evaluator}; train one with "
                             "`omg fit --config configs/mini/habit_evaluator.yaml`")
        if replications < 1 or min_samples < 2 or diversity_pairs < 2 or (crop_stride is not None and crop_stride < 1):
            raise UsageError("HabitEvalCallback: replications >= 1, min_samples >= 2, diversity_pairs >= 2 and "
                             f"crop_stride >= 1, got {replications}, {min_samples}, {diversity_pairs}, {crop_stride}")
        self.evaluator_path, self.replications, self.crop_len = evaluator, replications, crop_len
        self.crop_stride, self.mode = crop_stride, mode
        self.min_samples, self.diversity_pairs, self.seed = min_samples, diversity_pairs, seed
        self.table = Path(table) if table else None
        self.metrics = parse_metrics(metrics, key="HabitEvalCallback.metrics", defaults=default_metrics(mode),
                                     from_prompts=False)
        self.evaluator: nn.Module | None = None

    def preflight(self, model: L.LightningModule, data: L.LightningDataModule | None = None) -> None:
        """The checks that need no trainer: ``omg.tools.lightning`` runs them before the run creates its
        folder, ``setup`` again for a Trainer used without the CLI."""
        habit_parts(model)  # a model with flow priors to draw the habit latents from
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
        vq, _ = habit_parts(pl_module)
        label = vq.row_label + (" (transfer distribution)" if self.mode == "transfer_distribution" else "")

        def replication(r: int) -> dict[str, float]:
            stop_if_signalled(trainer)
            values = evaluate_habits(pl_module, evaluator, items, self.seed + r, self.min_samples,
                                     diversity_pairs=self.diversity_pairs, mode=self.mode, metrics=self.metrics)
            rank_zero_info(f"omg: habit evaluation replication {r + 1}/{self.replications} ({label}): "
                           + ", ".join(f"{k} {v:.4f}" for k, v in values.items()))
            return values

        summary = protocol(replication, self.replications)
        for key, s in summary.items():
            pl_module.log(f"eval/{key}", s["mean"])
        settings = {"checkpoint": str(trainer.ckpt_path) if trainer.ckpt_path else None, "row": label,
                    "evaluator": self.evaluator_path, "mode": self.mode, "replications": self.replications,
                    "crops": len(items),
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
        rows = {k: rows[k] for k in sorted(rows, key=lambda r: ("(" in r, r != "EMA", r))}  # the paper's order
        table = paper_table(rows)
        if self.table is not None:
            self.table.parent.mkdir(parents=True, exist_ok=True)
            write_json(self.table, rows)
            atomic_write(self.table.with_suffix(".md"), (table + "\n").encode())
        print(f"\n{table}\n\n({settings['crops']} validation crops of {settings['crop_len']} frames every "
              f"{settings['crop_stride']}, "
              f"{self.replications} replications; written to {directory / 'habit_eval.md'})")
