"""The server's application: routes, the dynamic batcher and the result store.

Everything a route knows about a model comes from its generation card (``omg.generation``):
which inputs it takes, its frame limits, samplers and species. Sampling runs on one worker thread
(one model call at a time, off the event loop); requests that arrive within ``max_wait`` seconds
of each other for the same model and settings are answered by one ``generate`` call of at most
``max_batch`` motions when the card says ``row_seeds`` (each motion has its own noise seed, so
it is the same alone or batched); other families answer their requests one after another. A batched
call that fails is re-run job by job, so that only the request at fault fails.

Before FastAPI reads a byte, a pure-ASGI guard (``_Guard``) checks the ``Host`` (DNS rebinding) and the
``Origin`` of writes (another site's page), the content type, and the body as it streams in: over its
route's limit it is refused (413) whether chunked or not, and a body slower than ``read_timeout`` is cut
off (408). Uploads are parsed on their own small thread pool, never on the sampling thread (a character
uploaded for a result's motions is read, and the motions put onto it as ``--to_rig`` writes them, there);
results expire after ``result_ttl`` seconds and are capped at ``max_results_bytes`` in all, oldest dropped first.
"""

from __future__ import annotations

import asyncio
import inspect
import json
import logging
import os
import re
import secrets
import shutil
import tempfile
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from contextlib import asynccontextmanager
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import numpy as np
from fastapi import FastAPI, File, Form, Request, UploadFile
from fastapi.exceptions import RequestValidationError
from fastapi.responses import FileResponse, JSONResponse
from fastapi.staticfiles import StaticFiles
from pydantic import BaseModel, ConfigDict, Field
from starlette.exceptions import HTTPException

from omg.errors import UsageError
from omg.generation.progress import ProgressClock
from omg.generation.protocol import (
    GeneratedMotion,
    GenerationCard,
    GenerationRequest,
    Generator,
    card_inputs,
    check_request,
)
from omg.generation.timeline import TIMELINE_RANGES, parse_timeline
from omg.generation.write import check_finite_motions, write_generation
from omg.lit.sampling import MAX_SMOOTHING
from omg.registry import SAMPLERS
from omg.retarget import RIG_SUFFIXES
from omg.skeleton import body_parts, get_skeleton
from omg.tools.generate import check_plain_text, read_prompts

log = logging.getLogger("omg.serve")
STATIC = Path(__file__).parent / "static"
UPLOAD_SUFFIXES = (".bvh", ".npy", ".json", ".txt", ".amc", ".asf")
UPLOAD_ROUTES = ("/v1/transfer", "/v1/keyframes")  # multipart, with the upload's size limit
EXAMPLES = {"text": ["a person walks forward and waves", "a person jumps in place twice", "a person kicks with the "
                     "right leg"],
            "species": ["a dog runs and jumps over a log", "a horse trots in a circle", "a cat sneaks forward"]}
LOOPBACK = ("127.0.0.1", "localhost", "::1")  # the names of this machine a local page is loaded from
WRITES = ("POST", "PUT", "PATCH", "DELETE")


@dataclass
class Model:
    """One loaded checkpoint: its name in the API, its generator and card, and the second checkpoint's
    generator that makes its source motion from prompts (``--human_ckpt``) where the card takes one."""

    name: str
    ckpt: str
    generator: Generator
    card: GenerationCard
    source_module: Generator | None = None

    def info(self) -> dict[str, Any]:
        skeleton = get_skeleton(self.card.skeleton)  # the checkpoint's file name: no path of the server leaves it
        return {"name": self.name, "ckpt": Path(self.ckpt).name, "module": type(self.generator.module).__name__,
                "card": self.card.to_dict(), "parents": list(skeleton.parents), "joints": list(skeleton.names),
                # the names a body-part composition's entries take, for a card that takes them
                "body_parts": list(body_parts(skeleton)) if "parts" in self.card.timeline else [],
                # a timeline's numbers with their bounds and defaults (the page's fields), for a card that takes one
                "timeline_ranges": {name: asdict(r) for name, r in TIMELINE_RANGES.items()}
                if self.card.timeline else {},
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
    max_json_bytes: int = 64 * 2**10  # a JSON body: 16 prompts of 300 characters are under 10 KiB
    read_timeout: float = 60.0  # seconds a request's body may take to arrive, from its headers on
    result_ttl: float = 3600.0  # seconds a result's files are kept
    max_results_bytes: int = 2**30  # all results' files together; the oldest are dropped first
    parse_workers: int = 2  # uploads parsed at once (on their own threads, never the sampling thread)
    parse_timeout: float = 60.0  # seconds an upload's parse may take before its request is answered 422


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
    clock: ProgressClock | None = None  # the call in flight's progress, timed here
    seconds_per_step: dict[str, float] = field(default_factory=dict)  # per model, measured in its latest call

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
                try:
                    await self._call(group)
                except Exception as e:
                    if len(group) == 1:
                        _fail(group[0], e)
                        continue
                    # one request's fault (a prompt the text encoder chokes on) must not fail the others
                    # batched with it: each is sampled on its own, so that only the offending one fails
                    log.warning("a batch of %d requests failed (%s); sampling each alone", len(group), _one_line(e))
                    for job in group:
                        try:
                            await self._call([job])
                        except Exception as alone:
                            _fail(job, alone)

    async def _call(self, group: list[Job]) -> None:
        """One ``generate`` call answering ``group`` (raises what the call raised, answering none)."""
        self.busy = sum(j.rows for j in group)
        name = group[0].model.name
        # before the call's first step, its time left is at the seconds per step of the model's previous call
        self.clock = clock = ProgressClock(self.seconds_per_step.get(name))
        try:
            results = await asyncio.get_running_loop().run_in_executor(self.worker, _sample, group,
                                                                       self.limits.max_batch, clock)
            self.calls += 1
            for job, motions in zip(group, results):
                if not job.future.done():
                    job.future.set_result((motions, self.busy))
        finally:
            self.busy, self.clock = 0, None
            if clock.seconds_per_step is not None:
                self.seconds_per_step[name] = clock.seconds_per_step

    def progress(self) -> dict[str, Any] | None:
        """The batch in flight (None: none): its ``rows`` motions, its sampler's ``step`` of ``steps`` (0: a family
        without them), the call's motions made (``done``) of its ``motions``, and its ``elapsed_s`` and ``eta_s``
        (None until a rate is known) by this server's clock."""
        clock = self.clock
        if clock is None or (p := clock.latest) is None:
            return None
        left = clock.time_left()
        return {"rows": p.rows, "step": p.step, "steps": p.steps, "done": p.done, "motions": p.total,
                "elapsed_s": round(clock.elapsed(), 3), "eta_s": None if left is None else round(left, 3)}


def _fail(job: Job, e: Exception) -> None:
    """The job's request answers the error: 422 for a UsageError (the request's fault), else 500."""
    if not isinstance(e, UsageError):
        log.error("generation failed", exc_info=e)
    if not job.future.done():
        job.future.set_exception(e)


def _key(job: Job) -> tuple | None:
    """Jobs with the same key are sampled in one call; None: alone (a family without per-motion seeds, or a
    request with a source motion, a timeline or constraints)."""
    r = job.request
    if (not job.model.card.row_seeds or r.source is not None or r.source_module is not None or r.timeline is not None
            or r.control is not None):
        return None
    return (job.model.name, r.frames, r.steps, r.sampler, r.guidance, r.species, bool(r.prompts),
            tuple(sorted(r.options.items())))


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


def _sample(group: list[Job], max_batch: int, progress: ProgressClock) -> list[list[GeneratedMotion]]:
    """One ``generate`` call for a group of compatible jobs (their motions concatenated, each with its own
    seed), or the lone job's own call; ``progress`` hears how far it is."""
    if len(group) == 1 and _key(group[0]) is None:
        return [group[0].model.generator.generate(replace(group[0].request, progress=progress))]
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
                     batch_size=max_batch, progress=progress)
    motions = group[0].model.generator.generate(merged)
    for motion, k in zip(motions, repeats):
        motion.record["repeat"] = k
    out, start = [], 0
    for job in group:
        out.append(motions[start : start + job.rows])
        start += job.rows
    return out


