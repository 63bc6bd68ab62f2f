"""A rod model's template scaled at test time: what the label-free measures of a recording say
against the labelled mIoU of fresh frames, scale by scale.

    python scripts/experiments/template_scale.py MODEL RECORDING_BAG TEST_BAG \
        [--scales 0.9,1,1.1,1.2,1.3] [--out runs/scale.json]
    python scripts/experiments/template_scale.py MODEL RECORDING_BAG TEST_BAG \
        --lengths 1,1.5,2 --radii 0.6,0.8,1 --spheres 16   # the rod made longer and thinner
    python scripts/experiments/template_scale.py MODEL DATA_SET DATA_SET ...   # simulated

A simulated data set (`inseggan simulate`) stands for both: its training split (labels unread)
is the recording, its validation split the labelled frames.

For each scale s the rod's radius, centre span and lift are multiplied by s (the poses the
encoder reads are not changed); tau is calibrated anew without labels on the recording's
first 80 % (`selfcheck.calibrate`), the label-free measures are taken on its last 20 %
(`selfcheck.measure`: reconstruction L1, coverage, spill), and the labels of TEST_BAG's frames
are scored against its ground truth (all frames, and the K-Means- and Felzenszwalb-hard
subsets). The question it answers: does a measure that needs no label choose the scale that
labels best? (docs/experiments.md, 2026-11-27.)
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("model")
    ap.add_argument("recording")
    ap.add_argument("test_bag")
    ap.add_argument("--scales", default="0.9,1,1.1,1.2,1.3")
    ap.add_argument("--lengths", help="centre-span factors (with --radii: every pair)")
    ap.add_argument("--radii", help="radius factors")
    ap.add_argument("--spheres", type=int, help="resample the rod to this many spheres")
    ap.add_argument("--calibration-frames", type=int, default=200)
    ap.add_argument("--held-out-frames", type=int, default=80)
    ap.add_argument("--out")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    from inseggan_ros import data as data_mod
    from inseggan_ros import evaluate, selfcheck
    from inseggan_ros.metrics import mean_miou, miou_batch
    from inseggan_ros.segment import Segmenter
    from inseggan_ros.sizing import reshaped

    seg = Segmenter.from_checkpoint(args.model, device="cpu")
    G0, n = seg.G, seg.model_cfg.n_instances
    if (Path(args.recording) / "meta.json").is_file():  # a simulated data set
        frames = data_mod.load_sim_split(args.recording, "train", seg.prep_cfg,
                                         limit=args.calibration_frames + args.held_out_frames)
        frames = {"x": frames["x"], "fg": frames["fg"]}
        test = data_mod.load_sim_split(args.test_bag, "val", seg.prep_cfg)
    else:
        frames = selfcheck.load_bag_frames(args.recording, seg.prep_cfg)
        test = data_mod.load_bag(args.test_bag, seg.prep_cfg)
    calib, held = selfcheck.split_held_out(frames, limit=None)
    calib = {k: v[-args.calibration_frames:] if isinstance(v, np.ndarray) else v
             for k, v in calib.items()}
    held = {k: v[:args.held_out_frames] if isinstance(v, np.ndarray) else v
            for k, v in held.items()}
    base = evaluate.run_methods(test, n, None, ["kmeans", "felzenszwalb"], progress=False)
    subsets = {k: m for k, (_, m) in evaluate.hard_subsets(base, len(test["x"])).items()}
    sizes = ", ".join(f"{k} {int(m.sum())}" for k, m in subsets.items())
    print(f"{len(calib['x'])} calibration and {len(held['x'])} held-out frames of the "
          f"recording; {len(test['x'])} test frames ({sizes})")
    for name, r in base.items():
        print(f"  {name}: all {mean_miou(r['scores']):.3f} / "
              + " / ".join(f"{k} {mean_miou(r['scores'][m]):.3f}" for k, m in subsets.items()))
    rows = []
    if args.lengths or args.radii:
        pairs = [(float(a), float(b)) for a in (args.lengths or "1").split(",")
                 for b in (args.radii or "1").split(",")]
    else:
        pairs = [(float(v), float(v)) for v in args.scales.split(",")]
    for length, radius in pairs:
        seg.G, span = reshaped(G0, length, radius, args.spheres)
        s = f"{length:.2f} x {radius:.2f} (span {span:.3f})"
        seg.tau, _ = selfcheck.calibrate(seg, calib["x"], calib["fg"])
        m = selfcheck.measure(seg, held["x"], held["fg"])
        outs = [seg.segment_batch(test["x"][i:i + 50], test["fg"][i:i + 50])
                for i in range(0, len(test["x"]), 50)]
        scores = miou_batch(np.concatenate([o["labels"].cpu().numpy() for o in outs]),
                            test["labels"])
        row = {"length": length, "radius": radius, "span": span, "tau": seg.tau,
               "recon_l1": m["recon_l1"],
               "coverage": m["coverage"], "spill": m["spill"],
               "count_equals_n": m["count_equals_n"], "miou_all": float(mean_miou(scores)),
               **{f"miou_{k}": float(mean_miou(scores[mk])) for k, mk in subsets.items()}}
        rows.append(row)
        print(f"length x radius {s}: tau {row['tau']:.2f}; held-out L1 {row['recon_l1']:.3f}, "
              f"coverage {row['coverage']:.3f}, spill {row['spill']:.3f}, count = n "
              f"{row['count_equals_n']:.2f}; test mIoU {row['miou_all']:.3f} / "
              + " / ".join(f"{row[f'miou_{k}']:.3f}" for k in subsets), flush=True)
    if args.out:
        with open(args.out, "w") as f:
            json.dump({"model": args.model, "rows": rows}, f, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
