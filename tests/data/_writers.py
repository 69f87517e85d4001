"""Tiny dataset files in each supported layout, written by the loader tests themselves.

Every writer returns what it wrote (the true cameras and the pixel values), so that a test can
compare the loader's output with values it never had to read back through the package. The
geometry and image references here are float64 numpy written from the textbook pinhole model
(`x ~ K [R | t] X`, OpenCV axes), not from `mixnerf_eqx`.
"""

import json
from pathlib import Path

import numpy as np
from PIL import Image

# The project's shared benchmark data: shared/data beside the repository root
# (tests/data/<file> -> parents: tests/data, tests, <repo>, <repo's parent>).
SHARED_DATA = Path(__file__).resolve().parents[3] / "shared" / "data"
LEGO = SHARED_DATA / "nerf_synthetic" / "lego"
FERN = SHARED_DATA / "nerf_llff_data" / "fern"


def write_png(path: Path, pixels: np.ndarray) -> Path:
    """Writes an 8-bit RGB or RGBA PNG (creating its folder)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.asarray(pixels, np.uint8)).save(path)
    return path


def random_pixels(rng: np.random.Generator, height: int, width: int, channels: int) -> np.ndarray:
    return rng.integers(0, 256, size=(height, width, channels), dtype=np.uint8)


def truncate(path: Path, keep: int | None = None) -> None:
    """Cuts a file down to its first `keep` bytes, or to half of them (a damaged download)."""
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2 if keep is None else keep])


def look_at(centre, target=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """An OpenGL camera-to-world matrix (3x4: x right, y up, looking along -z) at `centre`
    looking at `target`."""
    centre = np.asarray(centre, np.float64)
    backward = centre - np.asarray(target, np.float64)
    backward /= np.linalg.norm(backward)
    right = np.cross(np.asarray(up, np.float64), backward)
    right /= np.linalg.norm(right)
    true_up = np.cross(backward, right)
    return np.stack([right, true_up, backward, centre], axis=1)


def orbit_poses(count: int, radius: float = 4.0, height: float = 1.0, phase: float = 0.0) -> np.ndarray:
    """`count` cameras (3x4) on a ring of `radius` at `height`, looking at the origin."""
    angles = 2 * np.pi * np.arange(count) / count + phase
    return np.stack([look_at((radius * np.cos(a), radius * np.sin(a), height)) for a in angles])


def homogeneous(pose: np.ndarray) -> list:
    return np.concatenate([pose, [[0.0, 0.0, 0.0, 1.0]]]).tolist()


# --- Blender (nerf_synthetic) -------------------------------------------------------------


def write_blender(
    scene_dir: Path,
    *,
    num_train: int = 5,
    num_test: int = 9,
    height: int = 6,
    width: int = 8,
    camera_angle_x: float = 0.7,
    seed: int = 0,
) -> dict:
    """A nerf_synthetic scene: `transforms_{train,test}.json` and RGBA PNGs under `train/` and
    `test/`. Returns the raw pixels and the 3x4 poses of each split (in frame order)."""
    rng = np.random.default_rng(seed)
    written = {"camera_angle_x": camera_angle_x}
    for split, count in (("train", num_train), ("test", num_test)):
        poses = orbit_poses(count, radius=4.0, phase=0.3)
        pixels = [random_pixels(rng, height, width, 4) for _ in range(count)]
        frames = []
        for index in range(count):
            write_png(scene_dir / split / f"r_{index}.png", pixels[index])
            frames.append(
                {"file_path": f"./{split}/r_{index}", "transform_matrix": homogeneous(poses[index])}
            )
        meta = {"camera_angle_x": camera_angle_x, "frames": frames}
        (scene_dir / f"transforms_{split}.json").write_text(json.dumps(meta))
        written[split] = {"pixels": pixels, "poses": poses}
    return written


def blender_reference_image(pixels: np.ndarray, factor: int) -> np.ndarray:
    """Float64 reference: box average of straight RGBA over `factor x factor` blocks, then
    composited on white."""
    rgba = pixels.astype(np.float64) / 255.0
    height, width, channels = rgba.shape
    out = rgba.reshape(height // factor, factor, width // factor, factor, channels).mean(axis=(1, 3))
    return out[..., :3] * out[..., 3:] + (1.0 - out[..., 3:])


# --- LLFF (nerf_llff_data) ----------------------------------------------------------------


def llff_rows(
    camtoworlds_llff: np.ndarray, height: float, width: float, focal: float, bounds: np.ndarray
) -> np.ndarray:
    """poses_bounds.npy rows from LLFF-convention (down, right, backward) 3x4 poses."""
    count = len(camtoworlds_llff)
    hwf = np.broadcast_to(np.array([height, width, focal])[None, :, None], (count, 3, 1))
    poses = np.concatenate([camtoworlds_llff, hwf], axis=2)
    return np.concatenate([poses.reshape(count, 15), bounds], axis=1)


def forward_facing_llff_poses(count: int, rng: np.random.Generator) -> np.ndarray:
    """LLFF-convention poses (columns down, right, backward, centre) of cameras spread on a
    small patch, all looking roughly along -z towards a scene at z < 0."""
    poses = []
    for _ in range(count):
        centre = np.array([rng.uniform(-0.5, 0.5), rng.uniform(-0.4, 0.4), rng.uniform(-0.1, 0.1)])
        target = (rng.uniform(-0.2, 0.2), rng.uniform(-0.2, 0.2), -10.0)
        opengl = look_at(centre, target=target, up=(0.0, 1.0, 0.0))
        right, up, backward = opengl[:, 0], opengl[:, 1], opengl[:, 2]
        poses.append(np.stack([-up, right, backward, centre], axis=1))
    return np.stack(poses)


def write_llff(
    scene_dir: Path,
    *,
    count: int = 20,
    height: int = 6,
    width: int = 8,
    focal_full: float = 40.0,
    names: list[str] | None = None,
    seed: int = 0,
) -> dict:
    """An LLFF scene: `poses_bounds.npy` (full size 8x the images) and RGB PNGs in `images_8/`,
    named `names` (default `image000.png`, ...). The LLFF tools store the poses in the sorted
    order of the file names, so row `i` belongs to the `i`-th name in sorted order.

    Returns the rows, and the pixels and names in sorted name order.
    """
    rng = np.random.default_rng(seed)
    names = names or [f"image{i:03d}.png" for i in range(count)]
    count = len(names)
    rows = llff_rows(
        forward_facing_llff_poses(count, rng),
        8.0 * height,
        8.0 * width,
        focal_full,
        np.stack([rng.uniform(2.0, 3.0, count), rng.uniform(20.0, 30.0, count)], axis=1),
    )
    scene_dir.mkdir(parents=True, exist_ok=True)
    np.save(scene_dir / "poses_bounds.npy", rows)
    by_name = {}
    for name in names:
        by_name[name] = random_pixels(rng, height, width, 3)
        write_png(scene_dir / "images_8" / name, by_name[name])
    return {"rows": rows, "pixels": [by_name[name] for name in sorted(names)], "names": sorted(names)}


# --- DTU (pixelNeRF rs_dtu_4) -------------------------------------------------------------


def rotation_from_axis_angle(axis, angle: float) -> np.ndarray:
    """Rodrigues' formula, float64."""
    axis = np.asarray(axis, np.float64)
    axis = axis / np.linalg.norm(axis)
    cross = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * cross + (1 - np.cos(angle)) * cross @ cross


