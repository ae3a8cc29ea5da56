"""Robot profiles: geometry, limits, gait defaults and sensor mounts of a 12-DOF quadruped.

A profile is a YAML file in ``config/robots/`` (every number there carries its source or an
"assumption:" comment); :func:`load_robot_model` turns it into a frozen :class:`RobotModel`.
No ROS, no pybullet: the simulator (``terrain_perception.sim``), the kinematics, the gait and
the controller all read the same object.

Conventions:
    * legs in the order ``LF, RF, LH, RH`` (index 0..3, same as ``terrain_msgs/Footstep``);
    * joints per leg ``hip_abduction`` (about base x), ``hip_flexion`` and ``knee`` (about the
      leg's y axis); joint vectors are ``(12,)`` in the order of :attr:`RobotModel.joint_names`
      or ``(4, 3)`` as ``[leg, joint]``;
    * all zero joint angles = leg straight down; positive flexion swings the foot backward;
    * "foot position" = centre of the foot sphere; the ground contact point is
      ``foot_radius_m`` below it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from terrain_perception.camera import PinholeCamera, StereoCamera
from terrain_perception.transforms import make_T, rot_y, rpy_to_R

LEG_NAMES = ('LF', 'RF', 'LH', 'RH')
JOINT_TYPES = ('hip_abduction', 'hip_flexion', 'knee')
#: +1 for left legs, -1 for right legs (index like LEG_NAMES).
LEG_SIDE = np.array([1.0, -1.0, 1.0, -1.0])
#: +1 for front legs, -1 for hind legs.
LEG_FRONT = np.array([1.0, 1.0, -1.0, -1.0])

REPO_ROOT = Path(__file__).resolve().parents[1]
ROBOT_CONFIG_DIR = REPO_ROOT / 'config' / 'robots'
URDF_DIR = Path(__file__).resolve().parent / 'sim' / 'robots'

# Rotation from a body-like camera frame (x forward, y left, z up) to the optical frame
# (z forward, x right, y down): columns are the optical axes expressed in the body-like frame.
R_BODYLIKE_OPTICAL = np.array([[0.0, 0.0, 1.0],
                               [-1.0, 0.0, 0.0],
                               [0.0, -1.0, 0.0]])


def _frozen(a: Any, shape: tuple | None = None, what: str = '') -> np.ndarray:
    arr = np.array(a, dtype=np.float64)
    if shape is not None and arr.shape != shape:
        raise ValueError(f'robot profile: {what} must have shape {shape}, got {arr.shape}')
    if not np.all(np.isfinite(arr)):
        raise ValueError(f'robot profile: {what} contains NaN or inf')
    arr.setflags(write=False)
    return arr


@dataclass(frozen=True, eq=False)
class RobotModel:
    """One quadruped profile. Lengths [m], angles [rad], masses [kg], frames in ``base_link``.

    Attributes:
        name: profile name (``littledog``, ``frog``).
        urdf_path: URDF file for the simulator.
        joint_names: 12 joint names, ``<leg>_<joint type>``, legs LF, RF, LH, RH.
        hip_offsets: ``(4, 3)`` hip-abduction axis origins in base_link [m].
        abduction_offset_m: lateral distance from the abduction axis to the leg plane, outward.
        thigh_length_m, shank_length_m: hip-flexion-to-knee and knee-to-foot-centre lengths.
        knee_sign: ``(4,)`` -1 = knee points backward (knee angle <= 0), +1 = forward.
        joint_lower, joint_upper: ``(12,)`` joint limits [rad].
        max_torque_nm, max_velocity_rad_s: actuator limits (every joint).
        foot_radius_m: radius of the spherical foot.
        standing_height_m: base_link origin above flat ground when standing.
        nominal_feet: ``(4, 3)`` foot contact points in base_link when standing [m].
        max_step_length_m: longest planned step, swing_height_m: nominal swing apex above the
            higher end of the step, body_move_per_period_m: body advance per gait period.
        swing_duration_s, shift_duration_s: default crawl timing [s];
            stability_margin_m: default COG margin inside the support triangle [m].
        body_mass_kg, body_size_m, body_inertia_diag: body link.
        link_masses_kg: ``(3,)`` hip, thigh, shank link masses.
        total_mass_kg: body plus legs.
        T_base_camera: 4x4 ``T_base_link_camera_optical`` of the left stereo camera.
        camera: left camera intrinsics; baseline_m, camera_rate_hz: stereo baseline and frame
            rate.
        T_base_imu: 4x4 ``T_base_link_imu``.
        position_gain, velocity_gain: pybullet POSITION_CONTROL gains.
        foot_friction: lateral friction coefficient of the feet in simulation.
        trot: whether the planner may choose Shao's trot for this robot (``gait.trot``).
        source_path: YAML file this profile was read from.
    """

    name: str
    urdf_path: Path
    joint_names: tuple
    hip_offsets: np.ndarray
    abduction_offset_m: float
    thigh_length_m: float
    shank_length_m: float
    knee_sign: np.ndarray
    joint_lower: np.ndarray
    joint_upper: np.ndarray
    max_torque_nm: float
    max_velocity_rad_s: float
    foot_radius_m: float
    standing_height_m: float
    stance_width_extra_m: float
    nominal_feet: np.ndarray
    max_step_length_m: float
    swing_height_m: float
    body_move_per_period_m: float
    swing_duration_s: float
    shift_duration_s: float
    stability_margin_m: float
    body_mass_kg: float
    body_size_m: np.ndarray
    body_inertia_diag: np.ndarray
    link_masses_kg: np.ndarray
    T_base_camera: np.ndarray
    camera: PinholeCamera
    baseline_m: float
    camera_rate_hz: float
    camera_mount_xyz_m: np.ndarray
    camera_pitch_down_rad: float
    T_base_imu: np.ndarray
    position_gain: float
    velocity_gain: float
    foot_friction: float
    source_path: Path = field(default=Path())
    trot: bool = True

    leg_names = LEG_NAMES

    @property
    def total_mass_kg(self) -> float:
        """Body plus four legs [kg]."""
        return float(self.body_mass_kg + 4.0 * np.sum(self.link_masses_kg))

    @property
    def leg_length_m(self) -> float:
        """Fully stretched thigh + shank [m]."""
        return self.thigh_length_m + self.shank_length_m

    @property
    def stereo(self) -> StereoCamera:
        """The rectified stereo pair (left intrinsics + baseline)."""
        return StereoCamera(self.camera, self.baseline_m)

    @property
    def nearest_ground_seen_m(self) -> float:
        """How far ahead of the base origin the camera's view of level ground begins, with the
        body level at its standing height: where the bottom image row's centre ray meets the
        ground [m]. Ground between the front feet and this line is never seen from the
        stance (the view moves on with the robot): FROG-I sees nothing of the 0.52 m ahead
        of its front feet, LittleDog nothing of 0.13 m."""
        cam = self.camera
        ray = self.T_base_camera[:3, :3] @ np.array([0.0, (cam.height - 1 - cam.cy) / cam.fy,
                                                     1.0])
        origin = self.T_base_camera[:3, 3] + np.array([0.0, 0.0, self.standing_height_m])
        if ray[2] >= 0.0:
            return float('inf')                 # the bottom row looks at or above the horizon
        return float(origin[0] - origin[2] / ray[2] * ray[0])

    @property
    def joint_limits(self) -> np.ndarray:
        """``(4, 3, 2)`` [lower, upper] per leg and joint [rad]."""
        return np.stack([self.joint_lower, self.joint_upper], axis=-1).reshape(4, 3, 2)

    @property
    def leg_plane_offsets(self) -> np.ndarray:
        """``(4, 3)`` hip-flexion origins in base_link at zero abduction [m]."""
        off = np.array(self.hip_offsets)
        off[:, 1] += LEG_SIDE * self.abduction_offset_m
        return off

    def joint_index(self, name: str) -> int:
        """Index of a joint name in the 12-vector; ValueError if unknown."""
        try:
            return self.joint_names.index(name)
        except ValueError:
            raise ValueError(f'{self.name}: unknown joint {name!r}') from None


def _leg_table(section: Mapping, key: str, shape: tuple) -> np.ndarray:
    table = section.get(key)
    if not isinstance(table, Mapping) or set(table) != set(LEG_NAMES):
        raise ValueError(f'robot profile: legs.{key} must map each of {LEG_NAMES}')
    return _frozen([table[leg] for leg in LEG_NAMES], (4,) + shape, f'legs.{key}')


def _require(d: Mapping, key: str, where: str) -> Any:
    if not isinstance(d, Mapping) or key not in d:
        raise ValueError(f'robot profile: missing key {where}{key}')
    return d[key]


def _positive(value: Any, what: str) -> float:
    v = float(value)
    if not np.isfinite(v) or v <= 0:
        raise ValueError(f'robot profile: {what} must be positive, got {value!r}')
    return v


def camera_mount(xyz: np.ndarray, pitch_down_rad: float) -> np.ndarray:
    """``T_base_camera_optical`` of a camera at ``xyz`` [m] looking forward, pitched down."""
    return make_T(rot_y(pitch_down_rad) @ R_BODYLIKE_OPTICAL, xyz)


def model_from_dict(data: Mapping, source_path: Path = Path()) -> RobotModel:
    """Build a :class:`RobotModel` from a parsed profile (see ``config/robots/*.yaml``)."""
    name = str(_require(data, 'name', ''))
    body = _require(data, 'body', '')
    legs = _require(data, 'legs', '')
    gait = _require(data, 'gait', '')
    cam = _require(data, 'camera', '')
    imu = _require(data, 'imu', '')
    ctrl = _require(data, 'control', '')

    hips = _leg_table(legs, 'hip_offsets_m', (3,))
    limits = _leg_table(legs, 'joint_limits_rad', (3, 2))
    if np.any(limits[..., 0] >= limits[..., 1]):
        raise ValueError('robot profile: every joint needs lower < upper in joint_limits_rad')
    knee_sign = _frozen(_require(legs, 'knee_sign', 'legs.'), (4,), 'legs.knee_sign')
    if not np.all(np.isin(knee_sign, (-1.0, 1.0))):
        raise ValueError(f'robot profile: legs.knee_sign must be +-1, got {knee_sign}')
    abd = float(_require(legs, 'abduction_offset_m', 'legs.'))
    if abd < 0:
        raise ValueError(f'robot profile: legs.abduction_offset_m must be >= 0, got {abd}')
    thigh = _positive(_require(legs, 'thigh_length_m', 'legs.'), 'legs.thigh_length_m')
    shank = _positive(_require(legs, 'shank_length_m', 'legs.'), 'legs.shank_length_m')
    foot_r = _positive(_require(legs, 'foot_radius_m', 'legs.'), 'legs.foot_radius_m')
    height = _positive(_require(gait, 'standing_height_m', 'gait.'), 'gait.standing_height_m')
    if height - foot_r >= thigh + shank:
        raise ValueError(f'robot profile: standing_height_m {height} is out of the legs\' reach')
    extra = float(gait.get('stance_width_extra_m', 0.0))

    nominal = np.array(hips)
    nominal[:, 1] += LEG_SIDE * (abd + extra)
    nominal[:, 2] = -height

    width, height_px = int(_require(cam, 'width_px', 'camera.')), int(
        _require(cam, 'height_px', 'camera.'))
    hfov = np.radians(_positive(_require(cam, 'horizontal_fov_deg', 'camera.'),
                                'camera.horizontal_fov_deg'))
    fx = 0.5 * width / np.tan(hfov / 2.0)
    camera = PinholeCamera(width, height_px, fx, fx, (width - 1) / 2.0, (height_px - 1) / 2.0)
    mount_xyz = _frozen(_require(cam, 'mount_xyz_m', 'camera.'), (3,), 'camera.mount_xyz_m')
    pitch = np.radians(float(_require(cam, 'pitch_down_deg', 'camera.')))
    T_bc = camera_mount(mount_xyz, pitch)
    T_bc.setflags(write=False)
    T_bi = make_T(rpy_to_R(*_frozen(_require(imu, 'rpy_rad', 'imu.'), (3,), 'imu.rpy_rad')),
                  _frozen(_require(imu, 'xyz_m', 'imu.'), (3,), 'imu.xyz_m'))
    T_bi.setflags(write=False)

    urdf = Path(str(_require(data, 'urdf', '')))
    if not urdf.is_absolute():
        urdf = URDF_DIR / urdf
    joint_names = tuple(f'{leg}_{j}' for leg in LEG_NAMES for j in JOINT_TYPES)
    return RobotModel(
        name=name, urdf_path=urdf, joint_names=joint_names, hip_offsets=hips,
        abduction_offset_m=abd, thigh_length_m=thigh, shank_length_m=shank,
        knee_sign=knee_sign,
        joint_lower=_frozen(limits[..., 0].reshape(12)),
        joint_upper=_frozen(limits[..., 1].reshape(12)),
        max_torque_nm=_positive(_require(legs, 'max_torque_nm', 'legs.'), 'legs.max_torque_nm'),
        max_velocity_rad_s=_positive(_require(legs, 'max_velocity_rad_s', 'legs.'),
                                     'legs.max_velocity_rad_s'),
        foot_radius_m=foot_r, standing_height_m=height, stance_width_extra_m=extra,
        nominal_feet=_frozen(nominal),
        max_step_length_m=_positive(_require(gait, 'max_step_length_m', 'gait.'),
                                    'gait.max_step_length_m'),
        swing_height_m=_positive(_require(gait, 'swing_height_m', 'gait.'),
                                 'gait.swing_height_m'),
        body_move_per_period_m=_positive(_require(gait, 'body_move_per_period_m', 'gait.'),
                                         'gait.body_move_per_period_m'),
        swing_duration_s=_positive(_require(gait, 'swing_duration_s', 'gait.'),
                                   'gait.swing_duration_s'),
        shift_duration_s=_positive(_require(gait, 'shift_duration_s', 'gait.'),
                                   'gait.shift_duration_s'),
        stability_margin_m=float(_require(gait, 'stability_margin_m', 'gait.')),
        body_mass_kg=_positive(_require(body, 'mass_kg', 'body.'), 'body.mass_kg'),
        body_size_m=_frozen(_require(body, 'size_m', 'body.'), (3,), 'body.size_m'),
        body_inertia_diag=_frozen(_require(body, 'inertia_diag_kgm2', 'body.'), (3,),
                                  'body.inertia_diag_kgm2'),
        link_masses_kg=_frozen(_require(legs, 'masses_kg', 'legs.'), (3,), 'legs.masses_kg'),
        T_base_camera=T_bc, camera=camera,
        baseline_m=_positive(_require(cam, 'baseline_m', 'camera.'), 'camera.baseline_m'),
        camera_rate_hz=_positive(_require(cam, 'rate_hz', 'camera.'), 'camera.rate_hz'),
        camera_mount_xyz_m=mount_xyz, camera_pitch_down_rad=float(pitch),
        T_base_imu=T_bi,
        position_gain=_positive(_require(ctrl, 'position_gain', 'control.'),
                                'control.position_gain'),
        velocity_gain=_positive(_require(ctrl, 'velocity_gain', 'control.'),
                                'control.velocity_gain'),
        foot_friction=_positive(_require(ctrl, 'foot_friction', 'control.'),
                                'control.foot_friction'),
        source_path=Path(source_path),
        trot=_bool(gait.get('trot', True), 'gait.trot'),
    )


def _bool(v: Any, key: str) -> bool:
    if not isinstance(v, bool):
        raise ValueError(f'robot profile: {key} must be true or false, got {v!r}')
    return v


def available_robots() -> tuple:
    """Names of the profiles in ``config/robots/``."""
    return tuple(sorted(p.stem for p in ROBOT_CONFIG_DIR.glob('*.yaml')))


def load_robot_model(name_or_path: 'str | Path') -> RobotModel:
    """Load a profile by name (``'littledog'``, ``'frog'``) or from a YAML path.

    Raises ValueError naming the problem (unknown name, missing key, bad shape or value).
    """
    import yaml
    p = Path(name_or_path)
    if p.suffix not in ('.yaml', '.yml'):
        p = ROBOT_CONFIG_DIR / f'{name_or_path}.yaml'
        if not p.is_file():
            raise ValueError(f'unknown robot {name_or_path!r} (known: {available_robots()})')
    elif not p.is_file():
        raise ValueError(f'robot profile {p} does not exist')
    data = yaml.safe_load(p.read_text())
    if not isinstance(data, Mapping):
        raise ValueError(f'robot profile {p} is not a mapping')
    return model_from_dict(data, p)
