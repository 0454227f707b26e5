"""Learned perception: detector data, targets, training, the shipped weights, and the agent using them."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
import torch

from tidee.agent.classes import CLASSES
from tidee.agent.perception.detector.config import DetectorConfig, GenConfig
from tidee.agent.perception.detector.data import configs, frame_targets, iter_frames, pack
from tidee.agent.perception.detector.model import CenterDetector, decode, encode_targets

torch.set_num_threads(2)
# the shipped perception (detector + crop reclassifier) scores 0.81 on these 24 frames, the detector
# alone 0.73; untrained weights ~0
DETECTOR_FLOOR_MAP50 = 0.6


def test_generator_refuses_held_out_rooms_and_lists_training_rooms() -> None:
    jobs = configs(GenConfig(rooms_per_type=22, messes_per_room=1))
    seeds = sorted({s for _, s, _ in jobs})
    assert seeds[:20] == list(range(20)) and seeds[20:] == [10_000, 10_001]
    assert len(jobs) == 22 * 4 * 2
    with pytest.raises(ValueError, match="training rooms"):
        list(iter_frames(GenConfig(), jobs=[("Kitchen", 200, 0)], progress=False))
    from tidee.agent.perception.detector.config import GenDetectionConfig
    from tidee.agent.perception.detector.data import generate

    with pytest.raises(ValueError, match="training data only"):
        generate(GenDetectionConfig(out="/nonexistent", gen=GenConfig(split="test")))
    # the data says which renderer drew it: "auto" would depend on the machine
    with pytest.raises(ValueError, match="name the renderer"):
        generate(GenDetectionConfig(out="/nonexistent", gen=GenConfig(renderer="auto")))


def test_instance_masks_match_the_rendered_geometry() -> None:
    """Unproject every mask pixel with the true camera: it lands on (in) its object's box."""
    from tidee.protocol.messages import EpisodeSpec
    from tidee.server.episode import Episode

    ep = Episode(renderer="tiny")
    try:
        obs = ep.reset(
            EpisodeSpec(room_type="Kitchen", seed=3, mess_index=1, resolution=128), ground_truth=True
        )
        for _ in range(2):
            from tidee.protocol.messages import Action

            obs = ep.step(Action(name="LookDown"), ground_truth=True)
        inst, rows = frame_targets(obs.ground_truth.instance_seg, obs.ground_truth.objects, obs.depth)
        assert len(rows) >= 3
        cam = ep.camera_pose_world(believed=False)
        k = obs.intrinsics
        by_id = {o["id"]: o for o in obs.ground_truth.objects}
        checked = 0
        for r in rows:
            m = inst == r["inst"]
            ys, xs = np.nonzero(m)
            assert r["pix"] == m.sum()
            assert r["box"] == [xs.min(), ys.min(), xs.max() + 1, ys.max() + 1]
            assert CLASSES[r["cls"]] == by_id[r["id"]]["type"]
            z = obs.depth[ys, xs]
            pts_cam = np.stack([(xs - k[0, 2]) / k[0, 0] * z, (ys - k[1, 2]) / k[1, 1] * z, z], 1)
            pts = pts_cam @ cam[:3, :3].T + cam[:3, 3]
            o = by_id[r["id"]]
            if o["type"] in ("Window", "Painting"):
                continue  # flush with a wall: the box is thinner than the render
            centre, size = np.array(o["position"]), np.array(o["size"])
            # rotated objects: the box's circumscribed sphere, plus a render tolerance
            inside = np.linalg.norm(pts - centre, axis=1) <= 0.5 * np.linalg.norm(size) + 0.05
            assert inside.mean() > 0.95, (o["type"], inside.mean())
            checked += 1
        assert checked >= 3
    finally:
        ep.close()