class GenerateBody(BaseModel):
    """A generation: ``num_samples`` motions per prompt (in total for an unconditional model)."""

    model_config = ConfigDict(extra="forbid")  # a misspelt field ("num_sample") is an error, not a default

    model: str | None = Field(None, description="a loaded model's name (GET /v1/models); default: the first")
    prompts: list[str] = Field(default_factory=list, description="text prompts (for a text-conditioned model)")
    length: float | None = Field(None, gt=0, allow_inf_nan=False, description="seconds per motion (default 4)")
    num_samples: int = Field(1, ge=1, description="motions per prompt")
    seed: int = Field(0, ge=0, lt=2**62, description="motion i (prompt-major) is drawn with seed + i")
    steps: int | None = Field(None, ge=1, description="sampling steps (default: the model's)")
    sampler: str | None = Field(None, description="a sampler of the model's card")
    guidance: float | None = Field(None, ge=0, allow_inf_nan=False, description="classifier-free guidance scale")
    species: str | None = Field(None, description="the animal (models whose card takes a species)")
    timeline: list | dict | None = Field(None, description="a prompt timeline and body-part composition instead of "
                                         "prompts, as omg generate --timeline reads it (models whose card lists "
                                         "timeline)")
    constraints: dict[str, Any] | None = Field(None, description="spatial constraints, as a constraints file's JSON "
                                               "(docs/guide/control.md; keyframes give joints or positions, no file)")
    smoothing: float | None = Field(None, ge=0, le=MAX_SMOOTHING, allow_inf_nan=False,
                                    description="frames of the Gaussian every denoised estimate is smoothed over time "
                                    "by (models whose card lists the smoothing option; default: the model's, 0: off "
                                    "unless its config sets model.sampling.smoothing)")


