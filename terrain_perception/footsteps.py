"""Receding-horizon footstep planning with Shao's gait selection.

* **Cost map** (paper 000 sec. IV; paper 002 eq. 2-3): the foothold cost of every cell comes from
  :mod:`terrain_perception.features` (Kolter's local features or Shao's ``h + Dev(h)``); either
  the grid's own ``cost`` layer or one computed here by :func:`cost_layer`.
* **Receding-horizon search** (paper 000 sec. IV): the next ``horizon_steps`` footsteps in crawl
  order LH, LF, RH, RF, by a small beam search. Each foothold is a cell of its leg's search area
  (``lateral_search_m`` either side of the leg's line; ``blocked_lateral_search_m`` when nothing
  in that lane is half a stride ahead, so a leg steps around a rock instead of inching up to it,
  and ``empty_lane_lateral_search_m``, if wider, when nothing in that wider area is a candidate
  at all)
  that (a) has a finite cost, (b) was observed, or was filled with a finite line-of-sight upper
  bound close to its value, (c) is safe for the foot on the map (:func:`unsafe_cells`: slope and
  unevenness limits over the foot's radius plus its placement error, on the surface the ball
  foot rests on (:func:`foot_surface`), applied at ``map_safety_factor`` of their values
  because the map is coarser than the terrain), (d) is within the leg's reach (analytic IK
  within joint limits, with a reach margin) from the body pose during the swing, (e) leaves the
  next swing's support triangle able to hold the COG with ``stability_margin_m`` within reach,
  with at least one foothold for that next leg (one-swing lookahead), and (f) does not lead
  the rearmost other foot by more than ``max_leg_spread_m`` nor leave a foot far behind unable
  to lift. Among those, the foothold minimises
  omega x (cost + distance from the stride-rule foothold + height change). Salient contact
  patches (:mod:`terrain_perception.patches`) near a cell lower its cost. During each swing the
  COG sits in the other three feet's triangle shrunk by the margin, the body follows the feet's
  plane and crouches (down to ``min_crouch``) when that keeps every leg in reach. When a stance
  has no feasible continuation, ``recovery`` retries with another leg first, short re-placing
  steps, then half the margin; the status text names what was relaxed.
* **Gait selection** (paper 002 Fig. 4): per gait period the body advances ``A``; each leg's
  search area is ``[kL_{i-1}, wL_{i-1} + 2A]`` along the walking direction. If every cell of all
  four areas has Shao cost ``|h - ground| + Dev(h)`` below ``Threshold`` and every foot is in
  position (``kL - wL < A/2``) the plan trots with stride ``A``; otherwise it walks, choosing in
  each area the foothold of least cost weighted by ``omega = (x - centre)^2 + A`` (which keeps
  footholds off the area borders; on uniform cost it reproduces the paper's walk stride rule
  ``(2A + wL - kL) / 2``). The plan is remade after every swing, so a trot plan often starts
  half-way through a period (one diagonal pair swung, the other not): the test is then the one
  of that period's start and the other pair swings first (:meth:`FootstepPlanner.trot_phase`).

Frames: the grid's frame (``map``, z up). Poses are 4x4 ``T_map_base``. Legs are indexed
``LF, RF, LH, RH`` = 0..3 (``terrain_msgs/Footstep``). Footstep positions are ground contact
points [m].
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Callable, List, Optional, Tuple

import numpy as np

from terrain_perception import features
from terrain_perception.body_path import (BodyPath, BodyPathSettings, belly_samples,
                                          plan_body_path, top_field)
from terrain_perception.config import param
from terrain_perception.gait import body_pose_from_feet
from terrain_perception.grid import COST, ELEVATION, FILLED, OBSERVED, UPPER_BOUND, GridMap
from terrain_perception.kinematics import solve_ik
from terrain_perception.robot_model import LEG_NAMES, RobotModel

# Gait and status codes: the values of terrain_msgs/FootstepPlan.
GAIT_STAND, GAIT_WALK, GAIT_TROT = 0, 1, 2
GAIT_NAMES = {GAIT_STAND: 'stand', GAIT_WALK: 'walk', GAIT_TROT: 'trot'}
(STATUS_OK, STATUS_GOAL_REACHED, STATUS_NO_MAP, STATUS_BAD_MAP, STATUS_ROBOT_OUTSIDE_MAP,
 STATUS_NO_FOOTHOLD, STATUS_BAD_INPUT) = range(7)
LF, RF, LH, RH = 0, 1, 2, 3
#: Crawl (walk) order of paper 000 / the issue: LH, LF, RH, RF.
CRAWL_ORDER = (LH, LF, RH, RF)
_SAME_SIDE = {LF: LH, LH: LF, RF: RH, RH: RF}
_ACROSS = {LF: RF, RF: LF, LH: RH, RH: LH}
#: Trot pairs (diagonals), first pair first.
TROT_PAIRS = ((LF, RH), (RF, LH))


@dataclass(frozen=True)
class PlannerConfig:
    """Footstep planner parameters (defaults sized for the LittleDog-like profile)."""

    horizon_steps: int = param(4, 'footsteps planned ahead (receding horizon)', 1, 32)
    cost_source: str = param('layer', "foothold cost: the grid's 'cost' layer, or computed "
                             "here with features.cost_map ('kolter' or 'shao')",
                             choices=('layer', 'kolter', 'shao'))
    body_move_per_period_m: float = param(
        0.0, "Shao's A: body advance per gait period [m]; 0 = the robot profile's value",
        0.0, 2.0)
    trot_threshold_m: float = param(
        0.02, "Shao's Threshold on |h - ground| + Dev(h) [m] below which a cell counts as "
        'flat (paper 002: 0.02 m for FROG-I)', 0.0, 1.0)
    distance_weight_gain: float = param(
        1.0, "gain on the quadratic term of Shao's omega = gain (x - centre)^2 + A "
        '(paper: 1)', 0.0, 1e4)
    stride_centre: str = param(
        'adaptive', "where a leg's search area is centred along the walking direction (the "
        "foothold omega and the nominal-distance cost prefer): 'rule', the centre of Shao's "
        'area [foot + min_step, nominal + wL + 2A] (the paper\'s stride rule (2A + wL - kL) / 2) '
        "clipped to the max step length; 'capped', the centre of that area after the max-step "
        "cap (about half the max step on flat ground: a shorter, slower stride); 'adaptive', "
        "'rule' where every cell of the leg's capped area is flat by Shao's gait test "
        "(|h - ground| + Dev(h) < trot_threshold_m, the stance's mean foot height as ground) "
        "and 'capped' elsewhere: long strides on open ground, short ones among obstacles",
        choices=('capped', 'rule', 'adaptive'))
    min_step_m: float = param(0.01, 'shortest step along the walking direction [m]: a plan of '
                              'steps in place is no plan', 0.0, 1.0)
    lateral_search_m: float = param(0.03, 'half-width of each search area across the walking '
                                    'direction [m]', 0.0, 1.0)
    blocked_lateral_search_m: float = param(
        0.06, 'half-width across the walking direction of the search area of a blocked leg: one '
        'whose normal area has no foothold at least half a stride (A/2) ahead, e.g. a rock '
        'filling its lane; the leg then steps around it instead of inching up to it (0 = off) '
        '[m]', 0.0, 1.0)
    empty_lane_lateral_search_m: float = param(
        0.0, 'half-width across the walking direction of the search area of a blocked hind leg '
        'whose blocked_lateral_search_m area holds no foothold candidate at all (e.g. '
        'never-observed ground: a hind foot crossing the start\'s blind area, where only cells '
        'the front feet stood on are footholds); wider, it reaches the front feet\'s trail '
        'beside the lane; 0 (or not wider) = off [m]', 0.0, 1.0)
    cost_offset: float = param(0.02, 'added to the cost before the omega weighting so that '
                               'equal-cost cells still prefer the area centre [cost units]',
                               0.0, 1e3)
    stability_margin_m: float = param(0.01, 'least distance from the COG to the support '
                                      'triangle edges during a swing [m]', 0.0, 1.0)
    belly_clearance_m: float = param(
        0.015, 'every planned body pose keeps the underside of the body box this far above the '
        'highest map cell under it, rising (within the legs\' reach) or crouching less where '
        'that keeps it so, and a foothold whose next body pose cannot is no candidate: '
        'rocks-12cm ground-truth walks ended with LittleDog\'s belly (11.5 cm up standing) on '
        'a 10-11 cm rock while all four feet stood on the floor; unknown cells do not count; '
        'negative = off [m]', -1.0, 1.0)
    heading_weight_per_rad2: float = param(
        1.0, 'cost per square radian by which a foothold turns the stance (hind feet\'s '
        'midpoint to the front feet\'s, the body\'s yaw) off the plan\'s heading: 10 deg '
        'costs 0.03; at 5 the flat walk against a stance turned 3 deg a period drifted 4 cm '
        'sideways, at 1 under 1 cm [1/rad^2]', 0.0, 1e6)
    max_heading_error_rad: float = param(
        0.35, 'no foothold may turn the stance further than this off the plan\'s heading, '
        'unless it is already further and the step brings it back (0 = no limit) [rad]',
        0.0, 3.2)
    body_path: bool = param(
        True, "steer along a body path (terrain_perception.body_path) that keeps the belly "
        'belly_clearance_m clear of the map with the feet between the rocks, instead of '
        'straight at the goal (or along the goal-less line): on rocks-12cm every course has '
        'such lines, mostly beside the centre line; off with belly_clearance_m < 0')
    body_path_lookahead_m: float = param(
        0.3, 'the plan heads for the point this far along the body path [m]', 0.01, 10.0)
    body_path_resolution_m: float = param(0.025, 'lattice step of the body path search [m]',
                                          0.005, 1.0)
    body_path_headroom_m: float = param(
        0.04, 'the body path prefers at least this much room under the belly; it costs '
        '1 + body_path_weight x the shortfall share per metre [m]', 0.0, 1.0)
    body_path_weight: float = param(3.0, 'see body_path_headroom_m [-]', 0.0, 1e3)
    body_path_corridor_m: float = param(
        0.3, 'the body path keeps the body within this distance of the route: the line from '
        'where the first plan for the current goal started to the goal (without a goal, the '
        'goal-less line): going round a rock field is not crossing it; 0 = anywhere on the '
        'map [m]', 0.0, 100.0)
    min_crouch: float = param(0.8, 'lowest body height as a share of the standing height when '
                              'crouching keeps the legs in reach', 0.3, 1.0)
    reach_fraction: float = param(0.95, 'largest hip-to-foot distance as a share of the leg '
                                  'length', 0.1, 1.0)
    max_bound_gap_m: float = param(
        0.02, 'a never-observed filled cell is a foothold candidate only if its line-of-sight '
        'upper bound is at most this far above its filled height [m]', 0.0, 1.0)
    step_height_weight_per_m: float = param(
        2.0, 'cost per metre between a foothold and the mean height of the current stance '
        '[1/m]; keeps the body level enough for the other legs to stay in reach', 0.0, 1e4)
    max_slope_deg: float = param(30.0, 'steepest foothold (local plane over ~4 foot radii) '
                                 '[deg]: the feet friction limit atan(1.2) = 50 deg with margin',
                                 0.0, 90.0)
    max_unevenness: float = param(0.5, 'largest RMS deviation of the heights under the foot from '
                                  'their plane, in foot radii (edges, cracks, knobs); 0 = no '
                                  'safety filter', 0.0, 100.0)
    map_safety_factor: float = param(
        0.85, 'the safety filter on the map flags cells beyond this share of the unevenness and '
        'slope limits: a map coarser and noisier than the terrain under-reads the edges the '
        'foot meets (1 = no margin)', 0.1, 1.0)
    safety_surface: str = param(
        'foot', "what the slope and unevenness limits are applied to: 'heights', the map's "
        "heights; 'foot', the surface a ball foot lowered onto each cell rests on (the heights "
        'dilated by the foot, :func:`foot_surface`): floor next to a rock is safe once the foot '
        'does not touch the rock. With safety_window_m 0.01, rocks-12cm ground-truth walks '
        "crossed 2 of 12 seeds (0 with 'heights' over 2 foot radii, which refused ~80 % of "
        'the floor cells in the legs\' search areas where the walks stopped) and rocks-6cm 12 of '
        '12 (11); falls 4 of 12 on rocks-12cm (1). On a 1 cm map (the closed loop\'s) the '
        'dilation does nothing (no other cell centre is within the foot\'s radius) and the window '
        'keeps 2 cells each side: the filter is the one before there',
        choices=('heights', 'foot'))
    safety_window_m: float = param(
        0.01, 'half-side of the square over which the slope and unevenness are measured: '
        'the foot\'s radius plus the placement error (ground-truth walks: p95 2.5-7 mm); '
        '0 = 2 foot radii (the window before, 4.5 cm on a 5 mm map, which reached into the '
        'rocks beside a floor cell and measured their curvature) [m]', 0.0, 1.0)
    max_leg_spread_m: float = param(
        0.12, 'largest distance along the walking direction by which a new foothold may lead '
        'the rearmost other foot, both measured from their nominal places [m] (0 = no limit)',
        0.0, 10.0)
    min_stance_length: float = param(
        0.5, 'shortest distance along the walking direction between a front foot and the hind '
        'foot on its side, as a share of the nominal one (the hip spacing): a hind leg that '
        'catches up with a blocked front leg leaves a support polygon too short to balance on '
        '(0 = no limit) [-]', 0.0, 1.0)
    max_stance_length: float = param(
        1.3, 'longest distance along the walking direction between a front foot and the hind '
        'foot on its side, as a share of the nominal one: a front foot far ahead of a lagging '
        'hind foot leaves no body shift that keeps the hind foot in reach while the COG is over '
        'the other three (the stretched-stance stalls of the shortfall weight; 0 = no limit) '
        '[-]', 0.0, 10.0)
    min_stance_width: float = param(
        0.45, 'narrowest distance across the walking direction between a left foot and the right '
        'foot of its pair (front or hind), as a share of the nominal one: legs stepping around '
        'rocks must not bring a pair\'s feet together under the body, where the robot rolls '
        'over on the next swing (0 = no limit) [-]', 0.0, 1.0)
    max_stance_width: float = param(
        1.5, 'widest distance across the walking direction between a left foot and the right '
        'foot of its pair, as a share of the nominal one: legs stepping around rocks one side '
        'after the other spread the stance until no body pose keeps every foot within the hip '
        'joints\' limits (the closed loop\'s stalls, feet 13-15 cm from the body\'s centre '
        'line; 0 = no limit) [-]', 0.0, 10.0)
    nominal_weight_per_m2: float = param(
        20.0, "cost per square metre of distance from the stride rule's foothold (the search "
        'area centre): keeps legs from lagging into dead ends [1/m^2]', 0.0, 1e6)
    shortfall_weight_per_m2: float = param(
        50.0, "extra cost per square metre by which a foothold falls short of the stride "
        "rule's along the walking direction (not beside it, not beyond it): on rocks the cell "
        'next to a foot is often the cheapest, and a third of the steps in the loop were 1 cm '
        'long, which held every other leg back through the spread limit. With '
        'max_stance_length 1.3 the ground-truth walks cross 11 of 16 seeds (defaults before: '
        '6), about 25 % faster; alone it stretches the stance until the rearmost foot cannot '
        'swing (0 = off) [1/m^2]', 0.0, 1e6)
    patch_bonus: float = param(0.3, 'cost reduction factor for cells within a salient contact '
                               "patch's radius (0 = ignore patches)", 0.0, 1.0)
    beam_width: int = param(4, 'partial plans kept per step of the search', 1, 64)
    candidates_per_step: int = param(6, 'best footholds expanded per partial plan and step',
                                     1, 64)
    max_turn_rad: float = param(0.1, 'largest heading change towards the goal per plan [rad]',
                                0.0, 3.2)
    straight_lookahead_m: float = param(
        1.0, 'without a goal, walk along the line the first goal-less plan started on, '
        'steering (max_turn_rad per plan) at the point this far ahead on it; 0 = along the '
        "body's current heading, which wanders with the footholds (the graph content test's "
        'goal-less walks turned 35-60 deg in 42 s) [m]', 0.0, 100.0)
    recovery: bool = param(True, 'when stuck, retry with other legs first, short/backward '
                           're-placing steps and half the margin (named in the status)')
    goal_tolerance_m: float = param(0.03, 'body within this distance of the goal = reached [m]',
                                    0.0, 10.0)
    selection: str = param('cost', "foothold choice: 'cost' (this planner), or the benchmark "
                           "baselines 'nominal' (greedy: the search-area centre, cost ignored) "
                           "and 'random' (any feasible cell)",
                           choices=('cost', 'nominal', 'random'))
    random_seed: int = param(0, "seed of the 'random' baseline", 0, 2**31 - 1)


@dataclass
class Footstep:
    """One planned foothold (see ``terrain_msgs/Footstep``).

    Attributes:
        leg: 0..3 (LF, RF, LH, RH). position: (3,) ground contact point [m, map].
        cost: foothold cost at the cell. step_index: 0 = next. patch_index: -1 = none.
        body_xy: (2,) COG position [m, map] while this leg swings.
        body_height_m: base height above the feet's plane during the swing [m] (the planner
            crouches below the standing height when that keeps every leg in reach).
    """

    leg: int
    position: np.ndarray
    cost: float
    step_index: int
    patch_index: int = -1
    body_xy: np.ndarray = field(default_factory=lambda: np.full(2, np.nan))
    body_height_m: float = np.nan


@dataclass
class FootstepPlan:
    """Planner output. ``footsteps`` is empty unless ``status == STATUS_OK``."""

    status: int
    status_text: str
    gait: int = GAIT_STAND
    footsteps: List[Footstep] = field(default_factory=list)
    final_body_pose: np.ndarray = field(default_factory=lambda: np.eye(4))
    body_move_per_period_m: float = 0.0
    initial_feet: Optional[np.ndarray] = None   # (4, 3) contact points the plan starts from
    yaw: float = 0.0                            # walking direction [rad, map]
    check_note: str = ''                        # what plan_checked cut or changed, and why

    @property
    def ok(self) -> bool:
        return self.status == STATUS_OK


#: why a leg's search area has no candidate: no cell is a foothold at all (unobserved, unsafe,
#: infinite cost), before any stance limit
_EMPTY_AREA = 'no observed, finite-cost cell in its search area'


def failed(status: int, text: str) -> FootstepPlan:
    """An empty plan with an explanatory status."""
    return FootstepPlan(status, text)


# --------------------------------------------------------------------------------------------
# Cost maps
# --------------------------------------------------------------------------------------------

def cost_layer(grid: GridMap, source: str = 'layer',
               cost_config: Optional[features.CostConfig] = None) -> np.ndarray:
    """The foothold cost ``(nx, ny)`` to plan on: the grid's ``cost`` layer (``source='layer'``)
    or :func:`terrain_perception.features.cost_map` on its elevation (``'kolter'``/``'shao'``).

    Raises ValueError naming a missing layer or an unknown source."""
    if source == 'layer':
        if COST not in grid:
            raise ValueError(f"the grid has no '{COST}' layer (layers: {sorted(grid.layers)})")
        return grid[COST]
    if source not in features.METHODS:
        raise ValueError(f"unknown cost source {source!r}; use 'layer' or one of "
                         f'{features.METHODS}')
    if ELEVATION not in grid:
        raise ValueError(f"the grid has no '{ELEVATION}' layer to compute a cost from")
    cfg = cost_config or features.CostConfig()
    import dataclasses
    cfg = dataclasses.replace(cfg, method=source)
    return features.cost_map(grid[ELEVATION], grid.resolution_m, cfg)


def flatness_cost(heights: np.ndarray, ground_z: float,
                  dev: Optional[np.ndarray] = None) -> np.ndarray:
    """Shao's gait-selection cost ``|h - ground| + Dev(h)`` [m] (paper 002 eq. 2-3, with h taken
    relative to the current stance's ground height and its magnitude used, so a dip is not
    mistaken for flat ground). Dev comes from :func:`terrain_perception.features.shao_dev` on
    ``heights``, or is ``dev`` (the same shape) when the caller has it already."""
    h = np.asarray(heights, dtype=np.float64)
    return np.abs(h - ground_z) + (features.shao_dev(h) if dev is None else dev)


def foot_surface(heights: np.ndarray, resolution_m: float, foot_radius_m: float) -> np.ndarray:
    """Where a ball foot of radius ``rho = foot_radius_m`` [m] lowered straight down over each
    cell comes to rest, as the height of its lowest point [m]: the heights dilated by the ball,
    ``max over |d| <= rho of h(x + d) + sqrt(rho^2 - |d|^2) - rho``. Equal to the height on
    ground flat over the foot's radius; next to a rock's flank the foot rests against the flank
    and the surface rises with it. Unknown cells stay unknown and do not count for their
    neighbours."""
    from scipy import ndimage
    h = np.asarray(heights, dtype=np.float64)
    r = int(np.floor(foot_radius_m / resolution_m))
    if r < 1:
        return h.copy()
    d = np.arange(-r, r + 1) * resolution_m
    d2 = d[:, None] ** 2 + d[None, :] ** 2
    fp = d2 <= foot_radius_m ** 2
    lift = np.where(fp, np.sqrt(np.maximum(foot_radius_m ** 2 - d2, 0.0)) - foot_radius_m, 0.0)
    known = np.isfinite(h)
    out = ndimage.grey_dilation(np.where(known, h, -1e9), footprint=fp, structure=lift,
                                mode='nearest')
    return np.where(known, out, np.nan)


def unsafe_cells(heights: np.ndarray, resolution_m: float, foot_radius_m: float,
                 max_slope_deg: float = 30.0, rms_fraction: float = 0.5,
                 window_m: float = 0.0) -> np.ndarray:
    """Cells where a ball foot of radius ``rho = foot_radius_m`` [m] is unsafe: within the
    square of half-side ``window_m`` (at least 2 cells; 0: ~2 rho) around the cell, the
    heights' RMS deviation from their least-squares plane exceeds ``rms_fraction * rho`` (an
    edge, a crack or a knob under the foot), or the plane is steeper than ``max_slope_deg`` (the
    friction limit with margin). Unknown cells and windows
    with unknown heights are not flagged (the caller masks unknown cells separately)."""
    import cv2
    h = np.asarray(heights, dtype=np.float64)
    if window_m > 0:
        # at least 2 cells each side: a plane and its RMS fitted to 3 x 3 cells miss a roof's
        # ridge (on the closed loop's 1 cm map this keeps the 5 x 5 window of 2 foot radii)
        r = max(2, int(round(window_m / resolution_m)))
    else:
        r = max(1, int(round(2 * foot_radius_m / resolution_m)))
    u = np.arange(-r, r + 1, dtype=np.float64)
    n2 = float(len(u)) ** 2
    box = np.ones_like(u)

    def sep(a, k0, k1):
        # k0 along axis 0, k1 along axis 1, edges replicated (scipy's correlate1d 'nearest');
        # OpenCV's separable filter is ~9x faster on a 300 x 300 map. It skips a zero tap, so
        # a NaN under one does not spread: the validity of a window is taken from the box
        # filter alone (all taps 1) below.
        return cv2.sepFilter2D(a, cv2.CV_64F, k1, k0, borderType=cv2.BORDER_REPLICATE)

    m = sep(h, box, box) / n2
    whole = np.isfinite(m)          # no unknown height in the window
    var = sep(h * h, box, box) / n2 - m * m
    su2 = float(np.mean(u * u))
    cu, cv = sep(h, u, box) / n2, sep(h, box, u) / n2
    rms = np.sqrt(np.maximum(var - (cu * cu + cv * cv) / su2, 0.0))
    slope = np.hypot(cu, cv) / su2 / resolution_m
    with np.errstate(invalid='ignore'):
        return whole & ((rms > rms_fraction * foot_radius_m)
                        | (slope > np.tan(np.radians(max_slope_deg))))


def candidate_mask(grid: GridMap, cfg: PlannerConfig) -> np.ndarray:
    """Cells allowed as footholds: known height and either observed, or (never observed and)
    filled with a finite upper bound within ``max_bound_gap_m`` of the filled height, or
    given the height of the plane through the stance feet (layer ``contact``, blind cells the
    feet stood near). A grid without an ``observed`` layer (e.g. ground truth) allows every
    known cell."""
    h = grid[ELEVATION]
    ok = np.isfinite(h)
    if OBSERVED in grid:
        obs = grid[OBSERVED] > 0.5
        if UPPER_BOUND in grid:
            ub = grid[UPPER_BOUND]
            with np.errstate(invalid='ignore'):
                bounded = np.isfinite(ub) & (ub - h <= cfg.max_bound_gap_m)
        else:
            bounded = np.zeros_like(obs)
        if FILLED in grid:
            bounded &= grid[FILLED] > 0.5
        ok &= obs | bounded | _contact_layer(grid)
    return ok


def _contact_layer(grid: GridMap) -> np.ndarray:
    """Cells whose height the fill node took from the robot's stance feet (layer
    ``contact``): never seen, but the feet stood there."""
    if 'contact' not in grid:
        return np.zeros(grid.shape, bool)
    return grid['contact'] > 0.5


# --------------------------------------------------------------------------------------------
# Geometry helpers
# --------------------------------------------------------------------------------------------

def _inset_triangle(tri: np.ndarray, margin: float) -> Optional[np.ndarray]:
    """Vertices (3, 2) of the triangle shrunk by ``margin`` [m], or None if nothing is left."""
    (ax, ay), (bx, by), (cx, cy) = np.asarray(tri, dtype=np.float64).tolist()
    area2 = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)
    if abs(area2) < 1e-12:
        return None
    # Side lengths opposite each vertex (scalar math: numpy's per-call cost dominates here).
    la, lb, lc = math.hypot(cx - bx, cy - by), math.hypot(ax - cx, ay - cy), \
        math.hypot(bx - ax, by - ay)
    per = la + lb + lc
    inradius = abs(area2) / per
    if inradius <= margin:
        return None
    ix, iy = (la * ax + lb * bx + lc * cx) / per, (la * ay + lb * by + lc * cy) / per
    # Homothety about the incentre shrinks every edge's distance by the same factor.
    k = 1.0 - margin / inradius
    out = np.array([[ax, ay], [bx, by], [cx, cy]])
    if area2 < 0:
        out = out[[0, 2, 1]]
    return np.array([ix, iy]) + (out - [ix, iy]) * k


def _project_to_triangle(p: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Closest point of the (closed, either orientation) triangle ``tri`` to ``p`` (2,)."""
    if point_in_triangle_margin(p, tri) >= 0.0:
        return p.copy()
    best, bd = None, np.inf
    px, py = float(p[0]), float(p[1])
    tl = np.asarray(tri, dtype=np.float64).tolist()
    for i in range(3):
        (ax, ay), (bx, by) = tl[i], tl[(i + 1) % 3]
        ux, uy = bx - ax, by - ay
        t = min(max(((px - ax) * ux + (py - ay) * uy) / max(ux * ux + uy * uy, 1e-18), 0.0), 1.0)
        qx, qy = ax + t * ux, ay + t * uy
        d = (px - qx) ** 2 + (py - qy) ** 2
        if d < bd:
            best, bd = (qx, qy), d
    return np.array(best)


