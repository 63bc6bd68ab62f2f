"""`inseggan`: one command, its subcommands one module per group.

* app.py: the parser (the groups and their order) and `main`
* loop.py: loop, a recording to a model; its recipe files (recipes.py)
* recording.py: check, bag-info
* evaluate.py: eval
* simulate.py: simulate, simulate-bag, contact-sheet
* models.py: ship, export, card-settings, card-shape, card-run
* research.py: train, distill, shape-fit, self-fit, head, centres
* common.py: what several of them share
"""
from inseggan_ros.cli.app import build_parser, main

__all__ = ["build_parser", "main"]
