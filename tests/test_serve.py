"""``omg serve`` against a real running server (uvicorn on a free port) with tiny checkpoints of the three
families: a ControlNet (text → human), OmniMotionGPT (text → animal, with the ControlNet as its human
source) and a habit-transfer pair (VQ-VAE + flow prior), each fitted one step."""

from __future__ import annotations

import io
import itertools
import json
import os
import re
import signal
import socket
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest
import torch

from helpers import MINI, REPO, TINY_DIT
from helpers.forked import OmgProcess
from helpers.habit import CATEGORIES

pytest.importorskip("fastapi", reason="omg serve needs fastapi (pip install -e '.[dev]')")
httpx = pytest.importorskip("httpx", reason="the server tests talk to it with httpx")
# the tests share the servers, their checkpoints, the browser and the FBX figure: one worker builds them once
pytestmark = pytest.mark.xdist_group("serve")



def _fit_save(module, data, path: Path) -> Path:
    """One training step, then the checkpoint (as ``omg fit`` records the class)."""
    import lightning as L

    trainer = L.Trainer(max_steps=1, accelerator="cpu", logger=False, enable_checkpointing=False,
                        enable_progress_bar=False, enable_model_summary=False, default_root_dir=str(path.parent),
                        limit_val_batches=0)
    trainer.fit(module, data)
    module.hparams["_class_path"] = f"{type(module).__module__}.{type(module).__qualname__}"
    trainer.save_checkpoint(path)
    return path


def _data(path: Path, **kw):
    from omg.data.datamodule import MotionDataModule

    args = dict(batch_size=4, max_len=40, min_len=20, num_workers=0, shuffle_buffer=32, clips="whole")
    return MotionDataModule(str(path), **{**args, **kw})


@pytest.fixture(scope="session")
def serve_ckpts(tmp_path_factory) -> dict[str, Path]:
    """human.ckpt (ControlNet, hash text), animal.ckpt (OmniMotionGPT), habit.ckpt (flow prior over habit_vq.ckpt)."""
    from omg.data.paired import PairedDataModule
    from omg.lit.controlnet import ControlNetModule
    from omg.lit.habit import HabitPriorModule, HabitVQModule
    from omg.lit.omgpt import OmniMotionModule
    from omg.lit.pretrain import PretrainModule

    root = tmp_path_factory.mktemp("serve_ckpts")
    torch.manual_seed(0)
    human = _data(MINI / "human263/train")
    pretrain = PretrainModule(flavor="mini", dit=TINY_DIT, spec=human.spec,
                              ema_decay=0, optim={"warmup_steps": 1})
    _fit_save(pretrain, human, root / "pretrain.ckpt")
    controlnet = ControlNetModule(pretrained=str(root / "pretrain.ckpt"), text_encoder="hash",
                                  moc={"d_c": 16, "num_experts": 2}, spec=human.spec, ema_decay=0,
                                  optim={"warmup_steps": 1})
    _fit_save(controlnet, _data(MINI / "human263/train"), root / "human.ckpt")
    animal = _data(MINI / "animal_maa/train", max_len=32)
    stream = dict(train=str(MINI / "human_maa/train"), batch_size=4, max_len=32, min_len=20, num_workers=0,
                  shuffle_buffer=32, clips="whole")
    config = {"joint_layers": 1, "joint_heads": 2, "temporal_dim": 32, "temporal_layers": 1, "latent_dim": 32}
    omgpt = OmniMotionModule(flavor="mini", config=config, text_encoder="hash", spec=animal.spec, ema_decay=0)
    paired = PairedDataModule(str(MINI / "animal_maa/train"), human=stream, batch_size=4, max_len=32, min_len=20,
                              num_workers=0, shuffle_buffer=32, clips="whole")
    _fit_save(omgpt, paired, root / "animal.ckpt")
    quatvel = dict(batch_size=8, max_len=64, min_len=64, clips="windows", verify_shards=False)
    vq = HabitVQModule(CATEGORIES, flavor="tiny", text_encoder="hash", spec=_data(MINI / "animal_quatvel/train",
                                                                                  **quatvel).spec)
    _fit_save(vq, _data(MINI / "animal_quatvel/train", **quatvel), root / "habit_vq.ckpt")
    _fit_save(HabitPriorModule(str(root / "habit_vq.ckpt")), _data(MINI / "animal_quatvel/train", **quatvel),
              root / "habit.ckpt")
    return {"human": root / "human.ckpt", "animal": root / "animal.ckpt", "habit": root / "habit.ckpt",
            "pretrain": root / "pretrain.ckpt"}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class ThreadServer:
    """uvicorn serving the app in a thread of this process (the tests reach its models and batcher)."""

    def __init__(self, app, read_timeout: float = 60.0):
        import uvicorn

        from omg.tools.serve import server_config

        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.server = uvicorn.Server(server_config(app, "127.0.0.1", self.port, read_timeout, log_level="warning"))
        self.thread = threading.Thread(target=self.server.run, daemon=True)
        self.thread.start()
        deadline = time.monotonic() + 30
        while not self.server.started:
            assert time.monotonic() < deadline and self.thread.is_alive(), "the server did not start"
            time.sleep(0.02)

    def stop(self) -> None:
        self.server.should_exit = True
        self.thread.join(30)


@pytest.fixture(scope="session")
def server(serve_ckpts, tmp_path_factory):
    from omg.tools.serve import load_models
    from omg.tools.serve.app import Limits, create_app

    models = load_models([serve_ckpts["human"], serve_ckpts["animal"], serve_ckpts["habit"],
                          serve_ckpts["pretrain"]], serve_ckpts["human"], torch.device("cpu"))
    out = tmp_path_factory.mktemp("serve_results")
    app = create_app(models, out, Limits(max_batch=8, max_wait=0.3, max_samples=8, max_upload_bytes=2_000_000))
    running = ThreadServer(app)
    running.app, running.out, running.models = app, out, {m.name: m for m in models}
    yield running
    running.stop()


@pytest.fixture
def client(server):
    with httpx.Client(base_url=server.url, timeout=120) as c:
        yield c


def _generate(client, **body) -> dict:
    response = client.post("/v1/generate", json=body)
    assert response.status_code == 200, response.text
    return response.json()


# -- routes ---------------------------------------------------------------------------------


def test_health_and_models_come_from_the_cards(client):
    assert client.get("/healthz").json()["status"] == "ok"
    models = {m["name"]: m for m in client.get("/v1/models").json()["models"]}
    assert set(models) == {"human", "animal", "habit", "pretrain"}
    human, animal, habit = models["human"], models["animal"], models["habit"]
    assert human["card"]["inputs"] == ["text", "unconditional"] and human["card"]["skeleton"] == "smpl22"
    assert human["card"]["row_seeds"] and "ddim" in human["card"]["samplers"] and len(human["parents"]) == 22
    assert animal["card"]["skeleton"] == "smal35" and "dog" in animal["card"]["species"]
    assert animal["source_generator"] and len(animal["parents"]) == 35
    assert habit["card"]["needs"] == ["motion", "species"] and habit["card"]["open_species"]
    assert models["pretrain"]["card"]["inputs"] == ["unconditional"]
    assert client.get("/openapi.json").json()["paths"].keys() >= {"/v1/generate", "/v1/transfer", "/v1/models",
                                                                  "/healthz"}


def test_models_list_the_number_bounds_and_defaults_the_server_checks_with(client, server):
    """Each card's ``ranges`` (steps, guidance, the family's number options) and, where it takes a timeline, the
    timeline's numbers are the constants the server and ``--option`` check with: the page sets its fields from
    them (``GET /v1/models``), so it repeats none of them."""
    from omg.errors import UsageError
    from omg.generation.habit import TEMPERATURE
    from omg.generation.timeline import DEFAULT_TRANSITION, parse_timeline
    from omg.lit.sampling import MAX_SMOOTHING, MAX_STANCE_ROOT
    from omg.lit.timeline import DEFAULT_COUPLING

    def bounds(low, high=None, default=None, low_open=False):
        return {"low": low, "high": high, "default": default, "low_open": low_open}

    models = {m["name"]: m for m in client.get("/v1/models").json()["models"]}
    human, animal, habit = models["human"]["card"], models["animal"]["card"], models["habit"]["card"]
    module = server.models["human"].generator.module
    assert human["ranges"] == {"steps": bounds(1, human["max_steps"], human["default_steps"]),
                               "guidance": bounds(0, None, human["guidance"]),
                               "stance_root": bounds(0, MAX_STANCE_ROOT, module.stance_root),
                               "smoothing": bounds(0, MAX_SMOOTHING, 0)}
    assert human["max_steps"] == module.diffusion.num_timesteps and human["guidance"] == module.guidance_scale
    assert set(human["options"]) == {"stance_root", "smoothing"} and "option_ranges" not in human  # as it was
    assert animal["ranges"] == {"steps": bounds(1)}  # the human chain's steps: no bound of its own, no default
    assert habit["ranges"] == {"temperature": bounds(0, None, TEMPERATURE.default, low_open=True)}
    timeline = {"transition": bounds(0, None, DEFAULT_TRANSITION), "context": bounds(0),
                "coupling": bounds(0, 1, DEFAULT_COUPLING)}
    assert models["human"]["timeline_ranges"] == timeline
    assert models["animal"]["timeline_ranges"] == models["habit"]["timeline_ranges"] == {}
    # the same bounds refuse a value past them: --option, the timeline file, the API
    generator = server.models["human"].generator
    assert generator.option("smoothing", str(MAX_SMOOTHING)) == MAX_SMOOTHING
    for key, past in (("smoothing", MAX_SMOOTHING + 0.5), ("stance_root", MAX_STANCE_ROOT + 0.5)):
        with pytest.raises(UsageError, match=rf"give a number in \[0, {human['ranges'][key]['high']:g}\]"):
            generator.option(key, str(past))
    with pytest.raises(UsageError, match=r"coupling must be a number in \[0, 1\]"):
        parse_timeline({"timeline": [{"start": 0, "end": 1, "text": "a person walks"}], "chains": "separate",
                        "coupling": timeline["coupling"]["high"] + 0.5})
    assert parse_timeline([{"start": 0, "end": 1, "text": "a person walks"}]).transition == DEFAULT_TRANSITION
    response = client.post("/v1/generate", json={"model": "human", "prompts": ["a person walks"],
                                                 "smoothing": MAX_SMOOTHING + 0.5})
    assert response.status_code == 422 and "smoothing" in response.json()["detail"]


def test_generate_answers_joints_and_the_files_omg_generate_writes(client):
    result = _generate(client, model="human", prompts=["a person walks forward"], length=1.5, num_samples=2,
                       steps=3, seed=5)
    assert [m["frames"] for m in result["motions"]] == [30, 30] and result["fps"] == 20
    joints = np.asarray(result["motions"][1]["joints"])
    assert joints.shape == (30, 22, 3) and result["parents"][:3] == [-1, 0, 0]
    files = result["motions"][1]["files"]
    assert set(files) == {"bvh", "joints", "features"}
    npy = np.load(io.BytesIO(client.get(files["joints"]).content))
    np.testing.assert_allclose(npy, joints, atol=1e-4)
    assert client.get(files["bvh"]).text.startswith("HIERARCHY")
    assert np.load(io.BytesIO(client.get(files["features"]).content)).shape == (30, 263)
    settings = client.get(result["settings"]).json()
    assert settings["prompts"] == ["a person walks forward"] and settings["steps"] == 3
    assert [s["seed"] for s in settings["samples"]] == [5, 6] and [s["repeat"] for s in settings["samples"]] == [0, 1]


