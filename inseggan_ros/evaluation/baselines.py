"""Classical instance-segmentation baselines that the InSeGAN paper compares with.

K-Means, spectral clustering, GrabCut followed by K-Means, and Felzenszwalb superpixels, each on
a depth frame turned into heights above the bin floor. They give the numbers InSeGAN has to
beat (paper: K-Means 0.464, spectral 0.452, GrabCut+K-Means 0.486 on Insta-10; superpixels 0.398
on 10 cones) and a segmentation that works before any model is trained. The algorithms come from
scikit-learn, OpenCV and scikit-image; this module only prepares their input and turns their
output into a label image.

Every baseline has the same signature, `fn(heights, fg, n, seed=0) -> labels`:

- `heights`: (H, W) float image of heights above the bin floor, any units, larger = nearer the
  camera (64 x 64 at run time);
- `fg`: (H, W) boolean foreground mask (the pixels that belong to some object);
- `n`: the number of instances;
- returns an (H, W) uint8 label image: 0 outside `fg`, every `fg` pixel labelled 1..n, all n
  labels used (fewer only when `fg` has fewer than n pixels; all zeros when `fg` is empty).

The result depends on the inputs and `seed` only. Each baseline runs on one thread (see
`_single_threaded`). Bad input (shapes that differ, n outside 1..255, a seed outside
0..2**31-1, non-finite heights on the foreground) raises ValueError saying what was wrong.

Time per 64 x 64 frame, n = 5, on this project's 2-core machine (one thread, as always),
median (max) over the frames:

| frames | fg pixels | kmeans | spectral | grabcut_kmeans | felzenszwalb |
|---|---|---|---|---|---|
| 100 simulated bins, whole view | ~290 | 6 (8) ms | 5 (7) ms | 9 (15) ms | 4 (18) ms |
| 100 simulated bins, central half | ~1070 | 8 (16) ms | 9 (14) ms | 12 (18) ms | 4 (9) ms |
| 5 discs of radius 13 | 2556 | 9 (9) ms | 13 (14) ms | 14 (14) ms | 4 (4) ms |
| whole frame foreground, random heights | 4096 | 16 (18) ms | 41 (44) ms | 17 (20) ms | 3 (4) ms |

The slowest inputs found (random and ragged masks, n up to 24, sizes up to 80 x 80) are a
foreground of 64 separate 6 x 6 squares and a random 60 % of the pixels: spectral 0.1 s, the
others under 25 ms.

Mean mIoU on the two simulated sets (ground-truth fg): kmeans 0.85 / 0.80, spectral 0.92 / 0.92,
grabcut_kmeans 0.85 / 0.80 (with an exact fg GrabCut has nothing to remove), felzenszwalb
0.91 / 0.88; labelling all fg as one object scores 0.20.
"""
from __future__ import annotations

import functools
from collections.abc import Callable

import cv2
import numpy as np
from scipy import ndimage
from scipy.sparse import coo_matrix, csr_matrix
from scipy.sparse.csgraph import connected_components, minimum_spanning_tree
from scipy.spatial.distance import cdist
from sklearn.cluster import KMeans, spectral_clustering
from sklearn.feature_extraction.image import img_to_graph
from threadpoolctl import ThreadpoolController

from inseggan_ros.runtime.preprocess import fill_labels_nearest
from inseggan_ros.runtime.superpixels import depth_superpixels


# --------------------------------------------------------------------------- shared helpers

@functools.cache
def _threadpools() -> ThreadpoolController:
    """The BLAS/OpenMP pools of the libraries loaded above (found once: a scan costs ~2 ms)."""
    return ThreadpoolController()


def _single_threaded(fn: Callable[..., np.ndarray]) -> Callable[..., np.ndarray]:
    """Run `fn` with BLAS/OpenMP pools limited to one thread, and OpenCV's too.

    For a 64 x 64 frame threads only cost: on this 2-core machine under load, K-Means took
    ~400 ms with OpenMP's default threads and 6 ms on one.
    """
    @functools.wraps(fn)
    def wrapper(*args, **kwargs) -> np.ndarray:
        cv_threads = cv2.getNumThreads()
        cv2.setNumThreads(1)
        try:
            with _threadpools().limit(limits=1):
                return fn(*args, **kwargs)
        finally:
            cv2.setNumThreads(cv_threads)
    return wrapper