def test_targets_decode_back_to_their_boxes() -> None:
    boxes = np.array([[10, 20, 60, 90], [100, 100, 140, 120], [200, 30, 250, 200]], np.float32)
    classes = np.array([3, 17, 3])
    oop = np.array([0, 1, 0])
    t = encode_targets(boxes, classes, oop, len(CLASSES))
    out_hw = 64
    heat = np.full((1, len(CLASSES), out_hw, out_hw), -9.0, np.float32)
    heat[0][t["heat"] == 1] = 9.0
    size = np.zeros((1, 2, out_hw * out_hw), np.float32)
    off = np.zeros((1, 2, out_hw * out_hw), np.float32)
    oopl = np.full((1, 1, out_hw * out_hw), -9.0, np.float32)
    for k in range(int(t["mask"].sum())):
        i = t["ind"][k]
        size[0, :, i] = t["reg"][k, :2]
        off[0, :, i] = t["reg"][k, 2:]
        oopl[0, 0, i] = 9.0 if t["oop"][k] else -9.0
    out = {
        "heat": torch.from_numpy(heat),
        "size": torch.from_numpy(size.reshape(1, 2, out_hw, out_hw)),
        "off": torch.from_numpy(off.reshape(1, 2, out_hw, out_hw)),
        "oop": torch.from_numpy(oopl.reshape(1, 1, out_hw, out_hw)),
    }
    dets = sorted(decode(out, threshold=0.5)[0], key=lambda d: d.box[0])
    assert [d.cls for d in dets] == [3, 17, 3]
    assert [round(d.oop_prob) for d in dets] == [0, 1, 0]
    np.testing.assert_allclose([d.box for d in dets], boxes, atol=1e-3)
    # a second guess: class 40 also scores at the first box's centre cell
    i0 = int(t["ind"][0])
    out["heat"][0, 40].view(-1)[i0] = 1.0
    assert len(decode(out, threshold=0.5)[0]) == 3  # one class per peak
    multi = decode(out, threshold=0.5, classes_per_peak=2)[0]
    assert len(multi) == 4 and [d.cls for d in multi].count(40) == 1
    second = next(d for d in multi if d.cls == 40)
    first = next(d for d in multi if d.cell == second.cell and d.cls != 40)
    assert first.cls == 3 and first.box == second.box and second.score < first.score
    assert multi[-1] is second  # ranked by score with the rest


def test_peak_modes_keep_a_neighbours_peak_or_a_second_class() -> None:
    c, hw = len(CLASSES), 16
    heat = torch.full((1, c, hw, hw), -9.0)
    heat[0, 5, 8, 8] = 4.0  # a large object's centre ...
    heat[0, 5, 8, 9] = 2.0  # ... whose Gaussian spills onto the next cell,
    heat[0, 30, 8, 9] = 1.0  # where a small object of class 30 is centred
    heat[0, 12, 8, 8] = 0.5  # and a weaker second class on the large object's cell
    zeros = torch.zeros(1, 2, hw, hw)
    out = {"heat": heat, "size": zeros, "off": zeros, "oop": torch.zeros(1, 1, hw, hw)}
    by_mode = {
        m: sorted((d.cls, d.cell) for d in decode(out, threshold=0.5, peaks=m)[0])
        for m in ("class-max", "per-class", "per-class-single")
    }
    assert by_mode["class-max"] == [(5, (8, 8))]  # the neighbour's peak is suppressed
    assert by_mode["per-class"] == [(5, (8, 8)), (12, (8, 8)), (30, (8, 9))]
    assert by_mode["per-class-single"] == [(5, (8, 8))]  # class 30 is not its cell's best
    heat[0, 30, 8, 9] = 3.0
    assert sorted((d.cls, d.cell) for d in decode(out, threshold=0.5, peaks="per-class-single")[0]) == [
        (5, (8, 8)),
        (30, (8, 9)),
    ]
    with pytest.raises(ValueError, match="peaks='nms'"):
        decode(out, peaks="nms")


