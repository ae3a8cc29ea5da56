"""Body path (terrain_perception.body_path) and the footstep planner's belly clearance."""

import numpy as np
import pytest

from terrain_perception import features
from terrain_perception import footsteps as fs
from terrain_perception.body_path import plan_body_path
from terrain_perception.grid import GridMap
from terrain_perception.robot_model import load_robot_model

ROBOT = load_robot_model('littledog')       # belly 0.115 m up when standing on flat ground
RES = 0.01


def _grid(h, origin=(-0.5, -0.6)):
    g = GridMap(RES, origin, h.shape, {'elevation': h.astype(np.float32)})
    g['cost'] = features.cost_map(h, RES)
    return g


def _field(rock_h=0.11, rock_y=(-0.12, 0.12), rock_x=(0.6, 0.8), shape=(250, 120)):
    """Flat floor, one flat-topped block ``rock_h`` high over x in ``rock_x``, y in ``rock_y``
    [m] (grid x from -0.5, y from -0.6)."""
    h = np.zeros(shape)
    xs = -0.5 + (np.arange(shape[0]) + 0.5) * RES
    ys = -0.6 + (np.arange(shape[1]) + 0.5) * RES
    X, Y = np.meshgrid(xs, ys, indexing='ij')
    h[(X > rock_x[0]) & (X < rock_x[1]) & (Y > rock_y[0]) & (Y < rock_y[1])] = rock_h
    return h, X, Y


def _underside_top(g, path, heading=0.0):
    """Highest terrain under the body box at each path point (heading along +x)."""
    length, width, _ = ROBOT.body_size_m
    out = []
    for p in path:
        X, Y = g.cell_centers()
        xx, yy = np.meshgrid(X, Y, indexing='ij')
        under = (np.abs(xx - p[0]) <= 0.5 * length) & (np.abs(yy - p[1]) <= 0.5 * width)
        out.append(float(g['elevation'][under].max()) if under.any() else 0.0)
    return np.array(out)


def _dense(points, step=0.01):
    """The polyline ``points`` resampled every ``step`` [m]."""
    out = [points[0]]
    for a, b in zip(points[:-1], points[1:]):
        n = max(int(np.ceil(np.hypot(*(b - a)) / step)), 1)
        out += [a + (b - a) * t for t in np.linspace(0, 1, n + 1)[1:]]
    return np.array(out)


def test_on_open_ground_the_body_path_is_the_straight_line():
    h, _, _ = _field(rock_h=0.0)
    path = plan_body_path(_grid(h), ROBOT, [0.0, 0.0], [1.5, 0.1], 0.0)
    assert path.reaches_goal and path.blocked < 0.5
    np.testing.assert_allclose(path.points, [[0.0, 0.0], [1.5, 0.1]])
    # Beyond the map the rest of the way is straight on too.
    far = plan_body_path(_grid(h), ROBOT, [0.0, 0.0], [4.0, 0.4], 0.0)
    assert not far.reaches_goal
    np.testing.assert_allclose(far.points, [[0.0, 0.0], [4.0, 0.4]])


def test_the_body_path_goes_round_a_rock_too_tall_for_the_belly():
    # An 11 cm block on the centre line: the belly (11.5 cm up) would not clear it by 1.5 cm
    # with the feet on the floor. A 6 cm one it clears: no detour.
    h, _, _ = _field(rock_h=0.11)
    g = _grid(h)
    path = plan_body_path(g, ROBOT, [0.0, 0.0], [1.5, 0.0], 0.0)
    dense = _dense(path.points)
    assert path.reaches_goal
    assert _underside_top(g, dense).max() == 0.0          # never over the block
    assert np.abs(dense[:, 1]).max() > 0.12 + 0.05        # beside it by half a body width
    assert np.abs(dense[:, 1]).max() < 0.35               # and not further than it needs
    low, _, _ = _field(rock_h=0.06)
    straight = plan_body_path(_grid(low), ROBOT, [0.0, 0.0], [1.5, 0.0], 0.0)
    np.testing.assert_allclose(straight.points, [[0.0, 0.0], [1.5, 0.0]])
    # A wall across the whole map: no way round; the path still heads for the goal, to
    # the last position before the wall.
    wall, _, _ = _field(rock_h=0.11, rock_y=(-1.0, 1.0))
    blocked = plan_body_path(_grid(wall), ROBOT, [0.0, 0.0], [1.5, 0.0], 0.0)
    assert not blocked.reaches_goal
    end = blocked.points[-2]                  # the last lattice point, then straight on
    assert 0.3 < end[0] < 0.6


