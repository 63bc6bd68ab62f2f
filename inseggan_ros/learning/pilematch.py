"""A disc template's head sized by how its simulated piles look: no label, no gradient.

`shapefit.rod_discs` cuts a learned rod's radius profile into flat-ended discs, but the rod's
spheres blur a step such as a bolt's head over a sphere's length: the bolt's discs get a head
2.4 times as long and 0.8 times as wide as the bolt's, and fitting them to the frames by
reconstruction moves them further away (docs/experiments.md, 2026-11-29, evening). What the
frames do show is how parts of a shape come to rest in a pile: a bolt lies tilted on its head,
so the head's width sets the heights of the frames' parts, and its length the area each covers.

So the widest disc (a head, a flange) is scaled in length (its outer end kept where it is an
end, the neighbouring disc taking up the difference: the template as long as before) and in
radius, over a grid. Each variant is piled `piles` times by the physics simulator in the
user's bin, seen through the user's camera, and cut as the user's frames are; the variant
whose frames' heights (every pixel of the bin's crop, the floor included: the parts' heights
and their visible area at once) are distributed nearest to the user's frames' heights
(1-Wasserstein) is kept. A coarse grid first, then a finer one about its best, with more
piles (the distances of the best few differ by little more than their sampling noise).

A rod whose spheres are all alike has no step for the cut to find: a flange (the pin
connector's) is then made, not resized. Three discs, the middle one the widest; the grid also
scales the other discs' radius (`shafts`: the shaft as narrow as the flange is wide) and moves
the middle disc along the axis (`offsets`). A rod learned too short (a CPU's shape stage on a
tilted camera's bolts: two thirds of the bolt's length) is stretched whole along its axis, its
radii kept (`stretches`). The fine grid is over length and radius at the coarse best's shaft,
offset and stretch.

A nut is a disc with six flats and a hole: piles of a solid disc taught centre votes that lost
to Felzenszwalb on tilted nuts touching at one height (docs/experiments.md, 2026-12-03). With
`holes` above 0 the template's one disc is built as a hexagonal nut of six convex ring sectors
(`ConvexGenerator.init_ring`), its hole's faces at that fraction of its apothem, and the grid
runs over its thickness (`lengths`), width (`radii`) and hole.

A cone or a stopper tapers: its learned rod is a capsule of about the part's width, and piles
of it taught the tilted cones' centre votes 0.06 less on their K-Means-hard frames than piles of
the true cone (docs/experiments.md, 2026-12-03, evening). With `tapers` below 1 the one disc
is built as a pyramid's frustum (`ConvexGenerator.init_discs`), its far end's radius that
fraction of its radius, and the grid runs over its length, width and taper.

    inseggan shape-fit --model models/bolt --data data/bolt --out runs/bolt_head \
        --start discs --pieces 2 --walls 8 --iterations 0 --match-piles
    inseggan shape-fit --model models/pin_connector --data data/pin_connector \
        --out runs/pin_flange2 --start discs --pieces 3 --walls 8 --iterations 0 --match-piles \
        --pile-lengths 0.15,0.25,0.4 --pile-radii 0.9,1,1.1 --pile-shafts 0.5,0.65,0.8 \
        --pile-offsets 0,0.15
    inseggan shape-fit --model models/hex_nut --data data/hex_nut --out runs/nut_ring \
        --start discs --pieces 1 --walls 12 --iterations 0 --match-piles \
        --pile-lengths 0.35,0.42,0.5 --pile-radii 1,1.1,1.2 --pile-holes 0.5,0.65
    inseggan shape-fit --model models/cone --data data/cone --out runs/cone_taper \
        --start discs --pieces 1 --walls 8 --iterations 0 --match-piles \
        --pile-lengths 0.7,0.85,1 --pile-radii 1,1.15,1.3 --pile-tapers 0.1,0.4,0.7,1
"""
from __future__ import annotations

import itertools
import json
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Callable

import numpy as np
from tqdm import tqdm

from inseggan_ros.evaluation.evaluate import write_json
from inseggan_ros.runtime.model import CONVEX_MIN_EXTENT, check_ring, taper_slope
from inseggan_ros.runtime.model import build_models