@pytest.fixture(scope="module")
def tiny_train_frames() -> dict[str, np.ndarray]:
    cfg = GenConfig(
        rooms_per_type=1,
        messes_per_room=1,
        walks_per_config=1,
        frames_per_walk=3,
        resolution=128,
        room_types=("LivingRoom",),
    )
    return pack(list(iter_frames(cfg, progress=False)))


def _write_shard_dir(root, frames: dict[str, Any], rooms: list[str]) -> None:
    import json

    root.mkdir()
    np.savez_compressed(root / "shard_0000.npz", **frames)
    (root / "manifest.json").write_text(
        json.dumps(
            {
                "command": f"synthetic {root.name}",
                "classes": list(CLASSES),
                "shards": ["shard_0000.npz"],
                "rooms": rooms,
            }
        )
    )


def test_several_data_directories_load_as_one_and_refuse_a_shared_room(tiny_train_frames, tmp_path) -> None:
    from tidee.agent.perception.detector.data import load_datasets

    f = tiny_train_frames
    n = len(f["rgb"])
    assert n >= 2 and len(f["obj_frame"]) > 0
    # the same frames, written twice as if from two sets of rooms; the second copy's objects must
    # point at its frames
    _write_shard_dir(tmp_path / "a", f, ["LivingRoom:0"])
    _write_shard_dir(tmp_path / "b", f, ["LivingRoom:80"])
    data, manifests = load_datasets(f"{tmp_path / 'a'},{tmp_path / 'b'}")
    assert len(data["rgb"]) == 2 * n and [m["command"] for m in manifests] == ["synthetic a", "synthetic b"]
    assert np.array_equal(data["obj_frame"], np.concatenate([f["obj_frame"], f["obj_frame"] + n]))
    assert np.array_equal(data["rgb"][n:], f["rgb"]) and np.array_equal(
        data["obj_box"][len(f["obj_box"]) :], f["obj_box"]
    )
    _write_shard_dir(tmp_path / "c", f, ["LivingRoom:0"])
    with pytest.raises(ValueError, match="LivingRoom:0 is in both"):
        load_datasets([str(tmp_path / "a"), str(tmp_path / "c")])
    with pytest.raises(ValueError, match="no manifest.json"):
        load_datasets(str(tmp_path / "missing"))


@pytest.mark.parametrize("precision", ["fp32", "bf16"])
def test_a_few_training_steps_reduce_the_loss(tiny_train_frames, tmp_path, precision) -> None:
    from tidee.agent.learning import bf16_supported
    from tidee.agent.perception.detector.config import TrainConfig
    from tidee.agent.perception.detector.train import train_detector

    if precision == "bf16" and not bf16_supported("cpu"):
        pytest.skip("this CPU has no native bf16")
    cfg = TrainConfig(
        work_dir=str(tmp_path / "run"),
        steps=16,
        batch_size=4,
        lr=2e-3,
        warmup=2,
        log_every=4,
        ckpt_every=8,
        precision=precision,
    )
    model_cfg = DetectorConfig(input_size=128)
    r = train_detector(cfg, model_cfg, resume=False, progress=False, data=tiny_train_frames, ship=False)
    assert r["precision"] == precision
    losses = [h["total"] for h in r["history"]]
    assert len(losses) == 4
    assert losses[-1] < 0.7 * losses[0], losses
    assert (tmp_path / "run" / "checkpoint.pt").exists() and (tmp_path / "run" / "loss.png").exists()
    # resuming a finished run does no more steps and keeps the history
    r2 = train_detector(cfg, model_cfg, resume=True, progress=False, data=tiny_train_frames, ship=False)
    assert r2["steps"] == 16 and r2["history"] == r["history"]


