"""The paper's reduced TIDEE for 2-phase rearrangement (§4.5): remember the goal room, then
put the shuffled room back.

``RearrangePolicy.run()`` is one generator over both phases::

    walkthrough  look around, map the room (the tidy agent's mapping; pickupables merge only
                 within 25 cm), survey it (waypoints, then a second round with steps to spare),
                 remember every object it tracked, with each small object's footprint pooled
                 over its views (long axis, mean colour, top face's middle, or its body's
                 where the top is an edge along one side, as an open laptop's lid is; a thing
                 whose top no view saw, on a counter above the eye, takes its axis from the
                 outline of its sides) and, for each view within 2.5 m, the pose it was seen
                 from with its points and their colours; Done (the runner
                 switches to the unshuffle phase and starts a fresh map in the same start frame)
    unshuffle    look around, map the room again, the same survey for as many steps
                 match the two memories class by class (Hungarian on centroid distance and
                 colour; every track takes part, but tracks seen ``MIN_OBS`` times, and not
                 another's object tracked again, pair with each other first; a pair ruled
                 out below, or moved to beside a still object of its class, is matched again
                 without it while a sure track has no partner):
                   a pickupable now more than ``stay_m`` (and a third of its size) from its
                   match, both seen ``MIN_OBS`` times, has moved, unless another track of
                   its class holds its old place or held its new one (one whose own match
                   stayed with it is another object and does not count; by the new place,
                   only when its box does not reach there either);
                   a sure unshuffle track paired with nothing, far from every walkthrough
                   track of its class, moved from beside another object the walkthrough
                   tracked together with it: the one merged track of its class whose match
                   stayed and shrank is split (``split_merged``);
                   an openable whose box grew or shrank by ``open_m`` changed openness (on the
                   floor: when obstacle cells appeared or vanished beside it, each cell counted
                   for the nearest matched openable only)
                 each changed openable, nearest first: walk there, Close it (Open it when its
                   box shrank), not at a pixel nearer another tracked openable (try the next
                   standpoint); left as it is when the server says it already is
                 each moved object, nearest first: walk there, pick it up (when the hand
                   holds another kind of thing, put that back down where it lay and leave
                   the move: the pick hit a neighbour, or a still object taken for the one
                   believed moved), walk to its walkthrough place (where its views' rays
                   to their top-face middles cross), reach to the point there
                   (``Action.reach``; from another spot when something is in the way) and
                   put it down turned onto the walkthrough's long axis (``Action.yaw``);
                   beyond reach from every spot (a pillow in the middle of a bed), as near
                   it on the same surface as the arm goes; else on the receptacle tracked
                   under it. A put at the point
                   is then checked from the pose of a walkthrough view of the place (the
                   agent moves on a lattice from one start pose, so the pose recurs): when
                   the object's points as that view saw them fit the new frame turned or
                   shifted (``tidee.agent.mapping.view_match``), it is picked up and put
                   down again where the view saw it, turned back
                 with ``--unmatched commonsense`` (the commonsense row), then each object seen
                   twice that matches nothing of the walkthrough and that the OOP detector
                   finds out of place: tidied as the tidy agent tidies (``tidy_unmatched``)
    Done

Only the agent's own maps and detections decide; ``--perception oracle`` feeds it the
simulator's segmentation instead (a named variant in every report).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from scipy import ndimage
from scipy.optimize import linear_sum_assignment

from tidee.agent.classes import OPENABLE, PICKUPABLE, PLACEABLE_RECEPTACLES
from tidee.agent.mapping.config import MapConfig
from tidee.agent.mapping.footprint import FootprintVotes, axis_gap, footprint
from tidee.agent.mapping.geometry import project, unproject
from tidee.agent.mapping.memory import TrackedObject
from tidee.agent.mapping.view_match import FrameCrop, ObjectView, ViewMatch, grip_pixel, match_view
from tidee.agent.navigation.explore import FrontierExplorer
from tidee.agent.navigation.fmm import wrap_deg
from tidee.agent.policy.skills import (
    face_point,
    find_in_view,
    footprint_gap,
    goal_mask_near_box,
    look_around,
    mask_away_from,
    navigate,
    pitch_to,
    reachable_mask,
    rotate_to,
)
from tidee.agent.policy.tidy import Gen, TidyPolicy
from tidee.protocol.messages import INTERACT_M, Action, ActionName

SURVEY_SPACING_M = 1.2  # survey waypoints are at least this far apart
STAY_M = 0.15  # a pickupable this close to its walkthrough match has not moved
OTHER_M = 0.5  # another same-class track this close to an old or new place: no move
COLOUR_M = 2.0  # metres of matching cost per unit of mean-colour difference (RGB, 0-1)
OPEN_M = 0.15  # an openable's box growing (or shrinking) by this much changed its openness
SMALL_MERGE_M = 0.25  # the memory merges detections of a pickupable class this close (``map_config``)
MIN_OBS = 2  # tracks seen fewer times are not trusted to say that something moved
UNSURE_COST = 100.0  # matching cost (metres) added to a pair with a track seen fewer than MIN_OBS times
BANNED_COST = 10_000.0  # matching cost (metres) added to a pair ruled out as a move in an earlier round
REMATCH_ROUNDS = 4  # matchings tried at most (``match_phases``)
MERGED_RATIO = 1.4  # a walkthrough track this many times its stayed match's size (and
MERGED_GAIN_M = 0.05  # this much larger) may be that object and another one tracked as one
SAME_PIECE_M = 1.2  # two tracks of an openable class this close are one piece of furniture
STEP_UP_M = 0.7  # an openable's part in view but out of reach: walk to within this of it (x, y)
DOOR_CELLS = 8  # obstacle cells (5 cm) that must appear or vanish beside a floor-standing openable
FLOOR_STANDING_Z = 0.3  # an openable whose box starts below this stands on the floor
FLOOR_Z = 0.08  # a remembered object whose box starts this low stood on the floor
# a put reaches for the point this far above the remembered base: the eye (0.90 m) is below a
# counter top (0.92 m), so the ray to a point just over the top would meet the counter's front edge
REACH_LIFT_M = 0.10
REACH_SLACK = 0.05  # depth this much (relative) nearer than that point: something is in the way
SURFACE_TOL_M = 0.05  # the surface a pulled-in put lands on is this close to the remembered base
RETRY_PUT_M = 0.3  # a put at a point tried again stands at least this far from the spots tried
PULL_REACH_M = 1.45  # a put beyond reach is pulled in to this far from the eye (the limit: 1.5 m)
OVERHEAD_M = 0.05  # seen surfaces this much above the put's point are over it (``overhead``) ...
OVER_M = 0.1  # ... within this of it (x, y)
OVER_POINTS = 10  # ... when the frame has at least this many points there
FARTHER_M = 0.2  # ... then the next spot stands at least this much farther from the point,
BAND_M = 0.25  # ... within this of the farthest that reaches it where it can
VIEW_POINTS = 12  # a walkthrough view of a pickupable with this many points is kept ...
VIEW_NEAR_M = 2.5  # ... when they lie this close to the eye
VIEW_MARGIN_M = 0.02  # a view's points count when inside the walkthrough track's box grown by this ...
VIEW_ABOVE_M = 0.005  # ... and this much above its base (not the surface under it)
CHECK_VIEWS = 2  # a put is checked from at most this many of those views' poses ...
CHECK_STEPS = 40  # ... while this many steps are left over the reserve (a walk to a view's pose
# takes a quarter of them at most over lattice points stood on, half with the planner) ...
PENDING_STEPS = 30  # ... and this many more for each moved object still to put back
POSE_TOL_M = 0.01  # the agent stands at a view's pose when this close to it (and turned alike)
LATTICE_M = 0.25  # a move's length: every pose lies on a lattice this fine from the start pose
MEND_REACH_M = 1.3  # a mend picks the object from at most this far from the eye (the limit: 1.5 m)
REPLANS = 3  # a walk over the lattice plans again round a blocked move this many times at most
FIT_RATIO = 0.5  # a turn and shift fits the frame with at most this share of the mean misfit of none ...
FIT_MAX = 0.25  # ... and at most this much ...
FIT_SEEN = 0.6  # ... with this share of the points in front of what the frame shows: believed
OFF_M = 0.01  # a put believed this far off (x, y) ...
OFF_DEG = 8.0  # ... or turned this far (folded to a half turn) is mended
MENDS = 2  # at most this many times per object
GONE_M = 0.01  # a pixel whose surface went this much farther away when a pick took something ...
SAME_THING_M = 0.3  # ... and whose depth was this close to the pick pixel's: the thing taken


class WalkthroughOver(Exception):
    """Thrown into the policy by the runner when the walkthrough's step budget runs out."""


