"""Fault injection: a run killed anywhere resumes to exactly the state of the run never killed.

Tiny models on the CPU with a real Lightning Trainer and real shards. A kill is an exception
raised from a callback at the start of a step (the process state is then thrown away: the
resumed run builds a new Trainer, module and data module from the config). Every comparison
is bit for bit: weights, EMA, optimizer, LR schedule, noise RNG, data position, Lightning's
loop counters, and the batches each step trained on. A run may be killed again and again, each
time resuming from the checkpoint the last resumed run wrote.
"""

from __future__ import annotations

import socket
from pathlib import Path

import lightning as L
import pytest
import torch
from lightning.pytorch.callbacks import Callback

from helpers import TINY_DIT
from helpers.forked import OmgProcess
from helpers.resume import Recorder, assert_identical, final_state, run_until_killed
from omg.data.datamodule import MotionDataModule
from omg.lit.pretrain import PretrainModule, fresh_noise_seed

BATCHES_PER_EPOCH = 4
TOTAL_STEPS = 13  # three epoch boundaries (after steps 4, 8 and 12) and a part of a fourth epoch


def fit(shards, root, *, kill_at: int | None = None, resume: bool = False, num_workers: int = 0,
        accumulate: int = 1, validate: bool = False) -> tuple[Recorder, L.Trainer]:
    """One run (or the part of it before ``kill_at``); ``validate``: one validation batch at each
    epoch's end, as the shipped configs (val_check_interval == batches_per_epoch) validate."""
    L.seed_everything(0, verbose=False)
    data = MotionDataModule(str(shards / "train"), val=str(shards / "val") if validate else None, batch_size=4,
                            max_len=30, min_len=10, batches_per_epoch=BATCHES_PER_EPOCH, num_workers=num_workers,
                            shuffle_buffer=8)
    model = PretrainModule(flavor="mini", dit=TINY_DIT,
                           ema_decay=0.9, spec=data.spec, optim={"lr": 1e-3, "warmup_steps": 3})
    recorder = Recorder()
    validation = ({"limit_val_batches": 1, "val_check_interval": BATCHES_PER_EPOCH, "check_val_every_n_epoch": None}
                  if validate else {})
    trainer = run_until_killed(model, data, root, max_steps=TOTAL_STEPS, kill_at=kill_at, resume=resume,
                               callbacks=[recorder], keep_all=True, accumulate_grad_batches=accumulate, **validation)
    return recorder, trainer


def fit_killed(shards, root, kills: tuple[int, ...], **kwargs) -> dict[int, tuple]:
    """A run killed at the start of each step in ``kills``, each time resumed from ``last.ckpt``,
    then run to its end: what each step trained on."""
    steps = {}
    for i, kill_at in enumerate([*kills, None]):
        recorder, _ = fit(shards, root, kill_at=kill_at, resume=i > 0, **kwargs)
        assert i == 0 or min(recorder.steps) == kills[i - 1]  # resumed where the last run was killed
        steps.update(recorder.steps)
    return steps


@pytest.fixture(scope="session")
def uninterrupted(h263_shards, tmp_path_factory):
    root = tmp_path_factory.mktemp("uninterrupted")
    recorder, _ = fit(h263_shards, root)
    return recorder.steps, final_state(root)


def test_every_epoch_trains_on_new_batches(uninterrupted):
    steps, state = uninterrupted
    assert len(steps) == TOTAL_STEPS and state["global_step"] == TOTAL_STEPS
    assert state["data"] == [{"epoch": 3, "batches_done": 1}]
    epochs_done = state["loops"]["epoch_progress"]["total"]
    assert epochs_done == {"ready": 4, "started": 4, "processed": 3, "completed": 3}
    epochs = {}
    for step, (epoch, ids, lengths) in steps.items():
        assert epoch == step // BATCHES_PER_EPOCH
        epochs.setdefault(epoch, []).append((ids, lengths))
    assert epochs[0] != epochs[1][: len(epochs[0])] and epochs[1] != epochs[2] + epochs[1][len(epochs[2]):]
    assert epochs[0][:2] != epochs[2], "epoch 2 replays epoch 0"