def test_generate_follows_a_timeline_in_the_body(client, server):
    """A prompt timeline with a body part, sampled alone (never batched with another request), its settings
    recorded; the card says which models take one."""
    timeline = {"timeline": [{"start": 0, "end": 1, "text": "a person walks forward"},
                             {"start": 0.8, "end": 2, "text": "a person turns left"}],
                "parts": [{"parts": ["right_arm"], "text": "a person waves the right hand", "start": 0.5}]}
    result = _generate(client, model="human", timeline=timeline, num_samples=2, steps=2, seed=3)
    assert [m["frames"] for m in result["motions"]] == [40, 40]  # the timeline's 2 s
    settings = client.get(result["settings"]).json()
    assert settings["timeline"]["parts"][0]["parts"] == ["right_arm"] and settings["length_s"] == 2.0
    separate = _generate(client, model="human", timeline={**timeline, "chains": "separate", "coupling": 0.25},
                         num_samples=1, steps=2, seed=3)  # one chain per text, the motion joined from them
    recorded = client.get(separate["settings"]).json()["timeline"]
    assert recorded["chains"] == "separate" and recorded["coupling"] == 0.25
    smoothed = _generate(client, model="human", timeline=timeline, num_samples=2, steps=2, seed=3, smoothing=2)
    assert client.get(smoothed["settings"]).json()["smoothing"] == 2.0  # the same noise, smoothed over time
    rough, smooth = (np.asarray(r["motions"][0]["joints"]) for r in (result, smoothed))
    assert np.abs(np.diff(smooth, n=3, axis=0)).mean() < 0.5 * np.abs(np.diff(rough, n=3, axis=0)).mean()
    cards = {m["name"]: m["card"] for m in client.get("/v1/models").json()["models"]}
    assert "smoothing" in cards["human"]["options"] and "smoothing" in cards["pretrain"]["options"]
    assert cards["human"]["timeline"] == ["timeline", "parts"]
    assert cards["animal"]["timeline"] == cards["habit"]["timeline"] == cards["pretrain"]["timeline"] == []
    parts = {m["name"]: m["body_parts"] for m in client.get("/v1/models").json()["models"]}  # what the page offers
    assert parts["human"] == ["root", "torso", "left_arm", "right_arm", "left_leg", "right_leg", "legs", "arms",
                              "upper_body"]
    assert parts["animal"] == parts["habit"] == parts["pretrain"] == []


def test_animal_from_text_through_the_human_chain_and_unconditional(client):
    result = _generate(client, model="animal", prompts=["a dog jumps over a log"], length=1, steps=2)
    motion = result["motions"][0]
    assert np.asarray(motion["joints"]).shape == (20, 35, 3) and motion["record"]["animal"] == "dog"
    assert result["skeleton"] == "smal35"
    result = _generate(client, model="pretrain", length=1, num_samples=2, steps=2)
    assert len(result["motions"]) == 2 and result["motions"][0]["title"] == "unconditional"


def _bvh(path: Path) -> bytes:
    manifest = json.loads((path / "manifest.json").read_text())["clips"]
    return next((path / c["path"]).read_bytes() for c in manifest if c.get("domain") == "dog"
                and c["path"].endswith(".bvh"))


def test_transfer_an_uploaded_clip_to_another_species(client, shared_motion):
    upload = _bvh(shared_motion)
    response = client.post("/v1/transfer", data={"model": "habit", "to": "horse", "seed": "3"},
                           files={"file": ("clip.bvh", upload)})
    assert response.status_code == 200, response.text
    result = response.json()
    motion = result["motions"][0]
    assert np.asarray(motion["joints"]).shape[1:] == (35, 3) and "horse" in motion["title"]
    assert client.get(motion["files"]["bvh"]).text.startswith("HIERARCHY")
    assert client.get(result["settings"]).json()["category"] == "horse"


HUMAN_TAKE = "human/bandai1/dataset-1_bow_normal_001.bvh"
THREE_JOINT_RIG = (b"HIERARCHY\nROOT Hips\n{\n OFFSET 0 0 0\n CHANNELS 6 Xposition Yposition Zposition Zrotation "
                   b"Xrotation Yrotation\n JOINT Foo\n {\n  OFFSET 0 1 0\n  CHANNELS 3 Zrotation Xrotation Yrotation\n"
                   b"  End Site\n  {\n   OFFSET 0 1 0\n  }\n }\n}\nMOTION\nFrames: 2\nFrame Time: 0.05\n"
                   + b"0 0 0 0 0 0 0 0 0\n" * 2)  # no joint map fits it


def test_keyframes_are_a_takes_frames_retargeted_as_a_constraints_file_reads_them(client, server, shared_motion):
    """/v1/keyframes answers every frame of an uploaded take on the model's skeleton, the poses a constraints
    file's keyframe ``file`` and ``frame`` resolve to (the same importers); one of them, sent back as a keyframe's
    positions, is met."""
    from omg.generation.control import read_constraints

    take = shared_motion / HUMAN_TAKE
    response = client.post("/v1/keyframes", data={"model": "human"}, files={"file": ("bow.bvh", take.read_bytes())})
    assert response.status_code == 200, response.text
    answer = response.json()
    poses = np.asarray(answer["poses"])
    assert answer["frames"] == len(poses) > 30 and poses.shape[1:] == (22, 3) and answer["fps"] == 20
    assert answer["joints"][0] == "pelvis" and answer["source"] == "bow.bvh"
    card = server.models["human"].card
    control, _ = read_constraints({"keyframes": [{"time": 0.5, "file": str(take), "frame": 30}]}, card, 20)
    np.testing.assert_allclose(poses[30], control.targets[0, 10].numpy(), atol=1e-4)
    result = _generate(client, model="human", prompts=["a person bows"], length=1, steps=2,
                       constraints={"keyframes": [{"time": 0.5, "positions": answer["poses"][30]}]})
    assert set(result["motions"][0]["record"]["control_error_m"]) == {"keyframes[0]"}


@pytest.mark.parametrize("name, content, fields, status, message", [
    ("bow.bvh", None, {"model": "animal"}, 422, "model 'animal' takes no keyframes; its card lists no constraints"),
    ("bow.bvh", None, {"model": "nope"}, 404, "unknown model 'nope'"),
    ("bow.exe", b"MZ", {}, 422, "the upload 'bow.exe' is not a motion file"),
    ("bow.bvh", b"HIERARCHY\nROOT garbage {", {}, 422, "bow.bvh"),
    ("rig.bvh", "rig", {}, 422, "no registered map fits"),
    ("poses.npy", "npy", {}, 422, "poses.npy: a .npy keyframe holds smpl22 joint positions (T, 22, 3), got shape "
                                  "(4, 5)"),
    ("big.bvh", b"x" * 2_100_000, {}, 413, "2000000 bytes allowed for an upload (--max_upload_mb)"),
    ("big.bvh", b"x" * 2_010_000, {}, 413, "larger than the 2000000 bytes allowed (--max_upload_mb)"),  # the file's
    ("bow.bvh", None, {"joint_map": "../x"}, 422, "joint_map '../x': give a registered joint map's name"),
    ("bow.bvh", None, {"frame": "3"}, 422, "frame: Extra inputs are not permitted (the form's fields: file, model, "
                                           "joint_map)"),
], ids=["no-keyframes", "unknown-model", "not-motion", "garbled", "unfit-rig", "npy-shape", "body-too-large",
        "file-too-large", "joint-map-path", "misspelt-field"])
def test_bad_keyframe_uploads_are_one_line(client, shared_motion, name, content, fields, status, message):
    if content is None:
        content = (shared_motion / HUMAN_TAKE).read_bytes()
    elif content == "rig":
        content = THREE_JOINT_RIG
    elif content == "npy":
        buffer = io.BytesIO()
        np.save(buffer, np.zeros((4, 5), np.float32))
        content = buffer.getvalue()
    response = client.post("/v1/keyframes", data={"model": "human", **fields}, files={"file": (name, content)})
    detail = _one_line(response, status, message)
    assert "omg-upload-" not in detail and "/tmp" not in detail  # no server path leaks
    _one_line(client.post("/v1/keyframes", json={"model": "human"}), 415, "/v1/keyframes takes a multipart form")


# -- batching -------------------------------------------------------------------------------


def test_requests_that_arrive_together_are_one_call_and_each_result_is_its_own(client, server):
    bodies = [dict(model="human", prompts=[p], length=1, steps=3, seed=s)
              for p, s in (("a person walks", 1), ("a person runs in a circle", 7), ("a person waves", 3))]
    alone = [_generate(client, **b) for b in bodies]
    assert all(r["batched_motions"] == 1 for r in alone)
    calls = server.app.state.batcher.calls
    with ThreadPoolExecutor(3) as pool:
        together = list(pool.map(lambda b: _generate(client, **b), bodies))
    assert server.app.state.batcher.calls == calls + 1 and all(r["batched_motions"] == 3 for r in together)
    for a, b in zip(alone, together):
        np.testing.assert_allclose(np.asarray(a["motions"][0]["joints"]), np.asarray(b["motions"][0]["joints"]),
                                   atol=2e-4)  # the JSON's 4 decimals; the .npy files are compared exactly below
        x = np.load(io.BytesIO(client.get(a["motions"][0]["files"]["features"]).content))
        y = np.load(io.BytesIO(client.get(b["motions"][0]["files"]["features"]).content))
        np.testing.assert_allclose(x, y, rtol=0, atol=1e-5)


def test_row_seeds_leave_omg_generate_bitwise_as_it_was(server):
    """Without row seeds a request is sampled as before (one generator seeded with the batch seed); with
    them, each motion is its own whatever it is batched with."""
    from omg.generation.protocol import GenerationRequest

    generator = server.models["human"].generator
    module = generator.module
    request = GenerationRequest(prompts=["a person walks", "a person jumps"], frames=24, num_samples=2, seed=9,
                                steps=4)
    motions = generator.generate(request)
    texts = ["a person walks", "a person walks", "a person jumps", "a person jumps"]
    mask = torch.ones(4, 24, dtype=torch.bool)
    with torch.no_grad():  # the path before row seeds, spelled out: x_T from one generator seeded 9
        x = module.diffusion.ddim_sample(module.denoiser(texts, mask, None), (4, 24, 263), steps=4, mask=mask,
                                         generator=torch.Generator().manual_seed(9))
    for motion, row in zip(motions, module.denormalize(x)):
        assert np.array_equal(motion.features, row.float().numpy())
    alone = generator.generate(GenerationRequest(prompts=["a person jumps"], frames=24, steps=4, row_seeds=[11]))
    batched = generator.generate(GenerationRequest(prompts=texts[:2] + ["a person jumps"], frames=24, steps=4,
                                                row_seeds=[1, 2, 11]))
    np.testing.assert_allclose(alone[0].features, batched[2].features, rtol=0, atol=1e-5)
    assert not np.allclose(batched[0].features, batched[1].features)


def test_the_server_answers_while_it_samples(client, server):
    with ThreadPoolExecutor(1) as pool:
        slow = pool.submit(_generate, client, model="human", prompts=["a person walks"], length=3, steps=150)
        time.sleep(0.5)
        started = time.perf_counter()
        assert client.get("/healthz").status_code == 200
        assert time.perf_counter() - started < 1.0 and not slow.done()
        # the status shows the batch in flight: the sampler's step of its steps, the time left by the server's clock
        seen = []
        while not slow.done() and len(seen) < 3:
            if (progress := client.get("/v1/status").json()["progress"]) and progress["step"] > 0:
                seen.append(progress)
            time.sleep(0.05)
        assert slow.result()["motions"]
    assert len(seen) == 3, seen
    for p in seen:
        assert (p["rows"], p["steps"], p["done"], p["motions"]) == (1, 150, 0, 1) and 0 < p["step"] <= 150, p
        assert p["elapsed_s"] > 0 and p["eta_s"] >= 0, p
    assert [p["step"] for p in seen] == sorted(p["step"] for p in seen)
    # nothing in flight: no progress; the model's seconds per step kept for the next call's first estimate
    assert client.get("/v1/status").json()["progress"] is None
    assert server.app.state.batcher.seconds_per_step["human"] > 0


