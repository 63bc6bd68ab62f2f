"""Experiment: two centre-vote networks of different origin averaged. The model's net (e.g.
taught on piles of its learned part) and another model's (e.g. taught on the model's own labels
of its training frames, `inseggan centres --self-labels`) read the same frame; their heatmaps and
offsets are averaged before decoding, and the rest of the model's pipeline follows. Prints all /
K-Means-hard / Felzenszwalb-hard mIoU of each net alone and of the pair, with the classical
methods on the same frames (docs/experiments.md, 2026-11-29, day).

    python scripts/experiments/centre_ensemble.py --model models/bolt/model.pt \
        --other runs/dense/bolt_self_votes/model.pt --data data/bolt
"""
import torch
from label_rules import arguments, load

from inseggan_ros import centres, segment
from inseggan_ros.segment import Segmenter


def main(argv=None) -> int:
    ap = arguments(__doc__.split("\n")[0])
    ap.add_argument("--other", required=True,
                    help="a model whose centre-vote net is averaged with the first's")
    args = ap.parse_args(argv)
    use = []

    def averaged_labels(net, x, fg, n):
        inp = centres.net_input(x, fg)
        return centres.decode(torch.stack([m(inp) for m in use]).mean(0), fg, n)

    segment.centre_labels = averaged_labels  # the segmenter's votes, from the nets in `use`
    bench = load(args.model, args.data, args.split)
    other = Segmenter.from_checkpoint(args.other, device="cpu").centre_net
    if bench.seg.centre_net is None or other is None:
        ap.error("both models need a centre-vote network")
    bench.print_baselines()
    for name, nets in (("the model's net", [bench.seg.centre_net]), ("the other's", [other]),
                       ("both averaged", [bench.seg.centre_net, other])):
        use[:] = nets
        print(name, bench.row(bench.scores()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
