"""OmniMotionGPT (CVPR 2024, "Animal Motion Generation with Limited Data"): joint-aware motion
autoencoders for humans (SMPL-22) and animals (SMAL-35), aligned through a text space.

Per frame the motion is the ``maa`` representation seen as J + 1 tokens of 6 numbers: the J
joints' local rotations (6D; the root's is the global rotation) and the root translation padded
to 6. The static part S is the (J, 3) bone offsets, zero-padded to (J + 1, 3).

``MotionAutoencoder`` (one per domain, §3.1): a joint transformer over each pose's tokens (pose ⊕
offsets) -> F_j, a second joint transformer over the offsets -> F_o, a temporal transformer over
frames of F_j ⊕ F_o, temporal pooling by l and primal-joint pooling to Z (B, T/l, 7, C_j). The
decoder mirrors it with the target's offsets. ``LatentTextEncoder`` E_t maps Z to the sentence
feature; ``LatentTextDecoder`` D_t maps (sentence feature, Z) back to a latent (§3.1-3.2).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace

import torch
from torch import Tensor, nn

from omg.errors import UsageError
from omg.models.positions import sinusoidal_positions
from omg.motion import Representation
from omg.rotations import matrix_to_6d, sixd_to_matrix
from omg.settings import overrides
from omg.skeleton import Skeleton

NUM_PRIMAL = 7  # root, both leg ends, head, both arm (front leg) ends, chest branch point


@dataclass(frozen=True)
class OmniMotionConfig:
    """Sizes of the OmniMotionGPT networks; ``paper`` is §5's implementation details (see configs/omgpt.yaml)."""

    name: str = "paper"
    joint_dim: int = 16  # joint transformers: width 16 ...
    joint_layers: int = 2  # ... 2 layers
    joint_heads: int = 4  # not given in the paper
    temporal_dim: int = 256  # temporal transformers: width 256 ...
    temporal_layers: int = 2  # ... 2 layers
    temporal_heads: int = 4  # not given in the paper
    pool: int = 4  # temporal pooling l = 4: Z is 49 x 7 x 16 for 196 frames
    max_frames: int = 196  # the longest clip (HumanML3D / AnimalML3D: 196 frames at 20 fps)
    latent_dim: int = 256  # latent decoder D_t: causal transformer decoder, width 256 ...
    latent_layers: int = 4  # ... 4 layers
    latent_heads: int = 4  # not given in the paper
    # Off: D_t as the paper describes it (§3.1), a causal decoder reading Z and C. On (omg's variant,
    # configs/omgpt_variant.yaml): a GPT, latent frame t predicted from C and the frames before t (input
    # shifted right by one, C's projection as the start token); unshifted, it can copy each frame and ignore C.
    latent_shift: bool = False
    # Off: the root's translation as maa holds it, absolute positions (the paper, §3.1). On (omg's variant):
    # the autoencoders see the horizontal translation (x, z) as per-frame displacement, summed back on
    # decoding. Clips wander metres, so a decoder's small error on absolute positions is centimetres of jitter
    # every frame; on displacements it is smooth drift.
    root_velocity: bool = False
    dropout: float = 0.1

    @property
    def latent_frames(self) -> int:
        return math.ceil(self.max_frames / self.pool)

    @classmethod
    def from_name(cls, name: str, **overrides) -> OmniMotionConfig:
        if name not in PRESETS:
            raise UsageError(f"unknown OmniMotionGPT flavor {name!r}; known: {', '.join(PRESETS)}")
        known = {f.name for f in fields(cls)} - {"name"}
        if unknown := set(overrides) - known:
            raise UsageError(f"unknown model.config field(s) {sorted(unknown)}; fields: {', '.join(sorted(known))}")
        return replace(cls(name=name, **PRESETS[name]), **overrides)


PRESETS: dict[str, dict] = {
    "paper": {},
    # CPU minutes: one layer per joint / temporal transformer, narrower temporal and latent ones
    "mini": {"joint_layers": 1, "joint_heads": 2, "temporal_dim": 64, "temporal_layers": 1, "latent_dim": 64,
             "latent_layers": 2, "dropout": 0.0},
}