def test_the_families_without_sampler_steps_report_each_motion(server, shared_motion, tmp_path):
    """OmniMotionGPT reports each motion, with the steps of the second model making its human motion; habit
    transfer each motion alone."""
    from omg.generation.progress import Progress
    from omg.generation.protocol import GenerationRequest

    animal, heard = server.models["animal"], []
    animal.generator.generate(GenerationRequest(prompts=["a dog walks"], frames=20, num_samples=2, steps=2,
                                                source_module=animal.source_module, progress=heard.append))
    assert heard == [p for k in (0, 1) for p in (Progress(k, 1, 2, 0, 2), Progress(k, 1, 2, 1, 2),
                                                  Progress(k, 1, 2, 2, 2), Progress(k, 1, 2, 2, 2, finished=True))]
    habit, heard = server.models["habit"].generator, []
    (tmp_path / "dog.bvh").write_bytes(_bvh(shared_motion))
    habit.generate(GenerationRequest(prompts=None, frames=64, num_samples=2, species="horse",
                                     source=habit.read_source(tmp_path / "dog.bvh"), progress=heard.append))
    assert heard == [Progress(0, 1, 2), Progress(0, 1, 2, finished=True), Progress(1, 1, 2),
                     Progress(1, 1, 2, finished=True)]


# -- bad requests ---------------------------------------------------------------------------


# 404: a model that is not loaded; 422: a value the model cannot take (pydantic's and the cards' checks alike)
@pytest.mark.parametrize("body, status, message", [
    (dict(model="nope", prompts=["a person walks"]), 404, "unknown model 'nope'; loaded: human, animal, habit"),
    (dict(model="human", prompts=["a person walks"], sampler="heun"), 422, "unknown sampler 'heun'"),
    (dict(model="human", prompts=[" "]), 422, "prompt 1 is empty"),
    (dict(model="human", prompts=["a" * 301]), 422, "prompt 1 is 301 characters long; at most 300"),
    (dict(model="human", prompts=["a person walks"], length=100), 422, "length 100 s is 2000 frames; this model"),
    (dict(model="human", prompts=["a person walks"], length=1e308), 422, "length 1e+308 s is too many frames"),
    (dict(model="human", prompts=["a person walks"], length=-1), 422, "length: Input should be greater than 0"),
    (dict(model="human", prompts=["a person walks"], guidance="NaN"), 422, "guidance: Input should be a finite"),
    (dict(model="human", prompts=["a person walks"], seed=-3), 422, "seed: Input should be greater than or equal"),
    (dict(model="human", prompts=["a person walks"], seed=2**62), 422, "seed: Input should be less than"),
    (dict(model="human", prompts=["a person walks"], num_samples=9), 422, "9 motions asked for; at most 8"),
    (dict(model="human", prompts=["a person walks"], steps=5000), 422, "steps must be in 1..1000"),
    (dict(model="human", prompts=["a person walks"], num_sample=2), 422, "num_sample: Extra inputs are not permitted"),
    (dict(model="human", prompts=["a person walks"], smoothing=-1), 422, "smoothing: Input should be greater than or"),
    (dict(model="human", prompts=["a person walks"], smoothing=11), 422, "smoothing: Input should be less than or"),
    (dict(model="animal", prompts=["a dog walks"], smoothing=1), 422, "model 'animal' takes no option smoothing"),
    (dict(model="human", prompt="a person walks"), 422, "prompt: Extra inputs are not permitted"),
    (dict(model="human", timeline=[{"start": 0, "end": 1, "txt": "a person walks"}]), 422,
     "timeline: timeline[0]: unknown key 'txt'; a segment has start, end, text"),
    (dict(model="human", timeline={"parts": [{"parts": ["legs"], "text": "a person walks"}], "chains": "split"}), 422,
     "timeline: chains must be one of joint, separate, got 'split'"),
    (dict(model="human", prompts=["a person walks"], constraints={"keyframes": [], "keyframe": []}), 422,
     "constraints: unknown key 'keyframe'"),
    (dict(model="human", prompts="a person walks"), 422, "prompts: Input should be a valid list"),
    (dict(model="human", prompts=["a person\x00walks"]), 422, "prompt 1 holds the control character '\\x00'"),
    (dict(model="human", prompts=["a person\x85walks"]), 422, "prompt 1 holds the control character '\\x85'"),
    (dict(model="human", prompts=["a person walks", "\ud800 walks"]), 422, "prompt 2 holds a lone surrogate"),
    (dict(model="animal", prompts=["a dog walks"], species="do\udc80g"), 422, "species holds a lone surrogate"),
    (dict(model="animal", prompts=["a dog walks"], species="d" * 301), 422, "species is 301 characters long"),
    (dict(model="animal"), 422, "generates from prompts"),
    (dict(model="pretrain", prompts=["a person walks"]), 422, "unconditional"),
    (dict(model="animal", prompts=["a dog walks"], species="unicorn"), 422, "unknown animal 'unicorn'"),
    (dict(model="habit", prompts=["a dog walks"]), 422, "does not generate from prompts"),
    ([1, 2], 422, "Input should be a valid dictionary"),
    (dict(model="human", timeline=[{"start": 0, "end": 1, "text": "a person walks"},
                                   {"start": 2, "end": 3, "text": "a person waves"}]), 422,
     "timeline: a gap between timeline[0] (ends at 1 s) and timeline[1] (starts at 2 s)"),
    (dict(model="human", timeline={"parts": [{"parts": ["wings"], "text": "a person flies"}]}), 422,
     "timeline: parts[0]: unknown body part 'wings'; smpl22's: root, torso"),
    (dict(model="human", timeline=[{"start": 0, "end": 1, "text": "a\x00b"}]), 422,
     "timeline[0].text holds the control character"),
    (dict(model="human", prompts=["a person walks"], timeline=[{"start": 0, "end": 1, "text": "a person walks"}]),
     422, "give prompts or timeline (whose segments carry their texts), not both"),
    (dict(model="animal", timeline=[{"start": 0, "end": 1, "text": "a dog walks"}]), 422,
     "timeline: model 'animal' takes no prompt timeline; its card lists none"),
    (dict(model="pretrain", timeline=[{"start": 0, "end": 1, "text": "a person walks"}]), 422,
     "timeline: model 'pretrain' takes no prompt timeline; its card lists none"),
    (dict(model="human", prompts=["a person walks " * 3000] * 2), 413, "bytes allowed (--max_json_kb)"),
])
def test_bad_generate_requests_are_one_readable_line(client, body, status, message):
    response = _post_json(client, body)
    assert response.status_code == status, response.text
    detail = response.json()["detail"]
    assert isinstance(detail, str) and "\n" not in detail and "Traceback" not in detail
    assert message in detail, detail
    assert client.get("/healthz").status_code == 200


def _post_json(client, body, **kw):
    """JSON as Python's json writes it (ASCII: a lone surrogate as \\ud800, which httpx's json= cannot encode)."""
    return client.post("/v1/generate", content=json.dumps(body), headers={"content-type": "application/json"}, **kw)


def _one_line(response, status: int, words: str = "") -> str:
    assert response.status_code == status, response.text
    assert response.headers["content-type"] == "application/json", response.text
    detail = response.json()["detail"]
    assert isinstance(detail, str) and "\n" not in detail and "Traceback" not in detail and words in detail, detail
    return detail


@pytest.mark.parametrize("method, path, kw, status, words", [
    ("POST", "/v1/generate", dict(content=b"{not json", headers={"content-type": "application/json"}), 400,
     "the body is not valid JSON: Expecting property name"),
    ("POST", "/v1/generate", dict(content=b"model=human",
                                  headers={"content-type": "application/x-www-form-urlencoded"}),
     415, "/v1/generate takes a JSON body"),
    ("POST", "/v1/generate", dict(content=b'{"model": "human"}', headers={"content-type": "text/plain"}), 415,
     "not 'text/plain'"),
    ("POST", "/v1/transfer", dict(json={"model": "habit", "to": "horse"}), 415, "/v1/transfer takes a multipart form"),
    ("POST", "/v1/results/0123456789ab/character", dict(json={"file": "figure.glb"}), 415,
     "/v1/results/0123456789ab/character takes a multipart form"),
    ("POST", "/v1/transfer", dict(content=b"garbage",
                                  headers={"content-type": "multipart/form-data; boundary=x"}), 400, ""),
    ("POST", "/v1/transfer", dict(data={"model": "habit", "to": "horse"}, files={"other": ("a.txt", b"a")}), 422,
     "file: Field required"),
    ("GET", "/v1/generate", {}, 405, "Method Not Allowed"),
    ("PUT", "/v1/models", dict(content=b"{}"), 405, "Method Not Allowed"),
    ("GET", "/v1/nope", {}, 404, "Not Found"),
    ("GET", "/static/nope.js", {}, 404, "Not Found"),
    ("GET", "/v1/results/0123456789ab/generation.json", {}, 404, "no such result file"),
])
def test_each_route_refuses_with_its_status_and_one_line(client, method, path, kw, status, words):
    response = client.request(method, path, **kw)
    _one_line(response, status, words)
    if status == 405:
        assert response.headers["allow"]
    assert client.get("/healthz").status_code == 200


@pytest.mark.parametrize("name, content, fields, status, message", [
    ("clip.bvh", b"HIERARCHY\nROOT garbage {", {"to": "horse"}, 422, "clip.bvh"),
    ("clip.exe", b"MZ", {"to": "horse"}, 422, "is not a motion file"),
    ("clip.npy", b"\x93NUMPY garbled", {"to": "horse"}, 422, "clip.npy"),
    ("big.bvh", b"x" * 2_100_000, {"to": "horse"}, 413, "bytes allowed"),
    ("big.bvh", b"x" * 2_010_000, {"to": "horse"}, 413, "bytes allowed"),  # under the body's limit, over the file's
    ("clip.bvh", None, {"to": "horse", "model": "human"}, 422, "does not generate from"),
    ("clip.bvh", None, {"to": "horse", "model": "nope"}, 404, "unknown model 'nope'"),
    ("clip.bvh", None, {"to": "horse", "joint_map": "../../etc"}, 422, "joint_map"),
    ("clip.bvh", None, {"to": "hor\x07se"}, 422, "to holds the control character"),
    ("clip.bvh", None, {"to": "horse", "seed": "-1"}, 422, "seed: Input should be greater than or equal to 0"),
    ("clip.bvh", None, {"to": "horse", "num_samples": "many"}, 422, "num_samples: Input should be a valid integer"),
    ("clip.bvh", "rig", {"to": "horse"}, 422, "no registered map fits"),
    ("clip.bvh", None, {"to": "horse", "prompt": "a dog walks"}, 422, "prompt: Extra inputs are not permitted (the "
                                                                      "form's fields: file, model, to, prompts, seed,"),
], ids=["garbled-bvh", "not-motion", "garbled-npy", "too-large", "file-too-large", "wrong-model", "unknown-model",
        "joint-map-path", "to-control", "seed-neg", "num-samples-text", "unfit-rig", "misspelt-field"])
def test_bad_uploads_are_one_readable_line(client, shared_motion, name, content, fields, status, message):
    if content is None:
        content = _bvh(shared_motion)
    elif content == "rig":  # a rig of three joints: no joint map fits it
        content = THREE_JOINT_RIG
    response = client.post("/v1/transfer", data={"model": "habit", **fields}, files={"file": (name, content)})
    assert response.status_code == status, response.text
    detail = response.json()["detail"]
    assert isinstance(detail, str) and "\n" not in detail and "Traceback" not in detail and message in detail
    assert "omg-upload-" not in detail  # no server path leaks
    assert client.get("/healthz").status_code == 200


@pytest.mark.parametrize("path", ["/v1/results/../../etc/passwd", "/v1/results/abc/generation.json",
                                  "/v1/results/000000000000/generation.json", "/v1/results/%2e%2e/%2e%2e%2fsecret",
                                  "/v1/results/0123456789ab/..%2f..%2fsecret"])
def test_downloads_serve_only_the_servers_own_files(client, server, path):
    (server.out.parent / "secret").write_text("no")
    response = client.get(path)
    assert response.status_code == 404 and "no" != response.text


