"""Gait core: support margins, COG targets, swing clearance over terrain, footstep sequences."""

import numpy as np
import pytest

from terrain_perception import gait as G
from terrain_perception.grid import ELEVATION, GridMap
from terrain_perception.robot_model import load_robot_model
from terrain_perception.transforms import make_T, rot_z


def test_support_margin_of_a_square():
    sq = np.array([[0, 0], [1, 0], [1, 1], [0, 1.0]])
    assert G.support_margin([0.5, 0.5], sq) == pytest.approx(0.5)
    assert G.support_margin([0.2, 0.5], sq) == pytest.approx(0.2)
    assert G.support_margin([1.3, 0.5], sq) == pytest.approx(-0.3)
    # Two support points: minus the distance to the segment.
    assert G.support_margin([0.5, 0.4], sq[:2]) == pytest.approx(-0.4)


def test_projection_into_support_keeps_the_margin():
    tri = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    inside = np.array([0.2, 0.2])
    p, m = G.project_into_support(inside, tri, 0.1)
    np.testing.assert_allclose(p, inside)
    rng = np.random.default_rng(0)
    for pt in rng.uniform(-1, 2, size=(50, 2)):
        p, m = G.project_into_support(pt, tri, 0.1)
        assert m == pytest.approx(0.1, abs=1e-9) or G.support_margin(pt, tri) >= 0.1
        assert G.support_margin(p, tri) >= 0.1 - 1e-9
    # The nearest admissible point: from (2, 2) it is on the inset hypotenuse.
    p, _ = G.project_into_support([2.0, 2.0], tri, 0.1)
    assert p[0] == pytest.approx(p[1])
    # A margin larger than the inradius (0.293) gives the incentre with its margin.
    p, m = G.project_into_support([2.0, 2.0], tri, 0.5)
    r_in = 1.0 / (2.0 + np.sqrt(2.0))
    np.testing.assert_allclose(p, [r_in, r_in], atol=1e-6)
    assert m == pytest.approx(r_in, abs=1e-6)


def test_swing_clears_a_box_under_its_path():
    box_top = 0.05

    def height(xy):
        xy = np.asarray(xy)
        on = (np.abs(xy[..., 0] - 0.5) < 0.05) & (np.abs(xy[..., 1]) < 0.2)
        return np.where(on, box_top, 0.0)

    p0, p1 = np.array([0.4, 0.0, 0.0]), np.array([0.62, 0.0, 0.0])
    apex = G.swing_apex(p0, p1, height, clearance_m=0.02, corridor_m=0.01, min_lift_m=0.01)
    assert apex == pytest.approx(box_top + 0.02)
    sw = G.SwingTrajectory(p0, p1, apex, 0.5)
    t = np.linspace(0, 0.5, 2001)
    path = sw.position(t)
    np.testing.assert_allclose(path[0], p0, atol=1e-12)
    np.testing.assert_allclose(path[-1], p1, atol=1e-12)
    # Over the box (plus the foot's corridor) the foot is at least the clearance above it.
    over = np.abs(path[:, 0] - 0.5) < 0.06
    assert over.any()
    assert np.all(path[over, 2] >= box_top + 0.02 - 1e-9)
    # Everywhere the foot stays above the terrain.
    assert np.all(path[:, 2] >= height(path[:, :2]) - 1e-12)
    # Without terrain only the minimum lift applies.
    assert G.swing_apex(p0, p1, None, 0.02, 0.01, 0.03) == pytest.approx(0.03)


def test_swing_final_approach_descends_slowly_over_its_height():
    p0, p1 = np.array([0.0, 0.0, 0.01]), np.array([0.1, 0.0, 0.0])
    sw = G.SwingTrajectory(p0, p1, 0.05, 0.35, approach_m=0.02, approach_speed_m_s=0.1)
    assert sw.approach_s == pytest.approx(0.2) and sw.total_s == pytest.approx(0.55)
    t = np.linspace(0.0, sw.total_s, 5501)
    path = sw.position(t)
    np.testing.assert_allclose(path[0], p0, atol=1e-12)
    np.testing.assert_allclose(path[-1], p1, atol=1e-12)
    np.testing.assert_allclose(sw.position(0.35), p1 + [0.0, 0.0, 0.02], atol=1e-12)
    vz = np.gradient(path[:, 2], t)
    # the last 2 cm of the way down: at most the approach speed
    low = (t > 0.2) & (path[:, 2] < p1[2] + 0.02 - 1e-9)
    assert low.any() and np.all(vz[low] >= -0.1 - 1e-6)
    assert vz.min() < -0.5                       # the minimum-jerk lowering above it is fast
    # x-y are at the foothold before the approach starts: the foot comes straight down
    assert np.all(np.abs(path[low, 0] - p1[0]) < 1e-9)
    # Without an approach the lowering ends at the foothold at full minimum-jerk speed.
    plain = G.SwingTrajectory(p0, p1, 0.05, 0.35)
    assert plain.total_s == 0.35
    tp = np.linspace(0.0, 0.35, 3501)
    zp = plain.position(tp)[:, 2]
    assert np.gradient(zp, tp)[(tp > 0.2) & (zp < p1[2] + 0.02)].min() < -0.3
    # The approach never starts above the apex.
    low_apex = G.SwingTrajectory(p0, p1, 0.012, 0.35, approach_m=0.02, approach_speed_m_s=0.1)
    assert low_apex.approach_height_m == pytest.approx(0.012)
    assert low_apex.position(low_apex.total_s)[2] == pytest.approx(0.0)


