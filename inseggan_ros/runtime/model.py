"""InSeGAN (Cherian et al., ICCV 2021) in plain PyTorch: generator, discriminator, encoder.

Images are 64x64 depth maps in [-1, 1] (bin floor at -1). A scene is n latent codes z_i ~ N(0, I_d).

Generator G = renderer o compose o F:
  * pose decoder Gp: z -> axis-angle rotation + translation -> [R | t] (Rodrigues);
  * implicit template: a learned (nf, 4, 4, 4) tensor, upsampled by 3D ResBlocks to (nf/4, 16^3);
    it does not depend on z, so it is computed once per batch;
  * STN: the template resampled by [R | t] (affine_grid + grid_sample, trilinear);
  * instance feature F(z): two 3D convs, depth folded into channels, one 2D conv -> (2nf, 16, 16);
  * compose + render. `composite="average"` is the paper: average the n feature maps, render once
    (ConvTranspose x2 + tanh). `composite="zbuffer"` renders every instance alone with the same
    renderer and keeps, per pixel, the nearest (max) depth: exactly what inference does, so
    training and test see the same thing (in training a soft max, so that hidden instances
    still get gradient).
Discriminator D: 4 strided convs (InstanceNorm, LeakyReLU 0.2) and a 4x4 conv to one logit.
Encoder E: the same trunk; its first two convs ("derenderer") give a (2nf, 16, 16) map that is
compared with the generator's mean instance feature; the rest gives n x d codes.
Nothing here imports ROS or the rest of the package.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import torch
import torch.nn as nn
import torch.nn.functional as F

from inseggan_ros.core import checkpoint


RENDERERS = ("learned", "spheres", "convex")
RETIRED_FIELDS = ("template_size",)  # ModelConfig fields that old checkpoints may hold


@dataclass(frozen=True)
class ModelConfig:
    n_instances: int = 5
    latent_dim: int = 128
    nf: int = 64
    encoder_nf: int = 0  # the encoder's width (0: nf); a narrower one is faster at test time
    image_size: int = 64
    composite: str = "average"  # "average" (paper) or "zbuffer" (render alone, nearest wins)
    rotation_std: float = 1.0  # initial spread of decoded rotations, radians
    translation_std: float = 0.35  # initial spread of decoded translations, affine-grid units
    spectral_norm: bool = False  # spectral normalisation in the discriminator
    zbuffer_temperature: float = 0.05  # training composite: softmax(d_i / T)-weighted depths
    render_bias: float = 0.0  # initial bias of the renderer's last layer (-2.5: floor prior)
    renderer: str = "learned"  # "learned" (paper: 3D convs + 2D decoder), "spheres", "convex"
    spheres: int = 6  # spheres on the template rod ("spheres" renderer)
    coord_conv: bool = False  # the encoder also sees pixel coordinates (CoordConv)
    radius_profile: str = "free"  # rod radii: "free" (each in 0.5-1 x the largest) or
    # "monotone" (each at most 25 % smaller than the one before: cylinders, cones, bolts; no
    # dumbbells)
    height_gain: float = 1.8  # bin-crop width / max_height: template z units -> image heights
    floor_contact: bool = False  # an instance reaching below the floor is lifted until its
    # lowest point touches it (objects lie on the floor or on each other): for "spheres" the
    # lowest sphere, for "convex" the lowest corner
    pieces: int = 4  # "convex": convex pieces in the template's union
    walls: int = 4  # "convex": side planes of each piece (besides its top and bottom): 4 make
    # a box, and with each piece's own orientation and tilts a nut's sectors; 8 an octagon

    def __post_init__(self):
        if self.image_size != 64:
            raise ValueError("image_size must be 64 (the architecture's size), got "
                             f"{self.image_size}")
        if self.nf < 8 or self.nf % 8:
            raise ValueError(f"nf must be a multiple of 8 and >= 8, got {self.nf}")
        if self.encoder_nf != 0 and (self.encoder_nf < 8 or self.encoder_nf % 8):
            raise ValueError(f"encoder_nf must be 0 (= nf) or a multiple of 8 and >= 8, got "
                             f"{self.encoder_nf}")
        if self.latent_dim < 8 or self.latent_dim % 4:
            raise ValueError(f"latent_dim must be a multiple of 4 and >= 8, got {self.latent_dim}")
        if not 1 <= self.n_instances <= 20:
            raise ValueError(f"n_instances must be in 1..20, got {self.n_instances}")
        if self.composite not in ("average", "zbuffer"):
            raise ValueError(f"composite {self.composite!r} invalid; valid: average, zbuffer")
        if self.renderer not in RENDERERS:
            raise ValueError(f"renderer {self.renderer!r} invalid; valid: {', '.join(RENDERERS)}")
        if self.renderer == "learned" and self.encoder_nf not in (0, self.nf):
            raise ValueError("the learned renderer's L_i compares encoder and generator features: "
                             f"encoder_nf must be 0 or nf ({self.nf}), got {self.encoder_nf}")
        if self.renderer != "learned" and self.composite != "zbuffer":
            raise ValueError(f"the {self.renderer} renderer has no features to average: use "
                             "composite='zbuffer'")
        if self.radius_profile not in ("free", "monotone"):
            raise ValueError(f"radius_profile {self.radius_profile!r} invalid; valid: free, "
                             "monotone")
        if not 1 <= self.spheres <= 256:
            raise ValueError(f"spheres must be in 1..256, got {self.spheres}")
        if not 1 <= self.pieces <= 16:
            raise ValueError(f"pieces must be in 1..16, got {self.pieces}")
        if self.walls < 4 or self.walls % 4:
            raise ValueError(f"walls must be a multiple of 4 and >= 4 (a box needs 4), got "
                             f"{self.walls}")

    def to_dict(self) -> dict:
        return asdict(self)

    @staticmethod
    def from_dict(d: dict) -> "ModelConfig":
        """From a checkpoint's record; fields of retired experiments (the occupancy-grid
        template's `template_size`) are ignored."""
        return ModelConfig(**{k: v for k, v in d.items() if k not in RETIRED_FIELDS})


def init_weights(module: nn.Module) -> None:
    """Conv weights N(0, 0.02), as the paper's reference code."""
    for m in module.modules():
        if isinstance(m, (nn.Conv2d, nn.Conv3d, nn.ConvTranspose2d, nn.Linear)):
            nn.init.normal_(m.weight, 0.0, 0.02)
            if m.bias is not None:
                nn.init.zeros_(m.bias)


