"""One simulation run (ROS-free): a course, a robot, physics stepping, commands, sensors.

``SimSession`` is what the ``sim_bridge`` node wraps: it owns its own ``BulletClient``
(DIRECT), loads the course (:mod:`terrain_perception.terrain`) into a
:class:`~terrain_perception.sim.world.SimWorld`, spawns the robot profile standing on the flat
approach, and exposes

* :meth:`SimSession.step` -- fixed-rate physics, tracking the current joint command with the
  simulator's PD (``SimRobot.set_joint_targets``) at every physics step;
* :meth:`SimSession.command` -- a validated joint command (names, positions, optional
  velocities and a time-stamped trajectory); a bad one raises ``ValueError`` with the reason and
  leaves the last valid command in force;
* capture scheduling (periodic at the camera rate and/or on request) and :meth:`render`;
* :meth:`imu`, :meth:`joint_state`, :meth:`base_state` ground truth / sensor readings.

Time is the session's own simulated clock ``t_s`` (starts at 0).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import List, Optional, Sequence, Tuple

import numpy as np

from terrain_perception.camera import PinholeCamera, StereoCamera
from terrain_perception.config import param
from terrain_perception.grid import ELEVATION, GridMap
from terrain_perception.sim.world import (ImuConfig, ImuModel, ImuSample, LightConfig, SimWorld,
                                          WorldConfig, render_stereo)

COURSE_CHOICES = ('rocks-6cm', 'rocks-12cm', 'stones-15cm', 'flat')


@dataclass(frozen=True)
class SimSessionConfig:
    """What to simulate and how (the ``sim_bridge`` node's parameters)."""

    robot: str = param('littledog', 'robot profile name (config/robots/<name>.yaml) or path')
    course_class: str = param('rocks-6cm', 'terrain class to generate (flat: no rough '
                              'section)', choices=COURSE_CHOICES)
    course_seed: int = param(0, 'seed of the generated course and of its texture', 0, 2**31 - 1)
    course_file: str = param('', 'load the course from this .npz (GridMap.save) instead of '
                             'generating it')
    course_resolution_m: float = param(0.005, 'cell size of a generated course [m]',
                                       0.001, 0.1)
    start_x_m: float = param(0.4, 'initial base position x in the map frame [m]', -100.0, 100.0)
    start_y_m: float = param(0.0, 'initial base position y [m]', -100.0, 100.0)
    start_yaw_rad: float = param(0.0, 'initial heading [rad]', -np.pi, np.pi)
    settle_s: float = param(0.3, 'simulated time the robot stands still before t = 0 [s]',
                            0.0, 10.0)
    physics_rate_hz: float = param(500.0, 'physics steps per simulated second [Hz]',
                                   50.0, 10000.0)
    camera_rate_hz: float = param(0.0, 'periodic stereo captures per simulated second; '
                                  '0 = the robot profile\'s rate', 0.0, 100.0)
    periodic_capture: bool = param(True, 'capture at camera_rate_hz; false = only on '
                                   '/capture_request')
    periodic_min_gap: float = param(
        0.5, 'a periodic capture due sooner than this share of the camera period after the '
        'previous capture (a requested one) is skipped: a near-duplicate view costs a render '
        'and a pass of the whole perception chain; 0 = every periodic capture', 0.0, 1.0)
    image_scale: float = param(1.0, 'image size relative to the profile\'s camera '
                               '(intrinsics scale with it)', 0.05, 4.0)
    near_m: float = param(0.03, 'near clipping distance of the cameras [m]', 0.001, 10.0)
    far_m: float = param(8.0, 'far clipping distance of the cameras [m]', 0.1, 1000.0)
    shadows: bool = param(True, 'render shadows (TinyRenderer shadow map; about 2x slower)')
    imu_seed: int = param(0, 'seed of the IMU noise and bias', 0, 2**31 - 1)
    texture_texel_m: float = param(0.0, 'ground texture texel size [m]; 0 = 1.5 x the '
                                   'camera\'s pixel footprint where its optical axis meets '
                                   'flat ground when standing (no mipmaps in TinyRenderer: '
                                   'finer texels alias differently in the two views)',
                                   0.0, 0.1)


@dataclass(frozen=True)
class Capture:
    """One rendered stereo pair: left/right RGB (H, W, 3) uint8, left z-depth [m],
    ``T_world_camera`` of the left optical frame, sim time [s]."""

    stamp_s: float
    left: np.ndarray
    right: np.ndarray
    depth: np.ndarray
    T_world_camera: np.ndarray


@dataclass
class _Trajectory:
    start_s: float
    times: np.ndarray          # (P,) [s] from start
    idx: np.ndarray            # (J,) joint indices in the 12-vector
    positions: np.ndarray      # (P, J)
    velocities: Optional[np.ndarray]


def scaled_camera(cam: PinholeCamera, scale: float) -> PinholeCamera:
    """The same lens at ``scale`` times the image size (pixel-centre convention kept)."""
    if scale == 1.0:
        return cam
    w, h = max(1, int(round(cam.width * scale))), max(1, int(round(cam.height * scale)))
    sx, sy = w / cam.width, h / cam.height
    return PinholeCamera(w, h, cam.fx * sx, cam.fy * sy, (cam.cx + 0.5) * sx - 0.5,
                         (cam.cy + 0.5) * sy - 0.5)


def auto_texel_m(model, image_scale: float = 1.0) -> float:
    """1.5 x the ground footprint [m] of one pixel where the optical axis of the standing
    robot's camera meets flat ground (its typical viewing distance)."""
    T = model.T_base_camera
    height = model.standing_height_m + T[2, 3]
    down = -T[2, 2]                      # optical axis z component, pointing down
    distance = height / down if down > 0.05 else 20.0 * height
    return float(1.5 * distance / (model.camera.fx * image_scale))


def flat_course(length_m: float = 3.0, width_m: float = 1.0, resolution_m: float = 0.02
                ) -> GridMap:
    """A flat course (class ``flat``), same layout as the generated ones."""
    nx, ny = int(round(length_m / resolution_m)), int(round(width_m / resolution_m))
    return GridMap(resolution_m, (0.0, -0.5 * width_m), (nx, ny),
                   {ELEVATION: np.zeros((nx, ny), np.float32)},
                   metadata={'class': 'flat', 'seed': 0, 'resolution_m': resolution_m,
                             'origin_xy': [0.0, -0.5 * width_m], 'rough_extent_xy': [],
                             'max_height_m': 0.0})


class SimSession:
    """A robot on a course in its own pybullet DIRECT world; see the module docstring.

    Attributes:
        cfg: the session config. model: the robot profile. robot: the ``SimRobot``.
        course: the terrain grid. world: the ``SimWorld``. stereo: rendered camera model.
        t_s: simulated time [s]. dt_s: physics step [s].
    """

    def __init__(self, cfg: SimSessionConfig = SimSessionConfig(),
                 imu_cfg: ImuConfig = ImuConfig(), world_cfg: WorldConfig = WorldConfig(),
                 course: Optional[GridMap] = None) -> None:
        import pybullet
        from pybullet_utils.bullet_client import BulletClient

        from terrain_perception.kinematics import standing_joint_angles
        from terrain_perception.robot_model import load_robot_model
        from terrain_perception.sim.robots import SimRobot
        from terrain_perception.terrain import make_course

        self.cfg = cfg
        self.model = load_robot_model(cfg.robot)
        if course is None:
            if cfg.course_file:
                try:
                    course = GridMap.load(cfg.course_file)
                except FileNotFoundError as exc:
                    raise ValueError(f'course_file: {exc}') from exc
            elif cfg.course_class == 'flat':
                course = flat_course()
            else:
                course = make_course(cfg.course_class, cfg.course_seed, cfg.course_resolution_m)
        self.course = course
        self.dt_s = 1.0 / cfg.physics_rate_hz
        self.client = BulletClient(pybullet.DIRECT)
        c = self.client
        c.setGravity(0.0, 0.0, -9.81)
        c.setTimeStep(self.dt_s)
        texel = cfg.texture_texel_m or auto_texel_m(self.model, cfg.image_scale)
        world_cfg = replace(world_cfg, texture_tile_m=texel * world_cfg.texture_size_px)
        self.world = SimWorld(c, course, world_cfg, texture_seed=cfg.course_seed)
        ground = float(self.world.height_at(np.array([cfg.start_x_m, cfg.start_y_m])))
        self.robot = SimRobot.load(
            c, self.model, (cfg.start_x_m, cfg.start_y_m,
                            ground + self.model.standing_height_m + 0.002),
            (0.0, 0.0, cfg.start_yaw_rad))
        self.q_target = np.asarray(standing_joint_angles(self.model), float).reshape(12)
        self.dq_target = np.zeros(12)
        self._traj: Optional[_Trajectory] = None
        for _ in range(int(round(cfg.settle_s / self.dt_s))):
            c.stepSimulation()
        self.t_s = 0.0
        self.steps = 0
        self.stereo = StereoCamera(scaled_camera(self.model.camera, cfg.image_scale),
                                   self.model.baseline_m)
        self.camera_rate_hz = cfg.camera_rate_hz or self.model.camera_rate_hz
        self._next_capture_s = 0.0 if cfg.periodic_capture else np.inf
        self._requests: List[float] = []
        self._last_capture_s = -np.inf
        self.requests_already_served = 0   # requests for a time a capture was already taken at
        self.light = LightConfig(shadow=cfg.shadows)
        self.imu_model = ImuModel(imu_cfg, cfg.imu_seed, self.model.T_base_imu)

    def close(self) -> None:
        """Disconnect the physics client."""
        if self.client is not None:
            self.client.disconnect()
            self.client = None

    # -- commands -----------------------------------------------------------------------------
    def command(self, names: Sequence[str], positions: np.ndarray,
                velocities: Optional[np.ndarray] = None,
                times_s: Optional[Sequence[float]] = None,
                start_s: Optional[float] = None) -> None:
        """Set a new joint command after validating all of it.

        Args:
            names: joint names (a subset of the profile's 12 is allowed; others keep their
                current targets).
            positions: ``(P, J)`` or ``(J,)`` targets [rad] for the ``J`` named joints.
            velocities: same shape [rad/s], or None / empty.
            times_s: ``(P,)`` non-decreasing times from ``start_s`` [s] (a trajectory,
                interpolated linearly at the physics rate and held after the last point).
            start_s: sim time the trajectory starts at (default: now).

        Raises:
            ValueError: naming the problem (unknown / duplicate joint, NaN, outside the joint
                limits, shape mismatch, decreasing times); the previous command stays.
        """
        names = list(names)
        if not names:
            raise ValueError('command names no joints')
        if len(set(names)) != len(names):
            raise ValueError(f'command names a joint twice: {names}')
        unknown = [n for n in names if n not in self.model.joint_names]
        if unknown:
            raise ValueError(f'unknown joint name(s) {unknown} (known: '
                             f'{list(self.model.joint_names)})')
        idx = np.array([self.model.joint_names.index(n) for n in names])
        pos = np.asarray(positions, dtype=np.float64)
        if pos.ndim == 1:
            pos = pos[None, :]
        if pos.ndim != 2 or pos.shape[1] != len(names) or pos.shape[0] == 0:
            raise ValueError(f'command has positions of shape {pos.shape} for {len(names)} '
                             'joints')
        if not np.all(np.isfinite(pos)):
            raise ValueError('command positions contain NaN or inf')
        lo, hi = self.model.joint_lower[idx], self.model.joint_upper[idx]
        bad = (pos < lo - 1e-9) | (pos > hi + 1e-9)
        if np.any(bad):
            p, j = np.argwhere(bad)[0]
            raise ValueError(f'target {pos[p, j]:.4f} rad for {names[j]} is outside its limits '
                             f'[{lo[j]:.3f}, {hi[j]:.3f}]')
        vel = None
        if velocities is not None and np.size(velocities) > 0:
            vel = np.asarray(velocities, dtype=np.float64).reshape(pos.shape) \
                if np.size(velocities) == pos.size else None
            if vel is None:
                raise ValueError(f'command has {np.size(velocities)} velocities for '
                                 f'{pos.size} positions')
            if not np.all(np.isfinite(vel)):
                raise ValueError('command velocities contain NaN or inf')
        if times_s is None:
            times = np.zeros(pos.shape[0])
        else:
            times = np.asarray(times_s, dtype=np.float64).reshape(-1)
            if times.shape != (pos.shape[0],):
                raise ValueError(f'command has {times.size} times for {pos.shape[0]} points')
            if not np.all(np.isfinite(times)) or np.any(np.diff(times) < 0) or times[0] < 0:
                raise ValueError('command times must be finite, >= 0 and non-decreasing')
        start = self.t_s if start_s is None or start_s <= 0 else float(start_s)
        self._traj = _Trajectory(start, times, idx, pos, vel)
        self._apply_trajectory()

    def _apply_trajectory(self) -> None:
        tr = self._traj
        if tr is None:
            return
        tau = self.t_s - tr.start_s
        if tau <= tr.times[0] or len(tr.times) == 1:
            k, a = 0, 0.0
        elif tau >= tr.times[-1]:
            k, a = len(tr.times) - 2, 1.0
        else:
            k = int(np.searchsorted(tr.times, tau, side='right') - 1)
            span = tr.times[k + 1] - tr.times[k]
            a = (tau - tr.times[k]) / span if span > 0 else 1.0
        if len(tr.times) == 1:
            q = tr.positions[0]
            dq = tr.velocities[0] if tr.velocities is not None else np.zeros(len(tr.idx))
        else:
            q = (1 - a) * tr.positions[k] + a * tr.positions[k + 1]
            dq = ((1 - a) * tr.velocities[k] + a * tr.velocities[k + 1]
                  if tr.velocities is not None else np.zeros(len(tr.idx)))
            if tau >= tr.times[-1]:
                dq = np.zeros(len(tr.idx))
        self.q_target[tr.idx] = q
        self.dq_target[tr.idx] = dq

    # -- stepping -----------------------------------------------------------------------------
    def step(self, n: int = 1) -> None:
        """Advance ``n`` physics steps, tracking the command with the simulator's PD."""
        for _ in range(int(n)):
            self._apply_trajectory()
            self.robot.set_joint_targets(self.q_target, dq=self.dq_target)
            self.client.stepSimulation()
            self.steps += 1
            self.t_s = self.steps * self.dt_s

    # -- captures -----------------------------------------------------------------------------
    def request_capture(self, stamp_s: Optional[float] = None) -> None:
        """Ask for a capture at the first step at or after ``stamp_s`` (default: now). A
        request for a time a capture was already taken at or after is served by it and
        dropped: one that arrives while the periodic capture of that very step renders (the
        controller asks when its body settles, often on a periodic slot) would otherwise be a
        second, near-duplicate capture a few ms later, which also waits out the stereo node's
        rate limit (~0.5 s of wall at the loop's real-time factor; session 52)."""
        t = self.t_s if stamp_s is None else float(stamp_s)
        if t <= self._last_capture_s + 0.5 * self.dt_s:
            self.requests_already_served += 1
            return
        self._requests.append(t)

    def capture_due(self) -> bool:
        """True when a periodic capture or a request is due at the current time."""
        eps = 0.5 * self.dt_s
        return self.t_s + eps >= self._next_capture_s or any(
            self.t_s + eps >= r for r in self._requests)

    def mark_captured(self) -> None:
        """Mark the due captures done without rendering (nobody listens)."""
        eps = 0.5 * self.dt_s
        self._last_capture_s = self.t_s
        served = any(r <= self.t_s + eps for r in self._requests)
        self._requests = [r for r in self._requests if r > self.t_s + eps]
        if not np.isfinite(self._next_capture_s):
            return                               # no periodic captures
        period = 1.0 / self.camera_rate_hz
        if self.t_s + eps >= self._next_capture_s:
            self._next_capture_s = (np.floor((self.t_s + eps) / period) + 1.0) * period
        # A periodic slot right behind this capture (a requested one) would be a near-duplicate
        # view: in a 40 s loop run 8 of 119 captures came 4-68 ms of simulated time after the
        # previous one, each a ~350 ms render at 640x480 and a second pass of stereo -> plan
        # that waited out the stereo node's rate limit; they were 7 of its 8 slowest plans.
        gap = self.cfg.periodic_min_gap * period
        if served and self._next_capture_s < self.t_s + gap - eps:
            self._next_capture_s = np.ceil((self.t_s + gap - eps) / period - 1e-9) * period

    def render(self) -> Capture:
        """Render the stereo pair now and mark the due captures done."""
        self.mark_captured()
        T = self.robot.camera_pose()
        left, right, depth = render_stereo(self.client, T, self.stereo, self.cfg.near_m,
                                           self.cfg.far_m, self.light)
        return Capture(self.t_s, left, right, depth, T)

    # -- state --------------------------------------------------------------------------------
    def imu(self) -> ImuSample:
        """IMU reading now (acceleration from the velocity change since the last call)."""
        v, w = self.robot.base_velocity()
        return self.imu_model.update(self.t_s, self.robot.base_pose(), v, w)

    def joint_state(self) -> Tuple[Tuple[str, ...], np.ndarray, np.ndarray, np.ndarray]:
        """``(names, q [rad], dq [rad/s], tau [N m])``."""
        q, dq, tau = self.robot.joint_states()
        return tuple(self.model.joint_names), q, dq, tau

    def base_state(self) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(T_world_base, v_body [m/s], w_body [rad/s])``: pose and body-frame twist."""
        T = self.robot.base_pose()
        v, w = self.robot.base_velocity()
        R = T[:3, :3]
        return T, R.T @ v, R.T @ w



def measure_realtime_factor(session: SimSession, sim_seconds: float,
                            cameras: bool = True) -> dict:
    """Run ``session`` like the bridge does (physics + state readings at 100 Hz + due captures)
    for ``sim_seconds`` and time it on the wall clock (benchmarks only).

    Returns:
        ``{'rtf': sim s per wall s, 'physics_s': wall time in physics, 'render_s': wall time
        in rendering, 'captures': n, 'render_ms_per_pair': mean, 'image': 'WxH'}``.
    """
    import time
    n_steps = int(round(sim_seconds / session.dt_s))
    state_every = max(1, int(round(0.01 / session.dt_s)))
    physics = render = 0.0
    captures = 0
    for k in range(n_steps):
        t0 = time.perf_counter()
        session.step(1)
        if k % state_every == 0:
            session.imu()
            session.joint_state()
            session.base_state()
        t1 = time.perf_counter()
        physics += t1 - t0
        if session.capture_due():
            if cameras:
                session.render()
                captures += 1
            else:
                session.mark_captured()
            render += time.perf_counter() - t1
    wall = physics + render
    cam = session.stereo.left
    return {'rtf': sim_seconds / wall if wall > 0 else float('inf'), 'physics_s': physics,
            'render_s': render, 'captures': captures,
            'render_ms_per_pair': 1e3 * render / captures if captures else 0.0,
            'image': f'{cam.width}x{cam.height}'}
