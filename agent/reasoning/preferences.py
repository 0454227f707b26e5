"""A household's preferences: where things go, and where they never go.

A preference is one sentence, as a person would type it in the viewer or keep in a profile:

* a category: "the alarm clock goes on the desk" (that category, that receptacle);
* a negative: "never put the mug on the floor", "food is out of place on the floor";
* a group: "toys go in the box", "food never goes on the floor": the words before the
  receptacle name no category, so the MiniLM text encoder carries them to the categories whose
  names are nearest (``GROUP_SIMILARITY``, ``GROUP_MARGIN``).

A profile (``--preferences FILE``: JSON ``{"household": ..., "preferences": [sentences]}``, or
the same in YAML when PyYAML is installed) acts on both of the agent's questions, whatever its
OOP detector and placement model:

* **is it out of place?** an object a preference names is out of place (P = 1) when it rests
  on a receptacle the preference forbids, or on another receptacle than the one it asks for, and
  in place (P = 0) when it rests where it asks; other objects keep their detector's score. A
  preference moves only what the detector named at least ``SURE_OBSERVATIONS`` times, and
  never a track whose box overlaps that of another pickupable label the detector was surer of
  (``outvoted``): one detection of a small object is often another one (a key chain read as a
  candle, and also tracked as the key chain it is), and a preference would carry it off where
  the detector's own score would have left it;
* **where does it go?** the receptacle a preference asks for is ranked first, the ones it
  forbids are dropped, the rest keep the placement model's order (a variant without a
  placement model ranks only what preferences ask for); the policy searches for an asked
  receptacle it has not mapped before trying anything else, and tries every mapped one of it
  (then searches for another, with twice the usual search goals) before the model's next
  choice (``TidyPolicy.put_away``);
* **did it find them?** after its usual tidying the policy looks for the objects the category
  preferences name (``named_categories``) that it has not handled: it walks up to every
  mapped one its OOP score left alone (it judges again from up close), also after it has put
  one of that category away, and searches, like for a receptacle, for a category it has not
  seen (``TidyPolicy.asked_object_goal``);
* **did the put land where asked?** an object the agent put away is judged again where it came
  to rest: when a preference finds it out of place there, on something else than the put aimed
  at (the put's ray met the floor in front of the cabinet), it is picked again
  (``TidyPolicy._note_misputs``).

Sentences a person types in the viewer join the profile and, when it came from a file, are
written back to it, so a household's preferences persist from one run to the next.
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from tidee.agent.classes import PICKUPABLE
from tidee.agent.mapping.memory import TrackedObject
from tidee.agent.reasoning.language_oop.instructions import (
    _NEGATIVE_PHRASES,
    FLOOR,
    IN_PLACE,
    OUT_OF_PLACE,
    RECEPTACLES,
    _mentions,
    _tokens,
    parse_instruction,
)
from tidee.agent.reasoning.relations import words

SURE_OBSERVATIONS = 2  # detections of a track before a preference may call it out of place
GROUP_SIMILARITY = 0.4  # a category joins a group at least this similar to the group's words...
GROUP_MARGIN = 0.08  # ...and within this of the most similar category
_FILLER = {
    "the",
    "a",
    "an",
    "my",
    "our",
    "all",
    "any",
    "every",
    "i",
    "we",
    "want",
    "like",
    "please",
    "put",
    "keep",
}
_VERBS = {"go", "goes", "belong", "belongs", "is", "are", "be", "stay", "stays", "live", "lives", "put"}


@dataclass(frozen=True)
class Preference:
    text: str
    categories: tuple[str, ...]  # the categories it applies to
    receptacle: str  # a receptacle class or "Floor"
    polarity: str  # "in_place": goes there; "out_of_place": never there
    group: str | None = None  # the words a group preference used ("toys"), None for a category

    def describe(self) -> str:
        who = f"{self.group!r} ({', '.join(self.categories)})" if self.group else self.categories[0]
        where = "goes on" if self.polarity == IN_PLACE else "never on"
        return f"{who} {where} {self.receptacle}"


def parse_preference(text: str, encoder: Any | None = None) -> Preference:
    """A :class:`Preference` from a sentence; ValueError in one line when it names no receptacle,
    or no category and no group the encoder can carry to one."""
    text = str(text).strip()
    if not text:
        raise ValueError("an empty preference: say what goes where, e.g. 'the alarm clock goes on the desk'")
    try:
        ins = parse_instruction(text)
        return Preference(text, (ins.category,), ins.receptacle, ins.polarity)
    except ValueError as e:
        # no category named, or the only one is also a receptacle ("toys go in the box"): a group
        only_receptacle = all(c in RECEPTACLES for _, c in _mentions(_tokens(text)))
        if "no receptacle" in str(e) and not only_receptacle:
            raise ValueError(str(e) + _near_receptacles(_tokens(text))) from None
        if "no object category" not in str(e) and not ("no receptacle" in str(e) and only_receptacle):
            raise
    tokens = _tokens(text)
    mentions = _mentions(tokens)
    recs = [(i, c) for i, c in mentions if c in RECEPTACLES or c == FLOOR]
    if not recs:
        raise ValueError(
            f"no receptacle in {text!r}: say where it belongs (or never belongs), e.g. 'toys go in the box'"
            + _near_receptacles(tokens)
        )
    at, receptacle = recs[0]
    negations = {w for p in _NEGATIVE_PHRASES for w in p}
    phrase = [t for t in tokens[:at] if t not in _FILLER | _VERBS | negations | {"on", "in", "of", "to"}]
    if not phrase:
        raise ValueError(
            f"no object or group in {text!r}: name a category ('the mug') or a group ('toys') before "
            "the receptacle"
        )
    group = " ".join(phrase)
    members = group_members(group, encoder)
    joined = f" {' '.join(tokens)} "
    negative = any(f" {' '.join(p)} " in joined for p in _NEGATIVE_PHRASES)
    return Preference(text, members, receptacle, OUT_OF_PLACE if negative else IN_PLACE, group)


def _near_receptacles(tokens: Sequence[str]) -> str:
    """ "; did you mean ...?" for the words after the last "on" / "in", if any name is close."""
    import difflib

    at = max((i for i, t in enumerate(tokens) if t in ("on", "in", "into", "onto")), default=-1)
    said = " ".join(t for t in tokens[at + 1 :] if t not in _FILLER)
    if not said:
        return ""
    names = {words(r): r for r in sorted(RECEPTACLES)} | {"floor": FLOOR}
    near = difflib.get_close_matches(said, list(names), n=3, cutoff=0.5)
    return f"; did you mean {' or '.join(repr(n) for n in near)}?" if near else ""


def group_members(group: str, encoder: Any | None = None) -> tuple[str, ...]:
    """The pickupable categories MiniLM puts nearest ``group``'s words, best first."""
    import numpy as np

    if encoder is None:
        from tidee.agent.reasoning.language_oop.model import TextEncoder

        encoder = TextEncoder()
    cats = sorted(PICKUPABLE)
    vecs = np.asarray(encoder.encode([words(c) for c in cats] + [group]), dtype=np.float64)
    vecs /= np.linalg.norm(vecs, axis=1, keepdims=True)
    sims = vecs[:-1] @ vecs[-1]
    best = float(sims.max())
    if best < GROUP_SIMILARITY:
        near = ", ".join(words(cats[i]) for i in np.argsort(-sims)[:3])
        raise ValueError(f"{group!r} is near no object category (nearest: {near}); name one")
    keep = [i for i in np.argsort(-sims) if sims[i] >= max(GROUP_SIMILARITY, best - GROUP_MARGIN)]
    return tuple(cats[i] for i in keep)


