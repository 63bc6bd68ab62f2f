"""The convex template: exact height maps against ray casting, one connected body, gradients to
every template parameter, shape fidelity, and a short real training run that moves the learned
dimensions towards the true part's."""
import math

import numpy as np
import pytest
import torch
from scipy import ndimage

from inseggan_ros.evaluation import shape
from inseggan_ros.runtime import template as T
from inseggan_ros.runtime.model import ConvexGenerator, ModelConfig, rodrigues

SIZE = 64
PX = (torch.arange(SIZE) + 0.5) / SIZE * 2 - 1
Z_STEP = 1e-3


def _ray_cast(normals, offsets, px, py, zs):
    """Brute force: sample every vertical ray through a pixel centre at heights `zs` and keep the
    highest sample inside any piece (all half-spaces of it hold). -> (H, W) heights, 0 = floor."""
    U, V, Z = np.meshgrid(px, py, zs, indexing="xy")
    h = np.zeros((len(py), len(px)))
    for n, d in zip(normals, offsets):
        inside = np.ones(U.shape, bool)
        for (nx, ny, nz), dk in zip(n, d):
            inside &= nx * U + ny * V + nz * Z <= dk
        top = np.where(inside, Z, -np.inf).max(-1)
        h = np.maximum(h, np.where(np.isfinite(top), np.maximum(top, 0), 0))
    return h


SHAPES = {
    "box": lambda: [t[None] for t in T.box_planes((0.4, 0.25, 0.15))],
    "hex_prism": lambda: [t[None] for t in T.hex_prism_planes(0.6, 0.3)],
    # sectors overlapping by 3 pixels, so that the soft render shows no seams
    "nut_with_hole": lambda: T.ring_sector_planes(0.8, 0.2, 0.3, overlap=0.1),
}


@pytest.mark.parametrize("name", SHAPES)
def test_exact_height_map_matches_ray_casting(name):
    normals, offsets = SHAPES[name]()
    gen = torch.Generator().manual_seed(1)
    zs = np.arange(-1.5, 1.5, Z_STEP)
    for _ in range(3):  # random full 3D poses
        R = rodrigues(torch.randn(1, 3, generator=gen).double() * 1.5).float()
        t = torch.tensor([[0.1, -0.1, 0.3]]) + 0.1 * torch.randn(1, 3, generator=gen)
        nw, dw = T.pose_planes(normals, offsets, R, t)
        exact = T.height_map(nw, dw, PX, PX, temperature=0.0)[0].double().numpy()
        brute = _ray_cast(nw[0].double().numpy(), dw[0].double().numpy(), PX.double().numpy(),
                          PX.double().numpy(), zs)
        assert (brute > 0).sum() > 150, "the body is in view"
        agree = (exact > 0) == (brute > 0)
        both = agree & (brute > 0)
        # heights: the sampling step bounds the difference (measured: max 0.000998)
        assert np.abs(exact - brute)[both].max() <= Z_STEP + 1e-5
        # coverage: where the two differ, the ray grazes an edge: the body is thinner along it
        # than the sampling step; re-sampled 100 times finer there, they agree
        for r, c in zip(*np.nonzero(~agree)):
            fine = np.arange(exact[r, c] - 2 * Z_STEP, exact[r, c] + 2 * Z_STEP, Z_STEP / 100)
            if exact[r, c] == 0:  # brute force saw a sliver the exact map says is not there
                fine = np.arange(brute[r, c] - 2 * Z_STEP, brute[r, c] + 2 * Z_STEP, Z_STEP / 100)
            again = _ray_cast(nw[0].double().numpy(), dw[0].double().numpy(),
                              PX[c:c + 1].double().numpy(), PX[r:r + 1].double().numpy(), fine)
            assert abs(again[0, 0] - exact[r, c]) < 1e-4, (r, c, exact[r, c], brute[r, c])
        assert (~agree).sum() <= 2
        # the training renderer: coverage a sigmoid of the distance to the silhouette in pixels
        # (as the sphere template's), heights exact: 4 pixel centres from the nearest uncovered
        # one the silhouette is >= 3.5 pixels away; coverage measured >= 0.969 there
        soft = T.height_map(nw, dw, PX, PX, temperature=2 / SIZE)[0].double().numpy()
        if len(normals) == 1:  # one piece: it only lowers the body (and bleeds out of it);
            # a union also bleeds over its own occluding edges onto lower pieces (measured 0.17)
            assert (soft - exact)[exact > 0].max() < 1e-5
        inner = ndimage.distance_transform_edt(exact > 0) >= 4
        rel = (exact - soft)[inner] / exact[inner]
        print(name, "soft render 4 pixels inside: relative error max", rel.max(),
              "mean", rel.mean())
        assert inner.sum() > 20
        if len(normals) == 1:
            assert rel.max() < 1 - 1 / (1 + math.exp(-3)), rel.max()
        else:  # inside a union, where a piece occludes another, both are near their own
            # silhouettes and the soft render dips there (measured: mean 0.012-0.019, max 0.49)
            assert rel.mean() < 0.06, rel.mean()


