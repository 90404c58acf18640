"""The HumanML3D "T2M" text–motion evaluator (Guo et al., CVPR 2022), ported for loading its weights.

Papers on HumanML3D report R-precision, FID, MM-Dist and diversity in the feature space of
this evaluator, trained by the text2motion repository (``networks/modules.py``,
``utils/word_vectorizer.py``, ``networks/evaluator_wrapper.py``). To compare numbers with
them, omg loads the official ``checkpoints/t2m/text_mot_match/model/finest.tar`` into modules
with exactly the official parameter names and shapes:

    motion (B, T, 263) --normalise (evaluator mean/std), drop 4 foot contacts--> (B, T, 259)
      -> MovementConvEncoder: two stride-2 convs, T -> T/4 "movement units" (B, T/4, 512)
      -> MotionEncoderBiGRUCo: BiGRU over the m_len // 4 real units, last states -> (B, 512)
    "word/POS ..." tokens -> sos + ≤20 words + eos, padded with unk to 22
      -> GloVe (300) + POS one-hot (15) -> TextEncoderBiGRUCo: BiGRU, last states -> (B, 512)

The GRUs run on packed sequences, which the official code feeds sorted by length (longest
first); ``T2MEvaluator`` sorts each batch itself and returns rows in the caller's order.
Embeddings are not normalised: MM-Dist and R-precision use Euclidean distance, as published.

Text: HumanML3D keeps spaCy's tokens with every caption ("a/DET man/NOUN kick/VERB ...",
lemmatised nouns and verbs), and the importer stores them; pass those for published numbers.
A plain caption goes through ``tag_caption``, a small rule-based stand-in for spaCy (word lists
for closed classes, suffix rules, a vocabulary-checked lemmatiser): close, not identical.
"""

from __future__ import annotations

import pickle
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
import torch
from torch import Tensor, nn
from torch.nn.utils.rnn import pack_padded_sequence

from omg.errors import UsageError
from omg.motion import length_mask

# -- utils/word_vectorizer.py (official values) ----------------------------------------------

POS_enumerator = {
    "VERB": 0, "NOUN": 1, "DET": 2, "ADP": 3, "NUM": 4, "AUX": 5, "PRON": 6, "ADJ": 7, "ADV": 8,
    "Loc_VIP": 9, "Body_VIP": 10, "Obj_VIP": 11, "Act_VIP": 12, "Desc_VIP": 13, "OTHER": 14,
}  # fmt: skip
Loc_list = ("left", "right", "clockwise", "counterclockwise", "anticlockwise", "forward", "back", "backward",
            "up", "down", "straight", "curve")
Body_list = ("arm", "chin", "foot", "feet", "face", "hand", "mouth", "leg", "waist", "eye", "knee", "shoulder", "thigh")
Obj_List = ("stair", "dumbbell", "chair", "window", "floor", "car", "ball", "handrail", "baseball", "basketball")
Act_list = ("walk", "run", "swing", "pick", "bring", "kick", "put", "squat", "throw", "hop", "dance", "jump", "turn",
            "stumble", "dance", "stop", "sit", "lift", "lower", "raise", "wash", "stand", "kneel", "stroll",
            "rub", "bend", "balance", "flap", "jog", "shuffle", "lean", "rotate", "spin", "spread", "climb")
Desc_list = ("slowly", "carefully", "fast", "careful", "slow", "quickly", "happy", "angry", "sad", "happily",
             "angrily", "sadly")
VIP_dict = {"Loc_VIP": Loc_list, "Body_VIP": Body_list, "Obj_VIP": Obj_List, "Act_VIP": Act_list, "Desc_VIP": Desc_list}

GLOVE_FILES = ("our_vab_data.npy", "our_vab_words.pkl", "our_vab_idx.pkl")


@dataclass(frozen=True)
class T2MConfig:
    """The official evaluator's sizes (``EvaluatorModelWrapper`` for dataset t2m)."""

    dim_pose: int = 263
    dim_word: int = 300
    dim_pos_ohot: int = len(POS_enumerator)  # 15
    dim_text_hidden: int = 512
    dim_coemb_hidden: int = 512
    dim_movement_enc_hidden: int = 512
    dim_movement_latent: int = 512
    dim_motion_hidden: int = 1024
    unit_length: int = 4
    max_text_len: int = 20
    max_motion_length: int = 196


