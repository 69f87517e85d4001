"""The package's layers, as `docs/architecture.md` lists them, hold in the code: a module
imports only modules of its own layer or of the layers above it, and every module is listed."""

import ast
import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PACKAGE = REPO / "mixnerf_eqx"
UNIT = re.compile(r"(_?[a-z_]+/)*_?[a-z_]+(\.py|/)")


def documented_layers() -> list[list[str]]:
    """The layers of the architecture's diagram, top first: its first code block, the names
    at the start of each line (several, comma-separated, on one line), `|` lines between. A
    name is a path inside the package: a module (`_nn/rays.py`) or a folder (`data/`)."""
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


def package_files() -> list[Path]:
    return sorted(p for p in PACKAGE.rglob("*.py") if "configs" not in p.relative_to(PACKAGE).parts)


def is_group_marker(path: Path) -> bool:
    """A group folder's `__init__.py` (`_nn/`, `_train/`, ...): a docstring and nothing else, so
    importing a group imports none of its modules."""
    body = ast.parse(path.read_text()).body
    return path.name == "__init__.py" and len(body) == 1 and isinstance(body[0], ast.Expr)


def unit(path: Path, units: list[str]) -> str | None:
    """The listed unit a file belongs to: itself, or the deepest listed folder holding it."""
    relative = path.relative_to(PACKAGE).as_posix()
    held = [name for name in units if name == relative or (name.endswith("/") and relative.startswith(name))]
    return max(held, key=len) if held else None


def module_file(parts: list[str]) -> Path | None:
    """The file of the package's module `mixnerf_eqx.<parts>` (a module or a package)."""
    path = PACKAGE.joinpath(*parts)
    if path.with_suffix(".py").is_file():
        return path.with_suffix(".py")
    return path / "__init__.py" if (path / "__init__.py").is_file() else None


def imported_files(path: Path) -> set[Path]:
    """The package's files that `path` imports (relative or absolute imports; for a module with
    a stub beside it, such as the lazily loading `__init__.py`, the stub's imports too)."""
    found: set[Path | None] = set()
    here = list(path.parent.relative_to(PACKAGE).parts)
    stub = path.with_suffix(".pyi")
    sources = [path.read_text(), *([stub.read_text()] if stub.is_file() else [])]
    for node in (node for source in sources for node in ast.walk(ast.parse(source))):
        if isinstance(node, ast.ImportFrom) and node.level > 0:
            base = here[: len(here) - (node.level - 1)] + (node.module.split(".") if node.module else [])
        elif isinstance(node, ast.ImportFrom) and (node.module or "").split(".")[0] == "mixnerf_eqx":
            base = node.module.split(".")[1:]
        elif isinstance(node, ast.Import):
            found |= {
                module_file(a.name.split(".")[1:]) for a in node.names if a.name.startswith("mixnerf_eqx.")
            }
            continue
        else:
            continue
        for alias in node.names:
            found.add(module_file(base + [alias.name]) or module_file(base))
    return {file for file in found if file is not None} - {path}


def imported_units(path: Path, units: list[str]) -> set[str]:
    return {unit(file, units) for file in imported_files(path)} - {unit(path, units), None}


def test_every_module_is_in_one_documented_layer():
    layers = documented_layers()
    listed = [name for layer in layers for name in layer]
    assert len(layers) >= 6 and all(UNIT.fullmatch(name) for name in listed), layers
    assert len(listed) == len(set(listed)), "a module is listed twice"
    unlisted = [p for p in package_files() if unit(p, listed) is None and not is_group_marker(p)]
    assert not unlisted, f"not in docs/architecture.md: {unlisted}"
    empty = [name for name in listed if not any(unit(p, listed) == name for p in package_files())]
    assert not empty, f"listed in docs/architecture.md but not in the package: {empty}"


def test_no_module_imports_a_lower_layer():
    layers = documented_layers()
    listed = [name for layer in layers for name in layer]
    layer_of = {name: index for index, layer in enumerate(layers) for name in layer}
    wrong = []
    for path in package_files():
        here = unit(path, listed)
        if here is None:
            continue
        for imported in sorted(imported_units(path, listed)):
            if layer_of[imported] > layer_of[here]:
                wrong.append(
                    f"{path.relative_to(REPO)} imports {imported} "
                    f"(layer {layer_of[imported]} > {layer_of[here]})"
                )
    assert not wrong, "\n".join(wrong)


def test_the_check_sees_a_lower_import():
    """The import reader finds relative and absolute imports of the package's modules, down to
    the module inside a group, and a group's marker imports nothing."""
    listed = [name for layer in documented_layers() for name in layer]
    assert imported_units(PACKAGE / "_nn" / "field" / "base.py", listed) == {"_custom_types.py"}
    loop = imported_units(PACKAGE / "_runs" / "loop.py", listed)
    assert {"_train/state.py", "_train/sharding.py", "_runs/checkpoint.py", "_util/json_io.py"} <= loop
    assert {"_runs/loop.py", "data/", "runs.py", "nn.py", "_util/moved.py"} <= imported_units(
        PACKAGE / "__init__.py", listed
    )
    assert {"_util/allocator.py", "_util/typecheck.py"} <= imported_units(PACKAGE / "runtime.py", listed)
    assert is_group_marker(PACKAGE / "_nn" / "__init__.py")
    assert not is_group_marker(PACKAGE / "_nn" / "field" / "__init__.py")


def test_benchmarks_use_the_public_api():
    """Benchmarks import `mixnerf_eqx` as users do: no private module (`mixnerf_eqx._name`)."""
    private = []
    for path in sorted((REPO / "benchmarks").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            names = []
            if isinstance(node, ast.ImportFrom) and node.module:
                names = [node.module]
            elif isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            private += [f"{path.name}: {name}" for name in names if name.startswith("mixnerf_eqx._")]
    assert not private, private


def test_no_import_runs_back_up_between_folders():
    """The package's folders import one another without a cycle (`_predictive` uses the chunked
    map from `_nn`, not from `_inference`, whose viewer uses `_predictive`)."""
    import graphlib

    def folder(path: Path) -> str:
        parts = path.relative_to(PACKAGE).parts
        return parts[0] if len(parts) > 1 else parts[0].removesuffix(".py")

    graph: dict[str, set[str]] = {}
    for path in package_files():
        graph.setdefault(folder(path), set()).update(
            folder(file) for file in imported_files(path) if folder(file) != folder(path)
        )
    order = list(graphlib.TopologicalSorter(graph).static_order())  # CycleError on a cycle
    assert order.index("_nn") < order.index("_predictive") < order.index("_inference") < order.index("_runs")
    assert order.index("_train") < order.index("_runs")