# kills at the start of a step: 4 and 8 resume from a checkpoint written at an epoch's last batch
@pytest.mark.parametrize("kill_at", [1, 3, 4, 5, 8, 9])
def test_killed_run_resumes_bit_for_bit(h263_shards, uninterrupted, tmp_path, kill_at):
    steps, expected = uninterrupted
    first, _ = fit(h263_shards, tmp_path, kill_at=kill_at)
    assert max(first.steps) == kill_at  # killed in step kill_at, after the checkpoint of step kill_at
    second, _ = fit(h263_shards, tmp_path, resume=True)
    assert min(second.steps) == kill_at
    assert {**first.steps, **second.steps} == steps, "the resumed run trained on other batches"
    assert_identical(final_state(tmp_path), expected)


@pytest.fixture(scope="session")
def uninterrupted_validated(h263_shards, tmp_path_factory):
    root = tmp_path_factory.mktemp("uninterrupted_validated")
    recorder, _ = fit(h263_shards, root, validate=True)
    return recorder.steps, final_state(root)


# A run resumed from an epoch's last batch writes the next epoch's checkpoints, and a second kill
# resumes from one of those: at the next boundary (4, 8), twice more (4, 8, 12), or after a first
# resume mid-epoch (5, 8). Lightning once counted the resumed run's next epoch as the one resumed,
# so the checkpoint at the next boundary held its epoch counters one short; with validation at the
# epoch's end, a run resumed from it restarted the finished epoch and the stream replayed it.
@pytest.mark.parametrize("validate", [False, True], ids=["no-val", "val"])
@pytest.mark.parametrize("kills", [(4, 8), (4, 8, 12), (5, 8)], ids=lambda k: "-".join(map(str, k)))
def test_a_run_killed_again_and_again_resumes_bit_for_bit(h263_shards, uninterrupted, uninterrupted_validated,
                                                          tmp_path, kills, validate):
    steps, expected = uninterrupted_validated if validate else uninterrupted
    resumed = fit_killed(h263_shards, tmp_path, kills, validate=validate)
    assert resumed == steps, "the resumed runs trained on other batches"
    assert_identical(final_state(tmp_path), expected)


def test_resume_with_loader_workers(h263_shards, tmp_path_factory):
    full = tmp_path_factory.mktemp("full")
    steps, _ = fit(h263_shards, full, num_workers=2)
    root = tmp_path_factory.mktemp("killed")
    first, _ = fit(h263_shards, root, kill_at=4, num_workers=2)
    second, _ = fit(h263_shards, root, resume=True, num_workers=2)
    assert {**first.steps, **second.steps} == steps.steps
    assert_identical(final_state(root), final_state(full))


class AccumulatingStrategy(L.pytorch.strategies.SingleDeviceStrategy):
    """Accumulates gradients itself, as DeepSpeed does: Lightning calls its optimizer step on
    every micro-batch, and it steps the optimizer on the last micro-batch of each window."""

    def __init__(self, accumulate: int):
        super().__init__(device=torch.device("cpu"))
        self.accumulate, self.micro_batches = accumulate, 0

    @property
    def handles_gradient_accumulation(self) -> bool:
        return True

    def optimizer_step(self, optimizer, closure, model=None, **kwargs):
        closure()  # forward + backward of this micro-batch
        self.micro_batches += 1
        if self.micro_batches % self.accumulate == 0:
            optimizer.step()


class WeightsAfterStep(Callback):
    def __init__(self):
        self.weights, self.last_step = [], 0

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
        if trainer.global_step != self.last_step:  # a real optimizer step happened
            self.last_step = trainer.global_step
            self.weights.append({n: p.detach().clone() for n, p in pl_module.model.named_parameters()})


