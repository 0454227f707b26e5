"""Box AP and in/out-of-place AP (tidee.agent.evaluation.detection) on hand-built frames."""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import re
from pathlib import Path

import numpy as np
import pytest

from tidee.agent.classes import CLASS_INDEX, PICKUPABLE
from tidee.agent.evaluation.detection import commands, report
from tidee.agent.evaluation.detection import eval as ev
from tidee.agent.evaluation.detection import metrics as de
from tidee.agent.evaluation.detection.config import EvalDetectorConfig, EvalFusionConfig, EvalOopConfig
from tidee.agent.perception.base import Detection
from tidee.options import from_args

PICK = sorted(PICKUPABLE)
NON_PICK = sorted(set(CLASS_INDEX) - PICKUPABLE)
PAPER_TEX = Path("/work/shared/paper/tidee-eccv2022.tex")


def make_frames(
    objects: list[tuple[int, str, tuple[float, float, float, float], int]], n_frames: int, size: int = 64
) -> dict[str, np.ndarray]:
    """A packed frames dict from (frame, class name, box, oop) rows; rgb filled per frame."""
    rgb = np.zeros((n_frames, size, size, 3), np.uint8)
    rgb[:] = np.arange(n_frames, dtype=np.uint8)[:, None, None, None] * 20  # frames tell apart
    return {
        "rgb": rgb,
        "depth": np.ones((n_frames, size, size), np.float16),
        "obj_frame": np.array([o[0] for o in objects], np.int32),
        "obj_cls": np.array([CLASS_INDEX[o[1]] for o in objects], np.int16),
        "obj_box": np.array([o[2] for o in objects], np.float32).reshape(-1, 4),
        "obj_oop": np.array([o[3] for o in objects], np.uint8),
        "frame_room": np.array([f"Kitchen:200:{i % 2}" for i in range(n_frames)]),
    }


def perfect(frames: dict, oop_prob: str = "gt") -> list[list[Detection]]:
    """One detection per GT row, score 1; ``oop_prob`` "gt" (the label), "inverted" or "half"."""
    out: list[list[Detection]] = [[] for _ in range(len(frames["rgb"]))]
    for f, c, b, o in zip(frames["obj_frame"], frames["obj_cls"], frames["obj_box"], frames["obj_oop"]):
        p = {"gt": float(o), "inverted": 1.0 - float(o), "half": 0.5}[oop_prob]
        out[int(f)].append(
            Detection(
                label=de.CLASSES[int(c)], score=1.0, box=tuple(int(x) for x in b), oop_prob=p, source="fake"
            )
        )
    return out


class GTDetector:
    """A fake ``FrameDetector``: finds each frame by its pixels and returns its GT boxes, jittered.

    ``jitter`` (pixels) moves each box edge; scores are random; ``fp_rate`` adds a random box
    of a random class per GT with that probability. Deterministic in ``seed``.
    """

    name = "gt-fake"

    def __init__(
        self, frames: dict, jitter: float = 0.0, fp_rate: float = 0.0, oop_noise: float = 0.0, seed: int = 0
    ) -> None:
        self.frames, self.jitter, self.fp_rate, self.oop_noise = frames, jitter, fp_rate, oop_noise
        self.index = {
            hashlib.sha1(np.ascontiguousarray(im).tobytes()).hexdigest(): i
            for i, im in enumerate(frames["rgb"])
        }
        self.rng = np.random.default_rng(seed)

    def detect_batch(self, rgbs: np.ndarray, depths: np.ndarray) -> list[list[Detection]]:
        out = []
        h, w = rgbs.shape[1:3]
        for im in rgbs:
            i = self.index[hashlib.sha1(np.ascontiguousarray(im).tobytes()).hexdigest()]
            dets = []
            for r in np.nonzero(self.frames["obj_frame"] == i)[0]:
                box = np.asarray(self.frames["obj_box"][r], float) + self.rng.normal(0, self.jitter, 4)
                box = np.clip(np.round(box), 0, [w, h, w, h]).astype(int)
                oop = float(self.frames["obj_oop"][r])
                p = float(np.clip(oop + self.rng.normal(0, self.oop_noise), 0.01, 0.99))
                dets.append(
                    Detection(
                        label=de.CLASSES[int(self.frames["obj_cls"][r])],
                        score=float(self.rng.uniform(0.3, 1.0)),
                        box=tuple(box.tolist()),
                        oop_prob=p,
                        source="fake",
                    )
                )
                if self.rng.random() < self.fp_rate:
                    x0, y0 = self.rng.integers(0, w - 8), self.rng.integers(0, h - 8)
                    dets.append(
                        Detection(
                            label=de.CLASSES[int(self.rng.integers(len(de.CLASSES)))],
                            score=float(self.rng.uniform(0.0, 0.6)),
                            box=(int(x0), int(y0), int(x0) + 8, int(y0) + 8),
                            oop_prob=float(self.rng.random()),
                            source="fake",
                        )
                    )
            out.append(dets)
        return out


