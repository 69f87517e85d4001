"""DTU scans in pixelNeRF's `rs_dtu_4` layout, with RegNeRF's object masks when present.

A scan's folder holds `image/000000.png ...` (one image per view, in view order) and
`cameras.npz` with a projection matrix `world_mat_<i> = K [R | t]` per view, for the stored
images' pixels (the `scale_mat_<i>` entries are not needed). `rs_dtu_4` stores the rectified
images at 400x300, the protocol's resolution, already area-downsampled by 4 from 1600x1200, in
one lighting per view (the protocol's RegNeRF code reads light condition 3 of the original
release); images stored at the full 1600x1200 are area-downsampled by 4 here, with their
intrinsics.

Cameras follow RegNeRF: each projection matrix is decomposed into intrinsics and pose; the
poses of all the scan's views are recentred on their average pose and scaled so that the
largest camera coordinate is 1; every ray's origin then moves along the ray onto the plane
through the average camera (`z = 0`), from where the protocol's bounds, near 0.5 and far 3.5,
count. Directions keep a camera z-component of 1. There is no background colour.

Split (pixelNeRF's, as RegNeRF and MixNeRF use it): training views are the first `n` of
`[25, 22, 28, 40, 44, 48, 0, 8, 13]`; test views are the 49 views minus those nine minus the
excluded `[3, 4, 5, 6, 7, 16, 17, 18, 19, 20, 21, 36, 37, 38, 39]` (25 views).

Object masks (RegNeRF's `idrmasks`, 1600x1200 PNGs, white on the object) are read for the test
views from `<mask_root>/<scan>/mask/<id:03d>.png` or `<mask_root>/<scan>/<id:03d>.png` (the
release uses the first form for scans 40, 55, 63, 110 and 114, the second for the others), and
subsampled to the image size by taking every 4th pixel (OpenCV's nearest-neighbour resize, as
RegNeRF does). A pixel is on the object where all three channels are 255.

A `downscale` factor (`data.image_downscale`) area-averages the 400x300 images further, on top
of the protocol's resolution, and divides rows 0 and 1 of the intrinsics by it; a side that it
does not divide loses its remainder, half from each end, and the principal point moves with
the crop (see `mixnerf_eqx.data._downscale`). The masks follow the images: a downscaled pixel
is on the object where more than half of its block of 400x300 mask pixels is.
"""

import warnings
import zipfile
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from .._config import DataConfig
from ._dataset import Dataset, Views
from ._downscale import check_factor, downscale_image, downscale_intrinsics, downscale_mask
from ._errors import DatasetError
from ._files import area_downsample, check_same_size, list_images, read_image, read_images, require_file
from ._format import DatasetFormat, data_root
from ._poses import decompose_projection, recenter_poses
from ._splits import describe_validation, subsample_test_ids, validation_ids

__all__ = ["SCANS", "dtu_cameras", "load_dtu", "protocol_ids"]

SCANS = tuple(f"scan{number}" for number in (8, 21, 30, 31, 34, 38, 40, 41, 45, 55, 63, 82, 103, 110, 114))
TRAIN_IDS = (25, 22, 28, 40, 44, 48, 0, 8, 13)
EXCLUDED_IDS = (3, 4, 5, 6, 7, 16, 17, 18, 19, 20, 21, 36, 37, 38, 39)
NUM_VIEWS = 49
NEAR = 0.5
FAR = 3.5
FULL_SIZE = (1600, 1200)  # width, height of the original rectified images
FACTOR = 4
ORIGIN_PLANE_Z = 0.0
_ADVICE = "Point --data-dir (or MIXNERF_DATA_DIR) at the folder that holds pixelNeRF's rs_dtu_4/."