def test_parallel_batches_are_reproducible_and_resume_from_their_step(tiny_train_frames) -> None:
    from tidee.agent.perception.detector.train import Batches, ParallelBatches

    cfg = DetectorConfig(input_size=128)

    def draw(stream: ParallelBatches, n: int) -> list[torch.Tensor]:
        return [stream()[0] for _ in range(n)]

    a, b = (ParallelBatches(tiny_train_frames, cfg, 2, seed=3, workers=2) for _ in range(2))
    first = draw(a, 4)
    assert all(torch.equal(x, y) for x, y in zip(first, draw(b, 4)))
    # the two workers draw different batches, so the stream is not one batch repeated
    assert not torch.equal(first[0], first[1])
    assert a.state() == {"parallel_workers": 2, "start": 4}
    # a resumed stream restarts every worker from the saved step: the same batches as another resume there
    state = a.state()
    c, d = (ParallelBatches(tiny_train_frames, cfg, 2, seed=3, workers=2) for _ in range(2))
    c.set_state(state)
    d.set_state(state)
    resumed = draw(c, 2)
    assert all(torch.equal(x, y) for x, y in zip(resumed, draw(d, 2)))
    assert not torch.equal(resumed[0], first[0])
    assert c.state()["start"] == 6
    with pytest.raises(ValueError, match="same --loader-workers"):
        ParallelBatches(tiny_train_frames, cfg, 2, seed=3, workers=3).set_state(state)
    with pytest.raises(ValueError, match="--loader-workers 2"):
        Batches(tiny_train_frames, cfg, 2, seed=3).set_state(state)


def test_a_grown_model_starts_as_the_weights_it_grew_from(tmp_path) -> None:
    """--init with extra blocks and a head conv: same outputs before any step; foreign weights refused."""
    from tidee.agent.learning import save_checkpoint
    from tidee.agent.perception.detector.train import init_from

    torch.manual_seed(0)
    small = CenterDetector(DetectorConfig(input_size=128))
    with torch.no_grad():  # BN statistics and scales off their defaults, like trained weights
        for mod in small.modules():
            if isinstance(mod, torch.nn.BatchNorm2d):
                assert mod.running_mean is not None and mod.running_var is not None
                mod.weight.uniform_(0.5, 1.5)
                mod.bias.uniform_(-0.2, 0.2)
                mod.running_mean.uniform_(-0.5, 0.5)
                mod.running_var.uniform_(0.5, 2.0)
    path = tmp_path / "small.pt"
    save_checkpoint(path, config=small.cfg.to_dict(), state_dict=small.state_dict())
    grown = CenterDetector(DetectorConfig(input_size=128, extra_blocks=(1, 2, 1), head_conv=True, extra_s4=1))
    lineage = init_from(grown, path)
    assert lineage["new_tensors"] > 0 and len(lineage["sha256"]) == 64
    assert sum(p.numel() for p in grown.parameters()) > sum(p.numel() for p in small.parameters())
    x = torch.randn(2, 4, 128, 128)
    for mode in ("eval", "train"):
        small.train(mode == "train")
        grown.train(mode == "train")
        with torch.no_grad():
            a, b = small(x), grown(x)
        for k in a:
            torch.testing.assert_close(b[k], a[k], msg=f"{k} differs in {mode} mode")
    with torch.no_grad():  # and the grown blocks are real parameters that training moves
        grown.head_conv[1].weight.add_(0.1)
        assert not torch.allclose(grown(x)["heat"], small(x)["heat"])
    narrow = CenterDetector(DetectorConfig(input_size=128, neck=32))
    with pytest.raises(ValueError, match="not a subset"):
        init_from(narrow, path)


def test_only_shipped_weights_replace_the_loss_curve_in_the_docs(tmp_path, monkeypatch) -> None:
    """A candidate trained to runs/ keeps its curve in its work dir; weights written to the
    shipped directory copy theirs to docs/models/, which the manifest then names."""
    from tidee.agent import learning

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(learning, "WEIGHTS_DIR", (tmp_path / "weights").resolve())
    curve = tmp_path / "work" / "loss.png"
    curve.parent.mkdir()
    curve.write_bytes(b"curve")
    model = torch.nn.Linear(2, 1)
    assert learning.ship_weights(tmp_path / "runs" / "m.pt", model, {}, curve, "m_loss.png") == str(curve)
    assert (tmp_path / "runs" / "m.pt").exists() and not (tmp_path / "docs").exists()
    shipped = learning.ship_weights(tmp_path / "weights" / "m.pt", model, {}, curve, "m_loss.png")
    assert shipped == "docs/models/m_loss.png"
    assert (tmp_path / "docs" / "models" / "m_loss.png").read_bytes() == b"curve"


