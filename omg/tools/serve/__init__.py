"""``omg serve``: a local server with a page and an HTTP API over trained checkpoints of any family.

The checkpoints are loaded once; each model's generation card (``omg.generation``) tells the
page and ``GET /v1/models`` what it takes. ``POST /v1/generate`` and ``POST /v1/transfer`` answer
with the motions' joints and links to the files ``omg generate`` writes (``omg.generation.write``);
the page plays them in a three.js skeleton viewer shipped in ``static/vendor`` (nothing is fetched
from elsewhere). docs/guide/serving.md gives the routes and ``curl`` examples.
"""

from __future__ import annotations

import ipaddress
import logging
import re
import socket
import tempfile
from pathlib import Path

import torch

from omg.errors import UsageError
from omg.files import check_output_dir
from omg.tools.args import PositiveFiniteFloat, PositiveInt, repeated, run
from omg.tools.generate import resolve_device


def load_models(ckpts: list[Path], human_ckpt: Path | None, device: torch.device, ema: bool = True) -> list:
    """Each checkpoint as a ``Model`` named by its file (``last`` by its run folder), with the
    ``--human_ckpt`` module for the cards that take a source generator."""
    from omg.generation.registry import generator_for
    from omg.lit.checkpoint import load_module
    from omg.lit.pretrain import PretrainModule
    from omg.tools.serve.app import Model

    human = None
    if human_ckpt is not None:
        human = generator_for(load_module(human_ckpt), human_ckpt).to(device)
        if "text" not in human.generation_card().inputs:
            raise UsageError(f"--human_ckpt {human_ckpt} does not generate from prompts")
    models, names = [], set()
    for ckpt in ckpts:
        generator = generator_for(load_module(ckpt, default_class=PretrainModule, use_ema=ema), ckpt).to(device)
        card = generator.generation_card()
        name = _name(ckpt, names)
        names.add(name)
        models.append(Model(name=name, ckpt=str(ckpt), generator=generator, card=card,
                            source_module=human if card.source_generator else None))
    if human is not None and not any(m.source_module is not None for m in models):
        raise UsageError("--human_ckpt: no --ckpt takes a second checkpoint for its source motion (OmniMotionGPT)")
    return models


def model_rigs(models: list, to_rig: Path | None, joint_map: str | None) -> dict:
    """The ``--to_rig`` rig for each model skeleton it fits (a human character for the human models); one
    line where it fits none of them (the reason its first skeleton gave)."""
    from omg.retarget import read_rig

    if to_rig is None:
        return {}
    rigs, refusals = {}, []
    for skeleton in dict.fromkeys(m.card.skeleton for m in models):
        try:
            rigs[skeleton] = read_rig(to_rig, skeleton, joint_map)
        except UsageError as e:
            refusals.append(e)
    if not rigs:
        raise refusals[0]
    return rigs


def _name(ckpt: Path, taken: set[str]) -> str:
    path = Path(ckpt)
    stem = path.stem if path.stem not in ("last", "model", "checkpoint") else path.parent.parent.name or path.stem
    name, n = stem, 2
    while name in taken:
        name, n = f"{stem}-{n}", n + 1
    return name


