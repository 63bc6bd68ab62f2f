"""Learning the part's shape by reconstruction: a convex template fitted to the user's frames.

The rod of spheres learns from unlabelled frames where each part lies and which way its axis
points, but it is a solid of revolution: a box gets round ends, a nut is as tall as it is wide.
A convex template (`model.ConvexGenerator`) can be a box or a prism, but trained as a GAN from
scratch it did not learn (docs/experiments.md, 2026-11-23 and 24: its poses drifted out of the
image). So the rod model is the starting point, and the shape is fitted afterwards:

  1. the convex template starts as a box as long as the rod, as wide as its diameter and as
     thick as the frames' parts lying flat (`rod_box`), `pieces` copies of it; the rod model's
     encoder and pose decoder are kept, so every instance starts where the rod put it;
  2. template, encoder and pose decoder are fitted together to reconstruct the user's
     unlabelled training frames: the pyramid L1 of the z-buffered renders against each frame,
     under a random symmetry of the square. No discriminator, no label.

What the depth shows pulls the shape to the part: a box too long covers floor pixels, one too
tall stands above the surface it should explain.

    inseggan shape-fit --model runs/my_block/best.pt --data data/my_block --out runs/my_block_shape
    inseggan loop --model runs/my_block_shape/best.pt --data data/my_block --out runs/my_block_loop

(`--model`: a rod model, `inseggan train`'s; the shipped wooden_block is already the result.)

Writes out/best.pt, the model: a training checkpoint with the convex template, which the loop,
`export` and `eval` take, at the evaluation where the validation frames were reconstructed
best (no label read; without validation frames the last). Fitted on, the template keeps
lowering the reconstruction error by growing past the part (a box that covers a neighbour
explains pixels a misplaced instance leaves), so the fit is stopped by held-out frames, not by
its own loss (docs/experiments.md, 2026-11-26). Also out/last.pt (every `eval_every`
iterations; a killed run resumes from it), log.jsonl, curves.png and summary.json. Where the
caller knows the true part (a simulated data set), `report` adds the template's fidelity to
every evaluation: for the record only, never fitted to.
"""
from __future__ import annotations

import itertools
import json
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import torch
from tqdm import tqdm

from inseggan_ros.core import checkpoint
from inseggan_ros.learning import losses
from inseggan_ros.evaluation.evaluate import write_json
from inseggan_ros.runtime.model import (
    CONVEX_MIN_EXTENT, RING_PIECES, RING_WALLS, ConvexGenerator, ModelConfig, SphereGenerator)
from inseggan_ros.runtime.model import build_models


BARS = {"bar": 1, "tee": 2, "ell": 2, "u": 3}  # the starts of bars (`rod_bars`): their pieces
STARTS = ("box", "discs", *BARS)
MAX_BAR_WIDTH = 2.0  # `ShapeFitConfig.bar_width`, at most


