"""How well can any method do on the quick start's held-out views, given only its 4 training views?

A ceiling for the built-in scene, computed in float64 numpy with the scene's own ray caster. Every
held-out pixel that hits an object is given its true 3D point (perfect geometry) and is filled by
reprojection from the training cameras that see that point:

- `exact`: the colour the scene has at that point seen from the nearest (in angle) training camera
  that sees it, shaded exactly (training images of infinite resolution). It differs from the truth
  only by view-dependent shading (the specular highlight) and by the pixels no training camera sees.
- `bilinear`: the same point sampled bilinearly from the 64 x 64 training image itself, as a model
  that has learnt perfect geometry could at best interpolate it.

Pixels that no training camera sees are filled with the mean colour of the training views' object
pixels (no method can know more than a guess there); background pixels are white, as in the truth.
The reported PSNR is the mean over the held-out views of each view's PSNR, as `eval` reports it.

`--run RUN_DIR` (a run on the built-in scene) adds, under `"run"`: the run's own held-out PSNR;
`reprojected`, the same bilinear reprojection through the run's geometry instead of the truth
(its rendered depth where its opacity exceeds 0.5, white elsewhere; a training camera sees the
point where the run's depth of that camera agrees within 0.2); and per shape (and the
background) the share of the run's squared error, its mean opacity and its mean signed depth
error (positive: behind the true surface).

    python benchmarks/builtin_ceiling.py [--resolution 64] [--views 4] [--run RUN_DIR] [--out FILE.json]
"""

import argparse
import json
from pathlib import Path

import numpy as np

import mixnerf_eqx as mx
from mixnerf_eqx.data import procedural as scene
from mixnerf_eqx.metrics import mse_to_psnr


def _project(
    points: np.ndarray, camtoworld: np.ndarray, focal: float, resolution: int
) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates (column, row; pixel centres at +0.5) and a flag for points in front."""
    rotation, origin = camtoworld[:, :3], camtoworld[:, 3]
    local = (points - origin) @ rotation  # world to camera: R^T (p - o)
    depth = -local[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        cols = local[..., 0] / depth * focal + resolution / 2
        rows = -local[..., 1] / depth * focal + resolution / 2
    return np.stack([cols, rows], axis=-1), depth > 0


def _bilinear(image: np.ndarray, coords: np.ndarray) -> np.ndarray:
    """Samples `image` at pixel coordinates, clamping at the border."""
    size = image.shape[0]
    x = np.clip(coords[..., 0] - 0.5, 0.0, size - 1.0)
    y = np.clip(coords[..., 1] - 0.5, 0.0, size - 1.0)
    x0 = np.clip(np.floor(x).astype(int), 0, size - 2)
    y0 = np.clip(np.floor(y).astype(int), 0, size - 2)
    fx, fy = (x - x0)[..., None], (y - y0)[..., None]
    top = image[y0, x0] * (1 - fx) + image[y0, x0 + 1] * fx
    bottom = image[y0 + 1, x0] * (1 - fx) + image[y0 + 1, x0 + 1] * fx
    return top * (1 - fy) + bottom * fy


def _mean_psnr(estimates: np.ndarray, truths: np.ndarray) -> float:
    return float(
        np.mean([mse_to_psnr(float(np.mean((e - g) ** 2))) for e, g in zip(estimates, truths, strict=True)])
    )


def _test_rays(poses: np.ndarray, resolution: int) -> tuple[np.ndarray, np.ndarray]:
    """Origins and (unnormalised, camera z = -1) directions of every pixel of `poses`, float64."""
    camera_dirs = mx.nn.pixel_directions(scene._focal(resolution), resolution, resolution)
    directions = np.einsum("nij,hwj->nhwi", poses[:, :, :3], camera_dirs)
    return np.broadcast_to(poses[:, None, None, :, 3], directions.shape), directions


def run_report(run_dir: Path) -> dict:
    """The run's error by shape, and the ceiling's reprojection through the run's own geometry."""
    run = mx.runs.restore_run(run_dir)
    dataset, model = run.dataset, run.model
    if dataset.name != "builtin":
        raise ValueError(f"{run_dir} is a run on {dataset.name!r}, not on the built-in scene")
    resolution = dataset.test.images.shape[1]
    test = mx.render_views(model, dataset.test, dataset.near, dataset.far)
    train = mx.render_views(model, dataset.train, dataset.near, dataset.far)
    truth = dataset.test.images.astype(np.float64)
    test_poses = dataset.test.camtoworlds.astype(np.float64)
    train_poses = dataset.train.camtoworlds.astype(np.float64)
    origins, directions = _test_rays(test_poses, resolution)
    true_t, _, shape_ids = scene._intersect_scene(origins, directions)

    foreground = test.acc > 0.5
    points = origins + np.where(foreground, test.depth, 0.0)[..., None] * directions
    train_depth = np.where(train.acc > 0.5, train.depth, np.inf)
    train_images = dataset.train.images.astype(np.float64)
    estimate = np.tile(train_images[np.isfinite(dataset.train.depths)].mean(axis=0), test.depth.shape + (1,))
    best_cos = np.full(test.depth.shape, -np.inf)
    test_viewdirs = directions / np.linalg.norm(directions, axis=-1, keepdims=True)
    for index, pose in enumerate(train_poses):
        coords, in_front = _project(points, pose, dataset.train.focal, resolution)
        in_frame = in_front & np.all((coords >= 0) & (coords <= resolution), axis=-1)
        z = -((points - pose[:, 3]) @ pose[:, :3])[..., 2]
        seen_z = _bilinear(
            np.where(np.isfinite(train_depth[index]), train_depth[index], 1e3)[..., None], coords
        )
        visible = foreground & in_frame & (np.abs(seen_z[..., 0] - z) < 0.2)
        viewdirs = points - pose[:, 3]
        cosine = np.sum(viewdirs / np.linalg.norm(viewdirs, axis=-1, keepdims=True) * test_viewdirs, axis=-1)
        better = visible & (cosine > best_cos)
        estimate = np.where(better[..., None], _bilinear(train_images[index], coords), estimate)
        best_cos = np.where(better, cosine, best_cos)
    estimate = np.where(foreground[..., None], estimate, 1.0)

    squared = np.mean((test.rgb - truth) ** 2, axis=-1)
    shapes = {}
    for shape, name in ((-1, "background"), (0, "disc"), (1, "sphere"), (2, "box"), (3, "cylinder")):
        mask = shape_ids == shape
        entry = {
            "pixel_fraction": float(mask.mean()),
            "error_share": float(squared[mask].sum() / squared.sum()),
            "mean_opacity": float(test.acc[mask].mean()),
        }
        if shape >= 0:
            entry["mean_signed_depth_error"] = float(np.mean((test.depth - true_t)[mask]))
        shapes[name] = entry
    return {
        "run_dir": str(run_dir),
        "step": int(run.step),
        "psnr": _mean_psnr(test.rgb, truth),
        "reprojected": _mean_psnr(estimate, truth),
        "shapes": shapes,
    }


