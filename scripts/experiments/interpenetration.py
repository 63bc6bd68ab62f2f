"""How far a rod model's instances pass through one another: in the GAN's own samples and as
its encoder reads the validation frames of the part's data set.

    python scripts/experiments/interpenetration.py MODEL [--data DATA] [--frames 200]

For every two instances of a scene, the deepest overlap of a sphere of one with a sphere of the
other, in units of the rod's largest radius; rigid parts never
overlap. Prints the share of instance pairs that overlap by more than 5 % of the radius, the mean
and 90th percentile overlap, the rod's length, largest radius and lift (image units), and the
spread of the translations.
"""
from __future__ import annotations

import argparse

import torch

from inseggan_ros.data import load_sim_split
from inseggan_ros.model import SphereGenerator, rodrigues
from inseggan_ros.nodes.segmenter import resolve_model
from inseggan_ros.segment import Segmenter


def world_spheres(G: SphereGenerator, pose: torch.Tensor) -> torch.Tensor:
    """(B, n, 6) poses -> (B, n, K, 3) the posed spheres' centres, where `render_axes` draws
    them (lift and floor contact included: `SphereGenerator.posed_centres`)."""
    B, n = pose.shape[:2]
    axis = rodrigues(pose.reshape(B * n, 6)[:, :3])[:, :, 0].reshape(B, n, 3)
    c, cz = G.posed_centres(axis, pose[..., 3:], G.spheres())
    return torch.cat([c[..., :2], cz[..., None]], -1).reshape(B, n, -1, 3)


def overlaps(G: SphereGenerator, pose: torch.Tensor) -> torch.Tensor:
    """(B, n, 6) poses -> (B, n (n - 1)) deepest sphere overlap of each ordered instance pair,
    divided by the rod's largest radius."""
    c = world_spheres(G, pose)
    _, r = G.spheres()
    B, n, K, _ = c.shape
    d = (c[:, :, None, :, None] - c[:, None, :, None, :]).norm(dim=-1)  # (B, n, n, K, K)
    depth = (r.view(K, 1) + r.view(1, K) - d).clamp_min(0).amax((-1, -2))
    return depth[:, ~torch.eye(n, dtype=torch.bool)].reshape(B, -1) / r.max()


def report(label: str, over: torch.Tensor, pose: torch.Tensor) -> None:
    print(f"  {label}: pairs overlapping {float((over > 0.05).float().mean()):.3f}, mean depth "
          f"{float(over.mean()):.3f} r, p90 {float(over.quantile(0.9)):.3f} r; translation std "
          + " / ".join(f"{v:.3f}" for v in pose[..., 3:].reshape(-1, 3).std(0).tolist()))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("model")
    ap.add_argument("--data", help="data set with a val split (default: data/<model name>)")
    ap.add_argument("--frames", type=int, default=200)
    args = ap.parse_args(argv)
    torch.manual_seed(0)
    seg = Segmenter.from_checkpoint(resolve_model(args.model), device="cpu")
    G, E = seg.G, seg.encoder("float32")
    if not isinstance(G, SphereGenerator):
        raise SystemExit(f"{args.model}: not a sphere rod model")
    with torch.no_grad():
        c0, r = G.spheres()
        length = float(c0[-1, 0] - c0[0, 0] + r[0] + r[-1])
        print(f"{args.model}: rod length {length:.3f}, largest radius {float(r.max()):.3f}, "
              f"lift {float(G.lift):.3f} (image half-widths)")
        n, d = G.cfg.n_instances, G.cfg.latent_dim
        z = torch.randn(args.frames, n, d)
        pose = G.pose(z.reshape(-1, d)).reshape(args.frames, n, 6)
        report("GAN samples", overlaps(G, pose), pose)
        val = load_sim_split(args.data or f"data/{args.model}", "val", limit=args.frames)
        codes = E(torch.as_tensor(val["x"]))
        pose = G.pose(codes.reshape(-1, d)).reshape(len(codes), n, 6)
        report("encoded validation frames", overlaps(G, pose), pose)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