def rodrigues(axis_angle: torch.Tensor) -> torch.Tensor:
    """(B, 3) axis-angle -> (B, 3, 3) rotation matrices."""
    theta = axis_angle.norm(dim=1, keepdim=True).clamp_min(1e-8)
    kx, ky, kz = (axis_angle / theta).unbind(1)
    zero = torch.zeros_like(kx)
    K = torch.stack([zero, -kz, ky, kz, zero, -kx, -ky, kx, zero], 1).view(-1, 3, 3)
    s, c = torch.sin(theta)[..., None], torch.cos(theta)[..., None]
    eye = torch.eye(3, device=axis_angle.device, dtype=axis_angle.dtype).expand_as(K)
    return eye + s * K + (1 - c) * (K @ K)


def pose_matrix(p: torch.Tensor) -> torch.Tensor:
    """(M, 6) axis-angle rotation + translation (the pose decoder's output) -> (M, 3, 4) [R | t]."""
    return torch.cat([rodrigues(p[:, :3]), p[:, 3:, None]], dim=2)


def pose_features(theta: torch.Tensor) -> torch.Tensor:
    """(M, 3, 4) [R | t] of rod templates -> (M, 9): translation and the axis (template x in
    the world) up to sign, as the 6 distinct entries of a a^T: all that a render depends on."""
    a = theta[:, :, 0]
    i, j = torch.triu_indices(3, 3)
    return torch.cat([theta[:, :, 3], (a[:, :, None] * a[:, None, :])[:, i, j]], dim=1)


