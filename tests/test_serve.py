"""``omg serve`` against a real running server (uvicorn on a free port) with tiny checkpoints of the three
families: a ControlNet (text → human), OmniMotionGPT (text → animal, with the ControlNet as its human
source) and a habit-transfer pair (VQ-VAE + flow prior), each fitted one step."""

from __future__ import annotations

import io
import json
import os
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest
import torch

from helpers import MINI, REPO, TINY_DIT
from helpers.habit import CATEGORIES

pytest.importorskip("fastapi", reason="omg serve needs fastapi (pip install -e '.[dev]')")
httpx = pytest.importorskip("httpx", reason="the server tests talk to it with httpx")



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
    from omg.lit.controlnet import ControlNetModule
    from omg.lit.habit import HabitPriorModule, HabitVQModule
    from omg.lit.omgpt import OmniMotionModule
    from omg.lit.pretrain import PretrainModule

    root = tmp_path_factory.mktemp("serve_ckpts")
    torch.manual_seed(0)
    human = _data(MINI / "human263/train")
    pretrain = PretrainModule(flavor="mini", dit=TINY_DIT, spec=human.spec,
                              warmup_steps=1, ema_decay=0)
    _fit_save(pretrain, human, root / "pretrain.ckpt")
    controlnet = ControlNetModule(pretrained=str(root / "pretrain.ckpt"), text_encoder="hash",
                                  moc={"d_c": 16, "num_experts": 2}, spec=human.spec, warmup_steps=1, ema_decay=0)
    _fit_save(controlnet, _data(MINI / "human263/train"), root / "human.ckpt")
    animal = _data(MINI / "animal_maa/train", max_len=32)
    stream = dict(train=str(MINI / "human_maa/train"), batch_size=4, max_len=32, min_len=20, num_workers=0,
                  shuffle_buffer=32, clips="whole")
    config = {"joint_layers": 1, "joint_heads": 2, "temporal_dim": 32, "temporal_layers": 1, "latent_dim": 32}
    omgpt = OmniMotionModule(human_data=stream, flavor="mini", config=config, text_encoder="hash", spec=animal.spec,
                             ema_decay=0)
    _fit_save(omgpt, animal, root / "animal.ckpt")
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

    def __init__(self, app):
        import uvicorn

        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=self.port, log_level="warning"))
        self.thread = threading.Thread(target=self.server.run, daemon=True)
        self.thread.start()
        deadline = time.monotonic() + 30
        while not self.server.started:
            assert time.monotonic() < deadline and self.thread.is_alive(), "the server did not start"
            time.sleep(0.02)

    def stop(self) -> None:
        self.server.should_exit = True
        self.thread.join(30)