def test_a_failing_generation_is_500_and_the_next_request_works(client, server):
    module = server.models["human"].generator
    original = module.generate

    def broken(request):
        raise RuntimeError("CUDA out of memory\n(simulated)")

    module.generate = broken
    try:
        response = client.post("/v1/generate", json=dict(model="human", prompts=["a person walks"], steps=2))
    finally:
        del module.generate
    assert response.status_code == 500 and response.json()["detail"] == ("generation failed: CUDA out of memory "
                                                                         "(simulated)")
    assert module.generate == original
    assert _generate(client, model="human", prompts=["a person walks"], steps=2, length=1)["motions"]


def test_a_crash_outside_generation_is_one_line_of_json(client, server):
    """Any route's unforeseen error answers 500 as one line of JSON (it was uvicorn's plain-text page)."""
    model = server.models["pretrain"]
    model.info = lambda: {"broken": 1 / 0}  # a card that cannot be listed
    try:
        response = client.get("/v1/models")
    finally:
        del model.info
    assert _one_line(response, 500) == "the server failed: division by zero"
    assert client.get("/v1/models").status_code == 200


# -- one request cannot fail the others ---------------------------------------------------------


def test_a_poisoned_prompt_in_a_burst_fails_alone(client):
    """A prompt holding a lone surrogate passed the checks and broke the text encoder inside the shared batch:
    7 of 7 concurrent requests answered 500. It is now refused on its own (422) and the others answer."""
    bodies = [dict(model="human", prompts=[f"a person walks {i} steps"], length=1, steps=2, seed=i) for i in range(6)]
    bodies.insert(3, dict(model="human", prompts=["a person \ud800 walks"], length=1, steps=2))
    with ThreadPoolExecutor(len(bodies)) as pool:
        responses = list(pool.map(lambda body: _post_json(client, body), bodies))
    _one_line(responses.pop(3), 422, "prompt 1 holds a lone surrogate or undecodable byte '\\ud800'")
    assert [r.status_code for r in responses] == [200] * 6, [r.text for r in responses]


def test_a_batched_call_that_fails_is_answered_request_by_request(client, server):
    """A request the checks let through can still break the call it is batched in (here the model raises for
    one prompt, as a tokenizer might): the group is sampled again one request at a time, so only that request
    fails: 500 for the server's fault, 422 for a UsageError (the request's)."""
    from omg.errors import UsageError

    module = server.models["human"].generator
    real, calls = module.generate, []

    def generate(request):
        calls.append(list(request.prompts or []))
        for prompt in request.prompts or []:
            if "poison" in prompt:
                raise RuntimeError(f"the text encoder choked on {prompt!r}")
            if "refused" in prompt:
                raise UsageError(f"the text encoder refuses {prompt!r}")
        return real(request)

    prompts = ["a person walks", "a person runs", "a poison walks", "a person jumps", "a refused walk",
               "a person waves"]
    module.generate = generate
    try:
        with ThreadPoolExecutor(len(prompts)) as pool:
            responses = list(pool.map(lambda p: _post_json(client, dict(model="human", prompts=[p], length=1,
                                                                       steps=2)), prompts))
    finally:
        del module.generate
    assert any(len(c) > 2 and "a poison walks" in c for c in calls), calls  # they were batched together
    assert [responses[i].status_code for i in (0, 1, 3, 5)] == [200] * 4, [r.text for r in responses]
    assert _one_line(responses[2], 500) == "generation failed: the text encoder choked on 'a poison walks'"
    _one_line(responses[4], 422, "the text encoder refuses 'a refused walk'")
    assert _generate(client, model="human", prompts=["a person walks"], length=1, steps=2)["motions"]


# -- limits that hold for every body ------------------------------------------------------------

STRICT = dict(max_batch=8, max_wait=0.05, max_samples=4, max_upload_bytes=1_000_000, max_json_bytes=4096,
              read_timeout=1.5, parse_timeout=3.0)


def _server(serve_ckpts, out: Path, names: tuple[str, ...], **limits):
    from omg.tools.serve import load_models
    from omg.tools.serve.app import Limits, create_app

    models = load_models([serve_ckpts[n] for n in names], None, torch.device("cpu"))
    running = ThreadServer(create_app(models, out, Limits(**limits)), limits.get("read_timeout", 60.0))
    running.out, running.models = out, {m.name: m for m in models}
    return running


@pytest.fixture(scope="session")
def strict(serve_ckpts, tmp_path_factory):
    """A server with small limits: a 1 MB upload, a 4 KiB JSON body, 1.5 s to send it, 3 s to parse an upload."""
    running = _server(serve_ckpts, tmp_path_factory.mktemp("strict_results"), ("human", "habit"), **STRICT)
    yield running
    running.stop()


def _stream(sent: list[int], head: bytes, tail: bytes = b"", total: int = 64 << 20):
    """A body of ``total`` bytes in 1 MiB chunks (httpx sends a generator chunked, with no Content-Length);
    ``sent[0]``: how much of it the server took before it answered."""
    yield head
    while sent[0] < total:
        sent[0] += 1 << 20
        yield b" " * (1 << 20)
    yield tail


class _PeakTempFile:
    """The largest file open in this process (the server's thread) under the temporary folder, sampled every
    few milliseconds: where an upload being parsed is spooled."""

    def __enter__(self):
        self.peak, self._stop = 0, threading.Event()
        self._thread = threading.Thread(target=self._watch, daemon=True)
        self._thread.start()
        return self

    def _watch(self):
        import tempfile

        root = os.path.realpath(tempfile.gettempdir())
        while not self._stop.wait(0.002):
            for fd in os.listdir("/proc/self/fd"):
                try:
                    if os.readlink(f"/proc/self/fd/{fd}").startswith(root):
                        self.peak = max(self.peak, os.fstat(int(fd)).st_size)
                except OSError:
                    pass

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()


UPLOAD_HEAD = (b'--b\r\nContent-Disposition: form-data; name="to"\r\n\r\nhorse\r\n--b\r\nContent-Disposition: '
               b'form-data; name="file"; filename="big.bvh"\r\nContent-Type: text/plain\r\n\r\nHIERARCHY\n')


@pytest.mark.parametrize("route", ["/v1/generate", "/v1/transfer"])
def test_a_chunked_body_over_the_limit_is_refused_as_it_streams(strict, route):
    """A chunked body has no Content-Length to check: a 250 MiB JSON body was read and parsed in full, a 200 MiB
    upload written to disk before its refusal. It is counted as it arrives: 413 past the limit, the connection
    closed, and no more than the limit ever spooled."""
    sent = [0]
    if route == "/v1/generate":
        body, kind = _stream(sent, b'{"model": "human", "prompts": ["'), "application/json"
    else:
        body, kind = _stream(sent, UPLOAD_HEAD, b"\r\n--b--\r\n"), "multipart/form-data; boundary=b"
    with _PeakTempFile() as spooled:
        response = httpx.post(strict.url + route, content=body, headers={"content-type": kind}, timeout=60)
    _one_line(response, 413, "bytes allowed")
    assert spooled.peak <= STRICT["max_upload_bytes"] + 2**16, spooled.peak
    assert sent[0] < 24 << 20, sent  # of 64 MiB: the limit and the sockets' buffers
    assert httpx.get(strict.url + "/healthz").status_code == 200


def test_a_body_that_comes_too_slowly_is_408_and_closed(strict):
    """A client trickling its body (a byte every 0.1 s) held a connection and a request as long as it liked:
    the body must be in ``read_timeout`` seconds after the headers, else 408 and the connection is closed."""
    with socket.create_connection(("127.0.0.1", strict.port), timeout=10) as sock:
        sock.sendall(b"POST /v1/generate HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/json\r\n"
                     b"Content-Length: 1000\r\n\r\n")
        started, answer = time.monotonic(), b""
        sock.settimeout(0.1)
        while time.monotonic() - started < 10:
            try:
                sock.sendall(b" ")
                chunk = sock.recv(4096)
            except TimeoutError:
                continue
            except OSError:  # the server closed the connection as we wrote
                break
            if not chunk:
                break
            answer += chunk
        took = time.monotonic() - started
    head, _, body = answer.partition(b"\r\n\r\n")
    assert head.startswith(b"HTTP/1.1 408"), answer
    assert json.loads(body)["detail"] == "the request's body did not arrive within 1.5 s"
    assert 1.4 < took < 6, took


