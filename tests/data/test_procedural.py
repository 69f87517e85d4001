"""Tests of the built-in procedural scene.

The geometric checks recompute every ray from the stored poses and focal with their own
formula (not `mixnerf_eqx._nn.rays`), then check the hit points against the shapes' implicit
equations and against a brute-force ray march, so they do not share code with the renderer.
"""

import itertools

import hypothesis
import hypothesis.strategies as st
import numpy as np
import pytest

from mixnerf_eqx.data import procedural
from mixnerf_eqx.data.procedural import make_builtin_scene


@pytest.fixture(scope="module")
def scene():
    return make_builtin_scene()


@pytest.fixture(scope="module")
def small_scene():
    return make_builtin_scene(resolution=32, num_train_views=3, num_test_views=5)


def _splits(dataset):
    return [dataset.train, dataset.test]


def _rays(views):
    """Origins and unnormalised directions through every pixel centre, in float64."""
    poses = views.camtoworlds.astype(np.float64)
    rows, cols = np.indices((views.height, views.width), dtype=np.float64)
    u = (cols + 0.5 - views.width / 2) / views.focal
    v = (views.height / 2 - rows - 0.5) / views.focal
    right, up, back = (poses[:, None, None, :, k] for k in range(3))
    directions = u[..., None] * right + v[..., None] * up - back
    origins = np.broadcast_to(poses[:, None, None, :, 3], directions.shape)
    return origins, directions


def _on_some_surface(points, tol):
    """Whether each point satisfies the implicit equation of at least one shape."""
    x, y, z = points[..., 0], points[..., 1], points[..., 2]
    on_ground = (np.abs(z) < tol) & (np.hypot(x, y) <= procedural.GROUND_RADIUS + tol)

    radius = np.linalg.norm(points - procedural.SPHERE_CENTER, axis=-1)
    on_sphere = np.abs(radius - procedural.SPHERE_RADIUS) < tol

    lo, hi = procedural.BOX_MIN, procedural.BOX_MAX
    in_box = np.all((points >= lo - tol) & (points <= hi + tol), axis=-1)
    on_face = np.any((np.abs(points - lo) < tol) | (np.abs(points - hi) < tol), axis=-1)
    on_box = in_box & on_face

    cx, cy = procedural.CYLINDER_CENTER
    rho = np.hypot(x - cx, y - cy)
    height = procedural.CYLINDER_HEIGHT
    within_height = (z >= -tol) & (z <= height + tol)
    on_side = (np.abs(rho - procedural.CYLINDER_RADIUS) < tol) & within_height
    on_cap = (np.abs(z - height) < tol) & (rho <= procedural.CYLINDER_RADIUS + tol)
    return on_ground | on_sphere | on_box | on_side | on_cap


def _inside_some_solid(points):
    """Whether each point lies strictly inside a solid shape."""
    x, y, z = points[..., 0], points[..., 1], points[..., 2]
    in_sphere = np.linalg.norm(points - procedural.SPHERE_CENTER, axis=-1) < procedural.SPHERE_RADIUS
    in_box = np.all((points > procedural.BOX_MIN) & (points < procedural.BOX_MAX), axis=-1)
    cx, cy = procedural.CYLINDER_CENTER
    in_cylinder = (
        (np.hypot(x - cx, y - cy) < procedural.CYLINDER_RADIUS) & (z > 0) & (z < procedural.CYLINDER_HEIGHT)
    )
    return in_sphere | in_box | in_cylinder


def test_determinism():
    first = make_builtin_scene(resolution=32, num_train_views=3, num_test_views=4)
    second = make_builtin_scene(resolution=32, num_train_views=3, num_test_views=4)
    for a, b in zip(_splits(first), _splits(second), strict=False):
        for name in ("images", "camtoworlds", "depths"):
            x, y = getattr(a, name), getattr(b, name)
            assert x.dtype == y.dtype
            assert x.tobytes() == y.tobytes()
        assert a.focal == b.focal
        assert a.ids == b.ids


def test_dataset_fields(scene):
    assert scene.name == "builtin"
    assert (scene.near, scene.far) == (2.0, 6.0)
    assert scene.white_background
    assert scene.frustum == "cone"
    assert scene.train.ids == (0, 1, 2, 3)
    assert scene.test.ids == tuple(range(4, 12))
    expected_focal = 0.5 * 64 / np.tan(0.5 * np.deg2rad(procedural.FOV_DEGREES))
    for views, num_views in zip(_splits(scene), (4, 8), strict=False):
        assert views.images.shape == (num_views, 64, 64, 3)
        assert views.depths.shape == (num_views, 64, 64)
        assert views.camtoworlds.shape == (num_views, 3, 4)
        assert views.images.dtype == np.float32
        assert views.depths.dtype == np.float32
        assert views.camtoworlds.dtype == np.float32
        assert isinstance(views.focal, float)
        assert views.focal == pytest.approx(expected_focal)