@dataclass(frozen=True)
class ShapeFitConfig:
    pieces: int = 1  # convex pieces of the template (`ModelConfig.pieces`)
    walls: int = 4  # side planes of each (`ModelConfig.walls`: 4 make a box)
    iterations: int = 1500  # 0: the starting template as it is (the discs: see `rod_discs`)
    frames: int = 1000  # of the user's training frames, at most
    batch_size: int = 32
    encoder_lr: float = 1e-4  # encoder and pose decoder (already trained: small steps)
    template_lr: float = 3e-3  # the template's parameters
    recon_levels: int = 4
    eval_every: int = 250
    val_frames: int = 100  # reconstruction error reported on these (no label read)
    thickness: str = "data"  # the starting box's height: "data" (the frames' lower-quartile
    # foreground height, where thinner than the rod) or "rod" (the rod's diameter)
    start: str = "box"  # the starting template: "box" (`rod_box`, every piece a copy),
    # "discs" (`rod_discs`: the rod's radius profile as a stack of `pieces` prisms), "tee" or
    # "ell" (two pieces: two bars from the rod's box, joined as a T or an L: `rod_bars`) or "u"
    # (three pieces: three bars so joined as a U)
    hole: float = 0.0  # with start "discs": above 0, the one disc (pieces 1) as a hexagonal nut
    # whose hole's faces lie at this fraction of its apothem (`ConvexGenerator.init_ring`: six
    # pieces of 12 walls)
    taper: float = 1.0  # with start "discs": below 1, the one disc (pieces 1) a pyramid's
    # frustum whose far end's radius is this fraction of its radius (a cone, a stopper:
    # `ConvexGenerator.init_discs`); 1: a straight disc
    bar_width: float = 1.0  # with a start of bars: their width, times the rod's radius
    # (`rod_bars`; the family's width search tries others)
    seed: int = 0

    def __post_init__(self):
        for key in ("pieces", "frames", "batch_size", "recon_levels", "eval_every",
                    "val_frames"):
            if getattr(self, key) < 1:
                raise ValueError(f"{key} {getattr(self, key)!r} invalid; valid: >= 1")
        if self.iterations < 0:
            raise ValueError(f"iterations {self.iterations!r} invalid; valid: >= 0 (0: the "
                             "starting template, measured, not fitted)")
        if self.walls < 4 or self.walls % 4:
            raise ValueError(f"walls {self.walls!r} invalid; valid: a multiple of 4, >= 4")
        if self.thickness not in ("data", "rod"):
            raise ValueError(f"thickness {self.thickness!r} invalid; valid: data, rod")
        if self.start not in STARTS:
            raise ValueError(f"start {self.start!r} invalid; valid: {', '.join(STARTS)}")
        if self.start in BARS and (self.pieces, self.walls) != (BARS[self.start], 4):
            raise ValueError(f"start {self.start} is {BARS[self.start]} "
                             f"bar{'s' if BARS[self.start] > 1 else ''}; valid: pieces "
                             f"{BARS[self.start]} and walls 4 (not {self.pieces}, {self.walls})")
        if not 0 <= self.hole < 1:
            raise ValueError(f"hole {self.hole!r} invalid; valid: 0 (no hole) or a fraction "
                             "of the disc's apothem in (0, 1)")
        if self.hole and (self.start, self.pieces, self.walls) != ("discs", 1, RING_WALLS):
            raise ValueError(f"hole {self.hole:g} makes a ring of one disc; valid: with start "
                             f"discs, pieces 1 and walls {RING_WALLS} (not {self.start}, "
                             f"{self.pieces}, {self.walls})")
        if not 0 < self.taper <= 1:
            raise ValueError(f"taper {self.taper!r} invalid; valid: in (0, 1] (1: no taper)")
        if self.taper != 1 and (self.start, self.pieces, self.hole) != ("discs", 1, 0.0):
            raise ValueError(f"taper {self.taper:g} makes a frustum of one disc; valid: with "
                             f"start discs, pieces 1 and no hole (not {self.start}, "
                             f"{self.pieces}, hole {self.hole:g})")
        if not 0 < self.bar_width <= MAX_BAR_WIDTH:
            raise ValueError(f"bar_width {self.bar_width!r} invalid; valid: in (0, "
                             f"{MAX_BAR_WIDTH:g}] (times the rod's radius)")
        if self.bar_width != 1 and self.start not in BARS:
            raise ValueError(f"bar_width {self.bar_width:g} sizes bars; valid: with a start of "
                             f"{', '.join(BARS)} (not {self.start})")
        for key in ("encoder_lr", "template_lr"):
            if not 0 < getattr(self, key) < 1:
                raise ValueError(f"{key} {getattr(self, key)!r} invalid; valid: in (0, 1)")


