"""Every file under `benchmarks/results/` is named by a document, and every result a document
names exists: a figure nobody can trace to its file, or a file no page explains, is a defect.

A document names a result as `results/NAME` (or `benchmarks/results/NAME`), where `NAME` may
hold one brace group: `results/fidelity_cpu.{jsonl,md}` names both files.
"""

import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results"
DOCUMENTS = [
    REPO / "README.md",
    *sorted((REPO / "benchmarks").glob("*.md")),
    *sorted((REPO / "docs").glob("*.md")),
]
REFERENCE = re.compile(r"results/([A-Za-z0-9_.\-]*(?:\{[A-Za-z0-9_.,\-]+\}[A-Za-z0-9_.\-]*)?)")


def expand(name: str) -> list[str]:
    """`a{b,c}d` -> `abd`, `acd`; a name without braces is itself."""
    match = re.fullmatch(r"([^{]*)\{([^}]*)\}(.*)", name)
    if match is None:
        return [name]
    head, options, tail = match.groups()
    return [head + option + tail for option in options.split(",")]


def referenced() -> dict[str, list[str]]:
    """Each named result file -> the documents that name it."""
    found: dict[str, list[str]] = {}
    for document in DOCUMENTS:
        for raw in REFERENCE.findall(document.read_text()):
            for name in expand(raw.rstrip(".")):
                if name and "." in name:
                    found.setdefault(name, []).append(str(document.relative_to(REPO)))
    return found


def test_the_expansion_of_a_brace_group():
    assert expand("f.{jsonl,md,_summary.json}") == ["f.jsonl", "f.md", "f._summary.json"]
    assert expand("error_vs_time_cpu_{builtin,lego}.png") == [
        "error_vs_time_cpu_builtin.png",
        "error_vs_time_cpu_lego.png",
    ]
    assert expand("plain.json") == ["plain.json"]


def test_every_result_file_is_named_by_a_document():
    names = referenced()
    unnamed = sorted(path.name for path in RESULTS.iterdir() if path.is_file() and path.name not in names)
    assert not unnamed, f"result files no document names: {unnamed}"


def test_every_named_result_exists():
    missing = {name: where for name, where in referenced().items() if not (RESULTS / name).is_file()}
    assert not missing, f"named results that do not exist: {missing}"