def test_the_corridor_bounds_the_path_and_nothing_outside_it_matters():
    # An 11 cm block on the centre line, a 0.3 m corridor: the path goes round inside it. Rocks
    # and unknown cells outside the corridor change nothing (the search looks only inside it);
    # a corridor too narrow to pass the block stops the path before it.
    h, X, Y = _field(rock_h=0.11)
    corridor = (np.array([0.0, 0.0]), np.array([1.5, 0.0]), 0.3)
    path = plan_body_path(_grid(h), ROBOT, [0.0, 0.0], [1.5, 0.0], 0.0, corridor=corridor)
    dense = _dense(path.points)
    assert path.reaches_goal
    assert 0.12 + 0.05 < np.abs(dense[:, 1]).max() <= 0.3 + 1e-9
    rng = np.random.default_rng(3)
    outside = np.abs(Y) > 0.3 + 0.1
    h2 = h.copy()
    h2[outside] = rng.uniform(0.0, 0.15, int(outside.sum()))
    h2[outside & (X > 0.9)] = np.nan
    same = plan_body_path(_grid(h2), ROBOT, [0.0, 0.0], [1.5, 0.0], 0.0, corridor=corridor)
    np.testing.assert_array_equal(same.points, path.points)
    assert same.blocked == path.blocked and same.reaches_goal
    narrow = plan_body_path(_grid(h), ROBOT, [0.0, 0.0], [1.5, 0.0], 0.0,
                            corridor=(corridor[0], corridor[1], 0.1))
    assert not narrow.reaches_goal
    assert narrow.points[-2][0] < 0.6         # the last lattice point is before the block


def test_the_body_path_rejects_non_finite_input():
    h, _, _ = _field(rock_h=0.0)
    with pytest.raises(ValueError, match='finite'):
        plan_body_path(_grid(h), ROBOT, [0.0, np.nan], [1.0, 0.0], 0.0)


def test_unknown_cells_cost_more_but_do_not_block():
    # Unknown across all the width the body can use: the path crosses it, straight.
    h, X, Y = _field(rock_h=0.0)
    h[(X > 0.4) & (X < 0.9)] = np.nan
    path = plan_body_path(_grid(h), ROBOT, [0.0, 0.0], [1.5, 0.0], 0.0)
    assert path.reaches_goal
    np.testing.assert_allclose(path.points, [[0.0, 0.0], [1.5, 0.0]])


def test_the_planner_steers_round_the_rock_and_keeps_the_belly_clear():
    h, _, _ = _field(rock_h=0.11, rock_y=(-0.12, 0.06))     # more room on the left (+y)
    g = _grid(h)
    T = np.eye(4)
    T[:3, 3] = [0.25, 0.0, ROBOT.standing_height_m]
    feet = np.array(ROBOT.nominal_feet) + [0.25, 0.0, 0.0]
    feet[:, 2] = 0.0
    on = fs.FootstepPlanner(ROBOT, fs.PlannerConfig())
    assert on.set_map(g) is None
    plan = on.plan(T, np.array([1.5, 0.0]), feet=feet)
    assert plan.ok, plan.status_text
    assert plan.yaw == pytest.approx(on.cfg.max_turn_rad)   # turning left, as fast as allowed
    assert on.body_path is not None and on.body_path.points[:, 1].max() > 0.1
    off = fs.FootstepPlanner(ROBOT, fs.PlannerConfig(belly_clearance_m=-1.0))
    assert off.set_map(g) is None
    plan = off.plan(T, np.array([1.5, 0.0]), feet=feet)
    assert plan.ok and plan.yaw == pytest.approx(0.0) and off.body_path is None