def create_app(models: list[Model], out: Path, limits: Limits | None = None, remove_out: bool = False,
               allowed_hosts: tuple[str, ...] = LOOPBACK, rigs: dict[str, Any] | None = None,
               joint_map: str | None = None) -> FastAPI:
    """The application serving ``models``; results are written under ``out`` (one folder per result), which
    is removed at shutdown under ``remove_out`` (uvicorn re-raises SIGTERM after it: no later code runs).
    ``allowed_hosts``: the names a request's ``Host`` may give (``*``: any). ``rigs``: per model skeleton, the
    ``--to_rig`` rig (``omg.retarget.read_rig``) its motions are also written onto, with ``joint_map``: a
    BVH rig's ``.bvh``, a glTF character's ``.glb``, an FBX character's ``.fbx`` (the character animated), in
    place of the skeleton's BVH."""
    from omg.export import output_format

    limits = limits or Limits()
    rigs = rigs or {}
    by_name = {m.name: m for m in models}
    batcher = Batcher(limits)
    results = Results(out, limits.result_ttl, limits.max_results_bytes)
    parser = ThreadPoolExecutor(limits.parse_workers, thread_name_prefix="omg-upload")
    parsing = _Count()  # uploads queued or being parsed
    out.mkdir(parents=True, exist_ok=True)
    scrub = _scrubber(models, out)

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        tasks = [asyncio.create_task(batcher.run()), asyncio.create_task(results.expire_every(60.0))]
        yield  # uvicorn has answered the requests in flight when this resumes
        for task in tasks:
            task.cancel()
        batcher.worker.shutdown(wait=True)
        parser.shutdown(wait=False, cancel_futures=True)
        if remove_out:
            shutil.rmtree(out, ignore_errors=True)

    app = FastAPI(title="omg serve", version="1", lifespan=lifespan, default_response_class=_JSON,
                  description="Text-to-motion, animal motion and habit transfer from the checkpoints loaded; "
                              "each model's generation card says what it takes.")
    app.state.batcher, app.state.models, app.state.limits, app.state.results = batcher, by_name, limits, results
    app.add_middleware(_Guard, limits=limits, hosts=frozenset(h.lower().strip("[]") for h in allowed_hosts))

    @app.exception_handler(UsageError)
    async def usage_error(request: Request, e: UsageError):  # a value the request gave that cannot be served
        return _error(422, scrub(str(e)))

    @app.exception_handler(_Refusal)
    async def refused(request: Request, e: _Refusal):
        return _error(e.status, e.message, e.headers)

    @app.exception_handler(HTTPException)
    async def http_error(request: Request, e: HTTPException):  # 404, 405 (with its Allow header), a garbled form
        detail = e.detail if isinstance(e.detail, str) else json.dumps(e.detail)
        return _error(e.status_code, detail, e.headers)

    @app.exception_handler(RequestValidationError)
    async def invalid(request: Request, e: RequestValidationError):  # one line, not pydantic's list
        first = e.errors()[0]
        loc = first.get("loc", ())
        if first.get("type") == "json_invalid":  # not JSON at all: malformed, 400 (422 is for values)
            return _error(400, f"the body is not valid JSON: {first.get('ctx', {}).get('error', 'a decode error')} "
                               f"(at character {loc[-1] if loc else 0})")
        where = ".".join(str(p) for p in loc if p not in ("body", "query", "path"))
        return _error(422, f"{where or 'request'}: {first.get('msg', 'invalid')}")

    @app.exception_handler(Exception)
    async def crashed(request: Request, e: Exception):  # one line to the client, the traceback to the log
        # uvicorn closes the connection after an exception: the client must not send its next request on it
        return _error(500, f"the server failed: {scrub(_one_line(e))}", {"connection": "close"})

    async def _parse(file: UploadFile, name: str, suffix: str, read: Callable[[Path], Any]) -> Any:
        """The upload read by ``read`` from a temporary file, on the upload threads (never the sampling thread: a
        slow parse holds no one's generation); after parse_timeout the request is answered, and the parse ends on
        its own thread. Every field of the request is checked before this."""
        data = await file.read(limits.max_upload_bytes + 1)
        if len(data) > limits.max_upload_bytes:
            raise _Refusal(413, f"the upload is larger than the {limits.max_upload_bytes} bytes allowed "
                                "(--max_upload_mb)")
        if parsing.n >= 4 * limits.parse_workers:  # bounded: a burst of uploads waits no longer than this
            raise _Refusal(503, f"{parsing.n} uploads are being read; send this one again in a moment",
                           {"Retry-After": "5"})
        parsing.add(1)
        job = asyncio.wrap_future(parser.submit(_read_upload, read, data, suffix, name, parsing))
        try:
            return await asyncio.wait_for(asyncio.shield(job), limits.parse_timeout)
        except asyncio.TimeoutError:
            raise UsageError(f"the upload {name!r} took more than {limits.parse_timeout:g} s to read; send a "
                             "shorter clip") from None

    @app.get("/healthz", summary="the server answers")
    async def healthz():
        return {"status": "ok", "models": len(by_name), "queued": batcher.queue.qsize(), "sampling": batcher.busy}

    @app.get("/v1/models", summary="the loaded models and their generation cards")
    async def list_models():
        return {"models": [m.info() for m in models],
                "limits": {"max_batch": limits.max_batch, "max_samples": limits.max_samples,
                           "max_prompt_chars": limits.max_prompt_chars, "max_upload_bytes": limits.max_upload_bytes,
                           "max_json_bytes": limits.max_json_bytes, "result_ttl_s": limits.result_ttl,
                           "character_suffixes": character_suffixes()}}

    @app.get("/v1/status", summary="what the sampler is doing (the page's progress)")
    async def status():
        return {"queued": batcher.queue.qsize(), "sampling": batcher.busy, "calls": batcher.calls,
                "parsing": parsing.n, "progress": batcher.progress()}

    @app.post("/v1/generate", summary="motions from prompts (or none, for an unconditional model)")
    async def generate(body: GenerateBody):
        model = _model(by_name, models, body.model, "a request body")
        card = model.card
        prompts = _prompts(body.prompts, limits)
        if body.species is not None:
            _text(body.species, "species", limits)
        if body.sampler is not None:
            _sampler(card, body.sampler)
        spans = None if body.timeline is None else parse_timeline(
            body.timeline, "timeline", lambda text, what: _text(text, what, limits))
        rows = max(len(prompts), 1) * body.num_samples
        if rows > limits.max_samples:
            raise UsageError(f"{rows} motions asked for; at most {limits.max_samples} per request")
        length = body.length if body.length is not None else spans.end if spans is not None and spans.end else \
            min(4.0, card.max_frames / card.fps)
        if length * card.fps > 2 * card.max_frames:  # 1e308 s: no frame count to round
            raise UsageError(_length_message(card, length))
        request = GenerationRequest(prompts=prompts or None, frames=round(length * card.fps),
                                    num_samples=body.num_samples, seed=body.seed, steps=body.steps,
                                    sampler=body.sampler, guidance=body.guidance, species=body.species,
                                    batch_size=limits.max_batch, timeline=spans,
                                    options={} if body.smoothing is None else {"smoothing": body.smoothing})
        if model.source_module is not None and prompts:
            request.source_module = model.source_module
        _check(card, request, model, length)
        extra: dict[str, Any] = {"length_s": length}
        if body.constraints is not None:  # the same reading as --constraints: one line (422) per error
            from omg.generation.control import read_constraints

            request.control, extra["constraints"] = read_constraints(body.constraints, card, request.frames,
                                                                     "constraints", allow_files=False)
        return await _answer(model, request, rows, extra)

    @app.post("/v1/transfer", summary="an uploaded motion moved onto another species (or made by a model that "
                                      "takes a source motion)")
    async def transfer(file: UploadFile = File(..., description="a BVH, DeepMimic or .npy motion"),
                       model: str | None = Form(None), to: str | None = Form(None, description="the target species "
                                                                                "or a description of the animal"),
                       prompts: list[str] = Form([]), seed: int = Form(0, ge=0, lt=2**62),
                       num_samples: int = Form(1, ge=1), joint_map: str | None = Form(None), *, http: Request):
        # a misspelt field ("prompt") is an error, not a default, as in /v1/generate's body
        fields = [name for name in inspect.signature(transfer).parameters if name != "http"]
        if unknown := sorted(set((await http.form()).keys()) - set(fields)):
            raise UsageError(f"{unknown[0]}: Extra inputs are not permitted (the form's fields: {', '.join(fields)})")
        chosen = _model(by_name, [m for m in models if "motion" in m.card.inputs], model, "a source motion")
        card = chosen.card
        name = _upload_name(file.filename)
        # every field is checked before the upload is read
        if num_samples > limits.max_samples:
            raise UsageError(f"{num_samples} motions asked for; at most {limits.max_samples} per request")
        suffix = _upload_suffix(name)
        if joint_map is not None and not re.fullmatch(r"[\w\-]+", joint_map):
            raise UsageError(f"joint_map {joint_map!r}: give a registered joint map's name")
        if to is not None:
            _text(to, "to", limits)
        prompt_list = _prompts(prompts, limits)
        source = await _parse(file, name, suffix, lambda path: chosen.generator.read_source(path, joint_map))
        # the source sets the length where the card says so; else as long as the source allows
        request = GenerationRequest(prompts=prompt_list or None, frames=card.max_frames,
                                    num_samples=1 if card.deterministic_source else num_samples, seed=seed,
                                    species=to, source=source, batch_size=limits.max_batch)
        _check(card, request, chosen, None)
        return await _answer(chosen, request, request.num_samples * max(len(prompt_list), 1), {"source": name})

    @app.post("/v1/keyframes", summary="every frame of an uploaded take retargeted onto a model's skeleton: the "
                                       "poses a keyframe's positions are taken from (the page's control panel)")
    async def keyframes(file: UploadFile = File(..., description="a BVH, ASF/AMC, DeepMimic or .npy take"),
                        model: str | None = Form(None), joint_map: str | None = Form(None), *, http: Request):
        fields = [name for name in inspect.signature(keyframes).parameters if name != "http"]
        if unknown := sorted(set((await http.form()).keys()) - set(fields)):
            raise UsageError(f"{unknown[0]}: Extra inputs are not permitted (the form's fields: {', '.join(fields)})")
        chosen = _model(by_name, models, model)
        card = chosen.card
        if "keyframes" not in card.constraints:
            raise UsageError(f"model {chosen.name!r} takes no keyframes; its card lists "
                             f"{', '.join(card.constraints) or 'no constraints'}")
        name = _upload_name(file.filename)
        suffix = _upload_suffix(name)
        if joint_map is not None and not re.fullmatch(r"[\w\-]+", joint_map):
            raise UsageError(f"joint_map {joint_map!r}: give a registered joint map's name")
        from omg.generation.control import take_poses

        # the importers a constraints file's keyframe "file" is read by, placed in the model's world as there
        poses = await _parse(file, name, suffix, lambda path: take_poses(path, card, joint_map, ""))
        if not np.isfinite(poses).all():
            raise UsageError(f"the upload {name!r} retargets to NaN or inf positions; give another take")
        return {"model": chosen.name, "source": name, "fps": card.fps, "frames": len(poses),
                "skeleton": card.skeleton, "joints": list(get_skeleton(card.skeleton).names),
                "poses": np.round(poses.astype(np.float64), 4).tolist()}

    @app.get("/v1/results/{result}/{name}", summary="a file of a result (BVH, .joints.npy, .features.npy, the "
                                                    "settings JSON)")
    async def result_file(result: str, name: str):
        where = results.folder(result) if re.fullmatch(r"[0-9a-f]{12}", result) else None
        if isinstance(where, str):
            return _error(410, f"result {result} {where}; generate it again")
        path = _result_path(out, result, name) if where is not None else None
        if path is None:
            return _error(404, "no such result file")
        return FileResponse(path, filename=f"{result}_{name}")

    @app.post("/v1/results/{result}/character", summary="a result's motions on an uploaded character or rig, as "
                                                      "--to_rig writes them")
    async def character(result: str, file: UploadFile = File(..., description="a skinned glTF character (.glb, "
                                                                              ".gltf), an FBX character (.fbx, "
                                                                              "with Blender's module) or a BVH rig"),
                        joint_map: str | None = Form(None),
                        joint_map_file: UploadFile | None = File(None, description="the character's joint map (YAML, "
                                                                 "omg joint-map's scaffold finished) where no "
                                                                 "registered map fits its names"),
                        *, http: Request):
        fields = [name for name in inspect.signature(character).parameters if name not in ("http", "result")]
        if unknown := sorted(set((await http.form()).keys()) - set(fields)):
            raise UsageError(f"{unknown[0]}: Extra inputs are not permitted (the form's fields: {', '.join(fields)})")
        where = results.folder(result) if re.fullmatch(r"[0-9a-f]{12}", result) else None
        if isinstance(where, str):
            raise _Refusal(410, f"result {result} {where}; generate it again")
        if where is None:
            raise _Refusal(404, f"no result {result!r} on this server")
        name = _upload_name(file.filename)
        suffix = Path(name).suffix.lower()
        if suffix not in RIG_SUFFIXES:
            raise UsageError(f"the upload {name!r} is not a character or rig; give one of {', '.join(RIG_SUFFIXES)}")
        if joint_map is not None and not re.fullmatch(r"[\w\-]+", joint_map):
            raise UsageError(f"joint_map {joint_map!r}: give a registered joint map's name")
        map_text = None
        if joint_map_file is not None:
            if joint_map is not None:
                raise UsageError("give joint_map (a registered map's name) or joint_map_file (a YAML map), not both")
            map_text = (_upload_name(joint_map_file.filename), await joint_map_file.read(limits.max_json_bytes + 1))
            if len(map_text[1]) > limits.max_json_bytes:
                raise _Refusal(413, f"the joint map is larger than the {limits.max_json_bytes} bytes allowed")
        settings = json.loads((where / "generation.json").read_text())
        data = await file.read(limits.max_upload_bytes + 1)
        if len(data) > limits.max_upload_bytes:
            raise _Refusal(413, f"the upload is larger than the {limits.max_upload_bytes} bytes allowed "
                                "(--max_upload_mb)")
        if parsing.n >= 4 * limits.parse_workers:
            raise _Refusal(503, f"{parsing.n} uploads are being read; send this one again in a moment",
                           {"Retry-After": "5"})
        started = time.perf_counter()
        parsing.add(1)
        job = asyncio.wrap_future(parser.submit(_onto_character, where, settings, data, suffix, map_text or joint_map,
                                                name, parsing))
        try:
            written = await asyncio.wait_for(asyncio.shield(job), limits.parse_timeout)
        except asyncio.TimeoutError:
            raise UsageError(f"the upload {name!r} took more than {limits.parse_timeout:g} s to put the motions "
                             "onto") from None
        results.grow(result, sum((where / f).stat().st_size for files in written.values() for f in files))
        url = f"/v1/results/{result}"
        return {"id": result, "character": name, "seconds": round(time.perf_counter() - started, 3),
                "motions": [{"file": record["file"], "url": f"{url}/{written[record['file']][0]}",
                             "view": f"{url}/{written[record['file']][-1]}"} for record in settings["samples"]]}

    async def _answer(model: Model, request: GenerationRequest, rows: int, extra: dict) -> JSONResponse:
        started = time.perf_counter()
        try:
            motions, batched = await batcher.submit(model, request, rows)
            check_finite_motions(motions, Path(Path(model.ckpt).name), f" or guidance {request.guidance:g} too large"
                                 if request.guidance is not None else "")
            result = secrets.token_hex(6)
            settings = {"model": model.name, "ckpt": Path(model.ckpt).name,
                        "module": type(model.generator.module).__name__, "family": model.card.family,
                        "prompts": request.prompts, "num_samples": request.num_samples,
                        "frames": request.frames, "fps": model.card.fps, "seed": request.seed, **extra,
                        **model.generator.generation_settings(request), "row_seeds": model.card.row_seeds,
                        "representation": model.card.representation, "skeleton": model.card.skeleton}
            settings = _public(settings)  # a module's settings may name a checkpoint by its absolute path
            folder = out / result

            rig = rigs.get(model.card.skeleton)
            if rig is not None:
                settings["to_rig"] = Path(rig.source).name

            def write() -> int:
                write_generation(folder, motions, model.card, settings, preview=False, rig=rig, joint_map=joint_map,
                                 format=output_format(None, rig.source if rig is not None else None))
                return sum(f.stat().st_size for f in folder.iterdir())

            size = await asyncio.get_running_loop().run_in_executor(None, write)
        except UsageError:
            raise
        except Exception as e:  # one line to the client, the traceback to the server's log
            log.exception("request failed")
            return _error(500, f"generation failed: {scrub(_one_line(e))}")
        results.add(result, size)
        skeleton = get_skeleton(model.card.skeleton)
        files = sorted(p.name for p in folder.iterdir())
        url = f"/v1/results/{result}"
        return _JSON({
            "id": result, "model": model.name, "fps": model.card.fps, "skeleton": model.card.skeleton,
            "parents": list(skeleton.parents), "batched_motions": batched,
            "seconds": round(time.perf_counter() - started, 3), "settings": f"{url}/generation.json",
            "expires_in_s": limits.result_ttl,
            "motions": [{"title": m.title, "record": record, "frames": len(m.joints),
                         "joints": np.round(np.asarray(m.joints, np.float64), 4).tolist(),
                         "files": {kind: f"{url}/{record['file']}{ext}" for kind, ext in
                                   (("bvh", ".bvh"), ("glb", ".glb"), ("fbx", ".fbx"), ("joints", ".joints.npy"),
                                                     ("features", ".features.npy"))
                                   if f"{record['file']}{ext}" in files}}
                        for m, record in zip(motions, settings["samples"])]})

    app.mount("/static", StaticFiles(directory=STATIC), name="static")

    @app.get("/", include_in_schema=False)
    async def page():
        return FileResponse(STATIC / "index.html")

    return app