# model.init_args.config of OmniMotionModule: OmniMotionConfig's fields, each None (unset) the flavor's value
OmniMotionOverrides = overrides(OmniMotionConfig, "OmniMotionOverrides", __name__,
                                doc="OmniMotionConfig fields to override in the flavor's (unset: the flavor's value).")


# -- primal joints ----------------------------------------------------------------------------

def primal_joints(skeleton: Skeleton) -> tuple[int, ...]:
    """The 7 primal joints of ``skeleton`` in the semantic order shared by all skeletons: root,
    left and right leg ends (an animal's hind feet), head, left and right arm ends (front feet),
    chest branch point.

    They are found from the graph: the joints of degree ≠ 2 (branch points and leaves) among which
    the end effectors lie, plus the root and the chest, the branch point (degree ≥ 3) below the
    most end effectors. The head is the upper end effector nearest the midline; left lies
    towards +X (the rest pose faces +Z). Leaves with no human counterpart (tail, ears, mouth) are
    not kept: the 7 are those both skeletons share.
    """
    J = skeleton.num_joints
    degree = [len(skeleton.children(j)) + (skeleton.parents[j] >= 0) for j in range(J)]
    candidates = {j for j in range(J) if degree[j] != 2}
    effectors = list(skeleton.end_effectors)
    if len(effectors) != 5 or not set(effectors) <= candidates:
        raise ValueError(f"skeleton {skeleton.name!r}: primal-joint pooling needs 5 end effectors of degree != 2 "
                         f"(leaf or branch joints), got {effectors}")

    def ancestors(j: int) -> set[int]:
        out = set()
        while (j := skeleton.parents[j]) >= 0:
            out.add(j)
        return out

    branches = [j for j in candidates if j != 0 and degree[j] >= 3]
    below = {j: sum(j in ancestors(e) for e in effectors) for j in branches}
    if not below or max(below.values()) < 2:
        raise ValueError(f"skeleton {skeleton.name!r}: no chest branch point above the end effectors")
    chest = min((j for j in branches if below[j] == max(below.values())), key=lambda j: len(ancestors(j)))
    x = skeleton.rest_positions()[:, 0]
    upper = [e for e in effectors if chest in ancestors(e) or e == chest]
    lower = [e for e in effectors if e not in upper]
    if len(upper) != 3 or len(lower) != 2:
        raise ValueError(f"skeleton {skeleton.name!r}: expected 3 end effectors above the chest and 2 below, "
                         f"got {upper} and {lower}")
    head = min(upper, key=lambda e: abs(x[e]))
    arms = sorted((e for e in upper if e != head), key=lambda e: -x[e])  # left (+X) first
    legs = sorted(lower, key=lambda e: -x[e])
    return (0, legs[0], legs[1], head, arms[0], arms[1], chest)


# -- building blocks ----------------------------------------------------------------------------

def transformer(width: int, heads: int, layers: int, dropout: float) -> nn.TransformerEncoder:
    layer = nn.TransformerEncoderLayer(width, heads, 4 * width, dropout, activation="gelu", batch_first=True,
                                       norm_first=True)
    return nn.TransformerEncoder(layer, layers, enable_nested_tensor=False)


def pooled_mask(mask: Tensor, pool: int) -> Tensor:
    """(B, T) real frames -> (B, ceil(T / pool)) latent frames holding at least one real frame."""
    T = mask.shape[1]
    padded = nn.functional.pad(mask, (0, -T % pool))
    return padded.unflatten(1, (-1, pool)).any(-1)


def as_tokens(features: Tensor) -> Tensor:
    """maa features (B, T, (J + 1)·6) -> tokens (B, T, J + 1, 6)."""
    return features.unflatten(-1, (-1, 6))


def padded_offsets(offsets: Tensor) -> Tensor:
    """(B, J, 3) bone offsets -> (B, J + 1, 3), a zero row for the translation token."""
    return nn.functional.pad(offsets, (0, 0, 0, 1))