def _belly_gaps(g, plan, feet0):
    """For each footstep of ``plan``: the least height of the body box's underside above the
    terrain under it, the body at the step's planned swing pose over the stance before it."""
    from terrain_perception.body_path import belly_samples, top_field
    pts, spacing = belly_samples(ROBOT)
    top = top_field(g, spacing)
    stance, out = feet0.copy(), []
    for s in plan.footsteps:
        T = fs.body_pose(s.body_xy, stance, plan.yaw, ROBOT, height_m=s.body_height_m)
        p = pts @ T[:3, :3].T + T[:3, 3]
        ij = g.world_to_index(p[:, :2])
        out.append(float(np.min(p[:, 2] - top[ij[:, 0], ij[:, 1]])))
        stance[s.leg] = s.position
    return np.array(out)


def test_no_planned_body_pose_puts_the_belly_on_a_rock():
    # The body's front end just short of an 11.5 cm step up, feet on the floor, walking
    # straight at it (no body path): every planned swing pose keeps the belly 1.5 cm clear,
    # rising above the standing height (as far as the legs reach); without the check the
    # plan carries the belly onto the step's edge (gap 0).
    h, _, _ = _field(rock_h=0.115, rock_y=(-0.6, 0.6), rock_x=(0.13, 2.0))
    g = _grid(h)
    T = np.eye(4)
    T[:3, 3] = [0.0, 0.0, ROBOT.standing_height_m]
    feet = np.array(ROBOT.nominal_feet)
    feet[:, 2] = 0.0
    cfg = fs.PlannerConfig(body_path=False)
    planner = fs.FootstepPlanner(ROBOT, cfg)
    assert planner.set_map(g) is None
    plan = planner.plan(T, np.array([1.5, 0.0]), feet=feet)
    assert plan.ok, plan.status_text
    gaps = _belly_gaps(g, plan, feet)
    assert gaps.min() >= cfg.belly_clearance_m - 1e-3, (gaps, plan.status_text)
    assert max(s.body_height_m for s in plan.footsteps) > ROBOT.standing_height_m + 0.01
    # Three more centimetres of step: no reachable body pose clears it once the body is over
    # it; the plan stops short and says so.
    h2, _, _ = _field(rock_h=0.145, rock_y=(-0.6, 0.6), rock_x=(0.13, 2.0))
    g2 = _grid(h2)
    assert planner.set_map(g2) is None
    stuck = planner.plan(T, np.array([1.5, 0.0]), feet=feet)
    assert 'belly' in stuck.status_text, stuck.status_text
    assert len(stuck.footsteps) < 4
    if stuck.ok:
        assert _belly_gaps(g2, stuck, feet).min() >= cfg.belly_clearance_m - 1e-3
    off = fs.FootstepPlanner(ROBOT, fs.PlannerConfig(body_path=False, belly_clearance_m=-1))
    assert off.set_map(g) is None
    p_off = off.plan(T, np.array([1.5, 0.0]), feet=feet)
    assert p_off.ok and _belly_gaps(g, p_off, feet).min() < cfg.belly_clearance_m