Discs = list[tuple[float, float, float]]


@dataclass(frozen=True)
class PileMatchConfig:
    lengths: tuple[float, ...] = (0.4, 0.55, 0.7, 0.85, 1.0)  # the head's length, x the discs'
    radii: tuple[float, ...] = (0.9, 1.0, 1.1, 1.2, 1.3)  # its radius, x the discs'
    shafts: tuple[float, ...] = (1.0,)  # the other discs' radius, x theirs (a flange's shaft)
    offsets: tuple[float, ...] = (0.0,)  # a disc between two: its middle moved, x the length
    stretches: tuple[float, ...] = (1.0,)  # the whole template's length, x its own (radii kept)
    holes: tuple[float, ...] = (0.0,)  # above 0: the one disc as a hexagonal nut with a hole
    # of this fraction of its apothem (`ConvexGenerator.init_ring`); 0: a solid disc
    tapers: tuple[float, ...] = (1.0,)  # below 1: the one disc as a frustum whose far end's
    # radius is this fraction of its radius (`ConvexGenerator.init_discs`); 1: a straight disc
    piles: int = 200  # simulated piles of each variant of the coarse grid
    fine_piles: int = 600  # of the fine grid: half the coarse steps about its best, 3 x 3
    # (0: no fine grid)
    frames: int = 1500  # of the user's frames, at most
    seed: int = 0  # of the piles (every variant is piled from the same scene seeds)
    workers: int = 1  # simulation processes

    def __post_init__(self):
        # two lengths and radii at least: the fine grid steps between neighbours
        for name, least in (("lengths", 2), ("radii", 2), ("shafts", 1), ("stretches", 1)):
            v = getattr(self, name)
            if len(v) < least or any(f <= 0 for f in v) or list(v) != sorted(set(v)):
                raise ValueError(f"{name} {v!r} invalid; valid: {('one', 'two')[least - 1]} or "
                                 "more increasing factors above 0")
        if (not self.holes or list(self.holes) != sorted(set(self.holes))
                or not all(0 <= h < 1 for h in self.holes)):
            raise ValueError(f"holes {self.holes!r} invalid; valid: one or more increasing "
                             "fractions in [0, 1) of the disc's apothem (0: no hole)")
        if (not self.tapers or list(self.tapers) != sorted(set(self.tapers))
                or not all(0 < t <= 1 for t in self.tapers)):
            raise ValueError(f"tapers {self.tapers!r} invalid; valid: one or more increasing "
                             "fractions in (0, 1] of the disc's radius at its far end (1: no "
                             "taper)")
        if any(self.holes) and any(t != 1 for t in self.tapers):
            raise ValueError(f"holes {self.holes!r} and tapers {self.tapers!r} both set; valid: "
                             "a ring or a frustum, not both")
        if not self.offsets or list(self.offsets) != sorted(set(self.offsets)):
            raise ValueError(f"offsets {self.offsets!r} invalid; valid: one or more increasing "
                             "fractions of the template's length")
        for name in ("piles", "frames", "workers"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} {getattr(self, name)!r} invalid; valid: 1 or more")
        if self.fine_piles < 0:
            raise ValueError(f"fine_piles {self.fine_piles!r} invalid; valid: 0 (no fine grid) "
                             "or more")


def heights(x: np.ndarray) -> np.ndarray:
    """Frames (N, 1, H, W) as the model sees them -> every pixel's height, the floor's too."""
    return np.asarray(x, np.float32).ravel()


EDGE_STEP = 0.08  # model-input units a pixel (2 mm at the default 5 cm max_height): a depth edge