@pytest.mark.parametrize("answered_first", [False, True], ids=["first-request", "kept-alive"])
def test_headers_that_come_too_slowly_close_the_connection(strict, answered_first):
    """A client trickling its request's headers (a byte every 0.1 s) held its connection for good: uvicorn bounds
    neither the first request's headers nor, on a connection kept alive, the next one's."""
    with socket.create_connection(("127.0.0.1", strict.port), timeout=10) as sock:
        if answered_first:
            sock.sendall(b"GET /v1/models HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
            assert sock.recv(65536).startswith(b"HTTP/1.1 200")
        started, closed = time.monotonic(), False
        sock.settimeout(0.1)
        for byte in itertools.cycle(b"GET /v1/models HTTP/1.1\r\nX-Slow: " + b"a" * 1000):
            if time.monotonic() - started > 10:
                break
            try:
                sock.sendall(bytes([byte]))
                if sock.recv(4096) == b"":
                    closed = True
                    break
            except TimeoutError:
                continue
            except OSError:  # the server closed the connection as we wrote
                closed = True
                break
        took = time.monotonic() - started
    assert closed, "the connection was still open 10 s later"
    assert 1.4 < took < 6, took


def test_a_slow_upload_parse_holds_no_generation(strict, shared_motion):
    """Uploads were parsed on the one sampling thread (a 20 MiB BVH held another client's generation 110 s). They
    are parsed on their own bounded threads: a generation is answered while a parse runs, and a parse that takes
    longer than ``parse_timeout`` is answered 422 (its thread ends on its own)."""
    habit = strict.models["habit"].generator
    real, parsed = habit.read_source, threading.Event()

    def slow_read(path, joint_map=None):  # a parse of 4 s (the limit is 3 s): a large clip on a slow machine
        time.sleep(4)
        try:
            return real(path, joint_map)
        finally:
            parsed.set()

    habit.read_source = slow_read
    try:
        with ThreadPoolExecutor(1) as pool:
            upload = pool.submit(httpx.post, strict.url + "/v1/transfer", timeout=60, data={"model": "habit",
                                 "to": "horse"}, files={"file": ("dog.bvh", _bvh(shared_motion))})
            deadline = time.monotonic() + 10
            while httpx.get(strict.url + "/v1/status").json()["parsing"] == 0:
                assert time.monotonic() < deadline and not upload.done(), "the upload was not parsed"
                time.sleep(0.05)
            response = httpx.post(strict.url + "/v1/generate", timeout=60,
                                  json=dict(model="human", prompts=["a person walks"], length=1, steps=2))
            assert response.status_code == 200, response.text
            assert not parsed.is_set(), "the generation waited for the upload's parse"
            _one_line(upload.result(), 422, "the upload 'dog.bvh' took more than 3 s to read")
        assert parsed.wait(10)
    finally:
        del habit.read_source


# -- results: a lifetime and a size cap ----------------------------------------------------------


def test_results_expire_and_the_oldest_go_over_the_size_cap(client, serve_ckpts, tmp_path):
    """Results were never removed and had no cap. With ``max_results_bytes`` of 2.5 results, the third drops the
    first (410, its folder removed); after ``result_ttl`` a result expires (410, removed); an id never written
    is 404."""
    body = dict(model="human", prompts=["a person walks"], length=1, steps=2)
    probe = _generate(client, **body)
    size = sum(len(client.get(f).content) for f in probe["motions"][0]["files"].values())
    size += len(client.get(probe["settings"]).content)
    capped = _server(serve_ckpts, tmp_path / "capped", ("human",), max_results_bytes=int(2.5 * size))
    try:
        with httpx.Client(base_url=capped.url, timeout=60) as c:
            first, second, third = (_generate(c, **body) for _ in range(3))
            _one_line(c.get(first["settings"]), 410, f"result {first['id']} was dropped to keep all results under")
            assert not (capped.out / first["id"]).exists()
            for result in (second, third):
                assert c.get(result["motions"][0]["files"]["bvh"]).text.startswith("HIERARCHY")
            _one_line(c.get("/v1/results/0123456789ab/generation.json"), 404, "no such result file")
    finally:
        capped.stop()
    brief = _server(serve_ckpts, tmp_path / "brief", ("human",), result_ttl=2.0)
    try:
        with httpx.Client(base_url=brief.url, timeout=60) as c:
            result = _generate(c, **body)
            assert c.get(result["settings"]).status_code == 200 and (brief.out / result["id"]).is_dir()
            time.sleep(2.2)
            _one_line(c.get(result["settings"]), 410, f"result {result['id']} has expired: results are kept 2 s")
            assert not (brief.out / result["id"]).exists()
    finally:
        brief.stop()


# -- a local server only for local pages ---------------------------------------------------------


@pytest.mark.parametrize("host", ["evil.example", "evil.example:80", "127.0.0.1.nip.io", "localhost.evil.example",
                                  "[::2]:80", "::1"])
def test_a_host_name_not_of_this_server_is_refused(client, server, host):
    """DNS rebinding: a page of evil.example whose name now resolves to 127.0.0.1 reaches the server with its own
    name in the Host header; every route refuses it, results included."""
    result = _generate(client, model="human", prompts=["a person walks"], length=1, steps=2)
    for method, path in (("GET", "/v1/models"), ("GET", "/"), ("GET", result["settings"]),
                         ("POST", "/v1/generate")):
        response = client.request(method, path, headers={"host": host}, json=dict(model="human", prompts=["a"]))
        _one_line(response, 400, f"the Host {host!r} is not a name of this server")
    for name in (f"127.0.0.1:{server.port}", f"localhost:{server.port}", f"[::1]:{server.port}", "LocalHost"):
        assert client.get("/v1/models", headers={"host": name}).status_code == 200, name


def test_another_sites_page_cannot_post(client, server, shared_motion):
    """A plain HTML form on any site could post an upload to /v1/transfer (the browser sends it, Origin and all):
    a write whose Origin, or Referer, is not this server's own page is refused (403) before anything runs."""
    body = dict(model="human", prompts=["a person walks"], length=1, steps=2)
    before = sorted(server.out.iterdir())
    for headers in ({"origin": "http://evil.example"}, {"origin": "null"}, {"origin": f"http://localhost:{server.port}"},
                    {"origin": f"https://127.0.0.1:{server.port}.evil.example"},
                    {"referer": "http://evil.example/page.html"}):
        response = client.post("/v1/transfer", headers=headers, data={"model": "habit", "to": "horse"},
                               files={"file": ("clip.bvh", _bvh(shared_motion))})
        _one_line(response, 403, "is refused: only this server's own page may send one")
        _one_line(client.post("/v1/generate", json=body, headers=headers), 403)
    assert sorted(server.out.iterdir()) == before
    for headers in ({"origin": server.url}, {"referer": server.url + "/"}, {}):  # its own page, curl
        assert client.post("/v1/generate", json=body, headers=headers).status_code == 200, headers


def test_no_absolute_server_path_reaches_a_client(client, server, serve_ckpts, shared_motion):
    """The cards, the answers and the settings files name checkpoints by their file names: a page (or a
    rebinding one) learns nothing of the server's folders; a failure's message neither."""
    roots = {str(serve_ckpts["human"].parent), str(serve_ckpts["human"].parent.resolve()), str(server.out)}
    models = client.get("/v1/models")
    assert {m["ckpt"] for m in models.json()["models"]} == {"human.ckpt", "animal.ckpt", "habit.ckpt",
                                                             "pretrain.ckpt"}
    texts = [models.text]
    for result in (_generate(client, model="human", prompts=["a person walks"], length=1, steps=2),
                   _generate(client, model="animal", prompts=["a dog walks"], length=1, steps=2),
                   client.post("/v1/transfer", data={"model": "habit", "to": "horse"},
                               files={"file": ("clip.bvh", _bvh(shared_motion))}).json()):
        texts += [json.dumps(result), client.get(result["settings"]).text]
        assert client.get(result["settings"]).json()["ckpt"] in ("human.ckpt", "animal.ckpt", "habit.ckpt")
    module = server.models["human"].generator

    def broken(request):
        raise RuntimeError(f"cannot map {serve_ckpts['human']} into {server.out}/x")

    module.generate = broken
    try:
        failed = _post_json(client, dict(model="human", prompts=["a person walks"], steps=2))
    finally:
        del module.generate
    texts.append(_one_line(failed, 500, "cannot map human.ckpt into <results>/x"))
    assert not [(root, text[:200]) for text in texts for root in roots if root in text]


# -- the command ----------------------------------------------------------------------------


def test_omg_serve_binds_localhost_and_sigterm_finishes_the_request_in_flight(serve_ckpts, tmp_path):
    port = free_port()
    log = tmp_path / "serve.log"
    process = OmgProcess(["serve", "--ckpt", str(serve_ckpts["human"]), "--ckpt", str(serve_ckpts["habit"]),
                          "--port", str(port), "--device", "cpu"], env={"OMP_NUM_THREADS": "1"}, stdout=log,
                         stderr=log)
    try:
        url = f"http://127.0.0.1:{port}"
        deadline = time.monotonic() + 120  # a loaded machine takes a while to import torch and load
        while True:
            assert process.poll() is None, log.read_text()
            try:
                if httpx.get(f"{url}/healthz").status_code == 200:
                    break
            except httpx.TransportError:
                assert time.monotonic() < deadline, log.read_text()
                time.sleep(0.2)
        assert [m["name"] for m in httpx.get(f"{url}/v1/models").json()["models"]] == ["human", "habit"]
        with ThreadPoolExecutor(1) as pool:
            flight = pool.submit(httpx.post, f"{url}/v1/generate", timeout=120,
                                 json=dict(prompts=["a person walks"], length=2, steps=200))
            time.sleep(0.7)
            process.send_signal(signal.SIGTERM)
            response = flight.result()
        assert response.status_code == 200 and response.json()["motions"]
        assert process.wait(60) == -signal.SIGTERM  # uvicorn re-raises it once the requests are answered
    finally:
        if process.poll() is None:
            process.kill()
    text = log.read_text()
    assert "Traceback" not in text, text
    results = Path(re.search(r"\(results in (\S+)\)", text).group(1))
    assert results.name.startswith("omg-serve-") and not results.exists()  # the temporary results are removed
    assert f"on http://127.0.0.1:{port}/" in text


def test_bad_command_lines_are_one_line(serve_ckpts, capsys):
    from omg.cli import main

    with pytest.raises(SystemExit) as exit_:
        main(["serve", "--ckpt", str(serve_ckpts["habit"]), "--human_ckpt", str(serve_ckpts["human"])])
    assert exit_.value.code == 2
    assert "no --ckpt takes a second checkpoint" in capsys.readouterr().err


# -- the page in a real headless browser ----------------------------------------------------

CHROMIUM = Path("/usr/bin/chromium")
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--no-first-run", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync"]


@pytest.fixture(scope="session")
def browser():
    if not CHROMIUM.exists():
        pytest.skip("the page's test needs Debian's chromium (apt-get install -y chromium)")
    sync_api = pytest.importorskip("playwright.sync_api", reason="the page's test needs playwright (pip install "
                                                                 "playwright; its own browsers are not used)")
    with sync_api.sync_playwright() as p:
        browser = p.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
        yield browser
        browser.close()


def _canvas_colours(page) -> int:
    """Distinct colours on the viewer's canvas (a blank one has one)."""
    from PIL import Image

    image = Image.open(io.BytesIO(page.locator("#viewer canvas").screenshot())).convert("RGB")
    return len(set(image.resize((160, 120)).getdata()))


def _open_page(browser, server, width: int = 1280):
    """The page in a new browser context (``width`` x 800, downloads kept), its models listed: (the context, the
    page, the script errors it raises, the URLs it requests), the lists filling as it runs."""
    context = browser.new_context(accept_downloads=True, viewport={"width": width, "height": 800})
    page = context.new_page()
    requests, errors = [], []
    page.on("request", lambda r: requests.append(r.url))
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.goto(server.url + "/")
    page.wait_for_function("document.querySelectorAll('#model option').length == 4")
    return context, page, errors, requests


def _drawing(page, seconds: float = 2.0) -> tuple[float, float]:
    """(draws, changes of the frame shown) a second, over ``seconds`` with nothing done."""
    probe = "[window.omgViewer.draws, window.omgViewer.shownFrames, performance.now()]"
    start = page.evaluate(probe)
    page.wait_for_timeout(seconds * 1000)
    end = page.evaluate(probe)
    elapsed = (end[2] - start[2]) / 1000
    return (end[0] - start[0]) / elapsed, (end[1] - start[1]) / elapsed


def test_the_page_generates_plays_and_downloads(server, browser, shared_motion, tmp_path):
    context, page, errors, requests = _open_page(browser, server, width=1200)
    # nothing shown and nothing done: the scene is drawn a few times a second (IDLE_DRAW_MS), not on every
    # animation frame (a software renderer's core, a laptop's battery); below, a result plays at the full rate
    page.wait_for_timeout(1200)  # the loading's own second of full-rate drawing
    assert _drawing(page)[0] <= 6
    # chromium here draws WebGL in software (--disable-gpu): no multisampling, which would shade each pixel 4 times
    assert page.evaluate("window.omgViewer.antialias") is False
    page.select_option("#model", "human")
    assert page.locator("#upload-box").is_hidden() and page.locator("#text-box").is_visible()
    # an empty box asks for nothing: the page says so instead of sampling unconditional motion
    page.fill("#prompts", " \n ")
    page.click("#generate")
    page.wait_for_function("document.querySelector('#status').classList.contains('error')")
    assert page.locator("#status").inner_text() == "write a prompt (one per line), or tick unconditional"
    assert not [u for u in requests if u.endswith("/v1/generate")]
    page.fill("#prompts", "a person walks forward\na person waves")
    page.fill("#length", "1.5")
    page.fill("#steps", "200")  # a few seconds of sampling: many 250-ms polls of the status land on a step
    page.evaluate("""() => { const status = document.querySelector('#status'); window.shown = [];
        new MutationObserver(() => window.shown.push(status.textContent))
            .observe(status, {childList: true, characterData: true, subtree: true}); }""")
    page.click("#generate")
    page.wait_for_function("window.omgViewer.results == 1 && window.omgViewer.drawn > 5", timeout=120_000)
    # the progress: the sampler's step and the time left by the server's clock (not the seconds elapsed)
    shown = page.evaluate("window.shown")
    assert any(re.fullmatch(r"sampling… step ([1-9]\d*) of 200, about \d+ s left", text) for text in shown), shown
    assert page.locator(".sample").count() == 2
    page.wait_for_timeout(400)  # a progress poll in flight does not overwrite the answer
    assert page.locator("#status").inner_text().startswith("2 motion(s) in ")
    assert "a person waves" in page.locator("#samples").inner_text()
    assert _canvas_colours(page) > 3  # the grid and two coloured skeletons
    first = page.evaluate("window.omgViewer.frame")
    page.wait_for_function(f"window.omgViewer.frame != {first}")
    # playing skeletons are drawn when their frame changes (20 a second), not on every animation frame (60)
    draws, shown = _drawing(page)
    assert shown > 3 and draws <= shown + 0.5, (draws, shown)  # at most one draw more in two seconds
    page.click("#play")  # pause, then scrub
    page.locator("#scrubber").fill("10")
    page.wait_for_function("window.omgViewer.frame == 10")
    # the label is drawn with the frame (the next animation frame, later on a loaded machine); paused, it stays
    page.wait_for_function("document.getElementById('frame').textContent.startsWith('11 / 30')", timeout=10_000)
    page.wait_for_timeout(300)
    assert page.locator("#frame").inner_text().startswith("11 / 30")
    with page.expect_download() as download:
        page.locator(".sample a", has_text="BVH").first.click()
    path = tmp_path / "dl.bvh"
    download.value.save_as(path)
    assert path.read_text().startswith("HIERARCHY")
    for link in page.locator(".sample a").all()[1:4]:  # .joints.npy, .features.npy, settings JSON
        assert httpx.get(server.url + link.get_attribute("href")).status_code == 200
    # a bad request is one line on the page, and the page goes on
    page.fill("#length", "500")
    page.click("#generate")
    page.wait_for_function("document.querySelector('#status').classList.contains('error')")
    assert "length 500 s" in page.locator("#status").inner_text()
    # unconditional motion is asked for by its switch, which leaves the prompts out
    page.fill("#length", "1.5")
    page.check("#unconditional")
    assert page.locator("#prompts").is_disabled()
    page.click("#generate")
    page.wait_for_function("window.omgViewer.results == 2", timeout=60_000)
    assert page.locator(".sample").count() == 1 and "a person waves" not in page.locator("#samples").inner_text()
    # habit transfer: the upload and the species
    page.select_option("#model", "habit")
    assert page.locator("#upload-box").is_visible() and page.locator("#text-box").is_hidden()
    page.set_input_files("#upload", files=[{"name": "dog.bvh", "mimeType": "text/plain",
                                           "buffer": _bvh(shared_motion)}])
    page.fill("#species", "horse")
    page.click("#generate")
    page.wait_for_function("window.omgViewer.results == 3 && window.omgViewer.drawn > 2", timeout=60_000)
    assert "horse" in page.locator("#samples").inner_text()
    context.close()
    assert not errors, errors
    assert requests and all(u.startswith(server.url + "/") for u in requests), [u for u in requests
                                                                                if not u.startswith(server.url)]