def test_the_body_path_is_searched_once_per_map_pose_and_goal(monkeypatch):
    # plan_checked plans up to a dozen times from one pose: one search; a new map searches
    # again.
    h, _, _ = _field(rock_h=0.11, rock_y=(-0.12, 0.06))
    calls = []
    real = fs.plan_body_path
    monkeypatch.setattr(fs, 'plan_body_path', lambda *a, **k: calls.append(1) or real(*a, **k))
    planner = fs.FootstepPlanner(ROBOT, fs.PlannerConfig())
    assert planner.set_map(_grid(h)) is None
    T = np.eye(4)
    T[:3, 3] = [0.25, 0.0, ROBOT.standing_height_m]
    feet = np.array(ROBOT.nominal_feet) + [0.25, 0.0, 0.0]
    feet[:, 2] = 0.0
    plan = planner.plan_checked(T, np.array([1.5, 0.0]), feet, lambda legs, pos: (0, 'no'))
    assert not plan.ok and len(calls) == 1               # every first step refused: many plans
    first = planner.body_path
    assert planner.set_map(_grid(h)) is None
    planner.plan(T, np.array([1.5, 0.0]), feet=feet)
    assert len(calls) == 2
    np.testing.assert_allclose(planner.body_path.points, first.points)


@pytest.mark.parametrize('robot_name', ['littledog', 'frog'])
def test_the_compiled_headroom_kernel_equals_the_numpy_code(robot_name):
    """_body_path_kernel.belly_and_ground against body_path._belly_and_ground: bitwise equal
    maxima under the belly and ground under the feet, NaN where a foot's ground is unknown, and
    the same on-map test, for body positions on, across and off the map's border."""
    from terrain_perception import _body_path_kernel as kernel
    from terrain_perception import body_path as bp
    robot = load_robot_model(robot_name)
    rng = np.random.default_rng(3)
    h = rng.uniform(0.0, 0.12, (260, 200)).astype(np.float32)
    h[rng.random(h.shape) < 0.05] = np.nan              # unknown cells
    g = _grid(h)
    belly, spacing = bp.belly_samples(robot)
    top = bp.top_field(g, spacing)
    lo = np.asarray(g.origin_xy, dtype=np.float64)
    nodes = lo + rng.uniform(-0.2, 1.0, (3000, 2)) * np.asarray(g.length_xy)
    ring = float(robot.foot_radius_m) * np.array([[0, 0], [1, 0], [-1, 0], [0, 1], [0, -1]])
    for heading in (0.0, 0.4, -2.0):
        c, s = np.cos(heading), np.sin(heading)
        R = np.array([[c, -s], [s, c]])
        bxy = belly[:, :2] @ R.T
        fxy = (np.asarray(robot.nominal_feet)[:, None, :2] + ring[None]).reshape(-1, 2) @ R.T
        want_top, want_ground, want_on = bp._belly_and_ground(g, top, nodes, bxy, fxy, 5)
        got_top, got_ground = np.empty(len(nodes)), np.empty(len(nodes))
        got_on = np.empty(len(nodes), dtype=bool)
        kernel.belly_and_ground(nodes, bxy, fxy, 5, lo[0], lo[1], g.resolution_m, top,
                                np.ascontiguousarray(g['elevation'], dtype=np.float64),
                                got_top, got_ground, got_on)
        np.testing.assert_array_equal(got_on, want_on)
        assert 0.2 < want_on.mean() < 0.9          # both on- and off-map positions tested
        on = want_on
        np.testing.assert_array_equal(got_top[on], want_top[on])
        np.testing.assert_array_equal(got_ground[on], want_ground[on])   # NaNs in place too
        assert np.isnan(want_ground[on]).any() and np.isfinite(want_ground[on]).any()


def test_the_body_path_is_the_same_with_and_without_the_compiled_kernel():
    h, _, _ = _field(rock_h=0.11)
    g = _grid(h)
    from terrain_perception import body_path as bp
    try:
        paths = []
        for on in (False, True):
            bp.use_compiled_kernel(on)
            paths.append(plan_body_path(g, ROBOT, [0.0, 0.05], [1.6, 0.0], 0.0,
                                        corridor=(np.array([0.0, 0.0]), np.array([1.6, 0.0]),
                                                  0.3)))
    finally:
        bp.use_compiled_kernel(None)
    np.testing.assert_array_equal(paths[0].points, paths[1].points)
    assert paths[0].blocked == paths[1].blocked > 0