def protocol_ids(num_train_views: int) -> tuple[list[int], list[int]]:
    """The training and test view ids of the DTU few-shot protocol (see the module docstring)."""
    if num_train_views > len(TRAIN_IDS):
        raise DatasetError(
            f"{num_train_views} training views asked for, but the DTU protocol defines {len(TRAIN_IDS)} "
            f"({list(TRAIN_IDS)}). Ask for at most {len(TRAIN_IDS)} (data.num_train_views)."
        )
    held_out = set(TRAIN_IDS) | set(EXCLUDED_IDS)
    return list(TRAIN_IDS[:num_train_views]), [i for i in range(NUM_VIEWS) if i not in held_out]


def _read_cameras(path: Path, count: int) -> list[np.ndarray]:
    require_file(path, "DTU camera file", _ADVICE)
    try:
        # Opened here, not by np.load: np.load leaks its file handle when the archive is
        # damaged (a ResourceWarning on top of the DatasetError).
        with open(path, "rb") as handle, np.load(handle, allow_pickle=False) as cameras:
            keys = set(cameras.files)
            matrices = []
            for view in range(count):
                key = f"world_mat_{view}"
                if key not in keys:
                    raise DatasetError(
                        f"{path}: has no {key!r}, but the image folder holds {count} images; each image "
                        "needs its projection matrix. Restore the file from the rs_dtu_4 release."
                    )
                matrices.append(np.asarray(cameras[key]))
    except DatasetError:
        raise
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as error:
        raise DatasetError(f"{path}: not a readable .npz archive ({error}). {_ADVICE}") from None
    return matrices


def dtu_cameras(projections: Sequence[np.ndarray], source: Path) -> tuple[np.ndarray, np.ndarray]:
    """Decomposes and normalises a scan's projection matrices as RegNeRF does.

    **Arguments:**

    - `projections`: one `world_mat` per view, 3x4 or 4x4 (`K [R | t]`, OpenCV convention).
    - `source`: the camera file, named in errors.

    **Returns:**

    The intrinsics `(num_views, 3, 3)` and the recentred, rescaled OpenGL camera-to-world
    matrices `(num_views, 3, 4)`, both float64.
    """
    intrinsics, camtoworlds = [], []
    for view, matrix in enumerate(projections):
        matrix = np.asarray(matrix)
        if matrix.shape not in ((3, 4), (4, 4)) or not np.issubdtype(matrix.dtype, np.number):
            raise DatasetError(
                f"{source}: world_mat_{view} has shape {matrix.shape}; expected a 3x4 or 4x4 projection "
                "matrix. Restore the file from the rs_dtu_4 release."
            )
        matrix = matrix[:3].astype(np.float64)
        if not np.all(np.isfinite(matrix)) or abs(np.linalg.det(matrix[:, :3])) < 1e-12:
            raise DatasetError(f"{source}: world_mat_{view} is not a finite, invertible camera projection.")
        k, pose = decompose_projection(matrix)
        intrinsics.append(k)
        camtoworlds.append(pose)
    camtoworlds = recenter_poses(np.stack(camtoworlds))
    # RegNeRF's scale: the largest camera coordinate becomes 1.
    camtoworlds[:, :, 3] /= np.max(np.abs(camtoworlds[:, :, 3]))
    return np.stack(intrinsics), camtoworlds


def _mask_paths(
    mask_roots: Sequence[Path], scan: str, ids: Sequence[int], explicit: bool
) -> list[Path] | None:
    for root in mask_roots:
        scan_dir = root / scan
        if not scan_dir.is_dir():
            continue
        paths = []
        for view in ids:
            candidates = [scan_dir / "mask" / f"{view:03d}.png", scan_dir / f"{view:03d}.png"]
            found = [p for p in candidates if p.is_file()]
            if not found:
                raise DatasetError(
                    f"DTU object mask not found: neither {candidates[0]} nor {candidates[1]} exists, but "
                    f"{scan_dir} holds masks for other views. Restore RegNeRF's idrmasks for {scan}."
                )
            paths.append(found[0])
        return paths
    if explicit and mask_roots:
        raise DatasetError(
            f"DTU object masks not found: {mask_roots[0] / scan} is not a folder. Point data.dtu_mask_dir "
            "at RegNeRF's idrmasks folder (which holds one folder per scan)."
        )
    looked_in = ", ".join(str(root) for root in mask_roots) or "no folder given"
    warnings.warn(
        f"no DTU object masks for {scan} (looked in: {looked_in}); the test "
        "metrics will use every pixel, unlike the paper's masked metrics. Put RegNeRF's idrmasks there "
        "or set data.dtu_mask_dir.",
        UserWarning,
        stacklevel=3,
    )
    return None


