"""docs/architecture.md's layers hold: a module of ``evlatcorr`` imports only from its own layer or the layers below,
and every module has a layer."""

from __future__ import annotations

import ast
import re

from tests.commands import ROOT

PACKAGE = ROOT / "evlatcorr"
PLUMBING = {"", "__main__", "_lazy"}  # the package itself, ``python -m evlatcorr`` and its lazy attribute loader


def _layers() -> dict[str, int]:
    """Module name (``io.*``: a subpackage) -> its layer, from the table in docs/architecture.md."""
    layers = {}
    for line in (ROOT / "docs" / "architecture.md").read_text().splitlines():
        row = re.match(r"\| (\d)\. [^|]+ \| (.+?) \| ", line)
        if row:
            layers |= {name: int(row.group(1)) for name in re.findall(r"`([a-z_.*]+)`", row.group(2))}
    return layers


def _layer_of(module: str, layers: dict[str, int]) -> int | None:
    parts = module.split(".")
    for k in range(len(parts), 0, -1):
        prefix = ".".join(parts[:k])
        for key in (prefix, prefix + ".*"):
            if key in layers:
                return layers[key]
    return None


def _modules() -> dict[str, ast.Module]:
    out = {}
    for path in PACKAGE.rglob("*.py"):
        parts = path.relative_to(PACKAGE).with_suffix("").parts
        out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = ast.parse(path.read_text())
    return out


def _imported(tree: ast.Module) -> list[tuple[str, int]]:
    """The ``evlatcorr`` modules a file imports anywhere in it (inside functions too), without the prefix."""
    names = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.append((node.module, node.lineno))
        elif isinstance(node, ast.Import):
            names += [(alias.name, node.lineno) for alias in node.names]
    return [(name[len("evlatcorr."):], line) for name, line in names if name.startswith("evlatcorr.")]


def test_the_table_names_a_layer_for_every_module():
    layers = _layers()
    assert len(layers) > 30  # the table was read
    missing = sorted(m for m in _modules() if m not in PLUMBING and _layer_of(m, layers) is None)
    assert not missing, f"modules without a layer in docs/architecture.md: {missing}"


def test_no_module_imports_from_a_layer_above_its_own():
    layers = _layers()
    upward = []
    for module, tree in _modules().items():
        own = _layer_of(module, layers)
        if own is None:
            continue
        for imported, line in _imported(tree):
            other = _layer_of(imported, layers)
            if other is not None and other > own:
                upward.append(f"{module} (layer {own}) imports {imported} (layer {other}) at line {line}")
    assert not upward, "\n".join(upward)
