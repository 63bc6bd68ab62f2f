"""The part's template family, chosen by the user's own frames: no label, a small budget.

The shape stage learns a rod of spheres: a solid of revolution. Every shipped model of a part
that is not one took a recipe naming its family (`--convex-pieces 1` for the block, discs for
the bolt and the pin, a ring for the nut, a taper for the cone), chosen by someone who knew the
part. Here the loop tries every family the project has, each started from the learned (and
sized) rod, and keeps the one whose simulated piles look most like the user's frames:

  rod    the rod itself (cylinders, pins, rollers);
  box    one convex piece fitted to reconstruct the frames (`shapefit.fit_shape`: blocks,
         plates);
  bars   two convex pieces fitted so, started as two copies of the box: a union of convex
         pieces (a bracket, a plate with a step);
  bar    one bar as long as the rod and half as wide (`shapefit.rod_bars`), not fitted (the
         fitted box keeps the rod's outline, and a block's rod is a round blob: the box came
         out square), as thick as the frames' flat-lying parts, scaled across only, its width
         searched, as the tee's are (blocks, plates, flat bars); a candidate only when
         named (not in DEFAULT_FAMILIES);
  tee    two bars joined as a T, each as long as the rod and half as wide (`shapefit.rod_bars`),
         not fitted: fitted by reconstruction, two bars (started as copies of one box, as a T
         or as an L alike) became one slab on T-pieces' frames (docs/experiments.md); as
         thick as the frames' flat-lying parts (`shapefit.flat_top`), and so scaled across
         only (FLAT), their width then searched (`width_search`);
  ell    two bars joined as an L, so;
  u      three bars joined as a U, so (clips, staples, brackets);
  discs  the rod's radius profile cut into two flat-ended discs (a head on a shaft);
  ring   one hexagonal disc with a hole (nuts, washers);
  taper  one disc tapering to 0.4 of its radius (cones, stoppers).

Each candidate is measured by three label-free measures, and scored by the first and the
last (the second too with `edges`):
  * piles: `piles` scenes of the candidate, at each of `scales` (the whole template scaled;
    beyond the grid's end, step by step, where the best lies there: `scale_search`; with
    `flat_refine` the bars' before their width search, and with `refine` every candidate's,
    then the step about each one's best halved: `refine_scale`),
    simulated in the user's bin, through the user's camera, cut as the frames are; the
    1-Wasserstein distance of their heights (every pixel of the crop, the floor included: the
    parts' heights and visible area at once) to the user's frames' (`pilematch.heights`, the
    measure that sizes the bolt's head), at the candidate's best scale. Why scales: a rod
    sized by reconstruction comes out large (the shipped tilted cylinders' rod is 1.4 times
    the part: it covers more of each part), and piles of a template too large lie unlike the
    part's; piles of the true cylinder measure 0.05 against the frames, of that rod 0.36;
  * edges: the same piles, at that scale, by the 1-Wasserstein distance of their foreground
    pixels' distances to the nearest background or depth edge to the frames'
    (`pilematch.edge_distances`): how wide the parts' surfaces are. The heights alone do not
    tell a thin U from two fitted slabs of the same area (U-clips: 0.030 and 0.033); these
    do (0.029 and 0.81), in the order the models then segment (mIoU 0.68 and 0.47). Among
    the candidates of bars as thick as the rod they kept a U of bars too wide, whose model
    segmented U-clips worse than the L's (0.465 against 0.516); since the bars are as thick
    as the frames' flat parts and their width is searched, they keep the U at 0.49 of the
    width (edges' W1 0.026, the L's 0.357), whose model segments U-clips at 0.631 against the
    L's 0.546, and change no choice on T-pieces, Z-brackets or hex nuts; but on a small
    recording of blocks they made a taper's piles score about as well as the fitted box's
    (docs/experiments.md, 2026-12-07, day), so they are scored only when asked;
  * held-out reconstruction: the pyramid L1 of the candidate's renders (as made, unscaled),
    placed by its encoder, against frames no fit saw (`shapefit._recon` at level 1).
The kept family minimises the sum of those scored, each divided by its best value over the
candidates: a candidate must both pile like the part and explain the frames. The piles the
loop then simulates are of the kept candidate at its best scale. Everything is written to
out/family.json (each candidate's scores, scale and seconds), out/family.png (the scores),
out/views.png (each candidate at its scale from the top, the front and the side) and
each candidate's folder; a killed choice resumes candidate by candidate.
"""
from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from inseggan_ros.core import checkpoint
from inseggan_ros.evaluation.evaluate import write_json
from inseggan_ros.learning.pilematch import edge_distances, heights, pile_frames
from inseggan_ros.learning.shapefit import (BARS, MAX_BAR_WIDTH, ShapeFitConfig, _recon,
                                            fit_shape, hold_out)
