"""``DataSpec``: what a model knows of the features it reads.

A shard set's manifest produces it, ``omg fit`` links it from the data into the model, the
model's checkpoint stores it (as a plain dict, which ``torch.load(weights_only=True)`` reads)
and every component that meets another one's features (a ControlNet on a pretrained DiT, an
evaluator on generated motion, generation on a checkpoint) compares two of them with
``check_compatible``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass, fields

from omg.errors import UsageError

# The fields two components must agree on to exchange features, and what goes wrong otherwise.
# mean/std are not among them: each component normalises with its own statistics.
MUST_MATCH = {
    "representation": "the same numbers would mean different quantities",
    "skeleton": "joint indices and bone lengths would belong to another body",
    "feature_dim": "the feature vectors would have another width",
    "fps": "velocities are per frame, so a frame would mean another duration",
}


@dataclass(frozen=True)
class DataSpec:
    representation: str  # registered name (omg.motion), e.g. "humanml3d263"
    skeleton: str  # registered name (omg.skeleton), e.g. "smpl22"
    fps: float
    feature_dim: int  # D, features per frame
    mean: tuple[float, ...]  # (D,) per-feature statistics of the training data
    std: tuple[float, ...]  # (D,)

    def __post_init__(self) -> None:
        object.__setattr__(self, "fps", float(self.fps))
        object.__setattr__(self, "feature_dim", int(self.feature_dim))
        object.__setattr__(self, "mean", tuple(float(v) for v in self.mean))
        object.__setattr__(self, "std", tuple(float(v) for v in self.std))
        if self.fps <= 0 or self.feature_dim < 1:
            raise UsageError(f"data spec: fps must be > 0 and feature_dim >= 1, got {self.fps}, {self.feature_dim}")
        if not len(self.mean) == len(self.std) == self.feature_dim:
            raise UsageError(f"data spec: mean and std must hold feature_dim={self.feature_dim} values, "
                             f"got {len(self.mean)} and {len(self.std)}")

    @classmethod
    def coerce(cls, value: DataSpec | Mapping | None, what: str = "the model") -> DataSpec:
        """A DataSpec from itself or from its dict (manifests, checkpoints, configs)."""
        if isinstance(value, DataSpec):
            return value
        if value is None:
            raise UsageError(f"{what} needs its data spec (representation, skeleton, fps, stats): `omg fit` links it "
                             "from the data; in Python pass spec=MotionDataModule(...).spec")
        if not isinstance(value, Mapping):
            raise UsageError(f"{what}: a data spec is a mapping of {', '.join(f.name for f in fields(cls))}, "
                             f"got {type(value).__name__}")
        names = [f.name for f in fields(cls)]
        if missing := [k for k in names if k not in value]:
            raise UsageError(f"{what}: data spec lacks {', '.join(missing)}")
        return cls(**{k: value[k] for k in names})

    def to_dict(self) -> dict:
        """Plain types only (lists, not tuples): what checkpoints and hparams.yaml store."""
        out = asdict(self)
        out["mean"], out["std"] = list(self.mean), list(self.std)
        return out

    def conflicts(self, other: DataSpec | Mapping, names: tuple[str, ...] = tuple(MUST_MATCH)) -> dict[str, tuple]:
        """{field: (mine, theirs)} of the ``names`` that differ. ``other`` may be a partial dict
        (an evaluator that knows only some fields): a field it lacks cannot conflict."""
        theirs = other.to_dict() if isinstance(other, DataSpec) else dict(other)
        return {k: (getattr(self, k), theirs[k]) for k in names if k in theirs and getattr(self, k) != theirs[k]}

    def check_compatible(self, other: DataSpec | Mapping, mine: str, theirs: str, hint: str = "") -> None:
        """One-line UsageError naming every field of MUST_MATCH on which ``other`` differs, and why it matters."""
        if bad := self.conflicts(other):
            what = "; ".join(f"{k} {a} vs {b} ({MUST_MATCH[k]})" for k, (a, b) in bad.items())
            raise UsageError(f"{mine} and {theirs} differ: {what}{'; ' + hint if hint else ''}")


__all__ = ["DataSpec", "MUST_MATCH"]