@pytest.mark.parametrize("strategy", ["lightning", "deepspeed-like"])
def test_ema_follows_optimizer_steps_under_gradient_accumulation(h263_shards, strategy):
    accumulate, decay = 4, 0.9
    L.seed_everything(0, verbose=False)
    data = MotionDataModule(str(h263_shards / "train"), batch_size=2, max_len=30, min_len=10, batches_per_epoch=12,
                            num_workers=0, shuffle_buffer=8)
    model = PretrainModule(flavor="mini", dit=TINY_DIT,
                           ema_decay=decay, spec=data.spec, optim={"lr": 1e-2, "warmup_steps": 1})
    initial = {n: p.detach().clone() for n, p in model.model.named_parameters()}
    recorder = WeightsAfterStep()
    trainer = L.Trainer(accelerator="cpu", max_steps=3, accumulate_grad_batches=accumulate, logger=False,
                        enable_progress_bar=False, enable_model_summary=False, enable_checkpointing=False,
                        limit_val_batches=0, num_sanity_val_steps=0, callbacks=[recorder],
                        strategy=AccumulatingStrategy(accumulate) if strategy == "deepspeed-like" else "auto")
    trainer.fit(model, data)
    assert len(recorder.weights) == 3 and model.ema.updates == 3
    shadow = {n: t.float() for n, t in initial.items()}
    for u, weights in enumerate(recorder.weights):  # EMA.current_decay's warm-up, by hand
        d = min(decay, (1 + u) / (10 + u))
        shadow = {n: d * shadow[n] + (1 - d) * weights[n] for n in shadow}
    for n, expected in shadow.items():
        torch.testing.assert_close(model.ema.shadow[n], expected, rtol=0, atol=1e-6)