def edge_distances(x: np.ndarray) -> np.ndarray:
    """Frames (N, 1, H, W) as the model sees them -> every foreground pixel's distance (pixels)
    to the nearest background or depth edge (a height gradient above EDGE_STEP a pixel): how
    wide the parts' surfaces are between their edges, whatever their height. Thin bars measure
    about a pixel, a block's top many; where parts touch at one height no edge parts them, as
    in the user's frames. Why beside the heights: on U-clips piles of two fitted boxes matched
    the frames' heights as well as piles of the true U (W1 0.033 and 0.030) while their edge
    distances were 28 times as far (0.81 against 0.029), and their model segmented 0.21 mIoU
    worse (docs/experiments.md, 2026-12-07; `family.FamilyConfig.edges`)."""
    from scipy.ndimage import distance_transform_edt

    x = np.asarray(x, np.float32)
    out = []
    for f in x.reshape(-1, *x.shape[-2:]):
        fg = f > -1 + 1e-4
        gy, gx = np.gradient(f)
        out.append(distance_transform_edt(fg & (np.hypot(gx, gy) <= EDGE_STEP))[fg])
    return np.concatenate(out) if out else np.zeros(0, np.float32)


def head_variant(discs: Discs, length: float, radius: float, shaft: float = 1.0,
                 offset: float = 0.0, stretch: float = 1.0) -> Discs:
    """`discs` stretched along the axis by `stretch` about the template's middle (every disc's
    length and place, its radius kept), then with the widest one's length times `length` and
    radius times `radius`, every other disc's radius times `shaft`, and, for a disc between
    two, its middle moved along the axis by `offset` times the template's length. An end disc
    keeps its outer end, and its neighbour takes up the difference; a disc between two keeps
    its middle (then moved) and both neighbours take up what it gives or takes. Why the last
    two: a rod whose spheres are all alike (the pin connector's) is cut into discs with no
    step at all, and its flange, as narrow a shaft as it is wide a flange, exists only if the
    search makes it."""
    mid = (discs[0][0] + discs[-1][1]) / 2
    d = [[mid + (a - mid) * stretch, mid + (b - mid) * stretch, r] for a, b, r in discs]
    k = int(np.argmax([s[2] for s in d]))
    x0, x1, r = d[k]
    grow = (x1 - x0) * (length - 1)
    if offset and not 0 < k < len(d) - 1:
        raise ValueError(f"offset {offset:g} moves a disc between two; valid: 0 for a template "
                         "whose widest disc is at an end")
    if k == 0 and len(d) > 1:
        d[k][1] += grow
        d[k + 1][0] = d[k][1]
    elif k == len(d) - 1 and len(d) > 1:
        d[k][0] -= grow
        d[k - 1][1] = d[k][0]
    else:
        move = offset * (d[-1][1] - d[0][0])
        d[k][0], d[k][1] = x0 - grow / 2 + move, x1 + grow / 2 + move
        if k > 0:
            d[k - 1][1] = d[k][0]
        if k + 1 < len(d):
            d[k + 1][0] = d[k][1]
    for i, s in enumerate(d):
        s[2] *= radius if i == k else shaft
    if any(b - a <= 2 * CONVEX_MIN_EXTENT for a, b, _ in d):
        raise ValueError(f"head length x{length:g}, offset {offset:g} leaves a disc shorter "
                         f"than {2 * CONVEX_MIN_EXTENT} template units; valid: factors that "
                         "keep every disc of the template")
    return [tuple(float(v) for v in s) for s in d]


def _fine(values: tuple[float, ...], best: float) -> tuple[float, ...]:
    """Three values about `best`, half the grid's step to each side of it."""
    i = values.index(best)
    lo = (values[i] - values[i - 1]) / 2 if i > 0 else (values[1] - values[0]) / 2
    hi = (values[i + 1] - values[i]) / 2 if i + 1 < len(values) else lo
    return tuple(round(v, 4) for v in (best - lo, best, best + hi) if v > 0)


