"""Model modules: shapes, gradients, pose spread; losses against brute force."""
from dataclasses import replace
import copy
import itertools
import math
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from inseggan_ros.learning import losses
from inseggan_ros.runtime.model import Discriminator, Encoder, Generator, ModelConfig, rodrigues

SMALL = dict(nf=8, latent_dim=16, n_instances=3)


@pytest.mark.parametrize("composite", ["average", "zbuffer"])
def test_generator_shapes_and_gradients(composite):
    torch.manual_seed(0)
    cfg = ModelConfig(composite=composite, **SMALL)
    G = Generator(cfg)
    z = torch.randn(4, 3, 16, requires_grad=True)
    x, mean_f = G(z, return_features=True)
    assert x.shape == (4, 1, 64, 64) and mean_f.shape == (4, 16, 16, 16)
    assert x.min() >= -1 and x.max() <= 1
    singles = G.render_instances(z)
    assert singles.shape == (4, 3, 64, 64)
    if composite == "zbuffer":  # the composite is the per-pixel max of the single renders
        G.eval()
        torch.testing.assert_close(G(z)[:, 0], G.render_instances(z).amax(1))
        G.train()
        soft = G(z)[:, 0]  # training: a soft max, between the mean and the max
        assert (soft <= singles.amax(1) + 1e-5).all() and (soft >= singles.mean(1) - 1e-5).all()
    x.mean().backward()
    assert z.grad.abs().sum() > 0
    for name, p in G.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all(), name
    assert G.template.grad.abs().sum() > 0, "the implicit template learns"


def test_initial_poses_spread_over_the_bin():
    G = Generator(ModelConfig(**SMALL))
    p = G.pose(torch.randn(2000, 16))
    std = p.std(0)
    assert torch.allclose(std[:3], torch.ones(3), atol=0.15)
    assert torch.allclose(std[3:], torch.full((3,), 0.35), atol=0.06)


def test_rodrigues_gives_rotations():
    aa = torch.randn(50, 3)
    R = rodrigues(aa)
    torch.testing.assert_close(R @ R.transpose(1, 2), torch.eye(3).expand(50, 3, 3),
                               atol=1e-5, rtol=0)
    torch.testing.assert_close(torch.linalg.det(R), torch.ones(50), atol=1e-5, rtol=0)
    Rz = rodrigues(torch.tensor([[0.0, 0.0, np.pi / 2]]))[0]
    torch.testing.assert_close(Rz @ torch.tensor([1.0, 0, 0]), torch.tensor([0.0, 1, 0]),
                               atol=1e-6, rtol=0)


def test_discriminator_and_encoder_shapes():
    cfg = ModelConfig(**SMALL)
    x = torch.randn(5, 1, 64, 64, requires_grad=True)
    assert Discriminator(cfg)(x).shape == (5, 1)
    assert Discriminator(ModelConfig(spectral_norm=True, **SMALL))(x).shape == (5, 1)
    z, h = Encoder(cfg)(x, return_features=True)
    assert z.shape == (5, 3, 16) and h.shape == (5, 16, 16, 16)
    z.sum().backward()
    assert x.grad is not None
    wider = Encoder(ModelConfig(**{**SMALL, "renderer": "spheres", "composite": "zbuffer",
                                   "encoder_nf": 16}))
    z, h = wider(x, return_features=True)  # an encoder of its own width: the same codes
    assert z.shape == (5, 3, 16) and h.shape == (5, 32, 16, 16)


def test_bad_model_configs():
    with pytest.raises(ValueError, match="composite 'sum' invalid; valid: average, zbuffer"):
        ModelConfig(composite="sum")
    with pytest.raises(ValueError, match="image_size must be 64"):
        ModelConfig(image_size=128)
    with pytest.raises(ValueError, match="encoder_nf must be 0 .* got 12"):
        ModelConfig(renderer="spheres", composite="zbuffer", encoder_nf=12)
    with pytest.raises(ValueError, match="learned renderer's L_i compares .* got 16"):
        ModelConfig(nf=32, encoder_nf=16)
    assert ModelConfig(nf=32, encoder_nf=32).encoder_nf == 32


# ------------------------------------------------------------------- alignment losses
def brute_force(z, z_hat):
    n = z.shape[1]
    out = []
    for b in range(z.shape[0]):
        out.append(min(float(((z[b] - z_hat[b, list(p)]) ** 2).mean())
                       for p in itertools.permutations(range(n))))
    return float(np.mean(out))


@pytest.mark.parametrize("n", [2, 3, 5])
def test_hungarian_matches_brute_force(n):
    g = torch.Generator().manual_seed(n)
    z, z_hat = torch.randn(6, n, 8, generator=g), torch.randn(6, n, 8, generator=g)
    assert losses.alignment_loss(z, z_hat, "hungarian").item() == pytest.approx(
        brute_force(z, z_hat), rel=1e-5)


def test_permuted_codes_align_to_zero_and_mean_gives_one():
    z = torch.randn(4, 5, 64)
    perm = z[:, torch.tensor([3, 0, 4, 1, 2])]
    for m in ("hungarian", "greedy"):
        assert losses.alignment_loss(z, perm, m).item() == pytest.approx(0, abs=1e-7)
    assert losses.alignment_loss(z, perm, "ot").item() == pytest.approx(0, abs=1e-3)
    zz = torch.randn(512, 5, 128)
    assert losses.alignment_loss(zz, torch.zeros_like(zz)).item() == pytest.approx(1.0, abs=0.01)