class JointTokens(nn.Module):
    """A shared joint transformer over the J + 1 tokens of one pose (or of the offsets)."""

    def __init__(self, in_dim: int, tokens: int, config: OmniMotionConfig):
        super().__init__()
        self.embed = nn.Linear(in_dim, config.joint_dim)
        self.joint_code = nn.Parameter(torch.randn(tokens, config.joint_dim) * 0.02)
        self.blocks = transformer(config.joint_dim, config.joint_heads, config.joint_layers, config.dropout)

    def forward(self, x: Tensor) -> Tensor:  # (..., J + 1, in_dim) -> (..., J + 1, C_j)
        lead = x.shape[:-2]
        h = self.embed(x) + self.joint_code
        return self.blocks(h.reshape(-1, *h.shape[-2:])).reshape(*lead, *h.shape[-2:])


class TemporalTokens(nn.Module):
    """A temporal transformer over frames of (J + 1) x C_in joint features."""

    def __init__(self, tokens: int, in_dim: int, out_dim: int, config: OmniMotionConfig):
        super().__init__()
        self.tokens, self.out_dim = tokens, out_dim
        self.embed = nn.Linear(tokens * in_dim, config.temporal_dim)
        self.blocks = transformer(config.temporal_dim, config.temporal_heads, config.temporal_layers, config.dropout)
        self.out = nn.Linear(config.temporal_dim, tokens * out_dim)

    def forward(self, x: Tensor, mask: Tensor) -> Tensor:  # (B, T, J + 1, C_in), (B, T) -> (B, T, J + 1, C_out)
        h = self.embed(x.flatten(2))  # (B, T, C_t)
        h = h + sinusoidal_positions(h.shape[1], h.shape[2], h.device).to(h.dtype)
        h = self.blocks(h, src_key_padding_mask=~mask)
        return self.out(h).unflatten(-1, (self.tokens, self.out_dim))