@dataclass
class _Search:
    """What measuring a head's variants needs: the starting discs, how a variant is made and
    piled, the user's frames and their heights, and what is known so far: the variants
    measured (kept in out/variants.jsonl) and those the grid skipped, each with why."""

    discs: Discs
    cfg: PileMatchConfig
    make: Callable[[Discs, float, Path, float], Path]
    piles: Callable[[Path, Path, int, int], np.ndarray]
    out: Path
    user: np.ndarray
    ref: np.ndarray  # the user's frames' heights
    report: Callable[[Path], dict] | None
    progress: bool
    done: dict = field(default_factory=dict)  # a variant measured with the same piles and user
    # frames is not measured again
    skipped: list = field(default_factory=list)  # the grid's variants the template cannot be

    @property
    def log(self) -> Path:
        return self.out / "variants.jsonl"

    def load(self) -> None:
        """The variants measured before (a killed search's, another grid's)."""
        if self.log.is_file():
            for line in self.log.read_text().splitlines():
                row = {"shaft": 1.0, "offset": 0.0, "stretch": 1.0, "hole": 0.0, "taper": 1.0,
                       **json.loads(line)}
                self.done[(*_variant(row), row["piles"], row["seed"], row["frames"])] = row

    def measure(self, stage: str, grid: list[tuple[float, ...]], count: int) -> list[dict]:
        """Each variant of `grid` piled `count` times, its heights' distance to the user's ->
        its row (measured now or before)."""
        from scipy.stats import wasserstein_distance  # here: a second to import

        cfg, done = self.cfg, self.done
        rows = []
        for v in tqdm(grid, desc=f"piles ({stage})", unit="variant", disable=not self.progress):
            key = (*v, count, cfg.seed, len(self.user))
            if key not in done:
                a, b, c, o, e, h, t = v
                name = (f"len{a:g}_rad{b:g}" + (f"_shaft{c:g}" if c != 1 else "")
                        + (f"_off{o:g}" if o else "") + (f"_str{e:g}" if e != 1 else "")
                        + (f"_hole{h:g}" if h else "") + (f"_taper{t:g}" if t != 1 else "")
                        + f"_piles{count}")
                file = self.make(head_variant(self.discs, *v[:5]), h,
                                 self.out / "variants" / f"{name}.pt", t)
                sim = self.piles(file, self.out / "piles" / name, count, cfg.seed)
                row = {"stage": stage, "length": a, "radius": b, "shaft": c, "offset": o,
                       "stretch": e, "hole": h, "taper": t, "piles": count, "seed": cfg.seed,
                       "frames": len(self.user),
                       "distance": float(wasserstein_distance(heights(sim), self.ref)),
                       **(self.report(file) if self.report else {})}
                with open(self.log, "a") as f:
                    f.write(json.dumps(row) + "\n")
                done[key] = row
            rows.append({**done[key], "stage": stage})
        return rows

    def valid(self, v: tuple[float, ...]) -> bool:
        """Whether the template can be variant `v`; if not, it is added to `skipped`."""
        try:
            d = head_variant(self.discs, *v[:5])
            if v[5]:
                check_ring(d[0], v[5])
            if v[6] != 1:
                taper_slope(d[0], v[6])
        except ValueError as e:  # a head too short for its neighbours, offset too far, a
            self.skipped.append({**dict(zip(VARIANT_KEYS, v)), "why": str(e)})  # ring's wall
            return False  # too thin, a frustum's walls too steep
        return True


def _check_one_disc(cfg: PileMatchConfig, discs: Discs) -> None:
    """Holes and tapers are grids of a template of one disc only."""
    if any(cfg.holes) and len(discs) != 1:
        raise ValueError(f"holes {cfg.holes} make a ring of one disc; valid: a template of one "
                         f"disc, not {len(discs)}")
    if any(t != 1 for t in cfg.tapers) and len(discs) != 1:
        raise ValueError(f"tapers {cfg.tapers} make a frustum of one disc; valid: a template "
                         f"of one disc, not {len(discs)}")