def test_greedy_is_never_better_and_ot_is_close():
    g = torch.Generator().manual_seed(1)
    z, z_hat = torch.randn(200, 5, 4, generator=g), torch.randn(200, 5, 4, generator=g)
    exact = losses.alignment_loss(z, z_hat, "hungarian").item()
    greedy = losses.alignment_loss(z, z_hat, "greedy").item()
    ot = losses.alignment_loss(z, z_hat, "ot").item()
    assert greedy >= exact - 1e-6 and greedy > exact  # measurably worse on random sets
    assert exact - 1e-6 <= ot <= exact * 1.1


def test_alignment_gradient_reaches_the_encoder_codes():
    z = torch.randn(3, 4, 8)
    z_hat = torch.randn(3, 4, 8, requires_grad=True)
    losses.alignment_loss(z, z_hat).backward()
    assert z_hat.grad.abs().sum() > 0


def test_adversarial_losses():
    big = torch.full((4, 1), 20.0)
    assert losses.d_loss(big, -big).item() < 1e-6
    assert losses.g_loss(-big).item() > 10
    x = torch.randn(3, 1, 8, 8, requires_grad=True)
    logits = (x ** 2).sum((1, 2, 3))[:, None]
    expected = float((4 * x.detach() ** 2).sum((1, 2, 3)).mean())
    assert losses.r1_penalty(logits, x).item() == pytest.approx(expected, rel=1e-5)


def test_generators_share_one_interface():
    """Every generator decodes poses and z-buffers; the explicit ones (TemplateGenerator) also
    render given poses and expose their template's geometry, which test-time fitting uses; old
    checkpoints' retired config fields are ignored."""
    from inseggan_ros.runtime.model import (
        ConvexGenerator, PoseGenerator, SphereGenerator, TemplateGenerator, make_generator)

    learned = make_generator(ModelConfig(**SMALL))
    assert isinstance(learned, PoseGenerator) and not isinstance(learned, TemplateGenerator)
    for renderer, cls in (("spheres", SphereGenerator), ("convex", ConvexGenerator)):
        G = make_generator(ModelConfig(**{**SMALL, "renderer": renderer,
                                          "composite": "zbuffer"}))
        assert isinstance(G, cls) and isinstance(G, TemplateGenerator)
        z = torch.randn(2, 3, SMALL.get("latent_dim", 128))
        pose = G.pose(z.reshape(6, -1)).reshape(2, 3, 6)
        torch.testing.assert_close(G.render_poses(pose, 32, G.geometry()),
                                   G.render_instances(z, 32))
        x, feats = G(z, return_features=True)
        assert x.shape == (2, 1, 64, 64) and feats is None
    with pytest.raises(ValueError, match="use composite='zbuffer'"):
        ModelConfig(renderer="spheres", composite="average")
    old = {**ModelConfig(**SMALL).to_dict(), "template_size": 32}
    assert ModelConfig.from_dict(old) == ModelConfig(**SMALL)


def test_convex_template_renders_in_float32_under_mixed_precision():
    """Training on a GPU runs under bfloat16 autocast; the convex template's corner solves have
    no bfloat16 kernel there, and its heights are differences of plane distances: it renders
    in float32 whatever the autocast, the same as without it, and its gradients flow."""
    from inseggan_ros.runtime.model import make_generator

    G = make_generator(ModelConfig(**{**SMALL, "renderer": "convex", "composite": "zbuffer",
                                      "floor_contact": True}))
    z = torch.randn(2, 3, SMALL.get("latent_dim", 128))
    pose = G.pose(z.reshape(6, -1)).reshape(2, 3, 6).detach()
    plain = G.render_poses(pose, 32)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        mixed = G.render_poses(pose.bfloat16(), 32, G.geometry())
    assert mixed.dtype == torch.float32
    torch.testing.assert_close(mixed, G.render_poses(pose.bfloat16().float(), 32))
    mixed.mean().backward()
    assert G.extent.grad.abs().sum() > 0 and plain.dtype == torch.float32