# ------------------------------------------------------------------------- AP


def test_ap_perfect_and_empty():
    assert de.average_precision([0.9, 0.8, 0.1], [True, True, True], 3) == 1.0
    assert math.isnan(de.average_precision([0.5], [False], 0))
    assert de.average_precision([], [], 4) == 0.0


def test_ap_hand_computed_tp_fp_tp():
    # 2 GT; TP, FP, TP by descending score: recall .5 .5 1, precision 1 .5 2/3 -> envelope 1 2/3 2/3.
    # Recall points 0..0.50 (51) sample 1, points 0.51..1 (50) sample 2/3.
    ap = de.average_precision([0.9, 0.8, 0.7], [True, False, True], 2)
    assert ap == pytest.approx((51 * 1.0 + 50 * 2 / 3) / 101)
    # Order is by score, not by input order.
    assert de.average_precision([0.7, 0.9, 0.8], [True, True, False], 2) == pytest.approx(ap)
    # Missing recall: 1 of 2 GT found with precision 1 -> 51 of 101 points.
    assert de.average_precision([0.9], [True], 2) == pytest.approx(51 / 101)


def test_duplicate_detection_is_false_positive():
    frames = make_frames([(0, PICK[0], (10, 10, 30, 30), 0), (0, PICK[0], (40, 40, 60, 60), 0)], 1)
    dets = perfect(frames)
    assert de.evaluate_boxes(dets, frames)["map50"] == 1.0
    # A second box on the first object, scored between the two true ones: TP, FP, TP.
    dets[0][0].score, dets[0][1].score = 0.9, 0.7
    dup = [dets[0] + [Detection(PICK[0], 0.8, (11, 11, 30, 30))]]
    r = de.evaluate_boxes(dup, frames)
    assert r["map50"] == pytest.approx((51 + 50 * 2 / 3) / 101)
    # Ranked below every true detection, a duplicate costs nothing (the precision envelope).
    dup = [dets[0] + [Detection(PICK[0], 0.1, (11, 11, 30, 30))]]
    assert de.evaluate_boxes(dup, frames)["map50"] == 1.0


def test_matching_greedy_by_score_each_gt_once():
    gt = np.array([[0, 0, 10, 10], [20, 0, 30, 10]])
    det = np.array([[0, 0, 10, 10], [1, 0, 11, 10], [20, 0, 30, 10]])
    m = de.match_detections(det, [0.5, 0.9, 0.7], gt, 0.5)
    assert m.tolist() == [-1, 0, 1]  # the higher-scored det takes GT 0
    assert de.match_detections(det, [0.5, 0.9, 0.7], gt, 0.95).tolist() == [0, -1, 1]


