"""Whether a change leaves training alone: the same short runs in this working tree and at git
revisions, compared bit for bit.

    python benchmarks/same_training.py --against 3599290 --data-dir ../shared/data

Each config trains `--steps` steps (30 by default) with `python -m mixnerf_eqx.train` in a fresh
process per tree, from that tree's own package and configs, with the same overrides. A run is the
same as the working tree's when the SHA-256 of its final checkpoint's `state.eqx` (every leaf of
the model, optimiser state, occupancy grid, key and step), its training log (timings left out)
and its test metrics are equal. For refactors: a change meant to alter nothing must print
"identical" on every row. The configs are the built-in scene's grid and MLP configs, the
baseline's grid config and, with `--data-dir`, fern 3-view (`llff3_grid`) at 1/8 resolution.
"""

import argparse
import hashlib
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

import harness  # noqa: E402
from quickstart import quickstart_trees, remove_trees  # noqa: E402

# (name, config, overrides): small enough that each run takes seconds on a CPU.
CONFIGS = [
    ("builtin_grid", "builtin_grid", ["data.resolution=32"]),
    ("builtin (MLP)", "builtin", ["data.resolution=32", "model.num_coarse_samples=16", "model.num_fine_samples=16"]),
    ("baseline grid", "builtin_mipnerf_grid", ["data.resolution=32"]),
]
# With the paper's lambda_C ramp, which `llff3_grid` dropped when fern's validation views chose
# that: the same run at revisions from before and after that change, so that only code differs.
FERN = (
    "llff3_grid (fern 1/8)",
    "llff3_grid",
    ["data.scene=fern", "data.image_downscale=8", "data.max_test_views=1", "loss.lambda_colour_start=4.0"],
)
TIMING_KEYS = {"steps_per_s", "seconds", "elapsed_s", "time", "wall_s"}


def run_once(tree: Path, run_dir: Path, config: str, overrides: list[str]) -> dict[str, Any]:
    """Trains in `tree` and returns the digests of what the run wrote."""
    command = [
        sys.executable, "-m", "mixnerf_eqx.train", "--config", config, "--no-progress",
        "--run-dir", str(run_dir), *overrides,
    ]  # fmt: skip
    finished = subprocess.run(
        command, env={**os.environ, "PYTHONPATH": str(tree)}, cwd=tree, capture_output=True, text=True
    )
    if finished.returncode != 0:
        return {"error": finished.stderr.strip().splitlines()[-1] if finished.stderr.strip() else "failed"}
    (checkpoint,) = sorted((run_dir / "checkpoints").glob("*/state.eqx"))[-1:]
    log = [
        {key: value for key, value in json.loads(line).items() if key not in TIMING_KEYS}
        for line in (run_dir / "train_log.jsonl").read_text().splitlines()
    ]
    metrics = json.loads((run_dir / "metrics.json").read_text())
    digest = lambda data: hashlib.sha256(data).hexdigest()[:16]  # noqa: E731
    return {
        "state": digest(checkpoint.read_bytes()),
        "log": digest(json.dumps(log, sort_keys=True).encode()),
        "test": metrics.get("test"),
    }


def main(args: argparse.Namespace) -> None:
    scratch = Path(tempfile.mkdtemp(prefix="same-training-"))
    trees = quickstart_trees(args.against, scratch)
    configs = CONFIGS + ([FERN] if args.data_dir else [])
    common = [f"train.max_steps={args.steps}", "train.eval_every=0"]
    data_dir = [f"data.data_dir={json.dumps(str(Path(args.data_dir).resolve()))}"] if args.data_dir else []
    rows = []
    try:
        for name, config, overrides in configs:
            results = {}
            for label, tree in trees:
                run_dir = scratch / "runs" / f"{config}-{label.replace(' ', '-')}"
                scene = data_dir if config.startswith("llff") else []
                results[label] = run_once(tree, run_dir, config, [*overrides, *common, *scene])
            reference = results["working tree"]
            for label, result in results.items():
                same = "error" not in result and result == reference
                rows.append({"config": name, "tree": label, **result, "same": same})
                verdict = "identical" if same else ("ERROR " + result["error"] if "error" in result else "DIFFERS")
                print(f"{name:24s} {label:14s} state {result.get('state')} log {result.get('log')}  {verdict}")
    finally:
        remove_trees(trees)
    payload = {"against": args.against, "steps": args.steps, "rows": rows, "command": harness.command_line()}
    if args.out:
        harness.write_json(Path(args.out), payload)
    if not all(row["same"] for row in rows):
        raise SystemExit(1)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--against", nargs="+", required=True, help="git revisions to compare with")
    parser.add_argument("--steps", type=int, default=30)
    parser.add_argument("--data-dir", default=None, help="the dataset root (adds fern 3-view)")
    parser.add_argument("--out", default=None, help="write the rows as JSON here")
    main(parser.parse_args())