def test_sphere_template_is_one_connected_object_whatever_its_parameters():
    """The rod of spheres cannot split: after arbitrary (here: random, large) parameters, every
    single-instance render of a rod lying above the floor is one connected blob, and the height
    map is exact for one sphere. (A rod partly sunk below the floor can show as two pieces where
    a small sphere between two large ones is under it: 7 of 320 renders over 40 seeds with the
    template's own lift, none with lift 1.)"""
    from scipy import ndimage

    from inseggan_ros.runtime.model import SphereGenerator, make_generator

    torch.manual_seed(0)
    cfg = ModelConfig(renderer="spheres", composite="zbuffer", spheres=6, **SMALL)
    G = make_generator(cfg)
    assert isinstance(G, SphereGenerator)
    z = torch.randn(4, 3, 16, requires_grad=True)
    x = G(z)
    x.mean().backward()
    assert z.grad.abs().sum() > 0
    for name in ("length", "log_radius", "radius_shape", "lift"):
        assert getattr(G, name).grad.abs().sum() > 0, f"{name} learns"
    with torch.no_grad():  # a wild template: very long, uneven radii
        G.length.fill_(5.0)
        G.radius_shape.normal_(0, 3.0)
        G.log_radius.fill_(math.log(0.1))
        centres, radii = G.spheres()
        G.lift.fill_(1.0)  # well above the floor
        gaps = (centres[1:] - centres[:-1]).norm(dim=1)
        assert (gaps < radii[1:] + radii[:-1]).all(), "consecutive spheres overlap"
        for img in G.render_instances(torch.randn(8, 3, 16)).flatten(0, 1):
            drawn = img > -0.9
            if drawn.sum() > 4:
                assert ndimage.label(drawn.numpy())[1] == 1
        # one sphere of radius r at height 0 (centre on the floor): a hemisphere of height r
        G1 = SphereGenerator(ModelConfig(renderer="spheres", composite="zbuffer", spheres=1,
                                         **SMALL))
        G1.lift.fill_(0.0)
        G1.radius_shape.fill_(50.0)  # factor 1
        G1.log_radius.fill_(math.log(0.4))
        G1.pose[-1].weight.zero_()  # identity pose at the image centre
        img = G1.render_instances(torch.zeros(1, 1, 16))[0, 0]
        top = (img.max() + 1) / 2 / (cfg.height_gain / 2)  # back to template units
        assert float(top) == pytest.approx(0.4, abs=0.01)
        assert float(img[0, 0]) == -1.0  # the floor far from it


def test_pyramid_l1_is_l1_at_one_level_and_sees_far_misses_at_coarse_ones():
    a = torch.full((1, 1, 16, 16), -1.0)
    b = a.clone()
    a[..., 0:2, 0:2] = 1.0  # a blob here
    b[..., 6:8, 6:8] = 1.0  # its target, not overlapping
    assert losses.pyramid_l1(a, b, 1).item() == pytest.approx(F.l1_loss(a, b).item())
    near = a.clone().roll((3, 3), (2, 3))  # closer, still not overlapping at full resolution
    assert losses.pyramid_l1(near, b, 1).item() == pytest.approx(losses.pyramid_l1(a, b, 1).item())
    assert losses.pyramid_l1(near, b, 4) < losses.pyramid_l1(a, b, 4)


def test_monotone_rod_profile_cannot_become_a_dumbbell():
    from inseggan_ros.runtime.model import SphereGenerator

    G = SphereGenerator(ModelConfig(renderer="spheres", composite="zbuffer", spheres=6,
                                    radius_profile="monotone", **SMALL))
    with torch.no_grad():
        for seed in range(5):
            G.radius_shape.copy_(torch.randn(6, generator=torch.Generator().manual_seed(seed)) * 5)
            _, r = G.spheres()
            assert (r[1:] <= r[:-1] + 1e-7).all() and (r[1:] >= 0.75 * r[:-1] - 1e-7).all()
    with pytest.raises(ValueError, match="radius_profile"):
        ModelConfig(renderer="spheres", composite="zbuffer", radius_profile="wavy")


def test_pyramid_l1_per_frame_averages_to_the_batch_loss():
    a, b = torch.randn(3, 1, 16, 16), torch.randn(3, 1, 16, 16)
    per = losses.pyramid_l1(a, b, 3, per_frame=True)
    assert per.shape == (3,)
    assert per.mean().item() == pytest.approx(losses.pyramid_l1(a, b, 3).item(), rel=1e-6)
    assert per[1].item() == pytest.approx(losses.pyramid_l1(a[1:2], b[1:2], 3).item(), rel=1e-6)


def test_fast_pooling_gives_the_same_numbers_as_avg_pool2d():
    """`pool2x2` (the test-time fit's pooling) is `F.avg_pool2d(x, 2)`, odd sides included;
    `refine._composite_loss`, which pools each input once for all its composites, is
    `pyramid_l1` per frame against the input repeated. (Bit for bit on the machines measured;
    compared here to float32 rounding, which is what another CPU's kernels may change.)"""
    from inseggan_ros.runtime.refine import _composite_loss

    gen = torch.Generator().manual_seed(0)
    for shape in [(200, 1, 32, 32), (3, 5, 16, 16), (2, 1, 7, 9), (1, 1, 64, 64)]:
        x = torch.randn(shape, generator=gen) * 100
        torch.testing.assert_close(losses.pool2x2(x), F.avg_pool2d(x, 2))
    B, K = 3, 40
    composite = torch.rand(B * K, 1, 32, 32, generator=gen) * 2 - 1
    target = torch.rand(B, 1, 32, 32, generator=gen) * 2 - 1
    expected = losses.pyramid_l1(composite, target.repeat_interleave(K, 0), 3, per_frame=True)
    torch.testing.assert_close(_composite_loss(composite, target), expected.reshape(B, K))
    with torch.no_grad():  # pyramid_l1 pools with pool2x2 without gradients: the same loss
        torch.testing.assert_close(losses.pyramid_l1(composite, target.repeat_interleave(K, 0),
                                                     3, per_frame=True), expected)