def test_iou_threshold_behaviour():
    # 10x10 GT; detection shifted by 4 px: IoU = 60 / 140 = 0.43.
    frames = make_frames([(0, PICK[0], (0, 0, 10, 10), 0)], 1)
    dets = [[Detection(PICK[0], 0.9, (4, 0, 14, 10))]]
    assert de.box_iou(np.array([[4, 0, 14, 10]]), np.array([[0, 0, 10, 10]]))[0, 0] == pytest.approx(60 / 140)
    r = de.evaluate_boxes(dets, frames, iou_thresholds=(0.4, 0.5))
    assert r["map50"] == 0.0
    assert r["map"] == pytest.approx(0.5)  # AP 1 at 0.4, 0 at 0.5
    oop = de.evaluate_oop({"v": [[0.0]]}, dets, frames)["rows"]["v"]["iou"]
    assert oop["0.25"]["map"] == 1.0 and oop["0.5"]["map"] == 0.0


def test_boxes_per_class_and_size():
    objs = [
        (0, PICK[0], (0, 0, 10, 10), 0),
        (0, PICK[1], (20, 20, 60, 60), 0),
        (1, PICK[0], (0, 0, 10, 10), 0),
    ]
    frames = make_frames(objs, 2)
    dets = perfect(frames)
    dets[1] = [Detection(PICK[1], 0.9, (0, 0, 10, 10))]  # wrong class in frame 1: a miss and an FP
    r = de.evaluate_boxes(dets, frames)
    per = {c["class"]: c for c in r["per_class"]}
    assert per[PICK[0]]["n_gt"] == 2 and per[PICK[0]]["ap50"] == pytest.approx(51 / 101)
    assert per[PICK[1]]["ap50"] == pytest.approx(1.0)  # its TP is ranked above the FP
    assert r["per_class"][0]["class"] == PICK[0]  # sorted by GT count
    assert r["by_size"]["small"]["n_gt"] == 2 and r["by_size"]["medium"]["n_gt"] == 1
    assert r["by_size"]["medium"]["map50"] == 1.0
    assert math.isnan(r["by_size"]["large"]["map50"])
    with pytest.raises(ValueError, match="lists of detections"):
        de.evaluate_boxes(dets[:1], frames)
    with pytest.raises(ValueError, match="not one of"):
        de.evaluate_boxes([[Detection("Spaceship", 1.0, (0, 0, 1, 1))], []], frames)


# ------------------------------------------------------------------------- OOP


def oop_frames() -> dict:
    rng = np.random.default_rng(3)
    objs: list[tuple[int, str, tuple[float, float, float, float], int]] = []
    for f in range(6):
        for k in range(5):
            x, y = 12 * k, int(rng.integers(0, 40))
            objs.append((f, PICK[(f + k) % len(PICK)], (x, y, x + 10, y + 12), int((f + k) % 3 == 0)))
        objs.append((f, NON_PICK[f % len(NON_PICK)], (0, 50, 64, 64), 0))  # not pickupable: left out
    return make_frames(objs, 6)


def test_oop_oracle_labels_perfect_inverted_low():
    frames = oop_frames()
    dets = perfect(frames)
    rows = {
        name: [[float(p) for p in ps] for ps in probs]
        for name, probs in (
            ("gt", [[d.oop_prob for d in ds] for ds in perfect(frames, "gt")]),
            ("inverted", [[d.oop_prob for d in ds] for ds in perfect(frames, "inverted")]),
            ("half", [[d.oop_prob for d in ds] for ds in perfect(frames, "half")]),
        )
    }
    r = de.evaluate_oop(rows, dets, frames)
    n_pick = sum(1 for c in frames["obj_cls"] if de.CLASSES[int(c)] in PICKUPABLE)
    assert r["n_gt_in_place"] + r["n_gt_out_of_place"] == n_pick == r["n_detections"]
    for thr in ("0.25", "0.5"):
        assert r["rows"]["gt"]["iou"][thr]["map"] == 1.0
        inv = r["rows"]["inverted"]["iou"][thr]
        # Inverted: every wrong-category copy ranks above every right one, so precision is the
        # category's share of the objects at every recall: the lowest AP with all objects found.
        assert inv["ap_in_place"] == pytest.approx(r["n_gt_in_place"] / n_pick)
        assert inv["ap_out_of_place"] == pytest.approx(r["n_gt_out_of_place"] / n_pick)
        assert inv["ap_out_of_place"] < 0.5
        assert inv["map"] <= r["rows"]["half"]["iou"][thr]["map"] < 1.0  # no better than a coin


