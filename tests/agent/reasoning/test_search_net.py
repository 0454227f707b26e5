"""The visual search network: model, training, search points and the shipped weights."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from tidee.agent.classes import CLASS_INDEX, CLASSES  # noqa: E402
from tidee.agent.learning import read_manifest  # noqa: E402
from tidee.agent.mapping.geometry import GridSpec  # noqa: E402
from tidee.agent.mapping.maps import SemanticMapper  # noqa: E402
from tidee.agent.reasoning.search import config as search_config  # noqa: E402
from tidee.agent.reasoning.search import data as search_data  # noqa: E402
from tidee.agent.reasoning.search import eval as search_eval  # noqa: E402
from tidee.agent.reasoning.search import model as search_model  # noqa: E402
from tidee.agent.reasoning.search import train as search_train  # noqa: E402
from tidee.server.splits import split_of  # noqa: E402

torch.set_num_threads(1)


def _synthetic(n_maps: int = 6, seed: int = 0) -> dict:
    """Maps whose class channel marks the one instance of that class: the net must copy it over."""
    rng = np.random.default_rng(seed)
    x = np.zeros((n_maps, search_model.C_IN, search_model.IN_SIZE, search_model.IN_SIZE), np.uint8)
    insts, rooms = [], []
    grid = GridSpec.centred(search_model.IN_SIZE, 0.1)
    for m in range(n_maps):
        rows = []
        for c in (CLASS_INDEX["Bed"], CLASS_INDEX["Sofa"]):
            cx, cy = rng.uniform(-3, 3, size=2)
            i, j = grid.to_cell((cx, cy))
            x[m, c, i - 3 : i + 4, j - 3 : j + 4] = 255
            rows.append((c, cx, cy, 0.3, 0.3, 0.0))
        insts.append(np.asarray(rows, np.float32))
        rooms.append(("Bedroom", m, -1))
    return {
        "x": x,
        "inst": insts,
        "owner": np.arange(n_maps),
        "seen": [[] for _ in range(n_maps)],
        "rooms": rooms,
    }


def test_model_output_shapes():
    model = search_model._build_model(width=8, embed=8).eval()
    x = torch.zeros(2, search_model.C_IN, search_model.IN_SIZE, search_model.IN_SIZE)
    cls = torch.tensor([[0, 5, 7], [1, 2, 3]])
    with torch.no_grad():
        out = model(x, cls)
    assert out.shape == (2, 3, search_model.OUT_SIZE, search_model.OUT_SIZE)


def test_search_input_of_a_fresh_map():
    mapper = SemanticMapper(classes=CLASSES)
    x = search_model.search_input(mapper)
    assert x.shape == (search_model.C_IN, 128, 128) and x.dtype == np.float32
    assert x.max() == 0.0


def test_targets_peak_on_the_footprint():
    inst = np.array([[3, 1.0, -2.0, 0.5, 0.2, 0.0]], np.float32)
    t = search_data.target_heat(inst, [3, 4])
    assert t.shape == (2, 64, 64)
    assert t[1].max() == 0.0
    i, j = search_model.out_grid().to_cell((1.0, -2.0))
    assert t[0, i, j] == pytest.approx(1.0)
    i, j = search_model.out_grid().to_cell((1.0, 0.0))  # 1.8 m from the footprint
    assert t[0, i, j] < 0.01


def test_a_few_training_steps_reduce_the_loss():
    torch.manual_seed(0)
    data = _synthetic()
    rng = np.random.default_rng(0)
    x, c, t = search_train._batch(data, range(4), rng, 2, augment=False)
    model = search_model._build_model(width=8, embed=8)
    opt = torch.optim.Adam(model.parameters(), lr=5e-3)
    xt, ct, tt = torch.from_numpy(x), torch.from_numpy(c), torch.from_numpy(t)
    losses = []
    for _ in range(12):
        loss = torch.nn.functional.binary_cross_entropy_with_logits(
            model(xt, ct), tt, pos_weight=torch.tensor(10.0)
        )
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()))
    assert losses[-1] < 0.7 * losses[0]


def test_train_search_net_ships_weights_with_a_manifest(tmp_path):
    cfg = search_config.SearchTrainConfig(
        out=str(tmp_path / "net.pt"),
        work_dir=str(tmp_path / "work"),
        steps=3,
        batch_size=2,
        classes_per_map=2,
        width=8,
        embed=8,
        val_fraction=0.34,
        threads=1,
        log_every=1,
    )
    summary = search_train.train_search_net(
        cfg, command="test", data=_synthetic(), progress=False, docs_png=None
    )
    assert summary["steps"] == 3 and len(summary["history"]) == 3
    manifest = read_manifest(tmp_path / "net.pt")
    assert manifest["command"] == "test" and "val" in manifest["metrics"]
    vs = search_model.VisualSearch.load(tmp_path / "net.pt")
    heat = vs.heatmap(SemanticMapper(classes=CLASSES), "Bed")
    assert heat.shape == (128, 128) and 0.0 <= heat.min() <= heat.max() <= 1.0


def test_augmentation_moves_instances_with_the_map():
    data = _synthetic(1)
    x = data["x"][0].astype(np.float32)
    inst = data["inst"][0]
    grid = GridSpec.centred(search_model.IN_SIZE, 0.1)
    for k in range(4):
        for flip in (False, True):
            xa, ia = search_train._augment(x, inst, k, flip)
            for row in ia:
                i, j = grid.to_cell(row[1:3])
                assert xa[int(row[0]), i, j] == 255


# --- farthest point sampling and search points -------------------------------------------------


def test_fps_spreads_points_in_order():
    pts = np.array([[0, 0], [0.1, 0], [5, 0], [5, 5], [0, 5], [2.5, 2.5]], float)
    idx = search_model.farthest_point_sampling(pts, 4)
    assert idx[0] == 0
    assert idx[1] == 3  # the farthest from (0, 0)
    assert set(idx[2:].tolist()) == {2, 4}
    assert len(set(idx.tolist())) == 4


def test_fps_k_larger_than_points_and_empty_input():
    pts = np.array([[0, 0], [1, 0], [2, 0]], float)
    assert sorted(search_model.farthest_point_sampling(pts, 10).tolist()) == [0, 1, 2]
    assert search_model.farthest_point_sampling(np.zeros((0, 2)), 3).size == 0
    assert search_model.farthest_point_sampling(pts, 0).size == 0
    # duplicates are never chosen twice; min_dist suppresses near neighbours
    assert search_model.farthest_point_sampling(np.zeros((5, 2)), 3).tolist() == [0]
    assert search_model.farthest_point_sampling(pts, 3, first=0, min_dist=1.5).tolist() == [0, 2]
    with pytest.raises(ValueError, match="first"):
        search_model.farthest_point_sampling(pts, 2, first=7)


def test_search_points_on_a_hand_made_heatmap():
    grid = GridSpec.centred(128, 0.1)
    heat = np.zeros((128, 128))
    a, b = grid.to_cell((2.0, 1.0)), grid.to_cell((-1.0, -3.0))
    heat[a[0] - 2 : a[0] + 3, a[1] - 2 : a[1] + 3] = 0.7
    heat[a] = 0.8
    heat[b[0] - 2 : b[0] + 3, b[1] - 2 : b[1] + 3] = 0.9
    pts, scores = search_model.search_points(heat, grid, threshold=0.5, k=3, min_dist_m=1.0)
    assert len(pts) == 2  # one per blob: the rest is suppressed
    assert np.allclose(pts[0], (-0.95, -2.95), atol=0.3)  # hottest first
    assert np.allclose(pts[1], (2.05, 1.05), atol=0.06)
    assert scores[0] >= scores[1]
    valid = np.ones_like(heat, bool)
    valid[b[0] - 3 : b[0] + 4, b[1] - 3 : b[1] + 4] = False
    pts, _ = search_model.search_points(heat, grid, threshold=0.5, k=3, valid=valid)
    assert len(pts) == 1 and np.allclose(pts[0], (2.05, 1.05), atol=0.06)
    # nothing above the threshold: fall back to the cells within half the maximum
    pts, _ = search_model.search_points(heat * 0.1, grid, threshold=0.5, k=3)
    assert len(pts) == 2
    with pytest.raises(ValueError, match="does not match"):
        search_model.search_points(np.zeros((10, 10)), grid)


def test_snap_to_mask_moves_points_onto_allowed_cells():
    grid = GridSpec.centred(256, 0.05)
    mask = np.zeros((256, 256), bool)
    mask[128:140, 128:140] = True
    out = search_model.snap_to_mask(np.array([[3.0, 3.0], [0.2, 0.2]]), mask, grid)
    for p in out:
        i, j = grid.to_cell(p)
        assert mask[i, j]
    assert search_model.snap_to_mask(np.array([[1.0, 1.0]]), np.zeros((256, 256), bool), grid) == []


# --- the shipped weights on held-out (test-room) maps -------------------------------------------


@pytest.fixture(scope="module")
def held_out_maps():
    """A few map snapshots of test rooms (oracle detections, short exploration): evaluation only."""
    from tidee.agent.perception import make_perception
    from tidee.protocol.transport import InProcessTransport

    cfg = search_config.SearchGenConfig(
        split="test", snapshots=2, max_steps=70, perception="oracle", workers=1
    )
    samples = []
    with InProcessTransport(renderer="tiny") as t:
        perception = make_perception("oracle")
        for job in (("Bedroom", 200, None), ("Kitchen", 201, None), ("LivingRoom", 202, None)):
            res = search_data.snapshot_config(job, cfg, t, perception)
            samples += [{"x": x, "inst": res["inst"], "seen": seen} for x, seen in zip(res["x"], res["seen"])]
    return samples


def test_shipped_weights_load_and_beat_the_occupancy_baseline(held_out_maps):
    manifest = read_manifest(search_model.DEFAULT_WEIGHTS)  # checksum verified
    seeds = manifest["data"]["room_seeds"]
    assert seeds and all(split_of(s) in ("train", "train_pool") for s in seeds)  # training rooms only
    vs = search_model.VisualSearch.load()
    m = search_eval.heldout_metrics(vs, held_out_maps)
    assert m["network"]["n"] >= 20
    assert m["network"]["ap"] > m["occupancy"]["ap"] + 0.05, m
    assert m["network"]["hit"] > m["occupancy"]["hit"], m


def test_search_data_refuses_too_few_steps_for_its_late_snapshots() -> None:
    with pytest.raises(ValueError, match="max_steps > 60"):
        search_config.SearchGenConfig(out="d", max_steps=40)