class WordVectorizer:
    """GloVe vectors and POS one-hots of "word/POS" tokens, as the official ``WordVectorizer``.

    ``glove_dir`` holds ``our_vab_data.npy`` (N, 300), ``our_vab_words.pkl`` (word list) and
    ``our_vab_idx.pkl`` (word -> row). A word of a VIP list takes that list's POS; an unknown
    word is ``unk`` with POS OTHER.
    """

    def __init__(self, glove_dir: str | Path, prefix: str = "our_vab"):
        glove_dir = Path(glove_dir)
        files = [glove_dir / f"{prefix}{suffix}" for suffix in ("_data.npy", "_words.pkl", "_idx.pkl")]
        if missing := [f.name for f in files if not f.is_file()]:
            raise UsageError(f"glove_dir={str(glove_dir)!r} lacks {', '.join(missing)}: pass the folder of HumanML3D's "
                             f"GloVe files ({', '.join(GLOVE_FILES)}; text2motion's ./glove)")
        try:
            vectors = np.load(files[0], allow_pickle=False)
        except ValueError as e:  # an object array (pickled objects) or not an .npy file
            raise UsageError(f"glove_dir={str(glove_dir)!r}: {files[0].name} is not a plain array file ({e})") from None
        words = _read_vocabulary(files[1], list)
        self.word2idx = _read_vocabulary(files[2], dict)
        if not (vectors.ndim == 2 and all(isinstance(w, str) for w in words)
                and all(isinstance(w, str) and isinstance(i, int) and 0 <= i < len(vectors)
                        for w, i in self.word2idx.items())):
            raise UsageError(f"glove_dir={str(glove_dir)!r}: expected a (N, 300) array, a list of words and a dict "
                             "word -> row: not HumanML3D's GloVe files")
        if missing := [w for w in words if w not in self.word2idx]:
            raise UsageError(f"glove_dir={str(glove_dir)!r}: {files[2].name} has no row for {missing[0]!r}")
        self.word2vec = {w: vectors[self.word2idx[w]] for w in words}
        if "unk" not in self.word2vec:
            raise UsageError(f"glove_dir={str(glove_dir)!r}: the vocabulary has no 'unk' word; "
                             "not HumanML3D's GloVe files")

    def _get_pos_ohot(self, pos: str) -> np.ndarray:
        pos_vec = np.zeros(len(POS_enumerator))
        pos_vec[POS_enumerator.get(pos, POS_enumerator["OTHER"])] = 1
        return pos_vec

    def __len__(self) -> int:
        return len(self.word2vec)

    def __contains__(self, word: str) -> bool:
        return word in self.word2vec

    def __getitem__(self, item: str) -> tuple[np.ndarray, np.ndarray]:
        word, pos = item.split("/")
        if word not in self.word2vec:
            return self.word2vec["unk"], self._get_pos_ohot("OTHER")
        vip_pos = next((key for key, values in VIP_dict.items() if word in values), None)
        return self.word2vec[word], self._get_pos_ohot(vip_pos if vip_pos is not None else pos)


class _VocabularyUnpickler(pickle.Unpickler):
    """Unpickles plain data only. A list of str and a dict str -> int pickle without a single
    global (any protocol); a global is what lets a pickle call code, so none is resolved."""

    def find_class(self, module: str, name: str):
        raise pickle.UnpicklingError(f"{module}.{name}")


def _read_vocabulary(path: Path, kind: type) -> list | dict:
    """HumanML3D's ``*_words.pkl`` (a list of str) or ``*_idx.pkl`` (a dict str -> int), read
    without letting the file run code."""
    try:
        with open(path, "rb") as f:
            value = _VocabularyUnpickler(f).load()
    except pickle.UnpicklingError as e:
        raise UsageError(f"{path} holds pickled Python objects ({e}), not a plain {kind.__name__} of words: "
                         "refused (unpickling it could run code); not HumanML3D's GloVe file") from None
    except (EOFError, ValueError, TypeError, IndexError, KeyError) as e:
        raise UsageError(f"{path} is not a readable pickle ({type(e).__name__}: {e})") from None
    if type(value) is not kind:
        raise UsageError(f"{path} holds a {type(value).__name__}, not the {kind.__name__} of HumanML3D's GloVe file")
    return value