def hold_out(frames: np.ndarray, cfg: ShapeFitConfig) -> tuple[np.ndarray, np.ndarray]:
    """One sequence of the user's frames (a recording's) -> (training frames, validation
    frames): up to `cfg.frames` to fit and the next `cfg.val_frames` to measure the fit on;
    where there are fewer than both need, the last fifth (at most `cfg.val_frames`) is
    held out, so that the kept checkpoint is always the one that reconstructs unseen frames
    best."""
    n = len(frames)
    val = cfg.val_frames if n >= cfg.frames + cfg.val_frames else min(cfg.val_frames, n // 5)
    train = min(cfg.frames, n - val)
    return frames[:train], frames[train:train + val]


def rod_box(G: SphereGenerator, x=None) -> tuple[float, float, float]:
    """The starting box in the rod's own frame: half-extents (x along the rod's axis, y, z):
    the rod's bounding box, or with frames `x` ((N, 1, H, W) model inputs) as thick (z) as the
    lower quartile of their foreground heights, where that is thinner than the rod (parts
    lying flat on the floor: `ConvexGenerator.init_from_data`'s thickness)."""
    c, r = (t.detach().float() for t in G.spheres())
    half_len, rad = float((c[:, 0].abs() + r).max()), float(r.max())
    thick = rad
    if x is not None:
        x = torch.as_tensor(np.asarray(x), dtype=torch.float32)
        fg = x > -1 + 1e-4
        if fg.any():
            top = float(torch.quantile((x[fg][:1_000_000] + 1) / G.cfg.height_gain, 0.25))
            thick = min(rad, max(top / 2, 2 * CONVEX_MIN_EXTENT))
    return half_len, rad, thick


FLAT_BIN = 0.04  # model-input units (1 mm at the default 5 cm max_height): `flat_top`'s bins
FLAT_SPAN = 3  # bins either side a mode must top


def flat_top(x, height_gain: float) -> float | None:
    """Frames `x` ((N, 1, H, W) model inputs) -> the height (template units) of the lowest mode
    of their foreground heights, the top of a part lying flat on the floor: the first bin of
    FLAT_BIN (smoothed over three; then the fullest of it and its two neighbours, as they
    were counted) above every other within FLAT_SPAN, past the first
    foreground bin and fuller than it (there the threshold cut the heights: falling from it,
    they show no mode). None where there is none. Why not the lower quartile (`rod_box`):
    parts leaning on each other lift it; on U-clips (6 mm thick) it was 11.6 mm, and the
    bars made so, scaled whole, piled nearest the frames 13 mm thick and 22 mm across
    instead of 6 and 36 (docs/experiments.md)."""
    x = np.asarray(x, np.float32)
    h = x[x > -1 + 1e-4] + 1
    if h.size < 100:
        return None
    counts, edges = np.histogram(h, bins=np.arange(0.0, 2.0 + FLAT_BIN, FLAT_BIN))
    smooth = np.convolve(counts, np.ones(3) / 3, mode="same")
    first = int(np.argmax(counts > 0))
    for i in range(first + 1, len(smooth) - FLAT_SPAN):
        window = smooth[max(first, i - FLAT_SPAN):i + FLAT_SPAN + 1]
        if counts[i] > counts[first] and smooth[i] >= window.max():
            i = i - 1 + int(np.argmax(counts[i - 1:i + 2]))  # the fullest bin about it
            return float((edges[i] + FLAT_BIN / 2) / height_gain)
    return None


def rod_bars(G: SphereGenerator, kind: str, x=None, width: float = 1.0) -> tuple[list, list]:
    """Bars from the rod's box (`rod_box`: half-length a, radius b, half-thickness c): one 2a
    long across the top, alone ("bar": a block, a plate, a flat bar; at least as long as it is
    wide) or joined to one bar 2a long down from its middle (a T, "tee"), from its end (an L,
    "ell"), or to two from both its ends (a U, "u": three pieces), every bar b wide (together
    about the rod's footprint; `width` times that) and 2c high, the whole outline centred on the
    template's origin -> `ConvexGenerator.init_boxes`' (boxes, joints).
    Why the lone bar: the box fitted by reconstruction from the rod's box keeps the rod's
    outline, and a block's learned rod is a round blob, so the box came out a square slab
    (53.8 x 51.5 x 27.5 mm against the block's 50 x 25 x 15: volumetric IoU 0.50); the bar is
    half as wide as long and as thick as the frames' flat parts, and its width is searched.
    With frames `x`, c is half their flat parts' height (`flat_top`) where they show one: the
    bars' thickness is the frames', and the family's scale and width searches size their
    outline only (`family.FLAT`, `family.width_search`)."""
    a, b, c = rod_box(G, x)
    flat = flat_top(x, G.cfg.height_gain) if x is not None else None
    if flat is not None:
        c = max(flat / 2, 2 * CONVEX_MIN_EXTENT)
    w = max(width * b / 2, 2 * CONVEX_MIN_EXTENT)
    if kind not in BARS:
        raise ValueError(f"bars {kind!r} invalid; valid: {', '.join(BARS)}")
    if kind == "bar":
        a = max(a, w)
        return [(-a, a, -w, w, 2 * c)], [(0.0, 0.0)]
    a = max(a, 2 * w)
    shift = a - w  # the outline spans y -(2a - w)..w: its middle to 0
    top = (-a, a, -w + shift, w + shift, 2 * c)

    def down(x0):  # a bar from the top bar down, its left side at x0
        return (x0, x0 + 2 * w, -(2 * a - w) + shift, w + shift, 2 * c)
    if kind == "u":  # leg, top, leg: each piece's centre where it meets the next
        left, right = (-a + w, shift), (a - w, shift)
        return [down(-a), top, down(a - 2 * w)], [left, right, right]
    x0 = -w if kind == "tee" else a - 2 * w  # the second bar's side
    return [top, down(x0)], [(x0 + w, shift)] * 2


def rod_discs(G: SphereGenerator, pieces: int, walls: int, samples: int = 240
              ) -> list[tuple[float, float, float]]:
    """The rod's radius profile as `pieces` flat-ended discs: -> (x0, x1, r) per disc along the
    rod's axis (its own frame), in order from one end (`ConvexGenerator.init_discs`).

    The profile is the envelope of the rod's spheres, rho(x), sampled at `samples` points. The
    cuts are where a piecewise-constant cross-section best fits rho^2 (least squares, by
    dynamic programming over the cut positions), each disc as thick as its segment's mean
    cross-section (its volume kept) and its `walls`-sided polygon of the same area as that
    circle. Why: a rod's spheres round every end, and its radius changes smoothly along it,
    while a bolt's head is a flat-faced step. On the bolt the two discs of its shipped rod are
    closer to the true part than the rod (volumetric IoU 0.78 against 0.74), and piles of them
    teach the centre-vote net better than piles of the rod. Fitted on by reconstruction they
    drift from the part (IoU 0.78 -> 0.52 in 500 iterations, with the encoder frozen too), as
    the box does: `shape-fit --start discs --iterations 0` keeps them as they start
    (docs/experiments.md, 2026-11-29, evening)."""
    c, r = (t.detach().double().cpu() for t in G.spheres())
    cx = c[:, 0]
    x = torch.linspace(float((cx - r).min()), float((cx + r).max()), samples + 1,
                       dtype=torch.float64)
    x = (x[1:] + x[:-1]) / 2  # bin centres
    a = (r[None, :] ** 2 - (x[:, None] - cx[None, :]) ** 2).clamp_min(0).amax(1)  # rho^2
    # cost of one disc over samples [i, j): the squared deviation of rho^2 from its mean
    s1 = torch.cat([a.new_zeros(1), a.cumsum(0)])
    s2 = torch.cat([a.new_zeros(1), (a ** 2).cumsum(0)])

    def cost(i, j):
        return float(s2[j] - s2[i] - (s1[j] - s1[i]) ** 2 / (j - i))

    n, step = samples, float(x[1] - x[0])
    shortest = math.floor(2 * CONVEX_MIN_EXTENT / step) + 1  # samples: a disc init_discs takes
    if pieces * shortest > n:
        raise ValueError(f"pieces {pieces} invalid for discs on this rod; valid: "
                         f"1..{n // shortest}")
    best = [[math.inf] * (n + 1) for _ in range(pieces + 1)]
    cut = [[0] * (n + 1) for _ in range(pieces + 1)]
    best[0][0] = 0.0
    for k in range(1, pieces + 1):
        for j in range(k * shortest, n + 1):
            for i in range((k - 1) * shortest, j - shortest + 1):
                v = best[k - 1][i] + cost(i, j)
                if v < best[k][j]:
                    best[k][j], cut[k][j] = v, i
    bounds, j = [n], n
    for k in range(pieces, 0, -1):
        j = cut[k][j]
        bounds.append(j)
    bounds = bounds[::-1]
    edges = [float(x[0]) - step / 2 + b * step for b in bounds]
    polygon = math.sqrt(math.pi / (walls * math.tan(math.pi / walls)))  # same area as the circle
    discs = [(edges[k], edges[k + 1],
              polygon * math.sqrt(float(a[bounds[k]:bounds[k + 1]].mean())))
             for k in range(pieces)]

    return discs[::-1] if spill(discs[::-1]) < spill(discs) else discs


def start_discs(G: SphereGenerator, cfg: ShapeFitConfig) -> list[tuple[float, float, float]]:
    """The discs `cfg` starts from (`rod_discs`): a ring's one disc (`cfg.hole`) as the
    hexagon of the rod's cross-section, whatever the walls that build it."""
    return rod_discs(G, cfg.pieces, 6 if cfg.hole else cfg.walls)


def spill(discs) -> float:
    """The volume (per pi) a stack of discs, built as pieces in this order, holds beyond the
    discs themselves: each piece reaches back to the previous piece's centre
    (`ConvexGenerator.halfspaces`: one connected body), at its own radius, so a wider piece
    after a narrower one covers the narrower one's part up to that centre."""
    reach = []
    for i, (x0, x1, r) in enumerate(discs):
        c = (discs[i - 1][0] + discs[i - 1][1]) / 2 if i else x0
        reach.append((min(x0, c), max(x1, c), r))
    edges = sorted({v for x0, x1, _ in reach for v in (x0, x1)})
    total = 0.0
    for a, b in zip(edges, edges[1:]):
        m = (a + b) / 2
        built = max((r for x0, x1, r in reach if x0 <= m <= x1), default=0.0)
        meant = max((r for x0, x1, r in discs if x0 <= m <= x1), default=0.0)
        total += (b - a) * max(0.0, built ** 2 - meant ** 2)
    return total


def piece_order(discs) -> list:
    """`discs` (in any order) in the order of pieces that spills least (`spill`), the given
    order where no other spills less. Why: three discs in a row, the middle one the widest (a
    flange), spill whichever end comes first, as the flange reaches back into half a shaft;
    the flange first, each shaft after it reaching back into a piece no narrower, spill none."""
    discs = list(discs)
    orders = itertools.permutations(discs)
    return list(min(orders, key=spill))  # min keeps the first of equals: the given order


def convex_from_rod(state: dict, cfg: ShapeFitConfig, source="checkpoint", x=None,
                    discs=None):
    """A rod model's training checkpoint `state` -> (the convex model's state, G, E): the rod's
    encoder and pose decoder, the template the box `rod_box` gives (with the frames `x` when
    `cfg.thickness` is "data"), or with `cfg.start` "discs" the discs `rod_discs` gives (or
    `discs`, (x0, x1, r) each: `pilematch`), about the rod's axis.

    Why the thickness from the frames: a rod looks the same turned about its axis, so its
    poses say nothing of that turn, and a box as thick as it is wide looks the same under a
    quarter of it. Such a box gets no gradient to become flat (a block or a nut started so
    stayed as tall as wide for hundreds of iterations: docs/experiments.md); a flat one does,
    and the encoder learns to turn each instance onto its face."""
    _, rod, E = build_models(state, source)
    if not isinstance(rod, SphereGenerator):
        raise ValueError(f"{source}: shape fitting starts from a rod model (renderer 'spheres'), "
                         f"not {rod.cfg.renderer!r}")
    mcfg = {k: v for k, v in state["model_config"].items() if k != "template_size"}
    mcfg.update(renderer="convex", pieces=RING_PIECES if cfg.hole else cfg.pieces,
                walls=cfg.walls, floor_contact=True)
    G = ConvexGenerator(ModelConfig.from_dict(mcfg))
    G.pose.load_state_dict(rod.pose.state_dict())
    if cfg.start == "discs":  # about the pose's origin, as the rod's spheres are, lifted by
        # the floor contact instead of the rod's `lift`: so the rod's poses place them where
        # they placed it (the lift in the template's own frame would turn with each pose)
        discs = discs or start_discs(rod, cfg)
        if cfg.hole:
            G.init_ring(discs[0], cfg.hole, 0.0)
        else:
            G.init_discs(piece_order(discs), 0.0, cfg.taper)
    elif cfg.start in BARS:
        G.init_boxes(*rod_bars(rod, cfg.start, x if cfg.thickness == "data" else None,
                               cfg.bar_width))
    else:
        G.init_box(rod_box(rod, x if cfg.thickness == "data" else None))
    # without the rod encoder's distillation record: the encoder's next fit (the loop's) is
    # the one this model's card accounts for
    new = {k: v for k, v in state.items()
           if k not in ("format", "distill", "distill_record", "discriminator", "optimizers",
                        "rng")}
    new["model_config"] = G.cfg.to_dict()
    new["precision"] = "float32"
    return new, G, E


def _batch(x: torch.Tensor, idx: torch.Tensor, gen: torch.Generator) -> torch.Tensor:
    from inseggan_ros.learning.distill import _symmetry_batch

    return _symmetry_batch(x[idx], None, gen)[0]


def _recon(G, E, x: torch.Tensor, levels: int) -> torch.Tensor:
    z = E(x)
    B, n, d = z.shape
    pose = G.pose(z.reshape(B * n, d)).reshape(B, n, 6)
    return losses.pyramid_l1(G.zbuffer(G.render_poses(pose)), x, levels)


def _plot(history: list, path: Path) -> None:
    from inseggan_ros.core.viz import plot_history

    plot_history(history, path, [("reconstruction (training)", "train", ("l_recon",)),
                                 ("validation", "val", ("recon_l1", "shape_iou"))])


@dataclass
class _ShapeFit:
    """What the phases of one shape fit share: the convex model fitted (its checkpoint state,
    template, encoder), the optimiser, the generator of the batches' draws and symmetries, the
    held-out frames and the record so far."""

    cfg: ShapeFitConfig
    src: Path
    given: list | None  # the starting discs given, for the record
    state: dict
    G: ConvexGenerator
    E: torch.nn.Module
    opt: torch.optim.Optimizer
    gen: torch.Generator
    out: Path
    xv: torch.Tensor | None  # the validation frames, on the device
    report: Callable[[ConvexGenerator], dict] | None
    it: int = 0
    history: list = field(default_factory=list)
    before: float = 0.0  # seconds of the fit before this process (a resumed one)
    start: float = 0.0  # time.monotonic() when this process began fitting

    def seconds(self) -> float:
        return self.before + time.monotonic() - self.start

    def resume(self, device: str) -> None:
        """Continue from out/last.pt, a fit of the same model, config and discs only."""
        saved = checkpoint.load(self.out / "last.pt")
        rec = saved["shape_fit"]
        if (rec["config"] != asdict(self.cfg) or rec["source"] != str(self.src)
                or rec.get("discs") != self.given):
            raise ValueError(f"{self.out}: holds a shape fit of {rec['source']} with "
                             f"{rec['config']}; valid: the same model and config to resume, "
                             "or another --out")
        self.G.load_state_dict({k: v.to(device) for k, v in saved["generator"].items()})
        self.E.load_state_dict({k: v.to(device) for k, v in saved["encoder"].items()})
        self.opt.load_state_dict(rec["optimizer"])
        self.gen.set_state(rec["generator_rng"])
        self.it, self.history, self.before = rec["iteration"], rec["history"], rec["seconds"]

    def save(self, name: str = "last.pt") -> None:
        rec = {"config": asdict(self.cfg), "source": str(self.src), "discs": self.given,
               "iteration": self.it, "history": self.history,
               "seconds": self.seconds(), "optimizer": self.opt.state_dict(),
               "generator_rng": self.gen.get_state()}
        checkpoint.save(self.out / name, {
            **self.state,
            "generator": {k: v.detach().cpu() for k, v in self.G.state_dict().items()},
            "encoder": {k: v.detach().cpu() for k, v in self.E.state_dict().items()},
            "shape_fit": rec})

    def log(self, rec: dict) -> None:
        self.history.append(rec)
        with open(self.out / "log.jsonl", "a") as f:
            f.write(json.dumps(rec) + "\n")

    def validate(self) -> bool:
        """Logs the validation record; -> whether its reconstruction is the best yet."""
        rec = {"kind": "val", "iteration": self.it}
        improved = False
        if self.xv is not None:
            self.E.eval()
            with torch.no_grad():
                rec["recon_l1"] = round(float(_recon(self.G, self.E, self.xv, 1)), 5)
            self.E.train()
            seen = [h["recon_l1"] for h in self.history if h["kind"] == "val"]
            improved = not seen or rec["recon_l1"] < min(seen)
        if self.report is not None:
            shape = self.report(self.G)
            rec.update(shape_iou=shape["iou"], dims_mm=shape["dims_template_mm"],
                       true_dims_mm=shape["dims_true_mm"])
        self.log(rec)
        _plot(self.history, self.out / "curves.png")
        fields = ", ".join(f"{k} {v}" for k, v in rec.items() if k not in ("kind", "iteration"))
        if fields:  # nothing to say without validation frames or a true part
            tqdm.write(f"iter {self.it}: {fields}" + (" (best)" if improved else ""))
        return improved


def _fit(f: _ShapeFit, x: torch.Tensor, device: str, progress: bool) -> None:
    """Iterations up to `cfg.iterations`: template, encoder and pose decoder fitted to
    reconstruct batches of `x` under random symmetries, logged, validated and saved."""
    cfg = f.cfg
    bar = tqdm(total=cfg.iterations, initial=f.it, desc="shape fit", unit="it",
               disable=not progress, dynamic_ncols=True)
    running = math.nan
    while f.it < cfg.iterations:
        idx = torch.randint(0, len(x), (cfg.batch_size,), generator=f.gen)
        xb = _batch(x, idx, f.gen).to(device)  # the symmetries drawn on the CPU
        loss = _recon(f.G, f.E, xb, cfg.recon_levels)
        f.opt.zero_grad(set_to_none=True)
        loss.backward()
        f.opt.step()
        f.it += 1
        running = loss.item() if math.isnan(running) else 0.95 * running + 0.05 * loss.item()
        bar.update(1)
        bar.set_postfix(recon=f"{running:.4f}")
        if f.it % 50 == 0:
            f.log({"kind": "train", "iteration": f.it, "l_recon": round(running, 5)})
        if f.it % cfg.eval_every == 0 or f.it == cfg.iterations:
            if f.validate():
                f.save("best.pt")
            f.save()
    bar.close()


def fit_shape(model, train_x: np.ndarray, out, cfg: ShapeFitConfig = ShapeFitConfig(),
              val_x: np.ndarray | None = None, progress: bool = True,
              report: Callable[[ConvexGenerator], dict] | None = None,
              device: str = "cpu", discs=None) -> dict:
    """Fit a convex template to `train_x` ((N, 1, 64, 64) prepared frames, no labels) from the
    rod model `model` (a training checkpoint or model folder) -> summary (also
    out/summary.json); the model is its "model": out/best.pt (with `val_x`) or out/last.pt.
    Skipped when out/summary.json is there.
    `device`: where to fit ("auto": a GPU when there is one). `discs`: the starting discs
    (`cfg.start` "discs") instead of `rod_discs`' (`pilematch.match_head`'s)."""
    out = Path(out)
    if (out / "summary.json").is_file() and (out / "last.pt").is_file():
        return json.loads((out / "summary.json").read_text())
    if (out / "best.pt").is_file() and not (out / "last.pt").is_file():
        (out / "best.pt").unlink()  # of a run killed before its first save: begun again
    src = Path(model)
    src = src / "model.pt" if src.is_dir() else src
    if len(train_x) < 1:
        raise ValueError("shape fitting needs training frames; none were given")
    out.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(cfg.seed)
    x = torch.from_numpy(np.ascontiguousarray(train_x[:cfg.frames], dtype=np.float32))
    if discs is not None and cfg.start != "discs":
        raise ValueError(f"discs given for a template started as {cfg.start!r}; valid: start "
                         "'discs'")
    # 1. the convex template started from the rod, with the rod's encoder and pose decoder
    state, G, E = convex_from_rod(checkpoint.load(src), cfg, src, x, discs)
    given = [list(map(float, d)) for d in discs] if discs is not None else None
    xv = (torch.from_numpy(np.ascontiguousarray(val_x[:cfg.val_frames], dtype=np.float32))
          if val_x is not None and len(val_x) else None)
    device = checkpoint.pick_device(device)
    G, E = G.to(device), E.to(device)
    xv = xv.to(device) if xv is not None else None
    # 2. all three fitted to reconstruct the frames
    template = [getattr(G, k) for k in G.template_parameters]
    opt = torch.optim.Adam([{"params": list(E.parameters()) + list(G.pose.parameters()),
                             "lr": cfg.encoder_lr},
                            {"params": template, "lr": cfg.template_lr}], betas=(0.5, 0.999))
    f = _ShapeFit(cfg, src, given, state, G, E, opt, torch.Generator().manual_seed(cfg.seed),
                  out, xv, report)
    if (out / "last.pt").is_file():
        f.resume(device)
    f.start = time.monotonic()
    if f.it == 0 and f.validate():
        f.save("best.pt")
    E.train()
    _fit(f, x, device, progress)
    if not (out / "last.pt").is_file():
        f.save()
    vals = [h for h in f.history if h["kind"] == "val"]
    scored = [h for h in vals if "recon_l1" in h]
    best = min(scored, key=lambda h: h["recon_l1"]) if scored else None
    summary = {"source": str(src), "config": asdict(cfg), "discs": given, "iterations": f.it,
               "seconds": round(f.seconds(), 1), "frames": len(x),
               "first": vals[0] if vals else None, "last": vals[-1] if vals else None,
               "best": best, "model": str(out / ("best.pt" if best else "last.pt"))}
    write_json(out / "summary.json", summary)
    return summary
