"""The model's instances voted within depth superpixels (`InferenceConfig.superpixel_scale`).

The z-buffered labels come from renders of the encoder's poses: the instances are right (how
many parts, which pixels belong together) but their outlines are a few pixels off, and at 64 x
64 a few pixels are much of a part. A graph segmentation of the input's own heights at a fine
scale (Felzenszwalb and Huttenlocher 2004, the algorithm of the classical baseline, with more,
smaller segments) cuts the frame along its height edges into superpixels that rarely straddle
two parts; each superpixel then takes the label most of its pixels have. The model still
decides which superpixels form one part, so parts that touch at one height, which the
baseline merges, stay apart wherever the superpixels separate them. Measured on the seven
parts' validation splits and chosen there, never on the test splits (docs/experiments.md,
2026-11-26).

After the vote, `split_frame` (`InferenceConfig.split_scale`) finds parts the model missed:
where two renders land on one part, a third instance's label covers its own part and a
neighbour across a height edge; the coarse graph segmentation cuts it there and the second
piece gets an id of its own (chosen the same way, 2026-11-26, night).

Last, `drop_walls` takes the labels off a bin wall's top that a tilted camera sees inside the
bin region (`WALL_BAND`): foreground that is no part, and in an empty bin the only foreground;
and `drop_small` gives the pixels of an instance too small to be a part in view to its
neighbours.

Both segmentations depend on the input alone, not on the model's labels, so `frame_segments`
can compute them beforehand (`Segmenter(superpixel_thread=True)` does, in a second thread
while the encoder runs); the vote and the split use them where the labels' foreground is the
one they were made for, and otherwise segment anew: the labels are the same either way.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from skimage.measure import label as _connected_regions
from skimage.segmentation import felzenszwalb as _skimage_felzenszwalb

from inseggan_ros.runtime.preprocess import fill_labels_nearest

SIGMA = 0.3  # Gaussian pre-smoothing, pixels (the baseline's: keeps height steps sharp)
MIN_SIZE = 20  # pixels: smaller superpixels are merged into a neighbour
# A label that lies along the region's edge (at least WALL_SHARE of its pixels within WALL_BAND
# pixels of it) and is nowhere thicker than a wall's top (every pixel within WALL_THICKNESS of
# its outline) is a wall, not a part (`drop_walls`; measured: docs/experiments.md).
WALL_BAND = 6
WALL_SHARE = 0.8
WALL_THICKNESS = 3.0
# The fewest pixels an instance may label (`drop_small`): a part showing fewer does not count as
# in view (`evaluation.selfcheck.MIN_VISIBLE_PIXELS`, the cards' visible-instance count).
MIN_INSTANCE = 8


def depth_superpixels(heights: np.ndarray, fg: np.ndarray, scale: float = 200,
                      sigma: float = SIGMA, min_size: int = MIN_SIZE) -> np.ndarray:
    """Felzenszwalb-Huttenlocher graph segmentation of a height image -> (H, W) int segment
    ids. The heights are rescaled to 0..1 over fg and the background set to -1, a strong edge
    round every object; `scale` sets how large segments grow (smaller: more, finer segments)."""
    h = heights[fg]
    span = h.max() - h.min() if h.size else 0.0
    image = np.full(fg.shape, -1.0)
    image[fg] = (h - h.min()) / span if span > 0 else 0.0
    return _skimage_felzenszwalb(image, scale=scale, sigma=sigma, min_size=min_size,
                                 channel_axis=None)


@dataclass(frozen=True)
class Segments:
    """A frame's graph segmentations by scale, and the foreground they were made for."""

    fg: np.ndarray
    by_scale: dict[int, np.ndarray]

    def get(self, fg: np.ndarray, scale: int) -> np.ndarray | None:
        """The segmentation at `scale` for foreground `fg`, or None if there is none."""
        return self.by_scale.get(scale) if np.array_equal(self.fg, fg) else None


def frame_segments(heights: np.ndarray, fg: np.ndarray, scales) -> Segments:
    """The segmentations `vote_frame` and `split_frame` make at `scales` (0: that step is off)
    of a frame whose labels cover `fg` (the z-buffer's labels cover the input's foreground),
    made beforehand."""
    heights, fg = np.asarray(heights, np.float64), np.asarray(fg, bool)
    wanted = {s for s in scales if s > 0} if fg.any() else set()
    return Segments(fg.copy(), {s: depth_superpixels(heights, fg, scale=s) for s in wanted})


