"""Robot profiles: loading, derived geometry, URDF consistency, bad profiles refused."""

from pathlib import Path

import numpy as np
import pytest
import yaml

from terrain_perception import kinematics
from terrain_perception.robot_model import (LEG_NAMES, available_robots, load_robot_model,
                                            model_from_dict)
from terrain_perception.sim.urdf_gen import generate_urdf

ROBOTS = ('littledog', 'frog')


@pytest.mark.parametrize('name', ROBOTS)
def test_profile_loads_with_consistent_geometry(name):
    m = load_robot_model(name)
    assert name in available_robots()
    assert m.joint_names[:3] == ('LF_hip_abduction', 'LF_hip_flexion', 'LF_knee')
    assert len(m.joint_names) == 12 and m.joint_names[-1] == 'RH_knee'
    # Left legs on +y, front legs on +x.
    assert np.all(m.hip_offsets[[0, 2], 1] > 0) and np.all(m.hip_offsets[[1, 3], 1] < 0)
    assert np.all(m.hip_offsets[:2, 0] > 0) and np.all(m.hip_offsets[2:, 0] < 0)
    # The nominal stance is reachable and puts the contact points at -standing height.
    q = kinematics.standing_joint_angles(m)
    feet = kinematics.forward(m, q)
    np.testing.assert_allclose(feet[:, 2] - m.foot_radius_m, -m.standing_height_m, atol=1e-12)
    # Camera looks forward and down; optical x points to the robot's right.
    z_cam = m.T_base_camera[:3, 2]
    assert z_cam[0] > 0 and z_cam[2] < 0
    np.testing.assert_allclose(m.T_base_camera[:3, 0], [0, -1, 0], atol=1e-12)
    np.testing.assert_allclose(m.T_base_camera[:3, :3].T @ m.T_base_camera[:3, :3], np.eye(3),
                               atol=1e-12)
    assert m.stereo.baseline_m == m.baseline_m > 0


def test_littledog_matches_its_sources():
    m = load_robot_model('littledog')
    assert 2.5 <= m.total_mass_kg <= 3.0          # ~2.5-2.75 kg robot
    assert m.baseline_m == pytest.approx(0.03)      # short-baseline Tyzx head camera
    assert m.camera_rate_hz == pytest.approx(2.0)   # paper 000: pictures twice a second


def test_frog_matches_paper_002():
    m = load_robot_model('frog')
    assert (m.camera.width, m.camera.height) == (640, 480)
    assert m.body_move_per_period_m == pytest.approx(0.2)
    assert np.degrees(m.camera_pitch_down_rad) == pytest.approx(90.0 - 59.4)
    # It must be able to lift a foot over a 0.15 m stone from its stance.
    assert m.standing_height_m - 0.15 - m.foot_radius_m > abs(m.thigh_length_m -
                                                               m.shank_length_m)


@pytest.mark.parametrize('name', ROBOTS)
def test_committed_urdf_is_generated_from_profile(name):
    m = load_robot_model(name)
    assert m.urdf_path.read_text() == generate_urdf(m), \
        'run python -m terrain_perception.sim.urdf_gen and commit the URDFs'


def _profile_dict(name='littledog'):
    return yaml.safe_load((Path(load_robot_model(name).source_path)).read_text())


def test_bad_profiles_are_refused_naming_the_problem():
    with pytest.raises(ValueError, match='unknown robot'):
        load_robot_model('no_such_robot')
    d = _profile_dict()
    del d['legs']['thigh_length_m']
    with pytest.raises(ValueError, match='thigh_length_m'):
        model_from_dict(d)
    d = _profile_dict()
    d['legs']['hip_offsets_m'].pop('RH')
    with pytest.raises(ValueError, match='hip_offsets_m'):
        model_from_dict(d)
    d = _profile_dict()
    d['legs']['joint_limits_rad']['LF'][2] = [1.0, -1.0]
    with pytest.raises(ValueError, match='lower < upper'):
        model_from_dict(d)
    d = _profile_dict()
    d['gait']['standing_height_m'] = 1.0
    with pytest.raises(ValueError, match='reach'):
        model_from_dict(d)
    d = _profile_dict()
    d['camera']['baseline_m'] = float('nan')
    with pytest.raises(ValueError, match='baseline_m'):
        model_from_dict(d)


def test_model_arrays_are_read_only():
    m = load_robot_model('littledog')
    with pytest.raises(ValueError):
        m.hip_offsets[0, 0] = 1.0
    assert LEG_NAMES == m.leg_names


@pytest.mark.parametrize('name', ['littledog', 'frog'])
def test_nearest_ground_seen_is_where_the_image_ends(name):
    """Level ground just beyond ``nearest_ground_seen_m`` projects into the image's bottom row,
    ground 1 cm nearer below the image: the band the robot never sees from its stance."""
    m = load_robot_model(name)
    near = m.nearest_ground_seen_m
    T_world_base = np.eye(4)
    T_world_base[2, 3] = m.standing_height_m
    T_cam_world = np.linalg.inv(T_world_base @ m.T_base_camera)

    def row(x):
        p = T_cam_world @ np.array([x, 0.0, 0.0, 1.0])
        return m.camera.fy * p[1] / p[2] + m.camera.cy

    assert row(near) == pytest.approx(m.camera.height - 1, abs=1e-6)
    assert row(near + 0.01) < m.camera.height - 1 < row(near - 0.01)
    front = float(m.nominal_feet[:, 0].max())
    blind = {'littledog': 0.133, 'frog': 0.520}[name]
    assert near - front == pytest.approx(blind, abs=0.002)


def test_closed_loop_trials_start_with_the_rough_section_in_view():
    """A bench trial's front gap is widened to the robot's blind band (plus a margin), so no
    rough cell lies where no capture can see it; LittleDog's 0.3 m needs nothing."""
    from terrain_perception.bench.closed_loop import VIEW_MARGIN_M, _start_x, effective_gap
    from terrain_perception.terrain import COURSE_CLASSES
    for robot, course in (('littledog', 'rocks-6cm'), ('frog', 'stones-15cm')):
        m = load_robot_model(robot)
        start = _start_x(course, robot, 0.3)
        first_seen = start + m.nearest_ground_seen_m
        assert first_seen <= COURSE_CLASSES[course].approach_m - VIEW_MARGIN_M + 1e-9
        gap = COURSE_CLASSES[course].approach_m - start - m.nominal_feet[:, 0].max()
        assert gap == pytest.approx(effective_gap(robot, 0.3))
    assert effective_gap('littledog', 0.3) == 0.3
    assert effective_gap('frog', 0.3) == pytest.approx(0.57)
    assert effective_gap('frog', 0.8) == 0.8
