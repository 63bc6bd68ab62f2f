"""More simulated piles of a loop's learned part, and piles packed for a GPU machine as the
loop cut them.

The loop's encoder stage fits the encoder to `--scenes` piles of the learned part (1,500 by
default), at about 0.3 s an iteration on a 2-core CPU. A lent GPU runs many more iterations in
minutes (`scripts/device_train.py distill`), which asks for more distinct piles than the loop
made. `simulate` makes them with the scene of an existing piles folder (its meta.json: part,
camera, bin, noise) and another seed; `pack` writes one or more piles folders in
`device_train.py pack --with-labels`'s format, each frame cut as the loop cuts a bag-learned
model's piles (the model's preprocessing, bin and floor found in every frame), where `pack
--data` would cut them with the data set's known bin.

    python scripts/experiments/loop_piles.py simulate runs/x/loop/size_round2/sim runs/x/more \
        --train 6000 --seed 12 --workers 2
    python scripts/experiments/loop_piles.py pack runs/x/loop/size_round2/encoder/best.pt \
        runs/x/packed.npz runs/x/loop/size_round2/sim runs/x/more
"""
import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from device_train import write_packed  # noqa: E402
from inseggan_ros import checkpoint, data  # noqa: E402
from inseggan_ros.preprocess import PreprocessConfig  # noqa: E402


def simulate(args) -> None:
    from inseggan_ros.sim.dataset import DatasetSpec, generate, load_meta
    from inseggan_ros.sim.scene import SceneConfig

    meta = load_meta(args.like)
    spec = DatasetSpec(SceneConfig.from_dict(meta["scene"]),
                       {"train": args.train, "val": args.val, "test": 0}, seed=args.seed)
    generate(spec, args.out, workers=args.workers, progress=True)


def pack(args) -> None:
    prep = PreprocessConfig.from_dict(checkpoint.load(args.model)["preprocess_config"])
    xs, labels = [], []
    for root in args.piles:
        tr = data.load_sim_split(root, "train", prep, progress=True, as_given=True)
        xs.append(tr["x"])
        labels.append(tr["labels"])
    val = data.load_sim_split(args.piles[0], "val", prep, limit=100, as_given=True)
    info = {"source": "loop piles", "path": [str(p) for p in args.piles],
            "train_frames": int(sum(len(x) for x in xs)), "val_frames": len(val["x"])}
    write_packed(args.out, {"x": np.concatenate(xs), "labels": np.concatenate(labels)}, val,
                 prep, info, with_labels=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(required=True)
    p = sub.add_parser("simulate")
    p.add_argument("like", type=Path, help="a piles folder whose scene to simulate again")
    p.add_argument("out", type=Path)
    p.add_argument("--train", type=int, default=6000)
    p.add_argument("--val", type=int, default=0)
    p.add_argument("--seed", type=int, default=12)
    p.add_argument("--workers", type=int, default=2)
    p.set_defaults(func=simulate)
    p = sub.add_parser("pack")
    p.add_argument("model", type=Path, help="the checkpoint whose preprocessing cuts the piles")
    p.add_argument("out", type=Path)
    p.add_argument("piles", type=Path, nargs="+", help="piles folders; validation: the first's")
    p.set_defaults(func=pack)
    args = ap.parse_args()
    args.func(args)


if __name__ == "__main__":
    main()