def process_tokens(tokens: list[str], max_text_len: int = 20) -> tuple[list[str], int]:
    """The official dataset's framing: sos + words (cropped to ``max_text_len``) + eos, padded
    with unk to ``max_text_len + 2``; returns (tokens, sent_len counting sos and eos)."""
    if len(tokens) < max_text_len:
        tokens = ["sos/OTHER"] + tokens + ["eos/OTHER"]
        sent_len = len(tokens)
        tokens = tokens + ["unk/OTHER"] * (max_text_len + 2 - sent_len)
    else:
        tokens = ["sos/OTHER"] + tokens[:max_text_len] + ["eos/OTHER"]
        sent_len = len(tokens)
    return tokens, sent_len


# -- a small rule-based stand-in for HumanML3D's spaCy tokens --------------------------------

_CLOSED = {
    "DET": "a an the this that these those each every some another any no either neither all both",
    "PRON": "i you he she it we they me him her us them his hers its our their my your someone somebody something "
            "anyone anybody anything everyone everybody nothing himself herself itself themselves oneself who what "
            "which whom whose",
    "ADP": "in on at to from with into onto over under around across through along towards toward of by for about "
           "after before behind between like off out above below near beside against upon within without past via "
           "throughout per",
    "AUX": "is are was were be been being am has have had does do did can could will would should may might must shall",
    "NUM": "zero one two three four five six seven eight nine ten eleven twelve twenty thirty hundred",
    "ADV": "then again twice once thrice very also still together here there away sideways slightly just "
           "repeatedly backwards afterwards almost too quite so not",
    "ADJ": "small big large high low long short tall other few several multiple quick easy heavy light little "
           "full half first second third last next same different",
    "OTHER": "and or but while as if because until when where than",  # CCONJ/SCONJ: not in the enumerator
}
_TAG = {w: tag for tag, words in _CLOSED.items() for w in words.split()}
_TOKEN = re.compile(r"^[^/\s]+/[A-Za-z_]+$")


def _lemma_candidates(word: str) -> list[str]:
    """Possible base forms of an inflected noun/verb, most stripped first; the word itself last."""
    out = []
    if word.endswith("ies") and len(word) > 4:
        out.append(word[:-3] + "y")
    if word.endswith("ing") and len(word) > 5:
        base = word[:-3]
        out += [base, base + "e"] + ([base[:-1]] if base[-1] == base[-2] else [])
    if word.endswith("ed") and len(word) > 4:
        base = word[:-2]
        out += [base, base + "e", word[:-1]] + ([base[:-1]] if base[-1] == base[-2] else [])
    if word.endswith("es") and len(word) > 3:
        out.append(word[:-2])
    if word.endswith("s") and not word.endswith("ss") and len(word) > 3:
        out.append(word[:-1])
    return out + [word]


def tag_caption(caption: str, vocabulary: WordVectorizer | None = None) -> list[str]:
    """A plain caption -> HumanML3D-style "word/POS" tokens (an approximation of spaCy).

    As HumanML3D's ``process_text``: hyphens removed, only alphabetic words kept, nouns and verbs
    lemmatised except "left". Closed classes come from word lists; "-ly" words are ADV; a word
    after a subject (noun/pronoun) with no verb yet, or ending in -ing/-ed, is a VERB; any other
    open-class word is a NOUN. Lemmas are the first suffix-stripped form ``vocabulary`` knows
    (without one, words stay as written).
    """
    words = [w for w in caption.replace("-", "").lower().split() for w in re.findall(r"[a-z]+", w)]
    tokens, seen_subject, seen_verb = [], False, False
    for w in words:
        tag = _TAG.get(w)
        if tag is None:
            if w in Loc_list or w in Desc_list:
                tag = "ADV"  # their VIP class overrides this anyway
            elif w.endswith("ly") and len(w) > 4:
                tag = "ADV"
            elif w in Act_list or w.endswith(("ing", "ed")) or (seen_subject and not seen_verb):
                tag = "VERB"
            else:
                tag = "NOUN"
        if tag in ("NOUN", "VERB") and w != "left" and vocabulary is not None:
            w = next(c for c in _lemma_candidates(w) if c in vocabulary or c == w)
        seen_subject |= tag in ("NOUN", "PRON")
        seen_verb |= tag == "VERB"
        tokens.append(f"{w}/{tag}")
    return tokens


