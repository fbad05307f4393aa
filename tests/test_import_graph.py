"""The import graph flows one way (docs/design.md "Import layers"): scripts/import_graph, read from the source."""
from __future__ import annotations

import importlib.machinery
import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parent.parent
SCRIPT = REPO_ROOT / "scripts" / "import_graph"


@pytest.fixture(scope="module")
def checker():
    loader = importlib.machinery.SourceFileLoader("import_graph", str(SCRIPT))
    spec = importlib.util.spec_from_loader("import_graph", loader)
    module = importlib.util.module_from_spec(spec)
    sys.modules["import_graph"] = module  # dataclasses look their module up while the class is built
    try:
        loader.exec_module(module)
    finally:
        del sys.modules["import_graph"]
    return module


def test_no_circle_and_at_most_three_upward_imports(checker):
    graph = checker.import_graph(REPO_ROOT)
    assert len(graph.modules) > 50 and graph.imports
    assert graph.circles == []
    assert len(graph.upward) <= 3, [f"{i.path}:{i.line} {i.source} -> {i.target}" for i in graph.upward]
    assert graph.sideways == [], [f"{i.path}:{i.line} {i.source} -> {i.target}" for i in graph.sideways]
    assert graph.unlayered == []


def test_the_data_layer_imports_no_stage(checker):
    """The data layer (SLAMState and its records, the checkpoint, the observer) imports no stage, not even for
    type annotations."""
    graph = checker.import_graph(REPO_ROOT)
    stages = {m for m in graph.modules if checker.layer_of(m) == checker.LAYER_NAMES.index("stages")}
    assert stages >= {"mipslam.tracking", "mipslam.mapping", "mipslam.loop.closer"}
    state_layer = checker.LAYER_NAMES.index("state")
    low = [i for i in graph.imports if checker.layer_of(i.source) == state_layer and i.target in stages]
    assert low == [], [f"{i.path}:{i.line} {i.source} -> {i.target} ({i.kind})" for i in low]


def test_the_checker_finds_circles_and_upward_imports(checker, tmp_path):
    """On a made-up package: a circle through a lazy import, an upward import, a TYPE_CHECKING import that is not an
    edge, and ``from package import submodule``."""
    package = tmp_path / "mipslam"
    (package / "loop").mkdir(parents=True)
    (package / "__init__.py").write_text("")
    (package / "errors.py").write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n"
                                       "    from mipslam.state import SLAMState\n")
    (package / "state.py").write_text("from mipslam.loop import closer\n")
    (package / "loop" / "__init__.py").write_text("")
    (package / "loop" / "closer.py").write_text("def f():\n    from mipslam import state\n")
    graph = checker.import_graph(tmp_path)
    assert graph.circles == [["mipslam.loop.closer", "mipslam.state"]]
    assert [(i.source, i.target, i.kind) for i in graph.upward] == [("mipslam.state", "mipslam.loop.closer", "module")]
    assert [(i.source, i.target) for i in graph.imports if i.kind == "type"] == [("mipslam.errors", "mipslam.state")]


def test_the_script_runs_with_any_python(tmp_path):
    result = subprocess.run([sys.executable, str(SCRIPT), "--root", str(REPO_ROOT)], capture_output=True, text=True)
    assert result.returncode == 0, result.stdout + result.stderr
    assert "circles 0" in result.stdout.splitlines()[-1]
