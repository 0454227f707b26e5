"""Memex + rGCN placement: graph relations, message passing, batching, training, shipped weights."""

from __future__ import annotations

import math

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from tidee.agent.classes import CLASS_INDEX  # noqa: E402
from tidee.agent.mapping.memory import ObjectMemory  # noqa: E402
from tidee.agent.reasoning.rgcn.config import RGCNConfig, RGCNTrainConfig  # noqa: E402
from tidee.agent.reasoning.rgcn.data import check_seeds, heldout_rooms, placement_data  # noqa: E402
from tidee.agent.reasoning.rgcn.eval import evaluate_placement  # noqa: E402
from tidee.agent.reasoning.rgcn.memex import (  # noqa: E402
    PLACE_CLASSES,
    REL_INDEX,
    GraphNode,
    aabb_relations,
    make_graph,
    oriented_relations,
)
from tidee.agent.reasoning.rgcn.model import (  # noqa: E402
    DEFAULT_WEIGHTS,
    DEFAULT_WITHOUT_MEMEX,
    PlacementRGCN,
    RGCNPlacement,
    collate,
    load_rgcn,
    relational_mean,
)
from tidee.agent.reasoning.rgcn.train import train_rgcn  # noqa: E402


def _random_nodes(rng: np.random.Generator, n: int) -> list[GraphNode]:
    nodes = []
    for _ in range(n):
        lo = np.r_[rng.uniform(0, 3, 2), rng.choice([0.0, 0.45, 0.9, rng.uniform(0, 1.5)])]
        size = rng.uniform(0.1, 1.2, 3)
        nodes.append(GraphNode("Mug", tuple(lo), tuple(lo + size)))
    return nodes


def test_aabb_relations_match_box_relations_on_axis_aligned_boxes():
    rng = np.random.default_rng(0)
    for trial in range(5):
        nodes = _random_nodes(rng, 14)
        fast = {tuple(e) for e in aabb_relations(nodes)}
        # box_relations on yaw-0 boxes, without "facing" (no front on an axis-aligned box)
        slow = {tuple(e) for e in oriented_relations(nodes) if e[1] != REL_INDEX["facing"]}
        assert fast == slow, (
            f"trial {trial}: only fast {sorted(fast - slow)[:5]}, only slow {sorted(slow - fast)[:5]}"
        )
        assert len(fast) > 10


def test_supported_by_and_above_on_a_hand_built_stack():
    table = GraphNode("DiningTable", (0, 0, 0), (1.2, 0.8, 0.75))
    mug = GraphNode("Mug", (0.5, 0.3, 0.75), (0.6, 0.4, 0.85))
    chair = GraphNode("Chair", (1.3, 0.0, 0.0), (1.8, 0.5, 0.9))
    e = {(i, r, j) for i, r, j in aabb_relations([table, mug, chair]).tolist()}
    assert (1, REL_INDEX["supported_by"], 0) in e and (1, REL_INDEX["above"], 0) in e
    assert (0, REL_INDEX["below"], 1) in e
    assert (0, REL_INDEX["next_to"], 2) in e and (2, REL_INDEX["next_to"], 0) in e
    assert (1, REL_INDEX["supported_by"], 2) not in e


def test_relational_mean_on_a_hand_built_graph():
    # nodes 0, 1, 2; relation 0: 1->0, 2->0 ; relation 1: 2->1
    x = torch.tensor([[1.0, 0.0], [0.0, 2.0], [4.0, 4.0]])
    w = torch.stack([torch.eye(2), 2 * torch.eye(2)])
    edges = torch.tensor([[1, 0, 0], [2, 0, 0], [2, 1, 1]])
    out = relational_mean(x, edges, w, 3)
    assert torch.allclose(out[0], torch.tensor([2.0, 3.0]))  # mean of x1, x2 through W0
    assert torch.allclose(out[1], torch.tensor([8.0, 8.0]))  # x2 through W1
    assert torch.allclose(out[2], torch.zeros(2))  # no incoming edge


def test_collate_takes_the_object_out_of_its_graph():
    nodes = [
        GraphNode("DiningTable", (0, 0, 0), (1.2, 0.8, 0.75)),
        GraphNode("Mug", (0.5, 0.3, 0.75), (0.6, 0.4, 0.85)),
        GraphNode("Chair", (1.3, 0.0, 0.0), (1.8, 0.5, 0.9)),
    ]
    g = make_graph(nodes, aabb_relations(nodes), "Kitchen")
    b = collate([(g, 1, None, 0), (g, 0, None, 2)])
    assert b["oop_labels"].tolist() == [CLASS_INDEX["Mug"], CLASS_INDEX["DiningTable"]]
    assert b["scene_seg"].tolist() == [0, 0, 1, 1]
    assert b["scene_labels"].tolist() == [
        CLASS_INDEX["DiningTable"],
        CLASS_INDEX["Chair"],
        CLASS_INDEX["Mug"],
        CLASS_INDEX["Chair"],
    ]
    e = b["scene_edges"].tolist()
    nt, al = REL_INDEX["next_to"], REL_INDEX["aligned_with"]
    # sample 0 (mug out): table <-> chair next to and aligned; sample 1 (table out): mug and chair
    # are 0.7 m apart (not next to) with faces 0.1 m apart (aligned); nothing touches the OOP node
    assert sorted(map(tuple, e)) == sorted(
        [(0, nt, 1), (0, al, 1), (1, nt, 0), (1, al, 0), (2, al, 3), (3, al, 2)]
    )
    model = PlacementRGCN(RGCNConfig(hidden=16, use_memex=False))
    assert model(b).shape == (2, len(PLACE_CLASSES))


