"""Receding-horizon footstep planner and Shao's gait selection (papers 000 and 002)."""

import dataclasses

import numpy as np
import pytest

from terrain_perception import features
from terrain_perception import footsteps as fs
from terrain_perception.grid import GridMap
from terrain_perception.robot_model import load_robot_model

# Gait selection (paper 002 Fig. 4) is exercised on LittleDog's geometry with the trot allowed
# (its profile forbids it: paper 000's LittleDog crawls; see the last test).
ROBOT = dataclasses.replace(load_robot_model('littledog'), trot=True)
RES = 0.01


def _grid(heights, origin=(-0.75, -0.75), cost=True):
    g = GridMap(RES, origin, heights.shape, {'elevation': heights.astype(np.float32)})
    if cost:
        g['cost'] = features.cost_map(heights, RES)
    return g


def _flat(n=150):
    return _grid(np.zeros((n, n)))


def _rocks(seed, n=150, count=70, max_h=0.05):
    """Seeded synthetic rock field: flat-topped discs and cones of up to ``max_h``."""
    rng = np.random.default_rng(seed)
    X, Y = np.mgrid[0:n, 0:n]
    h = np.zeros((n, n))
    for _ in range(count):
        cx, cy = rng.integers(0, n, 2)
        r = rng.integers(3, 12)
        d = np.hypot(X - cx, Y - cy)
        top = rng.uniform(0.01, max_h)
        bump = np.where(d < r, top, 0.0) if rng.random() < 0.5 else np.clip(
            top * (1 - d / r), 0, None)
        h = np.maximum(h, bump)
    return _grid(h)


