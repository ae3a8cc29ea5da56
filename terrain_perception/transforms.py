"""Rigid transforms as 4x4 numpy arrays.

Naming: ``T_a_b`` maps points expressed in frame ``b`` into frame ``a`` (``p_a = T_a_b @ p_b``).
Quaternions are ``(x, y, z, w)`` like geometry_msgs and pybullet. Angles in radians.
Frames used by the project: ``map`` (fixed, z up), ``base_link`` (robot body, x forward,
z up), ``camera_optical`` (z forward along the optical axis, x right, y down; the left camera of
a stereo pair).
"""

from __future__ import annotations

import numpy as np


def make_T(R: np.ndarray | None = None, t: np.ndarray | None = None) -> np.ndarray:
    """4x4 transform from a 3x3 rotation and a translation [m]."""
    T = np.eye(4)
    if R is not None:
        T[:3, :3] = R
    if t is not None:
        T[:3, 3] = np.asarray(t, dtype=np.float64).reshape(3)
    return T


def invert(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4x4 transform."""
    R = T[:3, :3]
    out = np.eye(4)
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ T[:3, 3]
    return out


def transform_points(T: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Apply ``T`` to points ``(..., 3)`` (dtype kept); NaN points stay NaN.

    einsum rather than ``@``: a (N, 3) x (3, 3) product through BLAS starts its thread pool
    and is several times slower for the clouds this project moves around.
    """
    pts = np.asarray(pts)
    if not np.issubdtype(pts.dtype, np.floating):
        pts = pts.astype(np.float64)
    R = T[:3, :3].astype(pts.dtype, copy=False)
    return np.einsum('...j,ij->...i', pts, R, optimize=False) + T[:3, 3].astype(pts.dtype)


def rot_x(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def rot_y(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def rot_z(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def rpy_to_R(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """Rotation from roll, pitch, yaw (fixed axes x, y, z: ``R = Rz(yaw) Ry(pitch) Rx(roll)``)."""
    return rot_z(yaw) @ rot_y(pitch) @ rot_x(roll)


def R_to_rpy(R: np.ndarray) -> np.ndarray:
    """(roll, pitch, yaw) [rad] of a rotation, inverse of :func:`rpy_to_R`."""
    pitch = np.arcsin(np.clip(-R[2, 0], -1.0, 1.0))
    roll = np.arctan2(R[2, 1], R[2, 2])
    yaw = np.arctan2(R[1, 0], R[0, 0])
    return np.array([roll, pitch, yaw])


def quat_to_R(q: np.ndarray) -> np.ndarray:
    """Rotation matrix of a quaternion ``(x, y, z, w)`` (normalised here)."""
    x, y, z, w = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def R_to_quat(R: np.ndarray) -> np.ndarray:
    """Quaternion ``(x, y, z, w)`` with w >= 0 of a rotation matrix."""
    m = np.asarray(R, dtype=np.float64)
    tr = np.trace(m)
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = [0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s]
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = [(m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = [(m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s, (m[1, 0] - m[0, 1]) / s]
    q = np.asarray(q)
    q /= np.linalg.norm(q)
    return -q if q[3] < 0 else q


def yaw_of(T: np.ndarray) -> float:
    """Heading [rad] of a pose's x axis projected on the x-y plane."""
    return float(np.arctan2(T[1, 0], T[0, 0]))


def angle_between(R_a: np.ndarray, R_b: np.ndarray) -> float:
    """Geodesic angle [rad] between two rotations."""
    c = (np.trace(R_a.T @ R_b) - 1.0) / 2.0
    return float(np.arccos(np.clip(c, -1.0, 1.0)))