def _read_mask(path: Path, height: int, width: int) -> np.ndarray:
    image = read_image(path)
    mask_height, mask_width = image.shape[:2]
    step = mask_height // height
    if step < 1 or mask_height != step * height or mask_width != step * width:
        raise DatasetError(
            f"{path}: the mask is {mask_width}x{mask_height}, which is no whole multiple of the "
            f"{width}x{height} images. Use RegNeRF's idrmasks for this scan."
        )
    return np.all(image[::step, ::step, :3] == 255, axis=-1)


def _scan_images(scan_dir: Path) -> list[Path]:
    """The image files of a scan, in view order; all of the protocol's views must be there."""
    image_dir = scan_dir / "image"
    if not image_dir.is_dir():
        raise DatasetError(f"DTU image folder not found: {image_dir} is not a folder. {_ADVICE}")
    files = list_images(image_dir)
    if len(files) < NUM_VIEWS:
        raise DatasetError(
            f"{image_dir}: holds {len(files)} images; the DTU protocol needs the {NUM_VIEWS} views of a "
            "scan (000000.png to 000048.png). Restore the missing images."
        )
    return files


def _check_principal_points(
    intrinsics: np.ndarray, ids: Sequence[int], files: Sequence[Path], height: int, width: int, source: Path
) -> None:
    """Every view's principal point must lie inside its `width x height` image."""
    for view, matrix in zip(ids, intrinsics, strict=True):
        cx, cy = matrix[0, 2], matrix[1, 2]
        if not (0 < cx < width and 0 < cy < height):
            raise DatasetError(
                f"{source}: world_mat_{view} puts the principal point at ({cx:.1f}, {cy:.1f}), "
                f"outside the {width}x{height} image {files[view].name}: the cameras belong to images "
                "of another size. Use the cameras.npz that came with these images."
            )


def _load_views(
    files: Sequence[Path],
    ids: list[int],
    masks: list[Path] | None,
    intrinsics: np.ndarray,
    camtoworlds: np.ndarray,
    camera_path: Path,
    *,
    full_size: tuple[int, int],
    factor: int,
    downscale: int,
) -> Views:
    """The views `ids` of a scan (see `load_dtu`), with their masks when `masks` names them."""
    paths = [files[i] for i in ids]
    raw = read_images(paths)
    height, width = check_same_size(raw, paths)
    scale = factor if (width, height) == tuple(full_size) else 1
    images = np.stack([area_downsample(image, scale)[..., :3] for image in raw])
    k = intrinsics[ids].copy()
    # Pixel coordinates shrink with the image; the camera does not change.
    k[:, :2, :] /= scale
    height, width = images.shape[1:3]
    check_factor(downscale, height, width, paths[0])
    _check_principal_points(k, ids, files, height, width, camera_path)
    mask_stack = None if masks is None else np.stack([_read_mask(p, height, width) for p in masks])
    if downscale > 1:
        images = np.stack([downscale_image(image, downscale) for image in images])
        k = downscale_intrinsics(k, height, width, downscale)
        if mask_stack is not None:
            mask_stack = np.stack([downscale_mask(mask, downscale) for mask in mask_stack])
    return Views(
        images=images,
        camtoworlds=camtoworlds[ids].astype(np.float32),
        focal=float(np.mean(k[:, 0, 0])),
        ids=tuple(ids),
        intrinsics=k.astype(np.float32),
        masks=mask_stack,
        origin_plane_z=ORIGIN_PLANE_Z,
    )