def test_value_ranges(scene):
    for views in _splits(scene):
        assert np.all(np.isfinite(views.images))
        assert views.images.min() >= 0 and views.images.max() <= 1
        assert not np.any(np.isnan(views.depths))
        background = np.isinf(views.depths)
        assert np.all(views.depths[~background] > 0)
        assert np.all(views.images[background] == 1.0)
        finite = views.depths[~background]
        assert finite.min() >= scene.near and finite.max() <= scene.far


def test_foreground_is_not_white(scene):
    # Guards against the background test passing trivially on an all-white render.
    for views in _splits(scene):
        foreground = views.images[np.isfinite(views.depths)]
        assert np.mean(np.all(foreground == 1.0, axis=-1)) < 0.01


def test_cameras(scene):
    for views in _splits(scene):
        for pose in views.camtoworlds.astype(np.float64):
            rotation, centre = pose[:, :3], pose[:, 3]
            np.testing.assert_allclose(rotation.T @ rotation, np.eye(3), atol=1e-6)
            assert np.linalg.det(rotation) == pytest.approx(1.0, abs=1e-6)
            assert np.linalg.norm(centre) == pytest.approx(procedural.CAMERA_RADIUS, rel=1e-6)
            # OpenGL: the camera looks along its -z axis, towards the target, with +z world up.
            to_target = procedural.LOOK_AT - centre
            np.testing.assert_allclose(-rotation[:, 2], to_target / np.linalg.norm(to_target), atol=1e-6)
            assert abs(rotation[2, 0]) < 1e-6  # no roll: camera x stays horizontal
            assert rotation[2, 1] > 0
            assert centre[2] > 0


@pytest.mark.parametrize("split", ["train", "test"])
def test_hit_points_lie_on_a_surface(scene, split):
    views = getattr(scene, split)
    origins, directions = _rays(views)
    hit = np.isfinite(views.depths)
    points = origins[hit] + views.depths[hit].astype(np.float64)[:, None] * directions[hit]
    on_surface = _on_some_surface(points, tol=1e-4)
    assert np.all(on_surface), f"{np.sum(~on_surface)} hit points lie on no shape"


def test_no_earlier_hit_by_ray_marching(small_scene):
    # Every camera is 4 from the origin and the scene lies within 1.7 of it, so nothing can
    # be met before t = 2 (directions are at least unit length).
    ts = np.arange(2.0, 6.5, 3e-3)
    for views in _splits(small_scene):
        origins, directions = _rays(views)
        depths = views.depths.astype(np.float64)
        for view in range(views.num_views):
            o = origins[view].reshape(-1, 1, 3)
            d = directions[view].reshape(-1, 1, 3)
            depth = depths[view].reshape(-1, 1)
            points = o + ts[:, None] * d
            # Stop just short of the reported hit: every point before it must be empty space.
            before = ts[None, :] < depth - 1e-4
            inside = _inside_some_solid(points) & before
            assert not np.any(inside), f"view {view}: a solid is hit before the reported depth"
            # The ground is infinitely thin: look for the ray crossing its plane instead.
            z = points[..., 2]
            crossing = (z[:, :-1] > 0) & (z[:, 1:] <= 0) & before[:, 1:]
            rho = np.hypot(points[:, 1:, 0], points[:, 1:, 1])
            assert not np.any(crossing & (rho < procedural.GROUND_RADIUS - 1e-2))


def test_background_rays_miss_everything(small_scene):
    for views in _splits(small_scene):
        origins, directions = _rays(views)
        miss = np.isinf(views.depths)
        o, d = origins[miss], directions[miss]
        # Where a background ray meets the ground plane, it is outside the ground disc.
        t_plane = -o[:, 2] / d[:, 2]
        ground_xy = o[:, :2] + t_plane[:, None] * d[:, :2]
        crosses = (d[:, 2] < 0) & (np.linalg.norm(ground_xy, axis=-1) < procedural.GROUND_RADIUS)
        assert not np.any(crosses)
        # Closest approach to the sphere centre, an independent form of the sphere test.
        unit = d / np.linalg.norm(d, axis=-1, keepdims=True)
        offset = procedural.SPHERE_CENTER - o
        along = np.sum(offset * unit, axis=-1)
        closest = np.linalg.norm(offset - along[:, None] * unit, axis=-1)
        assert np.all(closest > procedural.SPHERE_RADIUS - 1e-6)
        ts = np.arange(2.0, 6.5, 5e-3)
        points = o[:, None] + ts[:, None] * d[:, None]
        assert not np.any(_inside_some_solid(points))


