"""``omg bench sides``: whether left and right survive in the text features."""

from __future__ import annotations

import json
from pathlib import Path

from omg.errors import UsageError


def _encoder_spec(spec: str):
    """``NAME`` or ``NAME:key=value,...`` (values read as YAML: ``minilm:side_gain=2``) -> the encoder."""
    import yaml

    from omg.text import build_text_encoder

    name, _, options = spec.partition(":")
    kwargs = {}
    for item in filter(None, options.split(",")):
        key, eq, value = item.partition("=")
        if not eq or not key.strip():
            raise UsageError(f"--encoders: {spec!r}: options are key=value pairs, as in minilm:side_gain=2")
        kwargs[key.strip()] = yaml.safe_load(value)
    return build_text_encoder(name.strip(), **kwargs)


def _prompt_set_captions(prompts: str) -> list[tuple[str, str]]:
    """(text, action) of a prompt file's prompts: the action is the prompt's targets, the angle left out
    ("turns left" and "makes a 90 degree turn to the left" are one action)."""
    from omg.metrics.following import load_prompts

    entries = load_prompts(None if prompts == "following" else prompts)

    def action(targets) -> str:
        return "; ".join(", ".join(f"{k}: {v}" for k, v in sorted(t.items()) if k != "angle") for t in targets)

    return [(e["text"], action(e["targets"])) for e in entries]


def bench_sides(manifests: tuple[Path, ...] = (), prompts: str | None = "following",
                encoders: tuple[str, ...] = ("minilm",)) -> list[dict]:
    """Does sidedness survive in the text features? For each text encoder and each set of captions,
    the cosine distance between every caption that names a side and its mirror image (left <->
    right), against the distance to captions of other actions and to other captions of the same
    action (other styles, paraphrases): ``omg.text.sides.side_separation``, for the sentence (EOT)
    feature, the mean of the token features, the token sets (Chamfer) and the side word's own token.
    Prints one Markdown row per (captions, encoder, feature); its ``ratio`` reads "left/right pairs
    are <ratio> as far apart as different actions".

    Args:
        manifests: clip manifests (``{"clips": [{texts, labels: {content}}]}``), e.g.
            ../shared/data/bandai1/manifest.json, read together as one set of captions; the action of a
            caption is its clip's content label
        prompts: a prompt file (``omg.metrics.following``) read as a second set, the action of a prompt
            being its targets: ``following`` for the built-in set, ``none`` for none
        encoders: registered text encoders (minilm, clip-vit-l-14, bge, hash), a list such as [minilm, hash];
            ``NAME:key=value,...`` passes options (``minilm:side_gain=2``)

    Returns:
        One row per (captions, encoder, feature): side, same_action, action, ratio, same_ratio, rank,
        captions.
    """
    from omg.files import MANIFEST_MAX_BYTES, read_file
    from omg.text.sides import side_separation

    sets = []
    if manifests:
        captions = []
        for path in manifests:
            try:
                clips = json.loads(read_file(path, "", MANIFEST_MAX_BYTES))["clips"]
            except (OSError, ValueError, KeyError, TypeError) as e:  # ValueError: also read_file's UsageError
                raise UsageError(f"--manifests: {path} is not a clip manifest ({{\"clips\": [...]}}): {e}") from None
            captions += [(t, str((c.get("labels") or {}).get("content", t)))
                         for c in clips for t in c.get("texts") or []]
        sets.append(("manifests", "manifests", captions))
    if prompts is not None and str(prompts).lower() != "none":
        sets.append(("prompt set", "prompts", _prompt_set_captions(str(prompts))))
    if not sets:
        raise UsageError("--manifests or --prompts: no captions to measure")
    rows = []
    print("| captions | encoder | feature | sided captions | d(left, right) | d(same action) "
          "| d(other action) | ratio to other action | ratio to same action | other actions nearer than the mirror |"
          "\n|---|---|---|---:|---:|---:|---:|---:|---:|---:|")
    for spec in encoders:
        encoder = _encoder_spec(spec)
        for label, option, captions in sets:
            try:
                result = side_separation(encoder, captions)
            except ValueError as e:
                raise UsageError(f"--{option}: {e}") from None
            for feature, r in result.items():
                rows.append({"captions": label, "encoder": spec, "feature": feature, **r})
                print(f"| {label} | {spec} | {feature} | {r['captions']} | {r['side']:.4f} | {r['same_action']:.4f} "
                      f"| {r['action']:.4f} | {r['ratio']:.3f} | {r['same_ratio']:.3f} | {r['rank']:.3f} |",
                      flush=True)
    return rows
