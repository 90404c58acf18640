"""The text-encoder interface: per-token features, a real-token mask and the end-of-text index.

Every encoder returns, per text, the features of its real tokens (start, words, end), the
last of which is the end-of-text (EOT) token that summarises the sentence. The base class
owns what they share: an LRU cache of those features keyed by text (on CPU, so a batch
encodes only its unseen captions), padding into a batch, the mask and the EOT index, and
staying frozen.
"""

from __future__ import annotations

import inspect
import warnings
from collections import OrderedDict
from collections.abc import Mapping
from dataclasses import dataclass, fields
from itertools import chain
from typing import Any, ClassVar, Sequence

import torch
from torch import Tensor, nn

from omg.errors import UsageError
from omg.registry import TEXT_ENCODERS
from omg.settings import set_fields


def bert_hidden_states(encoder: TextEncoder, texts: list[str]) -> tuple[Tensor, list[int]]:
    """A BERT encoder's last hidden states (B, n, D) of a batch and each text's token count; texts
    longer than the context are truncated (``[SEP]`` kept last) with a warning. ``encoder`` holds a
    ``tokenizers`` tokenizer (``tokenizer``) and a transformers ``BertModel`` (``model``)."""
    encodings = encoder.tokenizer.encode_batch(texts)
    for text, enc in zip(texts, encodings):
        if enc.overflowing:
            encoder._warn_truncated(text)
    lengths = [len(e.ids) for e in encodings]
    ids = torch.zeros(len(texts), max(lengths), dtype=torch.long)
    for b, enc in enumerate(encodings):
        ids[b, : len(enc.ids)] = torch.tensor(enc.ids)
    mask = (torch.arange(ids.shape[1]) < torch.tensor(lengths)[:, None]).long()
    hidden = encoder.model(input_ids=ids.to(encoder.device), attention_mask=mask.to(encoder.device)).last_hidden_state
    return hidden, lengths


@dataclass
class TextFeatures:
    """A batch of encoded texts; padding positions of ``tokens`` are zero."""

    tokens: Tensor  # (B, L, D) float32 per-token embeddings
    mask: Tensor  # (B, L) bool, True = a real token (start and end tokens included)
    eot: Tensor  # (B,) long, index of the end-of-text token: always the last real one

    def to(self, device: torch.device | str) -> TextFeatures:
        return TextFeatures(self.tokens.to(device), self.mask.to(device), self.eot.to(device))

    def trimmed(self) -> TextFeatures:
        """The same batch with L cut to its longest text: fixed-context encoders (CLIP) pad
        every text to 77 tokens, and what consumes the tokens (the MoC blocks) pays for every
        position, padded or not. Only padding is removed (itself when there is none)."""
        real = self.mask.any(0).nonzero()  # token positions real in some text
        length = int(real.max()) + 1 if len(real) else 0
        if len(self.eot):
            length = max(length, int(self.eot.max()) + 1)
        if length >= self.tokens.shape[1]:
            return self
        return TextFeatures(self.tokens[:, :length], self.mask[:, :length], self.eot)

    def padded(self, length: int) -> TextFeatures:
        """The same batch zero-padded to ``length`` tokens (as CLIP's fixed context pads it)."""
        extra = length - self.tokens.shape[1]
        if extra < 0:
            raise UsageError(f"cannot pad {self.tokens.shape[1]} tokens to {length}")
        tokens = torch.nn.functional.pad(self.tokens, (0, 0, 0, extra))
        return TextFeatures(tokens, torch.nn.functional.pad(self.mask, (0, extra)), self.eot)

    def eot_embedding(self) -> Tensor:
        """(B, D): the sentence summary, ``tokens[b, eot[b]]``."""
        return self.tokens[torch.arange(len(self.eot), device=self.eot.device), self.eot]


def encoding_spans(encoding) -> list[tuple[int, int]]:
    """A ``tokenizers`` Encoding's tokens as the (start, end) characters each covers, (0, 0) for special tokens."""
    return [(0, 0) if special else tuple(span) for span, special in zip(encoding.offsets, encoding.special_tokens_mask)]