def serve(
    *,
    ckpt: list[Path],
    human_ckpt: Path | None = None,
    host: str = "127.0.0.1",
    port: int = 8000,
    device: str | None = None,
    ema: bool = True,
    max_batch: PositiveInt = 16,
    max_wait: PositiveFiniteFloat = 0.05,
    max_samples: PositiveInt = 16,
    max_upload_mb: PositiveFiniteFloat = 20.0,
    max_json_kb: PositiveFiniteFloat = 64.0,
    read_timeout: PositiveFiniteFloat = 60.0,
    result_ttl: PositiveFiniteFloat = 3600.0,
    max_results_mb: PositiveFiniteFloat = 1024.0,
    allowed_hosts: list[str] | None = None,
    out: Path | None = None,
    to_rig: Path | None = None,
    joint_map: str | None = None,
    command: str = "",
) -> None:
    """Serve checkpoints on a local page and HTTP API (FastAPI on uvicorn) until Ctrl-C or SIGTERM.

    Args:
        ckpt: checkpoints to load, of any family that generates motion (repeat --ckpt for several)
        human_ckpt: a text-to-motion checkpoint (OMG ControlNet) that makes the human source motion of the
            checkpoints that take one (OmniMotionGPT: the OMG -> animal chain)
        host: address to bind (127.0.0.1: this machine only)
        port: port to listen on
        device: cpu, cuda, cuda:N or mps (default: cuda when available, else cpu)
        ema: use the EMA of the weights (--no_ema: the trained weights)
        max_batch: most motions sampled in one call (requests that arrive together are batched)
        max_wait: seconds a request waits for others to be batched with
        max_samples: most motions one request may ask for
        max_upload_mb: largest upload in MiB (counted as the body arrives, chunked or not: 413 beyond it)
        max_json_kb: largest JSON request body in KiB
        read_timeout: seconds a request's headers may take to arrive (the connection is closed after) and,
            from them on, its body (408 and the connection closed after)
        result_ttl: seconds a result's files are kept (then 410)
        max_results_mb: MiB of all results' files together; the oldest results are dropped first
        allowed_hosts: names a request's Host header may give besides the address bound (and this machine's
            loopback names when that is a loopback or wildcard address); * for any. Other names are refused:
            a web page cannot reach the server by rebinding its DNS name to it
        out: folder the results are written to (default: a temporary folder removed at exit)
        to_rig: write each result's motions onto this rig as well, for the models whose skeleton it fits: a BVH
            file's (sample_NNN.bvh on the rig), a skinned glTF character (.glb, .gltf: sample_NNN.glb, the
            character with the animation added) or an FBX character (.fbx: sample_NNN.fbx, the same, written
            by Blender: pip install 'omg[fbx]'), linked from each motion's files
        joint_map: the rig's joint map for --to_rig (a registered name or a YAML file; default: detected)
        command: the command line (unused; kept for the command's record)
    """
    import uvicorn

    from omg.tools.serve.app import Limits, create_app

    if not ckpt:
        raise UsageError("give at least one --ckpt")
    if not 0 <= port <= 65535:
        raise UsageError(f"--port {port}: give a port in 0..65535")
    hosts = host_names(host, allowed_hosts)
    if out is not None:  # before the checkpoints load: a file or /proc is one line, not a traceback later
        out = check_output_dir(out, "--out")
    device = resolve_device(device or ("cuda" if torch.cuda.is_available() else "cpu"))
    if joint_map is not None and to_rig is None:
        raise UsageError("--joint_map names the map of the --to_rig rig; give --to_rig RIG (.bvh, .glb, .gltf, "
                         ".fbx) with it")
    models = load_models(ckpt, human_ckpt, device, ema)
    rigs = model_rigs(models, to_rig, joint_map)
    temporary = out is None
    results = Path(tempfile.mkdtemp(prefix="omg-serve-")) if temporary else Path(out)
    limits = Limits(max_batch=max_batch, max_wait=max_wait, max_samples=max_samples,
                    max_upload_bytes=int(max_upload_mb * 2**20), max_json_bytes=int(max_json_kb * 2**10),
                    read_timeout=read_timeout, result_ttl=result_ttl,
                    max_results_bytes=int(max_results_mb * 2**20))
    app = create_app(models, results, limits, remove_out=temporary, allowed_hosts=hosts, rigs=rigs,
                     joint_map=joint_map)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    print(f"omg serve: {', '.join(m.name for m in models)} on http://{host}:{port}/ (results in {results})",
          flush=True)
    # uvicorn finishes the requests in flight on Ctrl-C / SIGTERM, runs the app's shutdown, then re-raises the signal
    uvicorn.Server(server_config(app, host, port, read_timeout, log_level="info", timeout_graceful_shutdown=600)).run()


def server_config(app, host: str, port: int, read_timeout: float, **options):
    """uvicorn's config for ``app``, whose connections must send a request's headers within ``read_timeout``
    seconds of opening (or of the previous answer, kept alive): uvicorn bounds neither, so a client
    trickling its headers held a connection for good. The body has its own bound (``app.Limits``)."""
    import uvicorn

    return uvicorn.Config(app, host=host, port=port, http=headers_within(read_timeout), **options)


def headers_within(seconds: float) -> type:
    """uvicorn's HTTP protocol class, closing a connection whose next request's headers have not all arrived
    ``seconds`` after it opened or after its previous answer (the time a request is served is not counted)."""
    from uvicorn.protocols.http.auto import AutoHTTPProtocol

    class HeadersWithin(AutoHTTPProtocol):
        def connection_made(self, transport) -> None:
            super().connection_made(transport)
            self._expect_headers()

        def on_response_complete(self) -> None:
            super().on_response_complete()
            self._expect_headers()

        def _expect_headers(self) -> None:
            answered = self.cycle  # uvicorn starts a new cycle when a request's headers are complete

            def expire() -> None:
                if self.cycle is answered and not self.transport.is_closing():
                    self.transport.close()

            self.loop.call_later(seconds, expire)

    return HeadersWithin


def host_names(host: str, allowed: list[str] | None) -> tuple[str, ...]:
    """The names a request's Host may give: the address bound; this machine's loopback names when it is a
    loopback or wildcard address (and its host names for a wildcard); ``--allowed_hosts``."""
    from omg.tools.serve.app import LOOPBACK

    names = [host]
    wildcard = host.strip("[]") in ("0.0.0.0", "::", "")
    try:
        loopback = ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        loopback = host.lower() == "localhost"
    if loopback or wildcard:
        names += LOOPBACK
    if wildcard:
        names += [socket.gethostname(), socket.getfqdn()]
    for name in allowed or []:
        if not re.fullmatch(r"\*|[A-Za-z0-9_.\-]+|\[?[0-9A-Fa-f:.]+\]?", name) or name.endswith(":"):
            raise UsageError(f"--allowed_hosts {name!r}: give host names or addresses without a port or scheme "
                             "(example.org, 192.168.1.5), or * for any")
        names.append(name)
    return tuple(dict.fromkeys(n.lower().strip("[]") for n in names))


def main(argv: list[str]) -> None:
    run(serve, repeated(argv, "--ckpt"), "omg serve")
