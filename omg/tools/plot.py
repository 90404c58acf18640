"""``omg plot RUN``: the training curves of a run folder as one PNG, from the metrics.csv that
``omg fit``'s CSVLogger writes (``<default_root_dir>/version_N/metrics.csv``; a resumed run adds a
version, so a run folder's versions are read in order as one run)."""

from __future__ import annotations

import csv
import io
import math
import re
from pathlib import Path

from omg.errors import UsageError
from omg.tools.args import run

METRICS_MAX_BYTES = 256 * 2**20  # a million steps logged every 50, a few dozen columns: tens of MiB
# one panel each, in this order: what a column of metrics.csv is
PANELS = (("training losses", lambda k: k.startswith("train/") and not _is_lr(k) and not k.endswith("_per_s")),
          ("learning rate", lambda k: _is_lr(k)),
          ("validation", lambda k: k.startswith("val/")),
          ("evaluation", lambda k: k.startswith(("eval/", "test/", "ood/"))))


def _is_lr(key: str) -> bool:
    return re.search(r"(^|[/_])lr($|[/_-])", key) is not None  # train/lr, lr-AdamW (LearningRateMonitor)


def metrics_files(path: Path) -> list[Path]:
    """The metrics.csv of a version folder, or those of a run folder's version_N folders, oldest first."""
    if not path.is_dir():
        raise UsageError(f"RUN {path}: no such folder; give a run folder (trainer.default_root_dir, e.g. runs/NAME) "
                         "or one of its version_N folders")
    if (path / "metrics.csv").is_file():
        return [path / "metrics.csv"]
    versions = [(int(m.group(1)), p / "metrics.csv") for p in path.iterdir()
                if (m := re.fullmatch(r"version_(\d+)", p.name)) and (p / "metrics.csv").is_file()]
    if not versions:
        raise UsageError(f"RUN {path}: no metrics.csv in it or in a version_N folder of it (omg fit's CSV logger "
                         "writes runs/NAME/version_N/metrics.csv)")
    return [file for _, file in sorted(versions)]


def read_metrics(files: list[Path]) -> dict[str, list[tuple[int, float]]]:
    """Each metric's (step, value) points, the files read in order (a later version's step replaces an
    earlier one's: a resumed run logs again from its checkpoint's step)."""
    from omg.files import read_text

    series: dict[str, dict[int, float]] = {}
    for file in files:
        rows = csv.DictReader(io.StringIO(read_text(file, "RUN", METRICS_MAX_BYTES)))
        if rows.fieldnames is None or "step" not in rows.fieldnames:
            raise UsageError(f"RUN {file}: not a Lightning metrics.csv (no step column)")
        for row in rows:
            try:
                step = int(float(row["step"]))
            except (TypeError, ValueError):
                continue
            for key, text in row.items():
                if key in ("step", "epoch") or not text:
                    continue
                try:
                    value = float(text)
                except ValueError:
                    continue
                if math.isfinite(value):
                    series.setdefault(key, {})[step] = value
    return {key: sorted(points.items()) for key, points in series.items()}


def plot(run_dir: Path, out: Path | None = None) -> Path:
    """Draw the training curves of a run folder to a PNG: training losses, learning rate, validation and
    evaluation metrics, one panel each, against optimizer steps.

    Args:
        run_dir: a run folder (trainer.default_root_dir, e.g. runs/mini_pretrain; its version_N folders are
            one run, resumed) or one version_N folder
        out: the PNG to write (default: RUN/curves.png)

    Returns:
        The PNG's path.
    """
    from omg.files import atomic_path, check_output_dir

    out = out or run_dir / "curves.png"
    series = read_metrics(metrics_files(run_dir))
    panels = [(title, {k: v for k, v in series.items() if wanted(k)}) for title, wanted in PANELS]
    panels = [(title, lines) for title, lines in panels if lines]
    if not panels:
        raise UsageError(f"RUN {run_dir}: no metrics logged yet (training logs every trainer.log_every_n_steps "
                         "steps, validation at trainer.val_check_interval)")
    check_output_dir(out.parent, "--out")
    out.parent.mkdir(parents=True, exist_ok=True)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(panels), 1, figsize=(9, 2.8 * len(panels)), sharex=True, squeeze=False)
    for ax, (title, lines) in zip(axes[:, 0], panels):
        for key, points in sorted(lines.items()):
            steps, values = zip(*points)
            ax.plot(steps, values, marker="." if len(points) < 30 else None, label=key)
        values = [v for points in lines.values() for _, v in points]
        if title != "learning rate" and min(values) > 0 and max(values) > 10 * min(values):
            ax.set_yscale("log")  # losses span decades, and a loss's terms differ by orders of magnitude
        ax.set_title(title, fontsize=10)
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=7, loc="best")
    axes[-1, 0].set_xlabel("optimizer step")
    fig.suptitle(str(run_dir), fontsize=9)
    fig.tight_layout()
    with atomic_path(out) as tmp:
        fig.savefig(tmp, dpi=100, format="png")
    plt.close(fig)
    last = max(step for points in series.values() for step, _ in points)
    print(f"wrote {out}: {', '.join(title for title, _ in panels)} to step {last}")
    return out


def main(argv: list[str]) -> None:
    run(plot, argv, "omg plot", as_positional=True)