def test_softmin_variant_agrees_with_exact_min():
    normals, offsets = SHAPES["nut_with_hole"]()
    R = rodrigues(torch.tensor([[0.3, -0.4, 0.9]]))
    nw, dw = T.pose_planes(normals, offsets, R, torch.tensor([[0.0, 0.1, 0.3]]))
    hard = T.height_map(nw, dw, PX, PX, temperature=2 / SIZE)
    soft = T.height_map(nw, dw, PX, PX, temperature=2 / SIZE, softmin=True)
    # log-sum-exp moves a top or bottom by at most T log(planes), at creases
    diff = (soft - hard).abs()
    print("softmin vs min: mean", float(diff.mean()), "max", float(diff.max()))
    assert diff.mean() < 0.01 and diff.max() < 0.2


def _random_generator(seed: int, pieces: int = 4, scale: float = 1.0) -> ConvexGenerator:
    torch.manual_seed(seed)
    G = ConvexGenerator(ModelConfig(renderer="convex", composite="zbuffer", latent_dim=16,
                                    pieces=pieces))
    with torch.no_grad():
        for name in G.template_parameters:
            p = getattr(G, name)
            p.copy_(torch.randn_like(p) * scale * (0.4 if name == "centre" else 1.0))
    return G


@pytest.mark.parametrize("seed", range(6))
def test_random_templates_are_one_bounded_connected_body(seed):
    G = _random_generator(seed)
    pieces = shape.template_pieces(G)
    corners = shape.vertices(pieces)  # raises if a piece were empty or unbounded
    assert np.isfinite(corners).all() and np.abs(corners).max() < 100
    # every piece overlaps the one before it (exact, by LP; a voxelisation of random pieces
    # also shows isolated voxels in the slivers at their acute corners)
    assert shape.components(pieces) == 1


@pytest.mark.parametrize("seed", range(3))
def test_corners_are_the_pieces_corners_and_floor_contact_lifts_the_lowest_onto_the_floor(seed):
    """`corners()` finds exactly the corners that scipy's half-space intersection finds; with
    floor_contact a body posed partly under the floor renders as the same body with its lowest
    corner on the floor (and one above the floor is left where it is)."""
    G = _random_generator(seed)
    x, real = G.corners()
    mine = np.unique(np.round(x[real].detach().double().numpy(), 5), axis=0)
    theirs = np.unique(np.round(shape.vertices(shape.template_pieces(G)), 5), axis=0)
    assert mine.shape == theirs.shape and np.allclose(mine, theirs, atol=1e-4)
    lifted = ConvexGenerator(ModelConfig(**{**G.cfg.to_dict(), "floor_contact": True}))
    lifted.load_state_dict(G.state_dict())
    gen = torch.Generator().manual_seed(seed)
    R = rodrigues(torch.randn(1, 3, generator=gen))
    lowest = float((x[real].detach() @ R[0].T)[:, 2].min())  # with the pose's height 0
    # the lowest corner under the floor by 0.2, then above it by 0.1
    w = _rotvec_of(R[0])
    for height, expect in ((-lowest - 0.2, -lowest), (-lowest + 0.1, -lowest + 0.1)):
        pose = torch.tensor([[*w, 0.05, -0.05, height]]).view(1, 1, 6)
        want = torch.tensor([[*w, 0.05, -0.05, expect]]).view(1, 1, 6)
        with torch.no_grad():
            torch.testing.assert_close(lifted.render_poses(pose), G.render_poses(want),
                                       atol=1e-4, rtol=0)