from inseggan_ros.runtime.model import RING_WALLS, build_models
from inseggan_ros.sim.scene import PileError

# each family: how its template is made from the rod (`shapefit.ShapeFitConfig`; None: the
# rod as it is). The fitted ones' iterations are `FamilyConfig.fit_iterations`.
FAMILIES: dict[str, ShapeFitConfig | None] = {
    "rod": None,
    "box": ShapeFitConfig(pieces=1, walls=4, start="box"),
    "bars": ShapeFitConfig(pieces=2, walls=4, start="box"),
    "bar": ShapeFitConfig(pieces=1, walls=4, start="bar", iterations=0),
    "tee": ShapeFitConfig(pieces=2, walls=4, start="tee", iterations=0),
    "ell": ShapeFitConfig(pieces=2, walls=4, start="ell", iterations=0),
    "u": ShapeFitConfig(pieces=3, walls=4, start="u", iterations=0),
    "discs": ShapeFitConfig(pieces=2, walls=8, start="discs", iterations=0),
    "ring": ShapeFitConfig(pieces=1, walls=RING_WALLS, start="discs", hole=0.5, iterations=0),
    "taper": ShapeFitConfig(pieces=1, walls=8, start="discs", taper=0.4, iterations=0),
}

# the candidates by default: all but the lone bar, which on hex nuts piled nearer the frames
# than the ring (heights' W1 0.041 against 0.066, its scale refined) and would be kept there,
# its model's labels not measured (docs/experiments.md, 2026-12-07, afternoon)
DEFAULT_FAMILIES = tuple(f for f in FAMILIES if f != "bar")

# the families scaled across only (`scaled_model`'s flat): their height is the frames' own
# (`shapefit.flat_top`)
FLAT = tuple(f for f, c in FAMILIES.items() if c is not None and c.start in BARS)
# the families fitted to the frames by reconstruction: their template becomes the model's (the
# others are the piles' part only, and the model keeps the rod, as with `match_piles`)
FITTED = tuple(f for f, c in FAMILIES.items() if c is not None and c.iterations)
MAX_SCALE = 4.0  # of a candidate's template, at most
TIME_SKIP = "not made: the time budget"  # a candidate's row where its share ran out
UNPILED = "not piled: at no scale tried did the bin hold the user's n parts of it"


