"""No function or method of the package or its tools is longer than 80 lines (from its `def`
to its last line), so that each reads as one step of the procedure it implements.

ALLOWED lists the functions still being split elsewhere; each is checked apart (expected to
fail until it is split) and must still exist, so that an entry left behind is seen."""
import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
FOLDERS = ("inseggan_ros", "tools")
MAX_LINES = 80
ALLOWED = (
    "inseggan_ros/cli/main.py::build_parser",
    "inseggan_ros/cli/main.py::cmd_loop",
    "inseggan_ros/learning/loop.py::run",
    "inseggan_ros/evaluation/modelcard.py::export_model",
    "inseggan_ros/evaluation/modelcard.py::export_label_free",
    "tools/bench_node.py::main",
)


def _functions(tree: ast.AST, prefix: str = ""):
    """(qualified name, lines from `def` to the last line) of every function in `tree`,
    methods and nested functions included."""
    for node in ast.iter_child_nodes(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            name = prefix + node.name
            yield name, node.end_lineno - node.lineno + 1
            yield from _functions(node, name + ".")
        elif isinstance(node, ast.ClassDef):
            yield from _functions(node, prefix + node.name + ".")
        else:
            yield from _functions(node, prefix)


def function_lengths() -> dict:
    """{"path::qualified name": lines} of every function outside tests."""
    out = {}
    for folder in FOLDERS:
        for path in sorted((ROOT / folder).rglob("*.py")):
            rel = path.relative_to(ROOT)
            if any(part.startswith("test") for part in rel.parts):
                continue
            for name, lines in _functions(ast.parse(path.read_text(), str(path))):
                key = f"{rel.as_posix()}::{name}"
                out[key] = max(lines, out.get(key, 0))  # a name defined twice: the longer
    return out


def test_no_function_is_longer_than_80_lines():
    long = {k: n for k, n in function_lengths().items() if n > MAX_LINES and k not in ALLOWED}
    assert not long, f"functions over {MAX_LINES} lines (split them into named steps):\n" + \
        "\n".join(f"  {k}: {n} lines" for k, n in sorted(long.items(), key=lambda kv: -kv[1]))


def test_the_allowed_functions_still_exist():
    lengths = function_lengths()
    gone = [k for k in ALLOWED if k not in lengths]
    assert not gone, f"ALLOWED names functions that are gone (remove them from it): {gone}"


@pytest.mark.xfail(strict=False, reason="being split by other engineers (cli/, learning/loop.py "
                   "run, evaluation/modelcard.py export_model and export_label_free, "
                   "tools/bench_node.py main); once it passes, remove it from ALLOWED")
@pytest.mark.parametrize("function", ALLOWED)
def test_an_allowed_function_is_split_too(function):
    lines = function_lengths().get(function, 0)
    assert lines <= MAX_LINES, f"{function}: {lines} lines"
