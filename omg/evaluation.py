"""Text-to-motion evaluation: prompt sets, one evaluation pass, and the published protocol.

One pass (``evaluate``) generates a motion for every prompt of a seeded prompt set through a
sampling function, embeds texts, real and generated motions with a frozen text–motion evaluator
and feeds the configured torchmetrics metrics. The protocol (``protocol``) repeats passes with R
seeds and reports per metric the mean and the 95% confidence interval 1.96·σ/√R with σ the
population std over replications, as the T2M / MDM evaluation scripts do.

Under DDP each rank generates a contiguous run of the global batches; batches and their seeds
depend only on the global batch index, so (with at least batch_size prompts per rank) the samples
do not depend on the world size, and the metric states (``sum`` / ``cat``) sync so every rank
computes the same values.
"""

from __future__ import annotations

import importlib
import inspect
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
import torch
from torch import Tensor, nn
from torchmetrics import Metric

from omg.data.windows import WindowSampler
from omg.errors import UsageError
from omg.files import atomic_write, write_json
from omg.metrics import EvalBatch
from omg.motion import DataSpec, get_representation, length_mask
from omg.registry import METRICS
from omg.skeleton import get_skeleton

DEFAULT_METRICS = ("fid", "r_precision", "mm_dist", "diversity", "multimodality")

# -- the evaluator ------------------------------------------------------------------------

def build_evaluator(spec: str | dict[str, Any] | nn.Module, key: str = "evaluator") -> nn.Module:
    """The frozen evaluator from a checkpoint path, ``{t2m: {checkpoint, glove_dir, mean_std_dir}}``
    (the T2M port), ``{class_path, init_args}`` or a module; errors name ``key``."""
    if isinstance(spec, nn.Module):
        model = spec
    elif isinstance(spec, (str, Path)):
        if not Path(spec).exists():
            raise UsageError(f"{key}: no evaluator checkpoint at {spec}; train one (configs/evaluator_*.yaml) "
                             f"or use the T2M port with {key}: {{t2m: {{checkpoint, glove_dir, mean_std_dir}}}}")
        from omg.lit.evaluator import load_evaluator  # imports Lightning: only when a checkpoint is given

        model = load_evaluator(str(spec), map_location="cpu")
    elif isinstance(spec, dict) and set(spec) == {"t2m"}:
        from omg.models.t2m import load_t2m_evaluator

        try:
            model = load_t2m_evaluator(**spec["t2m"])
        except TypeError as e:
            raise UsageError(f"{key}.t2m: {e}; give checkpoint, glove_dir and mean_std_dir") from None
    elif isinstance(spec, dict) and "class_path" in spec:
        module, _, name = str(spec["class_path"]).rpartition(".")
        try:
            cls = getattr(importlib.import_module(module), name)
        except (ImportError, AttributeError, ValueError):
            raise UsageError(f"{key}.class_path: {spec['class_path']!r} cannot be imported") from None
        # checked before it is called: a class_path must name an evaluator class, not any callable
        if not (isinstance(cls, type) and issubclass(cls, nn.Module)
                and all(callable(getattr(cls, m, None)) for m in ("encode_text", "encode_motion"))):
            raise UsageError(f"{key}.class_path: {spec['class_path']} is not a text-motion evaluator (an nn.Module "
                             "class with encode_text and encode_motion methods)")
        init_args = spec.get("init_args") or {}
        if not isinstance(init_args, dict):
            raise UsageError(f"{key}.init_args: expected a mapping of keyword arguments, got {init_args!r}")
        model = cls(**init_args)
    else:
        raise UsageError(f"{key}: expected a checkpoint path, {{t2m: {{...}}}} or {{class_path: ...}}, got {spec!r}")
    for method in ("encode_text", "encode_motion"):
        if not callable(getattr(model, method, None)):
            raise UsageError(f"{key}: {type(model).__name__} has no {method}(); it is not a text-motion evaluator")
    return model.eval().requires_grad_(False)