def load_dtu(
    scan_dir: Path,
    *,
    num_train_views: int,
    mask_roots: Sequence[Path] = (),
    masks_required: bool = False,
    max_test_views: int = 0,
    max_val_views: int = 0,
    full_size: tuple[int, int] = FULL_SIZE,
    factor: int = FACTOR,
    downscale: int = 1,
) -> Dataset:
    """Loads one DTU scan with the few-shot protocol's split and, when found, its test masks.

    **Arguments:**

    - `scan_dir`: the scan's folder (holding `image/` and `cameras.npz`).
    - `num_train_views`: the number of training views (at most 9).
    - `mask_roots`: folders that may hold RegNeRF's masks, one subfolder per scan; the first
      with a folder for this scan is used. Without any, the test views have no masks (and a
      warning says so).
    - `masks_required`: a missing mask folder is an error instead of a warning.
    - `max_test_views`: keep only this many of the protocol's test views, evenly spaced
      (0 keeps them all).
    - `max_val_views`: keep only this many validation views (the scan's views that are
      neither the protocol's training nor its test views), evenly spaced (0 keeps them all).
    - `full_size`: the `(width, height)` of full-size images, which are downsampled.
    - `factor`: the downsampling factor of full-size images.
    - `downscale`: area-average `downscale x downscale` blocks of the 400x300 images (and
      their masks), with the intrinsics to match (see the module docstring); 1 keeps them.

    **Returns:**

    A `Dataset` at the images' resolution (400x300 for `rs_dtu_4`), over `downscale`, with
    per-view intrinsics, rays starting on the average camera's plane, near 0.5, far 3.5 and
    no background colour.
    """
    files = _scan_images(scan_dir)
    camera_path = scan_dir / "cameras.npz"
    intrinsics, camtoworlds = dtu_cameras(_read_cameras(camera_path, len(files)), camera_path)
    train_ids, test_ids = protocol_ids(num_train_views)
    test_ids = subsample_test_ids(test_ids, max_test_views)
    val_ids, left_out = validation_ids(
        list(range(len(files))),
        train_ids + test_ids,
        max_val_views,
        centres=np.asarray(camtoworlds)[:, :3, 3],
        train_ids=train_ids,
        test_ids=test_ids,
    )

    def views(ids: list[int], masks: list[Path] | None) -> Views:
        return _load_views(
            files,
            ids,
            masks,
            intrinsics,
            camtoworlds,
            camera_path,
            full_size=full_size,
            factor=factor,
            downscale=downscale,
        )

    # Called here, not in a helper: the stack level of its warning counts on it.
    mask_paths = _mask_paths(mask_roots, scan_dir.name, test_ids, masks_required)
    return Dataset(
        name=scan_dir.name,
        train=views(train_ids, None),
        test=views(test_ids, mask_paths),
        near=NEAR,
        far=FAR,
        white_background=False,
        frustum="cone",
        val=views(val_ids, None) if val_ids else None,
        val_source=describe_validation(
            "views outside the protocol's training and test ids", "no view left over", val_ids, left_out
        ),
    )


# Where RegNeRF's object masks are looked for under the dataset root.
MASK_LAYOUTS = ("idrmasks", "submission_data/idrmasks")


def _load_from_config(scan_dir: Path, config: DataConfig) -> Dataset:
    if config.dtu_mask_dir:
        mask_roots = [Path(config.dtu_mask_dir).expanduser()]
    else:
        root = data_root(config)
        mask_roots = [root / layout for layout in MASK_LAYOUTS if (root / layout).is_dir()]
    return load_dtu(
        scan_dir,
        num_train_views=config.num_train_views,
        mask_roots=mask_roots,
        masks_required=bool(config.dtu_mask_dir),
        max_test_views=config.max_test_views,
        max_val_views=config.max_val_views,
        downscale=config.image_downscale,
    )


FORMAT = DatasetFormat(
    name="dtu",
    layouts=("rs_dtu_4/DTU", "rs_dtu_4"),
    scenes=SCANS,
    release="pixelNeRF's DTU release (rs_dtu_4/)",
    load=_load_from_config,
)