def dtu_cameras_known(count: int = 49, width: int = 16, height: int = 12, seed: int = 0):
    """Known OpenCV cameras (K with skew, R world-to-camera, t) looking at the origin from
    about 3 units.

    Returns `(intrinsics, rotations, translations)` as float64 stacks.
    """
    rng = np.random.default_rng(seed)
    ks, rs, ts = [], [], []
    for _ in range(count):
        fx, fy = rng.uniform(14.0, 18.0), rng.uniform(14.0, 18.0)
        cx, cy = width / 2 + rng.uniform(-2, 2), height / 2 + rng.uniform(-1.5, 1.5)
        k = np.array([[fx, rng.uniform(-0.5, 0.5), cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        centre = np.array([rng.uniform(-1, 1), rng.uniform(-1, 1), -3.0 + rng.uniform(-0.3, 0.3)])
        # An OpenCV camera (z forward) at `centre` looking roughly at the origin, slightly rolled.
        forward = -centre / np.linalg.norm(centre)
        right = np.cross(forward, [0.0, 1.0, 0.0])
        right /= np.linalg.norm(right)
        down = np.cross(forward, right)
        base = np.stack([right, down, forward])  # rows: the camera axes in world coordinates
        rotation = rotation_from_axis_angle([0, 0, 1], rng.uniform(-0.2, 0.2)) @ base
        ks.append(k)
        rs.append(rotation)
        ts.append(-rotation @ centre)
    return np.stack(ks), np.stack(rs), np.stack(ts)


def projection(
    k: np.ndarray, rotation: np.ndarray, translation: np.ndarray, scale: float = 1.0
) -> np.ndarray:
    """`scale * K [R | t]`, a 3x4 projection (DTU's world_mat up to its arbitrary scale)."""
    return scale * k @ np.concatenate([rotation, translation[:, None]], axis=1)


def write_dtu(
    root: Path,
    scan: str = "scan8",
    *,
    width: int = 16,
    height: int = 12,
    seed: int = 0,
    mask_layout: str | None = "nested",
) -> tuple[Path, dict]:
    """A DTU scan in the rs_dtu_4 layout under `root/rs_dtu_4/DTU/<scan>/` and, unless
    `mask_layout` is None, RegNeRF-style idrmasks (RGB, 4x the image size, white on the object)
    under `root/idrmasks/<scan>/mask/` ("nested") or `root/idrmasks/<scan>/` ("flat").

    Returns the scan folder and the written data (images, masks, K, R, t, projections).
    """
    rng = np.random.default_rng(seed)
    scan_dir = root / "rs_dtu_4" / "DTU" / scan
    ks, rs, ts = dtu_cameras_known(49, width, height, seed)
    images, masks, cameras = [], [], {}
    for view in range(49):
        image = random_pixels(rng, height, width, 3)
        write_png(scan_dir / "image" / f"{view:06d}.png", image)
        images.append(image)
        # world_mat as a 4x4 with an arbitrary scale (negative on odd views).
        matrix = np.eye(4)
        matrix[:3] = projection(ks[view], rs[view], ts[view], scale=(-2.5 if view % 2 else 0.7))
        cameras[f"world_mat_{view}"] = matrix
        cameras[f"scale_mat_{view}"] = np.eye(4)
        mask_small = rng.random((height, width)) < 0.5
        masks.append(mask_small)
        # Only the top-left pixel of each 4x4 block decides (nearest resize); the others hold
        # the opposite value, so any other sampling gives a different mask. Some off-object
        # pixels are nearly white (one channel 254), which is not on the object.
        big = np.where(np.kron(mask_small, np.ones((4, 4), bool))[..., None], 0, 255)
        big = np.broadcast_to(big, (4 * height, 4 * width, 3)).copy()
        nearly_white = ~mask_small & (rng.random((height, width)) < 0.4)
        big[::4, ::4] = np.where(mask_small[..., None], 255, 0)
        big[::4, ::4][nearly_white] = (255, 254, 255)
        if mask_layout is not None:
            mask_dir = root / "idrmasks" / scan / ("mask" if mask_layout == "nested" else "")
            write_png(mask_dir / f"{view:03d}.png", big)
    scan_dir.mkdir(parents=True, exist_ok=True)
    np.savez(scan_dir / "cameras.npz", **cameras)
    return scan_dir, {"images": images, "masks": masks, "K": ks, "R": rs, "t": ts, "P": cameras}


# --- transforms.json (nerfstudio / instant-ngp) -------------------------------------------


def write_transforms(
    scene_dir: Path,
    *,
    num_views: int = 10,
    height: int = 6,
    width: int = 8,
    intrinsics: dict | None = None,
    frame_overrides: dict[int, dict] | None = None,
    channels: int = 3,
    seed: int = 0,
) -> dict:
    """A `transforms.json` scene with images `images/frame_<i>.png` (names not zero-padded,
    so name order and number order differ) and top-level intrinsics `intrinsics`; the frames
    are stored in reverse order (nerfstudio promises none).

    Returns the JSON's content plus the 3x4 poses and the pixels in name order.
    """
    rng = np.random.default_rng(seed)
    intrinsics = {"fl_x": 7.0, "fl_y": 7.5, "cx": 3.1, "cy": 3.4, "w": width, "h": height} | (
        intrinsics or {}
    )
    poses = orbit_poses(num_views, radius=3.0, phase=0.3)
    pixels, frames = [], []
    for index in range(num_views):
        pixels.append(random_pixels(rng, height, width, channels))
        write_png(scene_dir / "images" / f"frame_{index + 1}.png", pixels[index])
        frame = {"file_path": f"images/frame_{index + 1}.png", "transform_matrix": homogeneous(poses[index])}
        frame |= (frame_overrides or {}).get(index, {})
        frames.append(frame)
    meta = intrinsics | {"camera_model": "OPENCV", "frames": frames[::-1]}
    (scene_dir / "transforms.json").write_text(json.dumps(meta))
    return {"poses": poses, "pixels": pixels, "meta": meta}


# --- Downscaling references (data.image_downscale) ----------------------------------------


def crop_offsets(height: int, width: int, factor: int) -> tuple[int, int]:
    """The documented crop: half of each side's remainder from the top (left), rounded down."""
    return (height % factor) // 2, (width % factor) // 2


def block_average(array: np.ndarray, factor: int) -> np.ndarray:
    """Float64 reference of an image (or mask) downscaled by `factor`: each side's remainder
    cropped as `crop_offsets` says, then the mean over `factor x factor` blocks."""
    height, width = array.shape[:2]
    top, left = crop_offsets(height, width, factor)
    out_height, out_width = height // factor, width // factor
    cropped = np.asarray(array, np.float64)[top : top + out_height * factor, left : left + out_width * factor]
    return cropped.reshape(out_height, factor, out_width, factor, *array.shape[2:]).mean(axis=(1, 3))


def block_centres(height: int, width: int, factor: int) -> tuple[np.ndarray, np.ndarray]:
    """Continuous pixel coordinates `(rows, cols)`, in the `height x width` image, of the
    centres of the blocks that the downscaled image's pixels average (pixel `i` spans
    `[i, i + 1)`)."""
    top, left = crop_offsets(height, width, factor)
    rows = top + factor * (np.arange(height // factor) + 0.5)
    cols = left + factor * (np.arange(width // factor) + 0.5)
    return np.meshgrid(rows, cols, indexing="ij")