def point_in_triangle_margin(p: np.ndarray, tri: np.ndarray) -> float:
    """Signed distance [m] from ``p`` (2,) to the nearest edge line of ``tri`` (3, 2): positive
    inside, negative outside (the stability margin of a COG over a support triangle)."""
    tri = np.asarray(tri, dtype=np.float64)
    a, b, c = tri
    area2 = (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])
    if abs(area2) < 1e-12:
        return -np.inf
    sgn = 1.0 if area2 > 0 else -1.0
    out = np.inf
    px, py = float(p[0]), float(p[1])
    t = tri.tolist()
    for i in range(3):     # scalar loop: numpy's per-call cost dominates on 2-vectors
        (ax, ay), (bx, by) = t[i], t[(i + 1) % 3]
        ux, uy = bx - ax, by - ay
        cross = ux * (py - ay) - uy * (px - ax)
        out = min(out, sgn * cross / math.hypot(ux, uy))
    return float(out)


def body_pose(body_xy: np.ndarray, feet: np.ndarray, yaw: float, robot: RobotModel,
              max_tilt_rad: float = 0.35, height_m: Optional[float] = None) -> np.ndarray:
    """Planned base pose (4x4) over the feet (4, 3) [m]: heading ``yaw``, z axis along the normal
    of the least-squares plane through the foot contacts (tilt capped at ``max_tilt_rad``), origin
    the standing height along that normal above the plane at ``body_xy``. Following the feet's
    plane keeps every leg near its nominal length on uneven ground, as the robot's posture
    adjustment does (paper 002 sec. III)."""
    feet = np.asarray(feet, dtype=np.float64)
    c_xy = feet[:, :2].mean(0)
    d = feet[:, :2] - c_xy
    # Least-squares plane z = z0 + grad . (xy - c_xy); centred, so z0 is the mean height and
    # grad solves the 2x2 normal equations (lstsq's minimum-norm answer when they are singular).
    M = d.T @ d
    rhs = d.T @ (feet[:, 2] - feet[:, 2].mean())
    det = M[0, 0] * M[1, 1] - M[0, 1] * M[1, 0]
    if abs(det) > 1e-12 * max(float(np.trace(M)) ** 2, 1e-30):
        grad = np.array([M[1, 1] * rhs[0] - M[0, 1] * rhs[1],
                         M[0, 0] * rhs[1] - M[1, 0] * rhs[0]]) / det
    else:
        grad = np.linalg.lstsq(d, feet[:, 2] - feet[:, 2].mean(), rcond=None)[0]
    z0 = float(feet[:, 2].mean())
    gnorm = float(np.hypot(*grad))
    if gnorm > np.tan(max_tilt_rad):
        grad = grad * (np.tan(max_tilt_rad) / gnorm)
    n = np.array([-grad[0], -grad[1], 1.0])
    n /= np.linalg.norm(n)
    h = np.array([np.cos(yaw), np.sin(yaw), 0.0])
    x = h - np.dot(h, n) * n
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, 0], T[:3, 2] = x, n
    T[:3, 1] = (n[1] * x[2] - n[2] * x[1], n[2] * x[0] - n[0] * x[2], n[0] * x[1] - n[1] * x[0])
    xy = np.asarray(body_xy, dtype=np.float64)
    z_plane = z0 + np.dot(grad, xy - c_xy)
    height = robot.standing_height_m if height_m is None else float(height_m)
    T[:3, 3] = np.array([xy[0], xy[1], z_plane]) + height * n
    return T