def pose_from_axis(axis: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """(..., 3) unit axes and (..., 3) translations -> (..., 6) poses whose rotation is the
    shortest one taking the template's x axis onto `axis` (for templates that are solids of
    revolution about x, every rotation with that axis renders the same)."""
    ex = torch.zeros_like(axis)
    ex[..., 0] = 1
    w = torch.cross(ex, axis, dim=-1)
    s = w.norm(dim=-1, keepdim=True)
    angle = torch.atan2(s, axis[..., :1])
    half_turn = torch.zeros_like(axis)
    half_turn[..., 2] = torch.pi  # axis = -x: any half turn about an axis normal to x
    w = torch.where(s > 1e-7, w / s.clamp_min(1e-12) * angle,
                    torch.where(axis[..., :1] > 0, torch.zeros_like(axis), half_turn))
    return torch.cat([w, t], -1)


def pose_decoder(d: int) -> nn.Sequential:
    """MLP code -> 6 pose numbers: d -> d/2 -> d/4 -> 6 as the paper (d = 128), LeakyReLU, no
    bias; at least 64 -> 32 hidden units for small codes."""
    h1, h2 = max(d // 2, 64), max(d // 4, 32)
    return nn.Sequential(nn.Linear(d, h1, bias=False), nn.LeakyReLU(0.2),
                         nn.Linear(h1, h2, bias=False), nn.LeakyReLU(0.2),
                         nn.Linear(h2, 6, bias=False))


class ResBlock3d(nn.Module):
    def __init__(self, cin: int, cout: int):
        super().__init__()
        self.body = nn.Sequential(
            nn.InstanceNorm3d(cin), nn.LeakyReLU(0.2), nn.Conv3d(cin, cout, 3, 1, 1),
            nn.InstanceNorm3d(cout), nn.LeakyReLU(0.2), nn.Conv3d(cout, cout, 3, 1, 1))
        self.bypass = nn.Conv3d(cin, cout, 1)

    def forward(self, x):
        return self.body(x) + self.bypass(x)


class PoseGenerator(nn.Module):
    """What every generator shares: codes z_i -> poses (the pose decoder G_p, its initial
    spread), single-instance renders z-buffered into a scene. Subclasses render."""

    template_parameters: tuple[str, ...] = ()  # explicit template: its own learning rate

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        self.cfg = cfg
        self.pose = pose_decoder(cfg.latent_dim)

    def render_instances(self, z: torch.Tensor) -> torch.Tensor:
        """(B, n, d) codes -> (B, n, 64, 64): every instance rendered alone."""
        raise NotImplementedError

    @torch.no_grad()
    def _spread_poses(self) -> None:
        """Rescale the pose decoder's last layer so that initial poses spread over the bin.

        With N(0, 0.02) weights every decoded pose is ~0: all instances land in one place and
        training collapses (measured on a prototype); rotations ~1 rad and translations ~0.35
        grid units apart gave a run that learned.
        """
        z = torch.randn(4096, self.cfg.latent_dim, generator=torch.Generator().manual_seed(0))
        h = self.pose[:-1](z)
        std = self.pose[-1](h).std(0).clamp_min(1e-8)
        target = torch.tensor([self.cfg.rotation_std] * 3 + [self.cfg.translation_std] * 3)
        self.pose[-1].weight.mul_((target / std)[:, None])

    def poses(self, z: torch.Tensor) -> torch.Tensor:
        """(M, d) codes -> (M, 3, 4) affine [R | t] for the spatial transformer."""
        return pose_matrix(self.pose(z))

    def alignment_features(self, z: torch.Tensor) -> torch.Tensor:
        """(B, n, d) codes -> what the encoder's alignment loss L_a compares: the codes
        themselves (the paper)."""
        return z

    def zbuffer(self, singles: torch.Tensor) -> torch.Tensor:
        """(B, n, H, W) single-instance renders -> (B, 1, H, W): per pixel the nearest surface
        (largest height) wins. In training a soft max, so that every instance gets gradient,
        weighted by how near it is; where all renders agree (background) it equals them."""
        if self.training and self.cfg.zbuffer_temperature > 0:
            w = torch.softmax(singles / self.cfg.zbuffer_temperature, dim=1)
            return (w * singles).sum(dim=1, keepdim=True)
        return singles.amax(dim=1, keepdim=True)


class Generator(PoseGenerator):
    """The paper's generator: a learned implicit 3D template posed by a spatial transformer,
    3D and 2D convolutions, a learned depth renderer; instance features averaged (the paper)
    or each instance rendered and z-buffered."""

    def __init__(self, cfg: ModelConfig):
        super().__init__(cfg)
        nf = cfg.nf
        self.template = nn.Parameter(torch.randn(1, nf, 4, 4, 4))
        self.template_net = nn.Sequential(
            ResBlock3d(nf, nf // 2), nn.Upsample(scale_factor=2, mode="nearest"),
            nn.InstanceNorm3d(nf // 2, affine=True),
            ResBlock3d(nf // 2, nf // 4), nn.Upsample(scale_factor=2, mode="nearest"),
            nn.InstanceNorm3d(nf // 4, affine=True))
        self.feature3d = nn.Sequential(
            nn.Conv3d(nf // 4, nf // 8, 3, 1, 1), nn.InstanceNorm3d(nf // 8, affine=True),
            nn.ReLU(),
            nn.Conv3d(nf // 8, nf // 8, 3, 1, 1), nn.InstanceNorm3d(nf // 8, affine=True),
            nn.ReLU())
        self.feature2d = nn.Sequential(
            nn.Conv2d(nf // 8 * 16, 2 * nf, 3, 1, 1), nn.InstanceNorm2d(2 * nf, affine=True),
            nn.ReLU())
        self.renderer = nn.Sequential(
            nn.ConvTranspose2d(2 * nf, nf, 4, 2, 1), nn.InstanceNorm2d(nf, affine=True), nn.ReLU(),
            nn.ConvTranspose2d(nf, 1, 4, 2, 1), nn.Tanh())
        init_weights(self)
        self._spread_poses()
        # floor prior: every single-instance render starts out as bin floor (tanh(-2.5) = -0.99),
        # so the composite's background is right from the start and only objects must be learned
        nn.init.constant_(self.renderer[-2].bias, cfg.render_bias)

    def instance_features(self, z: torch.Tensor) -> torch.Tensor:
        """(B, n, d) codes -> (B, n, 2nf, 16, 16) single-instance feature maps F(z_i)."""
        B, n, d = z.shape
        volume = self.template_net(self.template)  # (1, C, 16, 16, 16), once per batch
        theta = self.poses(z.reshape(B * n, d)).to(volume.dtype)
        C = volume.shape[1]
        grid = F.affine_grid(theta, [B * n, C, 16, 16, 16], align_corners=True)
        v = volume.expand(B * n, -1, -1, -1, -1).contiguous(memory_format=torch.channels_last_3d)
        v = F.grid_sample(v, grid, mode="bilinear", padding_mode="zeros", align_corners=True)
        v = self.feature3d(v.contiguous(memory_format=torch.channels_last_3d))
        f = self.feature2d(v.reshape(B * n, -1, 16, 16).contiguous())
        return f.reshape(B, n, *f.shape[1:])

    def render(self, features: torch.Tensor) -> torch.Tensor:
        """(M, 2nf, 16, 16) -> (M, 1, 64, 64) depth in [-1, 1]."""
        return self.renderer(features)

    def _render_each(self, f: torch.Tensor) -> torch.Tensor:
        """(B, n, 2nf, 16, 16) -> (B, n, 64, 64): every instance rendered alone."""
        B, n = f.shape[:2]
        return self.render(f.flatten(0, 1)).reshape(B, n, self.cfg.image_size, self.cfg.image_size)

    def render_instances(self, z: torch.Tensor) -> torch.Tensor:
        """(B, n, d) -> (B, n, 64, 64): every instance rendered alone (inference)."""
        return self._render_each(self.instance_features(z))

    def forward(self, z: torch.Tensor, return_features: bool = False):
        """(B, n, d) -> (B, 1, 64, 64) multi-instance depth (and the mean instance feature)."""
        f = self.instance_features(z)
        mean_f = f.mean(1)
        if self.cfg.composite == "average":
            x = self.render(mean_f)
        else:
            x = self.zbuffer(self._render_each(f))
        return (x, mean_f) if return_features else x


class TemplateGenerator(PoseGenerator):
    """Generators with an explicit template whose top-down height map is closed form: each
    instance is rendered alone from its pose (`render_poses`) and the scene z-buffered, in
    training as at test time; test-time pose fitting (`refine.py`) moves their poses.
    Units: the 64 x 64 image spans [-1, 1] in x and y, heights use the same unit (so rotations
    are rigid) and 2 / height_gain of them map to +1."""

    def __init__(self, cfg: ModelConfig):
        super().__init__(cfg)
        init_weights(self)
        self._spread_poses()
        size = cfg.image_size
        r = (torch.arange(size) + 0.5) / size * 2 - 1
        self.register_buffer("px", r.view(1, 1, 1, size), persistent=False)
        self.register_buffer("py", r.view(1, 1, size, 1), persistent=False)

    def geometry(self):
        """The template in its own frame (what `render_poses` takes as `template`): computed
        once while only the poses move."""
        raise NotImplementedError

    def render_poses(self, pose: torch.Tensor, size: int | None = None,
                     template=None) -> torch.Tensor:
        """(B, n, 6) poses (axis-angle rotation, translation) -> (B, n, size, size) renders."""
        raise NotImplementedError

    def template_spread(self) -> torch.Tensor:
        """A compactness measure of the template (its prior in training)."""
        raise NotImplementedError

    def pixel_grid(self, size: int | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """-> pixel centres x (1, 1, 1, size) and y (1, 1, size, 1) in [-1, 1]."""
        if size is None or size == self.cfg.image_size:
            return self.px, self.py
        g = (torch.arange(size, device=self.px.device, dtype=self.px.dtype) + 0.5) / size * 2 - 1
        return g.view(1, 1, 1, size), g.view(1, 1, size, 1)

    def render_instances(self, z: torch.Tensor, size: int | None = None) -> torch.Tensor:
        """(B, n, d) codes -> (B, n, size, size) single-instance renders (default image_size;
        a smaller size renders the same scene coarser, for cheap test-time refinement)."""
        B, n, d = z.shape
        return self.render_poses(self.pose(z.reshape(B * n, d)).reshape(B, n, 6), size)

    def forward(self, z: torch.Tensor, return_features: bool = False):
        """(B, n, d) codes -> (B, 1, 64, 64) z-buffered composite (no features to average)."""
        x = self.zbuffer(self.render_instances(z))
        return (x, None) if return_features else x


class SphereGenerator(TemplateGenerator):
    """The fastest generator, and the crispest: the template is a rod of K overlapping spheres
    on one axis, with a learned length and learned radii (a solid of revolution), and its
    height map seen from above is closed-form.

    A posed sphere (centre c, radius r) covers the pixels with |xy - c_xy| < r at height
    c_z + sqrt(r^2 - |xy - c_xy|^2); an instance's height is the max over its spheres, the floor
    (0) elsewhere. The centres are evenly spaced along the template's x axis over a learned
    length, no radius falls below half the largest, and consecutive spheres always overlap, so
    the template is one rigid, connected, straight object by construction: cylinders, pins,
    bolts (a thicker head), cones, nuts (short and wide) and, sunk into the floor by a negative
    `lift`, flat blocks. Free templates (an occupancy grid, a free chain of spheres) grew two
    blobs or bent into snakes that covered two objects at once (docs/experiments.md).
    Units: the 64 x 64 image spans [-1, 1] in x and y, heights use the same unit (so rotations
    are rigid) and 2 / height_gain of them map to +1. Silhouettes are softened over about one
    pixel (a sigmoid coverage) so that poses and the template get gradient. It starts as a
    short, thick rod.
    """

    template_parameters = ("log_radius", "radius_shape", "length", "lift")

    def __init__(self, cfg: ModelConfig):
        super().__init__(cfg)
        self.log_radius = nn.Parameter(torch.tensor(math.log(0.2)))
        self.radius_shape = nn.Parameter(
            torch.full((cfg.spheres,), 2.0 if cfg.radius_profile == "free" else 4.0))
        self.length = nn.Parameter(torch.tensor(0.2))  # axis length (centre to centre)
        self.lift = nn.Parameter(torch.tensor(0.2))  # height of the axis above the floor

    def spheres(self) -> tuple[torch.Tensor, torch.Tensor]:
        """-> centres (K, 3) about the rod's middle, radii (K,): the template in its own frame."""
        if self.cfg.radius_profile == "monotone":  # one end to the other, never growing
            steps = 0.75 + 0.25 * torch.sigmoid(self.radius_shape)
            radii = self.log_radius.exp() * torch.cat([steps.new_ones(1), steps[1:].cumprod(0)])
        else:
            radii = self.log_radius.exp() * (0.5 + 0.5 * torch.sigmoid(self.radius_shape))
        K = self.cfg.spheres
        # spacing below the smallest radius: consecutive spheres overlap whatever the length
        length = self.length.abs().clamp(max=0.95 * (K - 1) * float(radii.min().detach()))
        t = torch.linspace(-0.5, 0.5, K, device=radii.device) if K > 1 else radii.new_zeros(1)
        centres = torch.stack([t * length, torch.zeros_like(t), torch.zeros_like(t)], dim=1)
        return centres, radii

    def geometry(self) -> tuple[torch.Tensor, torch.Tensor]:
        return self.spheres()

    def template_spread(self) -> torch.Tensor:
        """Mean squared distance of the sphere centres from their mean (a compactness prior)."""
        c, _ = self.spheres()
        return (c ** 2).sum(1).mean()

    def alignment_features(self, z: torch.Tensor) -> torch.Tensor:
        """The pose as far as the rod's render depends on it: translation (3) and the axis
        direction up to sign (the 6 distinct entries of a a^T). A d-dimensional code decodes to
        6 pose numbers, so most of z cannot be recovered from an image: comparing the codes
        themselves leaves L_a stuck near 1 (measured), comparing these does not."""
        B, n, d = z.shape
        return pose_features(self.poses(z.reshape(B * n, d))).reshape(B, n, 9)

    def render_poses(self, pose: torch.Tensor, size: int | None = None,
                     template: tuple[torch.Tensor, torch.Tensor] | None = None) -> torch.Tensor:
        """(B, n, 6) poses (axis-angle rotation, translation: what the pose decoder outputs)
        -> (B, n, size, size) single-instance renders. `template`: `spheres()` computed
        beforehand (test-time refinement, where the template does not change)."""
        B, n = pose.shape[:2]
        axis = rodrigues(pose.reshape(B * n, 6)[:, :3])[:, :, 0].reshape(B, n, 3)
        return self.render_axes(axis, pose[..., 3:], size, template)

    def posed_centres(self, axis: torch.Tensor, t: torch.Tensor,
                      template: tuple[torch.Tensor, torch.Tensor]
                      ) -> tuple[torch.Tensor, torch.Tensor]:
        """(B, n, 3) unit axes and translations, `spheres()` -> where the posed spheres lie:
        centres (B n, K, 3) before the lift, and their heights (B n, K) with the lift and the
        floor contact, as `render_axes` draws them."""
        B, n = axis.shape[:2]
        centres, radii = template
        c = centres[:, 0, None] * axis.reshape(B * n, 1, 3) + t.reshape(B * n, 1, 3)  # (M, K, 3)
        cz = c[..., 2] + self.lift  # (M, K)
        if self.cfg.floor_contact:  # lowest point of the instance at or above the floor
            cz = cz + (radii - cz).amax(dim=1, keepdim=True).clamp_min(0)
        return c, cz

    def render_axes(self, axis: torch.Tensor, t: torch.Tensor, size: int | None = None,
                    template: tuple[torch.Tensor, torch.Tensor] | None = None,
                    grid: tuple[torch.Tensor, torch.Tensor] | None = None) -> torch.Tensor:
        """The renderer itself: (B, n, 3) unit axes of the rods (the template's x axis in the
        world) and (B, n, 3) translations -> (B, n, size, size) renders. The template is a solid
        of revolution about that axis, so a rotation about it changes nothing and the axis is
        all of the rotation that a render depends on. `grid`: `pixel_grid(size)`."""
        B, n = axis.shape[:2]
        template = self.spheres() if template is None else template
        c, cz = self.posed_centres(axis, t, template)
        r = template[1].view(1, -1, 1, 1)
        cx, cy, cz = c[..., 0, None, None], c[..., 1, None, None], cz[..., None, None]
        px, py = self.pixel_grid(size) if grid is None else grid
        pixel = 2.0 / px.shape[-1]
        if torch.is_grad_enabled():
            inside = r ** 2 - (px - cx) ** 2 - (py - cy) ** 2  # (M, K, H, W)
            cover = torch.sigmoid(inside / (2 * r * pixel))
            h = cover * (cz + inside.clamp_min(1e-4).sqrt()).clamp_min(0)
        else:  # the same numbers computed in place: at inference the (M, K, H, W) temporaries,
            # each freshly allocated, cost three times the arithmetic (8 starts x 5 rods)
            inside = (r ** 2 - (px - cx).square_()) - (py - cy).square_()
            cover = torch.sigmoid_(inside / (2 * r * pixel))
            h = inside.clamp_min_(1e-4).sqrt_().add_(cz).clamp_min_(0).mul_(cover)
        h = h.amax(dim=1)  # (M, H, W): the top of the union of spheres
        x = (h * (self.cfg.height_gain / 2)).clamp(0, 1) * 2 - 1
        return x.reshape(B, n, *x.shape[1:])


CONVEX_MIN_EXTENT = 0.03  # image half-widths (about a pixel): every piece holds a ball this big
CONVEX_MAX_TILT = 0.6  # a normal leans at most asin(0.6) = 37 degrees from its prism direction
RING_PIECES, RING_WALLS = 6, 12  # a hexagonal nut (`ConvexGenerator.init_ring`): six sectors,
# walls every 30 degrees


def check_ring(disc, hole: float) -> None:
    """Raises ValueError unless the disc (x0, x1, r) can be a ring with a hole of `hole` x r
    (`ConvexGenerator.init_ring`): each sector must hold its own centre's ball and its
    neighbour's."""
    x0, x1, r = (float(v) for v in disc)
    if (not 0 < hole < 1 or x1 - x0 <= 2 * CONVEX_MIN_EXTENT
            or r * (1 - hole) <= 2.2 * CONVEX_MIN_EXTENT):
        raise ValueError(f"ring of disc {tuple(disc)} with hole {hole:g} invalid; valid: a hole "
                         f"in (0, 1) x the radius leaving a wall thicker than "
                         f"{2.2 * CONVEX_MIN_EXTENT:g}, a disc longer than "
                         f"{2 * CONVEX_MIN_EXTENT:g}")


def taper_slope(disc, taper: float) -> float:
    """-> how far the walls of the disc (x0, x1, r) lean in per unit of its length when its far
    end's radius is `taper` x r (`ConvexGenerator.init_discs`); raises ValueError unless the
    tapered disc can be built: taper in (0, 1], the lean within what a tilt can give
    (CONVEX_MAX_TILT), the narrow end's radius above CONVEX_MIN_EXTENT."""
    x0, x1, r = (float(v) for v in disc)
    slope = r * (1 - taper) / (x1 - x0) if x1 > x0 else math.inf
    if (not 0 < taper <= 1 or x1 - x0 <= 2 * CONVEX_MIN_EXTENT
            or taper * r <= CONVEX_MIN_EXTENT or slope >= 0.95 * CONVEX_MAX_TILT):
        raise ValueError(f"taper {taper:g} of disc {tuple(disc)} invalid; valid: a taper in "
                         f"(0, 1] leaving the narrow end's radius above {CONVEX_MIN_EXTENT:g} "
                         f"and the walls leaning less than {0.95 * CONVEX_MAX_TILT:g} per unit "
                         "of length (a longer or narrower disc)")
    return slope


def _softplus_inverse(y: torch.Tensor) -> torch.Tensor:
    return y + torch.log(-torch.expm1(-y))


class ConvexGenerator(TemplateGenerator):
    """A template for any rigid part: a union of K convex pieces, each the intersection of a
    top, a bottom and `walls` side half-spaces, with the exact closed-form height map of
    `template.height_map` (smooth for gradients), pieces and instances z-buffered by max.

    Flat faces and sharp edges (a box), a hexagonal prism, pieces around a through hole (a
    nut's sectors), a head on a shaft (a bolt), a flange (a pin), tapers (cone, stopper).
    Parameters per piece (all in `template_parameters`, none of which can make it degenerate):
      * `centre` (3) and `orientation` (3, axis-angle): where the piece's prism frame lies;
      * `tilt` (P, 3): each normal is its prism direction (top, bottom, walls evenly around z)
        plus a deviation of norm < CONVEX_MAX_TILT, normalised; with the prism directions
        covering the sphere to within 47 degrees, every piece stays bounded;
      * `extent` (P): offset of each plane from the centre, CONVEX_MIN_EXTENT + softplus, so
        a piece always holds a ball of that radius around its centre, plus whatever it takes
        to also hold the previous piece's centre (that ball too): piece k overlaps piece k-1,
        so the union is one connected body by construction (free templates split into two
        blobs: docs/experiments.md).
    It starts as one box (`init_box`, `init_from_data`: of the size the training frames
    suggest), every piece a copy of it with a little jitter, so each piece wins some of the
    box's faces and gets gradient. Units and heights as `SphereGenerator`. Poses are full 3D
    rotations (axis-angle) and translations: what the pose decoder outputs.
    """

    template_parameters = ("centre", "orientation", "tilt", "extent")

    def __init__(self, cfg: ModelConfig):
        """The pose decoder as the others', the template as one default box (`init_box`)."""
        from inseggan_ros.runtime.template import prism_normals

        super().__init__(cfg)
        K, P = cfg.pieces, cfg.walls + 2
        self.register_buffer("base", prism_normals(cfg.walls), persistent=False)  # (P, 3)
        self.centre = nn.Parameter(torch.zeros(K, 3))
        self.orientation = nn.Parameter(torch.zeros(K, 3))
        self.tilt = nn.Parameter(torch.zeros(K, P, 3))
        self.extent = nn.Parameter(torch.zeros(K, P))
        self.init_box((0.25, 0.15, 0.1))

    @torch.no_grad()
    def init_box(self, half: tuple[float, float, float], jitter: float = 0.01) -> None:
        """Every piece: the box of half-extents `half` (image half-widths) standing on the floor
        (its bottom at height 0 when the pose's height is 0), offsets jittered by `jitter`."""
        K, P = self.extent.shape
        a, b, c = (float(v) for v in half)
        if min(a, b, c) <= CONVEX_MIN_EXTENT:
            raise ValueError(f"box half-extents {half} invalid; valid: each > {CONVEX_MIN_EXTENT}")
        dev = self.extent.device  # called on a model already moved to its device, too
        self.centre.copy_(torch.tensor([0.0, 0.0, c], device=dev).expand(K, 3))
        self.orientation.zero_()
        self.tilt.zero_()
        # (P,): the box's support function
        support = self.base.abs() @ torch.tensor([a, b, c], device=dev)
        noise = (torch.randn(K, P, generator=torch.Generator().manual_seed(0)) * jitter).to(dev)
        noise[0] = 0
        self.extent.copy_(_softplus_inverse((support - CONVEX_MIN_EXTENT + noise).clamp_min(1e-3)))

    @torch.no_grad()
    def init_boxes(self, boxes, joint) -> None:
        """Piece k: the box `boxes[k]` = (x0, x1, y0, y1, height) standing on the floor, along
        the template's axes, its centre at `joint` (x, y), halfway up the lowest box: one point
        inside all of them, or one point per piece, each inside its own box and the next one's
        (where no point is in all: a U's two legs), so that each piece holds the previous one's
        centre as it is (`halfspaces` adds no reach) and the boxes keep the outline given. Bars
        so make a T, an L or a U (`shapefit.rod_bars`), which a box fitted from copies of one
        box does not become (two copies fitted to T-pieces' frames stayed one square slab:
        docs/experiments.md, 2026-12-06, night)."""
        K, P = self.extent.shape
        if len(boxes) != K:
            raise ValueError(f"{len(boxes)} boxes for a template of {K} pieces; valid: {K}")
        dev = self.extent.device
        b = torch.tensor([[float(v) for v in box] for box in boxes], device=dev)
        lo = torch.stack([b[:, 0], b[:, 2], torch.zeros_like(b[:, 0])], 1)
        hi = torch.stack([b[:, 1], b[:, 3], b[:, 4]], 1)
        xy = torch.tensor(joint, dtype=torch.float32, device=dev)  # (2,) or (K, 2)
        if xy.shape not in ((2,), (K, 2)):
            raise ValueError(f"joint {joint} invalid; valid: one (x, y) or {K} of them")
        xy = xy.expand(K, 2)
        centre = torch.cat([xy, torch.full((K, 1), float(b[:, 4].min()) / 2, device=dev)], 1)
        prev = torch.cat([centre[:1], centre[:-1]])

        def inside(p):
            return (p > lo + CONVEX_MIN_EXTENT) & (p < hi - CONVEX_MIN_EXTENT)
        if not bool((inside(centre) & inside(prev)).all()):
            raise ValueError(f"joint {joint} invalid for boxes {boxes}; valid: a point inside "
                             "every box, or per box a point inside it and the next box, more "
                             f"than {CONVEX_MIN_EXTENT} from their sides")
        self.centre.copy_(centre)
        self.orientation.zero_()
        self.tilt.zero_()
        n = self.base  # (P, 3): the prism's directions, the template's own axes here
        support = ((lo + hi) / 2 - centre) @ n.T + ((hi - lo) / 2) @ n.abs().T  # (K, P)
        _, reach = self._normals_reach()
        self.extent.copy_(_softplus_inverse((support - reach - CONVEX_MIN_EXTENT).clamp_min(1e-3)))

    @torch.no_grad()
    def init_discs(self, segments, axis_height: float, taper: float = 1.0) -> None:
        """Piece k: a right prism about the template's x axis (its `walls` around that axis),
        spanning x0_k..x1_k with its walls at distance r_k from the axis, the axis at
        `axis_height`; `segments`: K (x0, x1, r), in order along the axis (a stack of discs:
        a solid of revolution with flat steps, such as a head on a shaft or a flange). Each piece
        also reaches back to the previous piece's centre (`halfspaces`: one connected body),
        unseen inside the previous piece where that one is the wider (`shapefit.piece_order`
        orders them so where it can: a flange first).

        `taper` below 1 (one piece only): the walls lean in along the axis, r at x0 and
        `taper` x r at x1, a pyramid's frustum (a cone's, a stopper's): each wall's normal
        tilted along the axis by the slope s (`taper_slope`), at distance (r + taper r) / 2 /
        sqrt(1 + s^2) from the piece's centre. Why: the learned rod is a capsule, and piles of
        it teach the centre votes a part without the cone's point (docs/experiments.md,
        2026-12-06)."""
        K, P = self.extent.shape
        if len(segments) != K:
            raise ValueError(f"{len(segments)} segments for a template of {K} pieces; valid: {K}")
        if taper != 1 and K != 1:
            raise ValueError(f"taper {taper:g} for a template of {K} pieces; valid: 1 (no taper) "
                             "or a template of one piece")
        slope = taper_slope(segments[0], taper) if taper != 1 else 0.0
        dev = self.extent.device
        seg = torch.tensor([[float(v) for v in s] for s in segments], device=dev)
        x0, x1, r = seg.unbind(1)
        if bool((x1 - x0 <= 2 * CONVEX_MIN_EXTENT).any()) or bool((r <= CONVEX_MIN_EXTENT).any()):
            raise ValueError(f"segments {segments} invalid; valid: each longer than "
                             f"{2 * CONVEX_MIN_EXTENT} with a radius above {CONVEX_MIN_EXTENT}")
        self.centre.copy_(torch.stack([(x0 + x1) / 2, torch.zeros_like(r),
                                       torch.full_like(r, float(axis_height))], 1))
        self.orientation.copy_(torch.tensor([0.0, math.pi / 2, 0.0], device=dev).expand(K, 3))
        self.tilt.zero_()
        if slope:  # the walls' normals lean towards +z of the piece, +x once turned
            u = slope / CONVEX_MAX_TILT  # `_normals_reach`: base + CONVEX_MAX_TILT t / |(1, t)|
            self.tilt[:, 2:, 2] = u / math.sqrt(1 - u * u)
            r = r * (1 + taper) / 2 / math.sqrt(1 + slope * slope)
        # the support wanted: the caps (top, bottom: along +-x once turned) at the segment's
        # ends, the walls at r; less what `halfspaces` adds by itself
        support = torch.cat([((x1 - x0) / 2)[:, None].expand(K, 2), r[:, None].expand(K, P - 2)], 1)
        _, reach = self._normals_reach()  # with the tilts set above
        self.extent.copy_(_softplus_inverse((support - reach - CONVEX_MIN_EXTENT).clamp_min(1e-3)))

    @torch.no_grad()
    def init_ring(self, disc, hole: float, axis_height: float = 0.0) -> None:
        """The disc `disc` (x0, x1, r: about the template's x axis, as `init_discs`) as a
        hexagonal nut: six flats at distance r from the axis (its apothem) and a through
        hole whose six faces lie at `hole` x r, one piece per flat (a ring sector).

        Sector k spans the angles 60k +- 30 degrees about the axis: its outer flat is wall 2k
        of the 12 (walls every 30 degrees), its hole face wall 2k + 6, its two cuts walls 2k + 4
        and 2k + 8, through the axis, each reaching CONVEX_MIN_EXTENT beyond it into the
        neighbour (`template.ring_sector_planes`' overlap: no seams in the soft render), where
        the neighbours' flats (walls 2k +- 2) bound it; its other walls are out of the way,
        twice as far as the flats. The piece's centre is on
        its cut with the next sector, halfway between hole and flat, where both sectors hold
        it and its ball: piece k + 1 reaches back to it (`halfspaces`), so the six make one
        connected body with the hole left open. Why: a nut's hole and flats are what the
        piles of a solid disc lack (docs/experiments.md, 2026-12-03)."""
        K, P = self.extent.shape
        if (K, P) != (RING_PIECES, RING_WALLS + 2):
            raise ValueError(f"a ring is {RING_PIECES} pieces of {RING_WALLS} walls; this "
                             f"template has {K} pieces of {P - 2} walls")
        check_ring(disc, hole)
        x0, x1, r = (float(v) for v in disc)
        dev = self.extent.device
        self.orientation.copy_(torch.tensor([0.0, math.pi / 2, 0.0], device=dev).expand(K, 3))
        self.tilt.zero_()
        self.centre.zero_()
        n, _ = self._normals_reach()  # (K, P, 3): the same prism directions for every piece
        mid = (r * (1 + hole) / 2) / math.cos(math.pi / 6)  # from the axis, on the cut
        axis = torch.tensor([(x0 + x1) / 2, 0.0, float(axis_height)], device=dev)
        k = torch.arange(K, device=dev)
        self.centre.copy_(axis + mid * n[k, 2 + 2 * k + 1])  # wall 2k + 1: 60k + 30 degrees
        # the offsets wanted, along the world normals (through the axis for the walls)
        along = (n * axis).sum(-1)  # (K, P)
        want = torch.full((K, P), 2 * r, device=dev)  # walls out of the way
        want[:, :2] = (x1 - x0) / 2  # the caps (along +-x)
        for j in (0, 2, 10):  # its flat, and its neighbours' (past the cuts' overlap)
            want[k, 2 + (2 * k + j) % 12] = r
        want[k, 2 + (2 * k + 6) % 12] = -hole * r
        want[k, 2 + (2 * k + 4) % 12] = 1.05 * CONVEX_MIN_EXTENT  # the cuts: just past the
        want[k, 2 + (2 * k + 8) % 12] = 1.05 * CONVEX_MIN_EXTENT  # centres' balls
        n, reach = self._normals_reach()
        own = (n * self.centre[:, None]).sum(-1)  # each plane's distance from its centre
        self.extent.copy_(_softplus_inverse(
            (along + want - own - reach - CONVEX_MIN_EXTENT).clamp_min(1e-3)))

    @torch.no_grad()
    def init_from_data(self, x, n_instances: int) -> tuple[float, float, float]:
        """Start as the box the training frames suggest: (N, 1, H, W) model inputs -> a square
        footprint of the mean visible area per instance, and as its thickness the lower quartile
        of the foreground heights (parts lying flat on the floor; the median counts parts
        resting on others). -> the half-extents used."""
        x = torch.as_tensor(x, dtype=torch.float32)
        fg = x > -1 + 1e-4
        if not fg.any():
            raise ValueError("init_from_data: no foreground pixels in the training frames")
        area = float(fg.float().mean()) * 4 / n_instances  # the image spans 2 x 2 units
        top = float(torch.quantile((x[fg] + 1) / self.cfg.height_gain, 0.25))
        side = max(area ** 0.5 / 2, 2 * CONVEX_MIN_EXTENT)
        half = (side, side, max(top / 2, 2 * CONVEX_MIN_EXTENT))
        self.init_box(half)
        return half

    def _normals_reach(self) -> tuple[torch.Tensor, torch.Tensor]:
        """-> (K, P, 3) unit normals in the template's frame, and (K, P) how far each plane must
        lie from its piece's centre for the piece to hold the previous piece's centre."""
        t = self.tilt
        n = self.base + CONVEX_MAX_TILT * t / torch.sqrt(1 + (t ** 2).sum(-1, keepdim=True))
        n = n / n.norm(dim=-1, keepdim=True)
        n = torch.einsum("kij,kpj->kpi", rodrigues(self.orientation), n)
        prev = torch.cat([self.centre[:1], self.centre[:-1]])  # piece k also holds centre k-1
        return n, F.relu((n * (prev - self.centre)[:, None]).sum(-1))

    def halfspaces(self) -> tuple[torch.Tensor, torch.Tensor]:
        """-> the template in its own frame: (K, P, 3) unit normals, (K, P) offsets."""
        n, reach = self._normals_reach()
        d = reach + CONVEX_MIN_EXTENT + F.softplus(self.extent)
        return n, d + (n * self.centre[:, None]).sum(-1)

    def geometry(self) -> tuple[torch.Tensor, torch.Tensor]:
        return self.halfspaces()

    def corners(self, template: tuple[torch.Tensor, torch.Tensor] | None = None
                ) -> tuple[torch.Tensor, torch.Tensor]:
        """-> every candidate corner of every piece (K, C, 3), the meeting point of three of its
        planes (C = P choose 3), and whether it is a corner of the piece (K, C) bool: inside
        all of its other planes. Differentiable in the template (a 3 x 3 solve each)."""
        n, d = self.halfspaces() if template is None else template
        K, P = d.shape
        idx = torch.combinations(torch.arange(P, device=d.device), 3)  # (C, 3)
        A, b = n[:, idx], d[:, idx]  # (K, C, 3, 3), (K, C, 3)
        ok = torch.linalg.det(A).abs() > 1e-6
        eye = torch.eye(3, device=d.device, dtype=d.dtype).expand_as(A)
        x = torch.linalg.solve(torch.where(ok[..., None, None], A, eye), b)
        inside = (torch.einsum("kpi,kci->kcp", n, x) <= d[:, None] + 1e-5).all(-1)
        return x, ok & inside

    def template_spread(self) -> torch.Tensor:
        """Mean squared distance of the piece centres from their mean (a compactness prior)."""
        return ((self.centre - self.centre.mean(0)) ** 2).sum(1).mean()

    def alignment_features(self, z: torch.Tensor) -> torch.Tensor:
        """The pose as a render shows it: translation (3) and each axis of the rotation up to
        sign (the 6 distinct entries of c c^T for each column c of R: 18), so that the 180
        degree turns of a box about its axes, which render the same, compare equal."""
        B, n, d = z.shape
        p = self.pose(z.reshape(B * n, d))
        cols = rodrigues(p[:, :3]).transpose(1, 2)  # (M, 3 columns, 3)
        i, j = torch.triu_indices(3, 3)
        outer = (cols[..., :, None] * cols[..., None, :])[..., i, j]  # (M, 3, 6)
        return torch.cat([p[:, 3:], outer.flatten(1)], 1).reshape(B, n, 21)

    def render_poses(self, pose: torch.Tensor, size: int | None = None,
                     template: tuple[torch.Tensor, torch.Tensor] | None = None) -> torch.Tensor:
        """(B, n, 6) poses (axis-angle rotation, translation) -> (B, n, size, size) renders.
        `template`: `halfspaces()` computed beforehand (it does not change while poses move)."""
        # In float32 even under mixed precision: the corners' 3 x 3 solves have no bfloat16
        # kernel on CUDA, and the heights are differences of nearly equal plane distances.
        with torch.autocast(pose.device.type, enabled=False):
            if template is not None:
                template = tuple(v.float() for v in template)
            return self._render_poses(pose.float(), size, template)

    def _render_poses(self, pose: torch.Tensor, size: int | None,
                      template: tuple[torch.Tensor, torch.Tensor] | None) -> torch.Tensor:
        from inseggan_ros.runtime.template import height_map, pose_planes

        B, n = pose.shape[:2]
        p = pose.reshape(B * n, 6)
        normals, offsets = self.halfspaces() if template is None else template
        R, t = rodrigues(p[:, :3]), p[:, 3:]
        if self.cfg.floor_contact:  # the lowest corner at or above the floor
            x, real = self.corners((normals, offsets))
            z = torch.einsum("mj,kcj->mkc", R[:, 2], x)  # corners' heights above t_z
            z = torch.where(real, z, torch.full_like(z, float("inf"))).flatten(1).amin(1)
            t = torch.cat([t[:, :2], t[:, 2:] + F.relu(-(z + t[:, 2]))[:, None]], 1)
        nw, dw = pose_planes(normals, offsets, R, t)
        px, py = self.pixel_grid(size)
        px, py = px.reshape(-1), py.reshape(-1)
        h = height_map(nw, dw, px, py, temperature=2.0 / px.numel())  # about a pixel
        x = (h * (self.cfg.height_gain / 2)).clamp(0, 1) * 2 - 1
        return x.reshape(B, n, *x.shape[1:])


def make_generator(cfg: ModelConfig) -> Generator:
    """The generator that `cfg.renderer` names."""
    return {"spheres": SphereGenerator,
            "convex": ConvexGenerator}.get(cfg.renderer, Generator)(cfg)


def _trunk(nf: int, sn: bool = False) -> list[nn.Module]:
    wrap = nn.utils.spectral_norm if sn else (lambda m: m)
    return [wrap(nn.Conv2d(1, nf, 4, 2, 1)), nn.LeakyReLU(0.2),
            wrap(nn.Conv2d(nf, 2 * nf, 4, 2, 1)), nn.InstanceNorm2d(2 * nf, affine=True),
            nn.LeakyReLU(0.2),
            wrap(nn.Conv2d(2 * nf, 4 * nf, 4, 2, 1)), nn.InstanceNorm2d(4 * nf, affine=True),
            nn.LeakyReLU(0.2),
            wrap(nn.Conv2d(4 * nf, 8 * nf, 4, 2, 1)), nn.InstanceNorm2d(8 * nf, affine=True),
            nn.LeakyReLU(0.2)]


class Discriminator(nn.Module):
    def __init__(self, cfg: ModelConfig):
        super().__init__()
        wrap = nn.utils.spectral_norm if cfg.spectral_norm else (lambda m: m)
        self.net = nn.Sequential(*_trunk(cfg.nf, cfg.spectral_norm),
                                 wrap(nn.Conv2d(8 * cfg.nf, 1, 4, 1, 0)))
        init_weights(self)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x).flatten(1)  # (B, 1) logits


class Encoder(nn.Module):
    def __init__(self, cfg: ModelConfig):
        super().__init__()
        self.cfg = cfg
        nf = self.width
        layers = _trunk(nf)
        if cfg.coord_conv:  # the image plus its x and y coordinates (CoordConv)
            layers[0] = nn.Conv2d(3, nf, 4, 2, 1)
            r = torch.linspace(-1, 1, cfg.image_size)
            grid = torch.stack(torch.meshgrid(r, r, indexing="xy"))[None]
            self.register_buffer("coords", grid, persistent=False)
        self.derender = nn.Sequential(*layers[:5])  # -> (2nf, 16, 16), compared with mean F
        self.head = nn.Sequential(*layers[5:],
                                  nn.Conv2d(8 * nf, cfg.n_instances * cfg.latent_dim, 4, 1, 0))
        init_weights(self)

    @property
    def width(self) -> int:
        """The trunk's base number of channels: `ModelConfig.encoder_nf`, or nf where that is 0."""
        return self.cfg.encoder_nf or self.cfg.nf

    def forward(self, x: torch.Tensor, return_features: bool = False):
        if self.cfg.coord_conv:
            x = torch.cat([x, self.coords.expand(x.shape[0], -1, -1, -1)], dim=1)
        h = self.derender(x)
        z = self.head(h).reshape(x.shape[0], self.cfg.n_instances, self.cfg.latent_dim)
        return (z, h) if return_features else z


def build(cfg: ModelConfig) -> tuple[Generator, Discriminator, Encoder]:
    return make_generator(cfg), Discriminator(cfg), Encoder(cfg)


def build_models(state: dict, path="checkpoint"):
    """(config, generator, encoder) rebuilt from a checkpoint's `state` (`core.checkpoint.load`),
    in float32; raises CheckpointError naming `path` when the state does not fit this version."""
    try:
        cfg = ModelConfig.from_dict(state["model_config"])
        G, E = make_generator(cfg), Encoder(cfg)
        G.load_state_dict({k: v.float() for k, v in state["generator"].items()})
        E.load_state_dict({k: v.float() for k, v in state["encoder"].items()})
    except (KeyError, TypeError, ValueError, RuntimeError) as e:
        raise checkpoint.CheckpointError(
            f"{path}: incompatible with this version of inseggan_ros "
            f"({type(e).__name__}: {str(e).splitlines()[0]})") from None
    return cfg, G, E