def test_floor_contact_lifts_a_sunken_rod_onto_the_floor():
    """With floor_contact a rod posed below the floor renders as the same rod lying on it (its
    lowest point at height 0); without it, it sinks out of sight."""
    from inseggan_ros.runtime.model import SphereGenerator

    def rod(floor_contact):
        G = SphereGenerator(ModelConfig(renderer="spheres", composite="zbuffer", spheres=4,
                                        floor_contact=floor_contact, **SMALL))
        with torch.no_grad():
            G.lift.fill_(0.0)
            G.radius_shape.fill_(50.0)  # all radii equal
            G.log_radius.fill_(math.log(0.2))
            G.length.fill_(0.4)
        return G

    on_floor = torch.tensor([[[0.0, 0.0, 0.0, 0.0, 0.0, 0.2]]])  # axis at height r: resting
    sunk = torch.tensor([[[0.0, 0.0, 0.0, 0.0, 0.0, -0.5]]])
    G = rod(True)
    with torch.no_grad():
        resting = G.render_poses(on_floor)
        assert torch.allclose(G.render_poses(sunk), resting)
        top = (resting.max() + 1) / 2 / (G.cfg.height_gain / 2)
        assert float(top) == pytest.approx(0.4, abs=0.025)  # 2 r (soft coverage: a bit less)
        floating = torch.tensor([[[0.0, 0.0, 0.0, 0.0, 0.0, 0.5]]])
        assert G.render_poses(floating).max() > resting.max()  # above the floor: unchanged
        assert (rod(False).render_poses(sunk) == -1).all()  # without: sunk out of sight


def test_multi_start_refinement_never_fits_worse_than_one_start():
    """Hypothesis 0 follows exactly the single-start trajectory (every scene is fitted on its
    own), so the best of several fits each frame at least as well; it is deterministic."""
    from inseggan_ros.runtime.model import make_generator
    from inseggan_ros.runtime.refine import refine_poses, start_poses

    torch.manual_seed(0)
    cfg = ModelConfig(renderer="spheres", composite="zbuffer", spheres=4, **SMALL)
    G, E = make_generator(cfg).eval(), Encoder(cfg).eval()  # E untrained: wrong first guesses
    for p in G.parameters():
        p.requires_grad_(False)
    with torch.no_grad():
        x = G.zbuffer(G.render_instances(torch.randn(4, 3, 16)))  # frames the model can draw

    def fit(pose):
        return losses.pyramid_l1(G.zbuffer(G.render_poses(pose, 32)),
                                 F.adaptive_avg_pool2d(x, 32), 3, per_frame=True)

    one = fit(refine_poses(G, start_poses(G, E, x, 1), x, 12))
    starts = start_poses(G, E, x, 6)  # the encoder's, 3 mirrored, 2 transposed
    assert starts.shape == (4, 6, 3, 6)
    assert torch.equal(start_poses(G, E, x, 10)[:, :6], starts)  # then 2 jittered
    assert torch.equal(starts[:, 0], start_poses(G, E, x, 1)[:, 0])
    multi_pose = refine_poses(G, starts, x, 12)
    multi = fit(multi_pose)
    assert (multi <= one + 1e-6).all()
    assert multi.sum() < one.sum()  # and here some frame did better
    assert torch.equal(multi_pose, refine_poses(G, start_poses(G, E, x, 6), x, 12))
    with pytest.raises(ValueError, match="hypotheses"):
        start_poses(G, E, x, 0)


def test_refining_only_the_best_fitting_start():
    """keep=1 chooses the start that fits best before refining it, and then refines exactly that
    one (the same poses as refining it alone); with 0 steps it is the choice alone."""
    from inseggan_ros.runtime.model import make_generator
    from inseggan_ros.runtime.refine import _fit_loss, refine_poses, start_poses

    torch.manual_seed(0)
    cfg = ModelConfig(renderer="spheres", composite="zbuffer", spheres=4, **SMALL)
    G, E = make_generator(cfg).eval(), Encoder(cfg).eval()
    for p in G.parameters():
        p.requires_grad_(False)
    with torch.no_grad():
        x = G.zbuffer(G.render_instances(torch.randn(4, 3, 16)))
    starts = start_poses(G, E, x, 4)
    fit = _fit_loss(G, starts, F.adaptive_avg_pool2d(x, 32), G.spheres())
    best = fit.argmin(1)
    assert len(set(best.tolist())) > 1 or (best > 0).any()  # the mirrors matter here
    chosen = starts[torch.arange(4), best]
    torch.testing.assert_close(refine_poses(G, starts, x, 0, keep=1), chosen)
    torch.testing.assert_close(refine_poses(G, starts, x, 6, keep=1),
                               refine_poses(G, chosen[:, None], x, 6))
    torch.testing.assert_close(refine_poses(G, starts, x, 6, keep=4), refine_poses(G, starts, x, 6))
    with pytest.raises(ValueError, match="keep"):
        refine_poses(G, starts, x, 6, keep=-1)
    torch.testing.assert_close(refine_poses(G, starts, x, 6, keep=0), refine_poses(G, starts, x, 6))


