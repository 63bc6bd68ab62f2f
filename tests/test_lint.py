"""ament's linters, as a ROS 2 package runs them under `colcon test` (ament_flake8, ament_pep257).

flake8 with the ament configuration, except lines of up to 100 characters (the project's width).
pep257 with the ament convention, except the project's docstring layout: a summary that may run
over several lines and need not end in a period (D205, D400, D415), closing quotes on the last
text line (D209), the summary on the first line (D213 is the opposite rule of D212) and
summaries that describe rather than command (D401).
"""
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PATHS = [str(ROOT / p) for p in ("inseggan_ros", "tests", "tools", "launch", "scripts", "setup.py")
         if (ROOT / p).exists()]


@pytest.mark.linter
def test_flake8():
    ament_flake8 = pytest.importorskip("ament_flake8.main")
    rc, errors = ament_flake8.main_with_errors(
        argv=["--config", str(ROOT / "tests" / "flake8.ini"), *PATHS])
    assert rc == 0, f"{len(errors)} code style errors:\n" + "\n".join(errors)


@pytest.mark.linter
def test_pep257():
    ament_pep257 = pytest.importorskip("ament_pep257.main")
    # the paths first: `--add-ignore` takes every argument after it, and paths given there
    # would be read as codes to ignore, leaving pep257 to check the working directory instead
    rc = ament_pep257.main(argv=[*PATHS, "--add-ignore", "D205", "D209", "D213", "D400", "D401",
                                 "D415"])
    assert rc == 0, "docstring style errors (printed above)"