def check_evaluator_spec(evaluator: nn.Module, data_spec: DataSpec, key: str = "evaluator") -> None:
    """The evaluator must read the same features as the data, where it says what it reads (its
    ``spec``: a DataSpec, or a dict of the fields it knows, as the T2M port has)."""
    if (spec := getattr(evaluator, "spec", None)) is not None:
        data_spec.check_compatible(spec, "the data", key)


# -- prompts ------------------------------------------------------------------------------

@dataclass
class PromptSet:
    """Captions with the real motions they describe: texts (N), lengths (N,), motions (N, T, D)
    un-normalised and zero beyond each length, categories (N), offsets (N, J, 3) or None.
    ``motions`` is None for a prompt file (``file_prompt_set``): prompts with targets, no real motion."""

    texts: list[str]
    lengths: Tensor
    motions: Tensor | None
    categories: list[str]
    offsets: Tensor | None = None
    labels: list[dict] | None = None  # each clip's labels ({content, style, ...}), {} when it has none

    def __len__(self) -> int:
        return len(self.texts)

    def slice(self, start: int, stop: int) -> PromptSet:
        T = int(self.lengths[start:stop].max())
        motions = None if self.motions is None else self.motions[start:stop, :T]
        return PromptSet(self.texts[start:stop], self.lengths[start:stop], motions,
                         self.categories[start:stop], None if self.offsets is None else self.offsets[start:stop],
                         None if self.labels is None else self.labels[start:stop])

    def repeat(self, count: int, repeats: int) -> PromptSet:
        """The first ``count`` prompts, each ``repeats`` times in a row (MultiModality's generations)."""
        index = torch.arange(min(count, len(self))).repeat_interleave(repeats)
        return PromptSet([self.texts[i] for i in index], self.lengths[index],
                         None if self.motions is None else self.motions[index],
                         [self.categories[i] for i in index], None if self.offsets is None else self.offsets[index],
                         None if self.labels is None else [self.labels[i] for i in index])


def prompt_set(samples: Sequence[dict], num: int, seed: int, windows: WindowSampler) -> PromptSet:
    """``num`` seeded prompts from decoded clips (``{"motion", "meta", "texts"}``): clips in a random
    order (repeating the set when it is smaller than ``num``), one random caption and one random
    window each. Clips without captions are used only when no clip has one (unlabeled data)."""
    pool = [s for s in samples if s["texts"]] or list(samples)
    if not pool:
        raise UsageError("the evaluation set holds no clips; set data.val to a shard directory")
    rng = np.random.default_rng(seed)
    order = np.concatenate([rng.permutation(len(pool)) for _ in range(math.ceil(num / len(pool)))])[:num]
    texts, windows_, categories, offsets, labels = [], [], [], [], []
    for i in order:
        s = pool[int(i)]
        start, length = (windows.whole if s["texts"] else windows.random)(len(s["motion"]), rng)
        texts.append(s["texts"][int(rng.integers(len(s["texts"])))] if s["texts"] else "")
        windows_.append(s["motion"][start:start + length])
        categories.append(s["meta"].get("category") or "")
        labels.append(s["meta"].get("labels") or {})
        offsets.append(s["meta"].get("offsets"))
    lengths = torch.tensor([len(w) for w in windows_])
    motions = torch.zeros(num, int(lengths.max()), windows_[0].shape[1])
    for b, w in enumerate(windows_):
        motions[b, : len(w)] = torch.from_numpy(np.ascontiguousarray(w))
    has_offsets = all(o is not None for o in offsets)
    return PromptSet(texts, lengths, motions, categories,
                     torch.tensor(np.array(offsets), dtype=torch.float32) if has_offsets else None, labels)