def reachable(robot: RobotModel, T_map_base: np.ndarray, feet_map: np.ndarray, legs: np.ndarray,
              reach_fraction: float) -> np.ndarray:
    """Which contact points ``feet_map`` (K, 3) [m, map] leg ``legs`` (K,) can reach from the base
    pose: IK within joint limits and hip-to-foot distance <= ``reach_fraction`` x leg length."""
    feet_map = np.asarray(feet_map, dtype=np.float64).reshape(-1, 3)
    legs = np.asarray(legs, dtype=np.int64).reshape(-1)
    R, t = T_map_base[:3, :3], T_map_base[:3, 3]
    centre = feet_map + np.array([0.0, 0.0, robot.foot_radius_m])
    p_base = (centre - t) @ R
    if len(legs) == 4 and np.array_equal(legs, np.arange(4)):   # one stance: one IK call
        return stance_in_reach(robot, p_base[None], reach_fraction)[0]
    flex = np.array(robot.leg_plane_offsets)[legs]
    ok = np.linalg.norm(p_base - flex, axis=1) <= reach_fraction * robot.leg_length_m
    idx = np.nonzero(ok)[0]          # IK (and its failure messages) only where it can succeed
    if len(idx):
        targets = np.broadcast_to(np.array(robot.nominal_feet) + [0, 0, robot.foot_radius_m],
                                  (len(idx), 4, 3)).copy()
        targets[np.arange(len(idx)), legs[idx]] = p_base[idx]
        ok[idx] = solve_ik(robot, targets, explain=False).ok[np.arange(len(idx)), legs[idx]]
    return ok


def stance_in_reach(robot: RobotModel, feet_base: np.ndarray,
                    reach_fraction: float) -> np.ndarray:
    """(P, 4) reachability of foot-sphere centres ``feet_base`` (P, 4, 3) [m, base_link]: IK
    within joint limits and hip-to-foot distance <= ``reach_fraction`` x leg length."""
    dist = np.linalg.norm(feet_base - np.array(robot.leg_plane_offsets), axis=-1)
    ok = dist <= reach_fraction * robot.leg_length_m
    rows = np.nonzero(np.all(ok, axis=1))[0]   # IK only for stances that can pass
    ok[:] = False
    if len(rows):
        ok[rows] = solve_ik(robot, feet_base[rows], explain=False).ok
    return ok