def text_tokens(text: str, vocabulary: WordVectorizer | None = None) -> list[str]:
    """Tokens of a HumanML3D token string ("a/DET man/NOUN ..."), of a HumanML3D text-file line
    ("caption#tokens#start#end"), or of a plain caption through ``tag_caption``."""
    if "#" in text:
        text = text.split("#")[1]
    parts = text.split()
    if parts and all(_TOKEN.match(p) for p in parts):
        return parts
    return tag_caption(text, vocabulary)


# -- networks/modules.py (official parameter names and shapes) -------------------------------


def init_weight(m: nn.Module) -> None:
    if isinstance(m, (nn.Conv1d, nn.Linear, nn.ConvTranspose1d)):
        nn.init.xavier_normal_(m.weight)
        if m.bias is not None:
            nn.init.constant_(m.bias, 0)


class MovementConvEncoder(nn.Module):
    """(B, T, input_size) -> (B, T/4, output_size): two stride-2 convolutions and a Linear."""

    def __init__(self, input_size: int, hidden_size: int, output_size: int):
        super().__init__()
        self.main = nn.Sequential(
            nn.Conv1d(input_size, hidden_size, 4, 2, 1),
            nn.Dropout(0.2, inplace=True),
            nn.LeakyReLU(0.2, inplace=True),
            nn.Conv1d(hidden_size, output_size, 4, 2, 1),
            nn.Dropout(0.2, inplace=True),
            nn.LeakyReLU(0.2, inplace=True),
        )
        self.out_net = nn.Linear(output_size, output_size)
        self.main.apply(init_weight)
        self.out_net.apply(init_weight)

    def forward(self, inputs: Tensor) -> Tensor:
        outputs = self.main(inputs.permute(0, 2, 1)).permute(0, 2, 1)  # (B, T/4, output_size)
        return self.out_net(outputs)


class TextEncoderBiGRUCo(nn.Module):
    """(B, L, 300) GloVe + (B, L, 15) POS, lengths sorted descending -> (B, output_size)."""

    def __init__(self, word_size: int, pos_size: int, hidden_size: int, output_size: int):
        super().__init__()
        self.pos_emb = nn.Linear(pos_size, word_size)
        self.input_emb = nn.Linear(word_size, hidden_size)
        self.gru = nn.GRU(hidden_size, hidden_size, batch_first=True, bidirectional=True)
        self.output_net = nn.Sequential(
            nn.Linear(hidden_size * 2, hidden_size),
            nn.LayerNorm(hidden_size),
            nn.LeakyReLU(0.2, inplace=True),
            nn.Linear(hidden_size, output_size),
        )
        self.input_emb.apply(init_weight)
        self.pos_emb.apply(init_weight)
        self.output_net.apply(init_weight)
        self.hidden_size = hidden_size
        self.hidden = nn.Parameter(torch.randn((2, 1, self.hidden_size), requires_grad=True))  # learned h0

    def forward(self, word_embs: Tensor, pos_onehot: Tensor, cap_lens: Tensor) -> Tensor:
        num_samples = word_embs.shape[0]
        input_embs = self.input_emb(word_embs + self.pos_emb(pos_onehot))  # (B, L, H)
        hidden = self.hidden.repeat(1, num_samples, 1)  # (2, B, H)
        emb = pack_padded_sequence(input_embs, cap_lens.data.tolist(), batch_first=True)
        _, gru_last = self.gru(emb, hidden)  # (2, B, H): forward and backward final states
        return self.output_net(torch.cat([gru_last[0], gru_last[1]], dim=-1))


class MotionEncoderBiGRUCo(nn.Module):
    """(B, T/4, 512) movement units, unit counts sorted descending -> (B, output_size)."""

    def __init__(self, input_size: int, hidden_size: int, output_size: int):
        super().__init__()
        self.input_emb = nn.Linear(input_size, hidden_size)
        self.gru = nn.GRU(hidden_size, hidden_size, batch_first=True, bidirectional=True)
        self.output_net = nn.Sequential(
            nn.Linear(hidden_size * 2, hidden_size),
            nn.LayerNorm(hidden_size),
            nn.LeakyReLU(0.2, inplace=True),
            nn.Linear(hidden_size, output_size),
        )
        self.input_emb.apply(init_weight)
        self.output_net.apply(init_weight)
        self.hidden_size = hidden_size
        self.hidden = nn.Parameter(torch.randn((2, 1, self.hidden_size), requires_grad=True))

    def forward(self, inputs: Tensor, m_lens: Tensor) -> Tensor:
        num_samples = inputs.shape[0]
        input_embs = self.input_emb(inputs)
        hidden = self.hidden.repeat(1, num_samples, 1)
        emb = pack_padded_sequence(input_embs, m_lens.data.tolist(), batch_first=True)
        _, gru_last = self.gru(emb, hidden)
        return self.output_net(torch.cat([gru_last[0], gru_last[1]], dim=-1))


