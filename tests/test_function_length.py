"""No function or method of the package or its tools is longer than 80 lines (from its `def`
to its last line), so that each reads as one step of the procedure it implements."""
import ast
from pathlib import Path


ROOT = Path(__file__).resolve().parents[1]
FOLDERS = ("inseggan_ros", "tools")
MAX_LINES = 80


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
    long = {k: n for k, n in function_lengths().items() if n > MAX_LINES}
    assert not long, f"functions over {MAX_LINES} lines (split them into named steps):\n" + \
        "\n".join(f"  {k}: {n} lines" for k, n in sorted(long.items(), key=lambda kv: -kv[1]))