def match_head(discs: Discs, user_x: np.ndarray,
               make: Callable[[Discs, float, Path, float], Path],
               piles: Callable[[Path, Path, int, int], np.ndarray], out,
               cfg: PileMatchConfig = PileMatchConfig(), progress: bool = True,
               report: Callable[[Path], dict] | None = None) -> dict:
    """The head of `discs` sized by pile statistics -> summary (also out/summary.json): every
    variant measured, the discs kept ("discs"), their hole ("hole", 0: none) and taper ("taper",
    1: none). `user_x`: the user's frames (N, 1, H, W); `make(discs, hole, file, taper)` writes
    a model with those discs to `file` (with `hole` above 0 the one disc as a ring,
    `cfg.holes`; with `taper` below 1 as a frustum, `cfg.tapers`); `piles(model_file, folder,
    count, seed)` simulates `count` piles of it into `folder` and returns their frames
    as the user's are cut. Each variant's result is kept in out/variants.jsonl as it is
    measured, so a killed search resumes where it stopped (and one with other grids reuses the
    variants measured alike); `report(model_file)` (a library part's true shape, for the record
    only) is added to each."""
    out = Path(out)
    config = json.loads(json.dumps(asdict(cfg)))  # as summary.json holds it
    start = [list(map(float, s)) for s in discs]
    if (out / "discs.json").is_file() and json.loads((out / "discs.json").read_text()) != start:
        raise ValueError(f"{out}: holds a search from other discs; valid: the same rod and "
                         "pieces to resume, or another output folder")
    if (out / "summary.json").is_file():
        finished = json.loads((out / "summary.json").read_text())
        if finished["config"] == config:
            return finished  # another config searches again, from the variants kept
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "discs.json", start)
    user = np.asarray(user_x[:cfg.frames])
    search = _Search(discs, cfg, make, piles, out, user, heights(user), report, progress)
    search.load()
    _check_one_disc(cfg, discs)
    # the coarse grid
    coarse = search.measure("coarse", [v for v in itertools.product(
        cfg.lengths, cfg.radii, cfg.shafts, cfg.offsets, cfg.stretches, cfg.holes, cfg.tapers)
        if search.valid(v)], cfg.piles)
    if not coarse:
        raise ValueError("no variant of the grid keeps every disc of the template; valid: "
                         "longer heads or smaller offsets")
    best = min(coarse, key=lambda r: r["distance"])
    fine = []
    if cfg.fine_piles:  # length and radius about the best, at its shaft, offset, stretch,
        # hole and taper
        fine = search.measure("fine", [v for a in _fine(cfg.lengths, best["length"])
                                       for b in _fine(cfg.radii, best["radius"])
                                       if search.valid(v := (a, b, *_variant(best)[2:]))],
                              cfg.fine_piles)
        best = min(fine, key=lambda r: r["distance"])
    summary = {"config": config, "discs_before": start,
               "coarse": coarse, "fine": fine, "best": best, "skipped": search.skipped,
               "discs": [list(s) for s in head_variant(discs, *_variant(best)[:5])],
               "hole": _variant(best)[5], "taper": _variant(best)[6]}
    _plot(coarse, cfg, out / "match.png")
    write_json(out / "summary.json", summary)
    return summary


VARIANT_KEYS = ("length", "radius", "shaft", "offset", "stretch", "hole", "taper")


def _variant(row: dict) -> tuple[float, float, float, float, float, float, float]:
    """A measured variant's factors: `head_variant`'s five, then its hole (0: none) and its
    taper (1: none)."""
    return (*(row[k] for k in VARIANT_KEYS[:5]), row.get("hole", 0.0), row.get("taper", 1.0))