def test_memory_and_training_rooms_are_checked():
    with pytest.raises(ValueError, match="both Memex memory rooms and rGCN training rooms"):
        check_seeds([0, 1], [1, 2])
    with pytest.raises(ValueError, match="training seeds"):
        check_seeds([0], [200])


@pytest.fixture(scope="module")
def tiny_data():
    return placement_data(train_rooms_per_type=2, memory_seeds=[0], cache_dir=None, progress=False)


def test_training_reduces_the_loss(tiny_data):
    assert len(tiny_data.memex) > 20 and tiny_data.n_samples > 50
    result = train_rgcn(
        RGCNTrainConfig(steps=100, batch_size=32, hidden=32, threads=1), data=tiny_data, progress=False
    )
    h = result["history"]
    assert h[-1]["cross_entropy"] < 0.8 * h[0]["cross_entropy"], h


def test_without_memex_has_no_memory_and_trains(tiny_data):
    result = train_rgcn(
        RGCNTrainConfig(steps=30, batch_size=16, hidden=16, use_memex=False, threads=1),
        data=tiny_data,
        progress=False,
    )
    model = result["model"]
    assert not hasattr(model, "mem_layers") and result["memex_nodes"] == 0
    assert all(math.isfinite(h["cross_entropy"]) for h in result["history"])


@pytest.fixture(scope="module")
def shipped():
    return load_rgcn(DEFAULT_WEIGHTS)


def test_shipped_weights_load_with_manifest(shipped):
    model, manifest = shipped
    assert model.cfg.use_memex and len(model.mem_labels) > 500
    assert manifest["data"]["memory_rooms"]["seeds"] == [0, 1, 2, 3, 4]
    assert "test_top3" in manifest["metrics"]
    without, man2 = load_rgcn(DEFAULT_WITHOUT_MEMEX)
    assert not without.cfg.use_memex and man2["data"]["memex_nodes"] == 0


def test_shipped_rgcn_clears_a_floor_on_test_rooms(shipped):
    rooms = [r for r in heldout_rooms("test", cache_dir=None, progress=False) if r.seed in (200, 201)]
    res = evaluate_placement(rooms, {"rgcn": shipped[0]})["rgcn"]
    assert res["samples"] > 100
    assert res["top3"] >= 0.6 and res["judge_score"] >= 0.6, res


def test_placement_model_ranks_from_an_object_memory(shipped):
    mem = ObjectMemory()
    mem.add_or_merge(
        "CounterTop",
        0.9,
        np.array([1.0, 0.0, 0.45]),
        np.array([0.5, -0.3, 0.0]),
        np.array([1.5, 0.3, 0.9]),
        1,
    )
    mem.add_or_merge(
        "Sink", 0.9, np.array([1.0, 1.5, 0.5]), np.array([0.6, 1.2, 0.0]), np.array([1.4, 1.8, 1.0]), 1
    )
    mug = mem.add_or_merge(
        "Mug", 0.8, np.array([2.5, 2.5, 0.05]), np.array([2.45, 2.45, 0.0]), np.array([2.55, 2.55, 0.1]), 1
    )
    ranked = RGCNPlacement(shipped[0]).predict(mug, mem, "Kitchen")
    names = [r for r, _ in ranked]
    assert sorted(names) == sorted(PLACE_CLASSES)
    assert abs(sum(p for _, p in ranked) - 1.0) < 1e-4
    assert all(a[1] >= b[1] for a, b in zip(ranked, ranked[1:]))
    assert names.index("CounterTop") < names.index("Toilet")
    with pytest.raises(ValueError, match="room_type"):
        RGCNPlacement(shipped[0]).predict(mug, mem, "Garage")


def _parser():
    import argparse

    from tidee.agent.reasoning.rgcn.commands import register

    p = argparse.ArgumentParser(prog="tidee")
    sub = p.add_subparsers(dest="group", required=True)
    register(
        *(sub.add_parser(g).add_subparsers(dest="what", required=True) for g in ("gen", "train", "eval"))
    )
    return p


def test_commands_build_their_configs_from_the_flags():
    from tidee.agent.reasoning.rgcn.config import CeilingConfig, PlacementEvalConfig, RGCNTrainCommand
    from tidee.options import from_args, to_argv

    args = _parser().parse_args(["train", "rgcn", "--without-memex", "--rooms-per-type", "3", "--steps", "5"])
    cfg = from_args(RGCNTrainCommand, args)
    assert cfg.without_memex and cfg.train == RGCNTrainConfig(steps=5, train_rooms_per_type=3)
    assert to_argv(cfg) == ["--steps", "5", "--rooms-per-type", "3", "--without-memex"]
    assert from_args(RGCNTrainCommand, _parser().parse_args(["train", "rgcn"])) == RGCNTrainCommand()

    args = _parser().parse_args(["eval", "placement", "--out", "x", "--split", "val", "--record"])
    assert from_args(PlacementEvalConfig, args) == PlacementEvalConfig(out="x", split="val", record=True)

    args = _parser().parse_args(["eval", "ceiling", "--report", "a", "--report", "b", "--out", "x"])
    assert from_args(CeilingConfig, args) == CeilingConfig(report=("a", "b"), out="x")


@pytest.mark.parametrize(
    "argv",
    [
        ["train", "rgcn", "--steps", "0"],
        ["eval", "placement", "--out", "x", "--split", "train"],  # training rooms would measure memorisation
        ["eval", "placement"],  # --out is required
        ["eval", "ceiling", "--out", "x"],  # --report is required
        ["eval", "ceiling", "--report", "a", "--out", "x", "--rooms-per-type", "0"],
    ],
)
def test_commands_refuse_bad_flags(argv, capsys):
    with pytest.raises(SystemExit):
        _parser().parse_args(argv)
    assert "error" in capsys.readouterr().err
