"""A project robot in a pybullet world: loading, joint PD targets, state, poses, contacts.

``SimRobot`` wraps one multibody in a caller-owned ``BulletClient`` (never the global pybullet
connection); the caller owns stepping and time. Joint vectors are ``(12,)`` in the order of
``RobotModel.joint_names`` (legs LF, RF, LH, RH x hip_abduction, hip_flexion, knee).
"""

from __future__ import annotations

from typing import Optional, Sequence

import numpy as np

from terrain_perception import kinematics
from terrain_perception.robot_model import LEG_NAMES, RobotModel
from terrain_perception.transforms import make_T, quat_to_R, rpy_to_R, R_to_quat


class SimRobot:
    """One robot loaded into a pybullet world.

    Attributes:
        client: the ``pybullet_utils.bullet_client.BulletClient`` it lives in.
        model: its :class:`RobotModel`.
        body_id: pybullet body unique id.
        joint_ids: ``(12,)`` pybullet joint indices in ``model.joint_names`` order.
        foot_links, camera_link, imu_link: pybullet link indices.
    """

    def __init__(self, client, model: RobotModel, body_id: int) -> None:
        self.client = client
        self.model = model
        self.body_id = body_id
        by_name = {}
        for i in range(client.getNumJoints(body_id)):
            info = client.getJointInfo(body_id, i)
            by_name[info[1].decode()] = i
            by_name['link:' + info[12].decode()] = i
        missing = [n for n in model.joint_names if n not in by_name]
        if missing:
            raise ValueError(f'{model.urdf_path} lacks joints {missing}')
        self.joint_ids = np.array([by_name[n] for n in model.joint_names], dtype=int)
        self.foot_links = np.array([by_name[f'link:{leg}_foot'] for leg in LEG_NAMES], dtype=int)
        # every other link by leg (hip, thigh, shank) for contact_forces_by_part; the rest
        # (base, camera, IMU) is the body
        self._leg_of_link = {by_name[f'link:{leg}_{part}']: k
                             for k, leg in enumerate(LEG_NAMES)
                             for part in ('hip', 'thigh', 'shank')
                             if f'link:{leg}_{part}' in by_name}
        self._foot_of_link = {int(link): k for k, link in enumerate(self.foot_links)}
        self.camera_link = by_name['link:camera_optical']
        self.imu_link = by_name['link:imu_link']
        self._jids = [int(j) for j in self.joint_ids]
        self._zeros = [0.0] * len(self._jids)
        # bound once: BulletClient.__getattr__ builds a partial on every attribute access
        self._get_joint_states = client.getJointStates
        self._set_motors = client.setJointMotorControlArray
        self._get_base = client.getBasePositionAndOrientation
        self._position_control = client.POSITION_CONTROL
        self._gains = {}
        self._pd: Optional[tuple] = None          # (kp, kd) of use_pd_servo, None = pybullet's
        self._tau_pd = np.zeros(len(self._jids))  # torques the PD servo applied last
        for link in self.foot_links:
            client.changeDynamics(body_id, int(link), lateralFriction=model.foot_friction,
                                  spinningFriction=0.01, rollingFriction=0.0,
                                  restitution=0.0)

    @classmethod
    def load(cls, client, model: RobotModel, base_xyz: Sequence[float] = (0.0, 0.0, 0.0),
             base_rpy: Sequence[float] = (0.0, 0.0, 0.0),
             q: Optional[np.ndarray] = None) -> 'SimRobot':
        """Load ``model``'s URDF at ``base_xyz`` [m] / ``base_rpy`` [rad], joints at ``q``.

        ``q`` defaults to the nominal standing angles; place the base at
        ``standing_height_m`` above the ground to start standing. The joints hold ``q``
        with the profile's PD gains until the first :meth:`set_joint_targets`.
        """
        quat = R_to_quat(rpy_to_R(*base_rpy))
        flags = client.URDF_USE_INERTIA_FROM_FILE
        body = client.loadURDF(str(model.urdf_path), list(base_xyz), list(quat), flags=flags)
        robot = cls(client, model, body)
        if q is None:
            q = kinematics.standing_joint_angles(model)
        robot.reset_joints(q)
        robot.set_joint_targets(q)
        return robot

    # -- commands -------------------------------------------------------------------------
    def reset_joints(self, q: np.ndarray) -> None:
        """Teleport the joints to ``q`` (12,) or (4, 3) [rad], zero velocity."""
        q = self._check_q(q)
        for j, v in zip(self._jids, q):
            self.client.resetJointState(self.body_id, j, float(v), 0.0)

    def reset_base(self, base_xyz: Sequence[float], base_rpy: Sequence[float]) -> None:
        """Teleport the base to a pose (world frame), zero velocity."""
        quat = R_to_quat(rpy_to_R(*base_rpy))
        self.client.resetBasePositionAndOrientation(self.body_id, list(base_xyz), list(quat))
        self.client.resetBaseVelocity(self.body_id, [0, 0, 0], [0, 0, 0])

    def set_joint_targets(self, q: np.ndarray, kp: Optional[float] = None,
                          kd: Optional[float] = None, max_force: Optional[float] = None,
                          dq: Optional[np.ndarray] = None) -> None:
        """Track joint targets with the simulator's PD (POSITION_CONTROL).

        Args:
            q: ``(12,)`` or ``(4, 3)`` target angles [rad]; must be finite.
            kp, kd: pybullet position / velocity gains (default: the profile's).
            max_force: torque limit [N m] (default: the profile's ``max_torque_nm``).
            dq: optional target velocities [rad/s] (default zero).

        After :meth:`use_pd_servo` the PD law tracks the targets, unless ``kp``, ``kd`` or
        ``max_force`` is given: that call (and every later one) uses pybullet's servo again.
        """
        q = self._check_q(q)
        if self._pd is not None:
            if max_force is None and kp is None and kd is None:
                self._apply_pd(q, self._zeros if dq is None
                               else self._check_q(dq, 'joint velocity'))
                return
            self._pd = None     # explicit gains or force: pybullet's servo again, from now on
        n = len(self._jids)
        kp = self.model.position_gain if kp is None else float(kp)
        kd = self.model.velocity_gain if kd is None else float(kd)
        f = self.model.max_torque_nm if max_force is None else float(max_force)
        gains = self._gains.get((kp, kd, f))
        if gains is None:
            gains = self._gains[(kp, kd, f)] = ([kp] * n, [kd] * n, [f] * n)
        dq = self._zeros if dq is None else self._check_q(dq, 'joint velocity').tolist()
        self._set_motors(
            self.body_id, self._jids, self._position_control,
            targetPositions=q.tolist(), targetVelocities=dq,
            positionGains=gains[0], velocityGains=gains[1], forces=gains[2])

    def use_pd_servo(self, kp_nm_per_rad: float, kd_nm_s_per_rad: float) -> None:
        """Model each joint's servo as a PD torque law evaluated at every
        :meth:`set_joint_targets` (every physics step): ``tau = kp (q* - q) + kd (dq* - dq)``,
        clipped at the profile's ``max_torque_nm``. pybullet's POSITION_CONTROL (the default)
        is a velocity constraint that holds any load up to the torque limit without deflecting;
        a PD servo deflects under load (``tau / kp`` rad), as a real position servo does.
        :meth:`joint_states` then reports the applied torques."""
        kp, kd = float(kp_nm_per_rad), float(kd_nm_s_per_rad)
        if not (np.isfinite(kp) and np.isfinite(kd) and kp > 0.0 and kd >= 0.0):
            raise ValueError(f'PD servo gains must be kp > 0 and kd >= 0, got kp={kp}, kd={kd}')
        self._pd = (kp, kd)
        # release pybullet's motors (they would otherwise hold the joints on their own)
        self._set_motors(self.body_id, self._jids, self.client.VELOCITY_CONTROL,
                         targetVelocities=self._zeros, forces=self._zeros)

    def _apply_pd(self, q_target: np.ndarray, dq_target) -> None:
        states = self._get_joint_states(self.body_id, self._jids)
        q = np.array([st[0] for st in states])
        dq = np.array([st[1] for st in states])
        kp, kd = self._pd
        f = self.model.max_torque_nm
        tau = np.clip(kp * (q_target - q) + kd * (np.asarray(dq_target) - dq), -f, f)
        self._tau_pd = tau
        self._set_motors(self.body_id, self._jids, self.client.TORQUE_CONTROL,
                         forces=tau.tolist())

    def _check_q(self, q: np.ndarray, what: str = 'joint vector') -> np.ndarray:
        q = np.asarray(q, dtype=float).reshape(-1)
        if q.shape != (12,):
            raise ValueError(f'{what} must have 12 entries, got {q.size}')
        if not np.isfinite(q.sum()):
            raise ValueError(f'{what} contains NaN or inf')
        return q

    # -- state ----------------------------------------------------------------------------
    def joint_states(self) -> tuple:
        """``(q, dq, tau)`` each ``(12,)``: angles [rad], rates [rad/s], motor torques [N m]."""
        states = self._get_joint_states(self.body_id, self._jids)
        a = np.array([(s[0], s[1], s[3]) for s in states])
        tau = a[:, 2].copy() if self._pd is None else self._tau_pd.copy()
        return a[:, 0].copy(), a[:, 1].copy(), tau

    def base_pose(self) -> np.ndarray:
        """``T_world_base`` 4x4."""
        pos, quat = self._get_base(self.body_id)
        return make_T(quat_to_R(quat), pos)

    def base_tilt_deg(self) -> float:
        """Angle between the base z axis and the world z axis [deg]."""
        x, y, _, _ = self._get_base(self.body_id)[1]
        c = 1.0 - 2.0 * (x * x + y * y)
        return float(np.degrees(np.arccos(min(1.0, max(-1.0, c)))))

    def base_velocity(self) -> tuple:
        """``(v, w)``: linear [m/s] and angular [rad/s] velocity of the base, world frame."""
        v, w = self.client.getBaseVelocity(self.body_id)
        return np.array(v), np.array(w)

    def camera_pose(self) -> np.ndarray:
        """``T_world_camera_optical`` 4x4 of the left stereo camera."""
        return self.base_pose() @ self.model.T_base_camera

    def imu_pose(self) -> np.ndarray:
        """``T_world_imu`` 4x4."""
        return self.base_pose() @ self.model.T_base_imu

    def foot_positions_world(self) -> np.ndarray:
        """``(4, 3)`` foot-sphere centres in the world frame [m] (contact = centre - radius)."""
        states = self.client.getLinkStates(self.body_id, [int(i) for i in self.foot_links],
                                           computeForwardKinematics=True)
        return np.array([s[4] for s in states])

    def foot_contacts(self, other_body: Optional[int] = None) -> np.ndarray:
        """``(4,)`` bool: foot touches something (or ``other_body`` if given)."""
        out = np.zeros(4, dtype=bool)
        for k, link in enumerate(self.foot_links):
            kw = {'bodyA': self.body_id, 'linkIndexA': int(link)}
            if other_body is not None:
                kw['bodyB'] = other_body
            out[k] = len(self.client.getContactPoints(**kw)) > 0
        return out

    def foot_contact_forces(self) -> np.ndarray:
        """``(4,)`` total normal contact force on each foot [N] (from anything but the robot
        itself; see :meth:`contact_forces_by_part`)."""
        return self.contact_forces_by_part()[0]

    def contact_forces_by_part(self) -> tuple:
        """Total normal contact force [N] on ``(feet (4,), legs (4,), body)``: the foot
        spheres, each leg's other links (hip, thigh, shank: a shank resting on a rock), and
        the body (base and head links). Contacts between the robot's own links are left out.
        """
        feet, legs, body = np.zeros(4), np.zeros(4), 0.0
        for p in self.client.getContactPoints(bodyA=self.body_id):
            if p[2] == self.body_id:
                continue
            link, f = p[3], p[9]
            k = self._foot_of_link.get(link)
            if k is not None:
                feet[k] += f
                continue
            k = self._leg_of_link.get(link)
            if k is not None:
                legs[k] += f
            else:
                body += f
        return feet, legs, body

    def non_foot_contacts(self, other_body: Optional[int] = None) -> int:
        """Number of contact points between the ground/world and anything but the feet."""
        kw = {'bodyA': self.body_id}
        if other_body is not None:
            kw['bodyB'] = other_body
        feet = set(int(i) for i in self.foot_links)
        return sum(1 for p in self.client.getContactPoints(**kw)
                   if p[3] not in feet and p[2] != self.body_id)