def _rotvec_of(R: torch.Tensor) -> list[float]:
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(R.double().numpy()).as_rotvec().tolist()


def test_without_the_chain_pieces_fall_apart():
    """The checks above can fail: two pieces placed apart give two bodies (negative control)."""
    n, d = T.box_planes((0.05, 0.05, 0.05))
    pieces = [(n.double().numpy(), (d + n @ torch.tensor(c)).double().numpy())
              for c in ([0.0, 0, 0], [0.5, 0, 0])]
    assert shape.components(pieces) == 2
    pts = shape.voxel_points(pieces, 0.02)
    idx = np.round((pts - pts.min(0)) / 0.02).astype(int)
    grid = np.zeros(idx.max(0) + 1, bool)
    grid[tuple(idx.T)] = True
    assert ndimage.label(grid)[1] == 2


def test_gradients_reach_every_template_parameter_and_the_pose_decoder():
    G = _random_generator(0, scale=0.3)
    G.init_box((0.3, 0.15, 0.1))
    with torch.no_grad():  # off the symmetric start, so that every piece shows somewhere
        G.centre.add_(torch.randn_like(G.centre) * 0.05)
        G.orientation.add_(torch.randn_like(G.orientation) * 0.3)
        G.tilt.add_(torch.randn_like(G.tilt) * 0.2)
    z = torch.randn(4, 3, 16)
    target = torch.rand(4, 1, 64, 64) * 2 - 1
    loss = (G(z) - target).abs().mean() + G.template_spread()
    loss.backward()
    for name, p in G.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all(), name
        assert p.grad.abs().sum() > 0, f"no gradient reaches {name}"
    for name in G.template_parameters:  # every piece's own parameters move
        g = getattr(G, name).grad.reshape(G.cfg.pieces, -1).abs().sum(1)
        assert (g > 0).all(), f"{name}: pieces without gradient {g}"


def test_generator_interface_and_alignment_features():
    G = _random_generator(2, scale=0.3)
    z = torch.randn(2, 3, 16)
    singles = G.render_instances(z)
    assert singles.shape == (2, 3, 64, 64) and singles.min() >= -1 and singles.max() <= 1
    pose = G.pose(z.reshape(6, 16)).reshape(2, 3, 6)
    torch.testing.assert_close(G.render_poses(pose), singles)
    torch.testing.assert_close(G.render_poses(pose, template=G.halfspaces()), singles)
    assert G.render_poses(pose, size=32).shape == (2, 3, 32, 32)
    G.eval()
    torch.testing.assert_close(G(z)[:, 0], singles.amax(1))
    f = G.alignment_features(z)
    assert f.shape == (2, 3, 21)
    # a half turn about any axis of the template renders a box the same; the features agree
    half_turn = rodrigues(torch.tensor([[math.pi, 0, 0]]))
    R = rodrigues(pose.reshape(6, 6)[:, :3])
    cols = lambda M: M.transpose(1, 2)  # noqa: E731
    outer = lambda M: cols(M)[..., :, None] * cols(M)[..., None, :]  # noqa: E731
    torch.testing.assert_close(outer(R @ half_turn), outer(R), atol=1e-5, rtol=0)
    with pytest.raises(ValueError, match="walls"):
        ModelConfig(renderer="convex", composite="zbuffer", walls=6)


