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


def test_bpy_is_imported_lazily_in_the_renderer():
    p = REPO / "generator" / "spikegen" / "render_blender.py"
    if p.exists():
        top = [m for m, node in _imports(p) if node.col_offset == 0]
        assert "bpy" not in top


def test_cli_starts_without_bpy_or_torch():
    code = ("import sys; from spikegen.cli import main; main(['--help']); "
            "print('bpy' in sys.modules, 'torch' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip().splitlines()[-1] == "False False"
