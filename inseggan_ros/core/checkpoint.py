"""Checkpoints: one file holds the model's config, its preprocessing, tau and the weights.

A checkpoint alone rebuilds its model. Files are written atomically (temporary file + rename), so a
killed training never leaves a half-written checkpoint. Inference needs only the generator and
encoder; `export_for_inference` strips the discriminator and optimiser state (and can store the
weights in half precision).
"""
from __future__ import annotations

import os
from pathlib import Path

FORMAT = "inseggan-ckpt-v1"


class CheckpointError(Exception):
    """A missing, unreadable or incompatible checkpoint; the message says which and why."""


def save(path, state: dict) -> Path:
    import torch

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    torch.save({"format": FORMAT, **state}, tmp)
    os.replace(tmp, path)
    return path


def load(path, map_location="cpu") -> dict:
    import torch

    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: no such model file")
    try:
        state = torch.load(path, map_location=map_location, weights_only=False)
    except Exception as e:
        raise CheckpointError(
            f"{path}: not a readable checkpoint ({type(e).__name__}: {e})") from None
    if not isinstance(state, dict) or state.get("format") != FORMAT:
        found = state.get("format") if isinstance(state, dict) else type(state).__name__
        raise CheckpointError(f"{path}: not an inseggan checkpoint (format {found!r}, "
                              f"expected {FORMAT!r})")
    return state


def pick_device(device: str = "auto") -> str:
    import torch

    if device == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if device not in ("cpu", "cuda") and not device.startswith("cuda:"):
        raise ValueError(f"device {device!r} invalid; valid: auto, cpu, cuda, cuda:<index>")
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise ValueError(f"device {device!r} asked for, but no CUDA device is available")
    return device


def export_for_inference(src, dst, half: bool = False) -> Path:
    """Keep what inference needs: configs, tau, G and E weights (optionally float16)."""
    state = load(src)
    keep = {k: v for k, v in state.items()
            if k not in ("discriminator", "optimizers", "rng", "format")}
    if half:
        for key in ("generator", "encoder"):
            keep[key] = {k: v.half() if v.is_floating_point() else v for k, v in keep[key].items()}
    keep["precision"] = "float16" if half else "float32"
    return save(dst, keep)


def width_state(module) -> dict:
    """What a checkpoint stores of a small network made from its width alone (a label head, the
    centre votes): {"width", "state_dict"}."""
    return {"width": module.width, "state_dict": module.state_dict()}


def from_width_state(cls, state: dict):
    """The network `cls(width)` with the weights of `width_state`'s record, in eval mode."""
    module = cls(int(state["width"]))
    module.load_state_dict(state["state_dict"])
    return module.eval()