def ddp_run(shards, root, kill_at=-1, resume: bool | Path = False, devices=2, record=None) -> tuple[int, str]:
    """tests/ddp_resume_run.py on ``devices`` gloo ranks, each its own process (forked from the preloaded server,
    tests/helpers/forked.py, with LOCAL_RANK set as torchrun sets it; Lightning's own launcher is
    tests/test_launch.py's): (the first nonzero exit code of a rank, or 0; the end of that rank's stderr);
    ``resume``: from ``root``'s last checkpoint (True) or from that file (another run's)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    env = {"MASTER_ADDR": "127.0.0.1", "MASTER_PORT": str(port), "OMP_NUM_THREADS": "1"}
    script = Path(__file__).with_name("ddp_resume_run.py")
    resume = str(resume) if isinstance(resume, Path) else str(int(resume))
    args = [str(shards), str(root), str(kill_at), resume, str(devices)] + ([record] if record else [])
    ranks, logs = [], [root.parent / f"{root.name}-rank{rank}.err" for rank in range(devices)]
    for rank, log in enumerate(logs):
        ranked = {"LOCAL_RANK": str(rank), "NODE_RANK": "0"} if devices > 1 else {}
        ranks.append(OmgProcess(args, script=script, env={**env, **ranked}, stderr=log))
    try:
        codes = [rank.wait(300) for rank in ranks]
    finally:
        for rank in ranks:
            rank.kill()
    failed = next((r for r, code in enumerate(codes) if code != 0), 0)
    return codes[failed], logs[failed].read_text()[-3000:]


# The multi-process tests: each gloo run starts its ranks' interpreters (10-20 s a run on 2 cores). They
# share the runs never killed; under xdist their group runs on one worker, which makes each run once.
@pytest.fixture(scope="session")
def never_killed(h263_shards, tmp_path_factory):
    """``never_killed(devices)``: the folder of tests/ddp_resume_run.py's run on ``devices`` gloo ranks,
    never killed, each rank's steps and start state recorded as ``fresh-rank{r}.pt`` and every step's checkpoint
    kept in ``ckpt/`` (each run once)."""
    runs = {}

    def run(devices: int):
        if devices not in runs:
            root = tmp_path_factory.mktemp(f"never_killed_{devices}")
            code, err = ddp_run(h263_shards / "train", root, devices=devices, record="fresh")
            assert code == 0, err
            runs[devices] = root
        return runs[devices]

    return run


@pytest.mark.slow
@pytest.mark.xdist_group("ddp_resume")
def test_two_rank_run_resumes_bit_for_bit(h263_shards, never_killed, tmp_path):
    """Two gloo ranks on the CPU: resume from an epoch boundary, be killed at the next boundary,
    resume again, and compare with the run never killed, each rank's noise RNG and the loop
    counters included."""
    shards = h263_shards / "train"  # 4 shards, 2 per rank
    # ddp_resume_run.py: 3 batches per epoch, 7 steps. A run killed at the start of step 3 leaves the
    # never-killed run's step-3 checkpoint (the kill comes after it is written): the chain starts from that
    # file, and its own kill, at step 6, is a real one
    [written] = (never_killed(2) / "ckpt").glob("epoch=*-step=3.ckpt")
    code, err = ddp_run(shards, tmp_path / "killed", kill_at=6, resume=written)
    assert code == 3, err
    code, err = ddp_run(shards, tmp_path / "killed", resume=True)
    assert code == 0, err
    expected, resumed = final_state(never_killed(2)), final_state(tmp_path / "killed")
    assert expected["noise_rng"].shape[0] == 2 and not torch.equal(*expected["noise_rng"])  # one state per rank
    assert_identical(resumed, expected)


# Elastic resume: a checkpoint of one world size resumed on another, killed mid-epoch (step 4 is
# epoch 1's second batch in ddp_resume_run.py).
@pytest.mark.slow
@pytest.mark.xdist_group("ddp_resume")
@pytest.mark.parametrize("old,new", [(2, 1), (1, 2)], ids=["2to1", "1to2"])
def test_resume_on_another_number_of_ranks(h263_shards, never_killed, tmp_path, old, new):
    shards, kill_at = h263_shards / "train", 4
    # the checkpoint an `old`-rank run killed at the start of step 4 leaves is the never-killed run's step-4
    # checkpoint (the kill comes after it is written; test_two_rank_run_resumes_bit_for_bit kills for real)
    [written] = (never_killed(old) / "ckpt").glob(f"epoch=*-step={kill_at}.ckpt")
    saved = torch.load(written, map_location="cpu", weights_only=False)
    assert saved["global_step"] == kill_at and saved["noise_rng"].shape[0] == old
    code, resumed_err = ddp_run(shards, tmp_path / "run", resume=written, devices=new, record="resumed")
    assert code == 0, resumed_err
    fresh_run = never_killed(new)  # the new world size from scratch
    for rank in range(new):
        resumed = torch.load(tmp_path / "run" / f"resumed-rank{rank}.pt", weights_only=False)
        fresh = torch.load(fresh_run / f"fresh-rank{rank}.pt", weights_only=False)
        # weights, EMA, optimizer and schedule: the checkpoint's, whatever the world size
        start = resumed["start"]
        noise = start.pop("noise_rng")
        assert_identical(start, {k: saved[k] for k in start}, f"rank {rank}")
        # noise: rank r keeps rank r's saved state; a rank the checkpoint has none for a fresh one
        if rank < old:
            assert torch.equal(noise, saved["noise_rng"][rank])
        else:
            expected = torch.Generator().manual_seed(fresh_noise_seed(0, kill_at, rank)).get_state()
            assert torch.equal(noise, expected)
            assert not torch.equal(noise, torch.Generator().manual_seed(rank).get_state())  # not step 0's replayed
        # data: the rest of the epoch and the next are the new world size's stream at the same position
        assert sorted(resumed["steps"]) == [4, 5, 6]
        assert resumed["steps"] == {step: fresh["steps"][step] for step in (4, 5, 6)}, f"rank {rank}"
    assert torch.load(tmp_path / "run" / "ckpt" / "last.ckpt", weights_only=False)["global_step"] == 7
    assert f"resuming a {old}-rank checkpoint on {new} ranks" in resumed_err  # said, not silent
