"""Walking controller core: footsteps -> statically stable body/foot motion -> joint targets.

Paper 000 (Kolter et al., sec. IV): from the planned footsteps, plan COG and foot trajectories
that keep static stability, then IK and PD joint control; dead reckoning along the *desired*
trajectory is the ICP prior and is re-anchored by ICP; the controller tells perception when
the body is stable enough for a picture. Paper 002 (Shao et al., sec. III): walk and trot
executed discontinuously (the body moves only while all four feet are down), waypoints turned
into joint space by IK and interpolated with cubic splines, COG kept in the support polygon.

Execution unit = one footstep (walk) or one diagonal pair (trot):

1. *shift*: all four feet down, the body moves so that the whole-robot COG is at least
   ``stability_margin_m`` inside the triangle of the legs that stay down (the nearest such
   point to the nominal body position over the next stance);
2. *swing*: the body holds still; the foot lifts, traverses at a height that clears the
   terrain under its path, and lands on the footstep.

Each segment's Cartesian motion is sampled at ``knot_dt_s``, converted by IK and interpolated
with a clamped ``scipy.interpolate.CubicSpline`` in joint space.

With joint torques, each foot's ground force is estimated (no foot sensors): a swing that meets
the ground early ends there (and, if that was centimetres above its foothold, the foot is
checked after a short hold and probed down if it hangs), a stance foot that should carry weight
before a swing but does not is probed down, and a stance foot that hangs (reads its own leg's
weight) is lowered slowly until it touches, so no body shift tips the robot over the diagonal of
the other two.

Frames: footsteps, feet and the body pose live in ``odom`` (the dead-reckoning frame);
``T_map_odom`` (from ICP) converts plans given in ``map``. Time is passed in [s]; the core
never reads a clock.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, NamedTuple, Optional

import functools

import numpy as np
from scipy.interpolate import CubicSpline

from terrain_perception import gait as gaitlib
from terrain_perception import kinematics
from terrain_perception.body_path import belly_samples
from terrain_perception.config import param
from terrain_perception.robot_model import LEG_NAMES, RobotModel
from terrain_perception.transforms import invert, make_T, rot_z, transform_points


@dataclass(frozen=True)
class WalkingConfig:
    """Walking controller parameters (0 = take the robot profile's value where noted)."""

    swing_duration_s: float = param(0.0, 'Duration of one crawl swing [s] (0 = profile)',
                                    0.0, 10.0)
    shift_duration_s: float = param(0.0, 'Duration of one body shift [s] (0 = profile)',
                                    0.0, 10.0)
    shift_zmp_offset_m: float = param(
        0.005, 'A body shift lasts at least long enough that its acceleration moves the ZMP at '
        'most this far from the COM\'s ground projection (cart-table model, h a / g, with the '
        'min-jerk peak acceleration 5.77 d / T^2): a quasi-static gait needs it well inside the '
        'stability margin; the profile\'s 0.35 s shifts reach 3.4 cm on flat ground [m] '
        '(0 = shift_duration_s alone)', 0.0, 0.5)
    trot_swing_fraction: float = param(0.7, 'Trot swing duration as a fraction of the crawl '
                                       'swing [-]', 0.1, 1.0)
    trot_max_step_fraction: float = param(1.0, 'Refuse trot pairs with a step longer than this '
                                          'fraction of max_step_length_m (the trot\'s COG sits '
                                          'on the support diagonal) [-]', 0.1, 3.0)
    stability_margin_m: float = param(0.0, 'COG distance inside the support triangle before '
                                      'a swing [m] (0 = profile)', 0.0, 0.5)
    terrain_clearance_m: float = param(0.0, 'Swing apex above the highest terrain under the '
                                       'swing path [m] (0 = half the profile swing height)',
                                       0.0, 0.5)
    knot_dt_s: float = param(0.02, 'Spacing of IK knots for the joint cubic splines [s]',
                             0.002, 0.5)
    plan_timeout_s: float = param(5.0, 'A plan older than this starts no new step [s]',
                                  0.1, 3600.0)
    max_step_factor: float = param(1.3, 'Reject steps longer than this times the profile\'s '
                                   'max_step_length_m [-]', 1.0, 3.0)
    touchdown_depth_m: float = param(0.002, 'Foot target this far below the foothold so the '
                                     'foot loads firmly [m]', 0.0, 0.05)
    still_settle_s: float = param(0.1, 'Body desired velocity zero this long before it counts '
                                  'as still [s]', 0.0, 5.0)
    still_joint_speed_rad_s: float = param(0.5, 'Stance joints slower than this count as still '
                                           '[rad/s]', 0.0, 100.0)
    capture_min_interval_s: float = param(0.5, 'Minimum time between capture requests [s] '
                                          '(paper 000: pictures twice a second)', 0.0, 60.0)
    reach_fraction: float = param(0.93, 'Body lowered so no foot is farther than this '
                                  'fraction of the leg length from its hip [-]', 0.5, 1.0)
    min_margin_fraction: float = param(0.3, 'Refuse a step whose COG margin would fall below '
                                       'this fraction of stability_margin_m because a full '
                                       'shift is out of reach [-]', 0.0, 1.0)
    min_swing_hip_height: float = param(0.6, 'Body at least this fraction of the standing '
                                        'height above the swing foot [-]', 0.0, 1.0)
    recenter: bool = param(True, 'Shift the body back over the centre of its four feet when '
                           'the plan is exhausted')
    contact_force_n: float = param(2.0, 'Vertical ground force on a foot [N], estimated from '
                                   'the joint torques, above which the foot counts as loaded; '
                                   'drives touchdown sensing (needs joint efforts; 0 = off, '
                                   'feet then land at the planned heights blindly)', 0.0, 1000.0)
    contact_ticks: int = param(3, 'Consecutive control ticks above contact_force_n that make a '
                               'touchdown (debounce) [-]', 1, 1000)
    contact_max_descent_m_s: float = param(0.25, 'A foot still descending faster than this '
                                           '(measured, from the joint rates) is in the air: '
                                           'decelerating a falling leg also loads its motors '
                                           '[m/s]', 0.0, 10.0)
    support_force_n: float = param(0.5, 'Before a leg lifts, each of the other three must carry '
                                   'more than this estimated vertical force [N], else it is '
                                   'lowered to the ground first (a light but real stance leg '
                                   'carries ~2 N on LittleDog; a hanging one reads about -1 N, '
                                   'its own weight)', -100.0, 1000.0)
    probe_contact_force_n: float = param(0.5, 'A probing foot (moving slowly, so its motors feel '
                                         'no inertia) has found the ground when its estimated '
                                         'vertical force exceeds this [N]; hanging it reads '
                                         'about -1 N (its own weight)', -100.0, 1000.0)
    swing_inward_lift: bool = param(
        True, 'a swing that moves the foot towards the body\'s centre line makes that sideways '
        'part while lifting (diagonally up and in) instead of at the apex')
    swing_lift_fore_aft_m: float = param(
        0.05, 'when no body pose reaches a swing\'s straight lift (a foot far behind or ahead '
        'of its hip: rocks-6cm ground-truth seed 0 stalled on LH 10 cm behind), a foot '
        'standing more than this behind or ahead of its nominal place (along the body) makes '
        'the part of its step beyond this while lifting; only then: done on every step it '
        'dragged the feet of flat strides (foot error 23 mm median); 0 = off [m]', 0.0, 1.0)
    shank_max_penetration_m: float = param(
        0.01, 'A body pose that puts a shank\'s axis (knee to foot) more than this below the '
        'height map, and deeper than the shank already is, is out of reach: the shank would '
        'rest on the terrain and hold its foot in the air (rocks-6cm ground-truth seed 1 fell '
        'so: six body shifts turned RH\'s shank into a rock, the foot hung 45 mm up and the '
        'shank read as a support); no check without a map or where it is unknown; negative = '
        'off. 1 cm, not 0: stereo maps draw rocks ~4-8 mm wide at their flanks (terrain-bench '
        'icp\'s map by region) and the dry run refused every step of a rocks-12cm loop trial '
        'over shanks 1-10 mm "into" them; on ground truth at 50 Hz rocks-12cm seeds 0-23 '
        'cross 6 of 24 with it against 2 (14 falls either way), rocks-6cm unchanged [m]',
        -1.0, 1.0)
    belly_clearance_m: float = param(
        0.012, 'The body is raised (within the legs\' reach) so that its underside stays this '
        'far above the highest map cell under its box, and a body pose the reach leaves lower '
        'than half of this (and lower than the body is now) is refused: rocks-12cm '
        'ground-truth walks stopped with the belly on a 10-11 cm rock while the feet stood on '
        'the floor. Alone, the reach capped the rise at 0-1 cm where it was needed (seeds '
        '0-11: 7 falls instead of 8); with the planner\'s belly_clearance_m (0.015, above '
        'this) and body path, see docs/BENCHMARKS.md; no effect where the map is unknown; '
        'negative = off [m]', -1.0, 1.0)
    swing_approach_m: float = param(
        0.0, 'The last this much of a swing\'s lowering is a slow straight descent at '
        'swing_approach_speed_m_s (capped by the apex): ground up to this much higher than '
        'believed is met slowly instead of at the minimum-jerk lowering\'s speed (LittleDog: '
        '0.8 m/s mid-way down), which kicks the body up when the estimate is off; adds the '
        'approach time to every swing (0 = off) [m]', 0.0, 0.1)
    swing_approach_speed_m_s: float = param(
        0.15, 'Descent speed of that final approach; below contact_max_descent_m_s so a '
        'contact during it counts [m/s]', 0.01, 1.0)
    swing_max_speed_m_s: float = param(
        0.0, 'A swing lasts at least long enough that the peak speed of its lift, its '
        'traverse and its lowering (each minimum-jerk) stays under this: a high apex over '
        'rocks is otherwise climbed and dropped in the same 0.35 s as a 4 cm flat step '
        '(2 m/s for a 10 cm drop), and a foot meeting a flank or the ground early hits it at '
        'that speed; the swinging leg\'s inertia also unloads the stance feet. On rocks-12cm '
        'ground truth 0.5 m/s slows touchdowns from 0.52 to 0.20 m/s (median) and halves the '
        'swing time with a stance foot under 1 N (20 to 9 %), but crosses 4 of 24 seeds with '
        '15 falls against 6 and 14, so it is off (0 = the fixed swing duration) [m/s]',
        0.0, 10.0)
    early_touchdown_fraction: float = param(0.75, 'Contact after this fraction of a swing ends '
                                            'the swing where the foot is: the ground is higher '
                                            'than planned [-]', 0.5, 1.0)
    early_touchdown_max_above_m: float = param(
        0.04, 'A contact while the swinging foot is still more than this above its foothold '
        'does not end the swing: the ground under the foothold is not that far off the map, '
        'so it is a shank or the foot touching an obstacle on the way [m]', 0.0, 1.0)
    probe_depth_m: float = param(0.03, 'A foot that is not loaded when it should be (after its '
                                 'swing, or before another leg lifts) is lowered up to this '
                                 'far below its foothold looking for the ground [m]', 0.0, 0.2)
    probe_speed_m_s: float = param(0.03, 'Descent speed while probing for the ground [m/s]',
                                   0.001, 1.0)
    body_tilt_gain: float = param(0.7, 'Share of the slope of the stance feet\'s plane (front '
                                  'vs hind, left vs right) by which the body pitches and rolls '
                                  'with it, so legs on higher ground are not folded while the '
                                  'others stretch (0 = level body) [-]', 0.0, 1.0)
    max_body_tilt_deg: float = param(15.0, 'Cap of that body pitch and roll [deg]', 0.0, 45.0)
    tilt_map_tolerance_m: float = param(
        0.015, 'For that tilt a foot counts at most this far above the height map under it: '
        'touchdown sensing cannot tell a foot on the ground from a shank resting on an '
        'obstacle with the foot in the air, and tilting the body after such a foot pitches it '
        'for nothing (no effect where the map is unknown or not set) [m]', 0.0, 1.0)
    hanging_force_n: float = param(
        -0.4, 'A stance foot whose estimated vertical force stays below this for contact_ticks '
        'ticks hangs: a hanging LittleDog foot reads about -0.8 N (its own weight), one that '
        'touches the ground 0 N or more [N]', -100.0, 1000.0)
    stance_extend_m_s: float = param(
        0.01, 'A hanging stance foot is lowered at this speed until it touches again (up to '
        'max_stance_extend_m per segment): a foot that ended its swing 1-2 mm above the ground '
        'otherwise lets the robot tip over the diagonal of the two feet that do carry it once '
        'the next body shift moves the COM over it (0 = off) [m/s]', 0.0, 1.0)
    max_stance_extend_m: float = param(0.01, 'Largest such lowering of a foot between two of '
                                       'its swings [m]', 0.0, 0.1)
    touchdown_verify_s: float = param(
        0.05, 'After a swing that a touchdown ended more than max_stance_extend_m above its '
        'foothold, the body holds still this long, then a swung foot that reads hanging '
        '(below hanging_force_n) is probed down to its foothold and probe_depth_m beyond, '
        'before the next body shift moves the COM over it: a swing foot that decelerates near '
        'its apex loads its motors like a contact and can end its swing there, centimetres '
        'above the ground (0 = off) [s]', 0.0, 1.0)
    attitude_gain: float = param(0.7, 'Share of the measured body tilt (IMU) that each body '
                                 'shift corrects by re-estimating the stance feet heights and '
                                 'changing the legs\' lengths (0 = level-body open loop) [-]',
                                 0.0, 1.0)


class Phase(NamedTuple):
    """The motion segment being executed: 'shift' (body moves, four feet down), 'swing',
    'probe' (a foot lowered slowly until it finds the ground) or 'verify' (the body holds
    still after a swing cut short in the air, to read whether the swung feet bear load)."""

    kind: str
    legs: tuple          # swinging legs (empty for a shift)
    t0: float            # start time [s]
    duration: float      # [s]


class JointCommand(NamedTuple):
    """Joint targets ``(12,)`` in ``RobotModel.joint_names`` order: angles [rad], rates [rad/s]."""

    positions: np.ndarray
    velocities: np.ndarray


@dataclass
class _Segment:
    kind: str                     # 'shift', 'swing' or 'probe'
    t0: float
    duration: float
    spline: Optional[CubicSpline]  # joint angles (12,) over [0, duration]; None in dry runs
    body_fn: Callable             # tau -> (x, y, z, yaw, pitch, roll) (odom)
    feet_end: np.ndarray          # (4, 3) contact points at the end (odom)
    body_end: np.ndarray          # (x, y, z, yaw) at the end
    legs: tuple = ()              # swinging legs
    moves_body: bool = True
    roll_end: Optional[np.ndarray] = None   # (4, 3) rolling displacement of the feet at the end
    feet_fn: Optional[Callable] = None      # tau -> (4, 3) planned contact points (odom)
    knots: Optional[np.ndarray] = None      # (n,) IK knot times [s]
    roll: Optional[np.ndarray] = None       # (n, 4, 3) rolling displacement at the knots
    q_end: Optional[np.ndarray] = None      # (12,) joint angles at the end (the last knot)
    approach_s: float = 0.0       # a swing's slow final approach at its end [s]

    def feet_at(self, tau: float) -> np.ndarray:
        """``(4, 3)`` contact points (odom) at ``tau`` into the segment, rolling included."""
        tau = min(max(float(tau), 0.0), self.duration)
        roll = np.stack([np.stack([np.interp(tau, self.knots, self.roll[:, k, a])
                                   for a in range(3)]) for k in range(4)])
        return np.asarray(self.feet_fn(tau), dtype=float) + roll

    @property
    def t_end(self) -> float:
        return self.t0 + self.duration

    def joints_many(self, taus: np.ndarray) -> tuple:
        """Angles and rates ``(P, 12)`` at times ``taus`` ``(P,)`` into the segment (clipped
        to it: after its end the final angles hold)."""
        x = self.spline.x
        taus = np.clip(np.asarray(taus, dtype=float), 0.0, self.duration)
        h = x[1] - x[0]
        i = np.minimum((taus / h).astype(int), len(x) - 2)
        dx = (taus - x[i])[:, None]
        c = self.spline.c[:, i, :]
        pos = ((c[0] * dx + c[1]) * dx + c[2]) * dx + c[3]
        vel = (3.0 * c[0] * dx + 2.0 * c[1]) * dx + c[2]
        return pos, vel

    def joints(self, tau: float) -> tuple:
        """Spline angles and rates (12,) at ``tau`` [s] into the segment (clipped).

        Evaluates the cubic pieces directly (uniform knots) - much cheaper per control tick
        than two ``CubicSpline.__call__``s.
        """
        x = self.spline.x
        tau = min(max(float(tau), 0.0), self.duration)
        h = x[1] - x[0]
        i = min(int(tau / h), len(x) - 2)
        dx = tau - x[i]
        c = self.spline.c[:, i, :]
        pos = ((c[0] * dx + c[1]) * dx + c[2]) * dx + c[3]
        vel = (3.0 * c[0] * dx + 2.0 * c[1]) * dx + c[2]
        return pos, vel


@dataclass
class _Step:
    legs: tuple
    targets: np.ndarray           # (k, 3) contact points, odom
    gait: str
    lift_fore_aft: bool = False   # set by _make_shift when only the fore-aft lift reaches


class WalkingController:
    """Executes a footstep sequence with a discontinuous crawl (walk) or trot.

    Typical use (one call per control tick)::

        ctl = WalkingController(model, WalkingConfig())
        ctl.set_footsteps(legs, xyz, 'walk', t_now)            # odom frame
        cmd = ctl.update(t_now, q_measured, dq_measured)       # -> JointCommand
        T_odom_base = ctl.odom_pose                             # dead reckoning
        if ctl.capture_due(t_now): ...                          # ask for a stereo picture

    Attributes:
        status: 'idle' (not initialised), 'standing', 'walking'.
        last_error: reason the last plan or step was rejected ('' if none).
        T_map_odom: latest ICP correction (identity until :meth:`apply_correction`).
    """

    def __init__(self, model: RobotModel, config: WalkingConfig = WalkingConfig(),
                 height: gaitlib.HeightFn = None) -> None:
        self.model = model
        self.config = config
        c = config
        self.swing_s = c.swing_duration_s or model.swing_duration_s
        self.shift_s = c.shift_duration_s or model.shift_duration_s
        self.margin_m = c.stability_margin_m or model.stability_margin_m
        self.clearance_m = c.terrain_clearance_m or 0.5 * model.swing_height_m
        self.height = height
        self.T_map_odom = np.eye(4)
        self.status = 'idle'
        self.last_error = ''
        self._feet = None          # (4, 3) contact points (odom)
        self._body = None          # (x, y, z, yaw, pitch, roll) at rest (odom)
        self._queue: list = []
        self._queue_in_map = False      # pending footsteps were given in map
        self._plan_t = -np.inf
        self._seg: Optional[_Segment] = None
        self._still_since = -np.inf
        self._last_capture = -np.inf
        self._q_last = None
        self._t = 0.0
        self._pending_swing: Optional[_Step] = None
        self._last_legs: tuple = ()          # legs of the latest swing started
        self._recentred_at = -1    # steps_done at the last recentring
        self._phi_ref = None       # (4, 2) shank pitch and roll angles when the contact was set
        self.steps_done = 0
        self.last_margin_m = np.nan
        self.foot_loads = np.full(4, np.nan)   # estimated vertical foot forces [N]
        self._load_count = np.zeros(4, dtype=int)
        self._touch_count = np.zeros(4, dtype=int)
        self._hanging_count = np.zeros(4, dtype=int)
        self._extend = np.zeros(4)        # hanging stance feet lowered since the segment began
        self._extend_sum = np.zeros(4)    # ... and since each foot's last swing or probe
        self._extend_t = np.nan
        self._q_meas: Optional[np.ndarray] = None
        self._loaded: Optional[np.ndarray] = None   # (4,) bool, None without torques
        self._probe_legs: tuple = ()
        self._verify = None     # (legs, until [s], extra depth (4,)) after a swing
        self.touchdowns = {'early': 0, 'probed': 0, 'not_found': 0, 'reanchored': 0,
                           'extended': 0, 'hanging_after_swing': 0}
        self._reanchor_checked = None   # stance last checked by _reanchor_feet
        self._R_tilt: Optional[np.ndarray] = None   # measured base tilt (yaw removed)
        self._dry = False          # check_footsteps: segments without joint splines
        # check_footsteps only (map and frames fixed for the controller's life): results of
        # _belly_z, _body_z and the current stance's shank depth by their exact inputs
        self._memo: Optional[dict] = None
        self.last_ik_reasons: tuple = ()

    # -- inputs ---------------------------------------------------------------------------
    def reset(self, t: float, q: Optional[np.ndarray] = None,
              T_odom_base: Optional[np.ndarray] = None) -> None:
        """(Re)initialise at time ``t`` [s] from measured joint angles (default: standing).

        The stance feet are placed by FK of ``q`` from the body pose ``T_odom_base``
        (default: identity, i.e. the odom frame starts at the body). The body is taken level.
        """
        m = self.model
        q = kinematics.standing_joint_angles(m) if q is None else \
            np.asarray(q, dtype=float).reshape(4, 3)
        if not np.all(np.isfinite(q)):
            raise ValueError('reset: joint angles contain NaN')
        T = np.eye(4) if T_odom_base is None else np.asarray(T_odom_base, dtype=float)
        yaw = float(np.arctan2(T[1, 0], T[0, 0]))
        T_level = make_T(rot_z(yaw), T[:3, 3])
        feet = transform_points(T_level, kinematics.forward(m, q))
        feet[:, 2] -= m.foot_radius_m
        self._feet = feet
        self._phi_ref = _shank_angles(q)
        self._body = np.array([T[0, 3], T[1, 3], T[2, 3], yaw, 0.0, 0.0])
        self._seg = None
        self._pending_swing = None
        self._verify = None
        self._extend = np.zeros(4)
        self._extend_sum = np.zeros(4)
        self._recentred_at = -1
        self._queue = []
        self._t = float(t)
        self._still_since = float(t)
        self._q_last = q.reshape(12)
        self.status = 'standing'

    def set_height_map(self, height: gaitlib.HeightFn) -> None:
        """Terrain for swing clearance: callable ``xy (N, 2) -> z (N,)`` or GridMap (map frame)."""
        self.height = height

    def apply_correction(self, T_map_odom: np.ndarray) -> None:
        """Re-anchor dead reckoning: the latest ICP estimate of ``T_map_odom`` (4x4)."""
        T = np.asarray(T_map_odom, dtype=float)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise ValueError(f'T_map_odom must be a finite 4x4 matrix, got shape {T.shape}')
        R = T[:3, :3]
        if np.abs(R.T @ R - np.eye(3)).max() > 1e-3 or abs(np.linalg.det(R) - 1.0) > 1e-3:
            raise ValueError('T_map_odom rotation is not orthonormal')
        if self._queue_in_map and self._queue:
            # Footsteps given in map stay where they are in the map: the pending ones were
            # converted with the previous correction; move them by the change.
            delta = invert(T) @ self.T_map_odom
            self._queue = [_Step(s.legs, transform_points(delta, s.targets), s.gait)
                           for s in self._queue]
        self.T_map_odom = T.copy()

    def set_footsteps(self, legs: np.ndarray, positions: np.ndarray, gait: str, t: float,
                      frame: str = 'odom') -> None:
        """Replace the pending footsteps (the step in progress finishes first).

        Args:
            legs: ``(N,)`` leg indices (LF=0, RF=1, LH=2, RH=3) in execution order.
            positions: ``(N, 3)`` contact points [m] in ``frame``.
            gait: 'walk' (one leg at a time), 'trot' (consecutive diagonal pairs) or 'stand'.
            t: time the plan was received / made [s] (for ``plan_timeout_s``).
            frame: 'odom' or 'map' (converted with the current ``T_map_odom``; a later
                :meth:`apply_correction` moves the pending ones so that they stay at their
                map positions; the step in progress keeps its target).

        Raises ValueError (and keeps the previous plan) on malformed input.
        """
        legs = np.asarray(legs, dtype=int).reshape(-1)
        pos = np.asarray(positions, dtype=float).reshape(-1, 3)
        if len(legs) != len(pos):
            raise ValueError(f'{len(legs)} legs but {len(pos)} positions')
        if np.any((legs < 0) | (legs > 3)):
            raise ValueError(f'leg indices must be 0..3, got {sorted(set(legs.tolist()))}')
        if not np.all(np.isfinite(pos)):
            raise ValueError('footstep positions contain NaN or inf')
        if gait not in ('walk', 'trot', 'stand'):
            raise ValueError(f"gait must be 'walk', 'trot' or 'stand', got {gait!r}")
        if frame == 'map':
            pos = transform_points(invert(self.T_map_odom), pos)
        elif frame != 'odom':
            raise ValueError(f"frame must be 'odom' or 'map', got {frame!r}")
        steps = []
        if gait == 'trot':
            if len(legs) % 2:
                raise ValueError('trot footsteps come in diagonal pairs; got an odd count')
            for k in range(0, len(legs), 2):
                pair = tuple(sorted((int(legs[k]), int(legs[k + 1]))))
                if pair not in [tuple(sorted(p)) for p in gaitlib.TROT_PAIRS]:
                    raise ValueError(f'trot step {k // 2} pairs {LEG_NAMES[pair[0]]} and '
                                     f'{LEG_NAMES[pair[1]]}, not a diagonal')
                steps.append(_Step((int(legs[k]), int(legs[k + 1])), pos[k:k + 2], 'trot'))
        elif gait == 'walk':
            steps = [_Step((int(lg),), p[None], 'walk') for lg, p in zip(legs, pos)]
        self._queue = steps
        self._queue_in_map = frame == 'map'
        self._plan_t = float(t)
        self.last_error = ''

    def clear_plan(self) -> None:
        """Drop the pending footsteps (the step in progress finishes)."""
        self._queue = []

    # -- main tick ------------------------------------------------------------------------
    def update(self, t: float, q: Optional[np.ndarray] = None,
               dq: Optional[np.ndarray] = None,
               tau: Optional[np.ndarray] = None,
               attitude: Optional[np.ndarray] = None) -> JointCommand:
        """Joint targets at time ``t`` [s]; ``q``/``dq``/``tau`` (12,) measured joint angles,
        rates and motor torques, ``attitude`` the measured base orientation (3x3, in any
        gravity-aligned frame, e.g. the IMU's); all optional.

        The first call initialises the stance from ``q`` if :meth:`reset` was not called.
        With torques, each foot's ground force is estimated (:func:`kinematics.foot_forces`)
        and touchdown is sensed: a swing that meets the ground early ends there, and a foot
        that should carry weight but does not (after its swing, or before another leg lifts)
        is lowered slowly until it does (``probe``). Without them feet land at the planned
        heights. With ``attitude``, each body shift levels the body: the stance feet heights
        are re-estimated from the commanded leg geometry seen through the measured tilt
        (``attitude_gain``).
        """
        t = float(t)
        if self._feet is None:
            self.reset(t, q)
        self._t = t
        self._sense(q, tau, dq)
        self._R_tilt = None
        if attitude is not None:
            R = np.asarray(attitude, dtype=float).reshape(3, 3)
            if np.all(np.isfinite(R)):
                self._R_tilt = rot_z(-float(np.arctan2(R[1, 0], R[0, 0]))) @ R
                if self._body is not None:
                    # what the levelling corrects is the tilt beyond the commanded one
                    self._R_tilt = self._R_tilt @ gaitlib.pose_to_T(
                        np.r_[0.0, 0.0, 0.0, 0.0, self._body[4:6]])[:3, :3].T
        while self._seg is not None and t >= self._seg.t_end:
            self._finish_segment()
            self._seg = self._next_segment(max(t, self._t))
        if self._seg is not None and self._touched_down(t):
            self._cut_segment(t)
            self._seg = self._next_segment(t)
        if self._seg is None:
            self._seg = self._next_segment(t)
        self._update_still(t, dq)
        if self._seg is None:
            self.status = 'standing'
            qs = self._stand_q()
            ext = self._extension_dq(qs, self._update_extension(t, qs))
            return JointCommand(self._clip(qs + ext) if ext is not None else qs, np.zeros(12))
        self.status = 'walking'
        pos, vel = self._seg.joints(t - self._seg.t0)
        ext = self._extension_dq(pos, self._update_extension(t, pos))
        if ext is not None:
            pos = pos + ext
        return JointCommand(self._clip(pos), vel)

    def preview(self, times: np.ndarray) -> JointCommand:
        """Joint targets ``(P, 12)`` at future times [s] without advancing the controller.

        Within the segment in progress they follow its spline; after its end they hold its
        final angles (segments start and end at rest, so the next one continues from there).
        Call after :meth:`update` for the current time.
        """
        times = np.asarray(times, dtype=float).reshape(-1)
        if self._seg is None:
            q = self._stand_q()
            ext = self._extension_dq(q)
            if ext is not None:
                q = self._clip(q + ext)
            return JointCommand(np.tile(q, (len(times), 1)), np.zeros((len(times), 12)))
        pos, vel = self._seg.joints_many(times - self._seg.t0)
        vel[times >= self._seg.t_end] = 0.0
        ext = self._extension_dq(pos[0]) if len(pos) else None
        if ext is not None:
            # (the segment's swing and probe legs are never extended)
            pos = pos + ext
        return JointCommand(self._clip(pos), vel)

    def _clip(self, q: np.ndarray) -> np.ndarray:
        # The IK knots respect the limits; the spline between knots may overshoot by a hair.
        return np.clip(q, self.model.joint_lower, self.model.joint_upper)

    # -- outputs --------------------------------------------------------------------------
    @property
    def odom_pose(self) -> np.ndarray:
        """``T_odom_base`` (4x4): dead reckoning along the desired body trajectory."""
        return gaitlib.pose_to_T(self._body_now())

    @property
    def map_pose(self) -> np.ndarray:
        """``T_map_base`` = ``T_map_odom @ T_odom_base``."""
        return self.T_map_odom @ self.odom_pose

    def odom_velocity(self) -> tuple:
        """Desired body ``(v (3,), w (3,))`` in odom [m/s, rad/s] at the last update time."""
        if self._seg is None or not self._seg.moves_body:
            return np.zeros(3), np.zeros(3)
        h = 1e-3
        tau = np.clip(self._t - self._seg.t0, 0.0, self._seg.duration)
        a = self._seg.body_fn(max(tau - h, 0.0))
        b = self._seg.body_fn(min(tau + h, self._seg.duration))
        dt = min(tau + h, self._seg.duration) - max(tau - h, 0.0)
        d = (b - a) / dt if dt > 0 else np.zeros(6)
        return d[:3], np.array([d[5], d[4], d[3]])

    @property
    def feet(self) -> np.ndarray:
        """``(4, 3)`` current stance contact points (odom); swing feet at their lift-off point."""
        return None if self._feet is None else self._feet.copy()

    @property
    def phase(self) -> Optional[Phase]:
        """Segment in progress, None when standing (a pending verification counts: the
        robot is not done with the step until it knows where the swung foot is)."""
        seg = self._seg
        if seg is None and self._verify is not None:
            legs, until, _ = self._verify
            d = self.config.touchdown_verify_s
            return Phase('verify', legs, until - d, d)
        return None if seg is None else Phase(seg.kind, seg.legs, seg.t0, seg.duration)

    def upcoming_stance(self) -> tuple:
        """``(feet (4, 3) odom, next_leg)``: where the feet will stand once the step in
        progress (its body shift and swing) is done, and the leg after it in the crawl order
        (None before the first step or after a trot pair). A new plan should start here:
        :meth:`set_footsteps` lets the step in progress finish."""
        if self._feet is None:
            return None, None
        feet = self._feet.copy()
        last = self._last_legs
        seg = self._seg
        if seg is not None and seg.kind == 'swing':
            feet[list(seg.legs)] = seg.feet_end[list(seg.legs)]
            last = seg.legs
        if self._pending_swing is not None:
            step = self._pending_swing
            feet[list(step.legs)] = step.targets
            last = step.legs
        if not last or len(last) != 1:
            return feet, None
        order = list(gaitlib.CRAWL_ORDER)
        return feet, order[(order.index(int(last[0])) + 1) % 4]

    def upcoming_body(self) -> Optional[np.ndarray]:
        """``T_odom_base`` (4x4) the next step starts from: the body pose at the end of the
        step in progress (the segment under way; a swing or probe holds the body where the
        shift before it left it), the current one at rest. A dry run of the next plan
        (:func:`check_footsteps` with ``T_body``) starts here, as this controller will."""
        if self._body is None:
            return None
        body = self._body if self._seg is None else self._seg.body_end
        return gaitlib.pose_to_T(np.asarray(body, dtype=float))

    @property
    def pending_steps(self) -> int:
        """Footsteps (or trot pairs) not yet started."""
        return len(self._queue)

    def is_still(self, t: Optional[float] = None) -> bool:
        """Body held still (desired) for ``still_settle_s`` and stance joints slow."""
        t = self._t if t is None else float(t)
        return t - self._still_since >= self.config.still_settle_s

    def capture_due(self, t: float) -> bool:
        """True (once per still window, at most every ``capture_min_interval_s``) when a
        stereo picture should be taken now; records the capture."""
        if self.is_still(t) and t - self._last_capture >= self.config.capture_min_interval_s:
            self._last_capture = float(t)
            return True
        return False

    # -- internals ------------------------------------------------------------------------
    def _body_now(self) -> np.ndarray:
        if self._body is None:
            return np.zeros(6)
        if self._seg is None:
            return self._body.copy()
        tau = np.clip(self._t - self._seg.t0, 0.0, self._seg.duration)
        return self._seg.body_fn(tau)

    def _update_still(self, t: float, dq: Optional[np.ndarray]) -> None:
        seg = self._seg
        moving = seg is not None and seg.moves_body
        if not moving and dq is not None:
            speed = np.abs(np.asarray(dq, dtype=float).reshape(4, 3)).max(axis=1)
            if seg is not None:
                speed[list(seg.legs)] = 0.0
            moving = bool(speed.max() > self.config.still_joint_speed_rad_s)
        if moving:
            self._still_since = np.inf
        elif self._still_since == np.inf:
            self._still_since = t

    def _stand_q(self) -> np.ndarray:
        res = self._ik(gaitlib.pose_to_T(self._body), self._feet)
        if res is None:
            return self._q_last.copy()
        self._q_last = res.reshape(12)
        return self._q_last.copy()

    def _ik(self, T_odom_base: np.ndarray, feet_contact: np.ndarray) -> Optional[np.ndarray]:
        centres = np.array(feet_contact, dtype=float)
        centres[:, 2] += self.model.foot_radius_m
        r = kinematics.solve_ik(self.model, kinematics.feet_in_base(T_odom_base, centres))
        return r.q if r.all_ok else None

    def _finish_segment(self) -> None:
        seg = self._seg
        self._extend_sum[list(seg.legs)] = 0.0
        self._feet = seg.feet_end.copy()
        self._body = seg.body_end.copy()
        self._q_last = seg.q_end.copy() if seg.spline is None else seg.spline(seg.duration)
        self._phi_ref = _shank_angles(self._q_last.reshape(4, 3))
        if seg.kind == 'swing':
            self.steps_done += len(seg.legs)
        elif seg.kind == 'probe':
            self.touchdowns['not_found'] += 1
            self._step_error(f'{"+".join(LEG_NAMES[k] for k in seg.legs)} found no ground '
                             f'within the probe depth below its foothold')
            if self._pending_swing is not None:
                # a stance foot carries nothing: lifting another leg now would tip the robot
                self._pending_swing = None
                self._queue = []
                self.last_error += '; step cancelled, standing'
        self._schedule_probes(seg)

    # -- touchdown sensing ----------------------------------------------------------------
    def _sense(self, q, tau, dq) -> None:
        """Estimate the feet's vertical ground forces from the joint torques."""
        thr = self.config.contact_force_n
        if q is None or tau is None or thr <= 0.0:
            self._loaded = None
            return
        q = np.asarray(q, dtype=float).reshape(4, 3)
        tau = np.asarray(tau, dtype=float).reshape(4, 3)
        if not (np.all(np.isfinite(q)) and np.all(np.isfinite(tau))):
            self._loaded = None
            return
        # base-frame z: the controller keeps the body level, so this is the vertical force
        J = kinematics.jacobian(self.model, q)
        fz = kinematics.foot_forces(self.model, q, tau, J)[:, 2]
        self.foot_loads = fz
        self._q_meas = q
        above = np.nan_to_num(fz, nan=0.0) > thr
        if dq is not None:
            dq = np.asarray(dq, dtype=float).reshape(4, 3)
            vz = np.einsum('kj,kj->k', J[:, 2, :], dq)
            above &= ~(vz < -self.config.contact_max_descent_m_s)
        self._load_count = np.where(above, self._load_count + 1, 0)
        self._loaded = self._load_count >= self.config.contact_ticks
        self._supporting = np.nan_to_num(fz, nan=-np.inf) > self.config.support_force_n
        touching = np.nan_to_num(fz, nan=-np.inf) > self.config.probe_contact_force_n
        self._touch_count = np.where(touching, self._touch_count + 1, 0)
        hanging = np.nan_to_num(fz, nan=np.inf) < self.config.hanging_force_n
        self._hanging_count = np.where(hanging, self._hanging_count + 1, 0)

    # -- hanging stance feet -------------------------------------------------------------
    def _update_extension(self, t: float, q: np.ndarray) -> Optional[np.ndarray]:
        """Lower every hanging stance foot (not swinging, not probing) by
        ``stance_extend_m_s`` since the last tick, as long as the leg at the commanded angles
        ``q`` (12,) is not near full stretch. Returns the legs' Jacobians at ``q`` if it
        computed them (for :meth:`_extension_dq` at the same angles), else None."""
        c = self.config
        dt = t - self._extend_t
        self._extend_t = t
        if c.stance_extend_m_s <= 0.0 or self._loaded is None or not 0.0 < dt < 0.2:
            return None
        moving = self._seg.legs if self._seg is not None else ()
        J = None
        for k in range(4):
            room = c.max_stance_extend_m - self._extend_sum[k] - self._extend[k]
            if k in moving or self._hanging_count[k] < c.contact_ticks or room <= 0.0:
                continue
            e = self._extend[k] + min(c.stance_extend_m_s * dt, room)
            if J is None:
                J = kinematics.jacobian(self.model, np.asarray(q, dtype=float).reshape(4, 3))
            # a leg near full stretch needs large joint motions to lower its foot (and cannot
            # at all when straight): more than 0.03 rad per mm (mid-range: ~0.01)
            if abs(np.linalg.det(J[k])) < 1e-9 or np.abs(np.linalg.solve(
                    J[k], [0.0, 0.0, -1e-3])).max() > 0.03:
                continue
            if self._extend[k] == 0.0 and self._extend_sum[k] == 0.0:
                self.touchdowns['extended'] += 1
            self._extend[k] = e
        return J

    def _extension_dq(self, q: np.ndarray, J: Optional[np.ndarray] = None
                      ) -> Optional[np.ndarray]:
        """(12,) joint change lowering the feet by ``_extend`` along the base's z at angles
        ``q`` (linearised: millimetres), or None. ``J``: the legs' Jacobians at ``q`` if the
        caller has them."""
        if not np.any(self._extend > 0.0):
            return None
        if J is None:
            J = kinematics.jacobian(self.model, np.asarray(q, dtype=float).reshape(4, 3))
        dq = np.zeros((4, 3))
        for k in np.nonzero(self._extend > 0.0)[0]:
            try:
                dq[k] = np.linalg.solve(J[k], [0.0, 0.0, -self._extend[k]])
            except np.linalg.LinAlgError:
                continue
        if not np.all(np.isfinite(dq)) or np.abs(dq).max() > 0.3:
            return None
        return dq.reshape(12)

    def _absorb_extension(self) -> None:
        """The lowered feet become the believed stance the next segment starts from."""
        if not np.any(self._extend > 0.0):
            return
        dq = self._extension_dq(self._q_last) if self._q_last is not None else None
        self._feet[:, 2] -= self._extend
        self._extend_sum += self._extend
        if dq is not None:
            self._q_last = np.asarray(self._q_last, dtype=float).reshape(12) + dq
        self._extend = np.zeros(4)

    def _touched_down(self, t: float) -> bool:
        """The segment in progress should end now: its moving feet met the ground."""
        seg, loaded = self._seg, self._loaded
        if loaded is None or not seg.legs:
            return False
        legs = list(seg.legs)
        if seg.kind == 'probe':
            return bool((self._touch_count[legs] >= self.config.contact_ticks).all())
        if seg.kind == 'swing' and t - seg.t0 >= self.config.early_touchdown_fraction \
                * (seg.duration - seg.approach_s) and t < seg.t_end and loaded[legs].all():
            # Higher than the foothold by more than the map can be wrong: not the ground
            # under the foothold but a shank or the foot meeting an obstacle on the way.
            above = seg.feet_at(t - seg.t0)[legs, 2] - seg.feet_end[legs, 2]
            if np.any(above > self.config.early_touchdown_max_above_m):
                return False
            self.touchdowns['early'] += 1
            return True
        return False

    def _cut_segment(self, t: float) -> None:
        """End the segment in progress at ``t``: the feet and body stay where they are."""
        seg = self._seg
        self._extend_sum[list(seg.legs)] = 0.0
        tau = min(max(t - seg.t0, 0.0), seg.duration)
        self._feet = seg.feet_at(tau)
        self._body = np.asarray(seg.body_fn(tau), dtype=float).copy()
        self._q_last = seg.joints(tau)[0]
        self._phi_ref = _shank_angles(self._q_last.reshape(4, 3))
        if seg.kind == 'swing':
            self.steps_done += len(seg.legs)
            self._schedule_verify(seg, t)
        elif seg.kind == 'probe':
            self.touchdowns['probed'] += 1
        self._schedule_probes(seg)

    def _schedule_verify(self, seg: _Segment, t: float) -> None:
        """After a swing cut by a touchdown more than ``max_stance_extend_m`` above its
        foothold (further than lowering a hanging stance foot reaches): check the swung feet
        once the body has held still ``touchdown_verify_s`` (:meth:`_next_segment`); a foot
        that hangs may have to go down that much further.

        Swings run to their end are not checked: a foot that has just landed carries little
        and can read below ``hanging_force_n`` while it touches (flat ground: 4 probes in 12
        steps, each pressing a foot into the ground, the body rising against the believed
        heights until a swing passed over a 2 cm slab under its foothold)."""
        c = self.config
        if c.touchdown_verify_s <= 0.0 or self._loaded is None:
            return
        extra = np.maximum(self._feet[:, 2] - seg.feet_end[:, 2], 0.0)
        if extra[list(seg.legs)].max() <= c.max_stance_extend_m:
            return
        self._verify = (tuple(seg.legs), t + c.touchdown_verify_s, extra)

    def _verified_probe(self, t0: float):
        """None while the body holds still after a swing, then a probe of the swung feet
        that hang (or False: nothing to probe)."""
        legs, until, extra = self._verify
        if t0 < until:
            return None
        self._verify = None
        hanging = tuple(k for k in legs if self._hanging_count[k] >= self.config.contact_ticks)
        if not hanging:
            return False
        self.touchdowns['hanging_after_swing'] += 1
        return self._make_probe(hanging, t0, float(extra[list(hanging)].max())) or False

    def _schedule_probes(self, seg: _Segment) -> None:
        """Before a swing (the body has shifted) the other three feet must carry weight.

        Not checked right after a swing: the landed foot carries little until the next shift
        moves the COG towards it, so its load cannot tell touching from hanging. (Probing it
        anyway was tried: each probe leaves the leg pressed a few mm into the ground, the body
        rises against the dead-reckoned heights and the next feet hang - a runaway.)
        """
        self._probe_legs = ()
        if self._loaded is None or self.config.probe_depth_m <= 0.0:
            return
        if seg.kind == 'shift' and self._pending_swing is not None:
            self._probe_legs = tuple(k for k in range(4) if k not in self._pending_swing.legs
                                     and not self._supporting[k])


    def _make_probe(self, legs: tuple, t0: float, extra_m: float = 0.0) -> Optional[_Segment]:
        """Lower ``legs`` slowly (body still) by up to ``probe_depth_m`` (plus ``extra_m``);
        shallower if the full depth is out of reach."""
        c = self.config
        feet0, body = self._feet.copy(), self._body.copy()
        rolling = np.ones(4, dtype=bool)
        rolling[list(legs)] = False
        for depth in (extra_m + c.probe_depth_m, extra_m + 0.6 * c.probe_depth_m,
                      extra_m + 0.3 * c.probe_depth_m):
            dur = max(depth / c.probe_speed_m_s, 2.0 * c.knot_dt_s)

            def feet_fn(tau, depth=depth, dur=dur):
                f = np.broadcast_to(feet0, np.shape(tau) + (4, 3)).copy()
                s = np.clip(np.asarray(tau) / dur, 0.0, 1.0)
                for leg in legs:
                    f[..., leg, 2] = feet0[leg, 2] - depth * s
                return f

            def body_fn(tau):
                return np.broadcast_to(body, np.shape(tau) + body.shape).copy() \
                    if np.ndim(tau) else body.copy()

            seg = self._build(t0, dur, 'probe', body_fn, feet_fn, rolling)
            if seg is not None:
                seg.feet_end = feet_fn(dur) + seg.roll_end
                seg.body_end = body
                seg.legs = tuple(legs)
                seg.moves_body = False
                return seg
        return None

    def _reanchor_feet(self) -> None:
        """Make the believed stance a valid start for the next segment.

        Every segment starts from the believed ``(_body, _feet)``, its stance feet rolled from
        ``_phi_ref``. If that first knot is out of reach, every new segment fails there
        ('pose 0') and the robot refuses every step from then on. Two ways it happened: the
        stance itself a fraction of a millimetre past a fully stretched leg (closed-loop run
        L): the feet are put where the last commanded angles (a valid configuration) hold
        them; or the stance in reach but ``_phi_ref`` stale (a ground-truth walk): the roll is
        restarted from the angles the stance is solved at."""
        if self._feet is None or self._body is None or self._q_last is None:
            return
        # Standing asks for a next segment at every tick; the check (four IK calls, ~0.4 ms,
        # most of a standing tick) is only needed when the stance it checks has changed.
        key = (self._body.tobytes(), self._feet.tobytes(), np.asarray(self._q_last).tobytes(),
               None if self._phi_ref is None else self._phi_ref.tobytes())
        if key == self._reanchor_checked:
            return
        self._reanchor_checked = key
        T = gaitlib.pose_to_T(self._body)
        q0 = self._ik(T, self._feet)
        if q0 is not None:
            # In reach; but a segment's knots roll the feet from the shank angles _phi_ref,
            # kept since the previous segment ended. When the stance was re-solved at other
            # angles (0.007 rad off in a rocks walk, seed 7), the first knot's target moves by
            # that roll (67 um there), past the reach of a fully stretched leg: every segment
            # then fails at 'pose 0'. Roll from the angles the stance is solved at instead.
            if self._phi_ref is not None:
                # the fixed-point iteration of _build at its first knot
                yaw = np.array([self._body[3]])
                q = q0
                for _ in range(3):
                    roll = self._rolling(q.reshape(1, 4, 3), np.cos(yaw), np.sin(yaw))[0]
                    q = self._ik(T, self._feet + roll)
                    if q is None:
                        self._phi_ref = _shank_angles(q0.reshape(4, 3))
                        self.touchdowns['reanchored'] += 1
                        break
            return
        q = np.asarray(self._q_last, dtype=float).reshape(4, 3)
        if not np.all(np.isfinite(q)):
            return
        feet = transform_points(T, kinematics.forward(self.model, q))
        feet[:, 2] -= self.model.foot_radius_m
        if np.abs(feet - self._feet).max() > 0.01:
            return   # not a hair past the reach: the belief is wrong in a way FK cannot mend
        self._feet = feet
        self.touchdowns['reanchored'] += 1

    def _next_segment(self, t0: float) -> Optional[_Segment]:
        self._absorb_extension()
        self._reanchor_feet()
        if self._verify is not None:
            seg = self._verified_probe(t0)
            if seg is None:
                return None          # holding still: is the swung foot on the ground?
            if seg is not False:
                return seg
        if self._probe_legs:
            legs, self._probe_legs = self._probe_legs, ()
            seg = self._make_probe(legs, t0)
            if seg is not None:
                return seg
        if self._pending_swing is not None:
            step = self._pending_swing
            self._pending_swing = None
            return self._make_swing(step, t0)
        if self._queue and t0 - self._plan_t <= self.config.plan_timeout_s:
            step = self._queue.pop(0)
            seg = self._make_shift(step, t0)
            if seg is None:
                self._queue = []
                return self._recenter(t0)
            self._pending_swing = step
            if seg.duration <= 0:
                self._pending_swing = None
                return self._make_swing(step, t0)
            return seg
        if self._queue:
            self.last_error = (f'plan is older than plan_timeout_s={self.config.plan_timeout_s}'
                               f' s; standing')
            self._queue = []
        return self._recenter(t0)

    def _goal_pose(self, feet: np.ndarray) -> np.ndarray:
        """Nominal body ``(x, y, z, yaw, pitch, roll)`` over ``feet``: level, or tilted with
        the feet's plane by ``body_tilt_gain``."""
        goal = gaitlib.body_pose_from_feet(feet, self.model.standing_height_m)
        c = self.config
        pitch, roll = gaitlib.body_tilt_from_feet(self._tilt_feet(feet), float(goal[3]),
                                                  c.body_tilt_gain,
                                                  np.radians(c.max_body_tilt_deg))
        return np.r_[goal, pitch, roll]

    def _tilt_feet(self, feet: np.ndarray) -> np.ndarray:
        """``feet`` (odom) with each height capped at ``tilt_map_tolerance_m`` above the
        height map under the foot, where the map knows it (what the body tilt follows)."""
        if self.config.body_tilt_gain <= 0.0 or self.height is None:
            return feet
        in_map = transform_points(self.T_map_odom, feet)
        ground = gaitlib.terrain_height(self.height, in_map[:, :2])
        cap = ground - (in_map[:, 2] - feet[:, 2]) + self.config.tilt_map_tolerance_m
        out = np.array(feet, dtype=float)
        known = np.isfinite(cap)
        out[known, 2] = np.minimum(out[known, 2], cap[known])
        return out

    def _shift_body(self, goal: np.ndarray, support: np.ndarray, margin: float, legs,
                    targets: np.ndarray, names: str, fore_aft: bool = False):
        """The body pose for the shift before swinging ``legs`` to ``targets``: the goal pose
        moved so that the COG keeps ``margin`` inside ``support`` during the whole swing (its
        feet sampled along :meth:`_swing_trajectory`), with every foot in reach; ``(body,
        poses, full_shift)``, or None (``last_error`` says why) if no pose reaches them."""
        m = self.model
        body = goal.copy()
        # Feet along the coming swing: the COG must keep the margin during all of it.
        taus = np.linspace(0.0, 1.0, 13)
        poses = np.repeat(self._feet[None], len(taus), axis=0)
        for k, leg in enumerate(legs):
            sw = self._swing_trajectory(self._feet[leg], targets[k],
                                        self._apex(self._feet[leg], targets[k]), 1.0, leg,
                                        fore_aft=fore_aft)
            poses[:, leg] = sw.position(taus * sw.total_s)
        nominal_off = transform_points(gaitlib.pose_to_T(goal),
                                       _standing_com(m)[None])[0, :2] - goal[:2]
        mean, extra = nominal_off, 0.0
        for _ in range(3):
            body[2] = self._body_z(goal[2], body, poses, legs)
            offs = self._com_offsets(body, poses)
            if offs is not None:
                mean = 0.5 * (offs.min(axis=0) + offs.max(axis=0))
                extra = float(np.linalg.norm(offs - mean, axis=1).max())
            cog, got = gaitlib.project_into_support(goal[:2] + mean, support, margin + extra)
            body[:2] = cog - mean
        body[2] = self._body_z(goal[2], body, poses, legs)
        full_shift = True
        if not self._reachable(body, poses):
            full_shift = False
            # The full COG shift puts a foot out of reach (e.g. past the abduction limit):
            # shift less, towards the nominal body pose, as long as a margin remains.
            for alpha in (0.2, 0.4, 0.6, 0.8, 1.0):
                cand = body.copy()
                cand[:2] = body[:2] + alpha * (goal[:2] - body[:2])
                cand[2] = self._body_z(goal[2], cand, poses, legs)
                if self._reachable(cand, poses):
                    body = cand
                    break
            else:
                self._step_error(f'no body pose keeps every foot in reach while stepping '
                                 f'{names}: ' + '; '.join(self.last_ik_reasons[:2]))
                return None
        return body, poses, full_shift

    def _recenter(self, t0: float) -> Optional[_Segment]:
        """Shift the body back over its feet once the plan is exhausted: once per stance.

        The shift levels the body on the measured tilt (``attitude_gain``), which changes the
        feet's believed heights and so the next goal pose: recentring again on the same feet
        would level again on a tilt read while the body still rocks from the last shift, a
        loop that can go on (11 recentrings in a row on one stance in a rocks walk) and keeps
        the body rocking. So it recentres once per count of executed steps. (A step cancelled
        after its body shift, when the body was already recentred at that count, leaves the
        body where the shift put it, inside the support triangle, until the next plan.)"""
        if not self.config.recenter or self._recentred_at == self.steps_done:
            return None
        goal = self._goal_pose(self._feet)
        # The nominal height, raised for the belly as a shift would be (within reach).
        goal[2] = self._body_z(goal[2], goal, self._feet[None], [])
        if np.linalg.norm(goal[:3] - self._body[:3]) < 2e-3 and \
                np.abs(goal[3:] - self._body[3:]).max() \
                < 2e-3:
            return None
        self._recentred_at = self.steps_done
        return self._shift_segment(goal, t0, legs_swing=())

    def _step_error(self, msg: str) -> None:
        self.last_error = msg

    def _com_offsets(self, body: np.ndarray, poses: np.ndarray) -> Optional[np.ndarray]:
        """COM minus body origin, world x-y ``(n, 2)``, for the robot at ``body`` on each foot
        pose of ``poses`` ``(n, 4, 3)``; None if a foot of any pose is out of reach."""
        T = gaitlib.pose_to_T(body)
        centres = np.array(poses, dtype=float)
        centres[..., 2] += self.model.foot_radius_m
        r = kinematics.solve_ik(self.model, kinematics.feet_in_base(T, centres))
        if not r.all_ok:
            self.last_ik_reasons = r.reasons
            return None
        com = transform_points(T, kinematics.com_base(self.model, r.q))
        return com[:, :2] - body[:2]

    def _make_shift(self, step: _Step, t0: float) -> Optional[_Segment]:
        m = self.model
        legs = list(step.legs)
        targets = np.array(step.targets, dtype=float)
        targets[:, 2] -= self.config.touchdown_depth_m
        d = np.linalg.norm(targets[:, :2] - self._feet[legs, :2], axis=1)
        if step.gait == 'trot' and np.any(
                d > self.config.trot_max_step_fraction * m.max_step_length_m + 1e-9):
            self._step_error(f'trot step of {LEG_NAMES[legs[int(np.argmax(d))]]} is '
                             f'{d.max():.3f} m, longer than {self.config.trot_max_step_fraction}'
                             f' x max_step_length_m; standing')
            return None
        if np.any(d > self.config.max_step_factor * m.max_step_length_m):
            self._step_error(f'step of {LEG_NAMES[legs[int(np.argmax(d))]]} is {d.max():.3f} m,'
                             f' longer than {self.config.max_step_factor} x max_step_length_m')
            return None
        after = self._feet.copy()
        after[legs] = targets
        goal = self._goal_pose(after)
        stay = [k for k in range(4) if k not in legs]
        support = self._feet[stay, :2]
        margin = self.margin_m if len(stay) >= 3 else 0.0
        names = "+".join(LEG_NAMES[k] for k in legs)
        found = self._shift_body(goal, support, margin, legs, targets, names)
        if found is None and self.config.swing_lift_fore_aft_m > 0.0:
            # The straight lift is out of reach (a foot far behind or ahead of its hip, e.g.
            # rocks-6cm ground-truth seed 0: LH 10 cm behind, every LH step refused here):
            # lift it along the step instead. Only then, so that ordinary strides keep the
            # straight lift (done always, it dragged the feet of flat strides that start
            # more than 5 cm behind the nominal place).
            first = self.last_error
            found = self._shift_body(goal, support, margin, legs, targets, names,
                                     fore_aft=True)
            if found is None:
                self.last_error = first
            else:
                step.lift_fore_aft = True
        if found is None:
            return None
        body, poses, full_shift = found
        offs = self._com_offsets(body, poses)
        got = float(gaitlib.support_margin(body[:2] + offs, support).min())
        if len(stay) >= 3 and got < self.config.min_margin_fraction * margin:
            self._step_error(f'stepping {names}: the COG margin would be {got:.4f} m, below '
                             f'{self.config.min_margin_fraction} x {margin} m with every foot '
                             f'in reach')
            return None
        mean = 0.5 * (offs.min(axis=0) + offs.max(axis=0))
        extra = float(np.linalg.norm(offs - mean, axis=1).max())
        seg = self._shift_segment(body, t0, legs_swing=legs)
        if seg is not None and len(stay) >= 3 and full_shift:
            # The stance feet roll a little during the shift: re-project onto the support
            # triangle they will really form.
            rolled = (self._feet + seg.roll_end)[stay, :2]
            cog, got2 = gaitlib.project_into_support(body[:2] + mean, rolled, margin + extra)
            if np.linalg.norm(cog - mean - body[:2]) > 1e-4:
                cand = body.copy()
                cand[:2] = cog - mean
                if self._reachable(cand, poses):
                    body = cand
                    seg = self._shift_segment(body, t0, legs_swing=legs)
        self.last_margin_m = got
        return seg

    def _reachable(self, body: np.ndarray, poses: np.ndarray) -> bool:
        """Every foot of every pose ``(n, 4, 3)`` reachable from the level body pose."""
        T = gaitlib.pose_to_T(body)
        centres = np.array(poses, dtype=float)
        centres[..., 2] += self.model.foot_radius_m
        r = kinematics.solve_ik(self.model, kinematics.feet_in_base(T, centres))
        if not r.all_ok:
            self.last_ik_reasons = r.reasons
            return False
        return self._shanks_clear(T, r.q) and self._belly_clear(body)

    def _belly_clear(self, body: np.ndarray) -> bool:
        """False (``last_ik_reasons`` says why) if the level body pose ``body`` holds its
        underside less than half of ``belly_clearance_m`` above the map and lower than the
        body now is below its own clearance height: the legs' reach capped the rise that
        :meth:`_body_z` asked for, and the belly would come down on the rock."""
        c = self.config
        need = self._belly_z(body)
        if not np.isfinite(need) or body[2] >= need - 0.5 * c.belly_clearance_m:
            return True
        if self._body is not None and need - body[2] <= self._belly_z(self._body) - \
                self._body[2] + 1e-3:
            return True
        gap = body[2] - (need - c.belly_clearance_m)
        self.last_ik_reasons = [f'belly {1000 * gap:.0f} mm above the terrain (the legs '
                                f'cannot lift the body {1000 * c.belly_clearance_m:.0f} mm '
                                'clear of it)']
        return False

    def _shank_depth(self, T: np.ndarray, q: np.ndarray) -> np.ndarray:
        """``(..., 4)`` how far each shank's axis dips below the height map [m] (negative: its
        clearance; -inf without a map) for the body pose ``T`` (4x4, odom) and joint angles
        ``q`` ``(..., 4, 3)``; sampled from the knee to where the foot sphere begins."""
        m = self.model
        lp = kinematics.leg_points(m, q)
        kn, ft = lp[..., 2, :], lp[..., 3, :]                  # knee, foot centre
        s = np.linspace(0.0, max(1.0 - 2.0 * m.foot_radius_m / m.shank_length_m, 0.0), 6)
        pts = kn[..., None, :] + s[:, None] * (ft - kn)[..., None, :]
        pts = transform_points(self.T_map_odom @ T, pts.reshape(-1, 3)).reshape(pts.shape)
        depth = gaitlib.terrain_height(self.height, pts[..., :2]) - pts[..., 2]
        return depth.max(axis=-1)

    def _shanks_clear(self, T: np.ndarray, q: np.ndarray) -> bool:
        """No shank of the poses ``q`` ``(n, 4, 3)`` at body pose ``T`` dips deeper than
        ``shank_max_penetration_m`` below the map and deeper than it does now (so a stance
        that already touches does not freeze the robot)."""
        tol = self.config.shank_max_penetration_m
        if tol < 0.0 or self.height is None or self._q_last is None:
            return True
        depth = self._shank_depth(T, q)
        key = None
        if self._memo is not None:
            key = ('shank', np.asarray(self._body, dtype=float).tobytes(),
                   np.asarray(self._q_last, dtype=float).tobytes())
            now = self._memo.get(key)
        if key is None or now is None:
            now = self._shank_depth(gaitlib.pose_to_T(self._body),
                                    np.asarray(self._q_last, dtype=float).reshape(4, 3))
            if key is not None:
                self._memo[key] = now
        bad = depth > np.maximum(tol, now + 0.002)
        if not bad.any():
            return True
        i, k = np.argwhere(bad)[0]
        self.last_ik_reasons = [f'pose {i} leg {LEG_NAMES[k]}: shank {1000 * depth[i, k]:.0f} mm '
                                f'into the terrain']
        return False

    def _body_z(self, z_nominal: float, body: np.ndarray, poses: np.ndarray, legs) -> float:
        """Body height for a swing: the nominal one, raised so the swing foot stays
        ``min_swing_hip_height`` below the hips and the belly ``belly_clearance_m`` above the
        map (:meth:`_belly_z`), and lowered so every foot stays in reach; if
        that is still not reachable everywhere (e.g. the abduction limit with a foot far out),
        the nearest height in +-4 cm at which every pose is reachable."""
        key = None
        if self._memo is not None:        # body[2] is not used
            b = np.asarray(body, dtype=float)
            key = ('body_z', np.float64(z_nominal).tobytes(), b[:2].tobytes(), b[3:].tobytes(),
                   np.asarray(poses, dtype=float).tobytes(), np.shape(poses), tuple(legs))
            z = self._memo.get(key)
            if z is not None:
                return z
        z = self._body_z_uncached(z_nominal, body, poses, legs)
        if key is not None:
            self._memo[key] = z
        return z

    def _body_z_uncached(self, z_nominal: float, body: np.ndarray, poses: np.ndarray,
                         legs) -> float:
        m = self.model
        z_min = float(poses[:, legs, 2].max()) + m.foot_radius_m + \
            self.config.min_swing_hip_height * m.standing_height_m if len(legs) else -np.inf
        z = min(max(z_nominal, z_min, self._belly_z(body)), self._max_body_z(body, poses))
        cands = z + np.array([0.0] + [s * k * 0.004 for k in range(1, 11) for s in (1, -1)])
        R = gaitlib.pose_to_T(body)[:3, :3]
        centres = np.array(poses, dtype=float)
        centres[..., 2] += m.foot_radius_m
        base = np.array([body[0], body[1], 0.0])
        local = (centres[None] - base - cands[:, None, None, None] * np.array([0, 0, 1.0])) @ R
        # The IK is per foot: the first height alone first (usually it reaches every pose).
        if kinematics.solve_ik(m, local[0], explain=False).all_ok:
            return float(cands[0])
        ok = kinematics.solve_ik(m, local, explain=False).ok.all(axis=(1, 2))
        return float(cands[int(np.argmax(ok))]) if ok.any() else z

    def _belly_z(self, body: np.ndarray) -> float:
        """Lowest body z (odom) keeping the underside of the body box ``belly_clearance_m``
        above the height map under it (level body at ``body``'s x, y, yaw; box sampled every
        ~2 cm); -inf without a map, with the check off or over unknown cells."""
        c = self.config
        if c.belly_clearance_m < 0.0 or self.height is None:
            return -np.inf
        key = None
        if self._memo is not None:
            key = ('belly_z', np.asarray(body, dtype=float)[[0, 1, 3]].tobytes())
            z = self._memo.get(key)
            if z is not None:
                return z
        thick = float(self.model.body_size_m[2])
        U, V = _belly_uv(self.model)
        cy, sy = np.cos(body[3]), np.sin(body[3])
        pts = np.stack([body[0] + cy * U - sy * V, body[1] + sy * U + cy * V,
                        np.zeros_like(U)], axis=-1)
        in_map = transform_points(self.T_map_odom, pts)
        ground = gaitlib.terrain_height(self.height, in_map[:, :2]) - in_map[:, 2]  # in odom
        z = float(ground.max()) + 0.5 * thick + c.belly_clearance_m
        if key is not None:
            self._memo[key] = z
        return z

    def _max_body_z(self, body: np.ndarray, feet_poses: np.ndarray) -> float:
        """Highest level-body z keeping every foot of ``feet_poses`` ``(n, 4, 3)`` within
        ``reach_fraction`` of the leg length from its hip-flexion origin."""
        m = self.model
        R = gaitlib.pose_to_T(body)[:3, :3]
        hips = m.leg_plane_offsets @ R.T + np.array([body[0], body[1], 0.0])
        centres = np.array(feet_poses, dtype=float)
        centres[..., 2] += m.foot_radius_m
        d2 = np.sum((centres[..., :2] - hips[:, :2]) ** 2, axis=-1)
        reach = self.config.reach_fraction * m.leg_length_m
        dz = np.sqrt(np.maximum(reach ** 2 - d2, 0.0))
        return float(np.min(centres[..., 2] + dz - hips[:, 2]))

    def _shift_segment(self, goal: np.ndarray, t0: float, legs_swing) -> Optional[_Segment]:
        start = self._body.copy()
        dyaw = (goal[3] - start[3] + np.pi) % (2 * np.pi) - np.pi
        delta = np.concatenate([goal[:3] - start[:3], [dyaw], goal[4:6] - start[4:6]])
        dur = self.shift_s * float(np.clip(np.linalg.norm(delta[:2]) / max(
            0.25 * self.model.body_move_per_period_m, 1e-6), 0.3, 1.0))
        feet0 = self._feet.copy()
        e = self.config.shift_zmp_offset_m
        if e > 0.0:
            h = max(float(start[2] - feet0[:, 2].mean()), 0.5 * self.model.standing_height_m)
            peak = 10.0 / np.sqrt(3.0) * float(np.linalg.norm(delta[:2]))   # a_max T^2
            dur = max(dur, float(np.sqrt(peak * h / (9.81 * e))))
        # Levelling only on four feet before a crawl swing (or at rest): the trot's body
        # rocks about the support diagonal, and correcting that rocking makes it worse.
        feet = self._levelled_feet() if len(legs_swing) <= 1 else feet0
        dz = feet[:, 2] - feet0[:, 2]

        def body_fn(tau, start=start, delta=delta, dur=dur):
            b, _ = gaitlib.min_jerk(np.asarray(tau) / dur)
            return start + np.multiply.outer(b, delta) if np.ndim(tau) else start + b * delta

        def feet_fn(tau):
            # the tilt correction is blended in with the body motion
            b, _ = gaitlib.min_jerk(np.asarray(tau) / dur)
            f = np.broadcast_to(feet0, np.shape(tau) + (4, 3)).copy()
            f[..., 2] += np.multiply.outer(b, dz)
            return f

        seg = self._build(t0, dur, 'shift', body_fn, feet_fn)
        if seg is None:
            self._step_error('body shift leaves the legs\' reach: '
                             + '; '.join(self.last_ik_reasons[:2]))
            return None
        seg.feet_end = feet + seg.roll_end
        seg.body_end = start + delta
        seg.legs = ()
        return seg

    def _levelled_feet(self) -> np.ndarray:
        """Stance contact points with their heights re-estimated through the measured tilt.

        The commanded joint angles put the feet at ``FK(q)`` in the body frame; if the body is
        really tilted by ``R_tilt``, they stand at ``R_tilt FK(q)`` relative to it. Planning the
        next level-body motion on those heights levels the body (``attitude_gain`` of it).
        Heights only: the feet's x-y stay the dead-reckoned ones.
        """
        feet = self._feet.copy()
        g = self.config.attitude_gain
        if self._R_tilt is None or g <= 0.0 or self._q_last is None:
            return feet
        rel = kinematics.forward(self.model, self._q_last.reshape(4, 3))
        # feet relative to the body in a yaw-free level frame, as commanded (body tilt)
        rel = rel @ gaitlib.pose_to_T(np.r_[0.0, 0.0, 0.0, 0.0, self._body[4:6]])[:3, :3].T
        dz = (rel @ self._R_tilt.T)[:, 2] - rel[:, 2]
        if not np.all(np.isfinite(dz)):
            return feet
        feet[:, 2] += g * dz
        return feet

    def _swing_trajectory(self, p0, p1, apex: float, dur: float, leg: Optional[int] = None,
                          fore_aft: bool = False) -> gaitlib.SwingTrajectory:
        """The swing from ``p0`` to ``p1``; with ``swing_inward_lift``, a foot that moves
        towards the body's centre line makes that sideways part while it lifts: a foot standing
        far out cannot be lifted straight up (the hip's abduction limit; rocks-6cm seed 1 stalled
        60 s with RH 5 cm outside its nominal place and every RH step refused at lift-off).
        ``fore_aft`` (the shift asks for it only when the straight lift is out of reach): a foot
        ``leg`` standing more than ``swing_lift_fore_aft_m`` behind or ahead of its nominal
        place (along the body) also makes the part of its step beyond that while lifting."""
        c = self.config
        lift_xy = None
        if self._body is not None:
            yaw = float(self._body[3])
            side = np.array([-np.sin(yaw), np.cos(yaw)])
            ahead = np.array([np.cos(yaw), np.sin(yaw)])
            step = np.asarray(p1)[:2] - np.asarray(p0)[:2]
            lead = np.zeros(2)
            if c.swing_inward_lift:
                out0 = float((np.asarray(p0)[:2] - self._body[:2]) @ side)
                lat = float(step @ side)
                if lat * out0 < 0.0:           # the move's sideways part points inwards
                    lead += lat * side
            if fore_aft and c.swing_lift_fore_aft_m > 0.0 and leg is not None:
                # how far the foot stands behind (< 0: ahead of) its nominal place
                nominal = float(self.model.nominal_feet[leg][0])
                behind = nominal - float((np.asarray(p0)[:2] - self._body[:2]) @ ahead)
                along = float(step @ ahead)
                excess = abs(behind) - c.swing_lift_fore_aft_m
                if excess > 0.0 and along * behind > 0.0:
                    lead += np.sign(along) * min(excess, abs(along)) * ahead
            if np.any(lead):
                lift_xy = lead
        return gaitlib.SwingTrajectory(p0, p1, apex, dur, approach_m=c.swing_approach_m,
                                       approach_speed_m_s=c.swing_approach_speed_m_s,
                                       lift_xy=lift_xy)

    def _make_swing(self, step: _Step, t0: float) -> Optional[_Segment]:
        m = self.model
        legs = list(step.legs)
        targets = np.array(step.targets, dtype=float)
        targets[:, 2] -= self.config.touchdown_depth_m
        dur = self.swing_s * (self.config.trot_swing_fraction if step.gait == 'trot' else 1.0)
        apexes = [self._apex(self._feet[leg], targets[k]) for k, leg in enumerate(legs)]
        dur = max(dur, self._swing_time_for_speed(legs, targets, apexes))
        swings = []
        for k, leg in enumerate(legs):
            p0, p1 = self._feet[leg], targets[k]
            swings.append(self._swing_trajectory(p0, p1, apexes[k], dur, leg,
                                                 fore_aft=step.lift_fore_aft))
        approach = max(sw.approach_s for sw in swings)
        dur += approach
        body = self._body.copy()
        feet0 = self._feet.copy()

        def body_fn(tau):
            return np.broadcast_to(body, np.shape(tau) + body.shape).copy() if np.ndim(tau) \
                else body.copy()

        def feet_fn(tau):
            f = np.broadcast_to(feet0, np.shape(tau) + (4, 3)).copy()
            for leg, sw in zip(legs, swings):
                f[..., leg, :] = sw.position(tau)
            return f

        rolling = np.ones(4, dtype=bool)
        rolling[legs] = False
        seg = self._build(t0, dur, 'swing', body_fn, feet_fn, rolling)
        if seg is None:
            self._step_error(f'swing of {"+".join(LEG_NAMES[k] for k in legs)} leaves the '
                             f'leg\'s reach: ' + '; '.join(self.last_ik_reasons[:2]))
            self._queue = []
            return self._recenter(t0)
        after = feet0 + seg.roll_end
        after[legs] = targets
        seg.feet_end = after
        seg.body_end = body
        seg.legs = tuple(legs)
        seg.moves_body = False
        seg.approach_s = approach
        self._last_legs = tuple(legs)
        return seg

    def _swing_time_for_speed(self, legs, targets: np.ndarray, apexes) -> float:
        """Shortest swing [s] whose lift, traverse and lowering stay under
        ``swing_max_speed_m_s``; 0 when off."""
        vmax = self.config.swing_max_speed_m_s
        if vmax <= 0.0:
            return 0.0
        need = 0.0
        for k, leg in enumerate(legs):
            p0, p1 = self._feet[leg], np.asarray(targets[k], dtype=float)
            need = max(need, gaitlib.SwingTrajectory.duration_for_speed(
                max(apexes[k] - p0[2], apexes[k] - p1[2], 0.0),
                float(np.hypot(*(p1[:2] - p0[:2]))), vmax))
        return need

    def _apex(self, p0: np.ndarray, p1: np.ndarray) -> float:
        """Swing apex in odom z, clearing the (map-frame) terrain under the path.

        The traverse is level in odom; when ``T_map_odom`` has roll or pitch the map height of
        a level odom line varies linearly along it, so the apex is the higher of the odom
        heights of the map apex above the two ends (both then clear it)."""
        key = None
        if self._memo is not None:
            key = ('apex', np.asarray(p0, dtype=float).tobytes(),
                   np.asarray(p1, dtype=float).tobytes())
            z = self._memo.get(key)
            if z is not None:
                return z
        z = self._apex_uncached(p0, p1)
        if key is not None:
            self._memo[key] = z
        return z

    def _apex_uncached(self, p0: np.ndarray, p1: np.ndarray) -> float:
        T = self.T_map_odom
        a, b = transform_points(T, p0[None])[0], transform_points(T, p1[None])[0]
        apex_map = gaitlib.swing_apex(a, b, self.height, self.clearance_m,
                                      corridor_m=1.5 * self.model.foot_radius_m,
                                      min_lift_m=self.model.swing_height_m)
        ends = np.array([[a[0], a[1], apex_map], [b[0], b[1], apex_map]])
        return float(transform_points(invert(T), ends)[:, 2].max())

    def _build(self, t0: float, dur: float, kind: str, body_fn, feet_fn,
               rolling: Optional[np.ndarray] = None) -> Optional[_Segment]:
        """Sample the Cartesian motion, IK every knot, spline the joints.

        Stance feet (``rolling`` True) roll on their spheres: the contact moves by
        ``r * (change of shank angle)`` (pure rolling), which the IK targets follow so that
        the PD does not fight the rolling (which would make the feet slip).
        """
        n = max(int(np.ceil(dur / self.config.knot_dt_s)), 2)
        taus = np.linspace(0.0, dur, n + 1)
        bodies = body_fn(taus)
        feet = feet_fn(taus)
        T = gaitlib.poses_to_T(bodies)
        c, s = np.cos(bodies[:, 3]), np.sin(bodies[:, 3])
        centres = feet.copy()
        centres[..., 2] += self.model.foot_radius_m
        rolling = np.ones(4, dtype=bool) if rolling is None else rolling
        roll = np.zeros_like(centres)
        for _ in range(4):
            local = np.einsum('nji,nkj->nki', T[:, :3, :3], centres + roll
                              - bodies[:, None, :3])
            res = kinematics.solve_ik(self.model, local)
            if not res.all_ok:
                self.last_ik_reasons = res.reasons
                return None
            roll = self._rolling(res.q, c, s) * rolling[:, None]
        q = res.q.reshape(len(taus), 12)
        # A dry run (check_footsteps) needs the checks and the end state, not the motion.
        spline = None if self._dry else CubicSpline(taus, q, axis=0, bc_type='clamped')
        seg = _Segment(kind=kind, t0=t0, duration=dur, spline=spline, body_fn=body_fn,
                       feet_end=None, body_end=None, feet_fn=feet_fn, knots=taus, roll=roll,
                       q_end=q[-1].copy())
        seg.roll_end = roll[-1]
        return seg

    def _rolling(self, q: np.ndarray, cos_yaw: np.ndarray, sin_yaw: np.ndarray) -> np.ndarray:
        """``(n, 4, 3)`` odom displacement of rolling spherical feet since ``_phi_ref``."""
        d = (_shank_angles(q) - self._phi_ref) * self.model.foot_radius_m
        dx, dy = d[..., 0], -d[..., 1]
        c, s = cos_yaw[:, None], sin_yaw[:, None]
        return np.stack([c * dx - s * dy, s * dx + c * dy, np.zeros_like(dx)], axis=-1)


def check_footsteps(model: RobotModel, config: WalkingConfig, feet: np.ndarray,
                    legs: np.ndarray, positions: np.ndarray, gait: str = 'walk',
                    height: gaitlib.HeightFn = None,
                    T_body: Optional[np.ndarray] = None) -> tuple:
    """Dry run of the controller's own feasibility checks: ``(n, reason)``, how many of the
    footsteps ``legs``/``positions`` it would execute from the stance ``feet`` (4, 3) (all in
    one frame) before refusing one, and why ('' if none is refused).

    The body starts at ``T_body`` (4x4, its x, y, z and heading), or at its nominal pose over
    ``feet`` (as after a recentring); if the feet are out of reach from there, at the nearest
    height within +-4 cm that reaches them (the controller crouches the same way). A planner
    can call it before publishing, so that its plans and the controller's stability and reach
    model agree (they are different models: the planner's body is a point at the COG).
    """
    feet = np.asarray(feet, dtype=float).reshape(4, 3)
    legs = np.asarray(legs, dtype=int).reshape(-1)
    positions = np.asarray(positions, dtype=float).reshape(-1, 3)
    ctl = WalkingController(model, config, height=height)
    ctl._dry = True
    ctl._memo = {}
    body = ctl._goal_pose(feet)
    if T_body is not None:
        T_body = np.asarray(T_body, dtype=float)
        body[:4] = [T_body[0, 3], T_body[1, 3], T_body[2, 3],
                    np.arctan2(T_body[1, 0], T_body[0, 0])]
    q = ctl._ik(gaitlib.pose_to_T(body), feet)
    if q is None:
        body[2] = ctl._body_z(body[2], body, feet[None], [])
        q = ctl._ik(gaitlib.pose_to_T(body), feet)
    if q is None:
        return 0, 'the stance itself is out of reach'
    ctl._feet, ctl._body, ctl._q_last = feet.copy(), body, q.reshape(12)
    ctl._phi_ref = _shank_angles(q.reshape(4, 3))
    try:
        ctl.set_footsteps(legs, positions, gait, 0.0)
    except ValueError as exc:
        return 0, str(exc)
    steps, done = list(ctl._queue), 0
    for step in steps:
        seg = ctl._make_shift(step, 0.0)
        if seg is None:
            return done, ctl.last_error
        ctl._seg = seg
        ctl._finish_segment()
        seg = ctl._make_swing(step, 0.0)
        if seg is None or seg.kind != 'swing':
            return done, ctl.last_error
        ctl._seg = seg
        ctl._finish_segment()
        done += len(step.legs)
    return done, ''


@functools.lru_cache(maxsize=8)
def _belly_uv(model: RobotModel) -> tuple:
    """The x and y columns of :func:`belly_samples` of ``model`` (read only), built once."""
    U, V = belly_samples(model)[0][:, :2].T
    U.flags.writeable = V.flags.writeable = False
    return U, V


@functools.lru_cache(maxsize=8)
def _standing_com(model: RobotModel) -> np.ndarray:
    """``kinematics.com_base`` of the standing joint angles of ``model`` (read only)."""
    com = kinematics.com_base(model, kinematics.standing_joint_angles(model))
    com.flags.writeable = False
    return com


def _shank_angles(q: np.ndarray) -> np.ndarray:
    """``(..., 4, 2)`` shank pitch (hip flexion + knee) and roll (abduction) [rad]."""
    q = np.asarray(q, dtype=float)
    return np.stack([q[..., 1] + q[..., 2], q[..., 0]], axis=-1)


__all__ = ['WalkingConfig', 'WalkingController', 'JointCommand', 'Phase', 'check_footsteps']
