"""Per-seed figures of a written record, laid out as a sweep folder for `sweep_verdict.py`.

Run folders are not kept, but the records under `results/` hold every seed's validation and
test figures. This writes `OUT/SCENE/seed_N/metrics.json` from one arm of a record, so that a
verdict can pair new runs with runs made earlier without training them again:

    python benchmarks/collect_runs.py benchmarks/results/full_res_fern_noramp_newval_runs.json \
        noramp --scene fern --out runs/verdict/shipped
    python benchmarks/collect_runs.py benchmarks/results/fern_probe_distortion.json mixnerf \
        --out runs/verdict/distortion --seeds 0 1 --step 14000

Two kinds of record are read: a runs record (`{"command": ..., "runs": {ARM: {SEED: m}}}`, one
scene, which `--scene` names and the command must train) and a verdict record written by
`sweep_verdict.py --out` (ARM is `mixnerf` or `baseline`, the first and second sweep; a run
it lists without figures, one that diverged, is written without figures and stays failed).
Each `metrics.json` written says which record it came from (`"collected_from"`); an existing
seed folder is an error, and nothing is written unless every seed can be. A verdict record
keeps no step count: `--step` writes the one its title gives, so that `sweep_verdict.py` can
check the pairs' steps.
"""

import argparse
import json
import sys
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

from sweep_verdict import runs_from_record  # noqa: E402


def _is_runs_record(record: dict[str, Any]) -> bool:
    runs = record.get("runs")
    return isinstance(runs, dict) and "scenes" not in record and all(
        isinstance(arm, dict) and all(isinstance(m, dict) for m in arm.values()) for arm in runs.values()
    )


def _is_verdict_record(record: dict[str, Any]) -> bool:
    return isinstance(record.get("scenes"), dict) and "names" in record and "unfinished" in record


def from_runs_record(record: dict[str, Any], arm: str, scene: str | None) -> dict[str, dict[int, Any]]:
    if scene is None:
        raise SystemExit("a runs record holds one scene's runs: say which with --scene")
    # The record names its scene only in the command that made it: the label must be there.
    if f"--scenes {scene}" not in record.get("command", ""):
        command = record.get("command", "")
        raise SystemExit(f"the record's command does not train --scenes {scene}: {command!r}")
    if arm not in record["runs"]:
        raise SystemExit(f"no arm {arm!r} in the record (it has {', '.join(sorted(record['runs']))})")
    return {scene: {int(seed): metrics for seed, metrics in record["runs"][arm].items()}}


def from_verdict_record(record: dict[str, Any], arm: str, scene: str | None) -> dict[str, dict[int, Any]]:
    if arm not in ("mixnerf", "baseline"):
        raise SystemExit(
            f"a verdict record's arms are 'mixnerf' and 'baseline' (its first and second), not {arm!r}"
        )
    # `sweep_verdict.runs_from_record` keeps every run an arm finished, a run without figures
    # (one that diverged) included, so that it stays a failed run.
    first, second = runs_from_record(record)
    scenes = {name: runs for name, runs in (first if arm == "mixnerf" else second).items()}
    if scene is not None:
        scenes = {name: runs for name, runs in scenes.items() if name == scene}
    if not scenes:
        raise SystemExit(f"no scene {scene!r} in the record (it has {', '.join(sorted(record['scenes']))})")
    return scenes


def collect(
    record_path: Path,
    arm: str,
    out: Path,
    scene: str | None,
    seeds: list[int] | None,
    step: int | None = None,
) -> list[Path]:
    """Writes one `metrics.json` per seed of `arm`; checks everything before writing anything."""
    record = json.loads(record_path.read_text())
    if _is_runs_record(record):
        scenes = from_runs_record(record, arm, scene)
    elif _is_verdict_record(record):
        scenes = from_verdict_record(record, arm, scene)
    else:
        raise SystemExit(f"{record_path}: neither a runs record nor a verdict record (of sweep_verdict.py)")
    planned = []
    for name, runs in scenes.items():
        missing = sorted(set(seeds or []) - set(runs))
        if missing:
            raise SystemExit(f"{name}: the record has no seed {', '.join(map(str, missing))} for {arm!r}")
        for seed in sorted(runs):
            if seeds is not None and seed not in seeds:
                continue
            folder = out / name / f"seed_{seed}"
            if folder.exists():
                raise SystemExit(f"{folder}: exists already (nothing written)")
            metrics = {**runs[seed], "collected_from": f"{record_path.name}, arm {arm}"}
            if step is not None:
                if metrics.get("step", step) != step:
                    said = metrics["step"]
                    raise SystemExit(f"{name}/seed_{seed}: the record says step {said}, not {step}"
                                     " (nothing written)")
                metrics["step"] = step
            planned.append((folder, metrics))
    for folder, metrics in planned:
        folder.mkdir(parents=True)
        (folder / "metrics.json").write_text(json.dumps(metrics, indent=1) + "\n")
    return [folder for folder, _ in planned]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("record", type=Path, help="a runs record or a verdict record (JSON)")
    parser.add_argument("arm", help="the arm whose runs to lay out")
    parser.add_argument("--out", type=Path, required=True, help="the sweep-like folder to write into")
    parser.add_argument("--scene", help="the scene (a runs record needs it; filters a verdict record)")
    parser.add_argument("--seeds", type=int, nargs="+", help="only these seeds (default: all the arm has)")
    parser.add_argument(
        "--step",
        type=int,
        help="the step the runs ended at, where the record keeps none (a verdict record's title says it)",
    )
    args = parser.parse_args(argv)
    if not args.record.is_file():
        raise SystemExit(f"{args.record}: no such record")
    for folder in collect(args.record, args.arm, args.out, args.scene, args.seeds, args.step):
        print(f"wrote {folder / 'metrics.json'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