def _pose(x=0.0, y=0.0, yaw=0.0):
    T = np.eye(4)
    c, s = np.cos(yaw), np.sin(yaw)
    T[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    T[:3, 3] = [x, y, ROBOT.standing_height_m]
    return T


def _planner(cfg, grid):
    """A planner with ``cfg`` on ``grid`` (which it must accept)."""
    planner = fs.FootstepPlanner(ROBOT, cfg)
    assert planner.set_map(grid) is None
    return planner


def _rh_behind(by):
    """Nominal feet on the ground (z = 0) and the stance with RH ``by`` [m] behind its
    nominal place: ``(nominal, feet)``."""
    nom = np.array(ROBOT.nominal_feet)
    feet = nom.copy()
    feet[:, 2] = 0.0
    feet[fs.RH, 0] -= by
    return nom, feet


def _check_plan_feasible(plan, cfg, robot=ROBOT):
    """Replay the plan: every swing keeps the COG inside the other three feet's triangle by the
    margin, and every foot (stance, lift-off and touchdown) is within reach of the body."""
    feet = plan.initial_feet.copy()
    for s in plan.footsteps:
        others = [k for k in range(4) if k != s.leg]
        margin = fs.point_in_triangle_margin(s.body_xy, feet[others, :2])
        assert margin >= cfg.stability_margin_m - 1e-9, (s.step_index, margin)
        assert 0.8 * robot.standing_height_m - 1e-9 <= s.body_height_m \
            <= robot.standing_height_m + 1e-9
        T = fs.body_pose(s.body_xy, feet, plan.yaw, robot, height_m=s.body_height_m)
        both = np.vstack([feet, s.position])
        legs = np.r_[np.arange(4), s.leg]
        assert np.all(fs.reachable(robot, T, both, legs, cfg.reach_fraction)), s.step_index
        # The hip-to-foot distance check is independent of the IK: recompute it here.
        p_base = (s.position + [0, 0, robot.foot_radius_m] - T[:3, 3]) @ T[:3, :3]
        hip = np.array(robot.leg_plane_offsets)[s.leg]
        assert np.linalg.norm(p_base - hip) <= cfg.reach_fraction * robot.leg_length_m + 1e-9
        feet[s.leg] = s.position


def test_shao_cost_on_a_hand_computed_grid():
    h = np.zeros((5, 5))
    h[2, 2], h[2, 3] = 0.02, 0.01
    dev = 4 * 0.02 / np.sqrt(2) + 3 * 0.02 / 2 + 0.01 / 2          # eq. 3 at the centre cell
    shao = features.cost_map(h, RES, features.CostConfig(method='shao'))
    assert shao[2, 2] == pytest.approx(0.02 + dev, abs=1e-6)          # eq. 2: h + Dev(h)
    assert fs.flatness_cost(h, 0.0)[2, 2] == pytest.approx(0.02 + dev, abs=1e-9)
    assert fs.flatness_cost(h, 0.005)[2, 2] == pytest.approx(0.015 + dev, abs=1e-9)
    # A dip is not flat for gait selection: |h - ground|.
    assert fs.flatness_cost(-h, 0.0)[2, 2] == pytest.approx(0.02 + dev, abs=1e-9)
    assert fs.flatness_cost(np.zeros((5, 5)), 0.0).max() == 0.0


def test_cost_layer_sources():
    g = _rocks(0)
    np.testing.assert_array_equal(fs.cost_layer(g, 'layer'), g['cost'])
    np.testing.assert_allclose(fs.cost_layer(g, 'shao'), features.cost_map(
        g['elevation'], RES, features.CostConfig(method='shao')))
    del g.layers['cost']
    with pytest.raises(ValueError, match="no 'cost' layer"):
        fs.cost_layer(g, 'layer')
    with pytest.raises(ValueError, match='unknown cost source'):
        fs.cost_layer(g, 'magic')


def test_flat_ground_trots_with_stride_A():
    cfg = fs.PlannerConfig()
    plan = fs.plan_footsteps(_flat(), ROBOT, _pose(), np.array([0.6, 0.0]), cfg)
    assert plan.ok and plan.gait == fs.GAIT_TROT, plan.status_text
    A = ROBOT.body_move_per_period_m
    assert plan.body_move_per_period_m == pytest.approx(A)
    pairs = {}
    for s in plan.footsteps:
        pairs.setdefault(s.step_index, []).append(s.leg)
    assert [sorted(v) for v in pairs.values()][:2] == [sorted(fs.TROT_PAIRS[0]),
                                                       sorted(fs.TROT_PAIRS[1])]
    first = {s.leg: s.position for s in plan.footsteps if s.step_index < 2}
    for leg, p in first.items():
        np.testing.assert_allclose(p[:2] - plan.initial_feet[leg, :2], [A, 0.0], atol=1e-9)


def test_replanning_after_every_pair_keeps_trotting_in_alternation():
    """Receding horizon on flat ground with FROG-I (which trots): the plan is remade after each
    executed pair, so every other plan starts half-way through a trot period. It must finish
    that period with the other pair, not judge the pair that just swung out of position and
    walk: before this, trot and walk plans alternated, each trot began with LF+RH wherever it
    stood, and the stance spread until the robot fell (blind stones-15cm, seeds 100-109)."""
    robot = load_robot_model('frog')
    A = robot.body_move_per_period_m
    g = GridMap(0.02, (-1.0, -1.5), (300, 150), {'elevation': np.zeros((300, 150), np.float32)})
    g['cost'] = features.cost_map(g['elevation'], 0.02)
    planner = fs.FootstepPlanner(robot, fs.PlannerConfig())
    assert planner.set_map(g) is None
    feet = np.array(robot.nominal_feet)
    feet[:, 2] = 0.0
    nominal_span = float(feet[fs.LF, 0] - feet[fs.LH, 0])
    swung = []
    for _ in range(10):
        body_xy = feet[:, :2].mean(axis=0)     # the controller's body goal: over the feet
        T = _pose(*body_xy)
        T[2, 3] = robot.standing_height_m
        plan = planner.plan(T, np.array([3.0, 0.0]), feet=feet)
        assert plan.ok and plan.gait == fs.GAIT_TROT, plan.status_text
        first = [s for s in plan.footsteps if s.step_index == plan.footsteps[0].step_index]
        swung.append(tuple(sorted(s.leg for s in first)))
        for s in first:
            np.testing.assert_allclose(s.position[:2] - feet[s.leg, :2], [A, 0.0], atol=1e-6)
            feet[s.leg] = s.position
        for front, hind in ((fs.LF, fs.LH), (fs.RF, fs.RH)):
            assert abs(feet[front, 0] - feet[hind, 0] - nominal_span) <= A + 1e-6, feet
    assert swung == [(fs.LF, fs.RH), (fs.RF, fs.LH)] * 5
    assert feet[:, 0].mean() == pytest.approx(5 * A, abs=1e-6)


def test_obstacle_selects_walk_in_crawl_order_and_avoids_edges():
    h = np.zeros((150, 150))
    g0 = _flat()
    ij = g0.world_to_index(np.array([0.20, 0.07]))    # a 3 cm block ahead of the LF foot
    h[ij[0] - 3:ij[0] + 4, ij[1] - 3:ij[1] + 4] = 0.03
    g = _grid(h)
    cfg = fs.PlannerConfig()
    plan = fs.plan_footsteps(g, ROBOT, _pose(), np.array([0.6, 0.0]), cfg)
    assert plan.ok and plan.gait == fs.GAIT_WALK, plan.status_text
    assert 'obstacle' in plan.status_text
    assert [s.leg for s in plan.footsteps] == [fs.LH, fs.LF, fs.RH, fs.RF]
    lf = plan.footsteps[1].position
    edge = g['cost'] > 0.1                       # the block's rim (slope / height differential)
    assert not edge[tuple(g.world_to_index(lf[:2]))]
    assert all(s.cost < 0.1 for s in plan.footsteps)
    _check_plan_feasible(plan, cfg)


def _lf_ahead():
    """Nominal feet on the ground (z = 0) with LF 0.6 A ahead: flat ground, feet out of
    position (kL - wL = 0.6 A > A / 2)."""
    feet = np.array(ROBOT.nominal_feet)
    feet[:, 2] = 0.0
    feet[fs.LF, 0] += 0.6 * ROBOT.body_move_per_period_m
    return feet


@pytest.mark.parametrize('centre', ['capped', 'rule', 'adaptive'])
def test_flat_but_feet_out_of_position_walks_with_the_stride_rule(centre):
    # the paper's stride rule alone: our spread limit (tested below) would cap the leading
    # LF's next stride while the other feet lag
    cfg = fs.PlannerConfig(max_leg_spread_m=0.0, stride_centre=centre)
    g = _flat()
    planner = _planner(cfg, g)
    A = ROBOT.body_move_per_period_m
    feet = _lf_ahead()
    plan = planner.plan(_pose(), np.array([0.6, 0.0]), feet=feet)
    assert plan.ok and plan.gait == fs.GAIT_WALK, plan.status_text
    assert 'out of position' in plan.status_text
    # Uniform cost: omega puts each foothold at the centre of its search area
    # [kL, wL + 2A]: the paper's stride (2A + wL - kL) / 2. 'capped' centres the area after
    # the max-step cap, 'rule' takes the paper's centre and clips it to the max step.
    long_steps = 0
    for s in plan.footsteps:
        u0 = feet[s.leg, 0]
        rule_hi = ROBOT.nominal_feet[s.leg][0] + 2 * A
        hi = min(rule_hi, u0 + ROBOT.max_step_length_m)
        lo = u0 + cfg.min_step_m
        # on flat ground 'adaptive' is the rule
        want = 0.5 * (lo + max(hi, lo)) if centre == 'capped' else \
            min(0.5 * (lo + max(rule_hi, lo)), max(hi, lo))
        long_steps += want > 0.5 * (lo + max(hi, lo)) + RES
        assert s.position[0] == pytest.approx(want, abs=RES)
        assert s.position[1] == pytest.approx(feet[s.leg, 1], abs=RES)
    # the two centres differ here: the rule's strides are longer where the cap binds
    assert (long_steps > 0) == (centre != 'capped')
    _check_plan_feasible(plan, cfg)


def test_adaptive_stride_is_capped_where_the_search_area_is_not_flat():
    # A 2.5 cm knob at the lateral edge of every leg's search area (Shao's flatness cost above
    # the 2 cm threshold there): 'adaptive' must take the short capped strides, not the rule's.
    h = np.zeros((150, 150))
    feet = _lf_ahead()
    for k in range(4):
        ij = _flat().world_to_index(np.array([[feet[k, 0] + 0.05,
                                               ROBOT.nominal_feet[k][1] + 0.03]]))[0]
        h[ij[0], ij[1]] = 0.025
    g = _grid(h)
    plans = {}
    for centre in ('capped', 'rule', 'adaptive'):
        cfg = fs.PlannerConfig(max_leg_spread_m=0.0, stride_centre=centre)
        plans[centre] = _planner(cfg, g).plan(_pose(), np.array([0.6, 0.0]), feet=feet)
        assert plans[centre].ok, plans[centre].status_text
    where = {c: np.array([s.position for s in p.footsteps]) for c, p in plans.items()}
    assert np.array_equal(where['adaptive'], where['capped'])
    # the knobs leave the centres apart: the rule still strides further
    assert where['rule'][:, 0].sum() > where['capped'][:, 0].sum() + RES


@pytest.mark.parametrize('seed', [0, 1, 2, 3])
def test_rough_terrain_plans_stay_in_reach_and_stable(seed):
    cfg = fs.PlannerConfig(horizon_steps=8)
    g = _rocks(seed)
    planner = fs.FootstepPlanner(ROBOT, cfg)
    assert planner.set_map(g) is None
    n_ok = 0
    for x0, yaw in ((-0.2, 0.0), (0.0, 0.3), (0.1, -0.4)):
        plan = planner.plan(_pose(x0, 0.0, yaw))
        if plan.status == fs.STATUS_NO_FOOTHOLD:
            continue
        assert plan.ok, plan.status_text
        n_ok += 1
        assert len(plan.footsteps) >= 1
        _check_plan_feasible(plan, cfg)
        cost = g['cost']
        for s in plan.footsteps:
            ij = g.world_to_index(s.position[:2])
            assert s.cost == pytest.approx(float(cost[ij[0], ij[1]]))
            assert s.position[2] == pytest.approx(float(g['elevation'][ij[0], ij[1]]))
    assert n_ok >= 2


def test_planner_prefers_low_cost_cells_over_the_nominal_foothold():
    g = _flat()
    cfg = fs.PlannerConfig(trot_threshold_m=0.0)     # never "flat": always walk and search
    cost = np.full(g.shape, 0.5, np.float32)
    # Cheap cells only in two bands across the path, off the nominal stride of each leg.
    for x in (-0.08, 0.14):
        i = g.world_to_index(np.array([x, 0.0]))[0]
        cost[i - 1:i + 2, :] = 0.0
    g['cost'] = cost
    planner = fs.FootstepPlanner(ROBOT, cfg)
    assert planner.set_map(g) is None
    plan = planner.plan(_pose(), np.array([0.6, 0.0]))
    assert plan.ok and plan.gait == fs.GAIT_WALK, plan.status_text
    assert [s.cost for s in plan.footsteps] == [0.0] * 4
    _check_plan_feasible(plan, cfg)


@pytest.mark.parametrize('shortfall, elsewhere, long_strides',
                         [(50.0, 0.1, True), (50.0, 0.5, False), (0.0, 0.1, False)])
def test_stride_shortfall_weight_trades_progress_for_cost(shortfall, elsewhere, long_strides):
    """On rough ground the cell next to a foot is often the cheapest (run U took a third of
    its rock steps at the 1 cm minimum): with a shortfall weight of 50 a saving of 0.1 does not
    buy a 5 cm shorter stride, but a saving of 0.5 still does; without it (the default) 0.1
    does."""
    g = _flat()
    cfg = fs.PlannerConfig(trot_threshold_m=0.0,     # never "flat": the capped stride centre
                           shortfall_weight_per_m2=shortfall)
    feet = np.array(ROBOT.nominal_feet)
    feet[:, 2] = 0.0
    cost = np.full(g.shape, elsewhere, np.float32)
    for x in np.unique(feet[:, 0]):                  # free cells 1-2 cm ahead of each foot
        i0 = g.world_to_index(np.array([x + 0.01, 0.0]))[0]
        cost[i0:i0 + 2, :] = 0.0
    g['cost'] = cost
    plan = _planner(cfg, g).plan(_pose(), np.array([0.6, 0.0]), feet=feet)
    assert plan.ok and len(plan.footsteps) == 4, plan.status_text
    dx = np.array([s.position[0] - feet[s.leg, 0] for s in plan.footsteps])
    if long_strides:
        assert np.all(dx >= 0.04), dx
    else:
        assert np.all(dx <= 0.025), dx
    _check_plan_feasible(plan, cfg)


def test_never_observed_cells_need_a_tight_upper_bound():
    cfg = fs.PlannerConfig()
    g = _rocks(5)
    obs = np.ones(g.shape, np.float32)
    xs, _ = g.cell_centers()
    ahead = (xs > 0.05)[:, None] & np.ones(g.shape, bool)       # everything ahead unobserved
    obs[ahead] = 0.0
    g['observed'] = obs
    g['filled'] = 1.0 - obs
    g['upper_bound'] = np.full(g.shape, np.nan, np.float32)
    plan = fs.plan_footsteps(g, ROBOT, _pose(), None, cfg)
    for s in plan.footsteps:
        assert g['observed'][tuple(g.world_to_index(s.position[:2]))] == 1.0
    # With a line-of-sight bound 1 cm above the filled height the cells become usable.
    g['upper_bound'] = np.where(ahead, g['elevation'] + 0.01, np.nan).astype(np.float32)
    plan2 = fs.plan_footsteps(g, ROBOT, _pose(), None, cfg)
    assert plan2.ok
    assert any(g['observed'][tuple(g.world_to_index(s.position[:2]))] == 0.0
               for s in plan2.footsteps)
    # A loose bound (10 cm above) is not enough.
    g['upper_bound'] = np.where(ahead, g['elevation'] + 0.10, np.nan).astype(np.float32)
    plan3 = fs.plan_footsteps(g, ROBOT, _pose(), None, cfg)
    for s in plan3.footsteps:
        assert g['observed'][tuple(g.world_to_index(s.position[:2]))] == 1.0


def test_salient_patch_attracts_the_foothold():
    g = _flat()
    g['elevation'][:] = 0.0
    h = np.zeros(g.shape)
    g0 = _grid(h)
    ij = g0.world_to_index(np.array([0.20, 0.07]))
    h[ij[0] - 3:ij[0] + 4, ij[1] - 3:ij[1] + 4] = 0.03     # force a walk
    g = _grid(h)
    cfg = fs.PlannerConfig(patch_bonus=0.9)
    planner = fs.FootstepPlanner(ROBOT, cfg)
    assert planner.set_map(g) is None
    base = planner.plan(_pose(), np.array([0.6, 0.0]))
    lh = base.footsteps[0]
    assert lh.leg == fs.LH and lh.patch_index == -1
    target = lh.position + [-0.02, 0.0, 0.0]                # a patch 2 cm behind that choice
    patches = (np.array([[5.0, 5.0, 0.0], target]), np.array([0.01, 0.006]))
    with_patch = planner.plan(_pose(), np.array([0.6, 0.0]), patches=patches)
    s0 = with_patch.footsteps[0]
    assert s0.patch_index == 1
    assert np.hypot(*(s0.position[:2] - target[:2])) <= 0.006 + 1e-9


def test_bad_inputs_give_an_explanatory_empty_plan():
    cfg = fs.PlannerConfig()
    planner = fs.FootstepPlanner(ROBOT, cfg)
    cases = []
    p = planner.set_map(None)
    cases.append((p, fs.STATUS_NO_MAP))
    cases.append((planner.plan(_pose()), fs.STATUS_NO_MAP))
    empty = _grid(np.full((50, 50), np.nan), cost=False)
    empty['cost'] = np.full((50, 50), np.nan, np.float32)
    cases.append((planner.set_map(empty), fs.STATUS_BAD_MAP))
    nocost = _grid(np.zeros((50, 50)), cost=False)
    cases.append((planner.set_map(nocost), fs.STATUS_BAD_MAP))
    assert 'cost' in cases[-1][0].status_text
    g = _flat()
    assert planner.set_map(g) is None
    cases.append((planner.plan(_pose(5.0, 0.0)), fs.STATUS_ROBOT_OUTSIDE_MAP))
    far = planner.plan(_pose(), np.array([3.0, 0.3]))    # beyond the local map: head there
    assert far.ok and far.yaw == pytest.approx(np.arctan2(0.3, 3.0))   # < max_turn_rad
    behind = planner.plan(_pose(), np.array([-0.5, 0.0]))            # turns at most 0.1 rad
    assert behind.ok and abs(behind.yaw) == pytest.approx(cfg.max_turn_rad)
    cases.append((planner.plan(_pose(), np.array([np.nan, 0.0])), fs.STATUS_BAD_INPUT))
    bad_T = _pose()
    bad_T[0, 3] = np.nan
    cases.append((planner.plan(bad_T), fs.STATUS_BAD_INPUT))
    cases.append((planner.plan(_pose(), np.array([0.01, 0.0])), fs.STATUS_GOAL_REACHED))
    cases.append((planner.plan(_pose(), feet=np.zeros((3, 3))), fs.STATUS_BAD_INPUT))
    # Nowhere to step: only the cells under the current feet are known.
    h = np.full((150, 150), np.nan)
    for f in planner._nominal_feet(_pose()):
        i, j = g.world_to_index(f[:2])
        h[i, j] = 0.0
    island = _grid(h)
    assert planner.set_map(island) is None
    cases.append((planner.plan(_pose(), np.array([0.6, 0.0])), fs.STATUS_NO_FOOTHOLD))
    assert 'LH' in cases[-1][0].status_text and 'cannot be reached' in cases[-1][0].status_text
    for plan, status in cases:
        assert plan.status == status, plan.status_text
        assert plan.footsteps == [] and plan.status_text


def test_map_safety_factor_refuses_slopes_just_below_the_limit():
    """The 1 cm map under-reads the slopes and edges the foot meets, so the map's filter keeps
    a margin: a 28 deg plane (under the 30 deg limit, above 0.9 x 30 = 27) is refused by
    default and accepted without the margin."""
    n = 150
    x = (np.arange(n) * RES)[:, None] * np.ones((1, n))
    g = _grid(np.tan(np.radians(28.0)) * x)
    inner = np.s_[10:-10, 10:-10]
    default = fs.FootstepPlanner(ROBOT, fs.PlannerConfig())
    assert default.set_map(g) is None and not default.allowed[inner].any()
    plain = fs.FootstepPlanner(ROBOT, fs.PlannerConfig(map_safety_factor=1.0))
    assert plain.set_map(g) is None and plain.allowed[inner].all()
    steep = _grid(np.tan(np.radians(31.0)) * x)
    assert plain.set_map(steep) is None and not plain.allowed[inner].any()


def test_foot_surface_rises_only_where_the_ball_touches_a_wall():
    """The ball foot (radius 9.5 mm) lowered next to a 10 cm wall rests on the wall's top edge
    within its radius of it and on the floor beyond."""
    res, rho = 0.005, ROBOT.foot_radius_m
    h = np.zeros((40, 40))
    h[20:, :] = 0.10                       # wall from x index 20 on
    c = fs.foot_surface(h, res, rho)
    np.testing.assert_allclose(c[20:], 0.10)
    np.testing.assert_allclose(c[:18], 0.0)              # 10 mm from the wall: free
    assert c[19, 5] == pytest.approx(0.10 + np.sqrt(rho ** 2 - res ** 2) - rho)
    unknown = h.copy()
    unknown[0, 0] = np.nan
    assert np.isnan(fs.foot_surface(unknown, res, rho)[0, 0])


def test_floor_beside_a_rock_is_safe_on_the_foot_surface():
    """Floor 1 cm from the foot of a 60 deg, 8 cm rock: the heights' filter over 2 foot radii
    (its window reaches into the flank) refuses it; the foot's resting surface over 1 cm
    allows it (the ball does not touch the flank there). 5 mm from the rock the ball rests
    against the flank: refused on the foot's surface, though the heights over 1 cm pass."""
    res = 0.005
    n = 80
    x = np.arange(n) * res
    h = np.clip((x - 0.2) * np.tan(np.radians(60.0)), 0.0, 0.08)[:, None] * np.ones((1, n))
    g = GridMap(res, (0.0, 0.0), h.shape, {'elevation': h.astype(np.float32)})
    g['cost'] = features.cost_map(h, res)
    far, near, flank = (int(round((0.2 + d) / res)) for d in (-0.01, -0.005, 0.01))
    j = n // 2
    plain = fs.FootstepPlanner(ROBOT, fs.PlannerConfig(safety_surface='heights',
                                                       safety_window_m=0.0))
    assert plain.set_map(g) is None
    assert not plain.allowed[far, j] and not plain.allowed[flank, j]
    small = fs.FootstepPlanner(ROBOT, fs.PlannerConfig(safety_surface='heights',
                                                       safety_window_m=0.01))
    assert small.set_map(g) is None and small.allowed[near, j]
    foot = fs.FootstepPlanner(ROBOT, fs.PlannerConfig())     # the defaults
    assert foot.set_map(g) is None
    assert foot.allowed[far, j] and not foot.allowed[near, j] and not foot.allowed[flank, j]


def test_on_a_1cm_map_the_foot_surface_filter_is_the_one_before():
    """On the closed loop's 1 cm map no other cell centre is within the foot's radius and the
    window keeps 2 cells each side: the defaults flag what the heights over 2 foot radii did."""
    g = _rocks(3)
    new = fs.FootstepPlanner(ROBOT, fs.PlannerConfig())
    old = fs.FootstepPlanner(ROBOT, fs.PlannerConfig(safety_surface='heights',
                                                     safety_window_m=0.0))
    assert new.set_map(g) is None and old.set_map(g) is None
    np.testing.assert_array_equal(new.allowed, old.allowed)
    assert 0.05 < new.allowed.mean() < 0.95


def test_a_foot_left_behind_holds_the_others_back():
    """A hind foot stranded 2 cm short of the spread limit behind its nominal place: no
    planned foothold leads the rearmost other foot (both from their nominal places) by more
    than max_leg_spread_m, and the stranded foot is the one that catches up first."""
    cfg = fs.PlannerConfig(trot_threshold_m=0.0, horizon_steps=8)   # walk, look far ahead
    planner = _planner(cfg, _flat())
    nom, feet = _rh_behind(cfg.max_leg_spread_m - 0.02)
    plan = planner.plan(_pose(), np.array([0.6, 0.0]), feet=feet, first_leg=fs.LF)
    assert plan.ok, plan.status_text
    _check_plan_feasible(plan, cfg)
    cur = feet.copy()
    for s in plan.footsteps:
        lag = np.delete(cur[:, 0] - nom[:, 0], s.leg)
        assert s.position[0] - nom[s.leg, 0] <= lag.min() + cfg.max_leg_spread_m + 1e-9
        cur[s.leg] = s.position
    rh = [s for s in plan.footsteps if s.leg == fs.RH]
    assert rh and rh[0].position[0] > feet[fs.RH, 0] + 0.05


def test_candidate_cells_observed_bounded_or_vouched_for_by_the_feet():
    n = 6
    elev = np.zeros((n, n), np.float32)
    observed = np.zeros((n, n), np.float32)
    observed[0] = 1
    filled = 1.0 - observed
    ub = np.full((n, n), np.nan, np.float32)
    ub[1] = 0.01                                   # bounded 1 cm above the fill
    ub[2] = 0.2                                    # bound far above: not trusted
    contact = np.zeros((n, n), np.float32)
    contact[3] = 1
    filled[3] = 0
    g = GridMap(0.01, (0.0, 0.0), (n, n), {'elevation': elev, 'observed': observed,
                                           'upper_bound': ub, 'filled': filled,
                                           'contact': contact})
    ok = fs.candidate_mask(g, fs.PlannerConfig(max_bound_gap_m=0.02))
    np.testing.assert_array_equal(ok.any(axis=1), [True, True, False, True, False, False])


def test_a_profile_without_the_trot_walks_on_flat_ground():
    robot = load_robot_model('littledog')
    assert robot.trot is False and load_robot_model('frog').trot is True
    from terrain_perception.grid import GridMap
    flat = GridMap(0.01, (-0.75, -0.75), (150, 150),
                   {'elevation': np.zeros((150, 150), np.float32)})
    flat['cost'] = features.cost_map(flat['elevation'], 0.01)
    T = np.eye(4)
    T[2, 3] = robot.standing_height_m
    plan = fs.plan_footsteps(flat, robot, T)
    assert plan.ok and plan.gait == fs.GAIT_WALK and 'walks only' in plan.status_text
    trotting = fs.plan_footsteps(flat, ROBOT, T)
    assert trotting.ok and trotting.gait == fs.GAIT_TROT


def _first_step_with_a_lagging_foot(lagging: int, lag_m: float, first_leg: int, **cfg_kw):
    """On flat ground, from the nominal stance with ``lagging`` ``lag_m`` behind its place (it
    was blocked), the first step of a one-step plan for ``first_leg`` (the leg-spread limit
    off): ``(feet, foothold)``."""
    cfg = fs.PlannerConfig(trot_threshold_m=0.0, horizon_steps=1, max_leg_spread_m=0.0,
                           recovery=False, **cfg_kw)
    planner = fs.FootstepPlanner(ROBOT, cfg)
    assert planner.set_map(_flat()) is None
    feet = np.array(ROBOT.nominal_feet)
    feet[:, 2] = 0.0
    feet[lagging, 0] -= lag_m
    plan = planner.plan(_pose(), np.array([0.6, 0.0]), feet=feet, first_leg=first_leg)
    assert plan.ok and plan.footsteps[0].leg == first_leg, plan.status_text
    return feet, np.asarray(plan.footsteps[0].position)


def test_a_lagging_front_foot_keeps_its_hind_foot_a_stance_length_behind():
    """LF lags 6 cm behind its nominal place (it was blocked): LH's next step may close up on
    it only to min_stance_length of the nominal front-hind spacing. Without the constraint (0;
    the leg-spread limit is off in both) LH steps to its stride-rule place, under the front
    foot: the test can fail."""
    nom = np.array(ROBOT.nominal_feet)
    spacing = nom[fs.LF, 0] - nom[fs.LH, 0]
    gaps = {}
    for msl in (0.65, 0.0):   # the default is 0.5: see config/footstep_planner.yaml
        feet, step = _first_step_with_a_lagging_foot(fs.LF, 0.06, fs.LH, min_stance_length=msl)
        gaps[msl] = feet[fs.LF, 0] - step[0]
    assert gaps[0.65] >= 0.65 * spacing - 1e-9
    assert gaps[0.0] < 0.65 * spacing - 0.02


def test_a_front_foot_leads_its_hind_foot_by_at_most_the_stance_length():
    """RH lags 5 cm behind its nominal place (it was blocked): RF's next step may lead it by
    at most max_stance_length of the nominal front-hind spacing, since a longer stance leaves
    no body shift that keeps RH in reach while the COG is over the other three feet. Without
    the limit (0; the leg-spread limit is off in both) RF steps to its stride-rule place and
    the stance gets longer than that: the test can fail."""
    nom = np.array(ROBOT.nominal_feet)
    spacing = nom[fs.RF, 0] - nom[fs.RH, 0]
    lead = {}
    for msl in (1.3, 0.0):
        feet, step = _first_step_with_a_lagging_foot(fs.RH, 0.05, fs.RF, max_stance_length=msl)
        lead[msl] = step[0] - feet[fs.RH, 0]
    assert lead[1.3] <= 1.3 * spacing + 1e-9
    assert lead[1.3] > feet[fs.RF, 0] - feet[fs.RH, 0]        # still a step forward
    assert lead[0.0] > 1.3 * spacing + 0.02


def _cell_centres(n: int, origin) -> tuple:
    """``(X, Y)`` (n, n): the cell centres [m] of an n x n grid of RES cells at ``origin``."""
    x = origin[0] + (np.arange(n) + 0.5) * RES
    y = origin[1] + (np.arange(n) + 0.5) * RES
    return np.meshgrid(x, y, indexing='ij')


def _blocked_lane_scene(offset_m: float = 0.0):
    """A 5 cm roof-shaped block in RF's lane (+-4.5 cm of its nominal line, moved ``offset_m``
    to the left) from 5 cm to 30 cm ahead of the foot, on flat ground: ``(grid, block mask,
    nominal feet, stance on the ground)``. A roof, not a flat top: every cell on it is steeper
    than the slope limit."""
    n, origin = 150, (-0.75, -0.75)
    nom = np.array(ROBOT.nominal_feet)
    X, Y = _cell_centres(n, origin)
    rf = nom[fs.RF]
    yc = rf[1] + offset_m
    box = (X > rf[0] + 0.05) & (X < rf[0] + 0.30) & (np.abs(Y - yc) < 0.045)
    g = _grid(np.where(box, 0.05 - 0.8 * np.abs(Y - yc), 0.0), origin)
    feet = nom.copy()
    feet[:, 2] = 0.0
    return g, box, nom, feet


def test_a_leg_blocked_in_its_lane_steps_around_the_obstacle():
    """A 5 cm roof-shaped block fills RF's lane (+-3 cm of its nominal line) from 5 cm to 30
    cm ahead of the foot: no safe cell in the lane is half a stride ahead. With the wider
    search of a blocked leg RF steps beside the block, at least A/2 ahead, onto a safe cell;
    without it (0) it can only inch up to the block, the test's counterfactual."""
    g, box, nom, feet = _blocked_lane_scene()
    rf = nom[fs.RF]
    A = ROBOT.body_move_per_period_m
    advance = {}
    for wide in (0.09, 0.0):
        cfg = fs.PlannerConfig(trot_threshold_m=0.0, horizon_steps=1, recovery=False,
                               blocked_lateral_search_m=wide)
        planner = fs.FootstepPlanner(ROBOT, cfg)
        assert planner.set_map(g) is None
        assert not planner.allowed[box].any()
        plan = planner.plan(_pose(), np.array([0.6, 0.0]), feet=feet, first_leg=fs.RF)
        assert plan.ok and plan.footsteps[0].leg == fs.RF, plan.status_text
        _check_plan_feasible(plan, cfg)
        p = plan.footsteps[0].position
        ij = g.world_to_index(p[:2])
        assert planner.allowed[ij[0], ij[1]]
        advance[wide] = (p[0] - rf[0], abs(p[1] - rf[1]))
    assert advance[0.09][0] >= 0.5 * A and advance[0.09][1] > 0.03
    assert advance[0.0][0] < 0.5 * A


def test_a_hind_leg_whose_lane_was_never_seen_reaches_the_trail_beside_it():
    """A leg's lane (+-7 cm of its nominal line) was never observed up to 15 cm ahead of the
    foot (FROG-I's hind feet in the start's blind area): no cell of it, nor of the blocked
    leg's +-6 cm search, is a foothold. With empty_lane_lateral_search_m = 0.12 RH steps
    forward onto the seen ground beside the lane (the front feet's trail in the loop); with 0
    (the blocked search alone, the test's counterfactual) RH has no foothold. RF, a front
    foot, in the same situation does not search wider: ahead of it nothing was stood on."""
    n, origin = 150, (-0.75, -0.75)
    nom = np.array(ROBOT.nominal_feet)
    X, Y = _cell_centres(n, origin)
    got = {}
    for leg, mate in ((fs.RH, fs.LH), (fs.RF, fs.LF)):
        foot = nom[leg]
        unseen = (X > foot[0] + 0.005) & (X < foot[0] + 0.15) & (np.abs(Y - foot[1]) < 0.07)
        g = _grid(np.zeros((n, n)), origin)
        g['observed'] = (~unseen).astype(np.float32)
        g['elevation'][unseen] = np.nan
        g['cost'][unseen] = np.nan
        feet = nom.copy()
        feet[:, 2] = 0.0
        feet[mate, 1] -= 0.04       # the stance-width limit from its pair admits the detour
        for wide in (0.12, 0.0):
            cfg = fs.PlannerConfig(trot_threshold_m=0.0, horizon_steps=1, recovery=False,
                                   blocked_lateral_search_m=0.06,
                                   empty_lane_lateral_search_m=wide)
            planner = fs.FootstepPlanner(ROBOT, cfg)
            assert planner.set_map(g) is None
            assert not planner.allowed[unseen].any()
            got[leg, wide] = planner.plan(_pose(), np.array([0.6, 0.0]), feet=feet,
                                          first_leg=leg)

    def steps(plan, leg):
        return plan.ok and plan.footsteps and plan.footsteps[0].leg == leg
    plan = got[fs.RH, 0.12]
    assert steps(plan, fs.RH), plan.status_text
    _check_plan_feasible(plan, fs.PlannerConfig(trot_threshold_m=0.0, horizon_steps=1,
                                                recovery=False))
    p = plan.footsteps[0].position
    assert p[0] > nom[fs.RH, 0] + 0.01 and abs(p[1] - nom[fs.RH, 1]) >= 0.07, p
    assert not steps(got[fs.RH, 0.0], fs.RH), got[fs.RH, 0.0].status_text
    assert not steps(got[fs.RF, 0.12], fs.RF), got[fs.RF, 0.12].status_text


def _rf_gap_to_lf(g, feet, **limits) -> float:
    """In a blocked-lane scene: how far (across the walking line) RF's one planned step lands
    to the right of LF, planned with the stance-width ``limits``."""
    cfg = fs.PlannerConfig(trot_threshold_m=0.0, horizon_steps=1, recovery=False, **limits)
    planner = fs.FootstepPlanner(ROBOT, cfg)
    assert planner.set_map(g) is None
    plan = planner.plan(_pose(), np.array([0.6, 0.0]), feet=feet, first_leg=fs.RF)
    assert plan.ok and plan.footsteps[0].leg == fs.RF, plan.status_text
    _check_plan_feasible(plan, cfg)
    return feet[fs.LF, 1] - plan.footsteps[0].position[1]


def test_a_pair_of_feet_keeps_the_stance_width():
    """The blocked-lane scene above, with LF standing 4 cm inside its nominal line: stepping
    around the block on the inside would put RF within 4-5 cm of LF across the walking
    direction (the demo's roll-over: front feet 5 cm apart). With min_stance_width the RF
    foothold keeps at least that share of the nominal width from LF; without it (0), the
    test's counterfactual, it does not."""
    g, _, nom, feet = _blocked_lane_scene()
    feet[fs.LF, 1] -= 0.04
    nominal_width = nom[fs.LF, 1] - nom[fs.RF, 1]
    gaps = {width: _rf_gap_to_lf(g, feet, min_stance_width=width) for width in (0.45, 0.0)}
    assert gaps[0.45] >= 0.45 * nominal_width - 1e-9
    assert gaps[0.0] < 0.45 * nominal_width


def test_a_pair_of_feet_keeps_within_the_widest_stance():
    """The blocked-lane scene with the block moved 3 cm inwards, so RF steps around it on the
    outside, and LF standing 4 cm outside its nominal line: the front pair would end up ~1.6
    nominal widths apart (the closed loop's stalls: feet 13-15 cm from the body's centre
    line, beyond the hip joints' limits). With max_stance_width 1.3 the RF foothold stays
    within 1.3 nominal widths of LF; without it (0), the test's counterfactual, it does not."""
    g, _, nom, feet = _blocked_lane_scene(offset_m=0.03)
    feet[fs.LF, 1] += 0.04
    nominal_width = nom[fs.LF, 1] - nom[fs.RF, 1]
    widths = {width: _rf_gap_to_lf(g, feet, max_stance_width=width) for width in (1.3, 0.0)}
    assert widths[1.3] <= 1.3 * nominal_width + 1e-9
    assert widths[0.0] > 1.3 * nominal_width


def test_plan_checked_keeps_what_the_executor_accepts():
    """plan_checked: a check accepting two steps cuts the plan to two (status says so); a check
    refusing any plan that starts with the planned first leg gets a plan starting with another
    leg; a check refusing everything gives an explanatory empty plan."""
    cfg = fs.PlannerConfig(trot_threshold_m=0.0, horizon_steps=4)
    planner = fs.FootstepPlanner(ROBOT, cfg)
    assert planner.set_map(_rocks(5)) is None
    feet = np.array(ROBOT.nominal_feet)
    feet[:, 2] = planner.grid.sample('elevation', feet[:, :2])
    goal = np.array([0.6, 0.0])
    full = planner.plan(_pose(), goal, feet=feet, first_leg=fs.LH)
    assert full.ok and len(full.footsteps) == 4

    cut = planner.plan_checked(_pose(), goal, feet, lambda legs, pos: (2, 'too far'),
                               first_leg=fs.LH)
    assert cut.ok and len(cut.footsteps) == 2 and 'kept 2 of 4' in cut.status_text
    assert 'too far' in cut.check_note
    for a, b in zip(cut.footsteps, full.footsteps):
        np.testing.assert_allclose(a.position, b.position)

    calls = []

    def not_lh(legs, pos):
        calls.append(int(legs[0]))
        return (0, 'LH refused') if legs[0] == fs.LH else (len(legs), '')
    other = planner.plan_checked(_pose(), goal, feet, not_lh, first_leg=fs.LH)
    assert other.ok and other.footsteps[0].leg != fs.LH
    assert 'LH refused' in other.status_text and calls[0] == fs.LH
    assert 'LH refused' in other.check_note and not full.check_note

    none = planner.plan_checked(_pose(), goal, feet, lambda legs, pos: (0, 'nothing fits'),
                                first_leg=fs.LH)
    assert not none.ok and none.status == fs.STATUS_NO_FOOTHOLD and not none.footsteps
    assert 'nothing fits' in none.status_text


def test_recovery_steps_the_rearmost_foot_before_stepping_others_back():
    """RH 11.5 cm behind its nominal place on flat ground and LH to step first: every LH
    foothold would lead RH by more than the spread limit, so the plan needs the recovery.
    The rearmost foot goes first, at least half a stride, and no foot is re-placed without
    advancing; without that try the recovery re-placed LH where it stood."""
    cfg = fs.PlannerConfig(trot_threshold_m=0.0, horizon_steps=4)
    planner = _planner(cfg, _flat())
    _, feet = _rh_behind(cfg.max_leg_spread_m - 0.005)
    stuck = _planner(dataclasses.replace(cfg, recovery=False), _flat())
    assert not stuck.plan(_pose(), np.array([0.6, 0.0]), feet=feet, first_leg=fs.LH).ok
    plan = planner.plan(_pose(), np.array([0.6, 0.0]), feet=feet, first_leg=fs.LH)
    assert plan.ok and 'rearmost foot (RH) first' in plan.status_text, plan.status_text
    _check_plan_feasible(plan, cfg)
    assert plan.footsteps[0].leg == fs.RH
    assert plan.footsteps[0].position[0] - feet[fs.RH, 0] >= 0.5 * ROBOT.body_move_per_period_m
    cur = feet.copy()
    for s in plan.footsteps:
        assert s.position[0] >= cur[s.leg, 0] + cfg.min_step_m - 1e-9, s
        cur[s.leg] = s.position


def test_plan_checked_falls_back_on_recovery_plans_the_executor_accepts():
    """An executor refusing the first step of every normal plan (each leg first): plan_checked
    returns a relaxed recovery plan whose first step it accepts, saying so; with the recovery
    off it returns the explanatory empty plan."""
    cfg = fs.PlannerConfig(trot_threshold_m=0.0, horizon_steps=4)
    planner = _planner(cfg, _rocks(5))
    feet = np.array(ROBOT.nominal_feet)
    feet[:, 2] = planner.grid.sample('elevation', feet[:, :2])
    goal = np.array([0.6, 0.0])
    normal = [planner.plan(_pose(), goal, feet=feet, first_leg=leg).footsteps[0]
              for leg in fs.CRAWL_ORDER]
    assert all(normal)

    def refuse_normal(legs, pos):
        same = any(s.leg == legs[0] and np.linalg.norm(s.position - pos[0]) < 0.005
                   for s in normal)
        return (0, 'the usual first steps refused') if same else (len(legs), '')
    plan = planner.plan_checked(_pose(), goal, feet, refuse_normal, first_leg=fs.LH)
    assert plan.ok and 'recovery (' in plan.status_text, plan.status_text
    assert 'would refuse the first step of every plan' in plan.check_note
    assert refuse_normal(np.array([plan.footsteps[0].leg]),
                         plan.footsteps[0].position[None])[0] == 1
    off = _planner(dataclasses.replace(cfg, recovery=False), _rocks(5))
    none = off.plan_checked(_pose(), goal, feet, refuse_normal, first_leg=fs.LH)
    assert not none.ok and 'the usual first steps refused' in none.status_text


def test_flatness_dev_window_equals_the_whole_maps():
    # _dev_at computes Shao's Dev on a window around the cells asked for: the values must be
    # the whole map's, at the map's edges and next to unknown cells too.
    rng = np.random.default_rng(0)
    h = rng.normal(0.0, 0.01, (150, 120))
    h[rng.random(h.shape) < 0.05] = np.nan
    g = _grid(np.nan_to_num(h), cost=True)
    g['elevation'] = h.astype(np.float32)
    planner = _planner(fs.PlannerConfig(), g)
    full = features.shao_dev(g['elevation'])
    for _ in range(100):
        c, d = rng.integers(0, 150), rng.integers(0, 120)
        ij = np.c_[np.clip(c + rng.integers(-5, 6, 30), 0, 149),
                   np.clip(d + rng.integers(-5, 6, 30), 0, 119)]
        np.testing.assert_allclose(planner._dev_at(ij), full[ij[:, 0], ij[:, 1]], rtol=1e-12)


def test_refused_steps_remember_the_controllers_refusals_from_one_stance():
    r = fs.RefusedSteps(tolerance_m=0.02, max_age_s=10.0)
    p = np.array([0.10, -0.07, 0.0])
    assert not r.report(5, 'refused before any plan', 1.0)         # nothing offered yet
    r.offered(5, fs.RH, p, t=2.0)
    assert not r.report(5, 'an earlier refusal', 1.5)             # older than the offer
    assert not r.report(5, '', 2.5)                               # no refusal
    assert not r.report(5, 'plan is older than plan_timeout_s=5.0 s', 2.5)  # not the step
    assert not r.report(4, 'another stance', 2.5)
    assert r.report(5, "body shift leaves the legs' reach", 3.0)
    assert not r.report(5, "body shift leaves the legs' reach", 3.1)  # already known
    assert r.refusal(5, fs.RH, p + [0.015, 0.0, 0.0], 4.0) == "body shift leaves the legs' reach"
    assert r.refusal(5, fs.RH, p + [0.03, 0.0, 0.0], 4.0) is None   # another foothold
    assert r.refusal(5, fs.LH, p, 4.0) is None                      # another leg
    assert r.refusal(6, fs.RH, p, 4.0) is None                      # another stance
    assert r.refusal(5, fs.RH, p, 13.5) is None                     # too old: tried again
    r.offered(5, fs.RH, p, t=14.0)
    assert r.report(5, 'refused again', 14.5)
    assert not r.report(6, '', 15.0)                               # it stepped: forgotten
    assert r.refusal(5, fs.RH, p, 15.0) is None
    with pytest.raises(ValueError, match='max_age_s'):
        fs.RefusedSteps(max_age_s=0.0)


def test_planner_on_perceived_and_filled_maps_crosses_on_low_cost_footholds():
    """`terrain-bench plan`'s perceived walk (course seed 1): the planner, fed only what a range
    sensor on the camera mount saw and Fill-Terrain guessed, crosses the rocks on footholds whose
    true cost is far below the terrain-blind greedy walk's on the same kind of maps, and the
    maps held filled never-seen cells (the fill took part)."""
    from terrain_perception.bench.plan import (PerceivedMaps, load_profile, unsafe_mask,
                                               walk_course)
    from terrain_perception.terrain import library_terrains, make_course
    name, _, cfg, cost_cfg = load_profile()
    robot = load_robot_model(name)
    course, truth = make_course('rocks-6cm', 1, 0.01), make_course('rocks-6cm', 1, 0.005)
    library = [np.asarray(t['elevation'], np.float64)
               for t in library_terrains(10, 0, 0.01, 0.06)]
    tcost = features.cost_map(course['elevation'], 0.01, cost_cfg)
    unsafe = unsafe_mask(truth, robot.foot_radius_m)
    x1 = course.metadata['rough_extent_xy'][1]
    out = {}
    for sel in ('cost', 'nominal'):
        c = dataclasses.replace(cfg, selection=sel,
                                max_unevenness=cfg.max_unevenness if sel == 'cost' else 0.0)
        maps = PerceivedMaps(course, robot, cost_cfg, library)
        r = walk_course(course, tcost, truth, unsafe, robot, c, cost_cfg, seed=0,
                        perceived=maps)
        rough = np.array(r['rough'], bool)
        assert r['failures'] == 0, r.get('failure')
        assert r['reached_x'] >= x1, f'{sel}: stopped at x = {r["reached_x"]:.2f} m'
        out[sel] = float(np.mean(np.array(r['cost'])[rough]))
        g = maps.grid()
        inside = np.isfinite(g['elevation'])
        assert (g['observed'][inside] < 0.5).any() and (g['filled'][inside] > 0.5).any()
    assert out['cost'] < 0.5 * out['nominal'], out



def _walk_on_flat(robot, goal_xy, periods: int, lookahead_m: float = 1.0,
                  turn_per_period_deg: float = 0.0):
    """Plans on flat ground from the origin, each from the stance the last one's first gait
    period left. After each period the stance is turned by ``turn_per_period_deg`` about its
    centre (feet turned by footholds chosen around rocks) and the body stands at the feet's
    yaw, as the walking controller puts it. Returns the body's ``(x, y, yaw [deg])`` after each
    period (fewer rows if the goal was reached)."""
    from terrain_perception.gait import body_pose_from_feet
    g = _grid(np.zeros((400, 300)), origin=(-0.5, -1.5))
    planner = fs.FootstepPlanner(robot, fs.PlannerConfig(straight_lookahead_m=lookahead_m))
    assert planner.set_map(g) is None
    T = _pose()
    feet = np.array(robot.nominal_feet)
    feet[:, 2] = 0.0
    a = np.radians(turn_per_period_deg)
    R = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    out = []
    for _ in range(periods):
        plan = planner.plan(T, goal_xy, feet=feet)
        if plan.status == fs.STATUS_GOAL_REACHED:
            break
        assert plan.ok, plan.status_text
        period = 2 if plan.gait == fs.GAIT_TROT else 4
        for s in plan.footsteps:
            if s.step_index < period:
                feet[s.leg] = s.position
        c = feet[:, :2].mean(axis=0)
        feet[:, :2] = c + (feet[:, :2] - c) @ R.T
        x, y, _, yaw = body_pose_from_feet(feet, robot.standing_height_m)
        T = _pose(x, y, yaw)
        out.append((x, y, np.degrees(yaw)))
    return np.array(out)


CRAWLER = load_robot_model('littledog')     # crawls only, as in the closed loop


@pytest.mark.parametrize('robot', [CRAWLER, ROBOT], ids=['crawl', 'trot'])
def test_without_a_goal_the_planner_holds_its_line_against_a_turning_stance(robot):
    # Every period the stance turns 3 deg left (the planner turns back at most max_turn_rad,
    # 5.7 deg, per plan). Following the body's heading, the walk turns a full 36 deg and
    # drifts sideways; holding the first plan's line, heading and offset stay near zero.
    wander = _walk_on_flat(robot, None, 12, lookahead_m=0.0, turn_per_period_deg=3.0)
    held = _walk_on_flat(robot, None, 12, turn_per_period_deg=3.0)
    assert wander[-1, 2] > 30.0 and wander[-1, 1] > 0.05, wander[-1]
    assert np.abs(held[:, 2]).max() < 6.0, held[:, 2]
    assert np.abs(held[:, 1]).max() < 0.02, held[:, 1]
    assert held[-1, 0] > 0.3, held[-1]
    # A goal clears the line: the next goal-less plan starts a new one where the body is.
    planner = _planner(fs.PlannerConfig(), _flat())
    assert planner.plan(_pose(), None).ok and planner.straight_line is not None
    assert planner.plan(_pose(), np.array([1.0, 0.5])).ok and planner.straight_line is None
    plan = planner.plan(_pose(0.1, 0.2, 0.3), None)
    assert plan.ok and plan.yaw == pytest.approx(0.3)
    np.testing.assert_allclose(planner.straight_line[0], [0.1, 0.2])


@pytest.mark.parametrize('robot', [CRAWLER, ROBOT], ids=['crawl', 'trot'])
def test_a_goal_off_the_heading_is_reached_walking_or_trotting(robot):
    # 28 deg to the left of the start heading. A trot step used to move each foot by A along
    # the heading only, so a trotting robot never turned and walked past the goal.
    goal = np.array([1.5, 0.8])
    walk = _walk_on_flat(robot, goal, 40)
    assert len(walk) < 40, walk[-1]
    assert np.linalg.norm(walk[-1, :2] - goal) < 0.1, walk[-1]
    assert walk[:, 2].max() > 25.0