def _glb_document(data: bytes) -> dict:
    import pygltflib

    return json.loads(pygltflib.GLTF2.load_from_bytes(data).to_json())


def _onto(client, result: str, name: str, content: bytes, **fields):
    return client.post(f"/v1/results/{result}/character", data=fields, files={"file": (name, content)})


def test_a_result_goes_onto_an_uploaded_character_or_rig(client, server, tmp_path):
    """``POST /v1/results/{id}/character``: each motion of the result on the uploaded character (the character
    whole, one animation added) or BVH rig (its hierarchy), downloadable as the result's files are."""
    from helpers import BANDAI_RIG, rig_bvh
    from helpers.characters import write_character

    result = _generate(client, model="human", prompts=["a person waves", "a person jumps"], length=1, steps=2)
    character = write_character(tmp_path / "my figure.glb")
    size = server.app.state.results.kept[result["id"]][1]
    answer = client.post(f"/v1/results/{result['id']}/character", files={"file": ("my figure.glb",
                                                                                    character.read_bytes())})
    assert answer.status_code == 200, answer.text
    body = answer.json()
    assert body["character"] == "my figure.glb" and [m["file"] for m in body["motions"]] == ["sample_000",
                                                                                              "sample_001"]
    kept = _glb_document(character.read_bytes())
    for motion in body["motions"]:
        assert re.fullmatch(rf"/v1/results/{result['id']}/{motion['file']}\.my_figure-[0-9a-f]{{6}}\.glb",
                            motion["url"]), motion
        animated = _glb_document(client.get(motion["url"]).content)
        assert animated["meshes"] == kept["meshes"] and animated["skins"] == kept["skins"]
        assert len(animated["animations"]) == 1 and animated["animations"][0]["name"] == motion["file"]
    one, two = (client.get(m["url"]).content for m in body["motions"])
    assert one != two  # each motion its own animation
    assert server.app.state.results.kept[result["id"]][1] == size + len(one) + len(two)  # counted in the cap
    rig = client.post(f"/v1/results/{result['id']}/character",
                      files={"file": ("bandai.bvh", rig_bvh(BANDAI_RIG).encode())})
    assert rig.status_code == 200, rig.text
    text = client.get(rig.json()["motions"][0]["url"]).text
    assert text.startswith("HIERARCHY") and "UpperArm_L" in text and "Frames: 20" in text


@pytest.mark.parametrize("name, content, fields, status, message", [
    ("figure.obj", b"o cube", {}, 422, "the upload 'figure.obj' is not a character or rig; give one of .bvh, .glb"),
    ("figure.glb", b"glTF garbled", {}, 422, "figure.glb: not a readable glTF 2.0 file"),
    ("figure.glb", b"not glTF at all", {}, 422, "figure.glb: not a readable glTF 2.0 file"),
    ("rig.bvh", b"HIERARCHY\nROOT garbage {", {}, 422, "rig.bvh"),
    ("figure.glb", None, {"joint_map": "../../etc"}, 422, "joint_map '../../etc': give a registered joint map's"),
    ("figure.glb", None, {"joint_map": "bandai"}, 422, "figure.glb: joint map 'bandai' needs joints the file lacks"),
    ("figure.glb", None, {"character": "x"}, 422, "character: Extra inputs are not permitted (the form's fields: "
                                                 "file, joint_map, joint_map_file)"),
    ("figure.glb", b"x" * 2_010_000, {}, 413, "bytes allowed (--max_upload_mb)"),
    ("figure.glb", None, {"result": "000000000000"}, 404, "no result '000000000000' on this server"),
    ("figure.glb", None, {"result": "animal"}, 422, "human rig"),
], ids=["not-a-rig", "garbled-glb", "no-magic", "garbled-bvh", "joint-map-path", "wrong-joint-map", "misspelt-field",
        "too-large", "unknown-result", "animal-result"])
def test_bad_character_uploads_are_one_readable_line(client, server, tmp_path, name, content, fields, status,
                                                     message):
    from helpers.characters import write_character

    if content is None:
        content = write_character(tmp_path / "figure.glb").read_bytes()
    result = fields.pop("result", None)
    if result in (None, "animal"):
        result = (_generate(client, model="human", prompts=["a person waves"], length=1, steps=2) if result is None
                  else _generate(client, model="animal", prompts=["a dog walks"], species="dog"))["id"]
    files = sorted(os.listdir(server.out / result)) if (server.out / result).is_dir() else None
    detail = _one_line(_onto(client, result, name, content, **fields), status, message)
    assert "omg-upload-" not in detail and "--to_rig" not in detail and str(tmp_path) not in detail
    assert (sorted(os.listdir(server.out / result)) if files is not None else None) == files  # nothing left
    assert client.get("/healthz").status_code == 200


OUTSIDE = REPO / "tests/data/characters"  # Khronos' Rigged Figure, whose names no registered map fits, and its map


def test_an_outside_character_goes_onto_a_result_with_its_uploaded_joint_map(client, server):
    """A character whose names no registered map fits, uploaded with its YAML joint map (``joint_map_file``):
    the motions go onto it (the sample with its own animation and the one added); without the map, or with one
    left TODO, or with a registered map's name too, one readable line."""
    figure = (OUTSIDE / "RiggedFigure.gltf").read_bytes()
    joint_map = (OUTSIDE / "RiggedFigure.joints.yaml").read_bytes()
    result = _generate(client, model="human", prompts=["a person waves"], length=1, steps=2)
    url = f"/v1/results/{result['id']}/character"
    _one_line(_onto(client, result["id"], "RiggedFigure.gltf", figure), 422,
              "RiggedFigure.gltf: cannot map the rig onto smpl22 (no registered map fits)")
    answer = client.post(url, files=[("file", ("RiggedFigure.gltf", figure)),
                                     ("joint_map_file", ("figure.yaml", joint_map))])
    assert answer.status_code == 200, answer.text
    motion = answer.json()["motions"][0]
    assert motion["url"] == motion["view"] and motion["url"].endswith(".glb")
    animated = _glb_document(client.get(motion["url"]).content)
    assert len(animated["animations"]) == 2 and animated["animations"][-1]["name"] == "sample_000"
    left = joint_map.replace(b"left_hip:       leg_joint_L_1", b"left_hip:       TODO")
    line = _one_line(client.post(url, files=[("file", ("RiggedFigure.gltf", figure)),
                                             ("joint_map_file", ("figure.yaml", left))]), 422, "left_hip is TODO")
    assert line.startswith("joint map figure.yaml: ") and "omg-upload-" not in line
    _one_line(client.post(url, data={"joint_map": "mixamo"}, files=[("file", ("RiggedFigure.gltf", figure)),
                                                                    ("joint_map_file", ("figure.yaml", joint_map))]),
              422, "not both")


def test_the_page_plays_the_motions_on_an_outside_character_with_its_joint_map(server, browser, tmp_path):
    """Khronos' Rigged Figure chosen on the page with its joint map (the two files at once): the motion goes onto
    it and its mesh moves in the view between two screenshots (their paths printed), played from the animation
    omg added, not the sample's own (its first); the download is the character as .glb."""
    context, page, errors, _ = _open_page(browser, server)
    page.select_option("#model", "human")
    _generate_on_character(page, [OUTSIDE / "RiggedFigure.gltf", OUTSIDE / "RiggedFigure.joints.yaml"],
                           ["a person walks forward"])
    assert "on RiggedFigure.gltf in" in page.locator("#status").inner_text()
    shots = _paused_frames(page, tmp_path / "outside_character", "Khronos' Rigged Figure", settle=500)
    # the camera fixed, what changed between the frames is the character: its mesh moved, and its root with the
    # motion (the sample's own animation keeps its root in place)
    changed = np.abs(shots[2]["pixels"] - shots[20]["pixels"]).max(-1) > 40
    assert changed.sum() > 200, changed.sum()  # a still view changes none (the tiny model's walk: 800 and more)
    assert np.abs(np.subtract(shots[20]["center"], shots[2]["center"])).max() > 0.01
    with page.expect_download() as download:
        page.locator(".sample a.character").first.click()
    assert download.value.suggested_filename.endswith(".glb")
    assert len(_glb_document(httpx.get(download.value.url).content)["animations"]) == 2
    context.close()
    assert not errors, errors


def _generate_on_character(page, files: list[Path], prompts: list[str], timeout: int = 120_000) -> None:
    """``prompts`` (1.5 s, 3 steps) generated onto the character chosen on the page (its file, and its joint map
    where it needs one); returns once each motion plays on it."""
    page.set_input_files("#character", [str(f) for f in files])
    page.fill("#prompts", "\n".join(prompts))
    page.fill("#length", "1.5")
    page.fill("#steps", "3")
    page.click("#generate")
    page.wait_for_function(f"window.omgViewer.results == 1 && window.omgViewer.characters == {len(prompts)}",
                           timeout=timeout)


def _paused_frames(page, stem: Path, what: str, settle: int = 200) -> dict[int, dict]:
    """The view paused with its camera fixed, at frames 2 and 20: each frame's canvas pixels, the camera's target
    and the motions' centre; a screenshot of each saved as ``STEM_frame_NN.png`` and its path printed."""
    page.click("#play")
    page.uncheck("#follow")
    shots = {}
    for frame in (2, 20):
        page.locator("#scrubber").fill(str(frame))
        page.wait_for_function(f"window.omgViewer.frame == {frame} && window.omgViewer.drawn > 0")
        page.wait_for_timeout(settle)  # a loaded machine draws late
        shots[frame] = {"pixels": _canvas_pixels(page), "target": page.evaluate("window.omgViewer.target"),
                        "center": page.evaluate("window.omgViewer.center")}
        path = stem.with_name(f"{stem.name}_frame_{frame:02d}.png")
        page.screenshot(path=path)
        print(f"screenshot of {what} at frame {frame}: {path}")
    return shots


def _canvas_pixels(page) -> np.ndarray:
    """(H, W, 3) the viewer's WebGL canvas alone (no label over it), as drawn last."""
    import base64

    from PIL import Image

    data = page.evaluate("document.querySelector('#viewer canvas').toDataURL('image/png')")
    return np.asarray(Image.open(io.BytesIO(base64.b64decode(data.split(",")[1]))).convert("RGB")).astype(int)


