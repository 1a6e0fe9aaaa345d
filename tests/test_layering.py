"""Layering: the generator never imports torch; bpy lives in the add-on and the one renderer
module only, imported lazily; the CLI starts without either."""
import ast
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def _imports(path):
    tree = ast.parse(path.read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                yield a.name.split(".")[0], node
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            yield node.module.split(".")[0], node


def test_generator_never_imports_torch():
    bad = [str(p) for p in (REPO / "generator").rglob("*.py") if any(m == "torch" for m, _ in _imports(p))]
    assert bad == []


def test_bpy_only_in_the_renderer_and_the_addon():
    allowed = {REPO / "generator" / "spikegen" / "render_blender.py"}
    bad = [str(p) for p in (REPO / "generator").rglob("*.py") if p not in allowed
           and any(m == "bpy" for m, _ in _imports(p))]
    bad += [str(p) for p in (REPO / "trainer").rglob("*.py") if any(m == "bpy" for m, _ in _imports(p))]
    assert bad == []


def _module_level_imports(tree):
    """Import nodes not inside a function (module level, or under a top-level if/try/with)."""
    stack = list(ast.iter_child_nodes(tree))
    while stack:
        node = stack.pop()
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
            continue
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            yield node
        stack.extend(ast.iter_child_nodes(node))


def test_bpy_is_imported_lazily_in_the_renderer():
    """Every generator module that imports bpy (there must be one: the renderer) does so only
    inside functions, so importing it never needs Blender."""
    users = [p for p in (REPO / "generator").rglob("*.py") if any(m == "bpy" for m, _ in _imports(p))]
    assert users, "no generator module imports bpy: the renderer is gone or renamed"
    for p in users:
        eager = [node.lineno for node in _module_level_imports(ast.parse(p.read_text()))
                 if any(name == "bpy" for name in _names(node))]
        assert eager == [], f"{p}: bpy imported at module level (lines {eager})"


def _names(node):
    if isinstance(node, ast.Import):
        return [a.name.split(".")[0] for a in node.names]
    return [node.module.split(".")[0]] if node.module and node.level == 0 else []


def test_cli_starts_without_bpy_or_torch():
    code = ("import sys; from spikegen.cli import main; main(['--help']); "
            "print('bpy' in sys.modules, 'torch' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip().splitlines()[-1] == "False False"
