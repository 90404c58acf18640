"""The server's application: routes, the dynamic batcher and the result store.

Everything a route knows about a model comes from its generation card (``omg.lit.generative``):
which inputs it takes, its frame limits, samplers and species. Sampling runs on one worker thread
(one model call at a time, off the event loop); requests that arrive within ``max_wait`` seconds
of each other for the same model and settings are answered by one ``generate`` call of at most
``max_batch`` motions when the card says ``row_seeds`` (each motion has its own noise seed, so
it is the same alone or batched); other families answer their requests one after another.
"""

from __future__ import annotations

import asyncio
import logging
import re
import secrets
import shutil
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from contextlib import asynccontextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from fastapi import FastAPI, File, Form, Request, UploadFile
from fastapi.exceptions import RequestValidationError
from fastapi.responses import FileResponse, JSONResponse
from fastapi.staticfiles import StaticFiles
from pydantic import BaseModel, Field

from omg.errors import UsageError
from omg.lit.generative import (
    GeneratedMotion,
    GenerationCard,
    GenerationRequest,
    GenerativeModule,
    card_inputs,
    check_request,
)
from omg.registry import SAMPLERS
from omg.skeleton import get_skeleton
from omg.tools.generate import check_finite_motions, read_prompts, write_generation

log = logging.getLogger("omg.serve")
STATIC = Path(__file__).parent / "static"
UPLOAD_SUFFIXES = (".bvh", ".npy", ".json", ".txt", ".amc", ".asf")
EXAMPLES = {"text": ["a person walks forward and waves", "a person jumps in place twice", "a person kicks with the "
                     "right leg"],
            "species": ["a dog runs and jumps over a log", "a horse trots in a circle", "a cat sneaks forward"]}


@dataclass
class Model:
    """One loaded checkpoint: its name in the API, its module and card, and the second module that makes
    its source motion from prompts (``--human_ckpt``) where the card takes one."""

    name: str
    ckpt: str
    module: GenerativeModule
    card: GenerationCard
    source_module: GenerativeModule | None = None

    def info(self) -> dict[str, Any]:
        skeleton = get_skeleton(self.card.skeleton)
        return {"name": self.name, "ckpt": self.ckpt, "module": type(self.module).__name__,
                "card": self.card.to_dict(), "parents": list(skeleton.parents), "joints": list(skeleton.names),
                "source_generator": self.source_module is not None,
                "examples": EXAMPLES["species" if "species" in self.card.inputs else "text"]
                if "text" in self.card.inputs else []}


@dataclass
class Limits:
    max_batch: int = 16  # motions in one sampling call
    max_wait: float = 0.05  # seconds a request waits for others to batch with
    max_samples: int = 16  # motions one request may ask for
    max_prompt_chars: int = 300
    max_upload_bytes: int = 20 * 2**20


@dataclass
class Job:
    model: Model
    request: GenerationRequest
    future: asyncio.Future
    rows: int


@dataclass
class Batcher:
    """Collects jobs for ``max_wait`` seconds (or ``max_batch`` motions) and runs them on one worker thread."""

    limits: Limits
    queue: asyncio.Queue = field(default_factory=asyncio.Queue)
    worker: ThreadPoolExecutor = field(default_factory=lambda: ThreadPoolExecutor(1, thread_name_prefix="omg-sample"))
    busy: int = 0  # motions being sampled now
    calls: int = 0  # sampling calls made (the page and the tests read how requests were batched)

    async def submit(self, model: Model, request: GenerationRequest, rows: int) -> tuple[list[GeneratedMotion], int]:
        job = Job(model, request, asyncio.get_running_loop().create_future(), rows)
        await self.queue.put(job)
        return await job.future

    async def run(self) -> None:
        loop = asyncio.get_running_loop()
        while True:
            jobs = [await self.queue.get()]
            deadline = loop.time() + self.limits.max_wait
            while sum(j.rows for j in jobs) < self.limits.max_batch and (left := deadline - loop.time()) > 0:
                try:
                    jobs.append(await asyncio.wait_for(self.queue.get(), left))
                except TimeoutError:
                    break
            for group in _groups(jobs, self.limits.max_batch):
                self.busy = sum(j.rows for j in group)
                try:
                    results = await loop.run_in_executor(self.worker, _sample, group, self.limits.max_batch)
                except Exception as e:  # the group's requests answer 500; the server goes on
                    log.exception("generation failed")
                    for job in group:
                        if not job.future.done():
                            job.future.set_exception(e)
                else:
                    self.calls += 1
                    for job, motions in zip(group, results):
                        if not job.future.done():
                            job.future.set_result((motions, self.busy))
                finally:
                    self.busy = 0