def _coloured(pixels: np.ndarray) -> np.ndarray:
    """(H, W) the pixels with a colour: not the white ground or the grey grid (the character's mesh here)."""
    return pixels.max(-1) - pixels.min(-1) > 30


def test_the_page_plays_the_motions_on_an_uploaded_character(server, browser, tmp_path):
    """The page at 1280x800: a character uploaded on the page gets the result's motions (the server's
    /v1/results/{id}/character), and its mesh moves in the view from the file's own animation; each motion is
    labelled with its prompt, the camera follows (or not), the results and downloads are in the viewport, and
    the download is the character with one animation. Two screenshots at different frames are saved (and their
    paths printed): the mesh moving."""
    import pygltflib

    from helpers.characters import write_character

    character = write_character(tmp_path / "figure.glb")
    context, page, errors, _ = _open_page(browser, server)
    page.select_option("#model", "human")
    # the kinds this server reads (.fbx too where Blender's module is there)
    from omg.tools.serve.app import character_suffixes

    assert page.get_attribute("#character", "accept") == ",".join([*character_suffixes(), ".yaml", ".yml"])
    _generate_on_character(page, [character], ["a person walks forward", "a person waves"])
    assert re.fullmatch(r"2 motion\(s\) in [\d.]+ s; on figure\.glb in [\d.]+ s", page.locator("#status").inner_text())
    # each motion labelled with its prompt, in the view, above its figure
    assert page.locator("#viewer .label").all_inner_texts() == ["a person walks forward", "a person waves"]
    view = page.locator("#viewer").bounding_box()
    for tag in page.locator("#viewer .label").all():
        box = tag.bounding_box()
        assert view["x"] <= box["x"] and box["x"] + box["width"] <= view["x"] + view["width"]
        assert view["y"] <= box["y"] < view["y"] + view["height"] / 2
    # the results, their downloads and the status without scrolling at 1280x800
    for element in [*page.locator(".sample").all(), *page.locator(".sample a").all(), page.locator("#status"),
                    page.locator("#controls")]:
        box = element.bounding_box()
        assert box and 0 <= box["x"] and box["x"] + box["width"] <= 1280 and 0 <= box["y"], box
        assert box["y"] + box["height"] <= 800, box
    assert page.evaluate("document.scrollingElement.scrollHeight") <= 800
    # the camera fixed: the mesh moves between two frames of its animation, nothing else does
    shots = _paused_frames(page, tmp_path / "character", "the character")
    assert page.evaluate("window.omgViewer.follow") is False
    before, after = shots[2], shots[20]
    mesh_before, mesh_after = _coloured(before["pixels"]), _coloured(after["pixels"])
    assert mesh_before.sum() > 2000 and mesh_after.sum() > 2000  # the mesh is drawn (the grid is grey)
    assert (mesh_before ^ mesh_after).sum() > 0.3 * mesh_before.sum()  # and has moved
    assert np.allclose(before["target"], after["target"], rtol=0, atol=1e-9)  # the camera stayed (to float noise)
    assert np.abs(np.subtract(after["center"], before["center"])).max() > 0.01  # while the motions moved
    # following: the camera's target keeps its place relative to the motions
    page.check("#follow")
    page.locator("#scrubber").fill("5")
    page.wait_for_function("window.omgViewer.frame == 5")
    page.wait_for_timeout(200)
    gap = np.subtract(page.evaluate("window.omgViewer.target"), page.evaluate("window.omgViewer.center"))
    page.locator("#scrubber").fill("25")
    page.wait_for_function("window.omgViewer.frame == 25")
    page.wait_for_timeout(200)
    moved = np.subtract(page.evaluate("window.omgViewer.target"), page.evaluate("window.omgViewer.center"))
    assert np.allclose(gap, moved, atol=1e-6) and page.evaluate("window.omgViewer.target") != after["target"]
    # the download: the character whole, with one animation
    with page.expect_download() as download:
        page.locator(".sample a.character").first.click()
    assert download.value.suggested_filename.endswith(".glb")
    animated = _glb_document(httpx.get(download.value.url).content)
    kept = json.loads(pygltflib.GLTF2().load(str(character)).to_json())
    assert animated["meshes"] == kept["meshes"] and len(animated["animations"]) == 1
    # a bad character is one line on the page; none: the skeletons again
    page.set_input_files("#character", files=[{"name": "broken.glb", "mimeType": "model/gltf-binary",
                                               "buffer": b"glTF garbled"}])
    page.wait_for_function("document.querySelector('#status').classList.contains('error')")
    assert "broken.glb: not a readable glTF 2.0 file" in page.locator("#status").inner_text()
    page.set_input_files("#character", files=[])
    page.wait_for_function("window.omgViewer.characters == 0")
    assert page.locator(".sample a.character").count() == 0
    context.close()
    assert not errors, errors


@pytest.fixture(scope="session")
def fbx_figure(tmp_path_factory) -> Path:
    """The tests' box figure (``helpers.characters``) as an FBX character, made by Blender (one start for the
    session); skips without Blender's Python module."""
    from helpers.blender_scenes import blender
    from omg.io.fbx import available

    if not available():
        pytest.skip("Blender's Python module (bpy) is not installed: pip install 'omg[fbx]', or point "
                    "OMG_BLENDER_PYTHON at a Python that has it (.ci/run installs one)")
    root = tmp_path_factory.mktemp("fbx_figure")
    blender("build", [{"path": str(root / "figure.fbx")}], root)
    return root / "figure.fbx"


def test_the_page_plays_the_motions_on_an_uploaded_fbx_character(server, browser, fbx_figure, tmp_path):
    """An FBX character chosen on the page: the server writes each motion onto it as .fbx (the download) and,
    from the same Blender run, as .glb (Blender's glTF exporter), which the view plays: the mesh moves between
    two screenshots at different frames (their paths printed); the download is the FBX."""
    from omg.io.fbx import BINARY_MAGIC

    context, page, errors, _ = _open_page(browser, server)
    page.select_option("#model", "human")
    assert ".fbx" in page.get_attribute("#character", "accept").split(",")
    _generate_on_character(page, [fbx_figure], ["a person walks forward"], timeout=240_000)
    assert re.fullmatch(r"1 motion\(s\) in [\d.]+ s; on figure\.fbx in [\d.]+ s", page.locator("#status").inner_text())
    shots = _paused_frames(page, tmp_path / "fbx_character", "the FBX character")
    # the camera fixed, what changed between the frames is the character: its mesh (Blender's grey material) moved
    changed = np.abs(shots[2]["pixels"] - shots[20]["pixels"]).max(-1) > 40
    assert changed.sum() > 1000, changed.sum()
    with page.expect_download() as download:
        page.locator(".sample a.character").first.click()
    assert download.value.suggested_filename.endswith(".fbx")
    assert httpx.get(download.value.url).content.startswith(BINARY_MAGIC)
    context.close()
    assert not errors, errors


def test_the_page_draws_a_path_drops_a_keyframe_and_edits_a_timeline(server, browser, shared_motion):
    """The Control panel: a path clicked on the ground grid, a keyframe from a frame of an uploaded BVH (retargeted
    by the server, /v1/keyframes), a timeline of two rows with a transition and a context typed (sent in the
    timeline's mapping and recorded as sampled); the request holds them in the documented format, the result
    shows each motion's control error and the constraints beside it; a bad timeline or a negative transition is
    the API's one line on the page; a model whose card takes none shows the panel disabled with why. The number
    fields' bounds and defaults are the server's constants, read from ``GET /v1/models`` when a model is chosen."""
    from omg.generation.control import read_constraints
    from omg.generation.timeline import DEFAULT_TRANSITION, parse_timeline
    from omg.lit.sampling import MAX_SMOOTHING
    from omg.lit.timeline import DEFAULT_COUPLING

    page = browser.new_page(viewport={"width": 1200, "height": 900})
    errors, sent = [], []
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
    page.on("request", lambda r: sent.append(r.post_data_json) if r.url.endswith("/v1/generate") else None)
    answers = []
    page.on("response", lambda r: answers.append(r) if r.url.endswith("/v1/generate") else None)
    page.goto(server.url + "/")
    page.wait_for_function("document.querySelectorAll('#model option').length == 4")
    page.select_option("#model", "animal")
    timeline_fields = ("#timeline-add", "#timeline-transition", "#timeline-context")
    assert all(page.locator(b).is_disabled() for b in ("#path-draw", "#keyframe-file", "#hold-feet",
                                                       *timeline_fields))
    assert "animal (omgpt) takes no constraints and no timeline" in page.locator("#control-why").inner_text()
    page.select_option("#model", "human")
    assert all(page.locator(b).is_enabled() for b in ("#path-draw", "#keyframe-file", "#hold-feet",
                                                      *timeline_fields))
    assert page.is_checked("#hold-feet")  # a path moves the root at its own pace: the feet held by default
    assert page.get_attribute("#timeline-transition", "placeholder") == f"{DEFAULT_TRANSITION:g} (default)"
    assert float(page.get_attribute("#smoothing", "max")) == MAX_SMOOTHING
    assert float(page.get_attribute("#parts-coupling", "placeholder")) == DEFAULT_COUPLING
    card = server.models["human"].card
    assert int(page.get_attribute("#steps", "max")) == card.max_steps
    assert float(page.get_attribute("#length", "min")) == card.min_frames / card.fps
    # the path: three clicks on the ground in front of the origin, a drag between them adds none
    page.click("#path-draw")
    box = page.locator("#viewer canvas").bounding_box()
    for fx, fy in ((0.5, 0.75), (0.6, 0.8), (0.7, 0.9)):
        page.mouse.click(box["x"] + fx * box["width"], box["y"] + fy * box["height"])
    page.mouse.move(box["x"] + 100, box["y"] + 600)
    page.mouse.down()
    page.mouse.move(box["x"] + 160, box["y"] + 640, steps=4)
    page.mouse.up()
    path = page.evaluate("window.omgControl.state.path")
    assert len(path) == 3 and all(len(p) == 2 and 0 < p[1] < 6 for p in path), path  # +Z: towards the camera
    assert path[1][0] > path[0][0] and path[2][0] > path[1][0]  # clicks to the right: +X on screen
    page.click("#path-undo")
    page.click("#path-draw")
    page.mouse.click(box["x"] + 0.7 * box["width"], box["y"] + 0.9 * box["height"])  # drawing is off
    assert len(page.evaluate("window.omgControl.state.path")) == 2
    page.click("#path-draw")
    page.mouse.click(box["x"] + 0.7 * box["width"], box["y"] + 0.9 * box["height"])
    path = page.evaluate("window.omgControl.state.path")
    assert len(path) == 3 and page.evaluate("window.omgControl.markers().editing")["path"] == 1
    # the keyframe: a frame of a real take, retargeted by the server
    take = (shared_motion / HUMAN_TAKE).read_bytes()
    page.set_input_files("#keyframe-file", files=[{"name": "bow.bvh", "mimeType": "text/plain", "buffer": take}])
    page.wait_for_function("window.omgControl.state.take !== null")
    assert "bow.bvh: " in page.locator("#keyframe-info").inner_text()
    page.fill("#keyframe-frame", "30")
    page.fill("#keyframe-time", "1.5")
    page.click("#keyframe-add")
    assert "at 1.5 s: bow.bvh frame 30" in page.locator("#keyframe-list").inner_text()
    # the timeline: two rows; the prompts box is not sent
    page.fill("#prompts", "a person dances")
    for start, end, text in ((0, 1, "a person walks forward"), (1, 2, "a person bows")):
        page.click("#timeline-add")
        row = page.locator("#timeline-rows .segment").last
        row.locator(".segment-start").fill(str(start))
        row.locator(".segment-end").fill(str(end))
        row.locator(".segment-text").fill(text)
    page.fill("#timeline-transition", "0.25")  # not the default: the recorded value is the page's
    page.fill("#timeline-context", "0.5")
    page.fill("#steps", "2")
    page.fill("#num_samples", "2")
    page.click("#generate")
    page.wait_for_function("window.omgViewer.results == 1", timeout=60_000)
    body = sent[-1]
    assert body["prompts"] == [] and "length" not in body
    assert body["timeline"] == {"timeline": [{"start": 0, "end": 1, "text": "a person walks forward"},
                                             {"start": 1, "end": 2, "text": "a person bows"}],
                                "transition": 0.25, "context": 0.5}
    recorded = httpx.get(server.url + answers[-1].json()["settings"]).json()["timeline"]
    assert recorded["transition"] == 0.25 and recorded["context"] == 0.5
    assert set(body["constraints"]) == {"path", "keyframes", "contacts"}
    assert body["constraints"]["contacts"] == list(card.contacts) == ["model", "ground"]
    assert body["constraints"]["path"] == {"points": [[0, 0], *path]}
    expected = httpx.post(server.url + "/v1/keyframes", data={"model": "human"},
                          files={"file": ("bow.bvh", take)}).json()["poses"][30]
    assert body["constraints"]["keyframes"] == [{"time": 1.5, "positions": expected}]
    parse_timeline(body["timeline"])  # the documented formats, as the CLI reads them
    read_constraints(body["constraints"], card, 40)
    # each motion's control error, and the constraints drawn beside each of the two motions
    records = page.evaluate("window.omgViewer.motions.map((m) => m.record)")
    for entry, record in zip(page.locator(".sample").all(), records, strict=True):
        text = entry.locator(".control-error").inner_text()
        shown = re.fullmatch(r"control error: keyframes\[0\] (\d+\.\d) cm( \(not met\))?, path (\d+\.\d) cm"
                             r"( \(not met\))?", text)
        assert shown, text
        errors_m = record["control_error_m"]
        assert abs(float(shown[1]) - 100 * errors_m["keyframes[0]"]) <= 0.051
        assert abs(float(shown[3]) - 100 * errors_m["path"]) <= 0.051
        assert bool(shown[2]) == ("keyframes[0]" in record["control_unmet"])
    markers = page.evaluate("window.omgControl.markers().result")
    assert markers == {"path": 2, "waypoint": 6, "keyframe": 44, "keyframe-bones": 2}, markers
    assert not errors, errors
    # waypoints instead of a dense path, and a bad timeline is one line on the page; emptied, the transition and
    # context fields leave the file's defaults: the bare list of segments is sent
    page.fill("#timeline-transition", "")
    page.fill("#timeline-context", "")
    page.select_option("#path-kind", "waypoints")
    page.locator("#timeline-rows .segment").last.locator(".segment-start").fill("1.5")
    page.locator("#timeline-rows .segment").first.locator(".segment-end").fill("1.2")
    page.click("#generate")
    page.wait_for_function("document.querySelector('#status').classList.contains('error')")
    assert "a gap between timeline[0] (ends at 1.2 s) and timeline[1] (starts at 1.5 s)" in \
        page.locator("#status").inner_text()
    assert sent[-1]["constraints"]["waypoints"] == [{"position": p} for p in path]
    assert sent[-1]["constraints"]["contacts"] == ["model", "ground"]
    assert sent[-1]["timeline"] == [{"start": 0, "end": 1.2, "text": "a person walks forward"},
                                    {"start": 1.5, "end": 2, "text": "a person bows"}]
    page.fill("#timeline-transition", "-1")  # the API reads transition before the segments: its line, not the gap's
    page.uncheck("#hold-feet")
    page.click("#generate")
    page.wait_for_function("document.querySelector('#status').textContent.includes('transition')")
    assert "contacts" not in sent[-1]["constraints"]  # the feet left free
    assert page.locator("#status").inner_text() == \
        "timeline: transition must be a finite number of seconds >= 0, got -1"
    assert "error" in page.get_attribute("#status", "class")
    page.close()
    assert errors == ["Failed to load resource: the server responded with a status of 422 (Unprocessable Entity)"] * 2


