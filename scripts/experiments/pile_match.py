"""Disc templates whose simulated piles look most like the user's frames: a head's length and
width chosen by pile statistics, with no label.

The disc template cut from a learned rod's profile (`shapefit.rod_discs`) keeps the rod's blur:
a bolt's head comes out 2.4 times too long and 0.8 times too wide, and fitting it by
reconstruction moves it further away. Here the widest disc (the head) is scaled in length
(the template's total length kept) and radius over a grid; 200 piles of each variant are
simulated with the data set's camera and compared with the user's unlabelled training frames
by the distribution of their heights: every pixel of the bin's crop, the floor included, so
that the parts' visible area counts as well as their heights (the choice: "all"; also printed:
the foreground pixels alone, each part's highest points and the mean visible area). The true
part's piles are scored the same way as a control, and every variant's volumetric IoU with the
true part is printed (not used for the choice). The first look at the idea; the product's
search is `inseggan_ros.pilematch` (`shape-fit --match-piles`), with the "all" statistic only.

    python scripts/experiments/pile_match.py --rod models/bolt \
        --discs runs/bolt_discs/best.pt --data data/bolt_full --object bolt --out runs/pile_match
"""
import argparse
import itertools
import json
from pathlib import Path

import numpy as np
import torch
from scipy import ndimage
from scipy.stats import wasserstein_distance


def stats(x: np.ndarray, fg: np.ndarray) -> dict:
    """(N, 1, H, W) model inputs and (N, H, W) foreground -> the samples compared."""
    h = x[:, 0]
    peaks = (ndimage.maximum_filter(h, size=(1, 7, 7)) == h) & fg
    return {"all": h.ravel(), "pixels": h[fg], "peaks": h[peaks], "area": fg.mean((1, 2))}


def distance(a: dict, b: dict) -> dict:
    d = {k: float(wasserstein_distance(a[k], b[k])) for k in ("all", "pixels", "peaks")}
    d["area"] = float(abs(a["area"].mean() - b["area"].mean()))
    return d


def simulate(obj: str, data: Path, out: Path, count: int, seed: int, workers: int):
    from inseggan_ros.sim.dataset import DatasetSpec, generate, load_meta
    from inseggan_ros.sim.scene import SceneConfig

    if not (out / "meta.json").is_file():
        scene = SceneConfig.from_dict({**load_meta(data)["scene"], "object": obj})
        generate(DatasetSpec(scene, {"train": 0, "val": 0, "test": count}, seed=seed), out,
                 workers=workers, progress=False)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--rod", required=True, help="the rod model the discs were cut from")
    ap.add_argument("--discs", required=True, help="shape-fit --start discs checkpoint")
    ap.add_argument("--data", required=True, help="the user's data set (its training frames)")
    ap.add_argument("--object", default=None, help="the true part: control and IoU only")
    ap.add_argument("--out", required=True)
    ap.add_argument("--lengths", default="0.4,0.55,0.7,0.85,1.0")
    ap.add_argument("--radii", default="0.9,1.0,1.1,1.2,1.3")
    ap.add_argument("--frames", type=int, default=600)
    ap.add_argument("--piles", type=int, default=200)
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args(argv)
    from inseggan_ros import checkpoint
    from inseggan_ros.data import load_sim_split, sim_preprocess_config
    from inseggan_ros.pilematch import disc_model, head_variant
    from inseggan_ros.shape import evaluate_generator
    from inseggan_ros.shapefit import ShapeFitConfig, rod_discs
    from inseggan_ros.sim.learned import model_camera, template_scale

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    prep = sim_preprocess_config(args.data)
    real = load_sim_split(args.data, "train", prep, limit=args.frames)
    ref = stats(real["x"], real["fg"])

    rod_file = Path(args.rod) / "model.pt" if Path(args.rod).is_dir() else Path(args.rod)
    rod_state = checkpoint.load(rod_file)
    rod = checkpoint.build_models(rod_state, rod_file)[1]
    state = checkpoint.load(args.discs)
    G = checkpoint.build_models(state, args.discs)[1]
    shape_cfg = ShapeFitConfig(pieces=G.extent.shape[0], walls=G.extent.shape[1] - 2,
                               iterations=0, start="discs")
    discs = rod_discs(rod, shape_cfg.pieces, shape_cfg.walls)
    scale = template_scale(state, G, model_camera(Path(args.discs), state))

    rows = []
    runs = [("truth", None, None)] if args.object else []
    runs += [(f"len{a}_rad{b}", float(a), float(b)) for a, b in itertools.product(
        args.lengths.split(","), args.radii.split(","))]
    for name, a, b in runs:
        piles = out / "piles" / name
        row = {"name": name, "length": a, "radius": b}
        if a is None:
            simulate(args.object, Path(args.data), piles, args.piles, args.seed, args.workers)
        else:
            file = disc_model(rod_state, shape_cfg, head_variant(discs, a, b),
                              out / "variants" / f"{name}.pt", rod_file)
            G = checkpoint.build_models(checkpoint.load(file), file)[1]
            if args.object:
                f = evaluate_generator(G, args.object, scale)
                row.update(iou=f["iou"], dims_mm=f["dims_template_mm"])
            simulate(str(file), Path(args.data), piles, args.piles, args.seed, args.workers)
        sim = load_sim_split(piles, "test", prep)
        row.update(distance(stats(sim["x"], sim["fg"]), ref))
        rows.append(row)
        print(json.dumps(row), flush=True)
    (out / "results.json").write_text(json.dumps(rows, indent=1))
    best = min((r for r in rows if r["length"] is not None), key=lambda r: r["all"])
    print("closest piles:", json.dumps(best))
    return 0


if __name__ == "__main__":
    torch.set_num_threads(1)
    raise SystemExit(main())
