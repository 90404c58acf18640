"""WebDataset shards of encoded motion: the sample schema, an atomic resumable writer, the
manifest, and validation.

A shard set is a directory of ``shard-NNNNNN.tar`` files plus ``manifest.json``. Each sample
is one clip stored under a key without dots:

- ``<key>.motion.npy``: float32 (T, D) features of the set's representation;
- ``<key>.meta.json``: id, representation, skeleton, fps, source, labels, category, and
  per-clip quantities the representation needs (bone offsets);
- ``<key>.texts.json``: a list of captions, empty for unlabeled data.

Shards are written under a temporary name and renamed when complete, so a shard file that
exists is whole. The manifest records each shard's sample count, byte size and sha256;
``iter_tar`` checks a shard against them as it reads (``ShardError`` names the shard and the
failed check) and ``check_shards`` (``omg shards inspect``) checks a whole set.
``build-state.json`` records the finished shards with the source position and feature
statistics they cover; an interrupted build resumes after the last of them.

``write_shards`` reads a source once for all its splits, in one process or several
(``LazyItem``: a source item read where the build gets to it), with output independent of the
number; ``merge_shard_sets`` joins the sets built from parts of a source into one, its
statistics pooled from the parts' raw sums.

One concern per module, dependencies pointing down this list: ``schema`` (names, keys, sample
encoding, statistics, ``ShardError``), ``remote`` (paths, URLs, ``pipe:`` commands), ``manifest``
(the manifest, merging sets), ``items`` (source items and their encoding), ``writer``
(``ShardWriter``), ``build`` (``write_shards``, the worker pool, progress), ``checks`` (checked
reading, whole-set checks).
"""

from omg.data.shards.build import BuildProgress, SourceItems, write_shards
from omg.data.shards.checks import ShardCheck, ShardSetCheck, check_shards, iter_tar, validate, verify_shard
from omg.data.shards.items import EncodedClip, LazyItem, encode_item, resolved
from omg.data.shards.manifest import Manifest, manifest_data, merge_shard_sets
from omg.data.shards.remote import PIPE_TIMEOUT_S, manifest_url, open_url, read_url, sibling_url, url_file_name
from omg.data.shards.schema import (
    BUILD_STATE,
    MANIFEST,
    META_KEYS,
    SCHEMA_VERSION,
    SHARD_CHECKS,
    SHARD_NAME,
    SHARD_PATTERN,
    FeatureStats,
    ShardError,
    decode_sample,
    encode_sample,
    sample_key,
)
from omg.data.shards.writer import BuildSummary, ShardWriter

__all__ = ["BUILD_STATE", "MANIFEST", "META_KEYS", "PIPE_TIMEOUT_S", "SCHEMA_VERSION", "SHARD_CHECKS", "SHARD_NAME",
           "SHARD_PATTERN", "BuildProgress", "BuildSummary", "EncodedClip", "FeatureStats", "LazyItem", "Manifest",
           "ShardCheck", "ShardError", "ShardSetCheck", "ShardWriter", "SourceItems", "check_shards", "decode_sample",
           "encode_item", "encode_sample", "iter_tar", "manifest_data", "manifest_url", "merge_shard_sets", "open_url",
           "read_url", "resolved", "sample_key", "sibling_url", "url_file_name", "validate", "verify_shard",
           "write_shards"]