def _rod(length: float, radius: float):
    """A small rod of 4 spheres of a known length and radius, resting on the floor, in eval."""
    from inseggan_ros.runtime.model import make_generator

    G = make_generator(ModelConfig(renderer="spheres", composite="zbuffer", spheres=4,
                                   **SMALL)).eval()
    with torch.no_grad():
        G.length.fill_(length)
        G.log_radius.fill_(math.log(radius))
        G.lift.fill_(radius)
    return G


def test_instances_swapped_in_from_other_starts(monkeypatch):
    """Three starts that each read a different one of three rods right: the best of them alone
    explains one rod, two swaps bring the other two in from the other starts. The fit loss
    never rises with more swaps, and 0 swaps is the plain choice. With keep 1 the swaps come
    before the fit; with every start fitted (keep 0), after it, from the fitted starts. Frames
    swapped a few at a time (SWAP_CHUNK) give what one batch gives."""
    from inseggan_ros.runtime import refine
    from inseggan_ros.runtime.refine import _fit_loss, refine_poses

    torch.manual_seed(2)
    G = _rod(length=0.5, radius=0.2)
    with torch.no_grad():
        truth = torch.tensor([[-0.5, -0.5, 0.3, 0.0, 0.0, 0.0], [0.5, 0.0, 1.2, 0.0, 0.0, 0.0],
                              [-0.3, 0.5, -0.7, 0.0, 0.0, 0.0]]).repeat(2, 1, 1)  # (2, 3, 6)
        x = G.zbuffer(G.render_poses(truth))
        off = torch.tensor([0.9, 0.9, 0.0, 0.0, 0.0, 0.0])  # a rod in the bin's far corner
        starts = off.repeat(2, 3, 3, 1)  # (B, H, n, 6): start h has rod h right
        for h in range(3):
            starts[:, h, h] = truth[:, h]
        target = F.adaptive_avg_pool2d(x, 32)
        template = G.spheres()

        def fit(pose):
            return _fit_loss(G, pose[:, None], target, template)[:, 0]

        plain = refine_poses(G, starts, x, 0, keep=1)
        torch.testing.assert_close(refine_poses(G, starts, x, 0, keep=1, swaps=0), plain)
        by_swaps = [fit(refine_poses(G, starts, x, 0, keep=1, swaps=k)) for k in range(4)]
        for before, after in zip(by_swaps, by_swaps[1:]):
            assert (after <= before + 1e-6).all()
        assert (by_swaps[2] <= fit(truth) + 1e-6).all()  # every rod explained after two
        assert (by_swaps[2] < _fit_loss(G, starts, target, template).min(1).values).all()
        with pytest.raises(ValueError, match="swaps"):
            refine_poses(G, starts, x, 0, keep=1, swaps=-1)
        # keep 1 and a fit: the swapped set is what is refined
        torch.testing.assert_close(
            refine_poses(G, starts, x, 4, keep=1, swaps=2),
            refine_poses(G, refine_poses(G, starts, x, 0, keep=1, swaps=2)[:, None], x, 4))
        # keep 0: without a fit the same swaps; with one, never worse than the fitted choice
        torch.testing.assert_close(refine_poses(G, starts, x, 0, keep=0, swaps=2),
                                   refine_poses(G, starts, x, 0, keep=1, swaps=2))
        fitted = fit(refine_poses(G, starts, x, 4, keep=0))
        assert (fit(refine_poses(G, starts, x, 4, keep=0, swaps=2)) <= fitted + 1e-6).all()
        # chunks of one frame: the same poses (the second frame's starts differ)
        starts[1] += 0.05 * torch.randn(starts[1].shape)
        whole = [refine_poses(G, starts, x, 0, keep=k, swaps=2) for k in (1, 0)]
        monkeypatch.setattr(refine, "SWAP_CHUNK", 1)
        for k, w in zip((1, 0), whole):
            torch.testing.assert_close(refine_poses(G, starts, x, 0, keep=k, swaps=2), w)
        assert not torch.equal(whole[0][0], whole[0][1])  # two different frames were chunked
    from inseggan_ros.core.settings import InferenceConfig

    InferenceConfig(refine_hypotheses=8, refine_keep=0, refine_swaps=4)
    with pytest.raises(ValueError, match="refine_swaps -1 invalid"):
        InferenceConfig(refine_keep=1, refine_swaps=-1)