@dataclass(frozen=True)
class FamilyConfig:
    families: tuple[str, ...] = DEFAULT_FAMILIES  # the candidates
    piles: int = 60  # simulated scenes of each candidate at each scale
    scales: tuple[float, ...] = (0.55, 0.7, 0.85, 1.0)  # of each candidate's whole template
    extend: int = 5  # steps beyond the grid's end where its best lies there (`scale_search`)
    refine: int = 0  # rounds of halving the scale step about a best scale (`refine_scale`):
    # one for every candidate, the rest for the leaders; off: on U-clips two rounds found the
    # two fitted boxes' piles nearest the frames (W1 0.029 at x0.92), and their model
    # segmented worse than the L's kept without (mIoU 0.474 against 0.516)
    leaders: int = 3  # the candidates of the best scores after the first round
    flat_refine: int = 0  # rounds of `refine_scale` about each flat family's best scale
    # before its width search (`FLAT`): as thick as the frames' flat parts, their piles'
    # heights W1 follows their visible area, in a minimum narrower than the grid's step (x0.85
    # in scale, x0.72 in area): on blocks the lone bar measured 0.114 at x0.85 and 0.035 at
    # x0.92 (the block's area), 0.128 at x0.71 and 0.020 at x0.77 at 1.43 times the width.
    # Off by default with the bar: it changes the T's, L's and U's scores too, unmeasured on
    # the parts they are for
    widths: int = 2  # steps of the bars' width search (`width_search`; 0: the width
    # `shapefit.rod_bars` gives)
    edges: bool = False  # the edge distances' W1 joins the score (each row records it either
    # way): on U-clips it keeps the U (mIoU 0.631) over the L (0.546 without the vote, 0.619
    # with it), and on a small recording of blocks it let a taper score about as the box
    # (docs/experiments.md, 2026-12-07, day): off until measured on a box-like part
    fit_iterations: int = 500  # of the fitted families (box, bars)
    frames: int = 600  # of the user's frames, at most, for the fits and the heights
    val_frames: int = 80  # held out of them for the reconstruction score
    seed: int = 0  # of the piles (every candidate piled from the same scene seeds)
    workers: int = 1  # simulation processes

    def __post_init__(self):
        unknown = [f for f in self.families if f not in FAMILIES]
        if not self.families or unknown or len(set(self.families)) != len(self.families):
            raise ValueError(f"families {self.families!r} invalid; valid: one or more of "
                             f"{', '.join(FAMILIES)}, each once")
        for key in ("extend", "refine", "leaders", "widths", "flat_refine"):
            if getattr(self, key) < 0:
                raise ValueError(f"{key} {getattr(self, key)!r} invalid; valid: >= 0")
        if not self.scales or any(not 0 < v <= MAX_SCALE for v in self.scales) \
                or list(self.scales) != sorted(set(self.scales)):
            raise ValueError(f"scales {self.scales!r} invalid; valid: one or more increasing "
                             f"factors in (0, {MAX_SCALE:g}]")
        for key in ("piles", "fit_iterations", "frames", "val_frames", "workers"):
            if getattr(self, key) < 1:
                raise ValueError(f"{key} {getattr(self, key)!r} invalid; valid: >= 1")
        if self.val_frames >= self.frames:
            raise ValueError(f"val_frames {self.val_frames} invalid; valid: fewer than frames "
                             f"({self.frames})")