def _key(job: Job) -> tuple | None:
    """Jobs with the same key are sampled in one call; None: alone (a family without per-motion seeds, or a
    request with a source motion)."""
    r = job.request
    if not job.model.card.row_seeds or r.source is not None or r.source_module is not None:
        return None
    return (job.model.name, r.frames, r.steps, r.sampler, r.guidance, r.species, bool(r.prompts))


def _groups(jobs: list[Job], max_batch: int) -> list[list[Job]]:
    groups: list[list[Job]] = []
    open_: dict[tuple, list[Job]] = {}
    for job in jobs:
        key = _key(job)
        group = open_.get(key) if key is not None else None
        if group is not None and sum(j.rows for j in group) + job.rows <= max_batch:
            group.append(job)
            continue
        group = [job]
        groups.append(group)
        if key is not None:
            open_[key] = group
    return groups


def _sample(group: list[Job], max_batch: int) -> list[list[GeneratedMotion]]:
    """One ``generate`` call for a group of compatible jobs (their motions concatenated, each with its own
    seed), or the lone job's own call."""
    if len(group) == 1 and _key(group[0]) is None:
        return [group[0].model.module.generate(group[0].request)]
    first = group[0].request
    prompts, seeds, repeats = [], [], []
    for job in group:
        r = job.request
        for index, (prompt, k) in enumerate((p, k) for p in (r.prompts or [None]) for k in range(r.num_samples)):
            prompts.append(prompt)
            seeds.append(r.seed + index)
            repeats.append(k)
    merged = replace(first, prompts=prompts if first.prompts else None,
                     num_samples=1 if first.prompts else len(prompts), seed=seeds[0], row_seeds=seeds,
                     batch_size=max_batch)
    motions = group[0].model.module.generate(merged)
    for motion, k in zip(motions, repeats):
        motion.record["repeat"] = k
    out, start = [], 0
    for job in group:
        out.append(motions[start : start + job.rows])
        start += job.rows
    return out


class GenerateBody(BaseModel):
    """A generation: ``num_samples`` motions per prompt (in total for an unconditional model)."""

    model: str | None = Field(None, description="a loaded model's name (GET /v1/models); default: the first")
    prompts: list[str] = Field(default_factory=list, description="text prompts (for a text-conditioned model)")
    length: float | None = Field(None, gt=0, allow_inf_nan=False, description="seconds per motion (default 4)")
    num_samples: int = Field(1, ge=1, description="motions per prompt")
    seed: int = Field(0, ge=0, lt=2**62, description="motion i (prompt-major) is drawn with seed + i")
    steps: int | None = Field(None, ge=1, description="sampling steps (default: the model's)")
    sampler: str | None = Field(None, description="a sampler of the model's card")
    guidance: float | None = Field(None, ge=0, allow_inf_nan=False, description="classifier-free guidance scale")
    species: str | None = Field(None, description="the animal (models whose card takes a species)")


