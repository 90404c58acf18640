"""An unseen species swaps only the habit latent (Behave Your Motion's transfer): ``omg transfer --to camel``
uses the nearest known category's (horse's) habit latent with the camel's own description as the condition."""

from __future__ import annotations

import numpy as np
import torch

from helpers.habit import CATEGORIES, QUATVEL
from helpers.habit import fit as _fit


def test_unseen_species_keeps_its_own_description_and_borrows_only_the_habit_latent(tmp_path):
    from omg.data.datamodule import MotionDataModule
    from omg.data.loaders import ClipDataset
    from omg.lit.habit import HabitVQModule
    from omg.tools.habit import transfer

    # condition_decoder: the description reaches the decoder too (without it, only the encoder before quantization)
    vq, path = _fit(lambda spec: HabitVQModule(CATEGORIES, flavor="tiny", condition_decoder=True, spec=spec),
                    tmp_path / "vq", 12)
    vq.eval()
    data = MotionDataModule(str(QUATVEL / "val"), verify_shards=False)
    dog = next(s for s in ClipDataset.from_shards(data.train_urls, data.feature_dim, data.windows).samples
               if s["meta"]["category"] == "dog")
    source = tmp_path / "dog.npy"
    np.save(source, np.asarray(dog["motion"][:64], dtype=np.float32))

    out = {to: transfer(source, to=to, ckpt=path, out=tmp_path / to, preview=False) for to in ("horse", "camel")}
    assert out["camel"]["category"] == "horse" and out["camel"]["retrieved"]
    assert out["camel"]["condition"] == "its own description"
    motion = {to: np.load(tmp_path / to / "transfer.features.npy") for to in out}
    assert not np.allclose(motion["camel"], motion["horse"], atol=1e-4)  # a camel is not a horse

    # ... and differs only by the condition: horse's habit latent with the camel description's embedding
    from omg.generation.registry import generator_for

    camel = generator_for(vq).species_condition("camel", None)
    k = vq.categories.index("horse")
    features = torch.from_numpy(np.asarray(dog["motion"][:64], dtype=np.float32))[None]
    z = vq.habit_latents(k, 1, seed=0)  # a sample of horse's flow (the default order's checkpoint holds them)
    with torch.no_grad():
        expected = vq.transfer(features, k, z, seed=0, text=camel["embedding"])[0]
        as_horse = vq.transfer(features, k, z, seed=0)[0]  # the old path: horse's text too
    np.testing.assert_allclose(motion["camel"], expected.numpy(), atol=1e-5)
    np.testing.assert_allclose(motion["horse"], as_horse.numpy(), atol=1e-5)
    assert not torch.allclose(camel["embedding"], vq.category_text[k].cpu())