def _check(heights: np.ndarray, fg: np.ndarray, n: int,
           seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Validated float64 heights and bool mask."""
    heights = np.asarray(heights)
    fg = np.asarray(fg)
    if heights.ndim != 2:
        raise ValueError(f"heights must be an (H, W) image, got shape {heights.shape}")
    if fg.shape != heights.shape:
        raise ValueError(f"fg must have the shape of heights {heights.shape}, got {fg.shape}")
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or not 1 <= n <= 255:
        raise ValueError(f"n must be an integer in 1..255 (uint8 labels), got {n!r}")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or not 0 <= seed < 2**31:
        raise ValueError(f"seed must be an integer in 0..2**31-1, got {seed!r}")
    if not (np.issubdtype(heights.dtype, np.integer) or np.issubdtype(heights.dtype, np.floating)):
        raise ValueError(f"heights must be a real numeric image, got dtype {heights.dtype}")
    heights = heights.astype(np.float64)
    fg = fg.astype(bool)
    if not np.isfinite(heights[fg]).all():
        raise ValueError("heights must be finite on every foreground pixel (NaN or inf found)")
    return heights, fg


def _trivial(fg: np.ndarray, n: int) -> np.ndarray | None:
    """The answer when there is nothing to cluster: one instance (all fg is label 1), or at
    most n fg pixels (one label each); None otherwise."""
    count = int(fg.sum())
    if n > 1 and count > n:
        return None
    labels = np.zeros(fg.shape, np.uint8)
    labels[fg] = 1 if n == 1 else np.arange(1, count + 1)
    return labels


def _features(heights: np.ndarray, mask: np.ndarray, height_weight: float) -> np.ndarray:
    """(x, y, height) per mask pixel: x, y divided by the image's longer side (so 0..1 and
    isotropic), height rescaled to 0..1 over the mask and multiplied by `height_weight`."""
    ys, xs = np.nonzero(mask)
    side = max(mask.shape)
    h = heights[mask]
    span = h.max() - h.min()
    h = (h - h.min()) / span if span > 0 else np.zeros_like(h)
    return np.column_stack([xs / side, ys / side, height_weight * h])


def _kmeans_labels(heights: np.ndarray, mask: np.ndarray, n: int, seed: int) -> np.ndarray:
    """K-Means on the mask pixels' features; labels 1..n on the mask, 0 elsewhere.

    Height weight 0.25 (heights span 0..1 over the mask, positions 0..1 across the image):
    enough for a height step to separate stacked objects, not so much that height alone slices
    one tilted object into layers. Chosen on two sets of 100 simulated 64 x 64 bins (20 each of
    5 cylinders, hex nuts, wooden blocks, cones, bolts; ground-truth fg): the whole 224 x 224
    view scaled down (objects ~7 px across) and its central 112 x 112 (~14 px). Mean mIoU of
    the two by weight: 0 -> 0.79, 0.1 -> 0.80, 0.2 -> 0.82, 0.25 -> 0.82, 0.3 -> 0.82,
    0.5 -> 0.78, 1 -> 0.66.
    """
    km = KMeans(n_clusters=n, n_init=10, random_state=seed)
    labels = np.zeros(mask.shape, np.uint8)
    labels[mask] = km.fit_predict(_features(heights, mask, height_weight=0.25)) + 1
    return labels


def _ensure_n_labels(labels: np.ndarray, heights: np.ndarray, n: int, seed: int) -> np.ndarray:
    """Split the largest region in two (K-Means) until n labels are used, then number 1..n."""
    labels = labels.copy()
    while True:
        ids, sizes = np.unique(labels[labels > 0], return_counts=True)
        if len(ids) >= n:
            break
        region = labels == ids[np.argmax(sizes)]
        halves = _kmeans_labels(heights, region, 2, seed)
        labels[halves == 2] = next(i for i in range(1, 256) if i not in ids)
    lut = np.zeros(256, np.uint8)
    lut[ids] = np.arange(1, len(ids) + 1)
    return lut[labels]


# --------------------------------------------------------------------------- the baselines

@_single_threaded
def kmeans(heights: np.ndarray, fg: np.ndarray, n: int, seed: int = 0) -> np.ndarray:
    """K-Means (scikit-learn, 10 restarts) on the fg pixels' (x, y, height) features, the
    paper's K-Means baseline. Height weight 0.25 against positions in image widths (see
    `_kmeans_labels`)."""
    heights, fg = _check(heights, fg, n, seed)
    trivial = _trivial(fg, n)
    if trivial is not None:
        return trivial
    return _kmeans_labels(heights, fg, n, seed)


def _link_pieces(affinity: csr_matrix, mask: np.ndarray, weight: float) -> csr_matrix:
    """Join the graph's connected pieces into one with `weight` edges along a minimum spanning
    tree of the pieces' centroids (each edge between the pixels of two pieces nearest to the
    other's centroid).

    Why: with more pieces than clusters the Laplacian's eigenvalue 0 has a multiplicity above
    n. ARPACK at full precision then took seconds to minutes (measured: 7 discs for n = 5,
    4 s; a 4 x 4 grid of squares, 80 s), and at a looser tolerance it returned mixtures of
    pieces even for n separate discs (mIoU 0.44). Linked, eigenvalue 0 is simple and a 1e-6
    tolerance finds the right clusters in milliseconds.
    """
    count, piece = connected_components(affinity, directed=False)
    if count == 1:
        return affinity
    points = np.column_stack(np.nonzero(mask)).astype(np.float64)  # row-major, as the graph
    sizes = np.bincount(piece)
    centroids = np.column_stack([np.bincount(piece, points[:, k]) / sizes for k in (0, 1)])
    distances = cdist(centroids, centroids) + 1e-9  # coincident centroids still get an edge
    np.fill_diagonal(distances, 0)
    tree = minimum_spanning_tree(distances).tocoo()
    ends = []
    for a, b in zip(tree.row, tree.col):
        for this, other in ((a, b), (b, a)):
            members = np.flatnonzero(piece == this)
            ends.append(members[np.argmin(((points[members] - centroids[other]) ** 2).sum(1))])
    ends = np.array(ends).reshape(-1, 2)
    links = coo_matrix((np.full(2 * len(ends), weight),
                        (np.r_[ends[:, 0], ends[:, 1]], np.r_[ends[:, 1], ends[:, 0]])),
                       shape=affinity.shape)
    return (affinity + links).tocsr()


@_single_threaded
def spectral(heights: np.ndarray, fg: np.ndarray, n: int, seed: int = 0) -> np.ndarray:
    """Spectral clustering (scikit-learn) of the fg pixel graph.

    Nodes are fg pixels, edges join 4-neighbours with weight exp(-beta * |dh| / std(|dh|)) +
    1e-6, beta = 10, as in scikit-learn's "segmenting the picture of greek coins" example:
    neighbours at similar heights bind strongly, a height step between two objects is a weak
    link (beta 1, 2, 5, 10, 20 gave mean mIoU 0.92, 0.90, 0.90, 0.92, 0.90 on the simulated
    bins of `_kmeans_labels`). The graph's diagonal (pixel values, not gradients) is dropped;
    the std is that of the gradients. Labels by 'cluster_qr' (deterministic; 'discretize'
    scored the same).

    Two steps keep the eigen-solver fast and the result sane on a ragged foreground: fg pieces
    under 5 pixels (specks of sensor noise) stay out of the graph and take the label of the
    nearest clustered pixel afterwards, and separate pieces are joined by 1e-6 links (the
    weakest edge the graph has anyway; see `_link_pieces`). Adding 1 % random specks to the
    simulated bins' fg cost 0.08 mIoU without the first step and nothing with it. ARPACK
    stops at a tolerance of 1e-6 (same mIoU as machine precision, 1e-4 lost a little; a
    foreground of 64 separate squares took 0.1 s instead of 0.4-0.6 s). If the clustering
    leaves a cluster empty, the largest one is split until n are used.
    """
    heights, fg = _check(heights, fg, n, seed)
    trivial = _trivial(fg, n)
    if trivial is not None:
        return trivial
    pieces, _ = ndimage.label(fg)
    core = fg & (np.bincount(pieces.ravel())[pieces] >= 5)
    if core.sum() <= n:  # nothing but specks: cluster them all
        core = fg
    graph = img_to_graph(heights, mask=core).tocoo()
    off = graph.row != graph.col
    grad = graph.data[off]
    std = grad.std() if grad.size else 0.0
    weights = np.exp(-10.0 * grad / std) if std > 0 else np.ones_like(grad)
    weights += 1e-6  # as in the example: a steep height step weakens an edge, never removes it
    count = int(core.sum())
    affinity = coo_matrix((weights, (graph.row[off], graph.col[off])), shape=(count, count))
    affinity = _link_pieces(affinity.tocsr(), core, weight=1e-6)
    clusters = spectral_clustering(affinity, n_clusters=n, assign_labels="cluster_qr",
                                   eigen_tol=1e-6, random_state=seed)
    labels = np.zeros(fg.shape, np.uint8)
    labels[core] = clusters + 1  # img_to_graph numbers the mask pixels in row-major order
    return fill_labels_nearest(_ensure_n_labels(labels, heights, n, seed), fg)


@_single_threaded
def grabcut_kmeans(heights: np.ndarray, fg: np.ndarray, n: int, seed: int = 0) -> np.ndarray:
    """Grabcut (OpenCV) refines the foreground, then K-Means as in `kmeans` splits it.

    GrabCut starts from `fg`: probable foreground inside it, probable background in a 3-pixel
    ring around it, definite background beyond; 3 iterations, OpenCV's RNG seeded with `seed`.
    Its image is the height image as 8-bit grey in three channels, the floor (height 0, or the
    lowest fg height if lower) black and the highest fg pixel white, with everything beyond the
    ring drawn as floor. That last step matters: bin walls are higher than the objects, and
    with them in the background colour model GrabCut kept only half of the true foreground on
    simulated bins; without them it keeps all of it, and from a foreground mask dilated by 2
    pixels (precision 0.52) it recovers the objects with precision 0.97 and recall 0.99.
    Fg pixels that GrabCut drops get the label of the nearest clustered pixel.
    """
    heights, fg = _check(heights, fg, n, seed)
    trivial = _trivial(fg, n)
    if trivial is not None:
        return trivial
    ring = ndimage.binary_dilation(fg, iterations=3)
    lo, hi = min(0.0, heights[fg].min()), heights[fg].max()
    refined = fg
    # GrabCut needs a height contrast and samples of both classes for its 5-component models.
    if hi > lo and (~fg).sum() >= 5:
        visible = ring & np.isfinite(heights)  # lost readings off fg are drawn as floor too
        grey = np.where(visible, np.clip((heights - lo) / (hi - lo), 0, 1), 0)
        image = cv2.cvtColor(np.round(grey * 255).astype(np.uint8), cv2.COLOR_GRAY2BGR)
        mask = np.full(fg.shape, cv2.GC_BGD, np.uint8)
        mask[ring] = cv2.GC_PR_BGD
        mask[fg] = cv2.GC_PR_FGD
        cv2.setRNGSeed(seed)
        cv2.grabCut(image, mask, None, np.zeros((1, 65)), np.zeros((1, 65)), 3,
                    cv2.GC_INIT_WITH_MASK)
        refined = fg & ((mask == cv2.GC_FGD) | (mask == cv2.GC_PR_FGD))
        if refined.sum() <= n:  # GrabCut dropped (nearly) everything: keep the input mask
            refined = fg
    return fill_labels_nearest(_kmeans_labels(heights, refined, n, seed), fg)


@_single_threaded
def felzenszwalb(heights: np.ndarray, fg: np.ndarray, n: int, seed: int = 0) -> np.ndarray:
    """Felzenszwalb-Huttenlocher graph segmentation (scikit-image), the paper's superpixels.

    Runs on heights rescaled to 0..1 over fg with the background set to -1 (a strong edge round
    every object), scale 200, sigma 0.3 and min_size 20 pixels: on 64 x 64 frames an object
    covers roughly 40-300 pixels, so min_size removes specks but not objects, and a small sigma
    keeps the height steps between touching objects sharp (mean mIoU 0.90 on the simulated bins
    of `_kmeans_labels`; scale 50..200, sigma 0.3..0.5, min_size 10..40 gave 0.82..0.90,
    sigma 0.5 always worse than 0.3). The n largest segments (counted on fg) are the
    instances; other fg pixels take the label of the nearest kept pixel. When fewer than n
    segments cover fg, the largest instance is split by K-Means until there are n. The
    algorithm is deterministic; `seed` only drives that split.
    """
    heights, fg = _check(heights, fg, n, seed)
    trivial = _trivial(fg, n)
    if trivial is not None:
        return trivial
    segments = depth_superpixels(heights, fg, scale=200)

    ids, sizes = np.unique(segments[fg], return_counts=True)
    keep = ids[np.argsort(-sizes, kind="stable")[:n]]
    lut = np.zeros(segments.max() + 1, np.uint8)
    lut[keep] = np.arange(1, len(keep) + 1)
    labels = np.where(fg, lut[segments], 0).astype(np.uint8)
    return _ensure_n_labels(fill_labels_nearest(labels, fg), heights, n, seed)


BASELINES: dict[str, Callable[[np.ndarray, np.ndarray, int, int], np.ndarray]] = {
    "kmeans": kmeans,
    "spectral": spectral,
    "grabcut_kmeans": grabcut_kmeans,
    "felzenszwalb": felzenszwalb,
}
