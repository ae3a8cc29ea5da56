"""RANSAC ground plane: known planes with outliers, pitch and height, repeatability, errors."""

import numpy as np
import pytest

from terrain_perception.ground_plane import (GroundPlaneConfig, camera_pitch_from_pose,
                                             fit_ground_plane, plane_from_normal)
from terrain_perception.transforms import invert, make_T, rot_x, transform_points


def camera_looking_down(pitch_rad, height_m):
    """T_world_cam of an optical frame at height h, pitched down by ``pitch`` about world y.

    Optical axes in the world (x forward, z up): z_cam = (cos p, 0, -sin p), x_cam = -y_world
    (right), y_cam = z_cam x x_cam... built explicitly below.
    """
    zc = np.array([np.cos(pitch_rad), 0.0, -np.sin(pitch_rad)])
    xc = np.array([0.0, -1.0, 0.0])
    yc = np.cross(zc, xc)
    return make_T(np.stack([xc, yc, zc], axis=1), [0.0, 0.0, height_m])


def ground_scene(rng, n_ground, n_out, pitch, height, noise=0.003):
    """Camera-frame points: ground z=0 ahead of the camera plus boxes/clutter above it."""
    g = np.column_stack([rng.uniform(0.3, 3.0, n_ground), rng.uniform(-1.0, 1.0, n_ground),
                         rng.normal(0, noise, n_ground)])
    o = np.column_stack([rng.uniform(0.3, 3.0, n_out), rng.uniform(-1.0, 1.0, n_out),
                         rng.uniform(0.05, 0.4, n_out)])
    T_world_cam = camera_looking_down(pitch, height)
    return transform_points(invert(T_world_cam), np.vstack([g, o])), T_world_cam


@pytest.mark.parametrize('pitch_deg,height', [(30.0, 0.35), (59.4, 0.6), (10.0, 0.2)])
def test_recovers_known_plane_with_40_percent_outliers(pitch_deg, height):
    rng = np.random.default_rng(1)
    pts, T = ground_scene(rng, 3000, 2000, np.radians(pitch_deg), height)
    assert np.isclose(camera_pitch_from_pose(T), np.radians(pitch_deg))
    plane = fit_ground_plane(pts, GroundPlaneConfig(sample_points=2000, iterations=200,
                                                    inlier_threshold_m=0.01))
    assert abs(np.degrees(plane.pitch_rad) - pitch_deg) < 0.3
    assert abs(plane.height_m - height) < 0.005
    assert plane.d == plane.height_m
    up_in_cam = invert(T)[:3, :3] @ np.array([0, 0, 1.0])
    assert plane.normal @ up_in_cam > np.cos(np.radians(0.3))
    assert 0.5 < plane.inlier_ratio < 0.7          # ~60% of the sample lies on the ground
    # The refitted plane passes through the ground points.
    assert np.median(np.abs(plane.distance(pts[:3000]))) < 0.005


def test_organized_cloud_with_nans_and_repeatable_seed():
    rng = np.random.default_rng(2)
    pts, _ = ground_scene(rng, 1200, 800, np.radians(40), 0.4)
    org = np.full((50, 50, 3), np.nan)
    org.reshape(-1, 3)[:2000] = pts
    a = fit_ground_plane(org, GroundPlaneConfig(seed=7))
    b = fit_ground_plane(org, GroundPlaneConfig(seed=7))
    np.testing.assert_array_equal(a.normal, b.normal)
    assert abs(np.degrees(a.pitch_rad) - 40) < 0.5


def test_a_plain_random_cloud_is_refused():
    rng = np.random.default_rng(3)
    with pytest.raises(ValueError, match='holds only'):
        fit_ground_plane(rng.uniform(-1, 1, (2000, 3)),
                         GroundPlaneConfig(inlier_threshold_m=0.002, min_inlier_ratio=0.2))


def test_too_few_or_degenerate_points_raise():
    with pytest.raises(ValueError, match='at least 3'):
        fit_ground_plane(np.array([[0, 0, 1.0], [np.nan, 0, 0], [1, 1, 1]]))
    line = np.column_stack([np.linspace(0, 1, 50)] * 3)
    with pytest.raises(ValueError, match='degenerate'):
        fit_ground_plane(line)


def test_plane_from_normal_orients_towards_camera():
    p = plane_from_normal([0, 2, 0], -1.0)    # 2y - 1 = 0: ground 0.5 m below a level y-down cam
    np.testing.assert_allclose(p.normal, [0, -1, 0])
    assert p.height_m == 0.5 and p.pitch_rad == 0.0
    # Up seen from a camera pitched 0.3 rad down is (0, -cos, -sin); given flipped here.
    q = plane_from_normal([0, np.cos(0.3), np.sin(0.3)], -2.0)
    assert np.isclose(q.d, 2.0, rtol=0.0, atol=1e-12) and np.isclose(q.pitch_rad, 0.3)
    assert np.isclose(camera_pitch_from_pose(camera_looking_down(0.25, 1.0)), 0.25)
    # An optical frame equal to the world frame looks straight up.
    assert np.isclose(camera_pitch_from_pose(make_T(rot_x(0.0))), -np.pi / 2)


def test_below_penalty_prefers_the_floor_under_a_larger_plateau():
    # A plateau 10 cm up holds more points than the visible floor: plain RANSAC takes the
    # plateau, the below-penalty (the floor points lie under the plateau) takes the floor.
    rng = np.random.default_rng(4)
    T = camera_looking_down(np.radians(30), 0.4)
    floor = np.column_stack([rng.uniform(0.3, 1.5, 1000), rng.uniform(-1, 1, 1000),
                             rng.normal(0, 0.001, 1000)])
    top = np.column_stack([rng.uniform(1.0, 2.5, 1500), rng.uniform(-1, 1, 1500),
                           0.1 + rng.normal(0, 0.001, 1500)])
    pts = transform_points(invert(T), np.vstack([floor, top]))
    plain = fit_ground_plane(pts, GroundPlaneConfig(below_penalty=0.0))
    assert abs(plain.height_m - 0.3) < 0.005
    ground = fit_ground_plane(pts, GroundPlaneConfig(below_penalty=2.0))
    assert abs(ground.height_m - 0.4) < 0.005
    assert abs(np.degrees(ground.pitch_rad) - 30) < 0.3
