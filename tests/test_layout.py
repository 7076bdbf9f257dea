"""The package's layout (docs/architecture.md): which room may import which, no private name across
a folder, and the size limits that keep every room readable.

Layers, left to right: ``ins ← signals ← fusion ← receiver``, with ``airdata`` beside ``ins`` (it may
import ``ins``); the top-level modules (``errors``, ``constants``, ``config``, ``cores``,
``io_guard``, ``chi2``, ``h5deflate``) are usable from every layer and import none. Inside a layer, the
sub-packages run one way too (:data:`INNER`): ``receiver``'s ``io`` and ``dsp`` at the bottom, ``scalar`` above them,
``deep`` above ``scalar``, ``cli`` on top. Every import counts, also those inside functions.
"""

import ast
from pathlib import Path

import pytest

PKG = Path(__file__).resolve().parents[1] / "ultratight"
# what each layer may import from the others
ALLOWED = {
    "ins": set(),
    "airdata": {"ins"},
    "signals": {"ins"},
    "fusion": {"ins", "signals", "airdata"},
    "receiver": {"ins", "signals", "fusion", "airdata"},
}
TOP_LEVEL = {"errors", "constants", "config", "cores", "io_guard", "chi2", "h5deflate"}
# inside a layer: what each sub-package may import from its siblings ("" = the layer's own files)
INNER = {
    "signals": {"": set(), "recording": {""}, "synth": {"", "recording"}},
    "fusion": {"": set(), "estimators": set(), "channel": {"estimators"}, "coupling": {"estimators"},
               "experiments": {"estimators", "coupling"}, "gins": {"estimators", "coupling"}},
    "receiver": {"": set(), "io": set(), "dsp": set(), "scalar": {"io", "dsp"}, "deep": {"io", "dsp", "scalar"},
                 "cli": {"io", "dsp", "scalar", "deep"}},
}
MAX_FOLDER_SHARE = 0.15        # of the package's lines, in one folder's own files
MAX_MODULE_LINES = 700
MAX_FUNCTION_LINES = 80
MAX_KERNEL_LINES = 100


def _modules():
    return sorted(p for p in PKG.rglob("*.py") if "__pycache__" not in p.parts)


def _module_name(path):
    rel = path.relative_to(PKG.parent).with_suffix("")
    parts = rel.parts[:-1] if rel.name == "__init__" else rel.parts
    return ".".join(parts)


def _imports(path):
    """(line, module, names) of every absolute import of ``ultratight`` in ``path``."""
    tree = ast.parse(path.read_text(), filename=str(path))
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                yield node.lineno, a.name, ()
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            if node.module == "ultratight":
                for a in node.names:
                    yield node.lineno, f"ultratight.{a.name}", ()
            else:
                yield node.lineno, node.module, tuple(a.name for a in node.names)


def _is_module(dotted):
    p = PKG.parent / Path(*dotted.split("."))
    return p.with_suffix(".py").is_file() or (p / "__init__.py").is_file()


@pytest.mark.parametrize("layer", sorted(ALLOWED))
def test_layers_import_only_to_their_left(layer):
    bad = []
    for path in sorted((PKG / layer).rglob("*.py")):
        for line, mod, _ in _imports(path):
            parts = mod.split(".")
            if parts[0] != "ultratight" or len(parts) < 2:
                continue
            target = parts[1]
            if target == layer or target in TOP_LEVEL or target == "__version__" or target in ALLOWED[layer]:
                continue
            bad.append(f"{path.relative_to(PKG.parent)}:{line} imports {mod}")
    assert not bad, "\n".join(bad)


@pytest.mark.parametrize("layer", sorted(INNER))
def test_rooms_inside_a_layer_import_one_way(layer):
    rooms = INNER[layer]
    bad = []
    for path in sorted((PKG / layer).rglob("*.py")):
        rel = path.relative_to(PKG / layer).parts
        room = rel[0] if len(rel) > 1 else ""
        assert room in rooms, f"{path}: room {room!r} of {layer} is not declared in INNER"
        for line, mod, _ in _imports(path):
            parts = mod.split(".")
            if parts[:2] != ["ultratight", layer] or len(parts) < 3:
                continue
            target = parts[2] if parts[2] in rooms else ""
            if target != room and target not in rooms[room]:
                bad.append(f"{path.relative_to(PKG.parent)}:{line} imports {mod}")
    assert not bad, "\n".join(bad)


