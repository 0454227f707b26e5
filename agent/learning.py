"""What every trained model of the agent shares: device choice, resumable checkpoints,
loss curves and the manifest that ships beside the weights.

A shipped model is ``agent/weights/<name>.pt`` (a state dict plus its architecture
config) and ``agent/weights/<name>.json``: the command that trained it, the data and its
seeds, the held-out metrics and the sha256 of the weights file.
"""

from __future__ import annotations

import hashlib
import json
import os
import time
from pathlib import Path
from typing import Any

from tidee.protocol.episode_log import write_json_atomic

WEIGHTS_DIR = Path(__file__).resolve().parent / "weights"


def pick_device(requested: str = "auto") -> str:
    import torch

    if requested == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if requested == "cuda" and not torch.cuda.is_available():
        raise ValueError("--device cuda asked for, but torch sees no GPU")
    return requested


def bf16_supported(device: str) -> bool:
    """Whether bf16 autocast runs natively here (AVX512-BF16/AMX through oneDNN, or a bf16 GPU).

    oneDNN also takes bf16 on plain AVX512 by emulating it, which is slower than fp32 (the
    detector: about 2.7x on an AVX512 Xeon without BF16); that is not native."""
    import torch

    if device.startswith("cuda"):
        return torch.cuda.is_bf16_supported()
    try:
        native = torch.cpu._is_avx512_bf16_supported() or torch.cpu._is_amx_tile_supported()
        return bool(native and torch.ops.mkldnn._is_mkldnn_bf16_supported())
    except (AttributeError, RuntimeError):
        return False


def resolve_precision(precision: str, device: str) -> str:
    """ "auto" -> "bf16" where ``device`` runs it natively, "fp32" elsewhere; "fp32" / "bf16" as asked."""
    if precision not in ("auto", "fp32", "bf16"):
        raise ValueError(f"precision must be auto, fp32 or bf16, not {precision!r}")
    if precision == "auto":
        return "bf16" if bf16_supported(device) else "fp32"
    return precision


