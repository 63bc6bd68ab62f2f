"""The `inseggan` command: its subcommands in three groups, the user's path first.

Expected errors (bad arguments, a bag that cannot be read, an existing output) print one line
`inseggan <command>: error: ...` and exit with status 2, without a traceback.
"""
from __future__ import annotations

import argparse
import sys
import textwrap

from inseggan_ros.cli import evaluate, loop, models, recording, research, simulate
from inseggan_ros.core.checkpoint import CheckpointError
from inseggan_ros.io.bags import BagError

DESCRIPTION = "Instance segmentation of identical parts in a bin from depth frames (InSeGAN), " \
              "learned from an unlabelled recording."
# (title, the commands' parsers in the order listed)
GROUPS = (
    ("your path: a recording to a shipped model", (
        loop.add_parser, recording.add_check, evaluate.add_eval, simulate.add_simulate,
        recording.add_bag_info, models.add_ship)),
    ("models and recordings", (
        models.add_export, models.add_card_settings, models.add_card_shape,
        models.add_card_run, simulate.add_simulate_bag, simulate.add_contact_sheet)),
    ("research commands (each stage of `loop` on its own, for experiments)", (
        research.add_train, research.add_distill, research.add_shape_fit,
        research.add_self_fit, research.add_head, research.add_centres)),
)
EPILOG = ("`inseggan COMMAND --help` lists a command's options; `inseggan loop --help-advanced` "
          "the loop's research options too.")


def _overview(sections: list[tuple[str, list[tuple[str, str]]]]) -> str:
    """The description: the groups of commands, each command with its one line."""
    lines = [*textwrap.wrap(DESCRIPTION, width=100), ""]
    for title, rows in sections:
        lines.append(f"{title}:")
        for name, summary in rows:
            lines += textwrap.wrap(summary, width=98, initial_indent=f"  {name:<15}",
                                   subsequent_indent=" " * 17)
        lines.append("")
    return "\n".join(lines + textwrap.wrap(EPILOG, width=100))


def build_parser() -> argparse.ArgumentParser:
    """The parser of every subcommand; its help lists them by group, not argparse's list."""
    parser = argparse.ArgumentParser(prog="inseggan", usage="inseggan [-h] COMMAND ...",
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND",
                                help=argparse.SUPPRESS, prog="inseggan")
    sections = []
    for title, adders in GROUPS:
        rows = []
        for add in adders:
            p = add(sub)
            summary = sub._choices_actions[-1].help  # the `help=` it was added with
            p.description = p.description or summary[0].upper() + summary[1:] + "."
            rows.append((p.prog.split()[-1], summary))
        sections.append((title, rows))
    parser.description = _overview(sections)
    return parser


def main(argv=None) -> int:
    """Parse the command line and run the subcommand; its expected errors as one line."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return args.func(args)
    except (BagError, CheckpointError, ValueError, FileExistsError, FileNotFoundError) as e:
        print(f"inseggan {args.command}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"inseggan {args.command}: interrupted", file=sys.stderr)
        return 130
