"""Rank the cameras to capture next: `python -m mixnerf_eqx.next_view RUN_DIR [--poses FILE] [...]`.

Loads the run's model and ranks candidate cameras by the model's mean predictive spread there
(`mixnerf_eqx._predictive.next_view`): by default the scene's validation cameras (views the
run holds but did not train on), or the camera-to-world matrices of `--poses` (a `.npy` file of
shape `(n, 3, 4)` or `(n, 4, 4)`, in the scene's convention). Prints the ranking, best first,
with each camera's distance to the nearest training camera; `--out FILE.json` writes it too.
The test views are never candidates.
"""

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from .._predictive.next_view import SCORES, check_candidate_poses, farthest_first, next_view
from .._runs.run_folder import restore_run
from .._util.compilation_cache import add_compilation_cache_argument
from .._util.typecheck import add_typecheck_argument
from .common import add_run_arguments, run_command


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="python -m mixnerf_eqx.next_view", description=__doc__.split("\n")[0])
    add_run_arguments(parser)
    parser.add_argument("--poses", type=Path, default=None, help="candidate camera-to-world matrices (.npy)")
    parser.add_argument("--score", choices=SCORES, default="depth", help="the spread ranked by (default: depth)")
    parser.add_argument("--width", type=int, default=48, help="pixels across each candidate's render (default 48)")
    parser.add_argument("--top", type=int, default=0, help="print this many candidates (0: all)")
    parser.add_argument("--out", type=Path, default=None, help="also write the ranking to this JSON file")
    add_typecheck_argument(parser)
    add_compilation_cache_argument(parser)
    return parser.parse_args(argv)


def _candidates(run, poses_file: Path | None) -> tuple[np.ndarray, list[str]]:
    if poses_file is not None:
        try:
            poses = np.load(poses_file, allow_pickle=False)
        except FileNotFoundError:
            raise ValueError(f"--poses {poses_file}: no such file") from None
        except (ValueError, OSError, EOFError) as error:
            raise ValueError(
                f"--poses {poses_file}: not a .npy array of camera-to-world matrices ({error})"
            ) from None
        if not isinstance(poses, np.ndarray):
            poses.close()
            raise ValueError(f"--poses {poses_file}: give a .npy file holding one array, not an .npz archive")
        poses = check_candidate_poses(poses)
        return poses, [f"pose {index}" for index in range(len(poses))]
    val = run.dataset.val
    if val is None or val.num_views == 0:
        raise ValueError(
            f"{run.dataset.name} has no validation cameras to rank: give candidate cameras with --poses FILE.npy"
        )
    return np.asarray(val.camtoworlds), [f"view {view_id}" for view_id in val.ids]


def run(args: argparse.Namespace) -> dict:
    if args.width < 2:
        raise ValueError(f"--width must be at least 2 pixels, got {args.width}")
    if args.top < 0:
        raise ValueError(f"--top must be 0 (all) or positive, got {args.top}")
    restored = restore_run(args.run_dir, checkpoint=args.checkpoint, data_dir=args.data_dir)
    if restored.model.mixture is None:
        raise ValueError("this run's model has no mixture heads (the mip-NeRF baseline): it predicts no spread")
    dataset = restored.dataset
    poses, names = _candidates(restored, args.poses)
    ranking = next_view(
        restored.model, dataset.train, poses, dataset.near, dataset.far, score=args.score, width=args.width
    )
    train_centres = np.asarray(dataset.train.camtoworlds, np.float64)[:, :3, 3]
    centres = np.asarray(poses, np.float64)[:, :3, 3]
    distance = np.linalg.norm(centres[:, None] - train_centres[None], axis=-1).min(axis=1)
    rows = [
        {
            "rank": rank + 1,
            "candidate": names[index],
            "index": int(index),
            "score": float(ranking.scores[index]),
            "opacity": float(ranking.opacity[index]),
            "distance_to_training": float(distance[index]),
        }
        for rank, index in enumerate(ranking.order)
    ]
    shown = rows if args.top == 0 else rows[: args.top]
    print(f"{'rank':>4}  {'candidate':<12} {args.score + ' spread':>13} {'opacity':>8} {'to training':>12}")
    for row in shown:
        print(
            f"{row['rank']:>4}  {row['candidate']:<12} {row['score']:>13.4f} {row['opacity']:>8.3f} "
            f"{row['distance_to_training']:>12.3f}"
        )
    farthest = names[int(farthest_first(poses, dataset.train.camtoworlds)[0])]
    print(f"\ncapture next: {rows[0]['candidate']} (the camera farthest from the training cameras: {farthest})")
    result = {"run_dir": str(args.run_dir), "step": restored.step, "score": args.score, "ranking": rows}
    if args.out is not None:
        args.out.write_text(json.dumps(result, indent=2))
        print(f"ranking: {args.out}")
    return result


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    return run_command(args, lambda: run(args), interrupted="ranking stopped")


if __name__ == "__main__":
    sys.exit(main())