def test_inference_config_validates_and_reads_old_checkpoints():
    from inseggan_ros.core.settings import InferenceConfig, SmoothConfig, apply

    old = InferenceConfig.from_dict({"refine_steps": 30, "hypotheses": 4})  # pre-smoothing models
    assert old == InferenceConfig(refine_steps=30, refine_hypotheses=4, refine_keep=0,
                                  smooth=SmoothConfig(iters=0))
    cfg = InferenceConfig(refine_steps=48, refine_hypotheses=8, refine_keep=2,
                          smooth=SmoothConfig(iters=20, full_res_iters=0))
    assert InferenceConfig.from_dict(cfg.to_dict()) == cfg
    assert apply(cfg, {"smooth_iters": 5}).smooth == SmoothConfig(iters=5, full_res_iters=0)
    for bad, match in (({"refine_steps": -1}, "refine_steps -1 invalid"),
                       ({"refine_hypotheses": 0}, "refine_hypotheses 0 invalid; valid: >= 1"),
                       ({"refine_keep": -2}, "refine_keep -2 invalid"),
                       ({"superpixel_scale": -1}, "superpixel_scale -1 invalid; valid: >= 0"),
                       ({"split_scale": -800}, "split_scale -800 invalid; valid: >= 0")):
        with pytest.raises(ValueError, match=match):
            InferenceConfig(**bad)
    with pytest.raises(ValueError, match="smooth_full_res_iters"):
        SmoothConfig(full_res_iters=-1)
    with pytest.raises(ValueError, match="encoder_precision 'half' invalid; valid: float32, "
                                         "bfloat16, auto"):
        InferenceConfig(encoder_precision="half")
    with pytest.raises(ValueError, match="centre_precision 'half' invalid; valid: float32, "
                                         "bfloat16, auto"):
        InferenceConfig(centre_precision="half")
    assert old.encoder_precision == old.centre_precision == "float32"
    fast = InferenceConfig(encoder_precision="auto")
    assert InferenceConfig.from_dict(fast.to_dict()) == fast
    with pytest.raises(ValueError, match="unknown inference settings"):
        InferenceConfig.from_dict({"refine_stpes": 3})


def test_settings_have_one_name_as_field_parameter_and_flag():
    """Every exposed setting is a field (smooth_<field> inside smooth), a node parameter and a
    flag of the same name; a parameters file and flags apply through that one table."""
    import argparse

    from inseggan_ros.core import settings

    names = [s.name for s in settings.exposed()]
    assert names == ["refine_steps", "refine_hypotheses", "refine_keep", "refine_swaps",
                     "smooth_iters",
                     "smooth_full_res_iters", "encoder_precision", "superpixel_scale",
                     "split_scale", "label_head", "centre_votes", "centre_precision",
                     "centre_superpixel_scale"]
    parser = argparse.ArgumentParser()
    settings.add_flags(parser, "(default: the model's)")
    args = parser.parse_args(["--refine-hypotheses", "8", "--smooth-full-res-iters", "0",
                              "--encoder-precision", "auto"])
    cfg = settings.apply(settings.InferenceConfig(), settings.from_flags(args))
    assert (cfg.refine_hypotheses, cfg.smooth.full_res_iters,
            cfg.encoder_precision) == (8, 0, "auto")
    assert settings.values(cfg)["refine_hypotheses"] == 8
    assert settings.apply(cfg, {"roi": [1, 2, 3, 4], "smooth_iters": 3}).smooth.iters == 3
    with pytest.raises(ValueError, match="refine_keep -1 invalid"):
        settings.apply(cfg, {"refine_keep": -1})


def test_a_cards_profile_row_is_what_the_node_runs_with_that_file(tmp_path):
    """`--also-profile FILE` (the cards' other rows) applies the file to the settings the model
    ships, as the segmenter node applies a --params-file to the model's own: what the file
    leaves out stays the model's, what it names wins. fastest.yaml turns the vote and the split
    off by name, so its row and the node agree for every model."""
    import argparse

    from inseggan_ros.core import settings
    from inseggan_ros.cli.common import also_profiles

    config = Path(__file__).resolve().parents[1] / "config"
    partial = tmp_path / "partial.yaml"
    partial.write_text("/**/segmenter:\n  ros__parameters:\n    refine_steps: 4\n")
    base = settings.InferenceConfig(refine_hypotheses=8, refine_keep=1, superpixel_scale=160,
                                    split_scale=800)
    files = [config / "fastest.yaml", config / "quality.yaml", partial]
    rows = also_profiles(argparse.Namespace(also_profile=files), base)
    assert (rows["partial"].refine_steps, rows["partial"].superpixel_scale,
            rows["partial"].refine_hypotheses) == (4, 160, 8)
    assert (rows["fastest"].superpixel_scale, rows["fastest"].split_scale) == (0, 0)
    quality = settings.read_params_file(config / "quality.yaml")
    assert "superpixel_scale" not in quality and "split_scale" not in quality
    assert (rows["quality"].superpixel_scale, rows["quality"].split_scale) == (160, 800)
    assert rows["quality"].refine_steps == quality["refine_steps"] > 0
    assert also_profiles(argparse.Namespace(also_profile=None), base) == {}