def test_sphere_depth_matches_stable_quadratic(scene):
    # Sphere pixels, with the root from the cancellation-free (Citardauq) form.
    views = scene.train
    origins, directions = _rays(views)
    hit = np.isfinite(views.depths)
    o, d = origins[hit], directions[hit]
    depth = views.depths[hit].astype(np.float64)
    points = o + depth[:, None] * d
    radius = np.linalg.norm(points - procedural.SPHERE_CENTER, axis=-1)
    sphere = np.abs(radius - procedural.SPHERE_RADIUS) < 1e-4
    assert sphere.sum() > 100
    o, d, depth = o[sphere], d[sphere], depth[sphere]
    offset = o - procedural.SPHERE_CENTER
    a = np.sum(d * d, axis=-1)
    b = 2 * np.sum(offset * d, axis=-1)
    c = np.sum(offset * offset, axis=-1) - procedural.SPHERE_RADIUS**2
    q = -0.5 * (b + np.sign(b) * np.sqrt(b * b - 4 * a * c))
    near_root = np.minimum(q / a, c / q)
    np.testing.assert_allclose(depth, near_root, rtol=1e-6)


def test_specular_makes_shading_view_dependent(scene):
    # A lit surface point seen from two training cameras: the highlight moves with the
    # viewer, while the shading without it does not.
    normals = np.tile([0.0, 0.0, 1.0], (4, 1))
    albedo = np.tile([0.5, 0.4, 0.3], (4, 1))
    point = np.array([0.0, 0.0, 0.0])
    centres = scene.train.camtoworlds[:, :, 3].astype(np.float64)
    viewdirs = point - centres
    viewdirs /= np.linalg.norm(viewdirs, axis=-1, keepdims=True)
    kwargs = dict(albedo=albedo, normals=normals, viewdirs=viewdirs, visibility=np.ones(4))
    with_specular = procedural.shade(**kwargs)
    without = procedural.shade(**kwargs, specular_strength=0.0)
    assert np.all(without == without[0])
    pairs = itertools.combinations(range(4), 2)
    assert max(np.abs(with_specular[i] - with_specular[j]).max() for i, j in pairs) > 0.02


def test_rendered_highlights(small_scene):
    views = small_scene.train
    poses = views.camtoworlds.astype(np.float64)
    images, depths = procedural._render(poses, views.height)
    matte, matte_depths = procedural._render(poses, views.height, specular_strength=0.0)
    np.testing.assert_array_equal(depths, matte_depths)
    np.testing.assert_array_equal(images.astype(np.float32), views.images)
    difference = np.abs(images - matte).max(axis=-1)
    assert np.all(difference[np.isinf(depths)] == 0)
    # Every training view shows some highlight.
    assert np.all(difference.reshape(len(poses), -1).max(axis=-1) > 0.1)


def test_poses_are_distinct_and_views_informative():
    for num_train, num_test in [(1, 1), (3, 8), (4, 8), (9, 12), (64, 64)]:
        train = procedural._train_poses(num_train)
        test = procedural._test_poses(num_test)
        centres = np.concatenate([train, test])[:, :, 3]
        distances = np.linalg.norm(centres[:, None] - centres[None], axis=-1)
        np.fill_diagonal(distances, np.inf)
        assert distances.min() > 0.05, (num_train, num_test)
    scene = make_builtin_scene(resolution=32, num_train_views=9, num_test_views=1)
    for depths in scene.train.depths:
        foreground = np.isfinite(depths).mean()
        assert 0.1 < foreground < 0.9


@pytest.mark.parametrize(
    "kwargs",
    [
        dict(resolution=7),
        dict(resolution=0),
        dict(resolution=True),
        dict(num_train_views=0),
        dict(num_train_views=65),
        dict(num_test_views=0),
        dict(num_test_views=1000),
    ],
)
def test_invalid_arguments(kwargs):
    with pytest.raises(ValueError):
        make_builtin_scene(**kwargs)


def test_non_integer_resolution():
    # A TypeError is also fine: under the package's runtime type checking the `int`
    # annotation rejects the float before the function body runs.
    with pytest.raises((TypeError, ValueError)):
        make_builtin_scene(resolution=64.0)


@hypothesis.settings(max_examples=10, deadline=None)
@hypothesis.given(
    resolution=st.integers(8, 24),
    num_train_views=st.integers(1, 10),
    num_test_views=st.integers(1, 10),
)
def test_any_valid_arguments(resolution, num_train_views, num_test_views):
    scene = make_builtin_scene(
        resolution=resolution, num_train_views=num_train_views, num_test_views=num_test_views
    )
    assert scene.train.images.shape == (num_train_views, resolution, resolution, 3)
    assert scene.test.images.shape == (num_test_views, resolution, resolution, 3)
    for views in _splits(scene):
        finite = views.depths[np.isfinite(views.depths)]
        assert np.all((finite >= scene.near) & (finite <= scene.far))
        assert views.images.min() >= 0 and views.images.max() <= 1
