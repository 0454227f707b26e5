"""The language out-of-place classifier (BERT-OOP), its Table-3 rows and instructions."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tidee.agent.classes import CLASSES, PICKUPABLE
from tidee.agent.learning import WEIGHTS_DIR
from tidee.agent.mapping.memory import TrackedObject
from tidee.agent.perception.base import Detection
from tidee.agent.perception.detector.config import room_seeds
from tidee.agent.reasoning.language_oop import config, data, frames
from tidee.agent.reasoning.language_oop.paragraphs import object_paragraph, paragraph_support, size_word
from tidee.agent.reasoning.relations import words

torch = pytest.importorskip("torch")
pytest.importorskip("transformers")

# the modules that import torch, once it is known to be there
from tidee.agent.reasoning.language_oop import eval as lo_eval  # noqa: E402
from tidee.agent.reasoning.language_oop import instructions, model, train  # noqa: E402

torch.set_num_threads(1)

# Hand-written paragraphs in the paper's form: where things belong, and where they do not.
SAMPLES = [
    (
        "The mug is next to the counter top. The mug is supported by the counter top. "
        "The mug is closest to the bowl.",
        0,
    ),
    ("The mug is supported by the floor. The mug is closest to the pillow.", 1),
    (
        "The bowl is next to the counter top. The bowl is supported by the counter top. "
        "The bowl is closest to the mug.",
        0,
    ),
    ("The bowl is next to the bed. The bowl is supported by the bed. The bowl is closest to the pillow.", 1),
    (
        "The pillow is next to the bed. The pillow is supported by the bed. "
        "The pillow is closest to the cell phone.",
        0,
    ),
    (
        "The pillow is next to the sink. The pillow is supported by the counter top. "
        "The pillow is closest to the mug.",
        1,
    ),
    ("The alarm clock is next to the side table. The alarm clock is supported by the side table.", 0),
    ("The alarm clock is next to the toilet. The alarm clock is supported by the floor.", 1),
    (
        "The soap bar is next to the sink. The soap bar is supported by the sink. "
        "The soap bar is closest to the cloth.",
        0,
    ),
    ("The soap bar is next to the sofa. The soap bar is supported by the sofa.", 1),
    (
        "The laptop is next to the desk. The laptop is supported by the desk. "
        "The laptop is closest to the pen.",
        0,
    ),
    ("The laptop is next to the stove burner. The laptop is supported by the counter top.", 1),
]


def _category(paragraph: str) -> str:
    name = paragraph.split(" is ")[0].removeprefix("The ")
    return {words(c): c for c in PICKUPABLE}[name]


@pytest.fixture(scope="module")
def encoder() -> model.TextEncoder:
    return model.TextEncoder()


@pytest.fixture(scope="module")
def trained(encoder: model.TextEncoder) -> model.LanguageOOPClassifier:
    """A head trained briefly on SAMPLES (not the shipped weights)."""
    samples = [data.OOPSample(p, y, "Kitchen", _category(p)) for p, y in SAMPLES]
    emb = encoder.encode([s.paragraph for s in samples])
    y = np.array([s.label for s in samples], np.float32)
    torch.manual_seed(0)
    head = model.LanguageOOPHead()
    model.fit_head(
        head,
        emb,
        y,
        steps=150,
        batch_size=12,
        lr=1e-3,
        weight_decay=0.01,
        seed=0,
        device="cpu",
        progress=False,
    )
    return model.LanguageOOPClassifier(
        head, encoder, train.replay_set(samples, emb, 8, np.random.default_rng(0))
    )


# ----------------------------------------------------------------------------- encoder and head
def test_embedding_shape_norm_and_determinism(encoder: model.TextEncoder) -> None:
    texts = [SAMPLES[0][0], SAMPLES[1][0], SAMPLES[0][0]]
    a = encoder.encode(texts)
    assert a.shape == (3, config.EMBED_DIM) and a.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(a, axis=1), 1.0, atol=1e-5)  # sentence-transformers' Normalize
    np.testing.assert_array_equal(a[0], a[2])
    fresh = model.TextEncoder(encoder.path)
    fresh._model, fresh._tokenizer = encoder._model, encoder._tokenizer  # same weights, empty cache
    np.testing.assert_allclose(fresh.encode(texts[:2]), a[:2], atol=1e-5)
    assert encoder.encode([]).shape == (0, config.EMBED_DIM)


def test_encoder_path_must_be_a_model_folder(tmp_path) -> None:
    with pytest.raises(FileNotFoundError, match="config.json"):
        model.TextEncoder(tmp_path)


def test_training_steps_reduce_the_loss(encoder: model.TextEncoder) -> None:
    emb = encoder.encode([p for p, _ in SAMPLES])
    y = np.array([label for _, label in SAMPLES], np.float32)
    torch.manual_seed(0)
    head = model.LanguageOOPHead()
    hist = model.fit_head(
        head,
        emb,
        y,
        steps=60,
        batch_size=12,
        lr=1e-3,
        weight_decay=0.01,
        seed=0,
        device="cpu",
        log_every=10,
        progress=False,
    )
    assert hist[-1]["bce"] < 0.7 * hist[0]["bce"]


def test_fused_head_starts_blind_to_the_visual_feature() -> None:
    torch.manual_seed(0)
    head = model.FusedOOPHead().eval()
    text = torch.randn(4, config.EMBED_DIM)
    with torch.no_grad():
        a = head(text, torch.randn(4, config.VISUAL_DIM))
        b = head(text, None)
    torch.testing.assert_close(a, b)
    assert model.make_head(head.config()).config() == head.config()


# ----------------------------------------------------------------------------- instructions
@pytest.mark.parametrize(
    "text, expected",
    [
        ("I want my alarm clock on the desk", ("AlarmClock", "Desk", "in_place")),
        ("alarm clock on the desk is out of place", ("AlarmClock", "Desk", "out_of_place")),
        ("put the towel on the towel holder", ("Towel", "TowelHolder", "in_place")),
        ("The pillows belong on the bed.", ("Pillow", "Bed", "in_place")),
        ("Don't leave the laptop on the bed", ("Laptop", "Bed", "out_of_place")),
        ("soap bottle on the countertop is misplaced", ("SoapBottle", "CounterTop", "out_of_place")),
    ],
)
def test_parse_instruction(text: str, expected: tuple[str, str, str]) -> None:
    assert tuple(instructions.parse_instruction(text)) == expected


def test_parse_instruction_says_what_is_missing() -> None:
    with pytest.raises(ValueError, match="no object category"):
        instructions.parse_instruction("put it on the desk")
    with pytest.raises(ValueError, match="no receptacle"):
        instructions.parse_instruction("I like my alarm clock")


def test_instruction_moves_probability_the_asked_way(trained: model.LanguageOOPClassifier) -> None:
    para = (
        "The mug is next to the counter top. The mug is supported by the counter top. "
        "The mug is closest to the bowl."
    )
    clf = trained.copy()
    before = float(clf.predict([para])[0])
    report = instructions.apply_instruction(clf, "the mug on the counter top is out of place", steps=50)
    after = float(clf.predict([para])[0])
    assert report["instruction"]["polarity"] == "out_of_place"
    assert after > before + 0.2 and after > 0.5
    assert float(trained.predict([para])[0]) == pytest.approx(before)  # the copy was tuned, not the original

    floor = "The alarm clock is next to the toilet. The alarm clock is supported by the floor."
    clf = trained.copy()
    before = float(clf.predict([floor])[0])
    instructions.apply_instruction(clf, "I want my alarm clock on the floor", steps=50)
    assert float(clf.predict([floor])[0]) < before - 0.2


def test_an_instruction_leaves_other_objects_on_the_receptacle_alone() -> None:
    """Shipped head: "the laptop on the bed is out of place" must not drag the cell phone on
    the bed along (MiniLM puts the two paragraphs close). Replay samples of other categories
    on the bed, held to the head's own probabilities, are what keep it; without them the
    cell phone follows the laptop."""
    base = model.LanguageOOPClassifier.load()
    phone = [
        "The cell phone is supported by the bed. The cell phone is next to the pillow.",
        "The cell phone is next to the pillow. The cell phone is supported by the bed. "
        "The cell phone is closest to the laptop.",
    ]
    laptop = ["The laptop is supported by the bed. The laptop is next to the pillow."]
    before = base.predict(phone)
    assert before.max() < 0.1
    kept = base.copy()
    instructions.apply_instruction(kept, "the laptop on the bed is out of place")
    assert kept.predict(laptop)[0] > 0.7
    assert np.abs(kept.predict(phone) - before).max() < 0.3
    again = base.copy()
    instructions.apply_instruction(again, "the laptop on the bed is out of place")  # same seed, same head
    np.testing.assert_array_equal(again.predict(phone + laptop), kept.predict(phone + laptop))
    dragged = base.copy()
    instructions.apply_instruction(
        dragged, "the laptop on the bed is out of place", distill=False, neighbour_share=0.0
    )
    assert np.abs(dragged.predict(phone) - before).max() > 0.5


# ----------------------------------------------------------------------------- paragraphs, rows, agent
def _records() -> list[dict]:
    def rec(oid, typ, lo_, hi, moved=False):
        c = [(a + b) / 2 for a, b in zip(lo_, hi)]
        return {
            "id": oid,
            "type": typ,
            "moved": moved,
            "centroid": c,
            "box_min": list(lo_),
            "box_max": list(hi),
        }

    return [
        rec("CounterTop_0", "CounterTop", (0, 0, 0), (2, 0.6, 0.9)),
        rec("Mug_0", "Mug", (0.5, 0.2, 0.9), (0.6, 0.3, 1.0)),
        rec("Mug_1", "Mug", (3.0, 2.0, 0.0), (3.1, 2.1, 0.1), moved=True),
    ]


def test_config_paragraphs_from_ground_truth_boxes() -> None:
    paras = data.config_paragraphs(_records())
    assert set(paras) == {"Mug_0", "Mug_1"}
    assert "The mug is supported by the counter top." in paras["Mug_0"][0] and paras["Mug_0"][1] == 0
    assert "The mug is supported by the floor." in paras["Mug_1"][0] and paras["Mug_1"][1] == 1
    assert paragraph_support(paras["Mug_1"][0]) == "Floor"


def test_training_and_evaluation_refuse_the_wrong_rooms() -> None:
    with pytest.raises(ValueError, match="held-out"):
        lo_eval.evaluate_language_oop(None, split="train")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="held-out"):
        # the instruct eval picks settings on val, reports on test
        config.InstructEvalConfig(out="unused", split="train")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="val or test|train, val or test"):
        room_seeds("pool", 1)


class _FloorStub:
    """P(oop) = 0.9 for anything on the floor, else 0.1; records what it was asked."""

    visual_dim = 0

    def __init__(self) -> None:
        self.seen: list[str] = []

    def predict(self, paragraphs, visual=None):
        self.seen += list(paragraphs)
        return np.array([0.9 if "supported by the floor" in p else 0.1 for p in paragraphs])


def test_oracle_language_row_matches_detections_to_ground_truth() -> None:
    frames = {
        "obj_frame": np.array([0, 0, 1]),
        "obj_box": np.array([[10, 10, 30, 30], [50, 50, 60, 60], [0, 0, 5, 5]], np.float32),
        "obj_id": np.array(["Mug_0", "Mug_1", "Mug_0"]),
        "frame_room": np.array(["Kitchen:200:0"] * 2),
    }
    dets = [
        [
            Detection("Mug", 0.9, (11, 10, 30, 30)),
            Detection("Mug", 0.8, (50, 50, 60, 61)),
            Detection("Mug", 0.5, (100, 100, 120, 120)),
        ],
        [],
    ]
    stub = _FloorStub()
    row = lo_eval.oracle_language_row(stub, scenes={"Kitchen:200:0": _records()}, cache_dir=None)  # type: ignore[arg-type]
    assert row(frames, dets) == [[0.1, 0.9, 0.5], []]


def test_language_oop_scores_tracked_objects() -> None:
    def obj(i, label, lo_, hi):
        lo_, hi = np.array(lo_, float), np.array(hi, float)
        return TrackedObject(id=i, label=label, score=1.0, centroid=(lo_ + hi) / 2, box_min=lo_, box_max=hi)

    objects = [
        obj(0, "CounterTop", (0, 0, 0), (2, 0.6, 0.9)),
        obj(1, "Mug", (0.5, 0.2, 0.9), (0.6, 0.3, 1.0)),
        obj(2, "Mug", (3, 2, 0), (3.1, 2.1, 0.1)),
    ]
    oop = model.LanguageOOP(classifier=_FloorStub())  # type: ignore[arg-type]
    probs = oop.score_all(objects[1:], objects, "Kitchen")
    assert probs == {1: 0.1, 2: 0.9}
    assert objects[2].meta["paragraph"].startswith("The mug")


def _floor_depth(pitch_deg: float, n: int = 64) -> np.ndarray:
    """z-depth of a camera 0.9015 m above an endless floor, pitched down by ``pitch_deg``."""
    f, c = n / 2, (n - 1) / 2
    v = (np.arange(n) - c) / f
    th = math.radians(pitch_deg)
    down = v * math.cos(th) + math.sin(th)  # downward component of the ray (z = 1)
    d = np.where(down > 1e-3, frames.CAMERA_HEIGHT_M / np.maximum(down, 1e-3), 0.0)
    return np.repeat(np.minimum(d, 20.0)[:, None], n, 1).astype(np.float32)


@pytest.mark.parametrize("pitch", [0.0, 30.0, 60.0])
def test_pitch_is_recovered_from_a_floor(pitch: float) -> None:
    assert frames.estimate_pitch(_floor_depth(pitch)) == pitch


# ----------------------------------------------------------------------------- shipped weights
def test_shipped_weights_oracle_language_ap() -> None:
    clf = model.LanguageOOPClassifier.load(WEIGHTS_DIR / "language_oop.pt")
    res = lo_eval.evaluate_language_oop(clf, "test", rooms_per_type=1, messes_per_room=1, progress=False)
    assert res["samples"] > 50 and res["n_out_of_place"] >= 10
    assert res["map"] >= 0.8, res


def test_size_sentence_only_for_categories_with_variants() -> None:
    from tidee.agent.reasoning.relations import ObjectRef, relation_paragraph

    floor_vase = ObjectRef("v", "Vase", (0, 0, 0.4), (-0.15, -0.15, 0.0), (0.15, 0.15, 0.85))
    small_vase = ObjectRef("w", "Vase", (0, 0, 0.1), (-0.05, -0.05, 0.0), (0.05, 0.05, 0.2))
    mug = ObjectRef("m", "Mug", (1, 0, 0.05), (0.95, -0.05, 0.0), (1.05, 0.05, 0.1))
    assert size_word(floor_vase) == "large" and size_word(small_vase) == "small"
    assert size_word(ObjectRef("x", "Vase", (0, 0, 0))) is None  # no box: no size
    assert object_paragraph(floor_vase, [mug]).startswith(
        "The vase is large. The vase is supported by the floor."
    )
    assert object_paragraph(small_vase, [mug]).startswith("The vase is small. ")
    assert object_paragraph(mug, [floor_vase]) == relation_paragraph(
        mug, [floor_vase]
    )  # no variants: no size


def test_shipped_head_reads_the_size_of_a_vase_on_the_floor() -> None:
    """The catalog's large vase stands on the floor, a small one does not: the shipped head
    tells them apart from the size sentence alone."""
    clf = model.LanguageOOPClassifier.load()
    large, small = clf.predict(
        [
            "The vase is large. The vase is supported by the floor.",
            "The vase is small. The vase is supported by the floor.",
        ]
    )
    assert large < 0.5 < small


def test_fused_samples_are_matched_pickupable_detections_with_their_features() -> None:
    from tidee.agent.reasoning.language_oop.fused_train import detection_samples, held_out_room

    cls = {n: i for i, n in enumerate(CLASSES)}
    frames = {
        "depth": np.full((1, 128, 128), 2.0, np.float16),
        "frame_room": np.array(["Bedroom:19:0"]),
        "obj_frame": np.array([0, 0, 0]),
        "obj_cls": np.array([cls["Mug"], cls["Book"], cls["Bed"]]),
        "obj_box": np.array([[10, 10, 30, 30], [60, 60, 90, 90], [0, 90, 128, 128]], np.float32),
        "obj_oop": np.array([1, 0, 0], np.uint8),
    }
    feat = np.ones(64, np.float32)
    dets = [
        [
            Detection("Mug", 0.9, (10, 10, 30, 31), feature=feat),  # matches the moved mug
            Detection("Book", 0.8, (61, 60, 90, 90)),  # the book, no feature
            Detection("Pen", 0.7, (100, 10, 120, 30), feature=feat),  # nothing there: no sample
            Detection("Bed", 0.9, (0, 90, 128, 128)),
        ]
    ]  # not pickupable: context only
    s = detection_samples(frames, dets)
    assert s["categories"] == ["Mug", "Book"] and s["labels"] == [1, 0]
    assert s["features"].shape == (2, 64) and s["features"][0].sum() == 64 and s["features"][1].sum() == 0
    assert all(p.startswith("The mug") for p in s["paragraphs"][:1]) and s["rooms"] == ["Bedroom:19:0"] * 2
    assert held_out_room("Bedroom:19:0") and not held_out_room("Kitchen:10003:None")


def test_only_shipped_oop_heads_draw_their_loss_curve_in_the_docs(tmp_path) -> None:
    from tidee.agent.learning import loss_curve_path

    shipped = loss_curve_path(WEIGHTS_DIR / "language_oop_fused.pt", "language_oop_fused_loss.png")
    assert shipped == "docs/models/language_oop_fused_loss.png"
    candidate = loss_curve_path(
        tmp_path / "runs" / "fused" / "language_oop_fused.pt", "language_oop_fused_loss.png"
    )
    assert candidate == str(tmp_path / "runs" / "fused" / "language_oop_fused_loss.png")
    assert (
        loss_curve_path(WEIGHTS_DIR / "language_oop.pt", "language_oop_loss.png", asked="x/curve.png")
        == "x/curve.png"
    )
    # the training commands resolve it this way: neither default names the docs any more
    assert config.TrainConfig().loss_png is None
