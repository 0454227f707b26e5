"""Instructions that alter the language OOP head (paper §3.2, §4.6).

:func:`parse_instruction` reads "I want my alarm clock on the desk" as (AlarmClock, Desk,
in place); :func:`apply_instruction` fine-tunes the head on the relations it names. A live
agent calls it for a typed preference, so this module is part of the agent's run time; its
evaluation (paper Table S2) is :mod:`.instruct_eval`.
"""

from __future__ import annotations

import re
import time
from collections.abc import Sequence
from typing import Any, NamedTuple

import numpy as np
import torch

from tidee.agent.classes import CLASSES, PICKUPABLE, RECEPTACLES, WITH_VARIANTS
from tidee.agent.reasoning.language_oop.config import ANCHOR_WEIGHT
from tidee.agent.reasoning.language_oop.model import LanguageOOPClassifier, fit_head
from tidee.agent.reasoning.language_oop.paragraphs import (
    LARGEST_SIZE_WORD,
    SIZE_WORDS,
    SUPPORT_RE,
    paragraph_support,
)
from tidee.agent.reasoning.relations import FLOOR, words

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


def with_support(paragraph: str, inst: Instruction) -> str:
    """The paragraph with its supported-by sentence naming the instructed receptacle."""
    if SUPPORT_RE.search(paragraph) is None:
        return f"{paragraph} {inst.sentence()}".strip()
    return SUPPORT_RE.sub(inst.sentence().replace("\\", "\\\\"), paragraph, count=1)


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
    rewritten = named + [with_support(paras[i], inst) for i in pick if supports[i] != inst.receptacle]
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