def test_model_outputs_have_the_documented_shapes() -> None:
    cfg = DetectorConfig()
    m = CenterDetector(cfg).eval()
    with torch.inference_mode():
        out = m(torch.zeros(2, 4, 256, 256))
    assert out["heat"].shape == (2, len(CLASSES), 64, 64)
    assert out["size"].shape == out["off"].shape == (2, 2, 64, 64)
    assert out["oop"].shape == (2, 1, 64, 64) and out["feat"].shape == (2, cfg.neck, 64, 64)


def test_folded_batch_norm_computes_what_the_trained_model_does() -> None:
    """The agent's copy of the detector has every batch norm folded into its convolution: the same
    outputs to float rounding, no BatchNorm2d left, and the trained module itself untouched."""
    import copy

    from tidee.agent.perception.detector.model import fold_batchnorm

    torch.manual_seed(0)
    m = CenterDetector(DetectorConfig(extra_blocks=(1, 1, 1), head_conv=True, extra_s4=1))
    m.train()
    with torch.no_grad():  # running statistics and affine weights far from their initial values
        for _ in range(3):
            m(torch.randn(2, 4, 128, 128) * 2 + 0.5)
        for bn in (x for x in m.modules() if isinstance(x, torch.nn.BatchNorm2d)):
            bn.weight.uniform_(0.5, 1.5)
            bn.bias.uniform_(-0.2, 0.2)
    m.eval()
    with pytest.raises(ValueError, match="eval"):
        fold_batchnorm(copy.deepcopy(m).train())
    folded = fold_batchnorm(copy.deepcopy(m))
    assert not any(isinstance(x, torch.nn.BatchNorm2d) for x in folded.modules())
    assert any(isinstance(x, torch.nn.BatchNorm2d) for x in m.modules())
    x = torch.randn(2, 4, 128, 128)
    with torch.inference_mode():
        a, b = m(x), folded(x)
    for k in a:
        torch.testing.assert_close(b[k], a[k], rtol=1e-4, atol=1e-4)


# ------------------------------------------------------------------ the shipped weights
@pytest.fixture(scope="module")
def shipped():
    from tidee.agent.perception.learned import LearnedPerception

    return LearnedPerception.load(threshold=0.05)


@pytest.fixture(scope="module")
def test_room_frames() -> dict[str, np.ndarray]:
    from tidee.agent.perception.detector.data import held_out_frames

    # one test room per type, its tidy and first messy configuration, 3 frames each: 24 frames
    return held_out_frames("test", rooms_per_type=1, messes=1, frames_per_walk=3, seed=7, progress=False)


def test_shipped_detector_manifest_is_complete(shipped) -> None:
    m = shipped.manifest
    assert m["command"].startswith("tidee train detector")
    assert "never val/test" in m["data"]["split"] and m["data"]["frames"] > 1000
    assert m["bytes"] < 30 * 2**20
    assert {"box_map50", "box_map50_95"} <= set(m["metrics"]), sorted(m["metrics"])


def test_shipped_detector_clears_an_accuracy_floor_on_test_rooms(shipped, test_room_frames) -> None:
    from tidee.agent.evaluation.detection.metrics import evaluate_boxes

    dets = shipped.detect_batch(test_room_frames["rgb"], test_room_frames["depth"].astype(np.float32))
    r = evaluate_boxes(dets, test_room_frames)
    assert r["map50"] >= DETECTOR_FLOOR_MAP50, r["map50"]
    for frame in dets:
        for d in frame:
            assert d.source == "learned" and 0 <= d.oop_prob <= 1 and d.feature.shape == (64,)
            x0, y0, x1, y1 = d.box
            assert 0 <= x0 < x1 <= 256 and 0 <= y0 < y1 <= 256