# -- answers ------------------------------------------------------------------------------------------------------


class _JSON(JSONResponse):
    """JSON in ASCII: a lone surrogate a client sent, echoed in a message, cannot break the answer's encoding."""

    def render(self, content: Any) -> bytes:
        return json.dumps(content, ensure_ascii=True, allow_nan=False, separators=(",", ":")).encode("ascii")


def _error(status: int, detail: str, headers: dict[str, str] | None = None) -> _JSON:
    return _JSON({"detail": _one_line(detail)}, status_code=status, headers=headers)


class _Refusal(Exception):
    def __init__(self, status: int, message: str, headers: dict[str, str] | None = None):
        super().__init__(message)
        self.status, self.message, self.headers = status, message, headers


USER_TEXT = {"prompts", "title", "to", "species", "animal", "description", "source"}  # never rewritten by _public


def _public(value: Any, key: str = "") -> Any:
    """``value`` without the server's absolute paths (a checkpoint a module's settings name): their file names."""
    if isinstance(value, dict):
        return {k: _public(v, k) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_public(v, key) for v in value]
    if isinstance(value, str) and key not in USER_TEXT and os.path.isabs(value):
        return Path(value).name
    return value


def _scrubber(models: list[Model], out: Path):
    """A message with the server's own paths (checkpoints, results, temporary files) replaced by their names."""
    pairs = {}
    for m in models:
        for path in (Path(m.ckpt), Path(m.ckpt).resolve()):
            pairs[str(path)] = path.name
            pairs[str(path.parent)] = "<checkpoints>"
    for path in (out, out.resolve()):
        pairs[str(path)] = "<results>"
    pairs[tempfile.gettempdir()] = "<tmp>"
    order = sorted((p for p in pairs if len(p) > 1), key=len, reverse=True)

    def scrub(text: str) -> str:
        for path in order:
            text = text.replace(path, pairs[path])
        return text

    return scrub


