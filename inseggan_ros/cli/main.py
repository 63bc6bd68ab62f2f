"""`python -m inseggan_ros.cli.main ...` (as torchrun starts it): the `inseggan` command, whose
parser and subcommands are the modules beside this one (`inseggan_ros.cli`)."""
import sys

from inseggan_ros.cli.app import build_parser, main

__all__ = ["build_parser", "main"]

if __name__ == "__main__":
    sys.exit(main())