def test_shape_fidelity_of_known_bodies():
    """A box 2 mm shorter and 1 mm wider than wooden_block, posed anywhere, aligns back to it
    with the IoU the sizes allow; six sectors around a hexagonal hole are hex_nut's collision
    shape (the convex hulls of its six wedges close the round hole's arcs into chords)."""
    truth = shape.part_pieces("wooden_block")
    n, d = T.box_planes((0.024, 0.013, 0.0075))
    R = shape._rotvec(np.array([0.3, -0.2, 1.0]))
    moved = shape.transformed([(n.double().numpy(), d.double().numpy())], R,
                              np.array([0.01, 0, 0.02]))
    f = shape.fit(moved, truth, voxel=0.001, refine_evals=40)
    expected = (48 * 25 * 15) / (50 * 25 * 15 + 48 * 26 * 15 - 48 * 25 * 15)  # 0.9245
    assert abs(f.iou - expected) < 0.01, f.iou
    np.testing.assert_allclose(f.dims_template_mm, [48, 26, 15], atol=0.05)
    np.testing.assert_allclose(f.dims_true_mm, [50, 25, 15], atol=0.01)
    assert not f.mirrored
    nut = T.ring_sector_planes(0.024, 0.008 * math.cos(math.pi / 6), 0.013)
    R = shape._rotvec(np.array([-0.5, 0.2, 0.4]))
    tpl = shape.transformed([(nut[0][k].double().numpy(), nut[1][k].double().numpy())
                             for k in range(6)], R, np.array([0.0, 0.03, 0.0]))
    g = shape.fit(tpl, shape.part_pieces("hex_nut"), voxel=0.001)
    print("nut", g.to_dict())
    # the same body, moved: what 1 mm voxels and the alignment's refinement leave
    np.testing.assert_allclose(g.dims_template_mm, g.dims_true_mm, atol=0.5)
    assert g.iou > 0.95, g.iou


def test_a_rod_of_spheres_as_pieces_holds_the_spheres_and_little_else():
    """The rod's pieces (each sphere as the polytope of its tangent planes) contain every point
    of the exact union of spheres and exceed it by at most a thin shell; a rod of equal spheres
    as long as the cylinder part aligns onto it with the IoU of a capsule in a cylinder."""
    from inseggan_ros.runtime.model import SphereGenerator

    G = SphereGenerator(ModelConfig(renderer="spheres", composite="zbuffer", spheres=6))
    with torch.no_grad():
        G.radius_shape.copy_(torch.tensor([50.0, -2.0, 0.5, 3.0, -1.0, 2.0]))
        G.length.fill_(0.5)
    centres, radii = (t.detach().double().numpy() for t in G.spheres())
    pieces = shape.template_pieces(G)
    pts = np.random.default_rng(0).uniform(-0.6, 0.6, (200_000, 3))
    exact = (np.linalg.norm(pts[:, None] - centres[None], axis=2) <= radii).any(1)
    approx = shape.occupancy(pieces, pts)
    assert approx[exact].all()  # the polytopes hold the spheres
    assert approx.sum() <= 1.03 * exact.sum(), (approx.sum(), exact.sum())
    # a capsule of 12 mm radius and 40 mm overall length vs the 24 x 40 mm cylinder part
    with torch.no_grad():
        G.radius_shape.fill_(50.0)
        G.log_radius.fill_(math.log(0.012))
        G.length.fill_(0.040 - 2 * 0.012)
    f = shape.fit(shape.template_pieces(G), shape.part_pieces("cylinder"), voxel=0.0025,
                  mirror=False, refine_evals=0)
    np.testing.assert_allclose(f.dims_template_mm, [40, 24, 24], atol=1.0)
    r, L = 12.0, 40.0 - 24.0  # capsule inside the cylinder: IoU = its volume / the cylinder's
    expected = (math.pi * r ** 2 * L + 4 / 3 * math.pi * r ** 3) / (math.pi * r ** 2 * 40.0)
    assert abs(f.iou - expected) < 0.03, (f.iou, expected)


def test_scale_from_the_data():
    from inseggan_ros.runtime.preprocess import PreprocessConfig, roi_from_camera
    from inseggan_ros.sim.camera import get_camera
    from inseggan_ros.sim.scene import BinConfig

    cam = get_camera("default")
    prep = PreprocessConfig(roi=roi_from_camera(cam, BinConfig()), floor_depth=cam.mount_height)
    s = shape.metres_per_unit(prep.to_dict(), cam, 1.8)
    # the crop is the bin's 90 mm floor less the pixels the margin shaves off: just under
    # 45 mm per half-width, and the height scale 1.8 x 50 mm / 2 = 45 mm agrees with it
    assert 0.040 < s[0] == s[1] < 0.045 and s[2] == pytest.approx(0.045)
    np.testing.assert_allclose(shape.metres_per_unit({"max_height": 0.05}, None, 1.8), 0.045)