def create_app(models: list[Model], out: Path, limits: Limits | None = None, remove_out: bool = False) -> FastAPI:
    """The application serving ``models``; results are written under ``out`` (one folder per result), which
    is removed at shutdown under ``remove_out`` (uvicorn re-raises SIGTERM after it: no later code runs)."""
    limits = limits or Limits()
    by_name = {m.name: m for m in models}
    batcher = Batcher(limits)
    out.mkdir(parents=True, exist_ok=True)

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        task = asyncio.create_task(batcher.run())
        yield  # uvicorn has answered the requests in flight when this resumes
        task.cancel()
        batcher.worker.shutdown(wait=True)
        if remove_out:
            shutil.rmtree(out, ignore_errors=True)

    app = FastAPI(title="omg serve", version="1", lifespan=lifespan,
                  description="Text-to-motion, animal motion and habit transfer from the checkpoints loaded; "
                              "each model's generation card says what it takes.")
    app.state.batcher, app.state.models, app.state.limits = batcher, by_name, limits

    @app.exception_handler(UsageError)
    async def usage_error(request: Request, e: UsageError):
        return JSONResponse({"detail": str(e)}, status_code=400)

    @app.exception_handler(RequestValidationError)
    async def invalid(request: Request, e: RequestValidationError):  # one line, not pydantic's list
        first = e.errors()[0]
        where = ".".join(str(p) for p in first.get("loc", ()) if p not in ("body", "query", "path"))
        return JSONResponse({"detail": f"{where or 'request'}: {first.get('msg', 'invalid')}"}, status_code=422)

    @app.middleware("http")
    async def upload_limit(request: Request, call_next):  # refused before the body is read
        size = request.headers.get("content-length")
        if size is not None and size.isdigit() and int(size) > limits.max_upload_bytes + 2**16:
            return JSONResponse({"detail": f"the request is larger than the {limits.max_upload_bytes} bytes "
                                           "allowed (--max_upload_mb)"}, status_code=413)
        return await call_next(request)

    @app.get("/healthz", summary="the server answers")
    async def healthz():
        return {"status": "ok", "models": len(by_name), "queued": batcher.queue.qsize(), "sampling": batcher.busy}

    @app.get("/v1/models", summary="the loaded models and their generation cards")
    async def list_models():
        return {"models": [m.info() for m in models],
                "limits": {"max_batch": limits.max_batch, "max_samples": limits.max_samples,
                           "max_prompt_chars": limits.max_prompt_chars, "max_upload_bytes": limits.max_upload_bytes}}

    @app.get("/v1/status", summary="what the sampler is doing (the page's progress)")
    async def status():
        return {"queued": batcher.queue.qsize(), "sampling": batcher.busy, "calls": batcher.calls}

    @app.post("/v1/generate", summary="motions from prompts (or none, for an unconditional model)")
    async def generate(body: GenerateBody):
        model = _model(by_name, models, body.model, "a request body")
        card = model.card
        prompts = read_prompts(body.prompts)
        if long := [i for i, p in enumerate(prompts) if len(p) > limits.max_prompt_chars]:
            raise UsageError(f"prompt {long[0] + 1} is {len(prompts[long[0]])} characters long; at most "
                             f"{limits.max_prompt_chars}")
        if body.sampler is not None:
            _sampler(card, body.sampler)
        rows = max(len(prompts), 1) * body.num_samples
        if rows > limits.max_samples:
            raise UsageError(f"{rows} motions asked for; at most {limits.max_samples} per request")
        length = body.length if body.length is not None else min(4.0, card.max_frames / card.fps)
        request = GenerationRequest(prompts=prompts or None, frames=round(length * card.fps),
                                    num_samples=body.num_samples, seed=body.seed, steps=body.steps,
                                    sampler=body.sampler, guidance=body.guidance, species=body.species,
                                    batch_size=limits.max_batch)
        if model.source_module is not None and prompts:
            request.source_module = model.source_module
        _check(card, request, model, length)
        return await _answer(model, request, rows, {"length_s": length})

    @app.post("/v1/transfer", summary="an uploaded motion moved onto another species (or made by a model that "
                                      "takes a source motion)")
    async def transfer(file: UploadFile = File(..., description="a BVH, DeepMimic or .npy motion"),
                       model: str | None = Form(None), to: str | None = Form(None, description="the target species "
                                                                                "or a description of the animal"),
                       prompts: list[str] = Form([]), seed: int = Form(0, ge=0, lt=2**62),
                       num_samples: int = Form(1, ge=1), joint_map: str | None = Form(None)):
        chosen = _model(by_name, [m for m in models if "motion" in m.card.inputs], model, "a source motion")
        card = chosen.card
        if num_samples > limits.max_samples:
            raise UsageError(f"{num_samples} motions asked for; at most {limits.max_samples} per request")
        suffix = Path(file.filename or "").suffix.lower()
        if suffix not in UPLOAD_SUFFIXES:
            raise UsageError(f"the upload {file.filename!r} is not a motion file; give one of "
                             f"{', '.join(UPLOAD_SUFFIXES)}")
        data = await file.read(limits.max_upload_bytes + 1)
        if len(data) > limits.max_upload_bytes:
            raise _Refusal(413, f"the upload is larger than the {limits.max_upload_bytes} bytes allowed")
        if joint_map is not None and not re.fullmatch(r"[\w\-]+", joint_map):
            raise UsageError(f"joint_map {joint_map!r}: give a registered joint map's name")
        with tempfile.TemporaryDirectory(prefix="omg-upload-") as folder:
            path = Path(folder) / f"upload{suffix}"
            path.write_bytes(data)
            loop = asyncio.get_running_loop()
            try:
                source = await loop.run_in_executor(batcher.worker, chosen.module.read_source, path, joint_map)
            except UsageError as e:
                raise UsageError(str(e).replace(str(path), file.filename or "the upload")) from None
            except Exception as e:  # a garbled file the reader did not foresee is still the upload's fault
                raise UsageError(f"could not read the upload {file.filename!r} as a motion: "
                                 f"{_one_line(e)}") from None
        prompt_list = read_prompts(prompts)
        # the source sets the length where the card says so; else as long as the source allows
        request = GenerationRequest(prompts=prompt_list or None, frames=card.max_frames,
                                    num_samples=1 if card.deterministic_source else num_samples, seed=seed,
                                    species=to, source=source, batch_size=limits.max_batch)
        _check(card, request, chosen, None)
        return await _answer(chosen, request, request.num_samples * max(len(prompt_list), 1),
                             {"source": file.filename})

    @app.get("/v1/results/{result}/{name}", summary="a file of a result (BVH, .joints.npy, .features.npy, the "
                                                    "settings JSON)")
    async def result_file(result: str, name: str):
        path = _result_path(out, result, name)
        if path is None:
            return JSONResponse({"detail": "no such result file"}, status_code=404)
        return FileResponse(path, filename=f"{result}_{name}")

    @app.exception_handler(_Refusal)
    async def refused(request: Request, e: _Refusal):
        return JSONResponse({"detail": e.message}, status_code=e.status)

    async def _answer(model: Model, request: GenerationRequest, rows: int, extra: dict) -> JSONResponse:
        started = time.perf_counter()
        try:
            motions, batched = await batcher.submit(model, request, rows)
            check_finite_motions(motions, Path(model.ckpt))
            result = secrets.token_hex(6)
            settings = {"model": model.name, "ckpt": model.ckpt, "module": type(model.module).__name__,
                        "family": model.card.family, "prompts": request.prompts, "num_samples": request.num_samples,
                        "frames": request.frames, "fps": model.card.fps, "seed": request.seed, **extra,
                        **model.module.generation_settings(request), "row_seeds": model.card.row_seeds,
                        "representation": model.card.representation, "skeleton": model.card.skeleton}
            folder = out / result
            await asyncio.get_running_loop().run_in_executor(
                None, lambda: write_generation(folder, motions, model.card, settings, preview=False))
        except UsageError:
            raise
        except Exception as e:  # one line to the client, the traceback to the server's log
            log.exception("request failed")
            return JSONResponse({"detail": f"generation failed: {_one_line(e)}"}, status_code=500)
        skeleton = get_skeleton(model.card.skeleton)
        files = sorted(p.name for p in folder.iterdir())
        url = f"/v1/results/{result}"
        return JSONResponse({
            "id": result, "model": model.name, "fps": model.card.fps, "skeleton": model.card.skeleton,
            "parents": list(skeleton.parents), "batched_motions": batched,
            "seconds": round(time.perf_counter() - started, 3), "settings": f"{url}/generation.json",
            "motions": [{"title": m.title, "record": record, "frames": len(m.joints),
                         "joints": np.round(np.asarray(m.joints, np.float64), 4).tolist(),
                         "files": {kind: f"{url}/{record['file']}{ext}" for kind, ext in
                                   (("bvh", ".bvh"), ("joints", ".joints.npy"), ("features", ".features.npy"))
                                   if f"{record['file']}{ext}" in files}}
                        for m, record in zip(motions, settings["samples"])]})

    app.mount("/static", StaticFiles(directory=STATIC), name="static")

    @app.get("/", include_in_schema=False)
    async def page():
        return FileResponse(STATIC / "index.html")

    return app