# -- the evaluator with omg's encode_motion / encode_text API --------------------------------


class T2MEvaluator(nn.Module):
    """The three official modules, the evaluator's mean/std and the word vectorizer."""

    spec = {"representation": "humanml3d263", "skeleton": "smpl22", "fps": 20.0, "feature_dim": 263}

    def __init__(self, vectorizer: WordVectorizer | None, mean: np.ndarray | Tensor, std: np.ndarray | Tensor,
                 config: T2MConfig = T2MConfig()):
        super().__init__()
        c = self.config = config
        self.vectorizer = vectorizer
        self.movement_encoder = MovementConvEncoder(c.dim_pose - 4, c.dim_movement_enc_hidden, c.dim_movement_latent)
        self.text_encoder = TextEncoderBiGRUCo(c.dim_word, c.dim_pos_ohot, c.dim_text_hidden, c.dim_coemb_hidden)
        self.motion_encoder = MotionEncoderBiGRUCo(c.dim_movement_latent, c.dim_motion_hidden, c.dim_coemb_hidden)
        self.register_buffer("mean", torch.as_tensor(np.asarray(mean), dtype=torch.float32).reshape(c.dim_pose))
        self.register_buffer("std", torch.as_tensor(np.asarray(std), dtype=torch.float32).reshape(c.dim_pose))

    @property
    def device(self) -> torch.device:
        return self.mean.device

    @torch.no_grad()
    def encode_motion(self, motion: Tensor, mask: Tensor | None = None) -> Tensor:
        """(B, T, 263) UN-normalised HumanML3D features, (B, T) bool -> (B, 512), in input order.

        As the official evaluation loader: at most 196 frames (HumanML3D's longest; longer
        motions keep their first 196), lengths cropped to whole 4-frame units, normalised with the
        evaluator's mean/std and zero-padded to 196 frames. The padding matters: the last unit's
        convolutions see the padded frames, so results match the official ones only this way.
        """
        c = self.config
        if motion.ndim != 3 or motion.shape[-1] != c.dim_pose:
            raise ValueError(f"T2M encodes humanml3d263 features (B, T, {c.dim_pose}), got {tuple(motion.shape)}")
        motion = motion.to(self.device, torch.float32)[:, : c.max_motion_length]
        B, T, _ = motion.shape
        lengths = mask.to(self.device)[:, :T].sum(1) if mask is not None else torch.full((B,), T, device=self.device)
        lengths = lengths.long() // c.unit_length * c.unit_length  # (B,) whole units, as the eval dataset crops
        if (lengths == 0).any():
            raise ValueError(f"T2M needs at least {c.unit_length} frames per motion, got lengths {lengths.tolist()}")
        x = (motion - self.mean) / self.std
        x = torch.nn.functional.pad(x, (0, 0, 0, c.max_motion_length - T))  # (B, 196, 263)
        x = x * length_mask(lengths, c.max_motion_length)[..., None]
        order = torch.argsort(lengths, descending=True, stable=True)  # pack_padded_sequence wants longest first
        movements = self.movement_encoder(x[order][..., :-4])  # (B, T'/4, 512)
        emb = self.motion_encoder(movements, (lengths[order] // c.unit_length).cpu())
        return emb[torch.argsort(order)]

    def tokenize(self, text: str) -> tuple[np.ndarray, np.ndarray, int]:
        """One text -> (word embeddings (22, 300), POS one-hots (22, 15), sent_len)."""
        if self.vectorizer is None:
            raise UsageError("this T2M evaluator was built without GloVe files: pass glove_dir to load_t2m_evaluator")
        tokens, sent_len = process_tokens(text_tokens(text, self.vectorizer), self.config.max_text_len)
        pairs = [self.vectorizer[t] for t in tokens]
        return np.stack([p[0] for p in pairs]), np.stack([p[1] for p in pairs]), sent_len

    @torch.no_grad()
    def encode_text(self, texts: Sequence[str]) -> Tensor:
        """Token strings ("a/DET man/NOUN walk/VERB ...") or plain captions -> (B, 512), in input order."""
        if isinstance(texts, str):
            raise TypeError(f"encode_text takes a list of texts, got the single string {texts!r}")
        words, pos, lens = zip(*(self.tokenize(t) for t in texts))
        word_embs = torch.as_tensor(np.stack(words), dtype=torch.float32, device=self.device)  # (B, 22, 300)
        pos_ohot = torch.as_tensor(np.stack(pos), dtype=torch.float32, device=self.device)  # (B, 22, 15)
        cap_lens = torch.tensor(lens)
        order = torch.argsort(cap_lens, descending=True, stable=True)
        emb = self.text_encoder(word_embs[order.to(self.device)], pos_ohot[order.to(self.device)], cap_lens[order])
        return emb[torch.argsort(order).to(self.device)]

    def load_official(self, checkpoint: dict) -> None:
        """Load ``finest.tar``'s three state dicts (strict: every official key, nothing else)."""
        names = ("movement_encoder", "text_encoder", "motion_encoder")
        if missing := [n for n in names if n not in checkpoint]:
            raise UsageError(f"the T2M checkpoint lacks {', '.join(map(repr, missing))} (keys: {sorted(checkpoint)}); "
                             "expected text2motion's checkpoints/t2m/text_mot_match/model/finest.tar")
        for name in names:
            try:
                getattr(self, name).load_state_dict(checkpoint[name], strict=True)
            except RuntimeError as e:
                raise UsageError(f"the T2M checkpoint's {name} does not fit the official t2m architecture "
                                 f"(dim_pose 263): {e}") from None


def _read_mean_std(mean_std_dir: str | Path) -> tuple[np.ndarray, np.ndarray]:
    d = Path(mean_std_dir)
    for mean_name, std_name in (("mean.npy", "std.npy"), ("t2m_mean.npy", "t2m_std.npy")):
        if (d / mean_name).is_file() and (d / std_name).is_file():
            try:
                return np.load(d / mean_name, allow_pickle=False), np.load(d / std_name, allow_pickle=False)
            except ValueError as e:  # an object array (pickled objects) or not an .npy file
                raise UsageError(f"mean_std_dir={str(d)!r}: {mean_name}/{std_name} "
                                 f"are not plain array files ({e})") from None
    raise UsageError(f"mean_std_dir={str(d)!r} holds neither mean.npy/std.npy nor t2m_mean.npy/t2m_std.npy: "
                     "pass the folder of the evaluator's normalisation "
                     "(text2motion's checkpoints/t2m/<model>/meta, or MDM's dataset/)")


def load_t2m_evaluator(checkpoint: str | Path, glove_dir: str | Path, mean_std_dir: str | Path,
                       map_location: str | torch.device = "cpu") -> T2MEvaluator:
    """The official T2M evaluator, frozen and in eval mode.

    Args:
        checkpoint: text2motion's ``checkpoints/t2m/text_mot_match/model/finest.tar``.
        glove_dir: the folder with ``our_vab_data.npy``, ``our_vab_words.pkl``, ``our_vab_idx.pkl``.
        mean_std_dir: the folder with the evaluator's ``mean.npy``/``std.npy`` (or ``t2m_mean.npy``/``t2m_std.npy``).
    """
    path = Path(checkpoint)
    if not path.is_file():
        raise UsageError(f"checkpoint={str(path)!r}: no such file; pass text2motion's "
                         "checkpoints/t2m/text_mot_match/model/finest.tar")
    vectorizer = WordVectorizer(glove_dir)
    mean, std = _read_mean_std(mean_std_dir)
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001 - not a torch file, or pickled objects a weights-only load refuses
        raise UsageError(f"checkpoint={str(path)!r} is not a loadable T2M checkpoint "
                         f"({type(e).__name__}: {e})") from None
    if not isinstance(state, dict):
        raise UsageError(f"checkpoint={str(path)!r} holds a {type(state).__name__}, not text2motion's checkpoint dict")
    evaluator = T2MEvaluator(vectorizer, mean, std)
    evaluator.load_official(state)
    evaluator.requires_grad_(False)
    return evaluator.to(map_location).eval()


__all__ = [
    "MotionEncoderBiGRUCo", "MovementConvEncoder", "POS_enumerator", "T2MConfig", "T2MEvaluator",
    "TextEncoderBiGRUCo", "VIP_dict", "WordVectorizer", "load_t2m_evaluator", "process_tokens", "tag_caption",
    "text_tokens",
]  # fmt: skip
