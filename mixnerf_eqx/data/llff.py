"""LLFF forward-facing scenes: `nerf_llff_data/<scene>/poses_bounds.npy` and `images_8/`.

Each row of `poses_bounds.npy` holds a 3x5 matrix (a camera-to-world matrix whose rotation
columns are LLFF's down, right, backward axes, plus a column with the full-size image's
height, width and focal length) and the view's near and far depth bounds. The loader follows
the NeRF LLFF loader: it reorders the axes to OpenGL's right, up, backward; scales the scene so
that the nearest bound becomes 1 / 0.75; and recentres the cameras on their average pose. The
images are the 8x downsampled `images_8/` (504x378), so the focal length is divided by 8.
A `downscale` factor (`data.image_downscale`) area-averages those images further, on top of
the protocol's 504x378, and divides the focal length by it; the NDC mapping takes the
downscaled focal length, width and height. A side that the factor does not divide (4 and 8
leave a remainder of 2 of the 378 rows) loses its remainder, half from each end, which keeps
the principal point at the centre; an odd remainder gives the views explicit intrinsics that
hold it (see `mixnerf_eqx.data._downscale`).

Rays live in normalised device coordinates (near plane 1 in the recentred world, sampling
bounds 0 and 1) with cylindrical frustums. The protocol holds out every 8th image for testing
and trains on `n` of the others, evenly spaced.
"""

from pathlib import Path

import numpy as np

from .._config import DataConfig
from ._dataset import Dataset, Views
from ._downscale import check_factor, downscale_centred_camera, downscale_image
from ._errors import DatasetError
from ._files import check_same_size, list_images, read_images, read_npy, require_dir
from ._format import DatasetFormat
from ._poses import check_camera, recenter_poses
from ._splits import describe_validation, holdout_split, subsample_test_ids, validation_ids

__all__ = ["SCENES", "llff_poses", "load_llff"]

SCENES = ("fern", "flower", "fortress", "horns", "leaves", "orchids", "room", "trex")
IMAGE_FACTOR = 8
HOLDOUT_EVERY = 8
BOUND_FACTOR = 0.75
NEAR = 0.0
FAR = 1.0
_ADVICE = "Point --data-dir (or MIXNERF_DATA_DIR) at the folder that holds nerf_llff_data/."


def llff_poses(
    poses_bounds: np.ndarray, source: Path
) -> tuple[np.ndarray, np.ndarray, tuple[float, float, float]]:
    """Turns the rows of `poses_bounds.npy` into recentred, rescaled OpenGL cameras.

    **Arguments:**

    - `poses_bounds`: the file's array, one row of 17 values per image.
    - `source`: the file, named in errors.

    **Returns:**

    The camera-to-world matrices `(num_views, 3, 4)` in float64, the rescaled depth bounds
    `(num_views, 2)`, and the full-size `(height, width, focal)` of the first camera.
    """
    array = np.asarray(poses_bounds)
    if array.ndim != 2 or array.shape[1] != 17 or array.shape[0] == 0:
        raise DatasetError(
            f"{source}: holds an array of shape {array.shape}; expected (num_images, 17), a 3x5 pose "
            "and two depth bounds per image. Regenerate it with the LLFF tools (imgs2poses.py)."
        )
    if not np.issubdtype(array.dtype, np.number) or not np.all(np.isfinite(array)):
        raise DatasetError(f"{source}: the poses or bounds are not finite numbers. Regenerate the file.")
    array = array.astype(np.float64)
    poses = array[:, :15].reshape(-1, 3, 5)
    bounds = array[:, 15:].copy()
    if np.any(bounds <= 0):
        raise DatasetError(f"{source}: some depth bounds are not positive. Regenerate the file.")
    height, width, focal = (float(v) for v in poses[0, :, 4])
    if not (height > 0 and width > 0 and focal > 0):
        raise DatasetError(
            f"{source}: the first camera's height, width and focal length are {height:g}, {width:g}, "
            f"{focal:g}; each must be positive. Regenerate the file."
        )
    # LLFF's columns are (down, right, backward); OpenGL's are (right, up, backward).
    camtoworlds = np.concatenate([poses[:, :, 1:2], -poses[:, :, 0:1], poses[:, :, 2:4]], axis=2)
    for index, camera in enumerate(camtoworlds):
        check_camera(camera, f"{source}: camera {index}")
    # Scale the scene so that the nearest content lies just beyond the NDC near plane (1).
    scale = 1.0 / (bounds.min() * BOUND_FACTOR)
    camtoworlds[:, :, 3] *= scale
    bounds *= scale
    return recenter_poses(camtoworlds), bounds, (height, width, focal)