# -- requests -----------------------------------------------------------------------------------------------------


def _model(by_name: dict[str, Model], candidates: list[Model], name: str | None, takes: str = "") -> Model:
    if name is not None:
        if name not in by_name:  # the model named is no resource of this server: 404, as for a result
            raise _Refusal(404, f"unknown model {name!r}; loaded: {', '.join(by_name) or 'none'}")
        if by_name[name] not in candidates:
            raise UsageError(f"model {name!r} does not generate from {takes}; it takes "
                             f"{card_inputs(by_name[name].card)}")
        return by_name[name]
    if not candidates:
        raise UsageError(f"no loaded model generates from {takes}")
    return candidates[0]


def _prompts(prompts: list[str], limits: Limits) -> list[str]:
    """``read_prompts``' checks (plain text, not empty), and the server's length limit."""
    prompts = read_prompts(prompts)
    if long := [i for i, p in enumerate(prompts) if len(p) > limits.max_prompt_chars]:
        raise UsageError(f"prompt {long[0] + 1} is {len(prompts[long[0]])} characters long; at most "
                         f"{limits.max_prompt_chars}")
    return prompts


def _text(text: str, what: str, limits: Limits) -> str:
    """A species, an animal's description or a timeline's text: text for the text encoder, as a prompt is."""
    check_plain_text(text, what)
    if len(text) > limits.max_prompt_chars:
        raise UsageError(f"{what} is {len(text)} characters long; at most {limits.max_prompt_chars}")
    return text