class _Refusal(Exception):
    def __init__(self, status: int, message: str):
        super().__init__(message)
        self.status, self.message = status, message


def _model(by_name: dict[str, Model], candidates: list[Model], name: str | None, takes: str = "") -> Model:
    if name is not None:
        if name not in by_name:
            raise UsageError(f"unknown model {name!r}; loaded: {', '.join(by_name) or 'none'}")
        if by_name[name] not in candidates:
            raise UsageError(f"model {name!r} does not generate from {takes}; it takes "
                             f"{card_inputs(by_name[name].card)}")
        return by_name[name]
    if not candidates:
        raise UsageError(f"no loaded model generates from {takes}")
    return candidates[0]


def _sampler(card: GenerationCard, name: str) -> None:
    if not card.samplers:
        raise UsageError(f"sampler {name!r}: this model has no sampler to choose")
    if name not in card.samplers:
        raise UsageError(f"unknown sampler {name!r}; this model's: {', '.join(card.samplers)}")
    SAMPLERS.get(name)


def _check(card: GenerationCard, request: GenerationRequest, model: Model, length: float | None) -> None:
    """``check_request`` with the API's words for the CLI's flags."""
    try:
        check_request(card, request, f"model {model.name!r}")
    except UsageError as e:
        message = str(e)
        if length is not None and message.startswith("--length"):
            message = (f"length {length:g} s is {request.frames} frames; this model makes "
                       f"{card.min_frames / card.fps:g}..{card.max_frames / card.fps:g} s "
                       f"({card.min_frames}..{card.max_frames} frames at {card.fps:g} fps)")
        for flag, field_ in (("--length", "length"), ("--steps", "steps"), ("--sampler", "sampler"),
                             ("--animal", "species"), ("--from_motion", "an uploaded motion (/v1/transfer)"),
                             ("--unconditional", "no prompts")):
            message = message.replace(flag, field_)
        raise UsageError(message) from None


def _result_path(out: Path, result: str, name: str) -> Path | None:
    """A file the server wrote, or None: names are checked, never joined blindly (no traversal)."""
    if not re.fullmatch(r"[0-9a-f]{12}", result) or not re.fullmatch(r"[\w][\w.\-]*", name) or ".." in name:
        return None
    path = out / result / name
    return path if path.is_file() and path.resolve().parent == (out / result).resolve() else None


def _one_line(e: BaseException) -> str:
    text = " ".join(str(e).split()) or type(e).__name__
    return text if len(text) <= 300 else text[:297] + "..."


__all__ = ["Batcher", "GenerateBody", "Limits", "Model", "create_app"]