def load_llff(
    scene_dir: Path,
    *,
    num_train_views: int,
    max_test_views: int = 0,
    max_val_views: int = 0,
    downscale: int = 1,
) -> Dataset:
    """Loads one LLFF scene with the few-shot protocol's split.

    **Arguments:**

    - `scene_dir`: the scene's folder (holding `poses_bounds.npy` and `images_8/`).
    - `num_train_views`: the number of training views.
    - `max_test_views`: keep only this many of the protocol's test views, evenly spaced
      (0 keeps them all).
    - `max_val_views`: keep only this many validation views (the images that are neither
      training nor test views), evenly spaced (0 keeps them all).
    - `downscale`: area-average `downscale x downscale` blocks of the 504x378 images and
      divide the focal length by it (see the module docstring); 1 keeps the protocol's images.

    **Returns:**

    A `Dataset` of NDC views (cylinder frustums, bounds 0 and 1, no background colour).
    """
    poses_path = scene_dir / "poses_bounds.npy"
    image_dir = require_dir(
        scene_dir / f"images_{IMAGE_FACTOR}",
        "LLFF image folder",
        f"The protocol uses the {IMAGE_FACTOR}x downsampled images (504x378) of nerf_llff_data. {_ADVICE}",
    )
    camtoworlds, _, (full_height, full_width, full_focal) = llff_poses(
        read_npy(poses_path, "LLFF camera file", _ADVICE), poses_path
    )
    # Plain name order (not numbers by value): LLFF's imgs2poses stores the poses in the
    # np.argsort order of the image names, and the NeRF loader pairs them with
    # sorted(os.listdir(...)); with unpadded names (img9, img10) the orders differ.
    files = sorted(list_images(image_dir), key=lambda p: p.name)
    if len(files) != len(camtoworlds):
        raise DatasetError(
            f"{image_dir}: holds {len(files)} images but {poses_path.name} has {len(camtoworlds)} poses; "
            "each image needs exactly one row. Restore the missing images (or poses) so the counts match."
        )
    train_ids, test_ids = holdout_split(len(files), HOLDOUT_EVERY, num_train_views, image_dir)
    test_ids = subsample_test_ids(test_ids, max_test_views)
    val_ids, left_out = validation_ids(
        list(range(len(files))),
        train_ids + test_ids,
        max_val_views,
        centres=camtoworlds[:, :3, 3],
        train_ids=train_ids,
        test_ids=test_ids,
    )

    def views(ids: list[int]) -> Views:
        paths = [files[i] for i in ids]
        images = read_images(paths)
        height, width = check_same_size(images, paths)
        expected = (full_width / IMAGE_FACTOR, full_height / IMAGE_FACTOR)
        if abs(width - expected[0]) > 1 or abs(height - expected[1]) > 1:
            raise DatasetError(
                f"{paths[0]}: the image is {width}x{height}, but {poses_path.name} describes "
                f"{full_width:.0f}x{full_height:.0f} images, whose 1/{IMAGE_FACTOR} is "
                f"{expected[0]:.0f}x{expected[1]:.0f}. Use the images_{IMAGE_FACTOR} folder that came "
                "with these poses."
            )
        check_factor(downscale, height, width, paths[0])
        focal, intrinsics = downscale_centred_camera(
            full_focal / IMAGE_FACTOR, height, width, downscale, len(ids)
        )
        return Views(
            images=np.stack([downscale_image(image[..., :3], downscale) for image in images]),
            camtoworlds=camtoworlds[ids].astype(np.float32),
            focal=focal,
            ids=tuple(ids),
            intrinsics=intrinsics,
            ndc=True,
        )

    return Dataset(
        name=scene_dir.name,
        train=views(train_ids),
        test=views(test_ids),
        near=NEAR,
        far=FAR,
        white_background=False,
        frustum="cylinder",
        val=views(val_ids) if val_ids else None,
        val_source=describe_validation(
            "images neither trained on nor held out for testing",
            "every image is a training or test view",
            val_ids,
            left_out,
        ),
    )


def _load_from_config(scene_dir: Path, config: DataConfig) -> Dataset:
    return load_llff(
        scene_dir,
        num_train_views=config.num_train_views,
        max_test_views=config.max_test_views,
        max_val_views=config.max_val_views,
        downscale=config.image_downscale,
    )


FORMAT = DatasetFormat(
    name="llff",
    layouts=("nerf_llff_data",),
    scenes=SCENES,
    release="the NeRF LLFF release (nerf_llff_data/)",
    load=_load_from_config,
)