def file_prompt_set(prompts: Sequence[dict], samples_per_prompt: int, fps: float, max_len: int) -> PromptSet:
    """A prompt file's prompts (``omg.metrics.following.load_prompts``: text, category, seconds,
    targets), each ``samples_per_prompt`` times in a row, ``seconds`` long at ``fps`` (at most
    ``max_len`` frames, at least 2); each row's labels carry its ``targets`` and its category as
    ``following``, which the metrics that read targets score. No real motions."""
    rows = [p for p in prompts for _ in range(samples_per_prompt)]
    lengths = torch.tensor([min(max_len, max(2, round(p["seconds"] * fps))) for p in rows])
    labels = [{"following": p["category"], "targets": p["targets"]} for p in rows]
    return PromptSet([p["text"] for p in rows], lengths, None, ["" for _ in rows], None, labels)


# -- metrics ------------------------------------------------------------------------------

def parse_metrics(spec: Sequence[str | dict[str, Any]] | dict[str, Any] | None,
                  key: str = "metrics", defaults: Sequence[str] = DEFAULT_METRICS,
                  from_prompts: bool = True) -> dict[str, dict]:
    """``[fid, {diversity: {num_pairs: 100}}]`` or ``{fid: {}, ...}`` -> {name: options}; ``defaults`` when
    None. ``from_prompts``: the metrics are fed generations from a prompt set (False: another pass, such
    as habit transfer's, which feeds transferred motions with their sources)."""
    spec = defaults if spec is None else spec
    items = list(spec.items()) if isinstance(spec, dict) else []
    if not isinstance(spec, dict):
        for entry in spec:
            if isinstance(entry, str):
                items.append((entry, {}))
            elif isinstance(entry, dict) and len(entry) == 1:
                items.append(next(iter(entry.items())))
            else:
                raise UsageError(f"{key}: each entry is a metric name or {{name: {{options}}}}, got {entry!r}")
    out = {}
    for name, options in items:
        if name not in METRICS:
            raise UsageError(f"{key}: unknown metric {name!r}; known metrics: {', '.join(METRICS.names())}")
        if not isinstance(options, dict | None):
            raise UsageError(f"{key}.{name}: options must be a mapping, got {options!r}")
        cls = METRICS.get(name)
        if not callable(getattr(cls, "eval_update", None)) or (from_prompts and not getattr(cls, "from_prompts", True)):
            raise UsageError(f"{key}: {name} cannot be computed from generated prompts (it needs other inputs); "
                             f"use {', '.join(DEFAULT_METRICS)}, clip_score, intra_fid, one_nna or foot_skating")
        out[name] = dict(options or {})
    return out


def build_metric(name: str, options: dict, context: dict, key: str = "metrics") -> Metric:
    """Instantiate a registered metric; arguments it takes from ``context`` (num_features, categories,
    skeleton, fps, seed) are filled in unless the options set them."""
    cls = METRICS.get(name)
    params = inspect.signature(cls).parameters
    kwargs = {k: v for k, v in context.items() if k in params} | options
    try:
        return cls(**kwargs)
    except (TypeError, ValueError) as e:
        raise UsageError(f"{key}.{name}: {e}") from None


def metric_values(name: str, value: Tensor | dict[str, Tensor]) -> dict[str, float]:
    if isinstance(value, dict):
        return {k: float(v) for k, v in value.items()}
    return {name: float(value)}


# -- one pass and the protocol ------------------------------------------------------------

Generate = Callable[[list[str], Tensor, int], Tensor]  # (texts, lengths, seed) -> (B, T, D) un-normalised


@dataclass
class EvalSettings:
    batch_size: int = 64
    mm_prompts: int = 100  # MultiModality: the first mm_prompts prompts ...
    mm_repeats: int = 30  # ... generated mm_repeats times each (T2M: 100 × 30)
    reference: bool = True  # also report the set-wise metrics of the real motions as real/<name>