def test_the_page_composes_body_parts_in_separate_chains(server, browser, tmp_path):
    """The Control panel's body-part composition: rows of part names and texts, sent as the timeline's ``parts``
    with the joint blend; its *separate chains* switch sends ``chains: "separate"`` with the coupling given, the
    motion comes back sampled so (its recorded settings) and a screenshot of it is saved (its path printed); a
    coupling out of range is the API's one line on the page. A model whose card takes no parts disables it. The
    smoothing field (sampling's ``smoothing``) shows where the card lists it and is sent, and recorded, when given."""
    from omg.generation.timeline import parse_timeline

    context, page, errors, _ = _open_page(browser, server)
    sent, answers = [], []
    page.on("request", lambda r: sent.append(r.post_data_json) if r.url.endswith("/v1/generate") else None)
    page.on("response", lambda r: answers.append(r) if r.url.endswith("/v1/generate") else None)
    page.select_option("#model", "animal")
    assert page.locator("#parts-add").is_disabled() and page.locator("#parts-separate").is_disabled()
    assert not page.locator("#smoothing").is_visible()  # an OmniMotionGPT card: no smoothing option
    page.select_option("#model", "human")
    assert page.locator("#smoothing").is_visible()
    assert page.locator("#parts-add").is_enabled() and page.locator("#parts-coupling").is_disabled()
    assert "parts (smpl22): root, torso, left_arm" in page.locator("#parts-names").inner_text()
    for names, text, start in (("legs, root", "a person walks forward", ""), ("arms", "a person waves", "0.5")):
        page.click("#parts-add")
        row = page.locator("#parts-rows .part").last
        row.locator(".part-parts").fill(names)
        row.locator(".part-text").fill(text)
        row.locator(".part-start").fill(start)
    parts = [{"parts": ["legs", "root"], "text": "a person walks forward"},
             {"parts": ["arms"], "text": "a person waves", "start": 0.5}]
    page.fill("#length", "1.5")
    page.fill("#steps", "2")
    page.click("#generate")  # the joint blend: parts alone, no chains
    page.wait_for_function("window.omgViewer.results == 1", timeout=60_000)
    assert sent[-1]["timeline"] == {"parts": parts} and sent[-1]["prompts"] == [] and sent[-1]["length"] == 1.5
    page.check("#parts-separate")
    page.fill("#parts-coupling", "0.25")
    page.click("#generate")
    page.wait_for_function("window.omgViewer.results == 2", timeout=60_000)
    assert sent[-1]["timeline"] == {"parts": parts, "chains": "separate", "coupling": 0.25}
    assert parse_timeline(sent[-1]["timeline"]).chains == "separate"  # the documented format, as the CLI reads it
    result = answers[-1].json()
    assert [m["frames"] for m in result["motions"]] == [30]
    recorded = httpx.get(server.url + result["settings"]).json()["timeline"]
    assert recorded["chains"] == "separate" and recorded["coupling"] == 0.25 and recorded["parts"][1]["start"] == 0.5
    assert page.evaluate("window.omgViewer.motions.length") == 1 and _canvas_colours(page) > 1
    shot = tmp_path / "separate_chains.png"
    page.screenshot(path=shot)
    print(f"screenshot of the page after separate chains: {shot}")
    assert not errors, errors
    page.fill("#parts-coupling", "2")
    page.click("#generate")
    page.wait_for_function("document.querySelector('#status').classList.contains('error')")
    assert page.locator("#status").inner_text() == "timeline: coupling must be a number in [0, 1], got 2"
    assert "smoothing" not in sent[-1]  # an empty field: the model's default, nothing sent
    page.uncheck("#parts-separate")  # joint again: the coupling is not sent
    page.fill("#smoothing", "1.5")
    page.click("#generate")
    page.wait_for_function("window.omgViewer.results == 3", timeout=60_000)
    assert sent[-1]["timeline"] == {"parts": parts} and sent[-1]["smoothing"] == 1.5
    assert httpx.get(server.url + answers[-1].json()["settings"]).json()["smoothing"] == 1.5
    context.close()


def test_a_character_rig_gets_each_motion_onto_the_character(serve_ckpts, tmp_path):
    """``omg serve --to_rig character.glb``: the rig is read for the models whose skeleton it fits (the human
    ones, not the animal's), and each human motion's files link the character animated (``glb``)."""
    import pygltflib

    from helpers.characters import write_character
    from omg.errors import UsageError
    from omg.tools.serve import load_models, model_rigs
    from omg.tools.serve.app import Limits, create_app

    character = write_character(tmp_path / "figure.glb")
    models = load_models([serve_ckpts["human"], serve_ckpts["animal"]], serve_ckpts["human"], torch.device("cpu"))
    rigs = model_rigs(models, character, None)
    assert set(rigs) == {"smpl22"}
    with pytest.raises(UsageError, match="human rig"):
        model_rigs([m for m in models if m.card.skeleton == "smal35"], character, None)
    running = ThreadServer(create_app(models, tmp_path / "out", Limits(), rigs=rigs))
    try:
        with httpx.Client(base_url=running.url, timeout=120) as client:
            result = _generate(client, model="human", prompts=["a person waves"], length=1, steps=2)
            files = result["motions"][0]["files"]
            assert set(files) == {"glb", "joints", "features"}
            animated = pygltflib.GLTF2.load_from_bytes(client.get(files["glb"]).content)
            kept = json.loads(pygltflib.GLTF2().load(str(character)).to_json())
            assert len(animated.animations) == 1 and json.loads(animated.to_json())["meshes"] == kept["meshes"]
            assert client.get(result["settings"]).json()["to_rig"] == "figure.glb"
            # the character uploaded for a result is the same code path: the same file, byte for byte
            upload = _onto(client, result["id"], "figure.glb", character.read_bytes())
            assert client.get(upload.json()["motions"][0]["url"]).content == client.get(files["glb"]).content
    finally:
        running.stop()
def test_omg_serve_to_rig_an_fbx_character_writes_each_motion_on_it(serve_ckpts, fbx_figure, tmp_path):
    """``omg serve --to_rig character.fbx``: each human motion is written onto the FBX character (``fbx`` in its
    files), which Blender opens with one action over the motion's frames, the mesh moving with the bones; an
    uploaded FBX for a result answers its .fbx to download and the .glb the page plays."""
    from helpers.blender_scenes import blender
    from omg.io.fbx import BINARY_MAGIC
    from omg.tools.serve import load_models, model_rigs
    from omg.tools.serve.app import Limits, create_app

    models = load_models([serve_ckpts["human"]], None, torch.device("cpu"))
    rigs = model_rigs(models, fbx_figure, None)
    assert set(rigs) == {"smpl22"}
    running = ThreadServer(create_app(models, tmp_path / "out", Limits(parse_timeout=300.0), rigs=rigs))
    try:
        with httpx.Client(base_url=running.url, timeout=300) as client:
            result = _generate(client, model="human", prompts=["a person waves"], length=1, steps=2)
            files = result["motions"][0]["files"]
            assert set(files) == {"fbx", "joints", "features"}
            (tmp_path / "served.fbx").write_bytes(client.get(files["fbx"]).content)
            assert client.get(result["settings"]).json()["to_rig"] == "figure.fbx"
            upload = _onto(client, result["id"], "figure.fbx", fbx_figure.read_bytes())
            assert upload.status_code == 200, upload.text
            motion = upload.json()["motions"][0]
            assert motion["url"].endswith(".fbx") and motion["view"].endswith(".glb")
            assert client.get(motion["url"]).content.startswith(BINARY_MAGIC)
            assert len(_glb_document(client.get(motion["view"]).content)["animations"]) == 1
    finally:
        running.stop()
    blender("probe", [{"path": str(tmp_path / "served.fbx"), "out": str(tmp_path / "served.npz"), "fps": 20}],
            tmp_path)
    probe = json.loads((tmp_path / "served.json").read_text())
    with np.load(tmp_path / "served.npz") as arrays:
        heads, skinned = arrays["heads"], arrays["skinned"]
    assert len(probe["actions"]) == 1 and len(heads) == result["motions"][0]["frames"]
    assert np.linalg.norm(heads[-1] - heads[0], axis=-1).max() > 0.02  # the bones move
    assert np.linalg.norm(skinned[-1] - skinned[0], axis=-1).max() > 0.02  # and the mesh with them


