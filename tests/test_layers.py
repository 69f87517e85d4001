"""The package's layers, as `docs/architecture.md` lists them, hold in the code: a module
imports only modules of its own layer or of the layers above it, and every module is listed."""

import ast
import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PACKAGE = REPO / "mixnerf_eqx"
MODULE = re.compile(r"(_?[a-z_]+\.py|_?[a-z_]+/)")


def documented_layers() -> list[list[str]]:
    """The layers of the architecture's diagram, top first: its first code block, the names
    at the start of each line (several, comma-separated, on one line), `|` lines between."""
    text = (REPO / "docs" / "architecture.md").read_text()
    block = text.split("```")[1]
    layers: list[list[str]] = [[]]
    for line in block.splitlines():
        if line.strip() == "|":
            layers.append([])
        elif line and not line[0].isspace():
            head = line.split("   ")[0] if "," in line.split("  ")[0] else line.split()[0]
            layers[-1] += [name.strip() for name in head.split(",") if name.strip()]
    return layers


def unit(path: Path) -> str:
    """The listed unit a file belongs to: `name.py` for a top-level module, `name/` for a
    subpackage."""
    relative = path.relative_to(PACKAGE)
    return relative.parts[0] + "/" if len(relative.parts) > 1 else relative.name


def imported_units(path: Path) -> set[str]:
    """The package's units that `path` imports (relative or absolute imports)."""
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.level > 0:
            base = path.parent
            for _ in range(node.level - 1):
                base = base.parent
            target = base.joinpath(*node.module.split(".")) if node.module else base
            names = [target / alias.name for alias in node.names] if target == PACKAGE else [target]
        elif isinstance(node, ast.ImportFrom) and node.module == "mixnerf_eqx":
            names = [PACKAGE / alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and (node.module or "").startswith("mixnerf_eqx."):
            names = [PACKAGE / node.module.split(".")[1]]
        elif isinstance(node, ast.Import):
            names = [PACKAGE / a.name.split(".")[1] for a in node.names if a.name.startswith("mixnerf_eqx.")]
        else:
            continue
        for name in names:
            resolved = name.resolve()
            if resolved == PACKAGE.resolve() or PACKAGE.resolve() not in resolved.parents:
                continue
            top = resolved.relative_to(PACKAGE.resolve()).parts[0]
            found.add(top + "/" if (PACKAGE / top).is_dir() else top.removesuffix(".py") + ".py")
    return found - {unit(path)}


def package_units() -> set[str]:
    return {unit(path) for path in PACKAGE.rglob("*.py") if "configs" not in path.relative_to(PACKAGE).parts}


def test_every_module_is_in_one_documented_layer():
    layers = documented_layers()
    listed = [name for layer in layers for name in layer]
    assert len(layers) >= 6 and all(MODULE.fullmatch(name) for name in listed), layers
    assert len(listed) == len(set(listed)), "a module is listed twice"
    assert set(listed) == package_units(), set(listed) ^ package_units()


def test_no_module_imports_a_lower_layer():
    layer_of = {name: index for index, layer in enumerate(documented_layers()) for name in layer}
    wrong = []
    for path in sorted(PACKAGE.rglob("*.py")):
        if "configs" in path.relative_to(PACKAGE).parts:
            continue
        here = unit(path)
        for imported in sorted(imported_units(path)):
            if layer_of[imported] > layer_of[here]:
                wrong.append(
                    f"{path.relative_to(REPO)} imports {imported} "
                    f"(layer {layer_of[imported]} > {layer_of[here]})"
                )
    assert not wrong, "\n".join(wrong)


def test_the_check_sees_a_lower_import(tmp_path):
    """The import reader finds relative and absolute imports of the package's modules."""
    sample = PACKAGE / "_field" / "base.py"
    assert imported_units(sample) == {"_custom_types.py"}
    assert {"_train_state.py", "_sharding.py", "_checkpoint.py"} <= imported_units(PACKAGE / "_train.py")
    assert "_train.py" in imported_units(PACKAGE / "__init__.py")


def test_benchmarks_use_the_public_api():
    """Benchmarks import `mixnerf_eqx` as users do: no private module (`mixnerf_eqx._name`)."""
    private = []
    for path in sorted((REPO / "benchmarks").glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            names = []
            if isinstance(node, ast.ImportFrom) and node.module:
                names = [node.module]
            elif isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            private += [f"{path.name}: {name}" for name in names if name.startswith("mixnerf_eqx._")]
    assert not private, private
