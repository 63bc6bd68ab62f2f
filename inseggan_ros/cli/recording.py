"""A recording and a model on it: `check` (a few frames segmented, the label-free measures)
and `bag-info` (what a bag holds)."""
from __future__ import annotations

import argparse
from pathlib import Path

from inseggan_ros.core import settings


def cmd_check(args) -> int:
    """Segment a few frames of a bag: a PNG sheet and the label-free measures."""
    import torch

    from inseggan_ros.evaluation import selfcheck
    from inseggan_ros.core.paths import resolve_bag, resolve_model
    from inseggan_ros.runtime.segment import Segmenter

    if args.frames < 1:
        raise ValueError(f"--frames {args.frames} invalid; valid: >= 1")
    torch.set_num_threads(1)  # as the node runs by default
    model = resolve_model(str(args.model), "--model")
    seg = Segmenter.from_checkpoint(model, device="cpu")
    seg.inference = settings.resolve(seg.inference, args, seg.stored_settings)
    bag = resolve_bag(str(args.bag), "--bag")
    frames = selfcheck.load_bag_frames(bag, seg.prep_cfg, args.topic, count=args.frames)
    out = selfcheck.segment_frames(seg, frames["x"], frames["fg"])
    m = selfcheck.measure(seg, frames["x"], frames["fg"], out)
    selfcheck.sheet_png(args.out, frames["x"], out, frames=range(len(frames["x"])))
    print(f"{model} on {bag} (frames {', '.join(map(str, frames['index']))}):")
    print(selfcheck.format_measures(m))
    print(f"wrote {args.out}: input | reconstruction | labels | each instance rendered alone")
    return 0


def cmd_bag_info(args) -> int:
    from inseggan_ros.io.bags import list_topics, read_frames

    topics = list_topics(args.bag)
    print(f"{args.bag}:")
    for t, (typ, n) in sorted(topics.items()):
        print(f"  {t}  [{typ}]  {n} messages")
    frames = list(read_frames(args.bag, depth_topic=args.topic, limit=1))
    if frames:
        f = frames[0]
        print(f"  depth: {f.depth.shape[1]}x{f.depth.shape[0]} {f.encoding}, frame_id "
              f"{f.frame_id!r}, labels {'yes' if f.labels is not None else 'no'}, camera_info "
              f"{'yes' if f.camera_info is not None else 'no'}")
    return 0


def add_check(sub) -> argparse.ArgumentParser:
    """The `check` command's options."""
    p = sub.add_parser("check", help="segment a few frames of a bag: PNG sheet and label-free "
                                     "measures")
    p.add_argument("--model", required=True,
                   help="model folder, model.pt or a shipped model's name")
    p.add_argument("--bag", required=True, help="bag path or a shipped bag's name")
    p.add_argument("--topic", help="depth topic (default: auto)")
    p.add_argument("--frames", type=int, default=6, help="frames spread over the bag (6)")
    settings.add_flags(p, "(default: the model's)")
    p.add_argument("--out", type=Path, default=Path("check.png"), help="PNG sheet (check.png)")
    p.set_defaults(func=cmd_check)
    return p


def add_bag_info(sub) -> argparse.ArgumentParser:
    """The `bag-info` command's options."""
    p = sub.add_parser("bag-info", help="topics and depth format of a rosbag2 bag")
    p.add_argument("bag")
    p.add_argument("--topic", help="depth topic (default: auto)")
    p.set_defaults(func=cmd_bag_info)
    return p
