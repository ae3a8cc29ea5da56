"""Speed-ups give what the code they replaced gave (test/speedup_reference.py), on realistic
inputs: stereo clouds of simulator-rendered pairs (LittleDog on rocks-6cm, as in the demo),
plus the edge cases (NaN, inf, float64 and integer input, few valid points)."""

import numpy as np
import pytest

import speedup_reference as ref
from terrain_perception.bench.stereo import (_body_pose, _course_scene, render_pair,
                                             robot_num_disparities)
from terrain_perception.ground_plane import GroundPlaneConfig, fit_ground_plane
from terrain_perception.robot_model import load_robot_model
from terrain_perception.stereo import StereoConfig, StereoPipeline


@pytest.fixture(scope='module')
def littledog_views():
    """Two rendered LittleDog views of rocks-6cm (pybullet, as the simulator bridge renders):
    ``[(stereo, config, left, right, frame)]`` with the pipeline's frame of each pair."""
    rm = load_robot_model('littledog')
    views = []
    for seed in (3, 4):
        course, padded = _course_scene('rocks-6cm', seed, 0.005)
        x0 = float(padded.metadata['rough_extent_xy'][0]) - 0.25
        T = _body_pose(np.random.default_rng(seed), x0, rm.standing_height_m) \
            @ rm.T_base_camera
        cfg = StereoConfig(num_disparities=robot_num_disparities(rm.stereo, T))
        left, right, _ = render_pair('pybullet', course, padded, rm.stereo, T, seed)
        frame = StereoPipeline(cfg, rm.stereo).process(left, right)
        views.append((rm.stereo, cfg, left, right, frame))
    return views


def assert_same_plane(a, b):
    np.testing.assert_array_equal(a.normal, b.normal)
    assert (a.d, a.pitch_rad, a.height_m, a.inlier_ratio, a.inliers) == \
        (b.d, b.pitch_rad, b.height_m, b.inlier_ratio, b.inliers)


def plane_or_error(fit, pts, cfg):
    try:
        return fit(pts, cfg)
    except ValueError as exc:
        return str(exc)


@pytest.mark.parametrize('penalty', [2.0, 0.0])
def test_ground_plane_equals_the_previous_code_on_rendered_clouds(littledog_views, penalty):
    cfg = GroundPlaneConfig(below_penalty=penalty)
    for _, _, _, _, frame in littledog_views:
        pts = frame.points                                   # float32 (H, W, 3), NaN holes
        assert pts.dtype == np.float32 and np.isnan(pts).any()
        noisy = pts.copy()
        rng = np.random.default_rng(0)
        bad = rng.random(noisy.shape[:2]) < 0.02
        noisy[bad, rng.integers(0, 3, int(bad.sum()))] = \
            rng.choice([np.inf, -np.inf, np.nan], int(bad.sum()))
        for cloud in (pts, noisy, noisy.astype(np.float64), noisy.reshape(-1, 3)):
            assert_same_plane(fit_ground_plane(cloud, cfg), ref.fit_ground_plane(cloud, cfg))
        # fewer valid points than the sample size: every valid point is used, in order
        few = noisy.reshape(-1, 3)[::100]
        assert_same_plane(fit_ground_plane(few, cfg), ref.fit_ground_plane(few, cfg))


def test_ground_plane_equals_the_previous_code_on_edge_cases():
    cfg = GroundPlaneConfig(sample_points=50, iterations=20)
    rng = np.random.default_rng(1)
    ints = rng.integers(-5, 5, (200, 3))
    ints[:, 2] = 0
    cases = [ints, ints.tolist(), np.array([[0, 0, 1.0], [np.nan, 0, 0], [1, 1, 1]]),
             np.array([[0, 0, 1.0], [1, 0, 1.0], [2, 0, 1.0], [np.inf, 1, 1]]),
             rng.uniform(-1, 1, (300, 3)).astype(np.float32)]
    for pts in cases:
        a, b = plane_or_error(fit_ground_plane, pts, cfg), \
            plane_or_error(ref.fit_ground_plane, pts, cfg)
        if isinstance(b, str):
            assert a == b
        else:
            assert_same_plane(a, b)