def batch_seed(seed: int, replication: int, stream: int, index: int) -> int:
    """An independent generation seed per (seed, replication, stream, global batch)."""
    return int(np.random.SeedSequence([seed, replication, stream, index]).generate_state(1)[0])


def _my_batches(n: int, batch_size: int, rank: int, world: int) -> list[tuple[int, int, int]]:
    """(global batch index, start, stop) of this rank's contiguous share of the batches. Batches
    shrink where there would be fewer than ranks: every rank needs samples to sync its metrics."""
    batch_size = max(1, min(batch_size, n // world))
    batches = math.ceil(n / batch_size)
    lo, hi = batches * rank // world, batches * (rank + 1) // world
    return [(b, b * batch_size, min(n, (b + 1) * batch_size)) for b in range(lo, hi)]


@torch.no_grad()
def evaluate(generate: Generate, evaluator: nn.Module, prompts: PromptSet, metrics: dict[str, dict], *,
             seed: int, replication: int = 0, settings: EvalSettings | None = None, spec: DataSpec | None = None,
             device: torch.device | str = "cpu", rank: int = 0, world_size: int = 1) -> dict[str, float]:
    """One evaluation pass over ``prompts``: {metric key: value}, the same on every rank.

    ``spec`` (the data's representation, skeleton, fps) decodes joint positions for the metrics
    that need them (FootSkating)."""
    device, settings = torch.device(device), settings or EvalSettings()
    has_real = prompts.motions is not None
    for name in metrics:  # a prompt file has no real motions; only an evaluator gives embeddings
        cls = METRICS.get(name)
        if not has_real and getattr(cls, "needs_real", True):
            raise UsageError(f"metric {name} compares with real motions, which a prompt file does not have; "
                             "score a prompt file with following, diversity, multimodality or foot_skating")
        if evaluator is None and getattr(cls, "needs_embeddings", True):
            raise UsageError(f"metric {name} reads the evaluator's embeddings: set an evaluator")
    if evaluator is not None:
        evaluator.to(device)
    categories = sorted(set(prompts.categories))
    label_values: dict[str, set] = {}
    for labels in prompts.labels or []:
        for key, value in labels.items():
            if key != "targets":  # a prompt file's targets are not class values
                label_values.setdefault(key, set()).add(str(value))
    context = {"categories": categories, "seed": seed + replication,
               "labels": {key: sorted(values) for key, values in label_values.items()}}
    if evaluator is not None:
        context["num_features"] = evaluator.encode_text([prompts.texts[0]]).shape[-1]
    representation = None
    if spec is not None:
        context |= {"skeleton": spec.skeleton, "fps": spec.fps}
        representation = get_representation(spec.representation, get_skeleton(spec.skeleton))
    built = {name: build_metric(name, opts, context).to(device) for name, opts in metrics.items()}
    reference = {name: build_metric(name, opts, context).to(device) for name, opts in metrics.items()
                 if settings.reference and has_real and getattr(built[name], "reference", False)}
    embeds = any(getattr(m, "needs_embeddings", True) for m in built.values())
    needs_joints = any(getattr(m, "needs_joints", False) for m in built.values())
    if needs_joints and representation is None:
        raise UsageError("joint-position metrics (foot_skating) need the data spec (representation, skeleton, fps) "
                         "to decode joint positions")
    category_index = {c: i for i, c in enumerate(categories)}

    def embed(motion: Tensor | None, mask: Tensor) -> Tensor | None:
        return evaluator.encode_motion(motion.to(device), mask).float() if embeds and motion is not None else None

    def decode(motion: Tensor | None, part: PromptSet) -> Tensor | None:
        if not needs_joints or motion is None:
            return None
        offsets = None if part.offsets is None else part.offsets.to(device)
        return representation.decode(motion.float(), offsets)

    for b, start, stop in _my_batches(len(prompts), settings.batch_size, rank, world_size):
        part = prompts.slice(start, stop)
        lengths = part.lengths.to(device)
        frames = int(part.lengths.max())
        gen = generate(part.texts, lengths, batch_seed(seed, replication, 0, b))[:, :frames]
        real = part.motions.to(device) if has_real else None
        mask = length_mask(lengths, frames)  # (B, T) real frames, shared by both sets
        out = EvalBatch(
            text=evaluator.encode_text(part.texts).float().to(device) if embeds else None, real=embed(real, mask),
            gen=embed(gen, mask), category=torch.tensor([category_index[c] for c in part.categories], device=device),
            mask=mask, real_joints=decode(real, part), gen_joints=decode(gen, part), labels=part.labels)
        for metric in built.values():
            if not getattr(metric, "repeated", False):
                metric.eval_update(out)
        for metric in reference.values():
            metric.eval_update(out, real=True)

    mm_metrics = [m for m in built.values() if getattr(m, "repeated", False)]
    if mm_metrics:
        repeated = prompts.repeat(settings.mm_prompts, settings.mm_repeats)
        ids = torch.arange(min(settings.mm_prompts, len(prompts))).repeat_interleave(settings.mm_repeats)
        for b, start, stop in _my_batches(len(repeated), settings.batch_size, rank, world_size):
            part = repeated.slice(start, stop)
            gen = generate(part.texts, part.lengths.to(device), batch_seed(seed, replication, 1, b))
            frames = int(part.lengths.max())
            out = EvalBatch(mm=embed(gen[:, :frames], length_mask(part.lengths, frames, device)),
                          mm_ids=ids[start:stop].to(device))
            for metric in mm_metrics:
                metric.eval_update(out)

    values: dict[str, float] = {}
    for name, metric in built.items():
        values |= metric_values(name, metric.compute())
    for name, metric in reference.items():
        values |= {f"real/{k}": v for k, v in metric_values(name, metric.compute()).items()}
    return values


def summarize(runs: Sequence[dict[str, float]]) -> dict[str, dict[str, Any]]:
    """Per key over replications: mean, std (population, np.std), ci95 = 1.96·std/√R, values."""
    R = len(runs)
    out = {}
    for key in runs[0]:
        values = np.array([run[key] for run in runs], dtype=np.float64)
        std = float(values.std())
        out[key] = {"mean": float(values.mean()), "std": std, "ci95": 1.96 * std / math.sqrt(R),
                    "values": values.tolist()}
    return out


def protocol(run: Callable[[int], dict[str, float]], replications: int) -> dict[str, dict[str, Any]]:
    """``run(replication)`` for replication 0..R-1, summarised."""
    if replications < 1:
        raise UsageError(f"replications must be >= 1, got {replications}")
    return summarize([run(r) for r in range(replications)])


# -- reports ------------------------------------------------------------------------------

def markdown_table(summary: dict[str, dict[str, Any]], replications: int) -> str:
    lines = [f"| metric | mean | ±95% CI ({replications} replications) |", "|---|---:|---:|"]
    for key, s in summary.items():
        lines.append(f"| {key} | {s['mean']:.4f} | ±{s['ci95']:.4f} |")
    return "\n".join(lines)


def write_report(directory: str | Path, summary: dict[str, dict[str, Any]], settings: dict[str, Any],
                 name: str = "eval") -> tuple[Path, Path]:
    """``<name>.json`` (settings + summary) and ``<name>.md`` (the table), each written atomically."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    replications = settings.get("replications", len(next(iter(summary.values()))["values"]))
    json_path, md_path = directory / f"{name}.json", directory / f"{name}.md"
    write_json(json_path, {"settings": settings, "metrics": summary})
    header = "\n".join(f"- {k}: {v}" for k, v in settings.items() if not isinstance(v, dict | list))
    atomic_write(md_path, f"# Evaluation\n\n{header}\n\n{markdown_table(summary, replications)}\n".encode())
    return json_path, md_path