@dataclass
class PreferenceProfile:
    """A household's preferences (see the module docstring)."""

    preferences: list[Preference] = field(default_factory=list)
    household: str = "home"
    path: Path | None = None  # where it was loaded from; typed preferences are written back there

    @classmethod
    def load(cls, path: str | Path, encoder: Any | None = None) -> PreferenceProfile:
        path = Path(path)
        try:
            raw = path.read_text()
        except OSError as e:
            raise ValueError(f"--preferences {path}: cannot read it ({e.strerror or e})") from None
        data = _parse_file(path, raw)
        if not isinstance(data, Mapping) or not isinstance(data.get("preferences"), list):
            raise ValueError(
                f"--preferences {path}: expected an object with a 'preferences' list of sentences, "
                'e.g. {"household": "home", "preferences": ["the alarm clock goes on the desk"]}'
            )
        prefs = []
        for k, text in enumerate(data["preferences"]):
            try:
                prefs.append(parse_preference(str(text), encoder))
            except ValueError as e:
                raise ValueError(f"--preferences {path}: preference {k + 1}: {e}") from None
        return cls(prefs, str(data.get("household", "home")), path)

    def add(self, text: str, encoder: Any | None = None) -> Preference:
        """Parse and keep a typed preference (written back to the profile's file, if any)."""
        pref = parse_preference(text, encoder)
        self.preferences.append(pref)
        if self.path is not None:
            from tidee.protocol.episode_log import write_json_atomic

            write_json_atomic(
                self.path, {"household": self.household, "preferences": [p.text for p in self.preferences]}
            )
        return pref

    def about(self, category: str) -> list[Preference]:
        return [p for p in self.preferences if category in p.categories]

    def named_categories(self) -> list[str]:
        """The categories the category preferences name (not the groups' members), in the
        order they were said: the objects the policy makes sure of after its usual tidying."""
        return list(dict.fromkeys(p.categories[0] for p in self.preferences if p.group is None))

    # ------------------------------------------------------------------ the two questions
    def adjust_oop(
        self, probs: Mapping[int, float], targets: Sequence[TrackedObject], objects: Sequence[TrackedObject]
    ) -> dict[int, float]:
        """P(out of place) after the preferences (see the module docstring)."""
        return {**probs, **self.verdicts(targets, objects)}

    def verdicts(
        self, targets: Sequence[TrackedObject], objects: Sequence[TrackedObject]
    ) -> dict[int, float]:
        """What the preferences decide for the ``targets`` they name, by track id: 1.0 out of
        place, 0.0 in place; a track they decide nothing about (seen too few times to move, or
        resting elsewhere than a "never" preference forbids) is left out."""
        out: dict[int, float] = {}
        named = [t for t in targets if self.about(t.label)]
        if not named:
            return out
        from tidee.agent.reasoning.oop import support_labels

        support = support_labels(list(named), list(objects))
        for t in named:
            on = support.get(t.id)
            sure = t.n_obs >= SURE_OBSERVATIONS and not outvoted(t, objects)  # only then may it move
            for p in self.about(t.label):
                if p.polarity == OUT_OF_PLACE and on == p.receptacle and sure:
                    out[t.id] = 1.0
                elif p.polarity == IN_PLACE and on == p.receptacle:
                    out[t.id] = 0.0
                elif p.polarity == IN_PLACE and sure:
                    out[t.id] = 1.0
        return out

    def asked(self, category: str) -> list[str]:
        """The receptacles preferences ask ``category`` to go on, in the order they were said
        (one a preference also forbids is not asked)."""
        prefs = self.about(category)
        never = {p.receptacle for p in prefs if p.polarity == OUT_OF_PLACE}
        wanted = dict.fromkeys(p.receptacle for p in prefs if p.polarity == IN_PLACE)
        return [r for r in wanted if r not in never]

    def rank(self, category: str, ranked: Iterable[tuple[str, float]]) -> list[tuple[str, float]]:
        """The placement model's ranking after the preferences."""
        prefs = self.about(category)
        wanted = {p.receptacle for p in prefs if p.polarity == IN_PLACE}
        never = {p.receptacle for p in prefs if p.polarity == OUT_OF_PLACE}
        head = [(r, 1.0) for r in self.asked(category)]
        return head + [(r, s) for r, s in ranked if r not in never and r not in wanted]


def outvoted(track: TrackedObject, objects: Sequence[TrackedObject]) -> bool:
    """Whether another pickupable label claims the same spot with a higher detection score: a
    track of another label whose 3D box overlaps this one's (two labels for one object; the
    surer one is believed)."""
    for o in objects:
        if o.id == track.id or o.label == track.label or o.label not in PICKUPABLE or o.score <= track.score:
            continue
        if bool(np.all(o.box_min <= track.box_max) and np.all(track.box_min <= o.box_max)):
            return True
    return False


def _parse_file(path: Path, raw: str) -> Any:
    if path.suffix in (".yaml", ".yml"):
        try:
            import yaml
        except ImportError:
            raise ValueError(
                f"--preferences {path}: YAML needs PyYAML (pip install pyyaml); or use JSON"
            ) from None
        try:
            return yaml.safe_load(raw)
        except yaml.YAMLError as e:
            raise ValueError(f"--preferences {path}: not YAML ({str(e).splitlines()[0]})") from None
    try:
        return json.loads(raw)
    except json.JSONDecodeError as e:
        raise ValueError(f"--preferences {path}: not JSON ({e.msg}, line {e.lineno})") from None
