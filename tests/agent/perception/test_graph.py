"""Perception networks as frozen TorchScript graphs: used only where they change nothing."""

from __future__ import annotations

import copy
import pickle
import random

import numpy as np
import pytest
import torch
from torch import nn

from tidee.agent.perception.graph import FrozenNet


class _Net(nn.Module):
    def __init__(self) -> None:
        super().__init__()
        self.conv = nn.Sequential(nn.Conv2d(4, 8, 3, 2, 1), nn.ReLU(inplace=True), nn.Conv2d(8, 8, 3, 1, 1))
        self.head = nn.Linear(8 + 2, 3)

    def forward(self, x: torch.Tensor, side: torch.Tensor) -> dict[str, torch.Tensor]:
        f = self.conv(x)
        return {"map": f, "out": self.head(torch.cat([f.mean((2, 3)), side], 1))}


class _Random(nn.Module):
    """Not a function of its inputs alone: a trace would bake one draw in."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x * random.random()


@pytest.mark.parametrize("precision", ["fp32", "bf16"])
def test_a_frozen_net_gives_the_eager_outputs_bit_for_bit(precision) -> None:
    torch.manual_seed(0)
    module = _Net().eval()
    net = FrozenNet(module, precision)
    for batch in (3, 1, 5):  # traced on a batch of 3, then others
        x = torch.randn(batch, 4, 32, 32).contiguous(memory_format=torch.channels_last)
        side = torch.randn(batch, 2)
        got = net(x, side)
        with torch.inference_mode(), torch.autocast("cpu", dtype=torch.bfloat16, enabled=precision == "bf16"):
            want = module(x, side)
        for k in want:
            assert got[k].dtype == want[k].dtype and torch.equal(got[k], want[k]), k
    assert net.frozen is True


def test_a_net_whose_graph_would_differ_runs_eagerly() -> None:
    net = FrozenNet(_Random(), "fp32")
    x = torch.ones(2, 3)
    net(x)
    assert net.frozen is False
    assert len({float(net(x)[0, 0]) for _ in range(5)}) > 1  # the module itself, drawing anew


def test_a_copy_or_a_pickle_traces_again_in_its_own_process() -> None:
    net = FrozenNet(_Net().eval(), "fp32")
    x, side = torch.randn(2, 4, 16, 16), torch.randn(2, 2)
    net(x, side)
    assert net.frozen is True
    for other in (copy.deepcopy(net), pickle.loads(pickle.dumps(net))):
        assert other.frozen is None and other._graph is None
        assert torch.equal(other(x, side)["out"], net(x, side)["out"]) and other.frozen is True


def test_the_shipped_networks_detect_the_same_as_their_eager_modules() -> None:
    """Frozen detector and crop classifier against the same modules run eagerly under autocast:
    the same detections, scores, boxes, features and masks on rendered test-room frames."""
    from tidee.agent.perception.detector.data import held_out_frames
    from tidee.agent.perception.learned import LearnedPerception

    frames = held_out_frames("test", rooms_per_type=1, messes=1, frames_per_walk=1, seed=3, progress=False)
    frozen, eager = LearnedPerception.load(), LearnedPerception.load()
    eager.net._graph = False
    assert eager.reclassifier_net is not None
    eager.reclassifier_net._graph = False
    n = 0
    for rgb, depth in zip(frames["rgb"], frames["depth"].astype(np.float32)):
        a, b = frozen.detect_batch(rgb[None], depth[None])[0], eager.detect_batch(rgb[None], depth[None])[0]
        assert [(d.label, d.score, d.box, d.oop_prob) for d in a] == [
            (d.label, d.score, d.box, d.oop_prob) for d in b
        ]
        for d, e in zip(a, b):
            assert np.array_equal(d.feature, e.feature) and np.array_equal(d.mask, e.mask)
        n += len(a)
    assert n > 0 and frozen.net.frozen and frozen.reclassifier_net.frozen