def test_oracle_label_ceiling_is_perfect_on_perfect_boxes_and_drops_with_missed_ones():
    frames = oop_frames()
    dets = perfect(frames, "half")  # the detections' own P(oop) is ignored
    r = de.evaluate_oop({de.CEILING_ROW: de.oracle_label_row(frames, dets)}, dets, frames)
    assert r["rows"][de.CEILING_ROW]["iou"]["0.5"]["map"] == 1.0
    shifted = [
        [
            Detection(d.label, d.score, (d.box[0] + 40, d.box[1], d.box[2] + 40, d.box[3]), oop_prob=0.5)
            for d in ds
        ]
        for ds in dets
    ]  # every box misplaced: nothing matches
    probs = de.oracle_label_row(frames, shifted)
    assert all(p == 0.5 for ps in probs for p in ps)
    assert de.evaluate_oop({"c": probs}, shifted, frames)["rows"]["c"]["iou"]["0.5"]["map"] < 0.5


def test_oop_class_label_ignored():
    frames = make_frames([(0, PICK[0], (0, 0, 10, 10), 1)], 1)
    dets = [[Detection(PICK[1], 0.8, (0, 0, 10, 10), oop_prob=0.9)]]  # wrong class, right box
    r = de.evaluate_oop({"v": [[0.9]]}, dets, frames)
    assert r["rows"]["v"]["iou"]["0.5"]["ap_out_of_place"] == 1.0
    with pytest.raises(ValueError, match="one P"):
        de.evaluate_oop({"v": [[0.9, 0.1]]}, dets, frames)


def test_oop_table_lists_unbuilt_rows():
    frames = oop_frames()
    dets = perfect(frames)
    r = de.evaluate_oop(
        {de.VISUAL_ROW: [[d.oop_prob for d in ds] for ds in dets], "BERT-OOP (language)": None}, dets, frames
    )
    table = report.oop_table_markdown(r)
    for name in de.OOP_ROWS:
        assert name in table
    assert table.count(report.NOT_BUILT) == 3  # language (given as None), fused, oracle (absent)
    assert "| dDETR-OOP (visual) | 100.00 | 100.00 | 100.00 | 100.00 | 100.00 | 100.00 |" in table
    assert "paper (AI2THOR)" in table and "90.70" in table


@pytest.mark.skipif(not PAPER_TEX.exists(), reason="the paper source is not in this checkout")
def test_paper_figures_match_the_tex():
    tex = PAPER_TEX.read_text()
    names = {
        "vilangOOP": "dDETR+BERT-OOP (fused)",
        "visualOOP": de.VISUAL_ROW,
        "langOOP": "BERT-OOP (language)",
        "oraclelangOOP": "Oracle-language",
    }
    for macro, row in names.items():
        line = re.search(r"^\$\\" + macro + r"\$ &(.*)\\\\", tex, re.MULTILINE)
        assert line is not None, macro
        cells = [c.strip().replace(r"\textbf{", "").rstrip("}") for c in line.group(1).split("&")]
        assert [None if c == "--" else float(c) for c in cells] == list(report.PAPER_TABLE3[row])


# ------------------------------------------------------------------------- runners and CLI


def test_run_evals_write_reports(tmp_path, monkeypatch):
    frames = oop_frames()
    monkeypatch.setattr(ev, "held_out_frames", lambda *a, **k: frames)
    det = GTDetector(frames, jitter=0.5, fp_rate=0.3, oop_noise=0.3, seed=1)
    r = ev.run_detector_eval(det, EvalDetectorConfig(out=str(tmp_path)), progress=False)
    assert 0.5 < r["map50"] <= 1.0
    md = (tmp_path / "detector.md").read_text()
    assert "gt-fake" in md and "mAP@0.5" in md and "ms/frame" in md and "Kitchen:200" in md
    assert json.loads((tmp_path / "detector.json").read_text())["data"]["frames"] == 6
    assert (tmp_path / "detector_examples.png").stat().st_size > 1000

    calls = []
    r = ev.run_oop_eval(
        det,
        EvalOopConfig(out=str(tmp_path), views=4, rooms_per_type=1, messes=1),
        progress=False,
        extra_rows={"Oracle-language": lambda fr, ds: (calls.append(1), [[0.5] * len(d) for d in ds])[1]},
    )
    assert calls and r["rows"]["Oracle-language"]["built"] and not r["rows"]["BERT-OOP (language)"]["built"]
    md = (tmp_path / "oop.md").read_text()
    assert md.count(report.NOT_BUILT) == 2 and "paper (AI2THOR)" in md
    assert r["data"]["configurations_expected"] == 4 and r["data"]["views_max"] == 3  # honest counts