def _upload_name(filename: str | None) -> str:
    """The upload's file name as messages and settings show it: its last part, printable, at most 100 characters."""
    name = Path(filename or "upload").name or "upload"
    name = "".join(c if c.isprintable() and not 0xD800 <= ord(c) <= 0xDFFF else "?" for c in name)
    return name if len(name) <= 100 else name[:97] + "..."


def _upload_suffix(name: str) -> str:
    suffix = Path(name).suffix.lower()
    if suffix not in UPLOAD_SUFFIXES:
        raise UsageError(f"the upload {name!r} is not a motion file; give one of {', '.join(UPLOAD_SUFFIXES)}")
    return suffix


def _read_upload(read: Callable[[Path], Any], data: bytes, suffix: str, name: str, parsing: _Count) -> Any:
    """The upload read by ``read`` from a temporary file (on an upload thread)."""
    try:
        with tempfile.TemporaryDirectory(prefix="omg-upload-") as folder:
            path = Path(folder) / f"upload{suffix}"
            path.write_bytes(data)
            try:
                return read(path)
            except UsageError as e:
                raise UsageError(str(e).replace(str(path), name).replace(folder, "")) from None
            except Exception as e:  # a garbled file the reader did not foresee is still the upload's fault
                raise UsageError(f"could not read the upload {name!r} as a motion: {_one_line(e)}") from None
    finally:
        parsing.add(-1)


def _onto_character(folder: Path, settings: dict, data: bytes, suffix: str, joint_map: str | tuple[str, bytes] | None,
                    name: str, parsing: _Count) -> dict[str, list[str]]:
    """A result's motions (``settings``: its ``generation.json``) on the uploaded character or rig, written
    beside them as ``--to_rig`` writes them (``read_rig``, then ``export_motion`` onto the rig: the same
    files, byte for byte), each named ``<motion>.<character>-<token>.<format>``, an FBX character's with its
    ``.glb`` beside it (Blender's glTF exporter, from the same keys: what the page plays); returns motion ->
    [the file, the .glb to view where it is another]. ``joint_map``: a registered map's name, or an uploaded
    YAML map as (its file name, its bytes). Runs on an upload thread."""
    from omg.export import export_motion, output_format
    from omg.io.fbx import one_blender_run
    from omg.retarget import load_joint_map, read_rig
    from omg.skeleton import get_skeleton

    stem = re.sub(r"[^\w\-]+", "_", Path(name).stem)[:40].strip("_") or "character"
    tag = f"{stem}-{secrets.token_hex(3)}"
    try:
        with tempfile.TemporaryDirectory(prefix="omg-upload-") as upload, \
                tempfile.TemporaryDirectory(prefix=".character-", dir=folder) as staged:
            path = Path(upload) / f"character{suffix}"
            path.write_bytes(data)
            if isinstance(joint_map, tuple):  # an uploaded map: read as --joint_map FILE reads one
                map_name, map_path = joint_map[0], Path(upload) / "joint_map.yaml"
                map_path.write_bytes(joint_map[1])
                try:
                    joint_map = load_joint_map(map_path)
                except UsageError as e:
                    raise UsageError(str(e).replace(str(map_path), map_name)) from None
            try:
                rig = read_rig(path, settings["skeleton"], joint_map)
            except UsageError as e:
                raise UsageError(str(e).replace(f"--to_rig {path}", name).replace(str(path), name)
                                 .replace(upload, "").replace("--joint_map", "joint_map")) from None
            except Exception as e:  # a garbled file the reader did not foresee is still the upload's fault
                raise UsageError(f"could not read the upload {name!r} as a character: {_one_line(e)}") from None
            format, written = output_format(None, rig.source), {}
            view = format == "fbx"  # the page's viewer plays glTF: an FBX character's motions come as .glb too
            with one_blender_run():  # onto an FBX character: the result's motions in one Blender run
                for record in settings["samples"]:
                    joints = np.load(folder / f"{record['file']}.joints.npy")
                    export_motion(Path(staged) / record["file"], joints, get_skeleton(settings["skeleton"]),
                                  settings["fps"], preview=False, rig=rig, joint_map=joint_map, format=format,
                                  view=view)
                    written[record["file"]] = [f"{record['file']}.{tag}.{kind}" for kind in (format, "glb")[: 1 + view]]
            for file, finals in written.items():  # named as --to_rig names it while written: the same bytes
                for final in finals:
                    os.replace(Path(staged) / f"{file}.{final.rsplit('.', 1)[1]}", folder / final)
            return written
    finally:
        parsing.add(-1)