def sha256_file(path: str | Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def save_checkpoint(path: str | Path, **state: Any) -> None:
    """Atomic torch.save (a crash mid-write never leaves a torn checkpoint)."""
    import torch

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    torch.save(state, tmp)
    os.replace(tmp, path)


def load_checkpoint(path: str | Path) -> dict[str, Any] | None:
    import torch

    path = Path(path)
    if not path.exists():
        return None
    return torch.load(path, map_location="cpu", weights_only=False)


def resume_training(
    path: str | Path, seed: int, model_config: dict[str, Any], model: Any, optimizer: Any, sampler: Any
) -> tuple[int, list[dict[str, float]]]:
    """Restore a training run from its checkpoint (model, optimiser, the sampler's and torch's
    random state); (step, history), or (0, []) when there is none. A checkpoint of another
    seed or architecture is refused."""
    import torch

    ck = load_checkpoint(path)
    if ck is None:
        return 0, []
    if ck["train_config"]["seed"] != seed or ck["model_config"] != model_config:
        raise ValueError(
            f"{path} was written by a different run (seed or architecture); "
            "pass --no-resume or another --work-dir"
        )
    model.load_state_dict(ck["model"])
    optimizer.load_state_dict(ck["optimizer"])
    sampler.set_state(ck["sampler"])
    torch.set_rng_state(ck["torch_rng"])
    return ck["step"], ck["history"]


def ship_weights(
    out: str | Path, model: Any, config: dict[str, Any], loss_curve: str | Path, docs_name: str
) -> str:
    """Write a trained model's weights for shipping (``config`` + CPU state dict); the path of
    its loss curve, for the manifest. Weights written to the shipped directory
    (``agent/weights/``) get their curve copied to ``docs/models/<docs_name>``; a candidate
    written anywhere else (``runs/...``) keeps its curve where it is, so that the docs always
    show the curve of the weights that ship."""
    import shutil

    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    state = {k: v.detach().cpu().contiguous() for k, v in model.state_dict().items()}
    save_checkpoint(out, config=config, state_dict=state)
    if not ships(out):
        return str(loss_curve)
    docs = Path("docs/models")
    docs.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(loss_curve, docs / docs_name)
    return f"docs/models/{docs_name}"


def loss_curve_path(out: str | Path, docs_name: str, asked: str | Path | None = None) -> str:
    """Where a training run draws its loss curve: ``asked`` when given; ``docs/models/<docs_name>``
    for weights written to the shipped directory (``agent/weights/``); beside the weights
    otherwise (``<out stem>_loss.png``), so that a candidate in ``runs/`` never replaces the
    curve of the weights that ship."""
    if asked:
        return str(asked)
    out = Path(out)
    return f"docs/models/{docs_name}" if ships(out) else str(out.with_name(f"{out.stem}_loss.png"))


def ships(out: str | Path) -> bool:
    """Whether weights written to ``out`` are the shipped ones (in ``agent/weights/``), whose
    loss curves the docs show; a candidate under ``runs/`` is not."""
    return Path(out).resolve().parent == WEIGHTS_DIR


def dataset_record(
    data_dir: str, data: dict[str, Any], manifests: list[dict[str, Any]], split: str, **extra: Any
) -> dict[str, Any]:
    """The manifest's ``data`` entry for a model trained on ``tidee gen detection`` directories:
    frames, rooms, and the generating command and room seeds of each directory."""
    return {
        "dir": data_dir,
        "frames": int(len(data["rgb"])),
        **extra,
        "rooms": sum(len(m.get("rooms", [])) for m in manifests),
        "parts": [
            {"command": m.get("command"), "rooms": len(m.get("rooms", [])), "room_seeds": m.get("config", {})}
            for m in manifests
        ],
        "split": split,
    }


def save_loss_curve(history: list[dict[str, float]], path: str | Path, title: str) -> None:
    """PNG of every loss term in ``history`` (one dict per logged step, with a "step" key)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if not history:
        return
    keys = [k for k in history[0] if k != "step"]
    fig, ax = plt.subplots(figsize=(7, 4), dpi=100)
    steps = [h["step"] for h in history]
    for k in keys:
        ax.plot(steps, [h.get(k, float("nan")) for h in history], label=k, lw=1.2)
    ax.set_yscale("log")
    ax.set_xlabel("step")
    ax.set_ylabel("loss")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)


def write_manifest(
    weights: str | Path, command: str, data: dict[str, Any], metrics: dict[str, Any], **extra: Any
) -> dict[str, Any]:
    """``<weights>.json`` beside the weights: command, data seeds, metrics, checksum."""
    weights = Path(weights)
    manifest = {
        "weights": weights.name,
        "sha256": sha256_file(weights),
        "bytes": weights.stat().st_size,
        "command": command,
        "data": data,
        "metrics": metrics,
        "written": time.strftime("%Y-%m-%dT%H:%M:%S"),
        **extra,
    }
    write_json_atomic(weights.with_suffix(".json"), manifest)
    return manifest


def read_manifest(weights: str | Path, verify: bool = True) -> dict[str, Any]:
    """The manifest of shipped weights; with ``verify``, the checksum must match the file."""
    weights = Path(weights)
    man_path = weights.with_suffix(".json")
    if not weights.exists():
        raise FileNotFoundError(f"no weights at {weights}; train them (see the README) or pass another path")
    if not man_path.exists():
        raise FileNotFoundError(f"{weights} has no manifest {man_path.name}")
    manifest = json.loads(man_path.read_text())
    if verify and manifest.get("sha256") != sha256_file(weights):
        raise ValueError(
            f"{weights} does not match the sha256 in {man_path.name}: the weights were changed "
            "without retraining through the repo's command"
        )
    return manifest


def update_manifest_metrics(weights: str | Path, metrics: dict[str, Any]) -> dict[str, Any]:
    """Merge held-out metrics (from an eval command) into a shipped manifest."""
    weights = Path(weights)
    man_path = weights.with_suffix(".json")
    manifest = json.loads(man_path.read_text())
    manifest.setdefault("metrics", {}).update(metrics)
    write_json_atomic(man_path, manifest)
    return manifest


__all__ = [
    "WEIGHTS_DIR",
    "pick_device",
    "sha256_file",
    "save_checkpoint",
    "load_checkpoint",
    "save_loss_curve",
    "loss_curve_path",
    "ships",
    "write_manifest",
    "read_manifest",
    "update_manifest_metrics",
]