@dataclass(frozen=True)
class Seen:
    """What a phase remembers of one tracked object (start frame, metres); for a pickupable
    also its footprint pooled over the views (``tidee.agent.mapping.footprint``): the long
    axis's heading (degrees, None when it showed none), its mean colour and where it stood,
    from its views' middles (each its top face's, or its body's where that is an edge along one
    side: ``FootprintVotes.middle``; x, y; None when no view had one)."""

    label: str
    centroid: np.ndarray
    box_min: np.ndarray
    box_max: np.ndarray
    n_obs: int
    axis_deg: float | None = None
    colour: np.ndarray | None = None  # mean RGB (0-1) of its points
    middle: tuple[float, float] | None = None  # where it stood (x, y), from its views' middles
    track_id: int | None = None  # its track in that phase's memory (None: not one track's own)

    @staticmethod
    def of(o: TrackedObject, votes: FootprintVotes | None = None) -> Seen:
        if votes is None:
            return Seen(
                o.label, o.centroid.copy(), o.box_min.copy(), o.box_max.copy(), o.n_obs, track_id=o.id
            )
        return Seen(
            o.label,
            o.centroid.copy(),
            o.box_min.copy(),
            o.box_max.copy(),
            o.n_obs,
            votes.heading_guess(),
            votes.colour,
            votes.middle(),
            o.id,
        )


@dataclass
class Move:
    """A pickupable the agent believes moved: where it is now and where it was."""

    now: TrackedObject
    then: Seen
    distance: float


@dataclass
class Toggle:
    """An openable the agent believes changed openness (``opened``: its box grew)."""

    now: TrackedObject
    then: Seen
    opened: bool
    change_m: float
    cells: tuple[int, int] | None = None  # obstacle cells that appeared / vanished beside it, when checked


def colour_gap(a: np.ndarray | None, b: np.ndarray | None) -> float:
    """How different two mean colours (RGB, 0-1) are; 0 when either is unknown."""
    return 0.0 if a is None or b is None else float(np.linalg.norm(a - b))


def _pairs(
    then: list[Seen],
    now: list[TrackedObject],
    colours: dict[int, np.ndarray] | None = None,
    min_obs: int = 1,
    banned: frozenset[tuple[int, int]] = frozenset(),
    kept: frozenset[tuple[int, int]] = frozenset(),
) -> list[tuple[Seen, TrackedObject, float]]:
    """One-to-one matching of same-class tracks (Hungarian) on centroid distance plus
    ``COLOUR_M`` per unit of colour difference (``colours``: track id -> the unshuffle's mean
    colour), so two mugs that both moved go back to their own places when they look different;
    plus ``UNSURE_COST`` for a pair in which either track was seen fewer than ``min_obs``
    times, so the matching pairs as many sure tracks with each other as it can before the
    distances count (a glimpse nearer a sure track's match does not take it); plus
    ``BANNED_COST`` for a pair in ``banned`` (``id()`` of its walkthrough and unshuffle tracks),
    less as much for one in ``kept``. A track that is another's object tracked again
    (``_tracked_twice``) pairs as one seen fewer than ``min_obs`` times does. Each pair comes
    with its centroid distance."""
    colours = colours or {}
    out = []
    for label in sorted({s.label for s in then} & {o.label for o in now}):
        a = [s for s in then if s.label == label]
        b = [o for o in now if o.label == label]
        dist = np.linalg.norm(
            np.array([s.centroid for s in a])[:, None, :] - np.array([o.centroid for o in b])[None, :, :],
            axis=2,
        )
        look = np.array([[colour_gap(s.colour, colours.get(o.id)) for o in b] for s in a])
        twice_a, twice_b = _tracked_twice(a), _tracked_twice(b)
        unsure = (
            np.array([s.n_obs < min_obs or id(s) in twice_a for s in a])[:, None]
            | np.array([o.n_obs < min_obs or id(o) in twice_b for o in b])[None, :]
        )
        ban = np.array([[(id(s), id(o)) in banned for o in b] for s in a], float)
        ban -= np.array([[(id(s), id(o)) in kept for o in b] for s in a])
        rows, cols = linear_sum_assignment(dist + COLOUR_M * look + UNSURE_COST * unsure + BANNED_COST * ban)
        out += [(a[r], b[c], float(dist[r, c])) for r, c in zip(rows, cols)]
    return out


def _tracked_twice(tracks: list[Any]) -> set[int]:
    """``id()`` of the tracks (of one phase and class) that are another's object tracked
    again (``same_object`` with a track seen more often)."""
    kept: list[Any] = []
    twice = set()
    for t in sorted(tracks, key=lambda t: -t.n_obs):
        if any(same_object(t, k) for k in kept):
            twice.add(id(t))
        else:
            kept.append(t)
    return twice


def _size(t: Seen | TrackedObject) -> float:
    """A track's larger footprint side (m)."""
    return float(np.max(t.box_max[:2] - t.box_min[:2]))


def _overlap(a: Seen | TrackedObject, b: Seen | TrackedObject, size: Any = max) -> bool:
    """Two tracks whose centres lie closer (x, y) than half the larger one's size (``size``:
    or the smaller one's)."""
    return float(np.linalg.norm(a.centroid[:2] - b.centroid[:2])) < 0.5 * size(_size(a), _size(b))


def _stayed(a: Seen | TrackedObject, d: float, stay_m: float) -> bool:
    """A track ``d`` metres from its match in the other phase stayed: nearer than ``stay_m`` and
    a third of its size (nearer, the metric counts it in place)."""
    return d <= max(stay_m, _size(a) / 3)


def _paired(pairs: list[tuple[Seen, TrackedObject, float]]) -> set[int]:
    """``id()`` of every track of a matching's pairs, of both phases."""
    return {id(s) for s, _, _ in pairs} | {id(o) for _, o, _ in pairs}


def same_object(a: Seen | TrackedObject, b: Seen | TrackedObject) -> bool:
    """Two tracks of one phase and class whose centres lie closer (x, y) than half the larger
    one's size: one object tracked twice (two tracks of one basketball), not two objects."""
    return a is not b and a.label == b.label and _overlap(a, b)


def find_moves(*args: Any, **kwargs: Any) -> list[Move]:
    """The moves ``match_phases`` finds."""
    return match_phases(*args, **kwargs)[0]


def match_phases(
    then: list[Seen],
    now: list[TrackedObject],
    stay_m: float = STAY_M,
    min_obs: int = MIN_OBS,
    colours: dict[int, np.ndarray] | None = None,
    other_m: float = OTHER_M,
) -> tuple[list[Move], list[tuple[Seen, TrackedObject, float]]]:
    """The moves of pickupables matched across the phases (every track takes part, sure ones pair first:
    ``_pairs``), both seen at least ``min_obs`` times, that are now farther from where they
    were than ``stay_m`` and than a third of their size (nearer, an object of that size still
    overlaps its old box by IoU 0.5: the metric counts it in place), whose old place no other
    track of their class now holds and whose new place none held in the walkthrough, within
    ``other_m`` (so a second instance or a stray track is not taken for a move). A track by the
    old place does not count when it is explained: its own walkthrough match stayed with it (a
    second apple that never moved, 30 cm from the first's old place) and is not the moved
    object tracked twice (``same_object``). A walkthrough track by the new place is explained
    the same way (its unshuffle match stayed with it), and only when its box does not reach the
    new place either: the walkthrough's memory merges two objects 25 cm apart into one track
    (two remotes on a coffee table) whose box spans both, and one of them, staying, would
    explain it while the other is the "mover"; a second soap bottle 20 cm from where the first
    was put, still where it stood, has a box of its own and is another object.

    A pair ruled out so is matched again without it (up to ``REMATCH_ROUNDS`` matchings) while
    a sure track of its class has no partner: a walkthrough glimpse of a second scrub brush, or
    the walkthrough's track of two remotes together, nearer the moved brush's (or remote's) new
    place than its own walkthrough track was, takes it in the first matching and leaves that
    track paired with nothing. So is a move to within ``other_m`` of another object of its
    class that stayed (allowed: a soap bottle put beside a second one) while a sure unshuffle
    track of its class has no partner: the track beside the still one is more likely an object
    the walkthrough did not see (the second of two salt shakers side by side), and the one
    paired with nothing the object that moved. A walkthrough track that was two objects is
    split after the matching (``split_merged``).

    Returns the moves and the matching they came from (``_pairs``'s, the last tried)."""
    then = [s for s in then if s.label in PICKUPABLE]
    now = [o for o in now if o.label in PICKUPABLE]
    twice = set().union(
        *(
            _tracked_twice([t for t in ts if t.label == c])
            for ts in (then, now)
            for c in {t.label for t in ts}
        )
    )
    banned: frozenset[tuple[int, int]] = frozenset()  # pairs ruled out
    kept: frozenset[tuple[int, int]] = frozenset()  # pairs that stayed or moved
    for _ in range(REMATCH_ROUNDS):
        pairs = _pairs(then, now, colours, min_obs, banned, kept)
        moves, ruled_out, stays, beside = _judge(pairs, then, now, stay_m, min_obs, other_m, twice)
        kept |= {(id(m.then), id(m.now)) for m in moves if all(m is not b for b in beside)} | {
            (id(s), id(o)) for s, o in stays
        }
        # a pair ruled out, or a move to beside another object of its class, takes part in no
        # other matching while a sure track of its class is left without a partner (the object
        # that did move, paired with nothing; the track beside the other, of an object the
        # walkthrough did not see)
        paired = _paired(pairs)
        left = {t.label for t in [*then, *now] if id(t) not in paired and t.n_obs >= min_obs}
        doubted = [*ruled_out, *((m.then, m.now) for m in beside)]
        more = {(id(s), id(o)) for s, o in doubted if s.label in left} - banned
        if not more:
            break
        banned |= more
    split = split_merged(pairs, then, now, stay_m, min_obs, other_m, [m.now for m in moves])
    # one object under two labels: the label seen more often says what it is (``split_merged``)
    moves = [m for m in moves if not any(_overlap(x.now, m.now, min) for x in split)]
    return moves + split, pairs


