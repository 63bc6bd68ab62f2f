"""`python -m inseggan_ros.cli ...`: the `inseggan` command."""
import sys

from inseggan_ros.cli.app import main

sys.exit(main())