def make_candidate(family: str, rod_file: Path, x: np.ndarray, val: np.ndarray, out: Path,
                   cfg: FamilyConfig, progress: bool = False, width: float = 1.0) -> Path:
    """The model of `family` made from the rod model `rod_file` (fitted to the frames `x`, kept
    where it reconstructs `val` best, for the fitted families; bars `width` times as wide as
    `shapefit.rod_bars` makes them) -> its file."""
    shape = FAMILIES[family]
    if shape is None:
        return Path(rod_file)
    if width != 1.0:
        shape = replace(shape, bar_width=width)
    if shape.iterations:
        shape = replace(shape, iterations=cfg.fit_iterations,
                        eval_every=max(1, cfg.fit_iterations // 2))
    shape = replace(shape, frames=len(x), val_frames=max(1, len(val)), seed=cfg.seed)
    return Path(fit_shape(rod_file, x, out, shape, val_x=val, progress=progress)["model"])


def scaled_model(file: Path, s: float, dest: Path, flat: bool = False) -> Path:
    """The model `file` with its template `s` times as large (a rod: `sizing.scale_state`; a
    convex template: every piece's centre and planes scaled about the template's origin; with
    `flat`, across only: its height kept), written to `dest`; `file` itself where `s` is 1.
    `flat` takes a template of upright prisms (no tilt, turned about z at most: the bars'),
    whose walls' planes then move with the scale and whose tops and bottoms stay."""
    from inseggan_ros.learning.sizing import scale_state
    from inseggan_ros.runtime.model import CONVEX_MIN_EXTENT, _softplus_inverse

    if s == 1.0:
        return Path(file)
    state = checkpoint.load(file)
    if state["model_config"].get("renderer", "spheres") == "spheres":
        if flat:
            raise ValueError(f"{file}: a rod is scaled whole; valid: flat with a convex template")
        scale_state(state, s)
    else:  # each plane at reach + MIN + softplus(extent) from its centre: all of it x s
        g = state["generator"]
        across = torch.ones(g["extent"].shape[-1], dtype=torch.bool)
        if flat:
            if g["tilt"].abs().max() > 0 or g["orientation"][:, :2].abs().max() > 0:
                raise ValueError(f"{file}: its pieces are tilted; valid: flat with upright "
                                 "prisms (no tilt, turned about z at most)")
            across[:2] = False  # `template.prism_normals`: top, bottom, then the walls
            g["centre"] = g["centre"] * torch.tensor([s, s, 1.0], dtype=g["centre"].dtype)
        else:
            g["centre"] = g["centre"] * s
        kept = s * (CONVEX_MIN_EXTENT + torch.nn.functional.softplus(g["extent"].double()))
        new = _softplus_inverse((kept - CONVEX_MIN_EXTENT).clamp_min(1e-4)).to(
            g["extent"].dtype)
        g["extent"] = torch.where(across, new, g["extent"])
    return checkpoint.save(dest, state)


def held_out_l1(file: Path, val: np.ndarray) -> float:
    """The candidate's renders, placed by its own encoder, against `val` (pyramid L1, level 1)."""
    state = checkpoint.load(file)
    _, G, E = build_models(state, file)
    G.eval(), E.eval()
    with torch.no_grad():
        xv = torch.from_numpy(np.ascontiguousarray(val, dtype=np.float32))
        return float(_recon(G, E, xv, 1))


def frame_measures(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Frames (N, 1, H, W) -> what the piles are compared on: every pixel's height
    (`pilematch.heights`) and every foreground pixel's distance to an edge
    (`pilematch.edge_distances`)."""
    return heights(x), edge_distances(x)


def pile_distance(file: Path, data, meta, view: dict, folder: Path, ref: tuple,
                  cfg: FamilyConfig) -> tuple[float, float]:
    """`cfg.piles` scenes of the model `file`'s template simulated as the user's frames were
    taken and cut as they are (`pilematch.pile_frames`) -> the W1 distances of their heights
    and of their edge distances to `ref` (the user's: `frame_measures`)."""
    from scipy.stats import wasserstein_distance  # here: scipy.stats takes a second to import

    x = pile_frames(file, data, meta, view, folder, cfg.piles, cfg.seed, cfg.workers)
    return tuple(float(wasserstein_distance(a, b)) for a, b in zip(frame_measures(x), ref))


def scale_search(measure, cfg: FamilyConfig, more=lambda: True) -> dict[float, float]:
    """`measure(scale)` (a pile distance) at each of `cfg.scales`, then, while the best is at
    an end of what was measured (and `more()`: the time budget holds another), one more step
    beyond it (the ends' own ratio), at most `cfg.extend` steps: a template learned too small
    or too large is still sized, and a grid that brackets the best costs nothing more.
    -> {scale: distance}."""
    def beyond(w1: dict[float, float], best: float) -> float | None:
        if len(w1) < 2:
            return None
        ordered = sorted(w1)
        return best * (ordered[-1] / ordered[-2] if best == ordered[-1]
                       else ordered[0] / ordered[1])
    return step_out(measure, {v: measure(v) for v in cfg.scales}, cfg.extend, beyond,
                    MAX_SCALE, more)


def step_out(measure, d: dict[float, float], steps: int, beyond, limit: float,
             more=lambda: True) -> dict[float, float]:
    """`d` ({value: distance}, measured) with, while its best value lies at an end of what was
    measured (or is all there is), `measure` at `beyond(d, best)` past that end, at most
    `steps` times, while `more()` and the value is in (0, `limit`] (`beyond` None: no step)
    -> all of them, sorted. The rule of the scale and the bars' width searches."""
    d = dict(d)
    for _ in range(steps):
        if not more():
            break
        best = min(d, key=d.get)
        if len(d) > 1 and best not in (min(d), max(d)):
            break
        v = beyond(d, best)
        if v is None or not 0 < round(v, 4) <= limit:
            break
        d[round(v, 4)] = measure(round(v, 4))
    return dict(sorted(d.items()))


def refine_scale(measure, w1: dict[float, float], rounds: int, more=lambda: True
                 ) -> dict[float, float]:
    """`rounds` times (while `more()`): `measure` at the geometric middle between the best
    scale of `w1` ({scale: distance}) and each of its measured neighbours, so that the step
    about the best halves (in log scale) each round -> `w1` with the new scales.

    Why: the heights' W1 falls steeply to a narrow minimum in scale (on U-clips the L measured
    0.145, 0.033 and 0.249 at x1.18, x1.38 and x1.63), narrower than the grid's step, so the
    candidates' distances at their best grid point compare where each grid happened to fall
    rather than each shape at its own size."""
    w1 = dict(w1)
    for _ in range(rounds):
        if not more():
            break
        ordered = sorted(w1)
        best = min(w1, key=w1.get)
        i = ordered.index(best)
        for j in (i - 1, i + 1):
            if 0 <= j < len(ordered):
                v = round(math.sqrt(best * ordered[j]), 4)
                if v not in w1 and 0 < v <= MAX_SCALE:
                    w1[v] = measure(v)
    return dict(sorted(w1.items()))


SCORED = ("pile_w1", "recon_l1")  # the measures a candidate's score sums
EDGES = "edge_w1"  # and with `FamilyConfig.edges`, this one


def combined(rows: list[dict], edges: bool = False) -> list[float]:
    """Each row's score: each of its measures (SCORED: the heights' W1 and the held-out
    reconstruction; with `edges` also the edge distances' W1 at the same scale) over the best
    candidate's, summed."""
    keys = SCORED + ((EDGES,) if edges else ())
    best = {k: max(min(r[k] for r in rows), 1e-9) for k in keys}
    return [sum(r[k] / best[k] for k in keys) for r in rows]


def choose(rod_file, frames: np.ndarray, data, meta, view: dict, out,
           cfg: FamilyConfig = FamilyConfig(), progress: bool = True,
           seconds: float = math.inf) -> dict:
    """Every family of `cfg` made from the rod model `rod_file`, piled and scored against the
    user's `frames` ((N, 1, H, W) prepared, no label; `data`, `meta` and `view` as the loop's
    piles take them) -> the choice (also out/family.json): "rows" (each candidate: family,
    model, its best scale and the model at it ("part"), pile_w1 there, recon_l1, score,
    seconds), "kept" (the family), "model" (its file as made) and "part" (at its scale: what
    the piles are of).
    Within `seconds` (the loop's time budget's share): the candidates are made in
    `cfg.families`' order, and one whose expected time (the mean of those made so far) no
    longer fits is not made (its row says so), nor does a scale search step past the grid's
    end once its candidate's share (the time left over the candidates left) is spent. The
    first candidate is always made.
    Skipped when out/family.json holds a choice of the same config and rod."""
    out = Path(out)
    config = json.loads(json.dumps(asdict(cfg)))
    done = json.loads((out / "family.json").read_text()) if (out / "family.json").is_file() \
        else None
    if done and done["config"] == config and done["rod"] == str(rod_file):
        return done
    frames = np.asarray(frames)[:cfg.frames]
    x, val = hold_out(frames, ShapeFitConfig(frames=cfg.frames - cfg.val_frames,
                                             val_frames=cfg.val_frames))
    ref = frame_measures(frames)
    out.mkdir(parents=True, exist_ok=True)
    log = out / "candidates.jsonl"
    rows = {r["family"]: r for r in map(json.loads, log.read_text().splitlines())
            if r["rod"] == str(rod_file) and r["config"] == config and "edge_w1" in r} \
        if log.is_file() else {}
    deadline, spent = time.monotonic() + seconds, []
    for k, family in enumerate(tqdm(cfg.families, desc="template family", unit="family",
                                    disable=not progress)):
        if family in rows:
            continue
        t0 = time.monotonic()
        if spent and t0 + sum(spent) / len(spent) > deadline:
            rows[family] = {"family": family, "skipped": TIME_SKIP}
            continue
        own = t0 + (deadline - t0) / (len(cfg.families) - k)  # this candidate's share's end
        try:
            file = make_candidate(family, Path(rod_file), x, val, out / family, cfg)
        except ValueError as e:  # a rod too short for two discs, a ring's wall too thin
            rows[family] = {"family": family, "skipped": str(e)}
            continue
        edges: dict[float, float] = {}
        more = (lambda own=own: time.monotonic() < own)
        measure = _measure(file, family, out / family, data, meta, view, ref, cfg, edges)
        w1 = scale_search(measure, cfg, more)
        if not any(map(math.isfinite, w1.values())):
            rows[family] = {"family": family, "skipped": UNPILED + "; at x" + "; at x".join(
                f"{v:g}: {why}" for v, why in measure.unpiled.items())}
            continue
        row = {"family": family, "model": str(file), "rod": str(rod_file), "config": config,
               "recon_l1": held_out_l1(file, val), **_at_best(w1, edges, file, out / family)}
        if family in FLAT and cfg.flat_refine:  # before the width search, within the stage's
            # time rather than the candidate's share: two piles a round find the parts' area,
            # where the grid's scales missed it (the width search's more, once the area is)
            _refine_row(row, cfg.flat_refine, data, meta, view, out, ref, cfg,
                        lambda: time.monotonic() < deadline)
        if family in FLAT and cfg.widths:
            row = _widths(row, Path(rod_file), x, val, data, meta, view, out, ref, cfg, more)
        row["seconds"] = round(time.monotonic() - t0, 1)
        _log(log, row)
        rows[family] = row
        spent.append(row["seconds"])
    _refine_leaders(rows, data, meta, view, out, ref, cfg, log, deadline)
    return _decide(rows, rod_file, config, out)


def _measure(file: Path, family: str, folder: Path, data, meta, view: dict, ref: tuple,
             cfg: FamilyConfig, edges: dict[float, float]):
    """-> measure(scale): the heights' pile distance of the candidate `file` of `family` at
    that scale (its model written to folder/scale{scale}.pt), the edge distances' kept in
    `edges`. The heights' alone choose the scale: they hold the parts' size (height and
    visible area)."""
    def measure(v: float) -> float:
        part = scaled_model(file, v, folder / f"scale{v:g}.pt", family in FLAT)
        try:
            w1, edges[v] = pile_distance(part, data, meta, view, folder / "piles", ref, cfg)
        except PileError as e:  # n parts this large do not stay in the user's bin: the
            measure.unpiled[v] = str(e)  # scale is not the part's (no distance)
            edges[v] = math.inf
            return math.inf
        return w1
    measure.unpiled = {}  # {scale: the simulator's reason} where no pile could be made
    return measure


WIDTH_STEP = 0.7  # the bars' width search's step (a factor)


def width_search(measure, steps: int, more=lambda: True) -> dict[float, float]:
    """`measure(width)` (a distance, 2 at the width 1 the search starts from) at WIDTH_STEP
    times it, then, while the best is at an end of what was measured (and `more()`), one
    more step beyond it: at most `steps` widths measured, each in (0, MAX_BAR_WIDTH]
    -> {width: distance}."""
    return step_out(measure, {1.0: 2.0}, steps,
                    lambda d, best: best * WIDTH_STEP if best == min(d) else best / WIDTH_STEP,
                    MAX_BAR_WIDTH, more)


def _widths(row: dict, rod_file: Path, x, val, data, meta, view: dict, out: Path, ref: tuple,
            cfg: FamilyConfig, more) -> dict:
    """A bars candidate's `row` (made at the width `shapefit.rod_bars` gives, its outline sized
    by the scale search) -> the row of the width whose piles' heights and edge distances (each
    over the first width's: the parts' visible area and the width of their surfaces) lie
    nearest the frames (`width_search`), "widths" recording each width's best scale and
    distances. Each width is piled at the scale that keeps the first's area (its best over the
    width's square root) and a grid step either side, searched beyond as the scales are.

    Why: the bars start as wide as the rod's radius, and the scale search sizes the outline,
    their width with it: on U-clips the T sized so measured the heights' W1 best of all
    (0.025) with its edges' W1 0.43 (docs/experiments.md)."""
    family, rows = row["family"], {1.0: row}
    step = cfg.scales[-1] / cfg.scales[-2] if len(cfg.scales) > 1 else 1 / 0.85

    def measure(f: float) -> float:
        folder = out / family / f"width{f:g}"
        file = make_candidate(family, rod_file, x, val, folder, cfg, width=f)
        s0 = row["scale"] / math.sqrt(f)
        grid = tuple(sorted({min(round(s0 * k, 4), MAX_SCALE) for k in (1 / step, 1, step)}))
        edges: dict[float, float] = {}
        w1 = scale_search(_measure(file, family, folder, data, meta, view, ref, cfg, edges),
                          replace(cfg, scales=grid), more)
        rows[f] = {**{k: v for k, v in row.items() if k != "refined"}, "model": str(file),
                   "folder": str(folder),
                   "recon_l1": held_out_l1(file, val), **_at_best(w1, edges, file, folder)}
        return (rows[f]["pile_w1"] / max(row["pile_w1"], 1e-9)
                + rows[f][EDGES] / max(row[EDGES], 1e-9))
    d = width_search(measure, cfg.widths, more)
    best = min(d, key=d.get)
    return {**rows[best], "width": best,
            "widths": {f"{f:g}": {"scale": r["scale"], "pile_w1": round(r["pile_w1"], 5),
                                  EDGES: round(r[EDGES], 5), "distance": round(d[f], 4)}
                       for f, r in rows.items()}}


def _at_best(w1: dict[float, float], edges: dict[float, float], file: Path,
             folder: Path) -> dict:
    """A candidate's row fields from its distances by scale: the best scale, the candidate
    `file` at it (`scaled_model`'s file in `folder`), its distances there and all of them."""
    scale = min(w1, key=w1.get)
    return {"scale": scale, "part": str(folder / f"scale{scale:g}.pt" if scale != 1.0 else file),
            "pile_w1": w1[scale], "edge_w1": edges[scale],
            "pile_w1_by_scale": {f"{v:g}": _finite(d) for v, d in w1.items()},
            "edge_w1_by_scale": {f"{v:g}": _finite(d) for v, d in edges.items()}}


def _finite(d: float) -> float | None:
    """A distance as a row records it: None where the scale could not be piled."""
    return round(d, 5) if math.isfinite(d) else None


def _log(log: Path, row: dict) -> None:
    with open(log, "a") as f:
        f.write(json.dumps(row) + "\n")


def _refine_leaders(rows: dict, data, meta, view: dict, out: Path, ref: tuple,
                    cfg: FamilyConfig, log: Path, deadline: float) -> None:
    """While the family's time lasts: every candidate's scale refined by one round
    (`refine_scale`), in the order of the combined scores, then the `cfg.leaders` of the best
    scores after it by the rest of `cfg.refine`'s rounds. Each row records the rounds it had
    ("refined") and is logged again (the last row of a family is the one a resumed choice
    reads). Why every candidate one round: a candidate whose grid points fell on both sides of
    a narrow minimum (the U on U-clips: 0.157, 0.045 and 0.195 at x1, x1.18 and x1.38) may lie
    below the leaders' best once measured near it."""
    scored = [r for r in rows.values() if "skipped" not in r]
    if not cfg.refine or not scored:
        return
    for rounds, top in ((1, len(scored)), (cfg.refine, cfg.leaders)):
        order = sorted(zip(combined(scored, cfg.edges), range(len(scored))))
        for _, i in order[:top]:
            row = scored[i]
            if row.get("refined", 0) >= rounds or time.monotonic() >= deadline:
                continue
            _refine_row(row, rounds, data, meta, view, out, ref, cfg,
                        lambda: time.monotonic() < deadline)
            _log(log, row)


def _refine_row(row: dict, rounds: int, data, meta, view: dict, out: Path, ref: tuple,
                cfg: FamilyConfig, more) -> None:
    """A candidate's `row` (in place) with its scale refined to `rounds` rounds in all
    (`refine_scale`, while `more()`), its best scale's fields, "refined" and "seconds" so."""
    t0 = time.monotonic()
    w1, edges = ({float(v): math.inf if d is None else d for v, d in row[k].items()}
                 for k in ("pile_w1_by_scale", "edge_w1_by_scale"))
    folder = Path(row.get("folder", out / row["family"]))
    measure = _measure(Path(row["model"]), row["family"], folder, data, meta, view, ref, cfg,
                       edges)
    w1 = refine_scale(measure, w1, rounds - row.get("refined", 0), more)
    row.update(_at_best(w1, edges, Path(row["model"]), folder), refined=rounds,
               seconds=round(row.get("seconds", 0.0) + time.monotonic() - t0, 1))


def _decide(rows: dict, rod_file, config: dict, out: Path) -> dict:
    """The candidate of the lowest combined score -> the choice, written to out/family.json and
    drawn to out/family.png."""
    scored = [r for r in rows.values() if "skipped" not in r]
    if not scored:
        raise ValueError(f"no template family could be made from {rod_file}: "
                         + "; ".join(f"{r['family']}: {r['skipped']}" for r in rows.values()))
    for r, s in zip(scored, combined(scored, bool(config.get("edges")))):
        r["score"] = round(s, 4)
    best = min(scored, key=lambda r: r["score"])
    choice = {"config": config, "rod": str(rod_file), "kept": best["family"],
              "model": best["model"], "scale": best["scale"], "part": best["part"],
              "rows": [{k: v for k, v in r.items() if k not in ("rod", "config")}
                       for r in rows.values()],
              "seconds": round(sum(r.get("seconds", 0.0) for r in scored), 1)}
    _plot(scored, best["family"], out / "family.png")
    _draw_views(scored, best["family"], out / "views.png")
    write_json(out / "family.json", choice)
    return choice


def _draw_views(rows: list[dict], kept: str, path: Path) -> None:
    """Each candidate's template at its best scale (the piles' part) seen from the top, the
    front and the side (`evaluation.shape.views_figure`), a row each, all at one scale, in
    template units (the model's 64-pixel crop spans 2 of them)."""
    from inseggan_ros.evaluation.shape import template_pieces, views_figure

    bodies = [(f"{r['family']}{' (kept)' if r['family'] == kept else ''} at x{r['scale']:g}",
               template_pieces(build_models(checkpoint.load(r["part"]), r["part"])[1]))
              for r in rows]
    views_figure(bodies, path, unit=1.0, unit_name="template units", dpi=80, voxels=80)


def _plot(rows: list[dict], kept: str, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = [r["family"] for r in rows]
    fig, axes = plt.subplots(1, 4, figsize=(13, 3))
    for ax, key, title in zip(axes, ("pile_w1", EDGES, "recon_l1", "score"),
                              ("piles' heights vs frames (W1)", "edge distances vs frames (W1)",
                               "held-out reconstruction L1", "combined (lower is kept)")):
        ax.bar(names, [r[key] for r in rows],
               color=["tab:green" if n == kept else "tab:gray" for n in names])
        ax.set_title(title, fontsize=9)
        ax.tick_params(axis="x", labelsize=8)
    fig.suptitle(f"template family: {kept} kept")
    fig.tight_layout()
    tmp = path.with_suffix(".tmp.png")
    fig.savefig(tmp, dpi=90)
    plt.close(fig)
    tmp.replace(path)