def ceiling(resolution: int, num_train_views: int, num_test_views: int) -> dict:
    train_poses = scene._train_poses(num_train_views)
    test_poses = scene._test_poses(num_test_views)
    train_images, train_depths = scene._render(train_poses, resolution)
    test_images, _ = scene._render(test_poses, resolution)
    focal = scene._focal(resolution)

    origins, directions = _test_rays(test_poses, resolution)
    t, normals, shape_ids = scene._intersect_scene(origins, directions)
    hit = np.isfinite(t)
    # Pixels that miss every shape take the scene's centre as their point: a harmless stand-in
    # (their estimate is white whatever it gives), never a camera's own position.
    points = np.where(hit[..., None], origins + scene._finite(t)[..., None] * directions, scene.LOOK_AT)
    test_viewdirs = directions / np.linalg.norm(directions, axis=-1, keepdims=True)

    fill = train_images[np.isfinite(train_depths)].mean(axis=0)

    # For every training camera: does it see the point (in frame and unoccluded), from which angle?
    best_cos = np.full(t.shape, -np.inf)
    exact = np.tile(fill, t.shape + (1,))
    bilinear = exact.copy()
    albedo = scene._albedo(points, normals, shape_ids)
    # Whether the light reaches a point does not depend on the camera: one shadow ray each.
    towards_test = scene._facing(normals, test_viewdirs)
    shadow_t, _, _ = scene._intersect_scene(
        points + 1e-6 * towards_test, np.broadcast_to(scene.LIGHT_DIRECTION, points.shape)
    )
    light = np.isinf(shadow_t).astype(np.float64)
    for index, pose in enumerate(train_poses):
        coords, in_front = _project(points, pose, focal, resolution)
        in_frame = in_front & np.all((coords >= 0) & (coords <= resolution), axis=-1)
        to_points = points - pose[:, 3]
        seen_t, _, _ = scene._intersect_scene(np.broadcast_to(pose[:, 3], points.shape), to_points)
        visible = hit & in_frame & (np.abs(seen_t - 1.0) < 1e-6)
        viewdirs = to_points / np.linalg.norm(to_points, axis=-1, keepdims=True)
        cosine = np.sum(viewdirs * test_viewdirs, axis=-1)
        better = visible & (cosine > best_cos)
        shaded = scene.shade(albedo, normals, viewdirs, light)
        exact = np.where(better[..., None], shaded, exact)
        bilinear = np.where(better[..., None], _bilinear(train_images[index], coords), bilinear)
        best_cos = np.where(better, cosine, best_cos)

    seen = np.isfinite(best_cos)
    result = {
        "resolution": resolution,
        "num_train_views": num_train_views,
        "num_test_views": num_test_views,
        "object_fraction": float(hit.mean()),
        "unseen_fraction_of_objects": float(1.0 - seen[hit].mean()),
    }
    for name, estimate in (("exact", exact), ("bilinear", bilinear)):
        estimate = np.where(hit[..., None], estimate, 1.0)
        per_view = [
            mse_to_psnr(float(np.mean((e - g) ** 2))) for e, g in zip(estimate, test_images, strict=True)
        ]
        seen_only = np.where((hit & ~seen)[..., None], test_images, estimate)
        result[name] = {
            "psnr": float(np.mean(per_view)),
            "psnr_per_view": per_view,
            "psnr_if_unseen_were_right": _mean_psnr(seen_only, test_images),
        }
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--resolution", type=int, default=64)
    parser.add_argument("--views", type=int, default=4, help="training views")
    parser.add_argument("--test-views", type=int, default=8)
    parser.add_argument("--run", type=Path, default=None, help="a run on the built-in scene to compare")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    result = ceiling(args.resolution, args.views, args.test_views)
    if args.run is not None:
        result["run"] = run_report(args.run)
    print(json.dumps(result, indent=1))
    if args.out is not None:
        args.out.write_text(json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main()