def test_a_parameters_file_applies_over_realtime_for_a_checkpoint_without_settings(tmp_path):
    """A training checkpoint stores no settings. A parameters file then applies over
    realtime.yaml's (what every exported model starts from), not over the bare built-in
    defaults: quality.yaml, which leaves the vote's and the split's scales to the model, keeps
    them on for it, in `inseggan eval --profile`, the self-fitting's labels and the node; a
    model that stores its own scale keeps it."""
    import argparse

    from conftest import checkpoint_without_settings

    from inseggan_ros.core import settings
    from inseggan_ros.runtime.segment import Segmenter
    from inseggan_ros.learning.selffit import _settings

    config = Path(__file__).resolve().parents[1] / "config"
    realtime = settings.read_params_file(config / "realtime.yaml")
    shipped = Path(__file__).resolve().parents[1] / "models" / "cylinder" / "model.pt"
    bare = checkpoint_without_settings(tmp_path / "bare.pt")

    seg = Segmenter.from_checkpoint(bare, device="cpu")
    assert not seg.stored_settings and seg.inference.superpixel_scale == 0  # bare defaults
    assert Segmenter.from_checkpoint(shipped, device="cpu").stored_settings
    args = argparse.Namespace(profile="quality")
    for cfg in (settings.resolve(seg.inference, args, seg.stored_settings),
                _settings(bare, "quality", tau=-0.5)[1]):
        assert (cfg.superpixel_scale, cfg.split_scale) == (realtime["superpixel_scale"],
                                                           realtime["split_scale"])
        assert (cfg.refine_steps, cfg.refine_swaps) == (48, 4)
    # no file: the bare settings stay what the checkpoint gives (eval's --refine-steps etc.)
    assert settings.resolve(seg.inference, argparse.Namespace(), False) == seg.inference
    # a model that stores its own scale keeps it under the same file
    own = settings.apply(seg.inference, {**realtime, "superpixel_scale": 160})
    assert settings.apply_file(own, "quality").superpixel_scale == 160


def test_a_bfloat16_encoder_gives_the_float32_labels():
    """The shipped cylinder model on bins it draws itself: the encoder in bfloat16 (native or
    not) segments as in float32, up to a few pixels."""
    from inseggan_ros.runtime.precision import native_bfloat16
    from inseggan_ros.runtime.segment import InferenceConfig, Segmenter

    path = Path(__file__).resolve().parents[1] / "models" / "cylinder" / "model.pt"
    seg = Segmenter.from_checkpoint(path, device="cpu")
    torch.manual_seed(0)
    with torch.no_grad():
        x = seg.G.zbuffer(seg.G.render_instances(torch.randn(6, 5, seg.model_cfg.latent_dim)))
    cfg = InferenceConfig(refine_steps=0, refine_hypotheses=8, refine_keep=1)
    a = seg.segment_batch(x, settings=cfg)["labels"]
    b = seg.segment_batch(
        x, settings=replace(cfg, encoder_precision="bfloat16"))["labels"]
    assert (a != b).float().mean() < 0.01
    assert seg.resolve_precision("auto") == ("bfloat16" if native_bfloat16("cpu") else "float32")
    assert seg.encoder("bfloat16") is seg.encoder("bfloat16")  # one copy of the weights
    assert seg.encoder("float32") is seg.E
    # its copy's channels-last layout (faster with native bfloat16) gives a plain bfloat16
    # copy's codes, up to bfloat16 rounding
    plain = copy.deepcopy(seg.E).to(torch.bfloat16)
    with torch.no_grad():
        codes, want = seg.encoder("bfloat16")(x), plain(x.to(torch.bfloat16)).float()
    torch.testing.assert_close(codes, want, rtol=0.02, atol=0.02 * float(want.abs().max()))


def test_a_bfloat16_centre_net_gives_the_float32_labels():
    """The shipped cylinder model's centre votes on bins it draws itself: the net in bfloat16
    (native or not), its last layer in float32, labels as in float32 up to a few pixels; one
    copy of its weights, and float32 the net itself."""
    from inseggan_ros.runtime.precision import CastCentreNet
    from inseggan_ros.runtime.segment import Segmenter

    path = Path(__file__).resolve().parents[1] / "models" / "cylinder" / "model.pt"
    seg = Segmenter.from_checkpoint(path, device="cpu")
    torch.manual_seed(1)
    with torch.no_grad():
        x = seg.G.zbuffer(seg.G.render_instances(torch.randn(8, 5, seg.model_cfg.latent_dim)))
    fg = x[:, 0] > -1 + 1e-4
    a, b = (seg.centre_votes(x, fg, 5, p) for p in ("float32", "bfloat16"))
    cfg = replace(seg.inference, centre_votes="on", encoder_precision="float32")
    for precision, want in (("float32", a), ("bfloat16", b)):  # the setting picks the net
        got = seg.model_labels(x, fg, settings=replace(cfg, centre_precision=precision))
        assert torch.equal(got["labels"], seg.model_labels(
            x, fg, settings=cfg, centres=want)["labels"])
    assert (a != b).float().mean() < 0.01
    assert (a[fg] > 0).all() and len(a.unique()) > 2, "the votes found instances"
    net = seg.centre_net_in("bfloat16")
    assert isinstance(net, CastCentreNet) and net is seg.centre_net_in("bfloat16")
    assert net.net.e1[0][0].weight.dtype == torch.bfloat16
    assert net.net.out.weight.dtype == torch.float32
    assert seg.centre_net_in("float32") is seg.centre_net
    assert seg.centre_net.out.weight.dtype == torch.float32, "the copy left the net as it was"