def test_swing_apex_reads_a_grid_map():
    g = GridMap.empty(0.01, (0.0, -0.5), (100, 100))
    g[ELEVATION] = np.zeros((100, 100), np.float32)
    g[ELEVATION][45:55, :] = 0.08
    g[ELEVATION][0:5, :] = np.nan          # unknown cells add no constraint
    apex = G.swing_apex([0.3, 0, 0], [0.7, 0, 0], g, 0.02, 0.01, 0.01)
    assert apex == pytest.approx(0.10, abs=1e-6)


@pytest.mark.parametrize('gait', ['walk', 'trot'])
def test_straight_footsteps_end_on_the_commanded_stance(gait):
    m = load_robot_model('littledog')
    T = make_T(rot_z(0.3), [1.0, 2.0, m.standing_height_m])
    legs, pos = G.straight_footsteps(m, T, 0.55, 0.1, gait=gait)
    n_periods = 6
    assert len(legs) == 4 * n_periods
    if gait == 'walk':
        assert legs[:4].tolist() == [G.LH, G.LF, G.RH, G.RF]
    else:
        assert legs[:4].tolist() == [G.LF, G.RH, G.RF, G.LH]
    end = G.nominal_feet_world(m, T) + 0.55 * np.array([np.cos(0.3), np.sin(0.3), 0.0])
    last = {int(lg): p for lg, p in zip(legs, pos)}
    np.testing.assert_allclose([last[k] for k in range(4)], end, atol=1e-12)
    body = G.body_pose_from_feet(end, m.standing_height_m)
    np.testing.assert_allclose(body, [1.0 + 0.55 * np.cos(0.3), 2.0 + 0.55 * np.sin(0.3),
                                      m.standing_height_m, 0.3], atol=1e-12)
    with pytest.raises(ValueError, match='max_step_length'):
        G.straight_footsteps(m, T, 1.0, 0.5)


def test_body_tilt_follows_the_feet_plane_and_poses_agree():
    """Front feet 4 cm above the hind ones, 0.2 m apart: the nose pitches up by gain x
    atan(0.04 / 0.2) (negative pitch); left 2 cm above right, 0.14 m apart: roll up on the
    left. The cap holds, gain 0 is level, and the batched poses equal the single ones."""
    feet = np.array([[0.1, 0.07, 0.06], [0.1, -0.07, 0.04], [-0.1, 0.07, 0.02],
                     [-0.1, -0.07, 0.0]])
    pitch, roll = G.body_tilt_from_feet(feet, 0.0, 1.0, np.radians(30))
    assert pitch == pytest.approx(-np.arctan2(0.04, 0.2))
    assert roll == pytest.approx(np.arctan2(0.02, 0.14))
    half = G.body_tilt_from_feet(feet, 0.0, 0.5, np.radians(30))
    assert half == pytest.approx((0.5 * pitch, 0.5 * roll))
    assert G.body_tilt_from_feet(feet, 0.0, 1.0, np.radians(5)) == pytest.approx(
        (-np.radians(5), np.radians(5)))
    assert G.body_tilt_from_feet(feet, 0.0, 0.0, 1.0) == (0.0, 0.0)
    # walking along -x: front and hind swap, so the same feet pitch the other way
    assert G.body_tilt_from_feet(feet[[2, 3, 0, 1]], np.pi, 1.0, 1.0)[0] == \
        pytest.approx(-pitch)
    bodies = np.array([[0.1, 0.2, 0.3, 0.4, pitch, roll], [0, 0, 0.1, -2.0, 0.0, 0.0]])
    T = G.poses_to_T(bodies)
    for k in range(2):
        np.testing.assert_allclose(T[k], G.pose_to_T(bodies[k]), atol=1e-12)
    # the tilted body's x axis climbs towards the front feet
    assert T[0, 2, 0] > 0


def test_swing_lift_xy_moves_sideways_while_lifting_and_ends_on_target():
    p0, p1 = np.array([0.0, -0.11, 0.0]), np.array([0.06, -0.07, 0.05])
    lead = np.array([0.0, 0.04])
    sw = G.SwingTrajectory(p0, p1, 0.09, 0.4, lift_xy=lead)
    plain = G.SwingTrajectory(p0, p1, 0.09, 0.4)
    for s in (sw, plain):
        np.testing.assert_allclose(s.position(0.0), p0, atol=1e-12)
        np.testing.assert_allclose(s.position(0.4), p1, atol=1e-12)
    top = 0.25 * 0.4                               # the end of the lift (lift_fraction 0.25)
    a, b = sw.position(top), plain.position(top)
    assert a[2] == pytest.approx(0.09) and b[2] == pytest.approx(0.09)
    # the sideways part is done by the top of the lift, the forward part barely started
    assert a[1] == pytest.approx(-0.07, abs=0.002) and a[0] < 0.002
    assert b[1] == pytest.approx(-0.11, abs=0.002)
    # and the foot rises with it: half-way up it is about half-way in
    t = np.linspace(0.0, top, 201)
    path = sw.position(t)
    k = int(np.argmin(np.abs(path[:, 2] - 0.045)))
    assert path[k, 1] == pytest.approx(-0.09, abs=0.004)
