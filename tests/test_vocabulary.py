"""Every jaxtyping shape string in the package uses the shared dimension vocabulary.

The vocabulary is documented in `mixnerf_eqx/_custom_types.py`. The test parses each module with `ast`
(nothing is imported), finds every jaxtyping dtype subscript such as `Float[Array, "*batch 3"]` (in
annotations, type aliases or anywhere else), and checks each dimension name after stripping its
modifiers.
"""

import ast
import re
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parent.parent / "mixnerf_eqx"

# The jaxtyping dtype wrappers whose second subscript argument is a shape string.
DTYPES = frozenset(
    {
        "Float",
        "Int",
        "Bool",
        "Shaped",
        "Key",
        "UInt32",
        "UInt8",
        "UInt",
        "Integer",
        "Num",
        "Real",
        "Inexact",
        "Float32",
        "Float64",
        "Int32",
        "Int64",
    }
)

VOCABULARY = frozenset(
    {
        "batch",  # `*batch`: any leading batch dims; `batch`: exactly one flat batch dim
        "num_samples",  # samples along a ray; `num_samples+1` are their edges
        "channels",  # colour channels
        "height",
        "width",
        "num_views",
        "num_pixels",
        "features",
        "resolution",  # grid cells per axis (the occupancy grid, a level of a grid field)
        "levels",  # the levels of a multi-resolution grid encoding
    }
)

# Names outside the shared vocabulary, each for a dimension the shared names cannot express.
JUSTIFIED_EXTRAS = frozenset(
    {
        # Samplers: edge counts not yet tied to `num_samples`, and the draws made from them.
        "num_edges",
        "num_prev_edges",
        "num_draws",
        # Empty-space skipping: a contiguous slice of the sample axis.
        "segment",
        # Input and output sizes of a dense layer or an encoding (they differ within one call).
        "in_features",
        "out_features",
        # Downscaling: the output image size differs from the input's within one call.
        "out_height",
        "out_width",
        # LPIPS backbone: the convolution kernel size.
        "kernel",
        # Hash grid: a level's table entries (fewer than the table size on coarse levels).
        "entries",
        # Grid lookups: the texels or cell corners blended for one point.
        "corners",
        # Training that skips: a batch's samples as one flat list (rays x samples).
        "points",
        # Predictive intervals: one row per interval mass (recalibrated quantile levels).
        "masses",
    }
)

ALLOWED = VOCABULARY | JUSTIFIED_EXTRAS


def _dtype_name(node: ast.expr) -> str | None:
    if isinstance(node, ast.Name):
        return node.id
    if isinstance(node, ast.Attribute):
        return node.attr
    return None


def _shape_strings(tree: ast.AST) -> list[tuple[int, str]]:
    """The (line, shape string) of every jaxtyping dtype subscript in a module."""
    found = []
    for node in ast.walk(tree):
        if not isinstance(node, ast.Subscript) or _dtype_name(node.value) not in DTYPES:
            continue
        if not isinstance(node.slice, ast.Tuple) or len(node.slice.elts) != 2:
            continue
        shape = node.slice.elts[1]
        if isinstance(shape, ast.Constant) and isinstance(shape.value, str):
            found.append((shape.lineno, shape.value))
    return sorted(found)


def dimension_names(shape: str) -> list[str]:
    """The bare dimension names of one shape string, modifiers and fixed sizes removed."""
    names = []
    for token in shape.split():
        name = token.lstrip("*#_?")
        name = re.sub(r"[+-]\d+$", "", name)
        if name in ("", "...") or name.isdigit():
            continue
        names.append(name)
    return names


def test_dimension_names_strips_modifiers():
    assert dimension_names("*#batch num_samples+1 3 ... _ _kernel num_edges-1") == [
        "batch",
        "num_samples",
        "kernel",
        "num_edges",
    ]
    assert dimension_names("") == []


def _unknown_names() -> list[str]:
    problems = []
    for path in sorted(PACKAGE.rglob("*.py")):
        tree = ast.parse(path.read_text(), filename=str(path))
        for line, shape in _shape_strings(tree):
            for name in dimension_names(shape):
                if name not in ALLOWED:
                    relative = path.relative_to(PACKAGE.parent)
                    problems.append(f"{relative}:{line}: unknown dimension {name!r} in {shape!r}")
    return problems


def test_scanner_finds_shape_strings():
    # The package is annotated throughout; an empty scan means the scanner is broken.
    count = sum(len(_shape_strings(ast.parse(p.read_text()))) for p in PACKAGE.rglob("*.py"))
    assert count > 100


def test_every_dimension_name_is_in_the_vocabulary():
    problems = _unknown_names()
    if problems:
        pytest.fail("dimension names outside the vocabulary:\n" + "\n".join(problems))