def test_register_parses_and_rejects_train():
    parser = argparse.ArgumentParser(prog="tidee")
    evs = parser.add_subparsers(dest="command").add_parser("eval").add_subparsers(dest="eval_cmd")
    commands.register(evs)
    a = parser.parse_args(
        [
            "eval",
            "detector",
            "--split",
            "test",
            "--out",
            "x",
            "--rooms-per-type",
            "2",
            "--frames-per-walk",
            "3",
            "--weights",
            "w.pt",
        ]
    )
    assert from_args(EvalDetectorConfig, a) == EvalDetectorConfig(
        split="test", out="x", rooms_per_type=2, frames_per_walk=3, weights="w.pt"
    )
    a = parser.parse_args(["eval", "oop", "--split", "val", "--out", "x", "--views", "4"])
    assert from_args(EvalOopConfig, a) == EvalOopConfig(split="val", out="x", views=4)
    a = parser.parse_args(["eval", "reclassifier", "--out", "x", "--alphas", "0.5,1", "--betas", "0"])
    cfg = from_args(EvalFusionConfig, a)
    assert (cfg.split, cfg.alphas, cfg.betas) == ("val", (0.5, 1.0), (0.0,))
    for bad in (
        ["eval", "oop", "--split", "train", "--out", "x"],
        ["eval", "reclassifier", "--alphas", "1,x", "--out", "x"],  # comma-separated numbers
        ["eval", "detector", "--out", "x", "--peaks", "nms"],
    ):
        with pytest.raises(SystemExit):
            parser.parse_args(bad)


def test_cli_handlers_run_and_return_zero(tmp_path, monkeypatch, capsys):
    frames = oop_frames()
    monkeypatch.setattr(ev, "held_out_frames", lambda *a, **k: frames)
    from tidee.agent.evaluation.detection import fusion

    monkeypatch.setattr(fusion, "held_out_frames", lambda *a, **k: frames)
    monkeypatch.setattr(
        ev, "_load_detector", lambda weights, reclassifier="default": GTDetector(frames, jitter=0.5, seed=5)
    )
    parser = argparse.ArgumentParser(prog="tidee")
    commands.register(parser.add_subparsers(dest="eval_cmd"))
    for argv in (
        ["detector", "--out", str(tmp_path / "d")],
        ["oop", "--out", str(tmp_path / "o"), "--views", "3", "--visual-only"],
    ):
        args = parser.parse_args(argv)
        assert args.func(args) == 0
    assert "mAP@0.5" in capsys.readouterr().out
    assert (tmp_path / "d" / "detector.json").exists() and (tmp_path / "o" / "oop.json").exists()
    # the fusion sweep needs a second stage to sweep; choosing it on the test rooms is refused
    with pytest.raises(ValueError, match="needs a detector with a crop reclassifier"):
        args = parser.parse_args(["reclassifier", "--out", str(tmp_path / "f")])
        args.func(args)
    with pytest.raises(SystemExit, match="validation rooms"):
        args = parser.parse_args(
            ["reclassifier", "--split", "test", "--record", "--out", str(tmp_path / "f")]
        )
        args.func(args)


def test_eval_detector_on_egl_frames_does_not_record_into_the_manifest():
    with pytest.raises(SystemExit, match="drop --record with --renderer egl"):
        commands.run_eval_detector(EvalDetectorConfig(out="x", record=True, renderer="egl"))