class TextEncoder(nn.Module):
    """A frozen text encoder: ``encoder(texts) -> TextFeatures`` on the encoder's device.

    Subclasses set ``name``, ``dim`` and ``max_tokens``, implement ``_encode`` and call
    ``_freeze()`` once their weights are in place. ``pad_to_max`` pads every batch to
    ``max_tokens`` (fixed-context models) instead of to its longest text. A cached entry
    costs n_tokens x dim x 4 bytes (CLIP, 15 tokens: 46 KB). Built under a meta device
    context, an encoder is structure only and reads no weights.
    """

    name: ClassVar[str]
    dim: int
    max_tokens: int
    pad_to_max: ClassVar[bool] = False

    def __init__(self, cache_size: int = 100_000):
        super().__init__()
        if cache_size < 0:
            raise UsageError(f"{self.name}: cache_size must be >= 0 (0 disables the cache), got {cache_size}")
        self.cache_size = cache_size
        self._cache: OrderedDict[str, Tensor] = OrderedDict()  # text -> (n, D) float32 on CPU

    def _encode(self, texts: list[str]) -> list[Tensor]:
        """Distinct texts -> per text the (n_i, D) features of its real tokens, EOT last."""
        raise NotImplementedError

    def _freeze(self) -> None:
        self.requires_grad_(False)
        self.eval()

    def train(self, mode: bool = True) -> TextEncoder:
        return super().train(False)  # always eval: a parent's .train() must not enable dropout

    @property
    def device(self) -> torch.device:
        return next(chain(self.parameters(), self.buffers())).device

    def _warn_truncated(self, text: str) -> None:
        shown = text if len(text) <= 60 else text[:57] + "..."
        warnings.warn(f"{self.name}: prompt {shown!r} is longer than its {self.max_tokens}-token context; "
                      f"truncated to the first {self.max_tokens} tokens (the end-of-text token kept last)")

    def token_spans(self, text: str) -> list[tuple[int, int]] | None:
        """Per token of ``text``'s features (start and end tokens included), the (start, end)
        characters of ``text`` it covers, (0, 0) for special tokens; None where unknown. This
        default reads a ``tokenizers`` tokenizer held as ``tokenizer`` (the BERT encoders')."""
        try:
            from tokenizers import Tokenizer
        except ImportError:
            return None
        tokenizer = getattr(self, "tokenizer", None)
        if not isinstance(tokenizer, Tokenizer):
            return None
        return encoding_spans(tokenizer.encode(text))

    # no_grad, not inference_mode: the features feed trainable layers that save them for backward
    @torch.no_grad()
    def sentence_embedding(self, features: TextFeatures) -> Tensor:
        """(B, D) the encoder's sentence embedding of a batch it encoded: the EOT feature, unless the
        encoder has a projection of its own into a joint space (CLIP's ``encode_text``)."""
        return features.eot_embedding()

    def forward(self, texts: Sequence[str]) -> TextFeatures:
        if isinstance(texts, str):
            raise TypeError(f"{self.name} encodes a list of texts, got the single string {texts!r}")
        rows: dict[str, Tensor] = {}
        for text in texts:
            if text in self._cache:
                self._cache.move_to_end(text)
                rows[text] = self._cache[text]
        missing = [t for t in dict.fromkeys(texts) if t not in rows]
        if missing:
            for text, x in zip(missing, self._encode(missing), strict=True):
                # a copy with its own storage: a view would keep the whole batch alive in the cache
                rows[text] = x.to("cpu", torch.float32, copy=True)
                self._remember(text, rows[text])
        return self._collate([rows[t] for t in texts]).to(self.device)

    def _remember(self, text: str, x: Tensor) -> None:
        if self.cache_size == 0:
            return
        self._cache[text] = x
        while len(self._cache) > self.cache_size:
            self._cache.popitem(last=False)

    def _collate(self, rows: list[Tensor]) -> TextFeatures:
        lengths = torch.tensor([len(x) for x in rows], dtype=torch.long)
        length = self.max_tokens if self.pad_to_max else max(map(len, rows), default=0)
        tokens = torch.zeros(len(rows), length, self.dim)
        for b, x in enumerate(rows):
            tokens[b, : len(x)] = x
        mask = torch.arange(length) < lengths[:, None]
        return TextFeatures(tokens, mask, lengths - 1)


def building_on_meta() -> bool:
    """Inside ``with torch.device("meta")`` (config tests): build the structure, read no weights."""
    return torch.get_default_device().type == "meta"


@dataclass(frozen=True)
class TextEncoderArgs:
    """The keyword arguments of omg's registered text encoders (``model.init_args.text_encoder_args``);
    each unset (None) is the encoder's default, and the encoder is given the keys that are set."""

    pretrained: str | None = None  # clip-vit-l-14: an open_clip tag or a local ViT-L-14 weights file (default openai)
    quick_gelu: bool | None = None  # clip-vit-l-14: None: the tag's
    model_dir: str | None = None  # bge-base-en-v1.5: its snapshot folder
    side_gain: float | None = None  # minilm: the side words' gain (0: off)
    dim: int | None = None  # hash: width ...
    max_tokens: int | None = None  # ... tokens per text ...
    vocab_size: int | None = None  # ... hashed vocabulary ...
    seed: int | None = None  # ... and its seed
    cache_size: int | None = None  # every encoder: texts whose features are kept
    # a plugin encoder's own keyword arguments (omg.registry.TEXT_ENCODERS), given to it as they are
    options: dict[str, Any] | None = None


def text_encoder_kwargs(args: TextEncoderArgs | Mapping | None) -> dict[str, Any]:
    """``args`` (a ``TextEncoderArgs``, a checkpoint's mapping or None) as ``build_text_encoder``'s keyword
    arguments, ``options`` among them. A mapping's keys that name no field are a plugin encoder's, as
    checkpoints written before the typed groups keep them: they count as ``options``."""
    if isinstance(args, Mapping):
        known = {f.name for f in fields(TextEncoderArgs)}
        if extra := {k: v for k, v in args.items() if k not in known}:
            options = {**(args.get("options") or {}), **extra}
            args = {**{k: v for k, v in args.items() if k in known}, "options": options}
    kwargs = set_fields(TextEncoderArgs, args, "model.init_args.text_encoder_args")
    options = kwargs.pop("options", None) or {}
    return {**kwargs, **options}


def build_text_encoder(spec: str | TextEncoder, **kwargs: Any) -> TextEncoder:
    """A text encoder by registered name (``clip-vit-l-14``, ``minilm``, ``hash``, a plugin's), or the instance
    itself. An argument the encoder does not take is one line naming it."""
    if isinstance(spec, TextEncoder):
        if kwargs:
            raise UsageError(f"text encoder given as a built {spec.name!r} instance; cannot apply {sorted(kwargs)}")
        return spec
    factory = TEXT_ENCODERS.get(spec)
    try:
        inspect.signature(factory).bind(**kwargs)
    except TypeError as e:  # an argument of another encoder, or a misspelt one
        raise UsageError(f"text encoder {spec!r}: {e} (model.init_args.text_encoder_args)") from None
    except ValueError:  # no signature to read (a builtin): let the call say
        pass
    return factory(**kwargs)