class _Count:
    """A count shared by the event loop and the upload threads."""

    def __init__(self) -> None:
        self.n, self._lock = 0, threading.Lock()

    def add(self, k: int) -> None:
        with self._lock:
            self.n += k


def _sampler(card: GenerationCard, name: str) -> None:
    if not card.samplers:
        raise UsageError(f"sampler {name!r}: this model has no sampler to choose")
    if name not in card.samplers:
        raise UsageError(f"unknown sampler {name!r}; this model's: {', '.join(card.samplers)}")
    SAMPLERS.get(name)


def _length_message(card: GenerationCard, length: float) -> str:
    frames = length * card.fps
    return (f"length {length:g} s is {f'{frames:.0f}' if frames < 1e9 else 'too many'} frames; this model makes "
            f"{card.min_frames / card.fps:g}..{card.max_frames / card.fps:g} s "
            f"({card.min_frames}..{card.max_frames} frames at {card.fps:g} fps)")


def _check(card: GenerationCard, request: GenerationRequest, model: Model, length: float | None) -> None:
    """``check_request`` with the API's words for the CLI's flags."""
    try:
        check_request(card, request, f"model {model.name!r}")
    except UsageError as e:
        message = str(e)
        if length is not None and message.startswith("--length"):
            message = _length_message(card, length)
        for flag, field_ in (("--length", "length"), ("--steps", "steps"), ("--sampler", "sampler"),
                             ("--animal", "species"), ("--from_motion", "an uploaded motion (/v1/transfer)"),
                             ("--unconditional", "no prompts"), ("--timeline", "timeline")):
            message = message.replace(flag, field_)
        raise UsageError(message) from None


# -- results ------------------------------------------------------------------------------------------------------


@dataclass
class Results:
    """The results this server wrote under ``out``, oldest first. Each is kept ``ttl`` seconds and all of them
    in ``max_bytes``, the oldest dropped first (never the one just written); the ids dropped are remembered (a
    bounded number) to answer 410 rather than 404. Only these are served: other folders of ``out`` are not."""

    out: Path
    ttl: float
    max_bytes: int
    kept: OrderedDict = field(default_factory=OrderedDict)  # id -> (time.monotonic() when written, bytes)
    gone: OrderedDict = field(default_factory=OrderedDict)  # id -> why it was dropped
    total: int = 0

    def add(self, result: str, size: int) -> None:
        self.kept[result] = (time.monotonic(), size)
        self.total += size
        self.prune()

    def grow(self, result: str, size: int) -> None:
        """Files of ``size`` bytes added to a kept result (a character's animation)."""
        if result in self.kept:
            written, before = self.kept[result]
            self.kept[result] = (written, before + size)
            self.total += size
            self.prune()

    def prune(self) -> None:
        now = time.monotonic()
        while self.kept:
            result, (written, _) = next(iter(self.kept.items()))
            if now - written > self.ttl:
                self._drop(result, f"has expired: results are kept {self.ttl:g} s (--result_ttl)")
            elif self.total > self.max_bytes and len(self.kept) > 1:
                self._drop(result, f"was dropped to keep all results under {self.max_bytes / 2**20:g} MiB "
                                   "(--max_results_mb)")
            else:
                break

    def folder(self, result: str) -> Path | str | None:
        """The result's folder; why it is gone (410); None for an id this server never wrote (404)."""
        self.prune()
        return self.out / result if result in self.kept else self.gone.get(result)

    async def expire_every(self, seconds: float) -> None:
        """Expired results are removed from the disk also while no request comes."""
        while True:
            await asyncio.sleep(min(seconds, self.ttl))
            self.prune()

    def _drop(self, result: str, why: str) -> None:
        _, size = self.kept.pop(result)
        self.total -= size
        shutil.rmtree(self.out / result, ignore_errors=True)
        self.gone[result] = why
        while len(self.gone) > 100_000:
            self.gone.popitem(last=False)


def _result_path(out: Path, result: str, name: str) -> Path | None:
    """A file the server wrote, or None: names are checked, never joined blindly (no traversal)."""
    if not re.fullmatch(r"[0-9a-f]{12}", result) or not re.fullmatch(r"[\w][\w.\-]*", name) or ".." in name:
        return None
    path = out / result / name
    return path if path.is_file() and path.resolve().parent == (out / result).resolve() else None


# -- the guard in front of the app --------------------------------------------------------------------------------


class _BodyRefused(Exception):
    """Raised into the app's read of a body that is over its limit or too slow; the guard answers instead."""