def _segments(pre: Segments | None, heights, fg, scale: int) -> np.ndarray:
    seg = pre.get(fg, scale) if pre is not None else None
    return depth_superpixels(np.asarray(heights, np.float64), fg, scale=scale) \
        if seg is None else seg


def vote_frame(lab: np.ndarray, heights: np.ndarray, n: int, scale: int,
               pre: Segments | None = None) -> np.ndarray:
    """(H, W) labels (0 = background, 1..n) and heights -> labels constant on each superpixel
    of the foreground (its most frequent label; ties to the lower label). Background stays
    background. `pre`: the frame's `frame_segments`, if made beforehand."""
    fg = lab > 0
    if scale <= 0 or not fg.any():
        return lab
    seg = _segments(pre, heights, fg, scale)
    ids = seg[fg]
    counts = np.bincount(ids * (n + 1) + lab[fg], minlength=(seg.max() + 1) * (n + 1))
    counts = counts.reshape(-1, n + 1)  # foreground pixels only: column 0 stays empty
    out = lab.copy()
    out[fg] = counts.argmax(1)[ids]
    return out


def vote_labels(labels: torch.Tensor, x: torch.Tensor, n: int, scale: int,
                pre: list[Segments] | None = None) -> torch.Tensor:
    """(B, H, W) labels of the (B, 1, H, W) model input -> `vote_frame` of each frame (`pre`:
    their `frame_segments`, if made beforehand)."""
    if scale <= 0:
        return labels
    lab, heights = labels.cpu().numpy(), x[:, 0].float().cpu().numpy()
    pre = [None] * len(lab) if pre is None else pre
    out = np.stack([vote_frame(lab[b], heights[b], n, scale, pre[b]) for b in range(len(lab))])
    return torch.from_numpy(out).to(labels.device)


def split_frame(lab: np.ndarray, heights: np.ndarray, n: int, scale: int,
                pre: Segments | None = None, founding: np.ndarray | None = None
                ) -> tuple[np.ndarray, np.ndarray]:
    """Parts the model missed, found again along the frame's height edges -> (labels, (n,)
    bool: which of the ids 1..n now label a piece cut off another instance).

    The bin holds n parts and the model renders n instances, but two renders can land on one
    part, leaving a neighbour to be covered by the label of a third: its label then spans two
    parts, with a height edge between them, while another label is missing or small. Each
    label is cut into pieces, by the graph segmentation at a coarse `scale` (the baseline's
    segments, or larger ones) and into its connected regions. Then, as long as some label has a
    piece besides its largest one (at least MIN_SIZE pixels): an unused id takes the largest
    such piece; when all n ids are used, the piece replaces the smallest label if it is larger
    than it, whose pixels go to the nearest remaining label. Background stays background.
    `pre`: the frame's `frame_segments`, if made beforehand.

    `founding` (H, W) bool, or None: where a part's centre may be (the centre votes' heatmap
    above its peak threshold). A piece then takes an unused id only if it holds such a pixel:
    a bin may hold fewer parts than n, and an unused id is then no missed part (on shipped
    models' bins of 0 to n parts, 180 of 189 pieces given an unused id were no part:
    docs/experiments.md)."""
    fg = lab > 0
    changed = np.zeros(n, bool)
    if scale <= 0 or not fg.any():
        return lab, changed
    out = lab.astype(np.int64)
    coarse = _segments(pre, heights, fg, scale)
    regions = _connected_regions(out, background=0, connectivity=1)
    pieces = np.unique(coarse * (regions.max() + 1) + regions, return_inverse=True)[1]
    pieces, count = pieces.reshape(lab.shape), pieces.max() + 1
    may_found = np.ones(count, bool)  # the pieces that may take an unused id
    if founding is not None:
        may_found = np.bincount(pieces[fg & founding], minlength=count) > 0
    for _ in range(2 * n):  # each round fills or replaces one id; a label never empties
        labelled = out > 0
        ids, sizes = np.unique(out[labelled], return_counts=True)
        pair = np.bincount(out[labelled] * count + pieces[labelled],
                           minlength=(n + 1) * count).reshape(n + 1, count)
        free = [k for k in range(1, n + 1) if k not in ids]
        smallest = ids[sizes.argmin()]
        best = (0, 0, 0)  # (size, label, piece) of the largest piece besides a label's largest
        for k in ids:
            if not free and k == smallest:
                continue
            others = pair[k].copy()
            others[others.argmax()] = 0  # all but the label's largest piece
            if free:
                others[~may_found] = 0
            j = others.argmax()
            if others[j] > best[0]:
                best = (others[j], k, j)
        size, k, piece = best
        if size < MIN_SIZE or (not free and size <= sizes.min()):
            break
        new = free[0] if free else smallest
        if not free:
            out[out == smallest] = 0  # its pixels go to the nearest label below
        out[(out == k) & (pieces == piece)] = new
        changed[new - 1] = True
    if (fg & (out == 0)).any():
        out = fill_labels_nearest(out, fg)
    return out.astype(lab.dtype), changed


