"""A run whose output is not a terminal prints plain progress lines (``omg fit --progress_every``),
and ``omg plot`` draws a run folder's curves from its metrics.csv, the versions of a resumed run as
one run. One short mini run (tiny DiT, a few steps) and its resume serve both."""

from __future__ import annotations

import re
import sys

import pytest
from PIL import Image

from helpers import REPO, TINY_DIT_ARG
from omg.cli import main
from omg.errors import UsageError
from omg.tools.plot import plot

MINI = REPO / "shards/mini/human263"
FIT = ["fit", "--config", str(REPO / "configs/mini/pretrain.yaml"), TINY_DIT_ARG, f"--data.train={MINI}/train",
       f"--data.val={MINI}/val", "--data.batch_size=4", "--data.max_len=30", "--data.min_len=20",
       "--data.num_workers=0", "--trainer.enable_model_summary=false", "--trainer.log_every_n_steps=1",
       "--trainer.val_check_interval=4", "--trainer.limit_val_batches=1"]


def _omg(*argv: str) -> None:
    saved = list(sys.argv)  # omg.cli sets sys.argv for LightningCLI
    try:
        main(list(argv))
    finally:
        sys.argv[:] = saved


@pytest.fixture(scope="module")
def run_folder(tmp_path_factory):
    return tmp_path_factory.mktemp("plot") / "run"


def test_a_run_not_on_a_terminal_prints_a_progress_line_every_n_steps(run_folder, capsys):
    _omg(*FIT, "--trainer.max_steps=4", "--progress_every=2", f"--trainer.default_root_dir={run_folder}")
    lines = [line for line in capsys.readouterr().out.splitlines() if line.startswith("step ")]
    assert [line.split(" | ")[0] for line in lines] == ["step 2/4", "step 4/4"]
    fields = lines[0].split(" | ")
    assert re.fullmatch(r"train/loss [0-9.e+-]+", fields[1]) and any(re.fullmatch(r"lr [0-9.e+-]+", f) for f in fields)
    assert re.fullmatch(r"[0-9.e+]+ steps/s", fields[-2]) and re.fullmatch(r"(\d+[hm])?\d+[ms] left", fields[-1])
    # resumed, with the lines turned off: the run folder gets a second version, and no line is printed
    _omg(*FIT, "--trainer.max_steps=6", "--progress_every=0", f"--trainer.default_root_dir={run_folder}",
         "--ckpt_path=last")
    assert not [line for line in capsys.readouterr().out.splitlines() if line.startswith("step ")]


def test_plot_draws_the_curves_of_a_run_folder(run_folder, tmp_path, capsys):
    if not (run_folder / "version_1/metrics.csv").is_file():
        test_a_run_not_on_a_terminal_prints_a_progress_line_every_n_steps(run_folder, capsys)
    capsys.readouterr()
    _omg("plot", str(run_folder))
    png = run_folder / "curves.png"
    assert capsys.readouterr().out.strip() == f"wrote {png}: training losses, learning rate, validation to step 6"
    with Image.open(png) as image:
        assert image.format == "PNG" and image.size == (900, 3 * 280)  # three panels
    out = tmp_path / "one.png"
    _omg("plot", str(run_folder / "version_0"), "--out", str(out))  # one version: the first run's 4 steps
    # (Lightning logs an optimizer step's metrics at its index: steps 0..3)
    assert capsys.readouterr().out.strip() == f"wrote {out}: training losses, learning rate, validation to step 3"


def test_plot_of_a_run_that_logged_nothing_yet_is_one_line(tmp_path):
    (tmp_path / "version_0").mkdir()
    (tmp_path / "version_0/metrics.csv").write_text("epoch,step\n")  # Lightning's file before the first log
    with pytest.raises(UsageError, match=r"no metrics logged yet \(training logs every trainer.log_every_n_steps"):
        plot(tmp_path)
    assert not (tmp_path / "curves.png").exists()