def test_short_training_run_moves_a_box_template_towards_the_true_block(tmp):
    """A real training run (simulated wooden blocks, the cpu_convex recipe scaled down) moves
    the template's dimensions and shape towards the true part's, from the generator's default
    box (21.7 x 13 x 9 mm against 50 x 25 x 15 mm; the part needs one piece). Measured here:
    dimension error 0.48 -> 0.33, IoU 0.15 -> 0.24 after 80 iterations (35 s on a busy core)."""
    from conftest import run_cli

    from inseggan_ros.data import datasets as data_mod
    from inseggan_ros.core.checkpoint import load
    from inseggan_ros.runtime.model import build_models
    from inseggan_ros.runtime.model import make_generator
    from inseggan_ros.sim.dataset import load_meta
    from inseggan_ros.sim.scene import SceneConfig
    from inseggan_ros.learning.train import get_config, train

    root = tmp / "blocks"
    run_cli("simulate", "--object", "wooden_block", "--instances", "3", "--count", "60",
            "--split", "0.8,0.1,0.1", "--workers", "1", "--quiet", "--out", root, check=True)
    prep = data_mod.sim_preprocess_config(root)
    frames = data_mod.load_sim_split(root, "train", prep)
    cfg = get_config("cpu_convex", nf=8, batch_size=8, n_instances=3, pieces=1,
                     template_init="default", max_iterations=80, eval_every=10**6,
                     checkpoint_every=10**6, seed=0)
    camera = SceneConfig.from_dict(load_meta(root)["scene"]).camera
    scale = shape.metres_per_unit(prep.to_dict(), camera, cfg.model.height_gain)
    truth = shape.part_pieces("wooden_block")

    def fidelity(G):
        return shape.fit(shape.scaled(shape.template_pieces(G), scale), truth, refine_evals=0)

    torch.manual_seed(cfg.seed)
    before = fidelity(make_generator(cfg.model))  # what training starts from
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        train(cfg, frames, None, tmp / "run", prep.to_dict(), {}, device="cpu", progress=False)
    finally:
        torch.set_num_threads(threads)
    after = fidelity(build_models(load(tmp / "run" / "last.pt"))[1])
    print("dimension error", before.dims_error, "->", after.dims_error, "IoU", before.iou, "->",
          after.iou, after.dims_template_mm)
    assert after.dims_error < before.dims_error - 0.05
    assert after.iou > before.iou + 0.03


def test_mirrored_and_transposed_starting_poses_render_the_mirrored_image():
    """`symmetry.map_rotations` (the convex template's test-time augmentation): the pose it
    maps a box's pose to renders exactly the mirrored or transposed render, for all 8
    symmetries of the square; and `matrix_to_rotvec` inverts `rodrigues` up to pi."""
    from inseggan_ros.runtime.symmetry import (
        SYMMETRIES, map_rotations, matrix_to_rotvec, symmetry_matrix, transform_image)

    gen = torch.Generator().manual_seed(0)
    w = torch.randn(500, 3, generator=gen)
    w = w / w.norm(dim=1, keepdim=True) * torch.rand(500, 1, generator=gen) * math.pi
    torch.testing.assert_close(rodrigues(matrix_to_rotvec(rodrigues(w))), rodrigues(w),
                               atol=1e-5, rtol=0)
    G = ConvexGenerator(ModelConfig(renderer="convex", composite="zbuffer", latent_dim=16,
                                    pieces=1))
    G.init_box((0.3, 0.15, 0.1))
    pose = torch.cat([torch.randn(1, 4, 3, generator=gen),
                      torch.rand(1, 4, 3, generator=gen) * 0.6 - 0.3], -1)
    with torch.no_grad():
        singles = G.render_poses(pose)
        for sym in SYMMETRIES:
            mapped = G.render_poses(map_rotations(pose, symmetry_matrix(sym)))
            torch.testing.assert_close(mapped, transform_image(singles, sym), atol=1e-4, rtol=0)
