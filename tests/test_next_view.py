"""The view to capture next: candidate checks, the ranking's contract, the farthest-camera
baseline (closed form) and the command."""

import json

import numpy as np
import pytest

import mixnerf_eqx as mx
from mixnerf_eqx._predictive.next_view import _small, check_candidate_poses
from mixnerf_eqx.cli.next_view import main as next_view_main
from mixnerf_eqx.data import Views, builtin_views_at, rays_at_poses


def test_candidate_poses_that_are_not_rotations_are_named():
    pose = np.concatenate([np.eye(3), np.zeros((3, 1))], axis=1)
    assert check_candidate_poses(np.stack([pose, pose])).shape == (2, 3, 4)
    square = np.concatenate([np.concatenate([pose, [[0, 0, 0, 1]]])[None]] * 2)
    assert check_candidate_poses(square).shape == (2, 3, 4)
    scaled = pose.copy()
    scaled[:, :3] *= 2.0
    with pytest.raises(ValueError, match="candidate pose 1's rotation part is not a rotation"):
        check_candidate_poses(np.stack([pose, scaled]))
    mirrored = pose.copy()
    mirrored[0, 0] = -1.0  # orthonormal, determinant -1
    with pytest.raises(ValueError, match="candidate pose 0's rotation part is not a rotation"):
        check_candidate_poses(mirrored[None])
    with pytest.raises(ValueError, match="candidate pose 0 is not finite"):
        check_candidate_poses(np.full((1, 3, 4), np.nan))
    with pytest.raises(ValueError, match=r"shape \(n, 3, 4\) or \(n, 4, 4\)"):
        check_candidate_poses(np.zeros((3, 4)))


def test_an_ndc_candidate_facing_away_is_refused(tiny_config, tiny_scene):
    model = mx.training.init_train_state(tiny_config, tiny_scene).model
    like = Views(images=np.zeros((1, 8, 8, 3), np.float32), camtoworlds=np.eye(3, 4, dtype=np.float32)[None], focal=8.0, ndc=True)
    away = np.eye(3, 4)
    away[:, :3] = np.diag([-1.0, 1.0, -1.0])  # turned half round: looking along +z
    with pytest.raises(ValueError, match="candidate pose 1 faces away from the scene"):
        mx.next_view(model, like, np.stack([np.eye(3, 4), away]), 0.0, 1.0)


def test_the_score_is_the_opacity_weighted_spread_of_a_small_render(short_run, tiny_scene):
    import equinox as eqx

    _, model = short_run
    pool = builtin_views_at([10.0, 100.0, 200.0], [15.0, 50.0, 30.0], resolution=32)
    ranking = mx.next_view(model, tiny_scene.train, pool.camtoworlds, tiny_scene.near, tiny_scene.far, width=16)
    small = _small(tiny_scene.train, 16)
    assert (small.width, small.height) == (16, 16) and small.focal == pytest.approx(tiny_scene.train.focal / 2)
    render = eqx.filter_jit(lambda m, r: m(r))
    for index, pose in enumerate(pool.camtoworlds):
        fine = render(model, rays_at_poses(small, pose[None], tiny_scene.near, tiny_scene.far).reshape(-1)).fine
        # Float64 reference: each ray's termination distance, uniform within each interval.
        weights = np.asarray(fine.weights, np.float64)
        edges = np.asarray(fine.t_edges, np.float64)
        masses = weights / np.maximum(weights.sum(-1, keepdims=True), 1e-300)
        centres, widths = 0.5 * (edges[:, 1:] + edges[:, :-1]), edges[:, 1:] - edges[:, :-1]
        mean = np.sum(masses * centres, -1, keepdims=True)
        std = np.sqrt(np.sum(masses * (widths**2 / 12 + (centres - mean) ** 2), -1))
        acc = np.asarray(fine.acc, np.float64)
        want = np.sum(acc * std) / np.sum(acc) / (tiny_scene.far - tiny_scene.near)
        assert ranking.scores[index] == pytest.approx(want, rel=1e-4)
        assert ranking.opacity[index] == pytest.approx(acc.mean(), rel=1e-5)
    assert list(ranking.order) == list(np.argsort(-ranking.scores))
    with pytest.raises(ValueError, match="score must be one of"):
        mx.next_view(model, tiny_scene.train, pool.camtoworlds, tiny_scene.near, tiny_scene.far, score="entropy")


def test_a_bounded_candidate_that_sees_nothing_is_refused(short_run, tiny_scene):
    import equinox as eqx

    _, model = short_run
    # The same model with its density head's bias pushed far down renders nothing anywhere.
    empty = eqx.tree_at(lambda m: m.field.density_head.bias, model, model.field.density_head.bias - 1e4)
    pool = builtin_views_at([10.0], [15.0], resolution=32)
    assert mx.next_view(model, tiny_scene.train, pool.camtoworlds, tiny_scene.near, tiny_scene.far).opacity[0] > 0.02
    with pytest.raises(ValueError, match="candidate pose 0 sees nothing of the scene"):
        mx.next_view(empty, tiny_scene.train, pool.camtoworlds, tiny_scene.near, tiny_scene.far)


def test_farthest_first_orders_by_the_nearest_training_centre():
    def at(x, y, z):
        pose = np.eye(3, 4)
        pose[:, 3] = (x, y, z)
        return pose

    train = np.stack([at(0, 0, 0), at(10, 0, 0)])
    candidates = np.stack([at(1, 0, 0), at(5, 0, 0), at(0, 3, 0), at(10, 0, 2)])
    # Nearest training centres at distances 1, 5, 3 and 2.
    assert list(mx.uncertainty.farthest_first(candidates, train)) == [1, 2, 3, 0]


def test_the_command_ranks_the_validation_cameras_and_poses_from_a_file(short_run, tmp_path, capsys):
    run_dir, _ = short_run
    out = tmp_path / "ranking.json"
    assert next_view_main([str(run_dir), "--width", "16", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "capture next: view" in printed and "the camera farthest from the training cameras" in printed
    ranking = json.loads(out.read_text())["ranking"]
    assert [row["rank"] for row in ranking] == [1, 2, 3, 4]
    assert all(row["candidate"].startswith("view ") for row in ranking)
    assert ranking[0]["score"] >= ranking[-1]["score"]

    poses = tmp_path / "poses.npy"
    np.save(poses, np.asarray(builtin_views_at([0.0, 90.0], [20.0, 40.0], resolution=8).camtoworlds))
    assert next_view_main([str(run_dir), "--width", "16", "--poses", str(poses), "--top", "1"]) == 0
    assert "capture next: pose" in capsys.readouterr().out
    bad = np.asarray(builtin_views_at([0.0], [20.0], resolution=8).camtoworlds).copy()
    bad[0, :, :3] *= 3.0
    np.save(poses, bad)
    assert next_view_main([str(run_dir), "--poses", str(poses)]) == 2
    assert "candidate pose 0's rotation part is not a rotation" in capsys.readouterr().err
    assert next_view_main([str(run_dir), "--width", "1"]) == 2
    assert "--width must be at least 2" in capsys.readouterr().err