def split_merged(
    pairs: list[tuple[Seen, TrackedObject, float]],
    then: list[Seen],
    now: list[TrackedObject],
    stay_m: float = STAY_M,
    min_obs: int = MIN_OBS,
    other_m: float = OTHER_M,
    moving: list[TrackedObject] | None = None,
) -> list[Move]:
    """Moves out of walkthrough tracks that were two objects: the walkthrough's memory merges
    two remotes side by side into one track, centred between them, and when one of them is
    moved the other alone stays matched with it, while the moved one's unshuffle track has no
    partner at all. For each such track (sure, unpaired, farther than ``other_m`` from every
    walkthrough track of its class; the most seen first) the one walkthrough track of its class
    that is sure, whose match stayed and is ``MERGED_RATIO`` times smaller and ``MERGED_GAIN_M``
    narrower than it, is split: the moved object stood where the stayer mirrors through the
    merged centre (2 x merged - stayer), its box the moved track's size there. No move when
    two tracks could be the merge, when a track already believed moved (``moving``) and seen
    at least as often lies within half the smaller one's size of it (one object under two
    labels, a vase also taken for a soap bottle; not a remote on a pillow: the moves of such
    tracks seen less often are dropped by ``match_phases``), or when the place found lies closer to the stayer
    than half their sizes' mean (two objects do not stand inside each other: a big box matched
    with a smaller view of itself)."""
    paired = _paired(pairs)
    merged = [
        (s, o)
        for s, o, d in pairs
        if s.n_obs >= min_obs
        and _stayed(s, d, stay_m)
        and _size(s) >= MERGED_RATIO * _size(o)
        and _size(s) - _size(o) >= MERGED_GAIN_M
    ]
    used: set[int] = set()
    moves = []
    for o in sorted(now, key=lambda t: -t.n_obs):
        if id(o) in paired or o.n_obs < min_obs:
            continue
        if any(
            s.label == o.label and np.linalg.norm(s.centroid[:2] - o.centroid[:2]) <= other_m for s in then
        ):
            continue
        if any(p.n_obs >= o.n_obs and _overlap(p, o, min) for p in moving or []):
            continue  # one object under two labels, put back as the other
        cands = [(s, stayer) for s, stayer in merged if s.label == o.label]
        if len(cands) != 1 or id(cands[0][0]) in used:
            continue
        s, stayer = cands[0]
        used.add(id(s))
        xy = 2 * s.centroid[:2] - stayer.centroid[:2]
        if np.linalg.norm(xy - stayer.centroid[:2]) < 0.25 * (_size(o) + _size(stayer)):
            continue
        half = (o.box_max[:2] - o.box_min[:2]) / 2
        centre = np.r_[xy, s.centroid[2]]
        box_min = np.r_[xy - half, s.box_min[2]]
        box_max = np.r_[xy + half, s.box_max[2]]
        split = Seen(o.label, centre, box_min, box_max, s.n_obs, middle=(float(xy[0]), float(xy[1])))
        moves.append(Move(o, split, float(np.linalg.norm(o.centroid - centre))))
    return moves


def _judge(
    pairs: list[tuple[Seen, TrackedObject, float]],
    then: list[Seen],
    now: list[TrackedObject],
    stay_m: float,
    min_obs: int,
    other_m: float,
    twice: set[int],
) -> tuple[list[Move], list[tuple[Seen, TrackedObject]], list[tuple[Seen, TrackedObject]], list[Move]]:
    """The moves among one matching's ``pairs`` (``match_phases``), the pairs of sure tracks
    that moved but were ruled out (their old place taken or new place held), those that
    stayed, and the moves to within ``other_m`` of a walkthrough track of their class that
    holds its own place (``holds_elsewhere``: among the moves too). A pair of two tracks that
    are each another's object tracked again (``twice``: ``id()`` of such tracks) is that other
    pair's object: no move of its own."""
    match_of = {id(o): (s, d) for s, o, d in pairs}  # unshuffle track -> its walkthrough match
    now_of = {id(s): (o, d) for s, o, d in pairs}  # walkthrough track -> its unshuffle match

    def explained(track: TrackedObject, mover: Seen) -> bool:
        """``track`` (an unshuffle track by ``mover``'s old place) is another object: its
        walkthrough match stayed with it and is not ``mover`` tracked twice (it is not ``mover``
        itself: that is paired with the moved track)."""
        match = match_of.get(id(track))
        return match is not None and _stayed(*match, stay_m) and not same_object(match[0], mover)

    def holds_elsewhere(track: Seen, mover: TrackedObject) -> bool:
        """``track`` (a walkthrough track by ``mover``'s new place) is another object that is
        still where it was: its unshuffle match stayed with it and is not ``mover`` tracked
        twice, and its box does not reach ``mover``'s centre (x, y)."""
        match = now_of.get(id(track))
        if match is None or not _stayed(track, match[1], stay_m) or same_object(match[0], mover):
            return False
        return box_gap(track.box_min[:2], track.box_max[:2], mover.centroid[:2]) > 0.0

    moves, ruled_out, stays, beside = [], [], [], []
    for s, o, d in pairs:
        if s.n_obs < min_obs or o.n_obs < min_obs or (id(s) in twice and id(o) in twice):
            continue
        if _stayed(s, d, stay_m):
            stays.append((s, o))
            continue
        # every track counts against a move, those seen once too (by the old place: unless explained)
        old_taken = any(
            p.label == s.label
            and p is not o
            and np.linalg.norm(p.centroid - s.centroid) <= other_m
            and not explained(p, s)
            for p in now
        )
        by_new = [
            q
            for q in then
            if q.label == o.label and q is not s and np.linalg.norm(q.centroid - o.centroid) <= other_m
        ]
        new_held = any(not holds_elsewhere(q, o) for q in by_new)
        if not old_taken and not new_held:
            moves.append(Move(o, s, d))
            if by_new:
                beside.append(moves[-1])
        else:
            ruled_out.append((s, o))
    return moves, ruled_out, stays, beside


def box_change(then: Seen, now: TrackedObject) -> tuple[float, float]:
    """(grown, shrunk): how far, in metres, the box's footprint reaches beyond the other's on
    its most changed side (a door swung open or a drawer pulled out grows it)."""
    grown = max(
        float(np.max(then.box_min[:2] - now.box_min[:2])), float(np.max(now.box_max[:2] - then.box_max[:2]))
    )
    shrunk = max(
        float(np.max(now.box_min[:2] - then.box_min[:2])), float(np.max(then.box_max[:2] - now.box_max[:2]))
    )
    return grown, shrunk


@dataclass(frozen=True)
class Occupancy:
    """A phase's 2D obstacle map and the cells it observed (``SemanticMapper``'s, same grid)."""

    obstacle: np.ndarray
    seen: np.ndarray

    @staticmethod
    def of(mapper: Any) -> Occupancy:
        return Occupancy(mapper.obstacle.copy(), mapper.explored | mapper.obstacle)


