"""What the language classifier reads: an object's relation paragraph, led by its size.

An object's spatial context is written as the paper's paragraph ("The alarm clock is next
to the desk. The alarm clock is supported by the sofa. The alarm clock is closest to the
mug."), led, for the categories with sub-category variants, by a sentence on its size from
its 3D box ("The vase is large."; a large vase stands on the floor, a small one does not).
The agent, the data generators and the evaluations all write paragraphs here.
"""

from __future__ import annotations

import re
from collections.abc import Sequence

from tidee.agent.classes import CLASSES, WITH_VARIANTS
from tidee.agent.reasoning.relations import FLOOR, ObjectRef, relation_paragraph, words

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


SUPPORT_RE = re.compile(r"The (.+?) is supported by the (.+?)\.")
_WORDS_TO_CLASS = {words(c): c for c in (*CLASSES, FLOOR)}


def paragraph_support(paragraph: str) -> str | None:
    """The receptacle class of a paragraph's supported-by sentence ("Floor" included)."""
    m = SUPPORT_RE.search(paragraph)
    return None if m is None else _WORDS_TO_CLASS.get(m.group(2))