def _plot(rows: list[dict], cfg: PileMatchConfig, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    # each cell the best of its shafts, offsets and stretches (NaN: no variant of the grid
    # keeps its discs)
    grid = np.array([[min((r["distance"] for r in rows if r["length"] == a
                           and r["radius"] == b), default=np.nan)
                      for b in cfg.radii] for a in cfg.lengths])
    fig, ax = plt.subplots(figsize=(5, 4))
    im = ax.imshow(grid, cmap="viridis_r", origin="lower")
    ax.set_xticks(range(len(cfg.radii)), [f"{v:g}" for v in cfg.radii])
    ax.set_yticks(range(len(cfg.lengths)), [f"{v:g}" for v in cfg.lengths])
    ax.set_xlabel("head radius (x the discs')")
    ax.set_ylabel("head length (x the discs')")
    ax.set_title("piles' heights vs the frames' (W1)"
                 + (", best of the other factors"
                    if len(cfg.shafts) * len(cfg.offsets) * len(cfg.stretches)
                    * len(cfg.holes) * len(cfg.tapers) > 1 else ""))
    fig.colorbar(im, ax=ax)
    fig.tight_layout()
    tmp = path.with_suffix(".tmp.png")
    fig.savefig(tmp, dpi=100)
    plt.close(fig)
    tmp.replace(path)


def disc_model(rod_state: dict, shape_cfg, discs: Discs, file, source="checkpoint",
               hole: float = 0.0, taper: float = 1.0) -> Path:
    """The rod model `rod_state` with the disc template `discs` (`shapefit.convex_from_rod`;
    with `hole` above 0 the one disc as a ring, with `taper` below 1 as a frustum) written to
    `file`: a model `simulate --object` piles up."""
    from inseggan_ros.core import checkpoint
    from inseggan_ros.learning.shapefit import convex_from_rod

    new, G, E = convex_from_rod(rod_state, replace(shape_cfg, hole=hole, taper=taper), source,
                                discs=discs)
    return checkpoint.save(file, {
        **new, "generator": {k: v.detach().cpu() for k, v in G.state_dict().items()},
        "encoder": {k: v.detach().cpu() for k, v in E.state_dict().items()}})


def pile_frames(file, data, meta, view: dict, folder: Path, count: int, seed: int,
                workers: int = 1) -> np.ndarray:
    """`count` piles of the model `file`'s template simulated as the user's frames were taken
    (`data`, `meta`: `piles.pile_scene`) into `folder`, cut as those frames are (`view`:
    `piles.pile_view`) -> their frames (N, 1, H, W). The folder is removed after: the measure
    made of the frames is kept, not the piles."""
    import shutil

    from inseggan_ros.data import datasets as data_mod
    from inseggan_ros.learning.piles import pile_scene
    from inseggan_ros.sim.dataset import DatasetSpec, generate

    shutil.rmtree(folder, ignore_errors=True)  # of a search killed while simulating it
    spec = DatasetSpec(pile_scene(data, meta, file), {"train": 0, "val": 0, "test": count},
                       seed=seed)
    generate(spec, folder, workers=workers, progress=False)
    x = data_mod.load_sim_split(folder, "test", **view)["x"]
    shutil.rmtree(folder)
    return x


def search(rod_file, shape_cfg, data, user_x: np.ndarray, out,
           cfg: PileMatchConfig = PileMatchConfig(), progress: bool = True,
           report: Callable | None = None) -> dict:
    """`match_head` for the discs `shape-fit --start discs` cuts from the rod model `rod_file`
    (`shapefit.convex_from_rod` with `shape_cfg`): the piles simulated as the user's frames
    were taken, `data` a simulated data set (its camera, noise and bin) or a
    `loop.BagFrames` (the camera and bin estimated from the bag), and cut as those frames are.
    `report(G)`: a library part's fidelity (`cli._shape_report`), for the record only."""
    from inseggan_ros.core import checkpoint
    from inseggan_ros.learning.piles import BagFrames, pile_view
    from inseggan_ros.learning.shapefit import start_discs
    from inseggan_ros.sim.dataset import load_meta

    rod_file = Path(rod_file)
    state = checkpoint.load(rod_file)
    if shape_cfg.start != "discs":
        raise ValueError(f"pile matching sizes the head of a disc template; valid: start "
                         f"'discs', not {shape_cfg.start!r}")
    view = pile_view(data, state)
    meta = None if isinstance(data, BagFrames) else load_meta(data)

    # the grid's rings must be buildable from these discs: the config says so (raises)
    cut = replace(shape_cfg, hole=max(cfg.holes)) if any(cfg.holes) else shape_cfg

    def make(discs: Discs, hole: float, file: Path, taper: float) -> Path:
        return disc_model(state, shape_cfg, discs, file, rod_file, hole, taper)

    def piles(file: Path, folder: Path, count: int, seed: int) -> np.ndarray:
        return pile_frames(file, data, meta, view, folder, count, seed, cfg.workers)

    def fidelity(file: Path) -> dict:
        f = report(build_models(checkpoint.load(file), file)[1])
        return {"iou": f["iou"], "dims_mm": f["dims_template_mm"]}

    _, rod, _ = build_models(state, rod_file)
    discs = start_discs(rod, cut)  # a ring's disc: the hexagon of the rod's cross-section
    return match_head(discs, user_x, make, piles, out, cfg, progress,
                      fidelity if report else None)