def door_evidence(
    grid: Any,
    then: Occupancy,
    now: Occupancy,
    box_min: np.ndarray,
    box_max: np.ndarray,
    reach_m: float = 0.9,
    others: list[tuple[np.ndarray, np.ndarray]] | None = None,
) -> tuple[int, int]:
    """(appeared, vanished): cells within ``reach_m`` of a footprint, observed in both phases, that
    are obstacles now but were free then (a door swung open, a drawer pulled out) and the
    other way round. The depth map decides, not the detector's boxes. ``others``: the other
    openables' footprints (box min, max corners); a cell nearer one of them than this footprint
    counts for that one, not this one (a fridge door swinging open beside a cabinet); inside
    two footprints, for the one whose centre is nearer."""
    x, y = grid.centres()

    def nearness(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(gap to the footprint, distance to its centre) per cell."""
        return footprint_gap(lo, hi, x, y), np.hypot(x - (lo[0] + hi[0]) / 2, y - (lo[1] + hi[1]) / 2)

    gap, centre = nearness(box_min, box_max)
    near = gap <= reach_m
    for lo, hi in others or []:
        other_gap, other_centre = nearness(lo, hi)
        near &= (other_gap > gap) | ((other_gap == gap) & (other_centre >= centre))
    both = near & then.seen & now.seen
    return int((both & now.obstacle & ~then.obstacle).sum()), int(
        (both & then.obstacle & ~now.obstacle).sum()
    )


def find_toggles(
    then: list[Seen],
    now: list[TrackedObject],
    open_m: float = OPEN_M,
    maps: tuple[Any, Occupancy, Occupancy] | None = None,
    min_cells: int = DOOR_CELLS,
) -> list[Toggle]:
    """Openables matched across the phases whose box grew or shrank by more than ``open_m``.
    With ``maps`` (grid, walkthrough and unshuffle occupancy), a piece standing on the floor
    must also show at least ``min_cells`` obstacle cells appear (or vanish) beside it, and
    that decides the direction: a big piece's boxes differ between views far more than its
    door does. A cell counts only for the matched openable whose footprint (both phases' boxes)
    is nearest it."""
    then = [s for s in then if s.label in OPENABLE]
    now = [o for o in now if o.label in OPENABLE]
    pairs = [(s, o) for s, o, d in _pairs(then, now) if d <= 1.0]  # farther: not the same piece
    spans = [(np.minimum(s.box_min, o.box_min), np.maximum(s.box_max, o.box_max)) for s, o in pairs]
    toggles = []
    for k, (s, o) in enumerate(pairs):
        grown, shrunk = box_change(s, o)
        if max(grown, shrunk) <= open_m:
            continue
        opened = grown >= shrunk
        if maps is not None and min(float(s.box_min[2]), float(o.box_min[2])) < FLOOR_STANDING_Z:
            grid, before, after = maps
            lo, hi = spans[k]
            others = spans[:k] + spans[k + 1 :]
            appeared, vanished = door_evidence(grid, before, after, lo, hi, others=others)
            if max(appeared, vanished) < min_cells:
                continue
            opened = appeared >= vanished
            cells = (appeared, vanished)
        else:
            cells = None
        toggles.append(Toggle(o, s, opened=opened, change_m=max(grown, shrunk), cells=cells))
    # One piece of furniture can leave two tracks (an open door seen apart from its body): keep
    # the larger change, so a second track never toggles it back.
    kept: list[Toggle] = []
    for t in sorted(toggles, key=lambda t: -t.change_m):
        if all(
            k.now.label != t.now.label
            or np.linalg.norm(k.now.centroid[:2] - t.now.centroid[:2]) > SAME_PIECE_M
            for k in kept
        ):
            kept.append(t)
    return kept


def box_gap(box_min: np.ndarray, box_max: np.ndarray, point: np.ndarray) -> float:
    """Metres from a 3D point to an axis-aligned box; 0 inside it."""
    return float(np.linalg.norm(np.maximum(np.maximum(box_min - point, point - box_max), 0.0)))


def neighbour_at(
    point: np.ndarray, target: TrackedObject, tracks: Iterable[TrackedObject]
) -> TrackedObject | None:
    """Another tracked openable whose box is nearer the 3D ``point`` than ``target``'s (the
    nearest such), or None. A track of the target's class within ``SAME_PIECE_M`` of it is
    the same piece (its open door tracked apart), not another."""
    own = box_gap(target.box_min, target.box_max, point)
    best: tuple[float, TrackedObject] | None = None
    for o in tracks:
        if o is target or o.label not in OPENABLE:
            continue
        if o.label == target.label and np.linalg.norm(o.centroid[:2] - target.centroid[:2]) <= SAME_PIECE_M:
            continue
        gap = box_gap(o.box_min, o.box_max, point)
        if gap < own and (best is None or gap < best[0]):
            best = (gap, o)
    return best[1] if best else None


def where_it_lay(before: Any, after: Any, pick: Action | None) -> np.ndarray | None:
    """The middle (start frame) of what a pick took, from two frames of one pose: the pixels
    round the pick's pixel whose surface went ``GONE_M`` farther away (or out of range) in the
    frame ``after`` it and lay within ``SAME_THING_M`` of its depth, lifted with the depth
    ``before``; None when the pick's pixel did not change or ``before`` is not of the same
    pose. ``GONE_M`` is small because a thing lying flat is thin: a book is 3 cm thick."""
    if before is None or after is None or pick is None or pick.x is None or pick.y is None:
        return None
    if not np.array_equal(before.camera_pose, after.camera_pose):
        return None
    d0, d1 = np.asarray(before.depth, float), np.asarray(after.depth, float)
    h, w = d0.shape
    u, v = min(int(pick.x * w), w - 1), min(int(pick.y * h), h - 1)
    with np.errstate(invalid="ignore"):
        gone = np.isfinite(d0) & (d0 > 0) & ~(d1 - d0 <= GONE_M) & (np.abs(d0 - d0[v, u]) <= SAME_THING_M)
    if not gone[v, u]:
        return None
    parts, _ = ndimage.label(gone)
    points, _ = unproject(d0, before.intrinsics, before.camera_pose, mask=parts == parts[v, u])
    return points.mean(axis=0) if len(points) else None


def lattice_key(pose: tuple[float, ...]) -> tuple[int, int]:
    """The lattice point (moves of ``LATTICE_M`` from the start pose) nearest a pose's (x, y)."""
    return int(round(pose[0] / LATTICE_M)), int(round(pose[1] / LATTICE_M))


def lattice_path(
    stood: set[tuple[int, int]],
    start: tuple[int, int],
    goal: tuple[int, int],
    most: int,
    blocked: set[frozenset[tuple[int, int]]] | None = None,
) -> list[tuple[int, int]] | None:
    """The fewest moves (each one lattice step along x or y, none of the pairs in
    ``blocked``) from ``start`` to ``goal`` through points in ``stood``, at most ``most``:
    the points after ``start``; None when there is no such path."""
    if start == goal:
        return []
    if goal not in stood:
        return None
    came: dict[tuple[int, int], tuple[int, int]] = {start: start}
    frontier = [start]
    for _ in range(most):
        nxt: list[tuple[int, int]] = []
        for i, j in frontier:
            for key in ((i + 1, j), (i - 1, j), (i, j + 1), (i, j - 1)):
                if key in came or key not in stood or (blocked and frozenset(((i, j), key)) in blocked):
                    continue
                came[key] = (i, j)
                if key == goal:
                    path = [key]
                    while came[path[-1]] != start:
                        path.append(came[path[-1]])
                    return path[::-1]
                nxt.append(key)
        frontier = nxt
    return None


def lattice_move(yaw_deg: float, here: tuple[int, int], there: tuple[int, int]) -> ActionName | None:
    """The move (ahead, back, left or right, no turn) from lattice point ``here`` to its
    neighbour ``there`` for an agent heading ``yaw_deg`` (a multiple of 90)."""
    want = (there[0] - here[0], there[1] - here[1])
    t = np.radians(yaw_deg)
    for name, (fwd, left) in (
        (ActionName.MoveAhead, (1, 0)),
        (ActionName.MoveBack, (-1, 0)),
        (ActionName.MoveLeft, (0, 1)),
        (ActionName.MoveRight, (0, -1)),
    ):
        dx = fwd * np.cos(t) - left * np.sin(t)
        dy = fwd * np.sin(t) + left * np.cos(t)
        if (int(round(dx)), int(round(dy))) == want:
            return name
    return None


def put_turn(goal_axis: float | None, held: tuple[float, float] | None, heading: float) -> float | None:
    """The put's turn (degrees, ``Action.yaw``) that lays a held object's long axis at
    ``goal_axis`` (its heading in the walkthrough): ``held`` is (the axis's heading as it lay
    when picked up, the agent's heading then); it has turned with the agent, now at
    ``heading``. None (put it down along the agent's heading) when either axis is unknown."""
    if goal_axis is None or held is None:
        return None
    lay, heading_then = held
    return axis_gap(goal_axis, lay + heading - heading_then)


class RearrangePolicy(TidyPolicy):
    """Walkthrough, then unshuffle (module docstring). Reuses the tidy agent's mapping,
    approach, pick and put skills; needs no OOP detector and no placement model, except for
    ``--unmatched commonsense``."""

    @staticmethod
    def map_config(config: MapConfig) -> MapConfig:
        """Pickupables merge only within ``SMALL_MERGE_M``: the memory's default (1 m, the
        original TIDEE's) makes one track of two apples on a counter, whose centroid lies
        between their places."""
        return replace(config, small_merge_distance=SMALL_MERGE_M)

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.votes: dict[tuple[str | None, int], FootprintVotes] = {}  # (phase, track id): its views
        self.views: dict[int, list[FrameCrop]] = {}  # walkthrough track id: its views within VIEW_NEAR_M
        self.aimed: np.ndarray | None = None  # the point the last put reached for
        self.pending = 0  # moved objects still to put back after the one in hand
        self.stood: set[tuple[int, int]] = set()  # lattice points stood on, both phases (``lattice_key``)
        self.walkthrough: list[Seen] = []
        self.unshuffle: list[Seen] = []  # the unshuffle's memory as the phases were compared
        self.moves: list[Move] = []
        self.toggles: list[Toggle] = []

    def score_objects(self, touched: list[TrackedObject] | None = None) -> None:
        """No out-of-place scoring (a rearrangement compares the room with its walkthrough):
        each frame's detections of pickupables add their footprints to their tracks' votes."""
        obs, mapper = self.body.obs, self.body.mapper
        if obs is None:
            return
        self.stood.add(lattice_key(self.body.pose))
        shape = obs.depth.shape
        for det, tid in zip(self.body.detections, mapper.last_track_ids):
            if tid is None or det.label not in PICKUPABLE:
                continue
            region = det.region(shape)
            if region[0].any() or region[-1].any() or region[:, 0].any() or region[:, -1].any():
                continue  # cut by the image's edge: a part of it, off centre
            pts, pix = unproject(obs.depth, obs.intrinsics, obs.camera_pose, mask=region)
            fp = footprint(pts, np.asarray(obs.rgb).reshape(-1, 3)[pix], eye=obs.camera_pose[:3, 3])
            if fp is not None:
                self.votes.setdefault((obs.phase, tid), FootprintVotes()).add(fp, obs.camera_pose[:2, 3])
            if obs.phase == "walkthrough" and len(pts) >= VIEW_POINTS:
                eye = obs.camera_pose[:3, 3]
                if float(np.linalg.norm(pts.mean(axis=0) - eye)) <= VIEW_NEAR_M:
                    crop = FrameCrop.of(
                        obs.rgb, obs.depth, obs.intrinsics, obs.camera_pose, region, self.body.pose
                    )
                    if crop is not None:
                        self.views.setdefault(tid, []).append(crop)

    def seen(self, o: TrackedObject) -> Seen:
        """``o`` as this phase saw it, with its pooled footprint."""
        assert self.body.obs is not None
        return Seen.of(o, self.votes.get((self.body.obs.phase, o.id)))

    def run(self) -> Gen:
        self.state.phase = "walkthrough"
        try:
            yield from look_around(self.body)
            yield from self.map_room()
            yield from self.survey(self.body.steps_left() - 1)
        except WalkthroughOver:
            pass
        walk_steps = int(self.body.obs.step)
        self.walkthrough = [self.seen(o) for o in self.body.mapper.memory]
        walk_map = Occupancy.of(self.body.mapper)
        self.event("walkthrough_done", steps=self.body.obs.step, objects=len(self.walkthrough))
        yield Action(ActionName.Done)  # the runner starts the unshuffle phase
        self.frontier = FrontierExplorer(self.body.mapper.grid)
        self.state.phase = "mapping"
        yield from look_around(self.body)
        yield from self.map_room()
        # As long a look as the walkthrough's, so both memories saw the room alike.
        yield from self.survey(
            min(walk_steps - self.body.obs.step, self.body.steps_left() - self.p.reserve_steps)
        )
        now = list(self.body.mapper.memory)
        self.unshuffle = [self.seen(o) for o in now]
        maps = (self.body.mapper.grid, walk_map, Occupancy.of(self.body.mapper))
        self.toggles = find_toggles(self.walkthrough, now, maps=maps)
        colours = {o.id: s.colour for o, s in zip(now, self.unshuffle) if s.colour is not None}
        self.moves, pairs = match_phases(self.walkthrough, now, colours=colours)
        self.event(
            "compared",  # every same-class pairing of the two memories (the log's account of the decision)
            pairs=[
                [
                    s.label,
                    round(d, 3),
                    s.n_obs,
                    o.n_obs,
                    [round(float(v), 3) for v in s.centroid],
                    [round(float(v), 3) for v in o.centroid],
                ]
                for s, o, d in pairs
            ],
        )
        self.state.oop_found = len(self.moves) + len(self.toggles)
        for t in self.toggles:
            t.now.out_of_place = True
            self.event(
                "openness_changed",
                label=t.now.label,
                track_id=t.now.id,
                opened=t.opened,
                change_m=round(t.change_m, 2),
                cells=t.cells,
                centroid=[round(float(v), 3) for v in t.now.centroid],
            )
        for m in self.moves:
            m.now.out_of_place = True
            self.event(
                "moved",
                label=m.now.label,
                track_id=m.now.id,
                distance=round(m.distance, 2),
                centroid=[round(float(v), 3) for v in m.now.centroid],
                goal=[round(float(v), 3) for v in m.then.centroid],
            )
        for t in sorted(self.toggles, key=self._distance):
            if self.body.steps_left() <= self.p.reserve_steps:
                break
            yield from self.restore_openness(t)
        moves = sorted(self.moves, key=self._distance)
        for k, m in enumerate(moves):
            if self.body.steps_left() <= self.p.reserve_steps:
                break
            self.pending = len(moves) - k - 1
            yield from self.put_back(m)
        if self.p.unmatched == "commonsense":
            yield from self.tidy_unmatched(now, pairs)
        self.state.phase = "done"
        self.state.end_reason = self.state.end_reason or "restored what it found"
        self.event("done", reason=self.state.end_reason, fixed=self.state.objects_fixed)
        yield Action(ActionName.Done)

    def tidy_unmatched(self, now: list[TrackedObject], pairs: list[tuple[Seen, TrackedObject, float]]) -> Gen:
        """The tidy agent's commonsense for what the walkthrough cannot explain (``--unmatched
        commonsense``): each pickupable of the unshuffle's memory seen ``MIN_OBS`` times that
        paired with no walkthrough track and was not believed moved, still tracked, and that
        the OOP detector finds out of place, nearest first, is tidied as the tidy agent tidies
        (approach, pick, put where the placement model ranks first). It goes to a plausible
        place, not to its own: RoomR counts it fixed only if that is where it was."""
        paired = {o.id for _, o, _ in pairs} | {m.now.id for m in self.moves}
        tracked = {o.id: o for o in self.body.mapper.memory}
        unmatched = [
            tracked[o.id]
            for o in now
            if o.label in PICKUPABLE and o.id not in paired and o.id in tracked and o.n_obs >= MIN_OBS
        ]
        if not unmatched:
            return
        probs = self.oop.score_all(unmatched, list(self.body.mapper.memory), self.room_type)
        out = [o for o in unmatched if probs[o.id] >= self.p.oop_threshold]
        for o in out:
            o.oop_prob, o.out_of_place = float(probs[o.id]), True
            self.event(
                "unmatched_oop",
                label=o.label,
                track_id=o.id,
                oop_prob=round(float(probs[o.id]), 3),
                centroid=[round(float(v), 3) for v in o.centroid],
            )
        for o in sorted(out, key=lambda t: float(np.linalg.norm(t.centroid[:2] - self.body.xy))):
            if self.body.steps_left() <= self.p.reserve_steps:
                break
            if o.id in {t.id for t in self.body.mapper.memory}:  # not taken along by an earlier pick
                yield from self.tidy_object(o)

    def survey(self, budget: int) -> Gen:
        """Walk to waypoints spread over the reachable map (farthest-point order from the
        agent, ``SURVEY_SPACING_M`` apart, nearest next) and look around at each, looking down
        at receptacle tops, until ``budget`` steps are spent; with steps to spare, a second
        round between the first's waypoints (``SURVEY_SPACING_M`` x 2/3 from every one so
        far): more views of each object make its place and heading surer."""
        start = self.body.obs.step
        mapper = self.body.mapper
        reach = reachable_mask(self.body)
        g = mapper.grid
        cells = np.argwhere(reach)
        if len(cells) == 0 or budget <= 0:
            return
        pts = g.origin + (cells + 0.5) * g.cell
        dist = np.linalg.norm(pts - self.body.xy, axis=1)
        for spacing in (SURVEY_SPACING_M, SURVEY_SPACING_M * 2 / 3):
            chosen: list[np.ndarray] = []
            while len(chosen) < 32:
                k = int(np.argmax(dist))
                if dist[k] < spacing:
                    break
                chosen.append(pts[k])
                dist = np.minimum(dist, np.linalg.norm(pts - pts[k], axis=1))
            here = self.body.xy
            while chosen and self.body.obs.step - start < budget:
                k = int(np.argmin([np.linalg.norm(p - here) for p in chosen]))
                goal = chosen.pop(k)
                left = budget - (self.body.obs.step - start)
                yield from navigate(
                    self.body,
                    goal_xy=(float(goal[0]), float(goal[1])),
                    budget=min(self.p.goal_step_budget, left),
                )
                here = self.body.xy
                for pitch in (30.0, 60.0):
                    if budget - (self.body.obs.step - start) < 6:
                        return
                    yield from pitch_to(self.body, pitch)
                    for _ in range(4):
                        yield Action(ActionName.RotateLeft)

    def _distance(self, item: Move | Toggle) -> float:
        return float(np.linalg.norm(item.now.centroid[:2] - self.body.xy))

    # ------------------------------------------------------------------ openness
    def restore_openness(self, t: Toggle) -> Gen:
        """Walk to the openable and set it back: Close when its box grew, Open when it shrank.
        A pixel nearer another tracked openable than this one is not acted on (``neighbour_at``:
        that would toggle the neighbour); the next standpoint is tried. A part in view beyond
        reach (the walk ends by the box's near edge, the end of an open door) is walked up to
        first (``STEP_UP_M``). When the server says it already is, it is left so: either it is
        as the walkthrough saw it or the direction was guessed wrong, and the other action was
        making things worse more often than not."""
        st = self.state
        st.target, st.phase, st.target_receptacle = t.now, "approaching", None
        shape = self.body.obs.depth.shape
        name = ActionName.CloseObject if t.opened else ActionName.OpenObject
        for radius in (0.6, 0.85):
            mask = goal_mask_near_box(self.body.mapper, t.now.box_min, t.now.box_max, radius)
            yield from navigate(self.body, goal_mask=mask, stop_radius=0.05, budget=self.p.goal_step_budget)
            yield from face_point(self.body, t.now.centroid)
            sighting = find_in_view(self.body, t.now, max_pixel_gap=0.3)
            if sighting is not None and sighting.distance > self.p.interact_m:
                # the walk stops at the box's near edge, an open door's end, from where the
                # part in view is out of reach: walk up to that part and look again
                sighting = yield from self._step_up_to(t.now, sighting.point)
            if sighting is None or sighting.distance > self.p.interact_m:
                continue
            other = neighbour_at(sighting.point, t.now, self.body.mapper.memory)
            if other is not None:
                self.event(
                    "openness_neighbour",
                    label=t.now.label,
                    track_id=t.now.id,
                    other=other.label,
                    other_id=other.id,
                )
                continue
            st.phase = "opening"
            yield sighting.action(name, shape)
            if self.body.obs.error == "blocked":  # the door would hit the agent: step back and retry
                yield Action(ActionName.MoveBack)
                yield sighting.action(name, shape)
            obs = self.body.obs
            if obs.success:
                st.objects_fixed += 1
                self.event("openness_restored", label=t.now.label, action=name.value)
                st.target = None
                return True
            if obs.error in ("already_open", "already_closed"):
                self.event("openness_unchanged", label=t.now.label, track_id=t.now.id, error=obs.error)
                st.target = None
                return False
        self.event("openness_failed", label=t.now.label, track_id=t.now.id)
        st.target = None
        return False

    def _step_up_to(self, track: TrackedObject, point: np.ndarray) -> Gen:
        """Walk to within ``STEP_UP_M`` (x, y) of ``point``, the part of ``track`` in view, face
        it and look again: the sighting there (None when gone from view)."""
        yield from navigate(
            self.body,
            goal_xy=(float(point[0]), float(point[1])),
            radius=STEP_UP_M,
            stop_radius=0.05,
            budget=self.p.goal_step_budget,
        )
        yield from face_point(self.body, point)
        return find_in_view(self.body, track, max_pixel_gap=0.3)

    # ------------------------------------------------------------------ objects
    def put_back(self, m: Move) -> Gen:
        """Pick the moved object up and put it down where the walkthrough saw it."""
        st = self.state
        st.target, st.target_receptacle, st.predictions = m.now, None, []
        st.phase = "approaching"
        sighting = yield from self.approach(m.now, self.p.approach_m)
        if sighting is None:
            self.event("unreachable", label=m.now.label, track_id=m.now.id)
            st.target = None
            return False
        votes = self.votes.get(("unshuffle", m.now.id))
        lay = votes.heading_guess() if votes is not None else None
        heading = self.body.pose[2]
        before = self.body.obs
        if not (yield from self.pick(m.now, sighting)):
            st.target = None
            return False
        held = self.body.obs.held
        if held != m.now.label:  # the hand holds another kind of thing: it lay there, unmoved
            yield from self.unpick(m.now.label, held, before)
            st.target = None
            return False
        st.phase = "placing"
        self.aimed = None
        placed = yield from self.put_at(m.then, None if lay is None else (lay, heading))
        if not placed:
            st.phase = "dropping"
            yield from self.drop()
            self.event("dropped", label=m.then.label)
        elif self.aimed is not None:
            yield from self.check_put(m.then, self.aimed, held)
        st.target = None
        return placed

    def unpick(self, label: str, held: str | None, before: Any) -> Gen:
        """Put back what a pick of a ``label`` took instead (``held``: its type, as the hand
        says), turned as it lay (the agent has not moved): where its points were in the frame
        ``before`` the pick (``where_it_lay``), else at the pixel it was picked at, else on the
        floor."""
        self.event("picked_another", label=label, held=held)
        self.state.phase = "dropping"
        point = where_it_lay(before, self.body.obs, self.picked_at)
        action = self.reach_action(point, 0.0) if point is not None else "no points"
        if not isinstance(action, str):
            yield action
            if self.body.obs.success:
                return
        at = self.picked_at
        if at is not None:
            yield Action(ActionName.PutObject, x=at.x, y=at.y, yaw=0.0)
            if self.body.obs.success:
                return
        yield from self.drop()

    def check_put(self, seen: Seen, aim: np.ndarray, held: str | None) -> Gen:
        """Look at the object just put down from the pose of a walkthrough view of its place
        (``ObjectView``; of ``CHECK_VIEWS`` at most, nearest first) and, when the frame says it
        lies off or turned (``match_view``), pick it up and put it down again where the view
        saw it, turned back; at most ``MENDS`` times, each checked from the same pose. Left as
        it is when no view's pose can be stood at, the match is not believed, or a pick takes
        something else."""
        kept = self.views.get(seen.track_id, []) if seen.track_id is not None else []
        made = [crop.view() for crop in kept]
        views = [
            v.within(seen.box_min, seen.box_max, VIEW_MARGIN_M, VIEW_ABOVE_M) for v in made if v is not None
        ]
        here = self.body.xy

        def cost(v: ObjectView) -> float:  # the walk there and how far it looked
            eye_to = float(np.linalg.norm(v.points.mean(axis=0)[:2] - np.array(v.pose[:2])))
            return float(np.hypot(v.pose[0] - here[0], v.pose[1] - here[1])) + eye_to

        views = sorted((v for v in views if len(v.points) >= VIEW_POINTS), key=cost)
        if not views:
            self.event(
                "put_unchecked", label=seen.label, why=f"no view of its place ({len(kept)} before the box)"
            )
            return False
        i, j = lattice_key(self.body.pose)
        if np.hypot(self.body.xy[0] - i * LATTICE_M, self.body.xy[1] - j * LATTICE_M) >= POSE_TOL_M:
            # the pose is corrected for noise, so no pose recurs exactly: nothing to compare
            self.event("put_unchecked", label=seen.label, why="the agent's pose is off the lattice")
            return False
        tried: list[tuple[float, float]] = []
        spare = self.p.reserve_steps + CHECK_STEPS + PENDING_STEPS * self.pending  # the others come first
        for view in views:
            if len(tried) >= CHECK_VIEWS or self.body.steps_left() <= spare:
                break
            if any(np.hypot(view.pose[0] - x, view.pose[1] - y) < POSE_TOL_M for x, y in tried):
                continue
            tried.append((view.pose[0], view.pose[1]))
            # the last mend: the place's misfit before it, the aim and the turn it undid
            undo: tuple[float, np.ndarray, float] | None = None
            for mend in range(MENDS + 1):
                if not (yield from self._stand_at(view)):
                    self.event("put_unchecked", label=seen.label, why="could not stand at a view's pose")
                    break
                obs = self.body.obs
                match = match_view(view, obs.rgb, obs.depth, obs.intrinsics, obs.camera_pose)
                turn = (match.turn_deg + 90.0) % 180.0 - 90.0  # a box turned half round is the same box
                believed = (
                    match.misfit <= FIT_RATIO * match.still_misfit
                    and match.misfit <= FIT_MAX
                    and match.seen >= FIT_SEEN
                )
                self.event(
                    "put_checked",
                    label=seen.label,
                    shift=[round(float(v), 3) for v in match.shift],
                    turn=round(match.turn_deg, 1),
                    misfit=round(match.misfit, 3),
                    still_misfit=round(match.still_misfit, 3),
                    seen=round(match.seen, 2),
                    believed=believed,
                )
                if undo is not None and match.still_misfit > undo[0]:
                    # the view's place fits the frame worse than before the mend: the mend
                    # moved the object away from it, so it goes back as it lay before
                    _, back_to, turned_by = undo
                    done = ViewMatch(aim[:2] - view.centre, 0.0, 0.0, 0.0, 1.0)
                    undone = yield from self._mend_put(view, done, back_to, -turned_by, held, seen)
                    self.event("mend_undone", label=seen.label, put=undone is not None)
                    return True
                off = float(np.hypot(*match.shift))
                if not believed or (off < OFF_M and abs(turn) < OFF_DEG) or mend == MENDS:
                    return True
                if self.body.steps_left() <= self.p.reserve_steps + CHECK_STEPS // 2:
                    return True
                target = match.moved_from(view.centre, aim)  # the put landed at its aim
                point = np.array([target[0], target[1], aim[2]])
                mended = yield from self._mend_put(view, match, point, -turn, held, seen)
                if mended is None:
                    return False
                undo, aim = (match.still_misfit, aim, -turn), mended
        return False

    def _stand_at(self, view: ObjectView) -> Gen:
        """Walk to ``view``'s pose over lattice points stood on before (``lattice_path``; the
        planner's map can hold a pose the agent stood on beside furniture as an obstacle),
        else with the planner, then turn and tilt as it was; whether the agent stands so."""
        x, y, yaw, pitch = view.pose
        goal = lattice_key(view.pose)
        blocked: set[frozenset[tuple[int, int]]] = set()
        for _ in range(REPLANS):
            here = lattice_key(self.body.pose)
            path = lattice_path(self.stood, here, goal, CHECK_STEPS // 4, blocked)
            if path is None:
                break
            for key in path:
                action = lattice_move(self.body.pose[2], here, key)
                if action is None:
                    break
                yield Action(action)
                if not self.body.obs.success:  # in the way in this phase (a door open now)
                    blocked.add(frozenset((here, key)))
                    break
                here = key
            if here == goal:
                break
        if lattice_key(self.body.pose) != goal:
            yield from navigate(self.body, goal_xy=(x, y), stop_radius=0.0, budget=CHECK_STEPS // 2)
        yield from rotate_to(self.body, yaw)
        yield from pitch_to(self.body, pitch)
        px, py, pyaw, ppitch = self.body.pose
        at = np.hypot(px - x, py - y) < POSE_TOL_M
        return bool(at and abs(wrap_deg(pyaw - yaw)) < 1.0 and abs(ppitch - pitch) < 1.0)

    def _mend_put(
        self, view: ObjectView, match: ViewMatch, target: np.ndarray, yaw: float, held: str | None, seen: Seen
    ) -> Gen:
        """Pick the object up where ``match`` says the view's points lie now (walking up to
        it first unless it is within ``MEND_REACH_M``; ``grip_pixel``) and put it down at
        ``target`` turned by ``yaw`` degrees; from elsewhere (``put_at``) when the point is
        out of reach or sight from here. The point put at, or None when the pick or the put
        failed (the object then lies wherever it went)."""
        centre = view.centre
        now = match.moved_to(centre, centre)
        top = np.array([now[0], now[1], float(np.max(view.points[:, 2]))])
        if float(np.linalg.norm(top - self.body.obs.camera_pose[:3, 3])) > MEND_REACH_M:
            lo, hi = top - np.array([0.05, 0.05, 0.0]), top + np.array([0.05, 0.05, 0.0])
            mask = goal_mask_near_box(self.body.mapper, lo, hi, 0.55)
            yield from navigate(self.body, goal_mask=mask, stop_radius=0.05, budget=CHECK_STEPS // 2)
            yield from face_point(self.body, top)
        obs = self.body.obs
        grip = grip_pixel(view, match, obs.rgb, obs.depth, obs.intrinsics, obs.camera_pose)
        if grip is None:
            pixel = self._pixel_of(top)
            grip = None if pixel is None else (int(pixel[0]), int(pixel[1]))
        if grip is None or float(np.linalg.norm(top - obs.camera_pose[:3, 3])) > MEND_REACH_M:
            self.event("mend_failed", label=seen.label, error="out of reach", message="")
            return None
        h, w = obs.depth.shape
        at = ((grip[0] + 0.5) / w, (grip[1] + 0.5) / h)
        self.state.phase = "picking"
        yield Action(ActionName.PickupObject, x=at[0], y=at[1])
        obs = self.body.obs
        if not obs.success:
            self.event("mend_failed", label=seen.label, error=obs.error, message=obs.message)
            return None
        if obs.held != held:  # something else was there: put it back where it was
            self.event("mend_failed", label=seen.label, error="picked another", message=str(obs.held))
            yield Action(ActionName.PutObject, x=at[0], y=at[1], yaw=0.0)  # turned as it lay
            return None
        self.state.phase = "placing"
        heading = self.body.pose[2]
        action = self.reach_action(target, yaw)
        if not isinstance(action, str):
            yield action
            if self.body.obs.success:
                self.event(
                    "put_mended",
                    label=seen.label,
                    target=[round(float(c), 3) for c in target],
                    turn=round(yaw, 1),
                )
                return target
        # out of reach or sight from here (a shelf above the eye): from the spots a put tries
        self.event(
            "mend_elsewhere", label=seen.label, why=action if isinstance(action, str) else str(obs.error)
        )
        self.aimed = None
        # put_at turns it by ``yaw`` from how it lay: its axis then is taken for 0 and the place's for -yaw
        there = replace(seen, middle=(float(target[0]), float(target[1])), axis_deg=0.0)
        if (yield from self.put_at(there, (-yaw, heading), again=True)):
            if self.aimed is not None:
                self.event(
                    "put_mended", label=seen.label, target=[round(float(c), 3) for c in self.aimed], turn=0.0
                )
            return self.aimed
        self.event("mend_failed", label=seen.label, error="put", message=str(self.body.obs.message))
        self.state.phase = "dropping"
        yield from self.drop()
        return None

    def support_of(self, seen: Seen) -> TrackedObject | None:
        """The receptacle track (in the current map) the remembered object stood on or in:
        its footprint under the object's centre, its top nearest the object's base."""
        base = float(seen.box_min[2])
        if base < FLOOR_Z:
            return None
        best: tuple[float, TrackedObject] | None = None
        for o in self.body.mapper.memory:
            if o.label not in PLACEABLE_RECEPTACLES:
                continue
            gap = float(footprint_gap(o.box_min, o.box_max, seen.centroid[0], seen.centroid[1]))
            if gap > 0.15 or o.box_min[2] > base + 0.1:
                continue
            score = gap + 0.5 * abs(float(o.box_max[2]) - base)
            if best is None or score < best[0]:
                best = (score, o)
        return best[1] if best else None

    def put_at(self, seen: Seen, held: tuple[float, float] | None = None, again: bool = False) -> Gen:
        """Put the held object at the remembered place (its top face's middle, ``Seen.middle``,
        else its box's centre): from beside it, reach to the point just above its base
        (``Action.reach``: the spot need not be in sight, a counter top at eye height never is),
        turned as it lay there (``held``: see ``put_turn``), from up to three spots, each at
        least ``RETRY_PUT_M`` from those tried (a toaster in the way from one side of a counter
        is not from another), and farther off than a spot from which something over the point
        hid it (``overhead``: a coffee table's top over the shelf under it; ``farther_off``);
        then on the receptacle tracked under it; on the floor where it stood on the floor."""
        # Where the walkthrough's views of its top face place it, else the box's centre; not the
        # centroid of the seen points: those lean towards the camera (with the simulator's masks,
        # 1 cm vs 5 cm median error from the true place).
        centre = (seen.box_min + seen.box_max) / 2 if seen.middle is None else seen.middle
        target = np.array([centre[0], centre[1], max(float(seen.box_min[2]), 0.0) + REACH_LIFT_M])
        support = self.support_of(seen)
        self.state.target_receptacle = support.label if support is not None else "Floor"
        tried: list[np.ndarray] = []  # spots stood on: the point out of sight or reach, or the put failed
        lo = target - np.array([0.05, 0.05, 0.0])
        hi = target + np.array([0.05, 0.05, 0.0])
        under_from: float | None = None  # a spot this far (x, y) from the point saw it under something
        for radius in (0.55, 0.8, 1.0):
            mask = goal_mask_near_box(self.body.mapper, lo, hi, radius)
            if under_from is not None:
                farther = self.farther_off(lo, hi, target, under_from)
                mask = farther if farther.any() else mask
            away = mask_away_from(mask, self.body.mapper.grid, tried, RETRY_PUT_M)
            mask = away if away.any() else mask
            yield from navigate(self.body, goal_mask=mask, stop_radius=0.05, budget=self.p.goal_step_budget)
            tried.append(self.body.xy.copy())
            yield from face_point(self.body, target)
            action = self.reach_action(target, put_turn(seen.axis_deg, held, self.body.pose[2]))
            if isinstance(action, str):
                self.event("aim_failed", label=seen.label, radius=radius, why=action)
                if action.startswith("something") and self.overhead(target):
                    under_from = float(np.linalg.norm(self.body.xy - target[:2]))
                continue
            yield action
            obs = self.body.obs
            if obs.success:
                self.aimed = target
                return self._put_back_done(seen, "reached", target, again)
            self.event(
                "put_failed", receptacle=self.state.target_receptacle, error=obs.error, message=obs.message
            )
        # Still out of reach from the nearest spot (a pillow in the middle of a bed): as near it
        # as the arm goes, on the same surface, rather than anywhere on the receptacle.
        near = self.pulled_in(target)
        if near is not None:
            action = self.reach_action(near, put_turn(seen.axis_deg, held, self.body.pose[2]))
            if not isinstance(action, str):
                yield action
                if self.body.obs.success:
                    return self._put_back_done(seen, "as near as it reaches", near, again)
                self.event(
                    "put_failed",
                    receptacle=self.state.target_receptacle,
                    error=self.body.obs.error,
                    message=self.body.obs.message,
                )
        if support is not None and (yield from self.put_on(support)):
            return self._put_back_done(seen, "on its receptacle", None, again)
        return False

    def overhead(self, point: np.ndarray) -> bool:
        """Whether the current frame shows something over ``point``: of its points within
        ``OVER_M`` (x, y) of it, at least ``OVER_POINTS``, most stand ``OVERHEAD_M`` or more
        above it (a coffee table's top over the shelf under it). A ray to a point below the
        eye meets whatever hides the point above the point, so the ray alone cannot tell a
        table's top from a sofa's back in front of the floor behind it."""
        obs = self.body.obs
        pts, _ = unproject(obs.depth, obs.intrinsics, obs.camera_pose)
        near = np.hypot(pts[:, 0] - point[0], pts[:, 1] - point[1]) < OVER_M
        if int(near.sum()) < OVER_POINTS:
            return False
        return float(np.median(pts[near, 2])) > float(point[2]) + OVERHEAD_M

    def farther_off(self, lo: np.ndarray, hi: np.ndarray, point: np.ndarray, near_m: float) -> np.ndarray:
        """Spots (nav grid mask) at least ``FARTHER_M`` farther from the put's point than
        ``near_m`` and within reach of it (``PULL_REACH_M`` from the eye), the outermost
        ``BAND_M`` of them where any: the farther off, the lower the ray to a point under a
        table's top, and the farther in under the top's edge it passes. Empty when none is
        within reach."""
        drop = float(self.body.obs.camera_pose[2, 3]) - float(point[2])
        reach_m = float(np.sqrt(max(PULL_REACH_M**2 - drop**2, 0.0))) - 0.05  # lo / hi: the point ± 5 cm
        mapper = self.body.mapper
        within = goal_mask_near_box(mapper, lo, hi, reach_m)
        farther = within & ~goal_mask_near_box(mapper, lo, hi, near_m + FARTHER_M)
        outer = farther & ~goal_mask_near_box(mapper, lo, hi, reach_m - BAND_M)
        return outer if outer.any() else farther

    def pulled_in(self, point: np.ndarray) -> np.ndarray | None:
        """``point`` moved level towards the agent until the arm reaches it (``PULL_REACH_M``
        from the eye), when it is beyond reach, in view, and the frame shows a surface at that
        height there (the same bed or table, not the floor beyond its edge); else None."""
        eye = self.body.obs.camera_pose[:3, 3]
        gap = point - eye
        flat = float(np.linalg.norm(gap[:2]))
        if float(np.linalg.norm(gap)) <= INTERACT_M or flat <= 0.0 or PULL_REACH_M <= abs(float(gap[2])):
            return None
        keep = float(np.sqrt(PULL_REACH_M**2 - gap[2] ** 2)) / flat
        near = np.array([eye[0] + gap[0] * keep, eye[1] + gap[1] * keep, point[2]])
        pixel = self._pixel_of(near)
        if pixel is None:
            return None
        _, _, z, seen_at = pixel
        # the put's point is REACH_LIFT_M above the surface: the ray through it meets the surface
        # a little beyond it, at the surface's height (the floor past an edge is far lower)
        if not seen_at >= z * (1 - REACH_SLACK):
            return None
        hit = eye + (near - eye) * (seen_at / z)
        if abs(float(hit[2]) - (float(point[2]) - REACH_LIFT_M)) > SURFACE_TOL_M:
            return None
        return near

    def _pixel_of(self, point: np.ndarray) -> tuple[float, float, float, float] | None:
        """Where a start-frame point falls in the current frame: (u, v, its depth along the
        optical axis, the depth the frame shows there); None when it is out of view."""
        obs = self.body.obs
        h, w = obs.depth.shape
        u, v, z = project(point[None, :], obs.intrinsics, obs.camera_pose)
        if not z[0] > 0 or not (0 <= u[0] < w and 0 <= v[0] < h):
            return None
        return float(u[0]), float(v[0]), float(z[0]), float(obs.depth[int(v[0]), int(u[0])])

    def reach_action(self, point: np.ndarray, yaw: float | None) -> Action | str:
        """A put at a start-frame point: its pixel and its distance from the eye; or why not
        (out of view, out of reach, something seen in front of it)."""
        obs = self.body.obs
        h, w = obs.depth.shape
        pixel = self._pixel_of(point)
        if pixel is None:
            return "not in view"
        u, v, z, seen_at = pixel
        reach = float(np.linalg.norm(point - obs.camera_pose[:3, 3]))
        # up to the protocol's limit, not ``interact_m``: the server checks the reach the agent
        # sends, not the true distance, so no margin for pose error is needed (a pillow in the
        # middle of a bed is 1.4 m from the nearest place to stand)
        if reach > INTERACT_M:
            return f"{reach:.2f} m away"
        if 0 < seen_at < z * (1 - REACH_SLACK):
            return f"something {seen_at:.2f} m away in front of it"
        return Action(ActionName.PutObject, x=(u + 0.5) / w, y=(v + 0.5) / h, yaw=yaw, reach=reach)

    def _put_back_done(
        self, seen: Seen, how: str, target: np.ndarray | None = None, again: bool = False
    ) -> bool:
        """Count a put (``again``: an object put back before, not counted again); ``target``:
        the point it reached for (start frame; the evaluation splits a put's error into the
        estimate's and the landing's)."""
        if not again:
            self.state.objects_fixed += 1
            self.placed.append((seen.label, seen.centroid[:2].copy(), self.state.target_receptacle or ""))
        where = {} if target is None else {"target": [round(float(v), 3) for v in target]}
        self.event("put_back", label=seen.label, how=how, receptacle=self.state.target_receptacle, **where)
        return True