def test_levenberg_marquardt_refinement_recovers_known_poses():
    """Frames drawn from known poses, fitted from nudged poses: the fitting loss never rises
    from one iteration to the next, and the fit ends far closer to the frames than it began
    (the scene's renders match; poses themselves are ambiguous under the rod's symmetry)."""
    from inseggan_ros.runtime.refine import _lm_fit, _pyramid_features

    torch.manual_seed(1)
    G = _rod(length=0.6, radius=0.25)
    with torch.no_grad():
        truth = torch.randn(6, 3, 6) * torch.tensor([0.3, 0.3, 1.5, 0.5, 0.5, 0.02])
        template = G.spheres()
        target = _pyramid_features(G.render_poses(truth, 32, template).amax(1, keepdim=True))
        start = truth + torch.randn(truth.shape) * torch.tensor([0.1, 0.1, 0.2, 0.06, 0.06, 0.02])

        def loss(pose):
            return (_pyramid_features(G.render_poses(pose, 32, template).amax(1, keepdim=True))
                    - target).abs().sum(1)

        losses_by_iter = [loss(_lm_fit(G, start, target, k, 32, template)) for k in range(0, 9, 2)]
    for before, after in zip(losses_by_iter, losses_by_iter[1:]):
        assert (after <= before + 1e-6).all()
    assert (losses_by_iter[-1] < 0.2 * losses_by_iter[0]).all()


@pytest.mark.parametrize("profile", ["free", "monotone"])
def test_transformed_poses_render_the_transformed_image(profile):
    """Under each of the 8 symmetries of the square (mirrored, transposed), the mapped poses
    render the transformed image, and the inverse mapping brings them back: exact for any
    solid of revolution, a rod with a thicker head (monotone radii) too."""
    from inseggan_ros.runtime.model import make_generator
    from inseggan_ros.runtime.symmetry import SYMMETRIES, transform_image, transform_poses

    cfg = ModelConfig(renderer="spheres", composite="zbuffer", spheres=4, radius_profile=profile,
                      **SMALL)
    G = make_generator(cfg)
    assert len(set(SYMMETRIES)) == 8
    with torch.no_grad():
        G.radius_shape.copy_(torch.tensor([50.0, -3.0, -3.0, -3.0]))  # a head at one end
        pose = torch.randn(2, 3, 6) * torch.tensor([0.8, 0.8, 0.8, 0.3, 0.3, 0.1])
        img = G.render_poses(pose)
        for sym in SYMMETRIES:
            moved = transform_poses(pose, sym)
            assert (G.render_poses(moved) - transform_image(img, sym)).abs().max() < 1e-4, sym
            back = G.render_poses(transform_poses(moved, sym, inverse=True))
            assert (back - img).abs().max() < 1e-4, sym


def test_written_out_adam_matches_torch_adam():
    from inseggan_ros.runtime.refine import _adam_fit

    target = torch.linspace(-1, 1, 12).reshape(2, 6)
    start = torch.zeros(2, 6)

    def loss_of(p):
        return ((p - target) ** 2 * torch.arange(1, 7.0)).sum() + p.abs().sum()

    ours = _adam_fit(start, loss_of, 25, lr=0.06)
    p = start.clone().requires_grad_(True)
    opt = torch.optim.Adam([p], lr=0.06)
    for _ in range(25):
        opt.zero_grad()
        loss_of(p).backward()
        opt.step()
    torch.testing.assert_close(ours, p.detach(), rtol=0, atol=1e-6)
    assert loss_of(ours) < loss_of(start)


def test_a_rod_of_more_spheres_can_be_longer_for_its_thickness():
    """`--spheres`: consecutive spheres must overlap, so a rod of K spheres is at most about
    K / 2 times as long as it is thick. The bolt (46 mm long, 10 mm shaft: 4.6) is beyond a
    rod of 6 and within one of 12."""
    from inseggan_ros.runtime.model import SphereGenerator

    def longest(k):
        G = SphereGenerator(ModelConfig(renderer="spheres", composite="zbuffer", spheres=k,
                                        radius_profile="monotone", **SMALL))
        with torch.no_grad():
            G.length.fill_(100.0)  # asks for far more than the overlap allows
            G.radius_shape.fill_(50.0)  # even radii
            centres, radii = G.spheres()
        span = float(centres[-1, 0] - centres[0, 0] + radii[0] + radii[-1])
        return span / float(2 * radii.min())

    assert longest(6) == pytest.approx((0.95 * 5 + 2) / 2, rel=1e-3)
    assert longest(6) < 4.6 < longest(12)


@pytest.mark.parametrize("floor_contact", [False, True])
def test_sphere_renders_at_inference_are_those_of_training(floor_contact):
    """The rod renderer computes in place when no gradient is wanted (inference): the same
    renders as the autograd path, for poses anywhere, at both sizes the pipeline uses."""
    from inseggan_ros.runtime.model import SphereGenerator

    torch.manual_seed(0)
    G = SphereGenerator(ModelConfig(renderer="spheres", composite="zbuffer", spheres=6,
                                    floor_contact=floor_contact, **SMALL))
    with torch.no_grad():
        G.radius_shape.normal_(0, 1.0)
    axis = F.normalize(torch.randn(8, 5, 3), dim=-1)
    t = torch.randn(8, 5, 3) * 0.4
    for size in (32, 64):
        with torch.enable_grad():
            want = G.render_axes(axis, t, size)
        assert want.requires_grad  # the autograd path, whose parameters learn
        with torch.no_grad():
            got = G.render_axes(axis, t, size)
        assert got.shape == (8, 5, size, size)
        torch.testing.assert_close(got, want.detach(), rtol=0, atol=1e-6)
        assert (want > -1).float().mean() > 0.05, "the rods are drawn"
