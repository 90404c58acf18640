"""Text encoders (registered by name on import): ``clip-vit-l-14`` (open_clip), ``minilm``
(offline default of the mini configs) and ``hash`` (unit tests)."""

from omg.text import clip, hashed, minilm  # noqa: F401  (registers the encoders)
from omg.text.base import TextEncoder, TextEncoderArgs, TextFeatures, build_text_encoder, text_encoder_kwargs
from omg.text.clip import ClipTextEncoder
from omg.text.hashed import HashTextEncoder
from omg.text.minilm import MiniLMTextEncoder

__all__ = ["TextEncoder", "TextEncoderArgs", "TextFeatures", "build_text_encoder", "text_encoder_kwargs",
           "ClipTextEncoder", "HashTextEncoder",
           "MiniLMTextEncoder"]
