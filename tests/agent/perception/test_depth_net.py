"""The depth-from-RGB network: shapes, a loss that falls, reproducible and resumable training,
the metrics, loading shipped weights, and (once shipped) their accuracy on test rooms."""

from __future__ import annotations

import argparse
import json
from typing import Any

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from tidee.agent.classes import CLASSES  # noqa: E402
from tidee.agent.learning import write_manifest  # noqa: E402
from tidee.agent.perception.depth import train as depth_train  # noqa: E402
from tidee.agent.perception.depth.config import DepthTrainConfig  # noqa: E402
from tidee.agent.perception.depth.eval import evaluate_depth, save_examples  # noqa: E402
from tidee.agent.perception.depth.model import DepthEstimator, DepthNet  # noqa: E402
from tidee.agent.perception.depth.train import to_tensors, train_depth, train_step  # noqa: E402
from tidee.agent.perception.detector.data import pack  # noqa: E402


@pytest.fixture(autouse=True)
def one_thread():
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)


def synthetic_frames(n: int = 8, size: int = 64, seed: int = 0) -> dict[str, np.ndarray]:
    """A floor receding to a wall: depth grows towards the top row, and the colour shows it."""
    rng = np.random.default_rng(seed)
    rows = np.linspace(1.0, 0.0, size, dtype=np.float32)[:, None]
    frames = []
    for i in range(n):
        far = rng.uniform(2.0, 5.0)
        depth = np.broadcast_to(0.5 + (far - 0.5) * rows, (size, size)).copy()
        depth[: size // 8] = 0.0 if i % 2 else 20.0  # nothing / beyond the far plane: not scored
        shade = np.clip(255 * (1 - depth / 6.0), 0, 255)
        rgb = np.stack([shade, shade * 0.8, shade * 0.5], -1) + rng.normal(0, 8, (size, size, 3))
        frames.append(
            {
                "rgb": np.clip(rgb, 0, 255).astype(np.uint8),
                "depth": depth,
                "inst": np.full((size, size), -1, np.int16),
                "objects": [],
                "room_type": ("Kitchen", "Bedroom")[i % 2],
                "seed": 0,
                "mess_index": None,
            }
        )
    return pack(frames)


def write_shards(root, frames: dict[str, Any]) -> None:
    root.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(root / "shard_p0_0000.npz", **frames)
    (root / "manifest.json").write_text(
        json.dumps(
            {
                "command": "synthetic",
                "classes": list(CLASSES),
                "shards": ["shard_p0_0000.npz"],
                "frames": len(frames["rgb"]),
                "rooms": ["Kitchen:0", "Bedroom:0"],
            }
        )
    )


class LookupEstimator:
    """Returns the true depth of a known frame (or garbage where nothing is scored)."""

    def __init__(self, frames: dict[str, np.ndarray]):
        self.depth = {rgb.tobytes(): d.astype(np.float32) for rgb, d in zip(frames["rgb"], frames["depth"])}

    def predict(self, rgb: np.ndarray) -> np.ndarray:
        d = self.depth[rgb.tobytes()].copy()
        d[(d <= 0.05) | (d >= 8)] = 123.0
        return d


class ConstantEstimator:
    def predict(self, rgb: np.ndarray) -> np.ndarray:
        return np.full(rgb.shape[:2], 2.0, np.float32)


@pytest.mark.parametrize("context", [False, True])
def test_output_shape_range_and_fused_copy(context):
    torch.manual_seed(0)
    net = DepthNet(context=context).eval()
    x = torch.rand(2, 3, 64, 96)
    with torch.inference_mode():
        d = net(x)
        fused = net.fused()(x)
    assert d.shape == (2, 64, 96)
    assert float(d.min()) >= net.min_depth * 0.999 and float(d.max()) <= net.max_depth * 1.001
    assert torch.allclose(d, fused, rtol=1e-4, atol=1e-5)
    with pytest.raises(ValueError, match="divisible by 16"):
        net(torch.rand(1, 3, 60, 64))

    rgb = np.random.default_rng(0).integers(0, 256, (120, 160, 3), dtype=np.uint8)
    est = DepthEstimator(net).predict(rgb)  # resized to 256^2 and back
    assert est.shape == (120, 160) and est.dtype == np.float32 and (est > 0).all()
    # the config kept in a weights file rebuilds the same network (older files have no context key)
    assert ("context" in net.config()) is context
    again = DepthNet(**net.config())
    again.load_state_dict(net.state_dict())
    with torch.inference_mode():
        assert torch.equal(again.eval()(x), d)


def test_the_context_branch_carries_the_whole_frame():
    """With context a pixel's depth depends on pixels far beyond the encoder's receptive field."""
    torch.manual_seed(0)
    x = torch.rand(1, 3, 256, 256)
    far = x.clone()
    far[:, :, :, 192:] = torch.rand(1, 3, 256, 64)  # change the right quarter only
    for context, moves in ((False, False), (True, True)):
        torch.manual_seed(1)
        net = DepthNet(context=context).eval()
        if context:
            assert net.global_context is not None
            torch.nn.init.normal_(net.global_context[0].weight, std=10.0)
        with torch.inference_mode():
            left = (net.log_depth(x) - net.log_depth(far))[0, :, :8].abs().max().item()
        # without context the left edge is out of reach: bit for bit the same
        assert (left > 0.0) is moves, (context, left)


def test_a_few_steps_reduce_the_loss():
    frames = synthetic_frames(n=4)
    rgb, depth = to_tensors(frames["rgb"], frames["depth"], "cpu")

    def run(precision: str) -> list[float]:
        torch.manual_seed(0)
        net = DepthNet()
        opt = torch.optim.AdamW(net.parameters(), lr=2e-3)
        return [train_step(net, opt, rgb, depth, 2e-3, precision)["loss"] for _ in range(8)]

    for precision in ("fp32", "bf16"):
        losses = run(precision)
        assert np.mean(losses[-3:]) < np.mean(losses[:3]), precision
        assert run(precision) == losses  # same seed, same numbers


def test_training_is_reproducible_and_resumable(tmp_path, monkeypatch):
    data = tmp_path / "data"
    write_shards(data, synthetic_frames(n=8))

    def config(out: str, work_dir: str, **changes) -> DepthTrainConfig:
        kw = dict(steps=4, batch_size=2, lr=2e-3, seed=3, eval_set=None, checkpoint_every=1, log_every=1)
        return DepthTrainConfig(
            data=str(data), out=str(tmp_path / out), work_dir=str(tmp_path / work_dir), **{**kw, **changes}
        )

    straight = train_depth(config("a.pt", "run_a"), progress=False)
    manifest = json.loads((tmp_path / "a.json").read_text())
    record = manifest["data"]
    assert (record["dir"], record["rooms"], record["frames"]) == (str(data), 2, 8)
    assert [part["command"] for part in record["parts"]] == ["synthetic"]
    assert (tmp_path / "run_a" / "depth_loss.png").exists()

    # Interrupt a second run after two steps, then resume it: it must end where the first did.
    real_step, calls = depth_train.train_step, []

    def interrupted(*args, **kwargs):
        if len(calls) == 2:
            raise KeyboardInterrupt
        calls.append(1)
        return real_step(*args, **kwargs)

    monkeypatch.setattr(depth_train, "train_step", interrupted)
    with pytest.raises(KeyboardInterrupt):
        train_depth(config("b.pt", "run_b"), progress=False)
    monkeypatch.setattr(depth_train, "train_step", real_step)
    resumed = train_depth(config("b.pt", "run_b", resume=True), progress=False)

    assert resumed["final_loss"] == straight["final_loss"]
    a = torch.load(tmp_path / "a.pt", weights_only=True)["state_dict"]
    b = torch.load(tmp_path / "b.pt", weights_only=True)["state_dict"]
    assert all(torch.equal(a[k], b[k]) for k in a)

    with pytest.raises(ValueError, match="different run"):
        train_depth(config("c.pt", "run_b", resume=True, seed=4), progress=False)


def test_metrics_perfect_and_constant(tmp_path):
    frames = synthetic_frames(n=4)
    perfect = evaluate_depth(LookupEstimator(frames), frames)
    assert perfect["abs_rel"] == 0 and perfect["rmse"] == 0 and perfect["delta1"] == 1
    assert set(perfect["abs_rel_by_room_type"]) == {"Kitchen", "Bedroom"}
    constant = evaluate_depth(ConstantEstimator(), frames)
    assert constant["abs_rel"] > 0.1 and constant["delta1"] < 1

    png = save_examples(ConstantEstimator(), frames, tmp_path / "examples.png", n=3)
    assert png.stat().st_size > 0


def test_load_checks_the_manifest(tmp_path):
    with pytest.raises(FileNotFoundError, match="tidee train depth"):
        DepthEstimator.load(tmp_path / "missing.pt")
    torch.manual_seed(0)
    net = DepthNet()
    path = tmp_path / "depth.pt"
    torch.save({"state_dict": net.state_dict(), "config": net.config()}, path)
    with pytest.raises(FileNotFoundError, match="manifest"):
        DepthEstimator.load(path)
    write_manifest(path, "test", {}, {})
    DepthEstimator.load(path)
    with open(path, "ab") as f:
        f.write(b"\0")
    with pytest.raises(ValueError, match="sha256"):
        DepthEstimator.load(path)


def test_eval_refuses_training_rooms(tmp_path):
    parser = argparse.ArgumentParser()
    groups = parser.add_subparsers(dest="cmd")
    gen_sub = groups.add_parser("gen").add_subparsers()
    train_sub = groups.add_parser("train").add_subparsers()
    eval_sub = groups.add_parser("eval").add_subparsers()
    from tidee.agent.perception.commands import register, run_eval_depth
    from tidee.agent.perception.depth.config import DEFAULT_WEIGHTS, DepthEvalConfig, EvalSet
    from tidee.options import from_args

    register(gen_sub, train_sub, eval_sub)
    with pytest.raises(SystemExit):  # a held-out split or nothing
        parser.parse_args(["eval", "depth", "--split", "train", "--out", str(tmp_path)])
    with pytest.raises(ValueError, match="test or val"):
        run_eval_depth(DepthEvalConfig(split="train", out=str(tmp_path)))  # type: ignore[arg-type]
    args = parser.parse_args(["eval", "depth", "--split", "val", "--messes", "0", "--out", str(tmp_path)])
    cfg = from_args(DepthEvalConfig, args)
    assert cfg == DepthEvalConfig(split="val", eval_set=EvalSet(messes=0), out=str(tmp_path))
    assert cfg.weights_path == DEFAULT_WEIGHTS
    args = parser.parse_args(["train", "depth", "--steps", "5"])
    cfg = from_args(DepthTrainConfig, args)
    assert cfg.steps == 5 and cfg.batch_size >= 1 and not cfg.resume
    assert cfg == DepthTrainConfig(steps=5)
    # the defaults are the shipped weights' run (agent/weights/depth.json): they reproduce them
    shipped, default = (
        json.loads(DEFAULT_WEIGHTS.with_suffix(".json").read_text())["train"],
        DepthTrainConfig(),
    )
    for key in ("steps", "batch_size", "lr", "seed", "context"):
        assert getattr(default, key) == shipped[key], key
    assert list(default.widths) == shipped["widths"]


def test_shipped_weights_on_test_rooms():
    from tidee.agent.perception.detector.data import held_out_frames

    frames = held_out_frames("test", rooms_per_type=1, messes=0, frames_per_walk=1, progress=False)
    metrics = evaluate_depth(DepthEstimator.load(), frames)
    assert metrics["frames"] == 4
    # shipped weights: 0.09 (delta1 0.90); a constant 1 m scores 0.36
    assert metrics["abs_rel"] < 0.14 and metrics["delta1"] > 0.8, metrics