class MotionAutoencoder(nn.Module):
    """The joint-aware autoencoder of one domain: (maa features, offsets) <-> Z (B, T/l, 7, C_j)."""

    def __init__(self, skeleton: Skeleton, config: OmniMotionConfig):
        super().__init__()
        self.skeleton, self.config = skeleton, config
        self.num_tokens = skeleton.num_joints + 1
        self.register_buffer("primal", torch.tensor(primal_joints(skeleton)), persistent=False)
        C, N = config.joint_dim, self.num_tokens
        # encoder E
        self.pose_joints = JointTokens(6 + 3, N, config)  # pose ⊕ padded offsets -> F_j
        self.enc_offsets = JointTokens(3, N, config)  # offsets -> F_o
        self.enc_temporal = TemporalTokens(N, 2 * C, C, config)
        # decoder D
        self.dec_offsets = JointTokens(3, N, config)
        self.dec_temporal = TemporalTokens(N, 2 * C, C, config)
        self.dec_joints = JointTokens(C, N, config)
        self.head = nn.Linear(C, 6)
        # the root's x and z translation in the features (the last token's first and third numbers)
        D = self.num_tokens * 6
        self.register_buffer("ground", torch.tensor([D - 6, D - 4]), persistent=False)
        # the internal features' per-dimension mean and scale (identity until ``standardize`` sets the data's
        # statistics): the networks read and write standardised features, callers pass and get raw maa
        self.register_buffer("feature_mean", torch.zeros(D), persistent=False)
        self.register_buffer("feature_scale", torch.ones(D), persistent=False)

    def standardize(self, mean: Tensor, scale: Tensor, ground_step: float | None = None) -> None:
        """Set the (D,) mean and scale by which raw maa features are standardised inside the autoencoder;
        with ``config.root_velocity`` the ground displacement has mean 0 and scale ``ground_step`` (metres
        per frame; the module passes one frame's time, so the networks read m/s)."""
        mean, scale = torch.as_tensor(mean, dtype=torch.float32).clone(), torch.as_tensor(scale, dtype=torch.float32)
        if self.config.root_velocity:
            mean[self.ground], scale = 0.0, scale.clone()
            scale[self.ground] = 1.0 if ground_step is None else ground_step
        self.feature_mean.copy_(mean)
        self.feature_scale.copy_(scale)

    def normalize(self, features: Tensor, mask: Tensor) -> Tensor:
        """Raw maa (B, T, D) -> the standardised features the networks read and write (zero at padding)."""
        features = features * mask[..., None]
        if self.config.root_velocity:  # ground position -> per-frame displacement (frame 0 keeps its position)
            ground = features[..., self.ground]
            features = features.index_copy(-1, self.ground, ground - nn.functional.pad(ground, (0, 0, 1, -1)))
        return (features - self.feature_mean) / self.feature_scale * mask[..., None]

    def denormalize(self, x: Tensor, mask: Tensor) -> Tensor:
        """The inverse of ``normalize``: standardised (B, T, D) -> raw maa, zero at padding."""
        features = (x * self.feature_scale + self.feature_mean) * mask[..., None]
        if self.config.root_velocity:
            features = features.index_copy(-1, self.ground, features[..., self.ground].cumsum(1))
        return features * mask[..., None]

    def encode(self, features: Tensor, offsets: Tensor, mask: Tensor) -> tuple[Tensor, Tensor]:
        """(B, T, (J+1)·6), (B, J, 3), (B, T) -> Z (B, ceil(T/l), 7, C_j) and its mask (B, ceil(T/l))."""
        pose = as_tokens(self.normalize(features, mask))  # (B, T, J + 1, 6)
        S = padded_offsets(offsets)  # (B, J + 1, 3)
        F_j = self.pose_joints(torch.cat([pose, S[:, None].expand(-1, pose.shape[1], -1, -1)], -1))  # (B, T, N, C)
        F_o = self.enc_offsets(S)[:, None].expand_as(F_j)  # (B, T, N, C)
        h = self.enc_temporal(torch.cat([F_j, F_o], -1), mask) * mask[..., None, None]  # (B, T, N, C)
        pool, T = self.config.pool, h.shape[1]
        h = nn.functional.pad(h, (0, 0, 0, 0, 0, -T % pool)).unflatten(1, (-1, pool))  # (B, T/l, l, N, C)
        weights = nn.functional.pad(mask, (0, -T % pool)).unflatten(1, (-1, pool)).float()  # (B, T/l, l)
        h = (h * weights[..., None, None]).sum(2) / weights.sum(2).clamp_min(1)[..., None, None]  # temporal pooling
        return h[:, :, self.primal], pooled_mask(mask, pool)  # primal-joint pooling: (B, T/l, 7, C)

    def unpool(self, z: Tensor, frames: int) -> Tensor:
        """Z (B, T/l, 7, C) -> (B, frames, J + 1, C): zeros at non-primal joints, each latent frame repeated l times."""
        B, L, _, C = z.shape
        h = z.new_zeros(B, L, self.num_tokens, C)
        h[:, :, self.primal] = z
        return h.repeat_interleave(self.config.pool, dim=1)[:, :frames]

    def decode(self, z: Tensor, offsets: Tensor, mask: Tensor) -> Tensor:
        """Z (B, T/l, 7, C_j), the target's offsets (B, J, 3), frames (B, T) -> maa features (B, T, (J+1)·6)."""
        h = self.unpool(z, mask.shape[1])  # (B, T, N, C)
        F_o = self.dec_offsets(padded_offsets(offsets))[:, None].expand_as(h)
        h = self.dec_temporal(torch.cat([h, F_o], -1), mask)  # (B, T, N, C)
        out = self.head(self.dec_joints(h))  # (B, T, N, 6) standardised
        return self.denormalize(out.flatten(2), mask)


class LatentTextEncoder(nn.Module):
    """E_t: a linear head from the flattened latent (zero beyond its frames) to the sentence feature."""

    def __init__(self, config: OmniMotionConfig, text_dim: int):
        super().__init__()
        self.frames = config.latent_frames
        self.proj = nn.Linear(self.frames * NUM_PRIMAL * config.joint_dim, text_dim)

    def forward(self, z: Tensor, mask: Tensor) -> Tensor:  # (B, L, 7, C), (B, L) -> (B, text_dim)
        z = (z * mask[..., None, None])[:, : self.frames]
        z = nn.functional.pad(z, (0, 0, 0, 0, 0, self.frames - z.shape[1]))
        return self.proj(z.flatten(1))


