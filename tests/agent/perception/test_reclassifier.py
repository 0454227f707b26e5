"""The detector's second stage: crops, fusion, training, the shipped weights in LearnedPerception."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from tidee.agent.classes import CLASSES
from tidee.agent.perception.reclassifier.config import DEFAULT_RECLASSIFIER, ReclassifierConfig
from tidee.agent.perception.reclassifier.model import CropClassifier, crop_inputs, frame_tensor, fuse

torch.set_num_threads(2)
# the shipped detector + reclassifier on the 24 test-room frames of test_detector's floor test
# score 0.81 (the detector alone 0.73); an untrained reclassifier renames everything at random (~0)
RECLASSIFIED_FLOOR_MAP50 = 0.65


def test_a_crop_shows_its_box_and_the_side_inputs_measure_it() -> None:
    rgb = np.zeros((1, 128, 128, 3), np.uint8)
    rgb[0, 32:64, 64:96] = (255, 0, 0)  # a red square, 32 px = a quarter of the image wide
    rgb[0, 32:64, 64:80, 1] = 255  # its left half yellow
    depth = np.full((1, 128, 128), 4.0, np.float32)
    depth[0, 32:64, 64:96] = 2.0
    cfg = ReclassifierConfig(crop=16, context=1.0)
    frames = frame_tensor(rgb, depth)
    box = torch.tensor([[64.0, 32.0, 96.0, 64.0]])
    crops, side = crop_inputs(frames, torch.tensor([0]), box, cfg)
    assert crops.shape == (1, 4, 16, 16) and side.shape == (1, 5)
    red = (1.0 - 0.5) / 0.25
    torch.testing.assert_close(crops[0, 0], torch.full((16, 16), red))  # all red
    assert crops[0, 1, :, :8].mean() > 1.5 and crops[0, 1, :, 8:].mean() < -1.5  # yellow on the left
    assert crops[0, 3].abs().max() < 1e-5  # depth relative to the object's
    # a quarter of a 90-degree view at 2 m is 1 m wide: log 1 = 0
    torch.testing.assert_close(
        side[0], torch.tensor([math.log(0.25), math.log(0.25), math.log(2.0), 0.0, 0.0])
    )
    flipped, _ = crop_inputs(frames, torch.tensor([0]), box, cfg, flip=torch.tensor([True]))
    torch.testing.assert_close(flipped[0, 1], crops[0, 1].flip(-1))
    # context: a grown crop sees the background around the box
    wide, _ = crop_inputs(frames, torch.tensor([0]), box, ReclassifierConfig(crop=16, context=2.0))
    assert wide[0, 0, 0, 0] < 0 and wide[0, 3, 0, 0] > 0


def test_fusion_weighs_the_crop_against_the_detector_and_background_lowers_the_score() -> None:
    c = 4
    crop = torch.tensor(
        [
            [0.0, 3.0, 0.0, 0.0, 0.0],  # the crop says class 1
            [0.0, 0.0, 0.0, 0.0, 5.0],
        ]
    )  # the crop says background
    heat = torch.tensor(
        [
            [4.0, -2.0, -4.0, -4.0],  # the detector says class 0
            [-4.0, -4.0, 3.0, -4.0],
        ]
    )
    score = torch.tensor([0.8, 0.8])
    cls, s = fuse(crop, heat, score, alpha=0.0, beta=0.0)
    assert cls[0] == 1 and torch.equal(s, score)
    cls, _ = fuse(crop, heat, score, alpha=10.0, beta=0.0)
    assert cls[0] == 0
    cls, s = fuse(crop, heat, score, alpha=1.0, beta=1.0)
    assert cls[1] == 2 and s[1] < 0.05 and 0.3 < s[0] < 0.8  # background: renamed, but hardly scored
    assert crop.shape[1] == c + 1


def test_a_few_training_steps_reduce_the_loss(tmp_path) -> None:
    from tidee.agent.perception.detector.config import GenConfig
    from tidee.agent.perception.detector.data import iter_frames, pack
    from tidee.agent.perception.reclassifier.config import ReclassifierTrainConfig
    from tidee.agent.perception.reclassifier.train import train_reclassifier

    cfg = GenConfig(
        rooms_per_type=1,
        messes_per_room=1,
        walks_per_config=1,
        frames_per_walk=3,
        resolution=128,
        room_types=("Kitchen",),
    )
    data = pack(list(iter_frames(cfg, progress=False)))
    tc = ReclassifierTrainConfig(
        work_dir=str(tmp_path / "run"),
        steps=30,
        batch_size=48,
        frames_per_batch=3,
        lr=3e-3,
        warmup=2,
        log_every=10,
        ckpt_every=15,
        precision="fp32",
    )
    r = train_reclassifier(
        tc, ReclassifierConfig(crop=24), resume=False, progress=False, data=data, ship=False
    )
    losses = [h["total"] for h in r["history"]]
    assert len(losses) == 3 and losses[-1] < 0.8 * losses[0], losses
    assert (tmp_path / "run" / "checkpoint.pt").exists() and (tmp_path / "run" / "loss.png").exists()
    r2 = train_reclassifier(
        tc, ReclassifierConfig(crop=24), resume=True, progress=False, data=data, ship=False
    )
    assert r2["steps"] == 30 and r2["history"] == r["history"]
    with pytest.raises(ValueError, match="different run"):
        train_reclassifier(
            tc, ReclassifierConfig(crop=32), resume=True, progress=False, data=data, ship=False
        )


def test_shapes_and_a_mismatched_reclassifier_is_refused() -> None:
    from tidee.agent.perception.detector.config import DetectorConfig
    from tidee.agent.perception.detector.model import CenterDetector
    from tidee.agent.perception.learned import LearnedPerception

    m = CropClassifier(ReclassifierConfig()).eval()
    with torch.inference_mode():
        out = m(torch.zeros(3, 4, 40, 40), torch.zeros(3, 5))
    assert out.shape == (3, len(CLASSES) + 1)
    with pytest.raises(ValueError, match="reclassifier knows 10 classes"):
        LearnedPerception(
            CenterDetector(DetectorConfig()), reclassifier=CropClassifier(ReclassifierConfig(num_classes=10))
        )


# ------------------------------------------------------------------ the shipped weights
@pytest.fixture(scope="module")
def test_room_frames() -> dict[str, np.ndarray]:
    from tidee.agent.perception.detector.data import held_out_frames

    return held_out_frames("test", rooms_per_type=1, messes=1, frames_per_walk=3, seed=7, progress=False)


def test_shipped_reclassifier_manifest_is_complete() -> None:
    from tidee.agent.learning import read_manifest

    m = read_manifest(DEFAULT_RECLASSIFIER)
    assert m["command"].startswith("tidee train reclassifier")
    assert "never val/test" in m["data"]["split"] and m["data"]["objects"] > 10_000
    assert m["bytes"] < 5 * 2**20
    fusion = m["metrics"]["fusion"]  # chosen on the validation rooms by `tidee eval reclassifier`
    assert fusion["command"].startswith("tidee eval reclassifier --split val")
    assert fusion["val_map50"] > fusion["val_map50_detector_alone"]


def test_shipped_reclassifier_renames_detections_on_test_rooms(test_room_frames) -> None:
    from tidee.agent.evaluation.detection.metrics import evaluate_boxes
    from tidee.agent.perception.learned import LearnedPerception

    both = LearnedPerception.load(threshold=0.05)
    alone = LearnedPerception.load(threshold=0.05, reclassifier=None)
    assert both.reclassifier is not None and alone.reclassifier is None
    rgb, depth = test_room_frames["rgb"], test_room_frames["depth"].astype(np.float32)
    d_both, d_alone = both.detect_batch(rgb, depth), alone.detect_batch(rgb, depth)
    r = evaluate_boxes(d_both, test_room_frames)
    assert r["map50"] >= RECLASSIFIED_FLOOR_MAP50, r["map50"]
    labels_both = [d.label for f in d_both for d in f]
    labels_alone = [d.label for f in d_alone for d in f]
    assert labels_both != labels_alone  # it renames some
    for frame in d_both:
        for d in frame:
            assert d.source == "learned" and 0.05 <= d.score <= 1 and d.feature.shape == (64,)
        assert [d.score for d in frame] == sorted((d.score for d in frame), reverse=True)


def test_detector_boxes_train_a_learned_fusion(tmp_path) -> None:
    """--boxes detector: the shipped detector's own detections, labelled by the ground truth they
    overlap, train a reclassifier that also reads the detector's logits; it starts as the model
    it is warm-started from, and a few steps reduce the loss."""
    from tidee.agent.perception.detector.config import GenConfig
    from tidee.agent.perception.detector.data import iter_frames, pack
    from tidee.agent.perception.reclassifier.config import ReclassifierTrainConfig
    from tidee.agent.perception.reclassifier.model import det_features
    from tidee.agent.perception.reclassifier.train import (
        DetectorBoxBatches,
        detector_boxes,
        train_reclassifier,
        warm_start,
    )

    cfg = GenConfig(
        rooms_per_type=1, messes_per_room=1, walks_per_config=1, frames_per_walk=4, room_types=("Kitchen",)
    )
    data = pack(list(iter_frames(cfg, progress=False)))
    boxes = detector_boxes(data, progress=False)
    n_cls = len(CLASSES)
    lab = boxes["det_label"]
    assert len(lab) == len(boxes["det_box"]) == len(boxes["det_heat"]) > 0
    assert boxes["det_heat"].shape[1] == n_cls and (boxes["det_score"] >= 0.05).all()
    assert ((lab >= 0) & (lab < n_cls)).sum() > 5 and (lab == n_cls).any()  # objects and background
    assert set(np.unique(lab)) <= set(range(n_cls + 1)) | {-100}
    # a labelled detection overlaps a ground-truth box of its class by IoU >= 0.5
    from tidee.agent.evaluation.detection.metrics import box_iou

    i = int(np.flatnonzero((lab >= 0) & (lab < n_cls))[0])
    f = boxes["det_frame"][i]
    gt = data["obj_box"][data["obj_frame"] == f]
    gcls = data["obj_cls"][data["obj_frame"] == f]
    ious = box_iou(boxes["det_box"][i : i + 1].astype(np.float64), gt.astype(np.float64))[0]
    assert ious.max() >= 0.5 and gcls[ious.argmax()] == lab[i]

    # warm start: the grown network computes what the plain one did
    plain = CropClassifier(ReclassifierConfig(crop=24)).eval()
    torch.save({"state_dict": plain.state_dict(), "config": plain.cfg.to_dict()}, tmp_path / "plain.pt")
    grown = CropClassifier(ReclassifierConfig(crop=24, det_inputs=True)).eval()
    warm_start(grown, tmp_path / "plain.pt")
    crops, side = torch.randn(3, 4, 24, 24), torch.randn(3, 5)
    det = det_features(torch.randn(3, n_cls), torch.rand(3))
    with torch.inference_mode():
        torch.testing.assert_close(grown(crops, side, det), plain(crops, side))
        with pytest.raises(ValueError, match="reads the detector's outputs"):
            grown(crops, side)

    tc = ReclassifierTrainConfig(
        work_dir=str(tmp_path / "run"),
        steps=30,
        batch_size=48,
        frames_per_batch=3,
        lr=3e-3,
        warmup=2,
        log_every=10,
        ckpt_every=15,
        precision="fp32",
        boxes="detector",
        init=str(tmp_path / "plain.pt"),
    )
    batches = DetectorBoxBatches(data, boxes, ReclassifierConfig(crop=24, det_inputs=True), tc)
    crops, side, labels, det = batches()
    assert crops.shape == (48, 4, 24, 24) and det.shape == (48, n_cls + 1) and labels.shape == (48,)
    r = train_reclassifier(
        tc, ReclassifierConfig(crop=24), resume=False, progress=False, data=data, ship=False
    )
    losses = [h["total"] for h in r["history"]]
    assert len(losses) == 3 and losses[-1] < 0.8 * losses[0], losses
    assert (tmp_path / "run" / "detector_boxes.npz").exists()


def test_a_gate_keeps_confident_detections_from_the_crop_classifier(test_room_frames) -> None:
    """Detections at or above the gate keep the detector's own class and score and never reach the
    crop classifier; those below are reclassified exactly as without a gate."""
    from tidee.agent.perception.learned import LearnedPerception

    rgb, depth = test_room_frames["rgb"], test_room_frames["depth"].astype(np.float32)
    alone = LearnedPerception.load(threshold=0.05, reclassifier=None)
    ungated = LearnedPerception.load(threshold=0.05)
    ungated.gate = None
    gated = LearnedPerception.load(threshold=0.05)
    gated.gate = 0.6

    def key(d):  # a detection's identity across the three runs: its box
        return d.box

    d_alone, d_ungated, d_gated = (p.detect_batch(rgb, depth) for p in (alone, ungated, gated))
    n_confident = 0
    for fa, fu, fg in zip(d_alone, d_ungated, d_gated):
        confident = {key(d): d for d in fa if d.score >= 0.6}
        n_confident += len(confident)
        by_box = {key(d): d for d in fg}
        for box, d in confident.items():
            assert by_box[box].label == d.label and by_box[box].score == d.score
        reclassified = {key(d): d for d in fu}
        for box, d in by_box.items():
            if box not in confident:  # below the gate: what the ungated run made of it
                assert reclassified[box].label == d.label and reclassified[box].score == d.score
    assert n_confident > 0
    # the stats count raw detections (before NMS): each is either gated or reclassified
    assert gated.stats["gated"] >= n_confident and ungated.stats["gated"] == 0
    assert gated.stats["gated"] + gated.stats["reclassified"] == ungated.stats["reclassified"]

    everything = LearnedPerception.load(threshold=0.05)
    everything.gate = 0.0  # every detection gated: the detector alone, and no crop is classified
    d_all = everything.detect_batch(rgb, depth)
    assert everything.stats["reclassified"] == 0
    assert [[(d.label, d.score) for d in f] for f in d_all] == [
        [(d.label, d.score) for d in f] for f in d_alone
    ]


def test_the_gate_chosen_is_the_lowest_that_keeps_the_map() -> None:
    from tidee.agent.evaluation.detection.fusion import choose_gate

    rows = [
        {"gate": None, "map50": 0.700},
        {"gate": 0.5, "map50": 0.690},
        {"gate": 0.6, "map50": 0.6985},
        {"gate": 0.7, "map50": 0.699},
        {"gate": 0.9, "map50": 0.701},
    ]
    assert choose_gate(rows, 0.002) == 0.6
    assert choose_gate(rows, 0.0) == 0.9
    assert choose_gate(rows[:2], 0.002) is None


def test_crops_of_one_frame_are_those_of_the_same_frame_given_once_per_crop() -> None:
    """The agent's case (every box from one frame, sampled from a view of it) against the batch
    case (one copy of the frame per box): the same crops and side inputs."""
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 256, (1, 64, 64, 3), dtype=np.uint8)
    depth = rng.uniform(0.5, 4.0, (1, 64, 64)).astype(np.float32)
    cfg = ReclassifierConfig(crop=16, context=1.2)
    boxes = torch.tensor([[4.0, 6.0, 30.0, 20.0], [10.0, 10.0, 60.0, 62.0], [0.0, 0.0, 5.0, 9.0]])
    one = crop_inputs(frame_tensor(rgb, depth), torch.zeros(3, dtype=torch.long), boxes, cfg)
    frames = frame_tensor(np.repeat(rgb, 3, 0), np.repeat(depth, 3, 0))
    each = crop_inputs(frames, torch.arange(3), boxes, cfg)
    assert torch.equal(one[0], each[0]) and torch.equal(one[1], each[1])


def test_the_detectors_normalised_input_makes_the_same_frame() -> None:
    from tidee.agent.perception.detector.model import preprocess

    rng = np.random.default_rng(1)
    rgb = rng.integers(0, 256, (2, 32, 32, 3), dtype=np.uint8)
    depth = rng.uniform(0.0, 12.0, (2, 32, 32)).astype(np.float32)  # beyond the detector's clamp too
    x = preprocess(rgb, depth).contiguous(memory_format=torch.channels_last)
    assert torch.equal(frame_tensor(rgb, depth, normalised=x[:, :3]), frame_tensor(rgb, depth))
