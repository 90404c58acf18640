"""``clip-vit-l-14``: the CLIP ViT-L/14 text tower (open_clip), OMG's text encoder.

Token features are the transformer's output after ``ln_final`` (before the projection into
the joint image-text space), 768-d over a 77-token context: what OMG's ControlNet reads. The EOT
token (the highest id, where open_clip pools) summarises the sentence; ``sentence_embedding``
projects it into the joint image-text space, CLIP's ``encode_text`` (768-d for ViT-L/14): the
"CLIP feature" OmniMotionGPT uses. Only the text tower is built: 124M parameters instead of
CLIP's 428M.
"""

from __future__ import annotations

import os
from contextlib import nullcontext

import torch
from torch import Tensor

from omg.errors import UsageError
from omg.registry import TEXT_ENCODERS
from omg.text.base import TextEncoder, TextFeatures, building_on_meta

ARCH = "ViT-L-14"
CONFIG_KEY = "model.init_args.text_encoder_args.pretrained"


@TEXT_ENCODERS.register("clip-vit-l-14")
class ClipTextEncoder(TextEncoder):
    """CLIP ViT-L/14 text tower (open_clip): 768-d token features after ln_final, 77 tokens, and the
    sentence embedding of ``encode_text`` (``sentence_embedding``).

    Args:
        pretrained: a local checkpoint file (a state dict or open_clip checkpoint of the full
            CLIP model or of the text tower alone; .pt/.bin/.safetensors, OpenAI's TorchScript
            file too), or an open_clip tag ("openai", "laion2b_s32b_b82k", ...) fetched from
            the network or the Hugging Face cache. None: random weights (tests only).
        quick_gelu: the activation the weights were trained with; None takes the tag's, and
            for a file assumes OpenAI's weights (QuickGELU), which OMG uses. Set False for
            LAION/DataComp ViT-L-14 files.
        cache_size: captions whose features are kept (LRU, on CPU).
    """

    name = "clip-vit-l-14"
    dim = 768
    max_tokens = 77
    pad_to_max = True  # CLIP's fixed context

    def __init__(self, pretrained: str | None = "openai", quick_gelu: bool | None = None,
                 cache_size: int = 100_000):
        super().__init__(cache_size)
        import open_clip  # heavy (timm, torchvision): only when a CLIP encoder is built
        from open_clip.model import _build_text_tower  # open_clip builds the tower alone only here

        tag = {} if pretrained is None or os.path.isfile(pretrained) else open_clip.get_pretrained_cfg(ARCH, pretrained)
        if quick_gelu is None:
            quick_gelu = tag.get("quick_gelu", False) if tag else True
        # find the file first: a missing one fails at once, not after building the tower
        path = None if pretrained is None or building_on_meta() else _weights_file(pretrained, tag)
        cfg = open_clip.get_model_config(ARCH)
        # with its text projection: token features come before it, the sentence embedding after it. The file's
        # tensors replace every weight, so the tower is built on the meta device and takes them, instead of
        # drawing 124M random values first (1.6 s of a CPU core)
        with torch.device("meta") if path is not None else nullcontext():
            self.tower = _build_text_tower(cfg["embed_dim"], cfg["text_cfg"], quick_gelu)
        if path is not None:
            _load_tower(self.tower, path)
            if self.tower.attn_mask is not None:  # not saved (a non-persistent buffer): made as open_clip makes it
                self.tower.register_buffer("attn_mask", self.tower.build_causal_mask(), persistent=False)
        self.tokenizer = open_clip.get_tokenizer(ARCH)
        self._freeze()

    def token_ids(self, text: str) -> list[int]:
        """open_clip's tokenization: [SOT] bpe... [EOT], truncated with EOT kept last."""
        tok = self.tokenizer
        ids = [tok.sot_token_id] + tok.encode(text) + [tok.eot_token_id]
        if len(ids) > self.max_tokens:
            self._warn_truncated(text)
            ids = ids[: self.max_tokens - 1] + [tok.eot_token_id]
        return ids

    def sentence_embedding(self, features: TextFeatures) -> Tensor:
        """(B, 768) CLIP's sentence embedding, ``encode_text`` (unnormalised): the EOT feature projected."""
        eot = features.eot_embedding().to(self.device)
        projection = self.tower.text_projection
        return projection(eot) if isinstance(projection, torch.nn.Linear) else eot @ projection

    def _encode(self, texts: list[str]) -> list[Tensor]:
        ids = [self.token_ids(t) for t in texts]
        # the causal mask makes positions past the longest text irrelevant: run only up to it
        n = max(map(len, ids))
        batch = torch.zeros(len(ids), n, dtype=torch.long)
        for b, row in enumerate(ids):
            batch[b, : len(row)] = torch.tensor(row)
        tower = self.tower
        x = tower.token_embedding(batch.to(self.device)) + tower.positional_embedding[:n]  # (B, n, D)
        x = tower.transformer(x, attn_mask=tower.attn_mask[:n, :n])
        x = tower.ln_final(x)
        return [x[b, : len(row)] for b, row in enumerate(ids)]


def _weights_file(pretrained: str, tag: dict) -> str:
    """``pretrained`` as a local file: itself, or the open_clip tag's download (or HF cache entry)."""
    import open_clip

    if os.path.isfile(pretrained):
        return pretrained
    if not tag:
        tags = ", ".join(open_clip.list_pretrained_tags_by_model(ARCH))
        raise UsageError(f"clip-vit-l-14: {CONFIG_KEY}={pretrained!r} is neither a file nor an open_clip "
                         f"{ARCH} tag ({tags})")
    try:
        return open_clip.download_pretrained(tag)
    except Exception as e:  # noqa: BLE001 - offline shows up as many error types; re-raised as one line
        raise UsageError(
            f"clip-vit-l-14 needs its weights: set {CONFIG_KEY} to a local open_clip {ARCH} checkpoint file; "
            f"could not download {pretrained!r} (no network? {type(e).__name__})"
        ) from e


def _load_tower(tower: torch.nn.Module, path: str) -> None:
    """Load the text-tower weights out of a CLIP (or text-tower-only) checkpoint file."""
    from open_clip.factory import load_state_dict  # unwraps "state_dict", "module.", TorchScript

    try:
        state = load_state_dict(path)
    except Exception as e:  # noqa: BLE001 - any unreadable file is the user's to fix
        raise UsageError(f"clip-vit-l-14: cannot read {CONFIG_KEY}={path!r}: {e}".splitlines()[0]) from e
    # CustomTextCLIP checkpoints nest the tower under "text."; CLIP ones keep it at the top level
    state = {k.removeprefix("text."): v for k, v in state.items()}
    wanted = tower.state_dict()
    if missing := [k for k in wanted if k not in state]:
        raise UsageError(f"clip-vit-l-14: {path} is not an open_clip {ARCH} checkpoint: it lacks "
                         f"{len(missing)} text-tower weights, e.g. {missing[:3]}")
    try:  # the file's tensors, in the tower's dtype (OpenAI's file is fp16), become its weights (``assign``)
        tower.load_state_dict({k: state[k].to(wanted[k].dtype) for k in wanted}, assign=True)
    except RuntimeError as e:
        raise UsageError(f"clip-vit-l-14: {path} does not fit {ARCH}'s text tower: "
                         f"{' '.join(str(e).split())[:300]}") from e