def test_each_detector_set_ships_with_verified_manifests() -> None:
    from tidee.agent.learning import WEIGHTS_DIR, read_manifest
    from tidee.agent.perception import DETECTOR_SETS, DETECTORS
    from tidee.agent.perception.detector.config import DEFAULT_WEIGHTS
    from tidee.agent.perception.reclassifier.config import DEFAULT_RECLASSIFIER
    from tidee.protocol.vocab import RENDERERS

    assert tuple(DETECTORS) == DETECTOR_SETS
    assert DETECTORS[DETECTOR_SETS[0]] == (DEFAULT_WEIGHTS.name, DEFAULT_RECLASSIFIER.name)
    for name, (det, rc) in DETECTORS.items():
        d, r = read_manifest(WEIGHTS_DIR / det), read_manifest(WEIGHTS_DIR / rc)  # checksums verified
        assert d["command"].startswith("tidee train detector"), name
        assert r["command"].startswith("tidee train reclassifier"), name
        assert {"alpha", "beta", "gate"} <= set(r["metrics"]["fusion"]), name
    # the set for both renderers was trained on frames of both
    renderers = {
        part["room_seeds"]["renderer"]
        for part in read_manifest(WEIGHTS_DIR / DETECTORS["tiny+egl"][0])["data"]["parts"]
    }
    assert renderers == set(RENDERERS) - {"auto"}  # every renderer there is


def test_the_detector_for_both_renderers_clears_the_floor_on_egl_test_frames() -> None:
    from tidee.agent.evaluation.detection.metrics import evaluate_boxes
    from tidee.agent.perception import make_perception
    from tidee.agent.perception.detector.data import held_out_frames
    from tidee.server.world import RendererUnavailable

    try:
        frames = held_out_frames(
            "test", rooms_per_type=1, messes=1, frames_per_walk=3, seed=7, renderer="egl", progress=False
        )
    except RendererUnavailable:
        pytest.skip("PyBullet's eglRenderer plugin does not load here")
    det = make_perception("learned", threshold=0.05, detector="tiny+egl")
    r = evaluate_boxes(det.detect_batch(frames["rgb"], frames["depth"].astype(np.float32)), frames)
    assert r["map50"] >= DETECTOR_FLOOR_MAP50, r["map50"]


def test_agent_runs_an_episode_with_learned_perception(tmp_path) -> None:
    from tidee.agent.config import AgentConfig, PolicyConfig
    from tidee.agent.runner import EpisodeRunner
    from tidee.protocol.messages import EpisodeSpec
    from tidee.protocol.transport import InProcessTransport

    cfg = AgentConfig(
        variant="CommonMemory",
        perception="learned",
        oop="visual",
        policy=PolicyConfig(mapping_step_budget=40),
    )
    spec = EpisodeSpec(room_type="Kitchen", seed=201, mess_index=0, resolution=128, max_steps=90)
    with InProcessTransport(renderer="tiny") as transport:
        runner = EpisodeRunner(cfg, transport, session="learned", log_dir=tmp_path)
        result = runner.run(spec, evaluate=True, episode_name="ep")
    assert result.record["perception"] == "learned"
    assert result.steps >= 40 and len(result.timings["perception_ms"]) == result.steps + 1
    from tidee.protocol.episode_log import LogReader

    memories = [m for k, m in LogReader(tmp_path / "ep").messages() if k == "memory"]
    assert memories, "no object memory was logged"
    objs = memories[-1].objects
    # the detector found and the mapper tracked several objects of this kitchen, with OOP probabilities
    assert len(objs) >= 5 and len({o.label for o in objs}) >= 3
    assert all(0.0 <= o.oop_prob <= 1.0 for o in objs)
