"""The package's import direction (README "Layout"): ``ins ← signals ← fusion ← receiver``, with
``airdata`` beside ``ins`` (it may import ``ins``) and the top-level modules (``errors``,
``constants``, ``io_guard``) usable from every layer. Every import counts, also those inside
functions."""

import ast
from pathlib import Path

import pytest

PKG = Path(__file__).resolve().parents[1] / "ultratight"
# what each sub-package may import from the others
ALLOWED = {
    "ins": set(),
    "airdata": {"ins"},
    "signals": {"ins"},
    "fusion": {"ins", "signals", "airdata"},
    "receiver": {"ins", "signals", "fusion", "airdata"},
}
TOP_LEVEL = {"errors", "constants", "io_guard"}


def _imports(path):
    tree = ast.parse(path.read_text(), filename=str(path))
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                yield node.lineno, a.name
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            if node.module == "ultratight":
                for a in node.names:
                    yield node.lineno, f"ultratight.{a.name}"
            else:
                yield node.lineno, node.module


@pytest.mark.parametrize("layer", sorted(ALLOWED))
def test_layers_import_only_to_their_left(layer):
    bad = []
    for path in sorted((PKG / layer).rglob("*.py")):
        for line, mod in _imports(path):
            parts = mod.split(".")
            if parts[0] != "ultratight" or len(parts) < 2:
                continue
            target = parts[1]
            if target == layer or target in TOP_LEVEL or target == "__version__" or target in ALLOWED[layer]:
                continue
            if target in ALLOWED or target not in TOP_LEVEL:
                bad.append(f"{path.relative_to(PKG.parent)}:{line} imports {mod}")
    assert not bad, "\n".join(bad)


def test_top_level_modules_import_no_layer():
    for name in TOP_LEVEL:
        for line, mod in _imports(PKG / f"{name}.py"):
            parts = mod.split(".")
            assert not (parts[0] == "ultratight" and len(parts) > 1 and parts[1] in ALLOWED), \
                f"ultratight/{name}.py:{line} imports {mod}"