def test_top_level_modules_import_no_layer():
    for name in TOP_LEVEL:
        for line, mod, _ in _imports(PKG / f"{name}.py"):
            parts = mod.split(".")
            assert not (parts[0] == "ultratight" and len(parts) > 1 and parts[1] in ALLOWED), \
                f"ultratight/{name}.py:{line} imports {mod}"


def test_no_private_name_crosses_a_folder():
    """``from A import _x`` or ``import A as M; M._x`` with A in another folder is a leak: make the
    name public in its home, or move the code that needs it into the same folder."""
    bad = []
    for path in _modules():
        here = path.parent
        tree = ast.parse(path.read_text(), filename=str(path))
        aliases = {}
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module \
                    and node.module.startswith("ultratight"):
                for a in node.names:
                    full = f"{node.module}.{a.name}"
                    if _is_module(full):
                        aliases[a.asname or a.name] = full
                    elif a.name.startswith("_") and not a.name.startswith("__"):
                        home = PKG.parent / Path(*node.module.split("."))
                        home = home if home.is_dir() else home.parent
                        if home != here:
                            bad.append(f"{path.relative_to(PKG.parent)}:{node.lineno} imports {full}")
            elif isinstance(node, ast.Import):
                for a in node.names:
                    if a.name.startswith("ultratight") and a.asname:
                        aliases[a.asname] = a.name
        for node in ast.walk(tree):
            if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) \
                    and node.value.id in aliases and node.attr.startswith("_") and not node.attr.startswith("__"):
                home = PKG.parent / Path(*aliases[node.value.id].split("."))
                home = home if home.is_dir() else home.parent
                if home != here:
                    bad.append(f"{path.relative_to(PKG.parent)}:{node.lineno} uses {aliases[node.value.id]}.{node.attr}")
    assert not bad, "\n".join(bad)


def _lines(path):
    return len(path.read_text().splitlines())


def test_no_folder_holds_more_than_its_share():
    total = sum(_lines(p) for p in _modules())
    folders = {}
    for p in _modules():
        folders[p.parent] = folders.get(p.parent, 0) + _lines(p)
    big = {str(d.relative_to(PKG.parent)): round(n / total, 3) for d, n in folders.items()
           if n > MAX_FOLDER_SHARE * total}
    assert not big, f"folders over {MAX_FOLDER_SHARE:.0%} of {total} lines: {big}"


def _is_kernel(fn):
    return any("jit" in ast.unparse(d) for d in fn.decorator_list)


def _kernel_module(tree):
    doc = ast.get_docstring(tree) or ""
    return "splitting" in doc.lower() and "speed" in doc.lower()


def test_module_and_function_sizes():
    """Modules up to 700 lines (a numba kernel module over it says in its docstring why splitting
    costs speed); functions up to 80 lines outside numba kernels; kernels over 100 lines say why in
    their docstring."""
    bad = []
    for path in _modules():
        tree = ast.parse(path.read_text(), filename=str(path))
        rel = path.relative_to(PKG.parent)
        if _lines(path) > MAX_MODULE_LINES and not _kernel_module(tree):
            bad.append(f"{rel}: {_lines(path)} lines")
        for node in ast.walk(tree):
            if not isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                continue
            n = node.end_lineno - node.lineno + 1
            if _is_kernel(node):
                doc = (ast.get_docstring(node) or "").lower()
                if n > MAX_KERNEL_LINES and "one kernel" not in doc:
                    bad.append(f"{rel}:{node.lineno} kernel {node.name}: {n} lines, no reason given")
            elif n > MAX_FUNCTION_LINES:
                bad.append(f"{rel}:{node.lineno} {node.name}: {n} lines")
    assert not bad, "\n".join(bad)
