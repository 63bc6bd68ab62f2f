"""Centre votes taught on the part's own unlabelled frames, labelled by the model itself.

`inseggan centres` teaches the net on piles of the *learned* part; where the learned part is not
the real one (the nut, the cone, the stopper, the pin connector) the net then votes badly on
real frames (docs/experiments.md, 2026-11-28 and 2026-11-29). Here its teacher is the shipped
model's own labels of the data set's training frames (its default settings; no true label of
them is read), as `inseggan self-fit` teaches the encoder. The iteration kept is the best on the
self-labels of held-out training frames; the true labels of the validation split are read only
to report the result.

    python scripts/experiments/self_centres.py models/hex_nut/model.pt data/hex_nut \
        runs/self_centres/hex_nut --frames 3000 --iterations 3000

Writes OUT/net.pt, OUT/curves.png, OUT/summary.json (`centres.train_net`) and OUT/model.pt (the
model with the net, `centre_votes: on`), and prints the validation split's mIoU.
"""
import argparse
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm


def self_labels(seg, x: np.ndarray, fg: np.ndarray, batch: int = 64) -> np.ndarray:
    """The model's own labels (its settings, centre votes off) of prepared frames."""
    cfg = replace(seg.inference, centre_votes="off")
    out = [seg.segment_batch(x[i:i + batch], fg[i:i + batch], settings=cfg)["labels"].numpy()
           for i in tqdm(range(0, len(x), batch), desc="self-labels")]
    return np.concatenate(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("model")
    ap.add_argument("data", help="a simulated data set (its train split's labels are not read)")
    ap.add_argument("out")
    ap.add_argument("--frames", type=int, default=3000, help="training frames to self-label")
    ap.add_argument("--held-out", type=int, default=200,
                    help="of those, kept out of training to choose the iteration")
    ap.add_argument("--iterations", type=int, default=3000)
    ap.add_argument("--width", type=int, default=16)
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args(argv)
    from inseggan_ros import checkpoint
    from inseggan_ros.centres import CentreConfig, centre_labels, miou_of, net_from_state
    from inseggan_ros.centres import net_state, train_net
    from inseggan_ros.data import load_sim_split
    from inseggan_ros.segment import Segmenter

    torch.set_num_threads(args.threads)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    seg = Segmenter.from_checkpoint(args.model, device="cpu")
    n = seg.model_cfg.n_instances
    train = load_sim_split(args.data, "train", seg.prep_cfg, limit=args.frames, progress=True)
    cache = out / "self_labels.npy"
    if cache.is_file():
        labels = np.load(cache)
    else:
        labels = self_labels(seg, train["x"], train["fg"])
        np.save(out / ".self_labels.npy", labels)
        (out / ".self_labels.npy").replace(cache)
    k = len(labels) - args.held_out
    fit = {"x": train["x"][:k], "fg": train["fg"][:k], "labels": labels[:k]}
    choose = {"x": train["x"][k:], "fg": train["fg"][k:], "labels": labels[k:]}
    print(f"self-labels of the training frames against their true labels (report only): "
          f"{miou_of(labels, train['labels'][:len(labels)]):.3f}")
    cfg = CentreConfig(width=args.width, iterations=args.iterations)
    summary = train_net(fit, choose, n, out, cfg)
    net = net_from_state(torch.load(out / "net.pt", weights_only=True))
    state = checkpoint.load(args.model)
    keep = {k: v for k, v in state.items() if k not in ("format", "optimizers", "rng")}
    keep.update(centre_net={**net_state(net), "sim": f"self-labels of {args.data}",
                            "summary": {k: v for k, v in summary.items() if k != "history"}},
                inference=replace(seg.inference, centre_votes="on").to_dict())
    checkpoint.save(out / "model.pt", keep)
    val = load_sim_split(args.data, "val", seg.prep_cfg)
    got = centre_labels(net.eval(), val["x"], val["fg"], n).numpy()
    print(f"best on the held-out self-labels {summary['best_val_miou']:.3f}; the validation "
          f"split's true labels: the net's instances alone {miou_of(got, val['labels']):.3f}; "
          f"model: {out / 'model.pt'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
