"""The launch files and config/d435.yaml as installed. `launch` and `launch_ros` are not on PyPI,
so the launch files cannot run here: they are checked as source (they parse, every executable,
parameter and shipped file they name exists) and the parameters they set are read back from
the real nodes over DDS."""
import ast
import subprocess
from pathlib import Path

import pytest
from conftest import REPO, get_params, installed_executable

pytestmark = pytest.mark.serial  # nodes over real DDS: run alone (setup.cfg)

LAUNCH_FILES = ("segmenter.launch.py", "demo.launch.py", "d435.launch.py")


def share() -> Path:
    return installed_executable("segmenter").parents[2] / "share" / "inseggan_ros"


def _tree(name):
    path = share() / "launch" / name
    assert path.is_file(), f"{name} is not installed (setup.py data_files; colcon build)"
    assert path.read_text() == (REPO / "launch" / name).read_text()
    return ast.parse(path.read_text())


def _keyword(call, name):
    return next((k.value for k in call.keywords if k.arg == name), None)


def _calls(tree, func):
    return [n for n in ast.walk(tree) if isinstance(n, ast.Call)
            and getattr(n.func, "id", getattr(n.func, "attr", None)) == func]


def _console_scripts():
    tree = ast.parse((REPO / "setup.py").read_text())
    entry = next(k.value for c in _calls(tree, "setup") for k in c.keywords
                 if k.arg == "entry_points")
    scripts = ast.literal_eval(entry)["console_scripts"]
    return {s.split("=")[0].strip() for s in scripts}


@pytest.mark.parametrize("name", LAUNCH_FILES)
def test_launch_file_parses_and_names_only_what_is_installed(name):
    tree = _tree(name)
    functions = {f.name for f in tree.body if isinstance(f, ast.FunctionDef)}
    assert "generate_launch_description" in functions
    for node in _calls(tree, "Node"):
        assert ast.literal_eval(_keyword(node, "package")) == "inseggan_ros"
        exe = ast.literal_eval(_keyword(node, "executable"))
        assert exe in _console_scripts()
        assert installed_executable(exe).is_file()
    # share = FindPackageShare("inseggan_ros"); PathJoinSubstitution([share, "config", "x"])
    shares = [ast.literal_eval(c.args[0]) for c in _calls(tree, "FindPackageShare")]
    assert "inseggan_ros" in shares
    files = []
    for c in _calls(tree, "PathJoinSubstitution"):
        parts = c.args[0].elts
        if isinstance(parts[0], ast.Name) and parts[0].id == "share":
            files.append(Path(*(ast.literal_eval(p) for p in parts[1:])))
    for f in files:
        assert (share() / f).is_file(), f"{name} names share/inseggan_ros/{f}: not installed"
    if name != "segmenter.launch.py":
        assert Path("launch/segmenter.launch.py") in files  # it includes the segmenter's


def _declared_arguments(tree):
    return {ast.literal_eval(c.args[0]) for c in _calls(tree, "DeclareLaunchArgument")}


def test_segmenter_launch_arguments_and_topic_names():
    from inseggan_ros.ros import common

    tree = _tree("segmenter.launch.py")
    assert _declared_arguments(tree) == {"model", "params_file", "namespace", "depth_topic",
                                         "camera_info_topic", "autostart"}
    consts = {t.id: ast.literal_eval(n.value) for n in tree.body if isinstance(n, ast.Assign)
              for t in n.targets}
    # the remaps start from the names the node really subscribes to
    assert consts["DEPTH"] == common.DEPTH_TOPIC
    assert consts["CAMERA_INFO"] == common.CAMERA_INFO_TOPIC
    # the ones the other launch files pass on are ones it declares
    for other in ("demo.launch.py", "d435.launch.py"):
        for inc in _calls(_tree(other), "IncludeLaunchDescription"):
            args = _keyword(inc, "launch_arguments")
            if args is not None and "segmenter" in ast.dump(inc):
                passed = {ast.literal_eval(k) for k in args.func.value.keys}
                assert passed <= _declared_arguments(tree), (other, passed)


def _node_parameters(tree) -> dict:
    """{executable: parameter names} from the Node(...) parameters=[{...}] dicts."""
    out = {}
    for node in _calls(tree, "Node"):
        exe = ast.literal_eval(_keyword(node, "executable"))
        given = _keyword(node, "parameters")
        sources = [given]
        if isinstance(given, ast.Name):  # a list built up first: its .append(...) calls
            sources = [c.args[0] for c in _calls(tree, "append")
                       if getattr(c.func.value, "id", None) == given.id]
        names = set()
        for source in sources:
            for d in ast.walk(source):
                if isinstance(d, ast.Dict):
                    names |= {ast.literal_eval(k) for k in d.keys}
        out[exe] = names
    return out


def test_parameters_the_launch_files_set_are_declared_by_the_nodes():
    """Every parameter name in a launch file, read back from the running node over DDS (an
    undeclared one reads as None)."""
    from test_bin_replay import stop

    wanted = {}
    for name in LAUNCH_FILES:
        for exe, names in _node_parameters(_tree(name)).items():
            wanted.setdefault(exe, set()).update(names)
    assert wanted == {"segmenter": {"model_path", "autostart"},
                      "bin_replay": {"source", "object", "bag_path", "loop", "rate"}}
    for exe, names in wanted.items():
        ns = f"/launch_{exe}"
        proc = subprocess.Popen([str(installed_executable(exe)), "--ros-args", "-r",
                                 f"__ns:={ns}"], stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, text=True)
        try:
            got = get_params(f"{ns}/{exe}", *sorted(names))
        finally:
            stop(proc)
        assert None not in got.values(), got