# --------------------------------------------------------------------------------------------
# Planner
# --------------------------------------------------------------------------------------------

@dataclass
class _State:
    feet: np.ndarray            # (4, 3) contact points [m]
    total: float                # accumulated weighted cost
    steps: List[Footstep]
    period_feet: np.ndarray     # (4, 3) feet at the start of the current gait period
    swing: tuple = ()           # (cog, T_map_base, height) for the next swing from ``feet``
    cands: Optional[tuple] = None   # scored footholds of the next swing (cached lookahead)


class FootstepPlanner:
    """Plans footsteps on one map. Build once per map (``set_map``), call :meth:`plan`.

    Args:
        robot: geometry and gait defaults (hip offsets, nominal stance, leg lengths, A).
        config: planner parameters.
        cost_config: weights for ``cost_source='kolter'``/``'shao'``.
    """

    def __init__(self, robot: RobotModel, config: PlannerConfig = PlannerConfig(),
                 cost_config: Optional[features.CostConfig] = None) -> None:
        self.robot = robot
        self.cfg = config
        self.cost_config = cost_config
        self.grid: Optional[GridMap] = None
        self.cost: Optional[np.ndarray] = None
        self.allowed: Optional[np.ndarray] = None
        self._rng = np.random.default_rng(config.random_seed)
        self._refusal_check = None      # set by plan_checked while it runs the recovery
        # Without a goal: the line to walk along, (origin (2,), unit direction (2,)) in the map.
        self.straight_line: Optional[Tuple[np.ndarray, np.ndarray]] = None
        # The body box's underside, sampled every <= 2 cm, in base_link; the map's heights
        # max-filtered over one sample spacing (set_map) make the samples' maximum the maximum
        # under the whole box.
        self._belly_pts, self._belly_spacing = belly_samples(robot)
        self._belly_top: Optional[np.ndarray] = None
        self._belly_blocked = False
        self.body_path: Optional[BodyPath] = None      # the last plan's (body_path on)
        self._route: Optional[Tuple[np.ndarray, np.ndarray]] = None    # (start, goal)
        self._path_cache: Optional[tuple] = None        # (key, BodyPath) of the last search
        # (min_crouch, the crouch levels tried, hip offsets (4, 3)) for _body_in_reach
        self._crouch_levels: tuple = (None, None, None)

    @property
    def A(self) -> float:
        """Shao's body movement per period [m]."""
        return self.cfg.body_move_per_period_m or self.robot.body_move_per_period_m

    def set_map(self, grid: GridMap) -> Optional[FootstepPlan]:
        """Take a new map (receding horizon: call on every map). Returns a failed plan saying
        why when the map cannot be planned on, else None."""
        self.grid = self.cost = self.allowed = None
        if grid is None:
            return failed(STATUS_NO_MAP, 'no map received yet')
        if ELEVATION not in grid:
            return failed(STATUS_BAD_MAP, f"map has no '{ELEVATION}' layer "
                          f'(layers: {sorted(grid.layers)})')
        if not np.any(np.isfinite(grid[ELEVATION])):
            return failed(STATUS_BAD_MAP, 'map is empty: no cell has a known elevation')
        try:
            cost = np.asarray(cost_layer(grid, self.cfg.cost_source, self.cost_config),
                              dtype=np.float64)
        except ValueError as exc:
            return failed(STATUS_BAD_MAP, f'cannot build the cost map: {exc}')
        if not np.any(np.isfinite(cost)):
            return failed(STATUS_BAD_MAP, 'cost layer has no finite value')
        self.grid, self.cost = grid, cost
        self._dev = None     # (i0, j0, Dev(h) of the cells from there): see _area_flat
        self.allowed = candidate_mask(grid, self.cfg) & np.isfinite(cost)
        self._belly_top = self._path_cache = None
        if self.cfg.belly_clearance_m >= 0:
            self._belly_top = top_field(grid, self._belly_spacing)
        if self.cfg.max_unevenness > 0:
            k = self.cfg.map_safety_factor
            h = grid[ELEVATION]
            if self.cfg.safety_surface == 'foot':
                h = foot_surface(h, grid.resolution_m, self.robot.foot_radius_m)
            self.allowed &= ~unsafe_cells(h, grid.resolution_m,
                                          self.robot.foot_radius_m, k * self.cfg.max_slope_deg,
                                          k * self.cfg.max_unevenness, self.cfg.safety_window_m)
        return None

    # ---- helpers ---------------------------------------------------------------------------
    def _nominal_feet(self, T_map_base: np.ndarray) -> np.ndarray:
        nom = np.array(self.robot.nominal_feet)
        xy = nom[:, :2] @ T_map_base[:2, :2].T + T_map_base[:2, 3]
        z = self.grid.sample(ELEVATION, xy).astype(np.float64)
        fallback = T_map_base[2, 3] - self.robot.standing_height_m
        return np.c_[xy, np.where(np.isfinite(z), z, fallback)]

    def _area(self, foot_u: float, nom_u: float, nom_v: float, wL: float, A: float,
              lateral_m: Optional[float] = None, ground_z: Optional[float] = None,
              cells: Optional[list] = None):
        """Search area of one leg: along-track [foot + min_step, nominal + wL + 2A] (capped by the
        max step length), across-track nominal +- ``lateral_m`` (default lateral_search).
        ``ground_z`` (the stance's height) lets ``stride_centre: adaptive`` test the area's
        flatness; without it 'adaptive' centres as 'capped'. Returns (u, v, centre_u); a list
        passed as ``cells`` gets the area's map points and cells appended, ``(xy, ij, inside)``
        (computed once for the flatness test and the caller)."""
        res = self.grid.resolution_m
        lo = foot_u + self.cfg.min_step_m
        rule_hi = nom_u + wL + 2.0 * A
        hi = min(rule_hi, foot_u + self.robot.max_step_length_m)
        hi = max(hi, lo)
        us = np.arange(lo, hi + 0.5 * res, res) if hi > lo else np.array([lo])
        w = self.cfg.lateral_search_m if lateral_m is None else lateral_m
        vs = nom_v + np.arange(-w, w + 0.5 * res, res) if w > 0 else np.array([nom_v])
        u, v = np.repeat(us, len(vs)), np.tile(vs, len(us))     # meshgrid 'ij', raveled
        centre = 0.5 * (lo + hi)
        mode = self.cfg.stride_centre
        geom = None
        if cells is not None or (mode == 'adaptive' and ground_z is not None):
            xy = self._to_map(u, v)
            geom = (xy,) + self._cells(xy)
            if cells is not None:
                cells.extend(geom)
        if mode == 'rule' or (mode == 'adaptive' and ground_z is not None
                              and self._area_flat(u, v, ground_z, geom)):
            centre = min(0.5 * (lo + max(rule_hi, lo)), hi)
        return u, v, centre

    def _area_flat(self, u: np.ndarray, v: np.ndarray, ground_z: float,
                   geom: Optional[tuple] = None) -> bool:
        """Shao's flatness test (paper 002 Fig. 4) on the cells at along/across-track ``u, v``:
        all observed and ``|h - ground_z| + Dev(h) < trot_threshold_m``. ``geom``: their
        ``(xy, ij, inside)`` if known."""
        _, ij, inside = geom if geom is not None else (None,) + self._cells(self._to_map(u, v))
        h = self.grid[ELEVATION][ij[:, 0], ij[:, 1]]
        if not np.all(inside & np.isfinite(h)):
            return False
        fc = flatness_cost(h, ground_z, self._dev_at(ij))
        return bool(np.all(fc < self.cfg.trot_threshold_m))

    #: half-width [cells] of the window of Shao's Dev computed at a time (the search areas of
    #: one plan lie within a few tens of cells of each other)
    _DEV_WINDOW = 40

    def _dev_at(self, ij: np.ndarray) -> np.ndarray:
        """Shao's Dev(h) at cells ``ij`` (inside the grid), from a cached window of the map
        (a new window around them when they leave it): the whole map's would cost ~10 ms per
        map, one area's bounding box a call per area."""
        i0, j0 = ij.min(0)
        i1, j1 = ij.max(0) + 1
        if self._dev is not None:
            a0, b0, dev = self._dev
            if a0 <= i0 and b0 <= j0 and i1 <= a0 + dev.shape[0] and j1 <= b0 + dev.shape[1]:
                return dev[ij[:, 0] - a0, ij[:, 1] - b0]
        n = self.grid.shape
        w = self._DEV_WINDOW
        ci, cj = (i0 + i1) // 2, (j0 + j1) // 2
        a0, b0 = max(min(i0, ci - w), 0), max(min(j0, cj - w), 0)
        a1, b1 = min(max(i1, ci + w), n[0]), min(max(j1, cj + w), n[1])
        # Dev is a 3x3 stencil: computed with a one-cell border, which is then dropped
        p0, q0 = max(a0 - 1, 0), max(b0 - 1, 0)
        dev = features.shao_dev(self.grid[ELEVATION][p0:a1 + 1, q0:b1 + 1])
        dev = dev[a0 - p0:a0 - p0 + (a1 - a0), b0 - q0:b0 - q0 + (b1 - b0)]
        self._dev = (a0, b0, dev)
        return dev[ij[:, 0] - a0, ij[:, 1] - b0]

    def _to_map(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        return self.origin + np.outer(u, self.hdir) + np.outer(v, self.ldir)

    def _uv(self, xy: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        d = np.asarray(xy)[..., :2] - self.origin
        return d @ self.hdir, d @ self.ldir

    def _cells(self, xy: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        ij = self.grid.world_to_index(xy)
        inside = self.grid.inside(ij)
        ij = np.where(inside[:, None], ij, 0)
        return ij, inside

    # ---- gait selection (paper 002 Fig. 4) -------------------------------------------------
    def trot_phase(self, feet: np.ndarray, A: float) -> Tuple[tuple, bool]:
        """Where the stance ``feet`` (4, 3) is in a trot period: ``(pairs, half_done)``, the
        diagonal pairs in the order they swing next (the pair further behind its nominal
        places first; ties: ``TROT_PAIRS`` order) and whether a period is half done (one
        pair ahead of the other by more than ``A/2`` along the heading: it swung, the other
        has not). Fig. 4 decides the gait once per period, but the plan is remade after every
        swing, so half the plans start between the two pairs of a period: judged as a new
        period there, the pair that just swung is out of position, the plan walks, and the
        crawl's next plan trots again from the wrong pair: the stance then spreads by A every
        few steps (FROG-I, flat, blind map: LF 0.97 m ahead of LH after 20 s, then a fall)."""
        kL = self._uv(feet)[0] - self.nom_u
        mean = [float(np.mean(kL[list(p)])) for p in TROT_PAIRS]
        lag = 1 if mean[1] < mean[0] else 0
        pairs = (TROT_PAIRS[lag], TROT_PAIRS[1 - lag])
        return pairs, mean[1 - lag] - mean[lag] > A / 2.0

    def select_gait(self, feet: np.ndarray, wL: float, A: float,
                    half_done: bool = False) -> Tuple[int, str]:
        """Fig. 4's test for one period from the feet (4, 3) and the body's along-track position
        ``wL`` [m]: trot when every search area is flat (Shao cost < Threshold) and every foot is
        in position (``kL - wL < A/2``), else walk. Returns ``(gait, reason)``.

        ``half_done`` (see :meth:`trot_phase`): the stance is half-way through a trot period,
        the body half-way (A/2) past where the period began; the test is the one the period
        had at its start: the pair that swung was A behind where it is, so ``kL - wL < A``
        for it and ``kL - wL < 0`` for the pair still to swing."""
        if not self.robot.trot:
            return GAIT_WALK, f'{self.robot.name} walks only (robot profile gait.trot)'
        ground = float(np.mean(feet[:, 2]))
        fu, _ = self._uv(feet)
        flat_all = True
        for k in range(4):
            u, v, _ = self._area(fu[k], self.nom_u[k], self.nom_v[k], wL, A)
            if not self._area_flat(u, v, ground):
                flat_all = False
                break
        if not flat_all:
            return GAIT_WALK, f'obstacle in the search area of leg {LEG_NAMES[k]}'
        kL = fu - self.nom_u
        if half_done:
            pairs, _ = self.trot_phase(feet, A)
            start = kL.copy()
            start[list(pairs[0])] += A / 2.0       # still to swing
            start[list(pairs[1])] -= A / 2.0       # swung by A, the body by A/2 since
            kL = start
        if np.all(kL - wL < A / 2.0):
            return GAIT_TROT, ('trot period half done, feet in position' if half_done else
                               'all search areas flat and feet in position')
        return GAIT_WALK, 'flat, but feet out of position (walk stride rule)'

    # ---- main entry --------------------------------------------------------------------------
    def plan(self, T_map_base: np.ndarray, goal_xy: Optional[np.ndarray] = None,
             feet: Optional[np.ndarray] = None, patches: Optional[Tuple[np.ndarray,
                                                                         np.ndarray]] = None,
             first_leg: Optional[int] = None) -> FootstepPlan:
        """Plan the next ``horizon_steps`` footsteps.

        Args:
            T_map_base: current base pose (4x4) in the map frame.
            goal_xy: (2,) goal [m, map]; None = straight ahead: along the line the first plan
                without a goal started on (``straight_lookahead_m``; 0 = the body's heading).
            feet: (4, 3) current contact points [m, map]; None = nominal stance at the pose.
            patches: optional ``(vertices (N, 3), radii (N,))`` of salient contact patches in
                the map frame.
            first_leg: the leg to move first in a walk (crawl order continues from it); None =
                the leg furthest behind its nominal place (ties: the first in crawl order).

        Returns:
            A plan; never raises on bad input (the status says what is wrong).
        """
        self.body_path = None
        if self.grid is None:
            return failed(STATUS_NO_MAP, 'no usable map (call set_map first)')
        T = np.asarray(T_map_base, dtype=np.float64)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            return failed(STATUS_BAD_INPUT, 'robot pose is not a finite 4x4 transform')
        if first_leg is not None and first_leg not in CRAWL_ORDER:
            return failed(STATUS_BAD_INPUT, f'first_leg must be one of 0..3, got {first_leg}')
        g = self.grid
        body_xy = T[:2, 3]
        if not g.inside(g.world_to_index(body_xy)):
            return failed(STATUS_ROBOT_OUTSIDE_MAP,
                          f'robot at ({body_xy[0]:.3f}, {body_xy[1]:.3f}) m is outside the map '
                          f'[{g.origin_xy[0]:.3f}..{g.origin_xy[0] + g.length_xy[0]:.3f}] x '
                          f'[{g.origin_xy[1]:.3f}..{g.origin_xy[1] + g.length_xy[1]:.3f}]')
        yaw_now = float(np.arctan2(T[1, 0], T[0, 0]))
        if goal_xy is None:
            yaw = self._straight_ahead(body_xy, yaw_now)
            remaining = np.inf
        else:
            self.straight_line = None
            goal = np.asarray(goal_xy, dtype=np.float64).reshape(-1)[:2]
            if goal.shape != (2,) or not np.all(np.isfinite(goal)):
                return failed(STATUS_BAD_INPUT, f'goal is not a finite (x, y): {goal_xy}')
            d = goal - body_xy
            remaining = float(np.hypot(*d))
            if remaining <= self.cfg.goal_tolerance_m:
                return FootstepPlan(STATUS_GOAL_REACHED, f'goal reached ({remaining:.3f} m away)',
                                    final_body_pose=T.copy())
            yaw = self._turn_towards(float(np.arctan2(d[1], d[0])), yaw_now)
        if self.cfg.body_path and self.cfg.belly_clearance_m >= 0:
            yaw = self._along_body_path(body_xy, yaw_now, yaw, goal_xy)
        if feet is None:
            Tb = T.copy()
            Tb[:3, :3] = body_pose(body_xy, np.zeros((4, 3)), yaw_now, self.robot)[:3, :3]
            feet = self._nominal_feet(Tb)
        feet = np.asarray(feet, dtype=np.float64)
        if feet.shape != (4, 3) or not np.all(np.isfinite(feet)):
            return failed(STATUS_BAD_INPUT, f'feet must be a finite (4, 3) array, got {feet}')
        if patches is not None:
            pv, pr = (np.asarray(patches[0], dtype=np.float64).reshape(-1, 3),
                      np.asarray(patches[1], dtype=np.float64).reshape(-1))
            self.patches = (pv, pr, float(pr.max())) if len(pv) else None
        else:
            self.patches = None
        refused = self._refusal_check
        if refused is not None:
            # plan_checked: the executor refused every normal plan; straight to the recovery.
            plan = failed(STATUS_NO_FOOTHOLD, 'every first step refused by the executor')
            yaw = yaw_now
        else:
            plan = self._plan_heading(feet, body_xy, yaw, remaining, first_leg)
        if not plan.ok and yaw != yaw_now:
            # Turning made the stance infeasible: keep the current heading this time.
            keep = self._plan_heading(feet, body_xy, yaw_now, remaining, first_leg)
            if keep.ok:
                keep.status_text += ' (turn towards the goal postponed)'
                plan, yaw = keep, yaw_now
        if plan.status == STATUS_NO_FOOTHOLD and self.cfg.recovery:
            plan = self._recover(plan, feet, body_xy, yaw_now, remaining, first_leg, refused)
            yaw = yaw_now if plan.ok else yaw
        plan.initial_feet = feet.copy()
        plan.yaw = yaw
        return plan

    def _along_body_path(self, body_xy: np.ndarray, yaw_now: float, yaw: float,
                         goal_xy: Optional[np.ndarray]) -> float:
        """The plan's heading along a body path (:mod:`terrain_perception.body_path`) to the
        goal, or without one to a point 2 m on along the goal-less line: towards the point
        ``body_path_lookahead_m`` along it, turning by at most max_turn_rad."""
        c = self.cfg
        route = None
        if goal_xy is not None:
            aim = np.asarray(goal_xy, dtype=np.float64).reshape(-1)[:2]
            if self._route is None or np.hypot(*(self._route[1] - aim)) > 0.01:
                self._route = (np.array(body_xy, dtype=np.float64), aim.copy())
            route = self._route
        elif self.straight_line is not None:
            origin, u = self.straight_line
            aim = origin + (float(np.dot(body_xy - origin, u)) + 2.0) * u
            route = (origin, origin + 1e3 * u)
        else:
            aim = body_xy + 2.0 * np.array([np.cos(yaw), np.sin(yaw)])
        if goal_xy is None:
            self._route = None
        corridor = (None if route is None or c.body_path_corridor_m <= 0
                    else (route[0], route[1], c.body_path_corridor_m))
        d = aim - body_xy
        if np.hypot(*d) < 1e-6:
            return yaw
        settings = BodyPathSettings(c.body_path_resolution_m, c.belly_clearance_m,
                                    c.body_path_headroom_m, c.body_path_weight)
        # plan_checked plans from the same pose up to a dozen times: search once per map,
        # pose and aim.
        key = (id(self._belly_top), tuple(np.round(body_xy, 6)), tuple(np.round(aim, 6)),
               settings, None if corridor is None else
               (tuple(corridor[0]), tuple(corridor[1]), corridor[2]))
        if self._path_cache is not None and self._path_cache[0] == key:
            self.body_path = self._path_cache[1]
        else:
            self.body_path = plan_body_path(
                self.grid, self.robot, body_xy, aim, float(np.arctan2(d[1], d[0])), settings,
                top=self._belly_top, corridor=corridor)
            self._path_cache = (key, self.body_path)
        p = self.body_path.lookahead(c.body_path_lookahead_m, aim) - body_xy
        if np.hypot(*p) < 1e-6:
            return yaw
        return self._turn_towards(float(np.arctan2(p[1], p[0])), yaw_now)

    def _turn_towards(self, bearing: float, yaw_now: float) -> float:
        """The plan's heading: towards ``bearing`` by at most max_turn_rad (a sudden heading
        change would rotate the hips away from feet planned for the old heading)."""
        turn = (bearing - yaw_now + np.pi) % (2 * np.pi) - np.pi
        return yaw_now + float(np.clip(turn, -self.cfg.max_turn_rad, self.cfg.max_turn_rad))

    def _straight_ahead(self, body_xy: np.ndarray, yaw_now: float) -> float:
        """Heading of a plan without a goal. The body's yaw follows its stance feet, and
        footholds placed around obstacles turn the stance, so planning along the current yaw
        lets the heading wander with no force back. Instead the first goal-less plan fixes a
        line (the body's position and heading then), and each plan steers at the point
        ``straight_lookahead_m`` ahead of the body's projection on it (pure pursuit): heading
        and sideways drift both come back. A goal clears the line."""
        L = self.cfg.straight_lookahead_m
        if L <= 0.0:
            return yaw_now
        if self.straight_line is None:
            self.straight_line = (np.array(body_xy, dtype=float),
                                  np.array([np.cos(yaw_now), np.sin(yaw_now)]))
        origin, u = self.straight_line
        along = float(np.dot(body_xy - origin, u))
        target = origin + (along + L) * u
        d = target - body_xy
        return self._turn_towards(float(np.arctan2(d[1], d[0])), yaw_now)

    def plan_checked(self, T_map_base: np.ndarray, goal_xy: Optional[np.ndarray],
                     feet: np.ndarray, check: Callable[[np.ndarray, np.ndarray],
                                                       Tuple[int, str]],
                     patches: Optional[Tuple[np.ndarray, np.ndarray]] = None,
                     first_leg: Optional[int] = None) -> FootstepPlan:
        """:meth:`plan`, then a dry run of the walk through ``check(legs, positions) ->
        (steps accepted, why not)``, the executor's own stability and reach model (the walking
        controller's ``check_footsteps``: it balances the whole-robot COM with the legs, this
        planner a point COG). Only the accepted prefix is kept; if the first step is refused,
        each other leg is tried first in turn, then (``recovery``) the relaxed plans of
        :meth:`_recover` whose first step is accepted. The status names what was cut and why."""
        plan = self.plan(T_map_base, goal_xy, feet=feet, patches=patches, first_leg=first_leg)
        if not plan.ok or plan.gait != GAIT_WALK or not plan.footsteps:
            return plan
        first = plan.footsteps[0].leg
        refusal = ''
        for leg in [first] + [lg for lg in CRAWL_ORDER if lg != first]:
            p = plan if leg == first else self.plan(T_map_base, goal_xy, feet=feet,
                                                    patches=patches, first_leg=leg)
            if not p.ok or not p.footsteps:
                continue
            n, why = self._checked_prefix(p, check)
            if n <= 0:
                refusal = refusal or why
                continue
            if leg != first:
                note = (f'{LEG_NAMES[leg]} first: the controller would refuse '
                        f'{LEG_NAMES[first]} first ({refusal})')
                p.check_note = note + ('; ' + p.check_note if p.check_note else '')
                p.status_text = note + '; ' + p.status_text
            return p
        why = ('the controller would refuse the first step of every plan from this stance '
               f'({refusal})')
        if self.cfg.recovery:
            # The relaxed plans of the recovery, each kept only if its first step is accepted.
            self._refusal_check = check
            try:
                p = self.plan(T_map_base, goal_xy, feet=feet, patches=patches, first_leg=first)
            finally:
                self._refusal_check = None
            if p.ok:
                p.check_note = why + ('; ' + p.check_note if p.check_note else '')
                p.status_text = f'{why}; {p.status_text}'
                return p
        return failed(STATUS_NO_FOOTHOLD, why)

    @staticmethod
    def _checked_prefix(plan: FootstepPlan, check) -> Tuple[int, str]:
        """Dry-run ``plan``'s steps through ``check``; cut it to the accepted prefix (noted in
        its status) if that is not empty. Returns ``check``'s ``(steps accepted, why not)``."""
        n, why = check(np.array([f.leg for f in plan.footsteps]),
                       np.array([f.position for f in plan.footsteps]))
        if 0 < n < len(plan.footsteps):
            plan.check_note = (f'kept {n} of {len(plan.footsteps)} steps: the controller '
                               f'would refuse the next: {why}')
            plan.status_text += f' ({plan.check_note})'
            plan.footsteps = plan.footsteps[:n]
        return n, why

    def _recover(self, failed_plan, feet, body_xy, yaw, remaining, first_leg,
                 check=None) -> FootstepPlan:
        """A stance with no feasible continuation (a re-estimated map can remove the footholds
        the previous plan counted on, a band of unsafe cells can cross a leg's path): retry
        with, in turn, a three times wider search across the walking line for the same leg,
        the other legs first, short or backward re-placing steps allowed, half the stability
        margin plus a deeper crouch, and the wider search with the other legs first. The first
        that plans is returned with the relaxation named in its status. The wider search comes
        first: letting the other legs go on while one is stuck leaves it ever further behind;
        next comes the foot furthest behind its nominal place, which holds the others back (the
        spread limit), so that stepping the others backward is the later resort. With ``check``
        (see :meth:`plan_checked`) a relaxed plan counts only if the executor accepts its first
        step, and is cut to the accepted prefix."""
        base = self.cfg
        fwd = {'lateral_search_m': 3.0 * base.lateral_search_m}
        wide = {**fwd, 'min_step_m': -0.03}
        others = [leg for leg in CRAWL_ORDER if leg != first_leg]
        hdir = np.array([np.cos(yaw), np.sin(yaw)])
        lag = (feet[:, :2] - body_xy) @ hdir - np.array(self.robot.nominal_feet)[:, 0]
        rear = int(np.argmin(lag))
        tries = [('wider search across the walking line, forward only', fwd, first_leg)]
        if rear != first_leg:
            tries += [(f'the rearmost foot ({LEG_NAMES[rear]}) first, wider search', fwd, rear)]
        tries += [('wider search across the walking line', wide, first_leg)]
        tries += [('another leg first', {}, leg) for leg in others]
        tries += [('re-placing a foot up to 3 cm back allowed', {'min_step_m': -0.03},
                   first_leg),
                  ('half stability margin, deeper crouch',
                   {'stability_margin_m': 0.5 * base.stability_margin_m,
                    'min_crouch': max(0.3, base.min_crouch - 0.15), 'min_step_m': -0.03},
                   first_leg)]
        tries += [('another leg first, wider search across the walking line', wide, leg)
                  for leg in others]
        try:
            for what, change, leg in tries:
                self.cfg = replace(base, horizon_steps=min(base.horizon_steps, 4), **change)
                plan = self._plan_heading(feet, body_xy, yaw, remaining, leg)
                if (plan.ok and check is not None and plan.gait == GAIT_WALK
                        and plan.footsteps and self._checked_prefix(plan, check)[0] <= 0):
                    continue
                if plan.ok:
                    plan.status_text = f'recovery ({what}): ' + plan.status_text
                    return plan
        finally:
            self.cfg = base
        return failed_plan

    def _plan_heading(self, feet, body_xy, yaw, remaining, first_leg) -> FootstepPlan:
        """Gait selection then trot or crawl search, walking along heading ``yaw``."""
        self.hdir = np.array([np.cos(yaw), np.sin(yaw)])
        self.ldir = np.array([-self.hdir[1], self.hdir[0]])
        self.origin = np.asarray(body_xy, dtype=np.float64).copy()
        nom = np.array(self.robot.nominal_feet)
        self.nom_u, self.nom_v = nom[:, 0], nom[:, 1]
        A = float(min(self.A, remaining))
        if first_leg is None:
            behind = self._uv(feet)[0] - self.nom_u
            first_leg = min(CRAWL_ORDER, key=lambda k: (round(behind[k], 6),
                                                        CRAWL_ORDER.index(k)))
        pairs, half = self.trot_phase(feet, A) if self.robot.trot else (TROT_PAIRS, False)
        gait, why = self.select_gait(feet, 0.0, A, half)
        plan = None
        if gait == GAIT_TROT:
            plan = self._plan_trot(feet, yaw, A, remaining, pairs, half)
            if plan is not None:
                plan.status_text = f'trot: {why}; ' + plan.status_text
            else:
                why = 'trot footholds not reachable, walking instead'
        if plan is None:
            plan = self._plan_walk(feet, yaw, A, remaining, first_leg)
            if plan.ok:
                plan.status_text = f'walk: {why}; ' + plan.status_text
        return plan

    # ---- trot ------------------------------------------------------------------------------
    def _plan_trot(self, feet, yaw, A, remaining, pairs=TROT_PAIRS,
                   half: bool = False) -> Optional[FootstepPlan]:
        """Trot periods of stride ``A`` from ``feet``: the diagonal ``pairs`` in that order
        (:meth:`trot_phase`); with ``half`` the period under way is finished first (its
        second pair swings with the body where it is), then whole periods follow, each
        re-tested by :meth:`select_gait`, the pair that led the period before leading."""
        cfg, g = self.cfg, self.grid
        steps: List[Footstep] = []
        cur = feet.copy()
        wL = 0.0
        n_periods = max(1, int(np.ceil(cfg.horizon_steps / 2))) + int(half)
        # after a half period the pair that swung in it leads the next ones
        order = (pairs[1], pairs[0]) if half else tuple(pairs)
        idx = 0
        # A trot step moves a foot by A along the heading, which cannot turn the stance: the
        # first period also turns each pair about the stance centre to the plan's heading
        # (at most max_turn_rad), or a trotting robot never turns towards its goal.
        feet_yaw = float(body_pose_from_feet(feet, 0.0)[3])
        turn = self._turn_towards(yaw, feet_yaw) - feet_yaw
        centre = feet[:, :2].mean(axis=0)
        Rturn = np.array([[math.cos(turn), -math.sin(turn)], [math.sin(turn), math.cos(turn)]])
        for period in range(n_periods):
            if idx >= cfg.horizon_steps:
                break
            if period > 0:
                gait, _ = self.select_gait(cur, wL, A)
                if gait != GAIT_TROT:
                    break
            if period == 0 and half:
                # the body is already half-way through this period
                wL_new, body_xy, swing = wL + 0.5 * A, self.origin + wL * self.hdir, pairs[:1]
            else:
                # Both pairs swing with the body half-way: feet move from A/2 behind to A/2
                # ahead of their nominal place.
                wL_new, body_xy, swing = wL + A, self.origin + (wL + 0.5 * A) * self.hdir, order
            for pair in swing:
                if idx >= cfg.horizon_steps:
                    break
                new = cur.copy()
                xy = cur[list(pair), :2] + A * self.hdir
                if period == 0 and turn != 0.0:
                    xy = centre + (cur[list(pair), :2] - centre) @ Rturn.T + A * self.hdir
                z = g.sample(ELEVATION, xy).astype(np.float64)
                ij, inside = self._cells(xy)
                if not np.all(inside & np.isfinite(z)) or not np.all(
                        self.allowed[ij[:, 0], ij[:, 1]]):
                    return None if not steps else self._finish(steps, cur, yaw, GAIT_TROT, A)
                new[list(pair)] = np.c_[xy, z]
                Tb = body_pose(body_xy, new, yaw, self.robot)
                if not (np.all(reachable(self.robot, Tb, new, np.arange(4), cfg.reach_fraction))
                        and np.all(reachable(self.robot, Tb, cur, np.arange(4),
                                             cfg.reach_fraction))):
                    return None if not steps else self._finish(steps, cur, yaw, GAIT_TROT, A)
                for leg, p in zip(pair, new[list(pair)]):
                    c = float(self.cost[tuple(g.world_to_index(p[:2]))])
                    steps.append(Footstep(leg, p.copy(), c, idx, -1, body_xy.copy(),
                                          self.robot.standing_height_m))
                cur = new
                idx += 1
            wL = wL_new
        if not steps:
            return None
        return self._finish(steps, cur, yaw, GAIT_TROT, A)

    def _finish(self, steps, feet, yaw, gait, A, text='') -> FootstepPlan:
        u, _ = self._uv(feet)
        body_u = float(np.mean(u - self.nom_u))
        body_xy = self.origin + body_u * self.hdir + float(
            np.mean(self._uv(feet)[1] - self.nom_v)) * self.ldir
        T = body_pose(body_xy, feet, yaw, self.robot)
        n = len({s.step_index for s in steps})
        return FootstepPlan(STATUS_OK, text or f'{n} step(s) planned', gait, steps, T, A)

    def _body_in_reach(self, body_xy, feet, yaw) -> Optional[np.ndarray]:
        """Body pose over ``feet`` at ``body_xy`` with every foot in reach: standing height
        first, then crouching (posture adjustment) down to ``min_crouch`` of it. With
        ``belly_clearance_m`` the body box's underside stays that far above the map: the
        body crouches no lower than that, and rises above the standing height when a rock
        under it needs it; None (``_belly_blocked`` set) when the legs cannot reach then."""
        h = self.robot.standing_height_m
        if self._crouch_levels[0] != self.cfg.min_crouch:
            self._crouch_levels = (self.cfg.min_crouch,
                                   np.linspace(1.0, self.cfg.min_crouch, 4),
                                   np.array(self.robot.leg_plane_offsets, dtype=np.float64))
        _, levels, hips = self._crouch_levels
        T = body_pose(body_xy, feet, yaw, self.robot)
        self._belly_blocked = False
        need = self._belly_need(T)
        if need > 0.0:
            levels = np.array([1.0 + need / h])
        elif np.isfinite(need):
            levels = levels[(1.0 - levels) * h <= -need]
        p = (feet + [0.0, 0.0, self.robot.foot_radius_m] - T[:3, 3]) @ T[:3, :3]
        # Lowering the base by dh along its own z raises every foot by dh in base_link.
        drop = (1.0 - levels) * h
        P = p[None] + drop[:, None, None] * np.array([0.0, 0.0, 1.0])
        # Distance check for all heights at once; IK level by level, usually one call.
        near = np.all(np.linalg.norm(P - hips, axis=-1)
                      <= self.cfg.reach_fraction * self.robot.leg_length_m, axis=1)
        k = next((int(i) for i in np.nonzero(near)[0]
                  if stance_in_reach(self.robot, P[i:i + 1], self.cfg.reach_fraction).all()),
                 None)
        if k is None:
            self._belly_blocked = need > 0.0 or len(levels) < 4
            return None
        self._last_crouch = float(levels[k])
        T = T.copy()
        T[:3, 3] -= drop[k] * T[:3, 2]
        return T

    def _belly_need(self, T: np.ndarray) -> float:
        """How far the body at pose ``T`` must rise along its z axis for its underside to clear
        the map by ``belly_clearance_m`` [m] (negative: how far it may sink); -inf with the
        check off or nothing known under the body."""
        if self._belly_top is None:
            return -np.inf
        pts = self._belly_pts @ T[:3, :3].T + T[:3, 3]
        ij, inside = self._cells(pts[:, :2])
        if not np.any(inside):
            return -np.inf
        top = self._belly_top[ij[inside, 0], ij[inside, 1]]
        gap = pts[inside, 2] - top
        return float(self.cfg.belly_clearance_m - gap.min()) / max(float(T[2, 2]), 0.5)

    # ---- walk (crawl) beam search ------------------------------------------------------------
    def _area_cells(self, state: _State, leg: int, fu0: np.ndarray, wL0: float, A: float,
                    Tb: np.ndarray, lateral_m: float):
        """The cells of ``leg``'s search area (half-width ``lateral_m``) that are allowed, keep
        the stance within the spread limits and are in reach from the body pose ``Tb``: ``(points
        (k, 3), u, v, cells (k, 2), area centre u)``, or ``(None, why not)``."""
        cfg, g = self.cfg, self.grid
        geom: list = []
        u, v, centre = self._area(fu0[leg], self.nom_u[leg], self.nom_v[leg], wL0, A,
                                  lateral_m, float(np.mean(state.feet[:, 2])), cells=geom)
        xy, ij, inside = geom
        ok = inside & self.allowed[ij[:, 0], ij[:, 1]]
        # A step back onto the foot's own cell is no step.
        ok &= np.hypot(*(xy - state.feet[leg, :2]).T) >= 0.75 * g.resolution_m
        if not np.any(ok):
            return None, _EMPTY_AREA
        fu, fv = self._uv(state.feet)        # the stance along / across the walking line
        if cfg.max_leg_spread_m > 0:
            # No foot further ahead of its nominal place than the rearmost other foot by more
            # than the spread: a foot left behind (an obstacle in its area) holds the others
            # back instead of ending up out of reach once the COG has moved on.
            lag = np.delete(fu - self.nom_u, leg)
            ok &= u - self.nom_u[leg] <= lag.min() + cfg.max_leg_spread_m
            if not np.any(ok):
                return None, (f'its search area {cfg.max_leg_spread_m} m or more ahead of the '
                              'rearmost other foot')
        # The stance's length along the walking line, front foot to the hind foot on its side,
        # as a share of the nominal spacing: at least min_stance_length (a hind foot closing up
        # on a blocked front foot leaves a support polygon too short), at most
        # max_stance_length (a hind foot left far behind cannot swing within reach).
        mate = _SAME_SIDE[leg]
        spacing = abs(self.nom_u[mate] - self.nom_u[leg])
        hind = leg in (LH, RH)
        if cfg.min_stance_length > 0:
            gap = cfg.min_stance_length * spacing
            ok &= (u <= fu[mate] - gap) if hind else (u >= fu[mate] + gap)
            if not np.any(ok):
                return None, (f'no cell of its search area keeps the stance {gap:.3f} m long '
                              f'(the {LEG_NAMES[mate]} foot)')
        if cfg.max_stance_length > 0:
            span = cfg.max_stance_length * spacing
            ok &= (u >= fu[mate] - span) if hind else (u <= fu[mate] + span)
            if not np.any(ok):
                return None, (f'no cell of its search area keeps the stance within {span:.3f} m '
                              f'(the {LEG_NAMES[mate]} foot)')
        # The stance's width across the walking line, this foot to the other foot of its pair,
        # as a share of the nominal width: at least min_stance_width (a left foot stays left of
        # its pair's right foot by it; feet together under the body roll the robot over), at
        # most max_stance_width (spread wider, no body pose keeps every foot in reach).
        mate = _ACROSS[leg]
        width = abs(self.nom_v[mate] - self.nom_v[leg])
        if cfg.min_stance_width > 0:
            gap = cfg.min_stance_width * width
            ok &= (v >= fv[mate] + gap) if self.nom_v[leg] > self.nom_v[mate] else \
                (v <= fv[mate] - gap)
            if not np.any(ok):
                return None, (f'no cell of its search area keeps the stance {gap:.3f} m wide '
                              f'(the {LEG_NAMES[mate]} foot)')
        if cfg.max_stance_width > 0:
            span = cfg.max_stance_width * width
            ok &= np.abs(v - fv[mate]) <= span
            if not np.any(ok):
                return None, (f'no cell of its search area keeps the stance within {span:.3f} m '
                              f'wide (the {LEG_NAMES[mate]} foot)')
        xy, u, v, ij = xy[ok], u[ok], v[ok], ij[ok]
        pts = np.empty((len(xy), 3))
        pts[:, :2] = xy
        pts[:, 2] = g[ELEVATION][ij[:, 0], ij[:, 1]]
        reach = reachable(self.robot, Tb, pts, np.full(len(pts), leg), cfg.reach_fraction)
        if not np.any(reach):
            return None, 'no cell of its search area is within reach'
        pts, u, v, ij = pts[reach], u[reach], v[reach], ij[reach]
        return pts, u, v, ij, centre

    def _candidates(self, state: _State, leg: int, feet0: np.ndarray, wL0: float, A: float,
                    Tb: np.ndarray):
        """Scored candidate footholds of ``leg`` (in its period's search area)."""
        cfg = self.cfg
        fu0, _ = self._uv(feet0)
        found = self._area_cells(state, leg, fu0, wL0, A, Tb, cfg.lateral_search_m)
        wide = cfg.blocked_lateral_search_m
        if wide > cfg.lateral_search_m and (
                found[0] is None or np.max(found[1]) < fu0[leg] + 0.5 * A):
            # Blocked: nothing half a stride ahead in the leg's lane (typically a rock filling
            # it). Inching up to the obstacle only lets the other legs close up on this one, so
            # search around it; the nominal-distance cost still prefers the lane.
            more = self._area_cells(state, leg, fu0, wL0, A, Tb, wide)
            if more[0] is None and more[1] == _EMPTY_AREA and leg in (LH, RH) and \
                    cfg.empty_lane_lateral_search_m > wide:
                # A hind foot with not one foothold in the wider search either (unseen ground,
                # the start's blind area): wider still, to the cells beside the lane that the
                # front feet stood on. Not a front foot: ahead of it nothing was stood on.
                more = self._area_cells(state, leg, fu0, wL0, A, Tb,
                                        cfg.empty_lane_lateral_search_m)
            if more[0] is not None and (found[0] is None or np.max(more[1]) > np.max(found[1])):
                found = more
        if found[0] is None:
            return None, found[1]
        pts, u, v, ij, centre = found
        # The stance's heading after the step (hind feet's midpoint to the front feet's, as
        # the controller sets the body's yaw), against the plan's: a front foot stepping 6 cm
        # round a rock turns it 8 deg, and such steps added up to 60 deg on rocks-12cm (seed 0)
        # while each plan turned back by max_turn_rad only.
        err = self._heading_error(state.feet, leg, u, v)
        if cfg.max_heading_error_rad > 0:
            err0 = abs(float(self._heading_error(state.feet, leg, *self._uv(
                state.feet[leg:leg + 1]))[0]))
            keep = (np.abs(err) <= cfg.max_heading_error_rad) | (np.abs(err) <= err0 + 1e-9)
            if not np.any(keep):
                return None, (f'no foothold keeps the stance within '
                              f'{np.degrees(cfg.max_heading_error_rad):.0f} deg of the heading')
            pts, u, v, ij, err = pts[keep], u[keep], v[keep], ij[keep], err[keep]
        cost = self.cost[ij[:, 0], ij[:, 1]]
        omega = (cfg.distance_weight_gain * ((u - centre) ** 2 + (v - self.nom_v[leg]) ** 2)
                 + A) / max(A, 1e-9)
        dz = np.abs(pts[:, 2] - float(np.mean(state.feet[:, 2])))
        # Distance from the stride-rule foothold (the area centre, paper 002 Fig. 4).
        d2 = (u - centre) ** 2 + (v - self.nom_v[leg]) ** 2
        short = np.maximum(centre - u, 0.0)
        J = omega * (np.maximum(cost, 0.0) + cfg.cost_offset + cfg.step_height_weight_per_m * dz
                     + cfg.nominal_weight_per_m2 * d2 + cfg.shortfall_weight_per_m2 * short ** 2
                     + cfg.heading_weight_per_rad2 * err ** 2)
        pidx = np.full(len(pts), -1)
        if self.patches is not None and cfg.patch_bonus > 0:
            pv, pr, rmax = self.patches
            # Only patches that can hold a candidate (centre within the area's box grown by
            # the largest radius): a hit needs |p - c| <= r, so the nearest hit is among them,
            # in the same order (same ties). A plan's map holds hundreds of patches, an area
            # a few.
            lo, hi = pts[:, :2].min(0) - rmax, pts[:, :2].max(0) + rmax
            near_box = np.flatnonzero((pv[:, 0] >= lo[0]) & (pv[:, 0] <= hi[0])
                                      & (pv[:, 1] >= lo[1]) & (pv[:, 1] <= hi[1]))
            if len(near_box):
                d = (np.linalg.norm(pts[:, None, :2] - pv[None, near_box, :2], axis=2)
                     - pr[None, near_box])
                near = np.argmin(d, axis=1)
                hit = d[np.arange(len(pts)), near] <= 0
                pidx = np.where(hit, near_box[near], -1)
                J = np.where(hit, J * (1.0 - cfg.patch_bonus), J)
        if cfg.selection == 'nominal':
            J = omega
        elif cfg.selection == 'random':
            J = self._rng.random(len(J))
        order = np.argsort(J, kind='stable')[:cfg.candidates_per_step]
        return (pts[order], cost[order], J[order], pidx[order]), ''

    def _heading_error(self, feet: np.ndarray, leg: int, u: np.ndarray,
                       v: np.ndarray) -> np.ndarray:
        """Heading of the stance ``feet`` with ``leg`` moved to each ``(u, v)`` (plan frame):
        the direction from the hind feet's midpoint to the front feet's, relative to the
        plan's heading [rad]."""
        fu, fv = self._uv(feet)
        # Pair means as (a + b) / 2, which is what the mean of two values computes: the same
        # numbers as averaging a per-candidate copy of the stance, without the copies.
        U = [float(x) for x in fu]
        V = [float(x) for x in fv]
        U[leg], V[leg] = u, v
        du = (U[LF] + U[RF]) / 2.0 - (U[LH] + U[RH]) / 2.0
        dv = (V[LF] + V[RF]) / 2.0 - (V[LH] + V[RH]) / 2.0
        return np.arctan2(dv, du)

    def _swing_pose(self, feet: np.ndarray, leg: int, yaw: float, A: float,
                    remaining: float):
        """COG and body pose for swinging ``leg`` from stance ``feet``: the body follows the
        feet (their mean offset from the nominal stance, A/8 ahead), projected into the other
        three feet's triangle shrunk by the stability margin, crouching if needed for reach.
        Returns ``(cog, T_map_base, height)`` or ``(None, reason, None)``."""
        cfg = self.cfg
        others = [k for k in range(4) if k != leg]
        inset = _inset_triangle(feet[others, :2], cfg.stability_margin_m)
        if inset is None:
            return None, (f'the support triangle for swinging {LEG_NAMES[leg]} cannot hold the '
                          f'COG with a {cfg.stability_margin_m} m margin'), None
        u, v = self._uv(feet)
        bu = float(np.mean(u - self.nom_u)) + A / 8.0
        bu = min(bu, remaining)
        nominal = self.origin + bu * self.hdir + float(np.mean(v - self.nom_v)) * self.ldir
        # Preferred COG: the nominal body projected into the shrunk triangle; if a leg cannot
        # reach from there, slide it towards the triangle's centre or back along the path.
        first = _project_to_triangle(nominal, inset)
        centre = inset.mean(axis=0)
        options = [first] + [first + t * (centre - first) for t in (0.35, 0.7, 1.0)] + [
            _project_to_triangle(nominal - 0.25 * A * self.hdir, inset)]
        belly = False
        for cog in options:
            Tb = self._body_in_reach(cog, feet, yaw)
            if Tb is not None:
                break
            belly |= self._belly_blocked
        if Tb is None:
            if belly:
                return None, (f'no body pose for swinging {LEG_NAMES[leg]} keeps the belly '
                              f'{self.cfg.belly_clearance_m} m above the terrain with every '
                              'stance leg in reach'), None
            return None, (f'shifting the COG into the support triangle for swinging '
                          f'{LEG_NAMES[leg]} puts a stance leg out of reach'), None
        return cog, Tb, float(self.robot.standing_height_m * self._last_crouch)

    def _plan_walk(self, feet, yaw, A, remaining, first_leg) -> FootstepPlan:
        """Beam search over the crawl. A partial plan is only kept if the next swing (after the
        horizon too) still has a stable, reachable body pose: no dead ends handed to the
        controller."""
        cfg = self.cfg
        start = CRAWL_ORDER.index(first_leg)
        legs = [CRAWL_ORDER[(start + s) % 4] for s in range(cfg.horizon_steps + 1)]
        pose0 = self._swing_pose(feet, legs[0], yaw, A, remaining)
        if pose0[0] is None:
            return failed(STATUS_NO_FOOTHOLD, 'the goal cannot be reached from here, no '
                          f'feasible first step: {pose0[1]}')
        root = _State(feet.copy(), 0.0, [], feet.copy())
        root.swing = pose0
        beam = [root]
        wL0 = 0.0
        last_fail = ''
        fallback = None
        for s in range(cfg.horizon_steps):
            leg, next_leg = legs[s], legs[s + 1]
            phase = s % 4
            if s > 0 and phase == 0:
                wL0 = min(wL0 + A, remaining)
            expansions = []
            for bi, st in enumerate(beam):
                if s > 0 and phase == 0:
                    st.period_feet = st.feet.copy()
                cands = st.cands
                if cands is None:
                    cands, why = self._candidates(st, leg, st.period_feet, wL0, A, st.swing[1])
                    if cands is None:
                        last_fail = f'leg {LEG_NAMES[leg]} has {why}'
                        continue
                for p, c, J, pi in zip(*cands):
                    expansions.append((st.total + float(J), bi, p, float(c), int(pi)))
            expansions.sort(key=lambda e: e[0])
            new_beam: List[_State] = []
            n_phase = (s + 1) % 4
            n_wL0 = min(wL0 + A, remaining) if n_phase == 0 else wL0
            for total, bi, p, c, pi in expansions:
                if len(new_beam) >= cfg.beam_width:
                    break
                st = beam[bi]
                nf = st.feet.copy()
                nf[leg] = p
                # Look one swing ahead: the next leg needs a stable, reachable body pose and at
                # least one foothold from it, or this partial plan is a dead end.
                cog, _, height = st.swing
                step = Footstep(leg, p.copy(), c, s, pi, cog.copy(), height)
                if s == 0 and fallback is None:
                    fallback = (step, nf)      # the best single first step, checked in itself
                nxt = self._swing_pose(nf, next_leg, yaw, A, remaining)
                if nxt[0] is None:
                    last_fail = f'after {LEG_NAMES[leg]} steps, {nxt[1]}'
                    continue
                # A foot more than A/2 behind the others (Shao's "in position" tolerance) must
                # stay liftable too (the COG moved into the others' triangle with it still in
                # reach), or it is stranded a few steps on.
                lag = self._uv(nf)[0] - self.nom_u
                rear = int(np.argmin(lag))
                if (rear not in (leg, next_leg)
                        and lag[rear] < np.mean(np.delete(lag, rear)) - 0.5 * A
                        and self._swing_pose(nf, rear, yaw, A, remaining)[0] is None):
                    last_fail = f'after {LEG_NAMES[leg]} steps, {LEG_NAMES[rear]} could not lift'
                    continue
                ns = _State(nf, total, st.steps + [step],
                            nf.copy() if n_phase == 0 else st.period_feet)
                ns.swing = nxt
                ns.cands, why = self._candidates(ns, next_leg, ns.period_feet, n_wL0, A, nxt[1])
                if ns.cands is None:
                    last_fail = (f'after {LEG_NAMES[leg]} steps, leg {LEG_NAMES[next_leg]} '
                                 f'has {why}')
                    continue
                new_beam.append(ns)
            if not new_beam:
                if s == 0 and fallback is not None:
                    # Every first step leaves the next leg stuck in this crawl order; take the
                    # best one (it is safe, stable and in reach) and let the next plan, which
                    # may start with another leg, continue.
                    return self._finish([fallback[0]], fallback[1], yaw, GAIT_WALK, A,
                                        f'1 step planned; no continuation found: {last_fail}')
                if s == 0:
                    return failed(STATUS_NO_FOOTHOLD, 'the goal cannot be reached from here, no '
                                  f'feasible first step: {last_fail}')
                best = beam[0]
                return self._finish(best.steps, best.feet, yaw, GAIT_WALK, A,
                                    f'{s} step(s) planned; horizon cut: {last_fail}')
            beam = new_beam
        best = beam[0]
        return self._finish(best.steps, best.feet, yaw, GAIT_WALK, A)


def plan_footsteps(grid: GridMap, robot: RobotModel, T_map_base: np.ndarray,
                   goal_xy: Optional[np.ndarray] = None, config: PlannerConfig = PlannerConfig(),
                   **kwargs) -> FootstepPlan:
    """One-shot convenience: :meth:`FootstepPlanner.set_map` then :meth:`FootstepPlanner.plan`."""
    planner = FootstepPlanner(robot, config)
    bad = planner.set_map(grid)
    if bad is not None:
        return bad
    return planner.plan(T_map_base, goal_xy, **kwargs)


class RefusedSteps:
    """Steps the executing controller refused although the planner's dry run of its checks
    (:func:`terrain_perception.controller.check_footsteps`) accepted them.

    The dry run cannot know everything the running controller does (the tilt its IMU
    measured, the feet's rolling, its levelled stance heights), so a step can pass it and still
    be refused; a planner that keeps offering that step livelocks (closed-loop run X: one RH
    step refused 163 times in 50 s of simulated time). The planner records the first step of
    each plan it sends together with the controller's step count (:meth:`offered`); a refusal
    the controller then reports without having stepped (:meth:`report`) makes that step, and
    any foothold of the same leg within ``tolerance_m`` of it, refused for the planner's checks
    (:meth:`refusal`) until the controller completes a step or ``max_age_s`` passes (a
    refusal can be transient: a measured tilt, a foot still settling)."""

    def __init__(self, tolerance_m: float = 0.02, max_age_s: float = 10.0) -> None:
        if not tolerance_m >= 0.0 or not max_age_s > 0.0:
            raise ValueError(f'RefusedSteps: tolerance_m {tolerance_m} must be >= 0 and '
                             f'max_age_s {max_age_s} > 0')
        self.tolerance_m, self.max_age_s = float(tolerance_m), float(max_age_s)
        self._offer: Optional[tuple] = None      # (steps_done, leg, position (3,), t)
        self._refused: List[tuple] = []          # (steps_done, leg, position (3,), why, t)

    def offered(self, steps_done: int, leg: int, position: np.ndarray, t: float) -> None:
        """The planner sent a plan whose first step is ``leg`` to ``position`` at time ``t``,
        planned from the stance after ``steps_done`` completed steps."""
        self._offer = (int(steps_done), int(leg), np.asarray(position, dtype=float).copy(),
                       float(t))

    def report(self, steps_done: int, error: str, t: float) -> bool:
        """The controller's state at time ``t``: its completed steps and its last refusal
        (``''`` if none). Returns True when it records a refusal of the offered step."""
        steps_done = int(steps_done)
        self._refused = [r for r in self._refused if r[0] == steps_done]
        o = self._offer
        if (not error or error.startswith('plan is older') or o is None
                or o[0] != steps_done or t < o[3]):
            return False
        if self.refusal(steps_done, o[1], o[2], t) is not None:
            return False                         # already known
        self._refused.append((steps_done, o[1], o[2], str(error), float(t)))
        return True

    def refusal(self, steps_done: int, leg: int, position: np.ndarray,
                t: float) -> Optional[str]:
        """Why the controller refused a step of ``leg`` near ``position`` from this stance, or
        None if it did not (or the refusal is older than ``max_age_s``)."""
        self._refused = [r for r in self._refused if t - r[4] <= self.max_age_s]
        p = np.asarray(position, dtype=float)
        for done, lg, q, why, _ in self._refused:
            if done == int(steps_done) and lg == int(leg) and \
                    np.linalg.norm(p[:2] - q[:2]) <= self.tolerance_m:
                return why
        return None