def split_labels(labels: torch.Tensor, x: torch.Tensor, n: int, scale: int,
                 pre: list[Segments] | None = None, founding: torch.Tensor | None = None
                 ) -> tuple[torch.Tensor, torch.Tensor]:
    """(B, H, W) labels of the (B, 1, H, W) model input -> `split_frame` of each frame:
    labels and (B, n) bool of the ids that now label a piece cut off another instance (`pre`:
    their `frame_segments`, if made beforehand; `founding`: (B, H, W), split_frame's)."""
    if scale <= 0:
        return labels, torch.zeros(len(labels), n, dtype=torch.bool, device=labels.device)
    lab, heights = labels.cpu().numpy(), x[:, 0].float().cpu().numpy()
    pre = [None] * len(lab) if pre is None else pre
    found = [None] * len(lab) if founding is None else founding.cpu().numpy()
    done = [split_frame(lab[b], heights[b], n, scale, pre[b], found[b])
            for b in range(len(lab))]
    out = np.stack([d[0] for d in done])
    changed = np.stack([d[1] for d in done])
    return torch.from_numpy(out).to(labels.device), torch.from_numpy(changed).to(labels.device)


def wall_frame(lab: np.ndarray) -> np.ndarray:
    """(H, W) labels -> the same with the labels of a bin wall's top set to 0 (background).

    A camera that looks into the bin at a tilt sees the top of a far wall inside the bin region
    found for it (the floor's box runs along the wall's inner edge): a band a few pixels wide
    along the region's edge, above min_height, so foreground, and so labelled: in an empty bin
    it is the only foreground. A part lying against that wall is thicker than the band, and
    lies mostly inside the region, so its label stays (WALL_BAND, WALL_SHARE, WALL_THICKNESS)."""
    from scipy.ndimage import distance_transform_edt

    H, W = lab.shape
    ys, xs = np.ogrid[:H, :W]
    band = np.minimum(np.minimum(ys, H - 1 - ys), np.minimum(xs, W - 1 - xs)) < WALL_BAND
    total = np.bincount(lab.ravel(), minlength=256)
    near = np.bincount(lab[band], minlength=256)
    walls = [k for k in np.flatnonzero(total[1:]) + 1 if near[k] >= WALL_SHARE * total[k]
             and distance_transform_edt(np.pad(lab == k, 1)).max() <= WALL_THICKNESS]
    return np.where(np.isin(lab, walls), 0, lab).astype(lab.dtype) if walls else lab


def small_frame(lab: np.ndarray, min_pixels: int = MIN_INSTANCE) -> np.ndarray:
    """(H, W) labels -> the same without instances of fewer than `min_pixels` pixels: their
    pixels take the nearest remaining label where they touch one (8-connected through
    labelled pixels: a rim or a corner cut off a part), else the background."""
    from scipy.ndimage import label as connected

    sizes = np.bincount(lab.ravel(), minlength=256)
    small = np.flatnonzero((sizes > 0) & (sizes < min_pixels))
    small = small[small > 0]
    if not len(small):
        return lab
    out = np.where(np.isin(lab, small), 0, lab).astype(lab.dtype)
    if out.any():
        regions, _ = connected(lab > 0, structure=np.ones((3, 3)))
        kept = np.isin(regions, np.unique(regions[out > 0])) & (lab > 0)
        out = np.where(kept, fill_labels_nearest(out, kept), 0).astype(lab.dtype)
    return out


def drop_walls(labels: torch.Tensor) -> torch.Tensor:
    """(B, H, W) labels -> `wall_frame` of each frame."""
    lab = labels.cpu().numpy()
    out = np.stack([wall_frame(f) for f in lab]) if len(lab) else lab
    return torch.from_numpy(out).to(labels.device)


def drop_small(labels: torch.Tensor, min_pixels: int = MIN_INSTANCE) -> torch.Tensor:
    """(B, H, W) labels -> `small_frame` of each frame."""
    lab = labels.cpu().numpy()
    out = np.stack([small_frame(f, min_pixels) for f in lab]) if len(lab) else lab
    return torch.from_numpy(out).to(labels.device)
