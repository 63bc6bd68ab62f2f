"""Self-labels made on a machine with many cores, for `inseggan self-fit` here to resume from.

`inseggan self-fit` spends most of its time labelling the user's frames at the quality settings
(about 1 s a frame per process for the pin connector). A lent machine with 16 cores does that
in minutes; this packs what it needs and unpacks its result as self-fit's own labels.npz:

    # here: the first 3,000 training frames, tau calibrated as self-fit calibrates it
    python scripts/experiments/device_self_labels.py pack runs/pin_connector_loop/encoder/best.pt \
        data/pin_connector 3000 packed/pin_self.npz
    # there (PyTorch, OpenCV, SciPy; nothing else of the stack): 15 labelling processes
    python scripts/experiments/device_self_labels.py label packed/pin_self.npz 15 $OUT/labels.npz
    # (with a 6th argument START to pack, only frames START.. travel; merge the labels made
    # here before START into the result)
    # here: self-fit finds its labels done and only fits the encoder
    cp labels.npz runs/pin_connector_self3k/labels.npz
    inseggan self-fit --model runs/pin_connector_loop/encoder/best.pt --data data/pin_connector \
        --out runs/pin_connector_self3k --frames 3000

The frames travel as float16 and the model without its optimiser (the packed file stays small),
so the labels can differ from this machine's at a few boundary pixels.
"""
import json
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from inseggan_ros import checkpoint  # noqa: E402
from inseggan_ros.selffit import SelfFitConfig, self_labels  # noqa: E402


def pack(model: str, data_root: str, frames: int, out: str, start: int = 0) -> None:
    """The first `frames` training frames from `start` on (the ones before it labelled here)."""
    from inseggan_ros import data
    from inseggan_ros.segment import Segmenter
    from inseggan_ros.selfcheck import calibrate

    model = Path(model).resolve()  # as `inseggan self-fit` names it in labels.npz
    seg = Segmenter.from_checkpoint(model, device="cpu")
    calib = data.load_sim_split(data_root, "val", seg.prep_cfg, limit=200)
    tau, _ = calibrate(seg, calib["x"], calib["fg"])
    tr = data.load_sim_split(data_root, "train", limit=frames)
    state = checkpoint.load(model)
    drop = ("optimizers", "discriminator", "rng", "distill", "format")
    slim = {k: v for k, v in state.items() if k not in drop}
    slim_file = Path(out).with_suffix(".pt")
    checkpoint.save(slim_file, slim)
    np.savez_compressed(out, x=tr["x"][start:].astype(np.float16),
                        fg=np.packbits(tr["fg"][start:], axis=-1), tau=tau, model=str(model),
                        slim=slim_file.name, start=start)
    print(f"{out}: {len(tr['x'])} frames, tau {tau:.3f}; {slim_file}")


def label(packed: str, workers: int, out: str, model_file: str | None = None) -> None:
    """`model_file`: label with this model instead of the packed one (the shipped model.pt of
    the same weights, when the packed file alone must travel)."""
    z = np.load(packed)
    x = z["x"].astype(np.float32)
    fg = np.unpackbits(z["fg"], axis=-1, count=64).astype(bool)
    tau, model = float(z["tau"]), str(z["model"])
    slim = Path(model_file) if model_file else Path(packed).with_name(str(z["slim"]))
    cfg = SelfFitConfig(frames=len(x), workers=workers)
    labels = self_labels(slim, x, fg, tau, Path(out), cfg)
    start = int(z["start"]) if "start" in z else 0  # frames before it: labelled elsewhere
    job = {"model": model, "settings": cfg.settings, "tau": tau, "frames": start + len(x)}
    done = np.arange(start + len(x)) >= start
    labels = np.concatenate([np.zeros((start, 64, 64), np.uint8), labels])
    np.savez(out, labels=labels, done=done, job=json.dumps(job))
    print(f"{out}: {len(x)} frames labelled at {cfg.settings} settings, tau {tau:.3f}, "
          f"on {torch.get_num_threads()} threads x {workers} processes")


if __name__ == "__main__":
    if sys.argv[1] == "pack":
        pack(sys.argv[2], sys.argv[3], int(sys.argv[4]), sys.argv[5], *map(int, sys.argv[6:7]))
    else:
        label(sys.argv[2], int(sys.argv[3]), sys.argv[4], *sys.argv[5:6])