class _Guard:
    """A pure-ASGI layer in front of the app, before FastAPI reads a byte of the body:

    - ``Host`` must name this server (``allowed_hosts``): a page of another site that rebinds its DNS name to
      127.0.0.1 sends its own name, and is refused (400);
    - a write (POST, ...) whose ``Origin`` (or, without one, ``Referer``) is another site's page is refused (403):
      a plain HTML form of any site could otherwise post to ``/v1/transfer``; requests without either (curl,
      scripts) are not a page's;
    - the POST routes' content types (415);
    - the body is counted as it streams in, chunked or with a ``Content-Length``: over its route's limit
      (the upload limit for ``/v1/transfer``, ``/v1/keyframes`` and a result's ``character``, the JSON limit for
      the others) the request is answered 413 and its connection closed, so the rest is never read; a body that has
      not arrived ``read_timeout`` seconds after the headers is answered 408 and closed."""

    def __init__(self, app, limits: Limits, hosts: frozenset[str]):
        self.app, self.limits, self.hosts = app, limits, hosts

    async def __call__(self, scope, receive, send) -> None:
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        headers = {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope["headers"]}
        limit, what = self._limit(scope["path"])
        refusal = self._refusal(scope, headers, limit, what)
        if refusal is not None:
            return await _send_error(send, *refusal)
        loop = asyncio.get_running_loop()
        deadline = loop.time() + self.limits.read_timeout
        seen, complete, refused, answered = 0, False, [], False

        async def receive_() -> dict:
            nonlocal seen, complete
            if refused:
                raise _BodyRefused
            if complete:  # the body is in: what comes now is the disconnect, whenever it comes
                return await receive()
            try:
                message = await asyncio.wait_for(receive(), max(deadline - loop.time(), 0.0))
            except asyncio.TimeoutError:
                refused.append((408, f"the request's body did not arrive within {self.limits.read_timeout:g} s"))
                raise _BodyRefused from None
            if message["type"] != "http.request":
                complete = True
                return message
            seen += len(message.get("body", b""))
            if seen > limit:
                refused.append((413, f"the request's body is larger than the {what}"))
                raise _BodyRefused
            complete = not message.get("more_body", False)
            return message

        async def send_(message: dict) -> None:
            nonlocal answered
            if refused:  # the app's own answer to the broken read (a 400) gives way to the refusal
                if not answered and message["type"] == "http.response.start":
                    answered = True
                    await _send_error(send, *refused[0])
                return
            await send(message)

        try:
            await self.app(scope, receive_, send_)
        except Exception:
            if not refused:
                raise
        if refused and not answered:
            await _send_error(send, *refused[0])

    def _limit(self, path: str) -> tuple[int, str]:
        if _upload_route(path):  # the file and a few form fields
            return (self.limits.max_upload_bytes + 2**16,
                    f"{self.limits.max_upload_bytes} bytes allowed for an upload (--max_upload_mb)")
        return self.limits.max_json_bytes, f"{self.limits.max_json_bytes} bytes allowed (--max_json_kb)"

    def _refusal(self, scope, headers: dict[str, str], limit: int, what: str) -> tuple[int, str] | None:
        host = headers.get("host")
        if "*" not in self.hosts and _host_name(host) not in self.hosts:
            return 400, (f"the Host {host!r} is not a name of this server; it answers to "
                         f"{', '.join(sorted(self.hosts))} (--allowed_hosts)")
        method, path = scope["method"], scope["path"]
        if method in WRITES:
            origin = headers.get("origin") or headers.get("referer")
            if origin is not None and not _same_origin(origin, host or ""):
                return 403, (f"a {method} from the page of {_origin(origin)!r} is refused: only this server's own "
                             "page may send one")
            kind = headers.get("content-type", "").split(";")[0].strip().lower()
            if method != "POST":
                pass
            elif path == "/v1/generate" and kind and not (kind == "application/json" or kind.endswith("+json")):
                return 415, f"{path} takes a JSON body (content-type: application/json), not {kind!r}"
            elif _upload_route(path) and kind != "multipart/form-data":
                return 415, f"{path} takes a multipart form (content-type: multipart/form-data), not {kind or 'none'!r}"
        length = headers.get("content-length", "")
        if length.isdigit() and int(length) > limit:
            return 413, f"the request's body is larger than the {what}"
        return None


def character_suffixes() -> list[str]:
    """The character and rig files this server reads: FBX only where Blender's module is there."""
    from omg.io.fbx import available

    return [s for s in RIG_SUFFIXES if s != ".fbx" or available()]


def _upload_route(path: str) -> bool:
    """The routes that take a multipart form with a file: a motion (UPLOAD_ROUTES), or a character for a result's
    motions."""
    return path in UPLOAD_ROUTES or re.fullmatch(r"/v1/results/[^/]+/character", path) is not None


async def _send_error(send, status: int, detail: str) -> None:
    """One line of JSON, and the connection closed: the rest of a refused body is never read."""
    body = json.dumps({"detail": _one_line(detail)}, ensure_ascii=True, separators=(",", ":")).encode("ascii")
    await send({"type": "http.response.start", "status": status,
                "headers": [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode()),
                            (b"connection", b"close")]})
    await send({"type": "http.response.body", "body": body})


def _host_name(host: str | None) -> str | None:
    """The name a Host header gives, lowercased, without its port ('[::1]:8000': '::1'); None if malformed."""
    host = (host or "").strip().lower()
    if host.startswith("["):
        end = host.find("]")
        return host[1:end] if end > 1 and host[end + 1:end + 2] in ("", ":") else None
    if host.count(":") > 1:  # IPv6 without brackets: no Host header a browser sends
        return None
    return host.split(":")[0] or None


def _origin(url: str) -> str:
    parts = urlsplit(url)
    return f"{parts.scheme}://{parts.netloc}" if parts.scheme and parts.netloc else url[:100]


def _same_origin(url: str, host: str) -> bool:
    """``url`` (an Origin or a Referer) is of this server's own page, the one at ``host`` (the Host header)."""
    parts = urlsplit(url.strip())
    if parts.scheme not in ("http", "https") or not parts.netloc:  # "null": a sandboxed or file:// page
        return False
    default = ":80" if parts.scheme == "http" else ":443"
    netloc, host = parts.netloc.lower().rsplit("@", 1)[-1], host.lower()
    return netloc.removesuffix(default) == host.removesuffix(default)


def _one_line(e: BaseException | str) -> str:
    text = " ".join(str(e).split()) or type(e).__name__
    return text if len(text) <= 300 else text[:297] + "..."


__all__ = ["LOOPBACK", "Batcher", "GenerateBody", "Limits", "Model", "Results", "create_app"]