class LatentTextDecoder(nn.Module):
    """D_t: a causal transformer decoder over latent frames, attending to the sentence feature C.

    With ``latent_shift`` (omg's variant; off in the paper and by default) it is a GPT over latent
    frames: output frame t reads C (the start token and the cross-attention memory) and the input
    frames before t, never frame t itself, so the text has to carry what the past does not.
    Unshifted, it can learn the identity and ignore C (what the first mini runs did)."""

    def __init__(self, config: OmniMotionConfig, text_dim: int):
        super().__init__()
        width, latent = config.latent_dim, NUM_PRIMAL * config.joint_dim
        self.embed = nn.Linear(latent, width)
        self.text = nn.Linear(text_dim, width)
        layer = nn.TransformerDecoderLayer(width, config.latent_heads, 4 * width, config.dropout, activation="gelu",
                                           batch_first=True, norm_first=True)
        self.blocks = nn.TransformerDecoder(layer, config.latent_layers)
        self.out = nn.Linear(width, latent)
        self.shift = config.latent_shift

    def forward(self, text: Tensor, z: Tensor, mask: Tensor) -> Tensor:  # (B, D_text), (B, L, 7, C), (B, L)
        c = self.text(text)[:, None]  # (B, 1, W)
        h = self.embed(z.flatten(2))  # (B, L, W)
        if self.shift:  # frame t sees C and Z_<t only
            h = torch.cat([c, h[:, :-1]], 1)
        h = h + sinusoidal_positions(h.shape[1], h.shape[2], h.device).to(h.dtype)
        causal = nn.Transformer.generate_square_subsequent_mask(h.shape[1], device=h.device, dtype=torch.bool)
        h = self.blocks(h, c, tgt_mask=causal, tgt_is_causal=True,
                        tgt_key_padding_mask=~mask)
        return self.out(h).unflatten(-1, z.shape[-2:]) * mask[..., None, None]  # (B, L, 7, C)


class OmniMotionGPT(nn.Module):
    """Both domains' autoencoders and text heads: ``human`` / ``animal`` each hold ``ae`` (E, D),
    ``text_encoder`` (E_t) and ``text_decoder`` (D_t)."""

    def __init__(self, human: Skeleton, animal: Skeleton, config: OmniMotionConfig, text_dim: int):
        super().__init__()
        self.config = config
        self.human = self._domain(human, text_dim)
        self.animal = self._domain(animal, text_dim)

    def _domain(self, skeleton: Skeleton, text_dim: int) -> nn.ModuleDict:
        return nn.ModuleDict({"ae": MotionAutoencoder(skeleton, self.config),
                              "text_encoder": LatentTextEncoder(self.config, text_dim),
                              "text_decoder": LatentTextDecoder(self.config, text_dim)})

    def translate(self, human: Tensor, human_offsets: Tensor, mask: Tensor, text: Tensor,
                  animal_offsets: Tensor) -> Tensor:
        """Inference: human maa (B, T, ·) + offsets, the target sentence feature C̃ (B, D_text) and the
        animal's offsets (B, J_a, 3) -> animal maa (B, T, (J_a + 1)·6)."""
        z, z_mask = self.human["ae"].encode(human, human_offsets, mask)
        z_animal = self.animal["text_decoder"](text, z, z_mask)
        return canonical_maa(self.animal["ae"].decode(z_animal, animal_offsets, mask)) * mask[..., None]


def canonical_maa(features: Tensor) -> Tensor:
    """maa features as the representation writes them: each joint's 6D rotation orthonormalised
    (Gram-Schmidt, the rotation ``decode`` would use anyway) and the translation's padding zero.
    A decoder's raw output is near, not on, that set; evaluators and files read the canonical form."""
    tokens = as_tokens(features)  # (..., J + 1, 6)
    rotations = matrix_to_6d(sixd_to_matrix(tokens[..., :-1, :]))
    root = torch.cat([tokens[..., -1, :3], torch.zeros_like(tokens[..., -1, 3:])], -1)
    return torch.cat([rotations, root[..., None, :]], -2).flatten(-2)


# -- geometry for the losses ---------------------------------------------------------------------

def end_effector_velocity(representation: Representation, features: Tensor, offsets: Tensor) -> Tensor:
    """Frame-to-frame velocity of the skeleton's end effectors by forward kinematics:
    (B, T, D) maa features, (B, J, 3) offsets -> (B, T − 1, 5, 3) metres per frame."""
    joints = representation.decode(features, offsets)[..., list(representation.skeleton.end_effectors), :]
    return joints[:, 1:] - joints[:, :-1]
