"""The package's layering, and habits of its sources, read from the source
text (no imports run).

Layers, lowest first; a module may import its own layer and those below:

    learning   torch and numpy only: state, safety rules, models, MPC
    scenarios  the typed Scenario, the named scenes, where a scene puts things
    systems    Drake LeafSystems and the geometry they share (cloth mesh,
               gripper capsules)
    tasks      what each task is: success, the benchmark referee, the
               scripted demonstrations
    diagrams   builders: the station (simulated, Panda, hardware) and the
               imitation diagram
    tools      runners, evaluation, report, benchmarks, the command line
"""

import ast
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
LAYERS = ("learning", "scenarios", "systems", "tasks", "diagrams", "tools")
PACKAGE = "fabric_imitation"


def _sources(folder: str) -> list[Path]:
    return sorted((ROOT / folder).rglob("*.py"))


def _imports(path: Path) -> list[tuple[int, str]]:
    """(line, module) of every import in the file, nested ones included."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            found.append((node.lineno, node.module))
    return found


def LayerBreaks(layers=LAYERS, sources=_sources, root=ROOT) -> list[str]:
    """'file:line imports module' for each import of a higher layer, and of
    Drake from `learning`."""
    breaks = []
    for rank, layer in enumerate(layers):
        for path in sources(layer):
            for line, module in _imports(path):
                parts = module.split(".")
                higher = (
                    parts[0] == PACKAGE
                    and len(parts) > 1
                    and parts[1] in layers
                    and layers.index(parts[1]) > rank
                )
                drake = layer == "learning" and parts[0] in ("pydrake", "drake")
                if higher or drake:
                    breaks.append(f"{path.relative_to(root)}:{line} imports {module}")
    return breaks


def test_no_layer_imports_a_higher_one_and_learning_has_no_drake():
    assert LayerBreaks() == []


def test_the_layer_check_catches_an_upward_import(tmp_path):
    for layer, text in (
        ("learning", "from pydrake.systems.framework import LeafSystem\n"),
        ("scenarios", "def f():\n    import fabric_imitation.systems.x\n"),
        ("systems", "from fabric_imitation.learning.state import S\n"),
    ):
        (tmp_path / layer).mkdir()
        (tmp_path / layer / "m.py").write_text(text)
    found = LayerBreaks(
        ("learning", "scenarios", "systems"),
        lambda layer: sorted((tmp_path / layer).glob("*.py")),
        tmp_path,
    )
    found = [b.split(" imports ")[1] for b in found]
    assert found == ["pydrake.systems.framework", "fabric_imitation.systems.x"]


@pytest.mark.parametrize("folder", LAYERS)
def test_cited_repository_pages_exist(folder):
    """A docstring or comment that names a Markdown page names one that the
    repository has."""
    cited = re.compile(r"(?<![\w/.])((?:[\w-]+/)*[\w-]+\.md)\b")
    missing = []
    for path in _sources(folder):
        for name in cited.findall(path.read_text()):
            candidates = [ROOT / name, path.parent / name, ROOT / "docs" / name]
            if not any(c.exists() for c in candidates):
                missing.append(f"{path.relative_to(ROOT)}: {name}")
    assert missing == []


@pytest.mark.parametrize("folder", LAYERS)
def test_no_function_defines_a_helper_it_never_uses(folder):
    unused = []
    for path in _sources(folder):
        for node in ast.walk(ast.parse(path.read_text())):
            if not isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                continue
            inner = [
                n for n in node.body if isinstance(n, ast.FunctionDef | ast.Lambda)
            ]
            used = {n.id for n in ast.walk(node) if isinstance(n, ast.Name)}
            unused += [
                f"{path.relative_to(ROOT)}:{n.lineno} {n.name}"
                for n in inner
                if isinstance(n, ast.FunctionDef) and n.name not in used
            ]
    assert unused == []
