"""Strict JSON for every metrics file: no bare `NaN` or `Infinity`.

Python's `json` writes non-finite floats as `NaN`, `Infinity` and `-Infinity`, which strict
parsers (JavaScript's `JSON.parse`, `jq`, most other languages) reject. `dumps` writes each
such number as `null` and, for a mapping at the top, says which ones and why under the key
`"non_finite"` (a path such as `test.psnr` or `history[3].loss`, and what the number was).
"""

import json
import math
from typing import Any

import numpy as np

NON_FINITE_KEY = "non_finite"


def _clean(value: Any, path: str, found: dict[str, str]) -> Any:
    if isinstance(value, dict):
        return {
            key: _clean(item, f"{path}.{key}" if path else str(key), found) for key, item in value.items()
        }
    if isinstance(value, list | tuple):
        return [_clean(item, f"{path}[{index}]", found) for index, item in enumerate(value)]
    if isinstance(value, np.ndarray | np.generic) and np.ndim(value) == 0:
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        found[path or "value"] = f"{value} (not a finite number: written as null)"
        return None
    return value


def strict(value: Any) -> tuple[Any, dict[str, str]]:
    """`value` with every non-finite float replaced by `None`, and the replaced paths."""
    found: dict[str, str] = {}
    return _clean(value, "", found), found


def dumps(value: Any, **kwargs: Any) -> str:
    """`json.dumps(value, **kwargs)` as strict JSON (see the module's docstring)."""
    clean, found = strict(value)
    if found and isinstance(clean, dict):
        clean = {**clean, NON_FINITE_KEY: {**clean.get(NON_FINITE_KEY, {}), **found}}
    return json.dumps(clean, allow_nan=False, **kwargs)