@pytest.fixture(scope="module")
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
    from omg.lit.generative import GenerationRequest

    module = server.models["human"].module
    request = GenerationRequest(prompts=["a person walks", "a person jumps"], frames=24, num_samples=2, seed=9,
                                steps=4)
    motions = module.generate(request)
    texts = ["a person walks", "a person walks", "a person jumps", "a person jumps"]
    mask = torch.ones(4, 24, dtype=torch.bool)
    with torch.no_grad():  # the path before row seeds, spelled out: x_T from one generator seeded 9
        x = module.diffusion.ddim_sample(module.denoiser(texts, mask, None), (4, 24, 263), steps=4, mask=mask,
                                         generator=torch.Generator().manual_seed(9))
    for motion, row in zip(motions, module.denormalize(x)):
        assert np.array_equal(motion.features, row.float().numpy())
    alone = module.generate(GenerationRequest(prompts=["a person jumps"], frames=24, steps=4, row_seeds=[11]))
    batched = module.generate(GenerationRequest(prompts=texts[:2] + ["a person jumps"], frames=24, steps=4,
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
        assert slow.result()["motions"]


# -- bad requests ---------------------------------------------------------------------------


@pytest.mark.parametrize("body, status, message", [
    (dict(model="nope", prompts=["a person walks"]), 400, "unknown model 'nope'; loaded: human, animal, habit"),
    (dict(model="human", prompts=["a person walks"], sampler="heun"), 400, "unknown sampler 'heun'"),
    (dict(model="human", prompts=[" "]), 400, "prompt 1 is empty"),
    (dict(model="human", prompts=["a" * 301]), 400, "prompt 1 is 301 characters long; at most 300"),
    (dict(model="human", prompts=["a person walks"], length=100), 400, "length 100 s is 2000 frames; this model"),
    (dict(model="human", prompts=["a person walks"], length=-1), 422, "length: Input should be greater than 0"),
    (dict(model="human", prompts=["a person walks"], guidance="NaN"), 422, "guidance: Input should be a finite"),
    (dict(model="human", prompts=["a person walks"], seed=-3), 422, "seed: Input should be greater than or equal"),
    (dict(model="human", prompts=["a person walks"], num_samples=9), 400, "9 motions asked for; at most 8"),
    (dict(model="human", prompts=["a person walks"], steps=5000), 400, "steps must be in 1..1000"),
    (dict(model="human", prompts=["a person\x00walks"]), 400, "control character"),
    (dict(model="animal"), 400, "generates from prompts"),
    (dict(model="pretrain", prompts=["a person walks"]), 400, "unconditional"),
    (dict(model="animal", prompts=["a dog walks"], species="unicorn"), 400, "unknown animal 'unicorn'"),
    (dict(model="habit", prompts=["a dog walks"]), 400, "does not generate from prompts"),
])
def test_bad_generate_requests_are_one_readable_line(client, body, status, message):
    response = client.post("/v1/generate", json=body)
    assert response.status_code == status, response.text
    detail = response.json()["detail"]
    assert isinstance(detail, str) and "\n" not in detail and "Traceback" not in detail
    assert message in detail, detail
    assert client.get("/healthz").status_code == 200


def test_garbled_json_is_one_line(client):
    response = client.post("/v1/generate", content=b"{not json", headers={"content-type": "application/json"})
    assert response.status_code == 422 and isinstance(response.json()["detail"], str)


@pytest.mark.parametrize("name, content, fields, status, message", [
    ("clip.bvh", b"HIERARCHY\nROOT garbage {", {"to": "horse"}, 400, "clip.bvh"),
    ("clip.exe", b"MZ", {"to": "horse"}, 400, "is not a motion file"),
    ("clip.npy", b"\x93NUMPY garbled", {"to": "horse"}, 400, "clip.npy"),
    ("big.bvh", b"x" * 2_100_000, {"to": "horse"}, 413, "bytes allowed"),
    ("clip.bvh", None, {"to": "horse", "model": "human"}, 400, "does not generate from"),
    ("clip.bvh", None, {"to": "horse", "joint_map": "../../etc"}, 400, "joint_map"),
    ("clip.bvh", "rig", {"to": "horse"}, 400, "no registered map fits"),
], ids=["garbled-bvh", "not-motion", "garbled-npy", "too-large", "wrong-model", "joint-map-path", "unfit-rig"])
def test_bad_uploads_are_one_readable_line(client, shared_motion, name, content, fields, status, message):
    if content is None:
        content = _bvh(shared_motion)
    elif content == "rig":  # a rig of three joints: no joint map fits it
        content = (b"HIERARCHY\nROOT Hips\n{\n OFFSET 0 0 0\n CHANNELS 6 Xposition Yposition Zposition Zrotation "
                   b"Xrotation Yrotation\n JOINT Foo\n {\n  OFFSET 0 1 0\n  CHANNELS 3 Zrotation Xrotation Yrotation\n"
                   b"  End Site\n  {\n   OFFSET 0 1 0\n  }\n }\n}\nMOTION\nFrames: 2\nFrame Time: 0.05\n"
                   + b"0 0 0 0 0 0 0 0 0\n" * 2)
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
    module = server.models["human"].module
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


# -- the command ----------------------------------------------------------------------------


def test_omg_serve_binds_localhost_and_sigterm_finishes_the_request_in_flight(serve_ckpts, tmp_path):
    port = free_port()
    env = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"}
    log = tmp_path / "serve.log"
    process = subprocess.Popen([sys.executable, "-m", "omg.cli", "serve", "--ckpt", str(serve_ckpts["human"]),
                                "--ckpt", str(serve_ckpts["habit"]), "--port", str(port), "--device", "cpu"],
                               cwd=REPO, env=env, stdout=log.open("w"), stderr=subprocess.STDOUT)
    try:
        url = f"http://127.0.0.1:{port}"
        deadline = time.monotonic() + 60
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


@pytest.fixture(scope="module")
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


def test_the_page_generates_plays_and_downloads(server, browser, shared_motion, tmp_path):
    context = browser.new_context(accept_downloads=True, viewport={"width": 1200, "height": 800})
    page = context.new_page()
    requests, errors = [], []
    page.on("request", lambda r: requests.append(r.url))
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.goto(server.url + "/")
    page.wait_for_function("document.querySelectorAll('#model option').length == 4")
    page.select_option("#model", "human")
    assert page.locator("#upload-box").is_hidden() and page.locator("#text-box").is_visible()
    page.fill("#prompts", "a person walks forward\na person waves")
    page.fill("#length", "1.5")
    page.fill("#steps", "3")
    page.click("#generate")
    page.wait_for_function("window.omgViewer.results == 1 && window.omgViewer.drawn > 5", timeout=60_000)
    assert page.locator(".sample").count() == 2
    page.wait_for_timeout(400)  # a progress poll in flight does not overwrite the answer
    assert page.locator("#status").inner_text().startswith("2 motion(s) in ")
    assert "a person waves" in page.locator("#samples").inner_text()
    assert _canvas_colours(page) > 3  # the grid and two coloured skeletons
    first = page.evaluate("window.omgViewer.frame")
    page.wait_for_function(f"window.omgViewer.frame != {first}")
    page.click("#play")  # pause, then scrub
    page.locator("#scrubber").fill("10")
    page.wait_for_function("window.omgViewer.frame == 10")
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
    # habit transfer: the upload and the species
    page.select_option("#model", "habit")
    assert page.locator("#upload-box").is_visible() and page.locator("#text-box").is_hidden()
    page.set_input_files("#upload", files=[{"name": "dog.bvh", "mimeType": "text/plain",
                                           "buffer": _bvh(shared_motion)}])
    page.fill("#species", "horse")
    page.click("#generate")
    page.wait_for_function("window.omgViewer.results == 2 && window.omgViewer.drawn > 2", timeout=60_000)
    assert "horse" in page.locator("#samples").inner_text()
    context.close()
    assert not errors, errors
    assert requests and all(u.startswith(server.url + "/") for u in requests), [u for u in requests
                                                                                if not u.startswith(server.url)]
