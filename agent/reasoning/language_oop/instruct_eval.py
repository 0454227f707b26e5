"""``tidee eval instruct``: altering placement priors by instruction (paper Table S2).

P(out of place) of ten relation pairs before and after an instruction
(:func:`.instructions.apply_instruction`) that calls them out of place, three preferences,
and the forgetting on unrelated pairs of held-out rooms.
"""

from __future__ import annotations

import time
from collections import defaultdict
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from tidee.agent.reasoning.language_oop.config import ANCHOR_WEIGHT, InstructEvalConfig
from tidee.agent.reasoning.language_oop.data import OOPSample, language_oop_samples
from tidee.agent.reasoning.language_oop.eval import show_path
from tidee.agent.reasoning.language_oop.instructions import (
    IN_PLACE,
    OUT_OF_PLACE,
    Instruction,
    apply_instruction,
    with_support,
)
from tidee.agent.reasoning.language_oop.model import LanguageOOPClassifier
from tidee.agent.reasoning.language_oop.paragraphs import paragraph_support
from tidee.agent.reasoning.relations import words

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
            with_support(p, inst) for p in same[:limit]
        ], f"{split} paragraphs of the category, support rewritten"
    return [inst.sentence()], f"bare sentence (category absent from the {split} rooms)"


def run_instruct_eval(cfg: InstructEvalConfig, progress: bool = True) -> dict[str, Any]:
    """Table S2: P(out of place) of ten relation pairs before and after an instruction that
    calls them out of place (each from the shipped head), plus three preferences ("I want my
    X on the Y") for pairs the head calls out of place; forgetting = mean |change| of
    P(out of place) over the test paragraphs of ``n_unrelated`` frequent pairs of other
    categories. ``split="val"`` runs the same on the validation rooms (for choosing the
    fine-tuning settings without looking at the test rooms). Writes instruct.json and instruct.md."""
    from tidee.protocol.episode_log import write_atomic, write_json_atomic

    weights, steps, split, seed, lr = cfg.weights, cfg.steps, cfg.split, cfg.seed, cfg.lr
    rooms_per_type, messes_per_room, cache_dir = cfg.rooms_per_type, cfg.messes_per_room, cfg.cache_dir
    anchor_weight, distill = cfg.anchor_weight, cfg.distill
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.time()
    base = LanguageOOPClassifier.load(weights, cfg.encoder_path)
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
    )[: cfg.n_unrelated]
    if len(unrelated) < min(20, cfg.n_unrelated):
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
        "weights": show_path(weights),
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
            f"- weights `{show_path(weights)}`; each instruction fine-tunes a fresh copy of the head "
            f"for {steps} steps "
            "(instructed relations + replay of training samples, "
            + (
                "held to the head's own probabilities before the instruction (distillation)"
                if distill
                else "with their training labels"
            )
            + ", L2 pull to the start weights)"
        ),
        (
            "- P(out of place) = mean over the held-out paragraphs with that relation "
            f"({rooms_per_type} {split} rooms per type x {messes_per_room} messes; "
            "`source` says where they come from)"
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
            f"{summary['table_s2_pairs']} "
            f"(mean {summary['mean_before']:.2f} -> {summary['mean_after']:.2f}); "
            f"preferences reaching P(in place) >= 0.7: "
            f"{summary['preferences_reached_0.7']}/{summary['preferences']}; "
            f"unrelated pairs: mean |change| {summary['unrelated_mean_abs_change']:.3f} "
            f"(worst instruction {summary['unrelated_worst_instruction']:.3f}; "
            f"largest change of one unrelated pair's mean {summary['unrelated_largest_pair_change']:.2f})."
        ),
        "",
    ]
    write_atomic(out / "instruct.md", "\n".join(lines).encode())
    return report
