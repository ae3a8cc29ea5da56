"""Localisation against the terrain and the two terrain models (Kolter et al., section II).

Each capture is a cloud in the camera-optical frame plus the dead-reckoning pose of the body
(``T_odom_base``) at the capture's stamp. :class:`IcpMapper`:

1. predicts the camera pose in ``map`` from dead reckoning and the current correction
   ``T_map_odom`` (the paper: "a very reasonable initial guess simply by using dead reckoning");
2. aligns a sparse, uniformly sub-sampled copy of the cloud to the **coarse model** with
   point-to-plane ICP, ``E = sum(((R p_i + t - q_i) . n_i)^2)`` with a robust kernel: by default
   :func:`constrained_icp` (Gauss-Newton that keeps the prior along the directions the
   geometry does not constrain, in every iteration), or Open3D's solver (``icp_solver``);
3. rejects the alignment when its fitness is low, its residual high, or its correction much
   larger than the drift dead reckoning can have accumulated since the last accepted capture
   (then the prior is kept and the capture is not fused);
4. fuses the full-resolution cloud into the **fine height map** (default 1 cm cells: per-cell
   mean, min, max, count, variance, last-seen stamp, observed mask; NaN where empty) and its
   sparse copy into the coarse model;
5. keeps the capture's camera pose (the occlusion-fill node needs the lines of sight).

Both models move with the robot: the fine map has a fixed size and is re-centred by whole cells,
the coarse model keeps only points within a radius, so memory does not grow with distance.

Frames: ``map`` (fixed, z up), ``odom`` (dead reckoning), ``base_link``, ``camera_optical``.
Poses are 4x4 ``T_a_b`` (``p_a = T_a_b p_b``). Times are float seconds from message stamps;
nothing here reads a clock.
"""

from __future__ import annotations

import collections
import dataclasses
import logging
from dataclasses import dataclass, field
from typing import Deque, Dict, Optional, Tuple

import numpy as np
import open3d as o3d
from scipy import ndimage
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation, Slerp

from terrain_perception.compiled import load_compiled
from terrain_perception.config import param
from terrain_perception.grid import ELEVATION, OBSERVED, VARIANCE, GridMap
from terrain_perception.transforms import (angle_between, invert, rot_z, transform_points,
                                           yaw_of)

MIN = 'min'
MAX = 'max'
COUNT = 'count'
LAST_SEEN = 'last_seen'

_REG = o3d.pipelines.registration
_LOG = logging.getLogger(__name__)


def _load_kernels():
    """The compiled fine-map kernels (terrain_perception._mapping_kernels), or None for the
    numpy code (``TERRAIN_MAPPING_NUMBA=0``, or numba missing: logged once)."""
    return load_compiled('_mapping_kernels', 'TERRAIN_MAPPING_NUMBA', 'fine map', _LOG)


_kernels = _load_kernels()


def use_compiled_kernels(enabled: Optional[bool] = True) -> bool:
    """Select the compiled fine-map kernels (``True``), the numpy code (``False``) or the
    default (``None``) for the following :meth:`FineHeightMap.add` and
    :meth:`FineHeightMap.rays_below` calls, process-wide; returns whether compiled is on.
    Both give bitwise the same maps."""
    global _kernels
    if enabled is None:
        _kernels = _load_kernels()
    elif enabled:
        from terrain_perception import _mapping_kernels
        _kernels = _mapping_kernels
    else:
        _kernels = None
    return _kernels is not None


@dataclass(frozen=True)
class MapperConfig:
    """Parameters of :class:`IcpMapper` (the ``icp_mapper`` node's parameters)."""

    # ---- input clouds
    min_range_m: float = param(0.05, 'nearest z-depth [m] of a cloud point used', 0.0, 10.0)
    max_range_m: float = param(1.5, 'farthest z-depth [m] of a cloud point used', 0.1, 20.0)
    min_points: int = param(200, 'fewest valid points a cloud needs', 10, 10_000_000)
    # ---- depth noise (stereo: Z = f b / d, so a disparity error sigma_d gives
    # sigma_z = Z^2 sigma_d / (f b); f b comes from the camera, see IcpMapper)
    disparity_sigma_px: float = param(0.0, 'disparity noise [px] of the stereo clouds; points '
                                      'weigh 1 / (sigma_z^2 + depth_sigma_floor_m^2) in the '
                                      'fine map and the degeneracy check (0 = equal weights; '
                                      'off by default: weights from the measured depth favour '
                                      'points measured too near, see the YAML)', 0.0, 10.0)
    depth_sigma_floor_m: float = param(0.003, 'range-independent height noise [m] (pose error, '
                                       'cell quantisation) added in quadrature to sigma_z; keeps '
                                       'the nearest points from outweighing all others',
                                       1e-5, 1.0)
    fine_max_range_m: float = param(1.5, 'farthest z-depth [m] of a point fused into the fine '
                                    'map (later captures see the same ground closer)', 0.1, 20.0)
    icp_max_range_m: float = param(1.5, 'farthest z-depth [m] of an ICP source point', 0.1,
                                   20.0)
    # ---- coarse model / ICP
    coarse_stride_px: int = param(8, 'pixel stride sub-sampling an organized cloud for ICP',
                                  1, 64)
    coarse_voxel_m: float = param(0.01, 'voxel size [m] of the ICP source and coarse model',
                                  0.001, 0.5)
    coarse_radius_m: float = param(1.5, 'coarse-model points farther than this [m] (x-y) '
                                   'from the robot are dropped', 0.2, 50.0)
    coarse_max_points: int = param(30000, 'cap on coarse-model points (newest kept)',
                                   100, 10_000_000)
    coarse_fusion: str = param(
        'weighted', 'how a capture joins the coarse model: weighted = each voxel (a fixed grid '
        'in map) keeps the mean of its observations, up to coarse_max_weight of them; '
        'average = Open3D\'s voxel down-sampling of model + capture, where a re-observed '
        'voxel moves half-way to the newest capture, so the model is the last few captures '
        'and follows a slow drift of the poses they were fused at (FROG-I on the stones, '
        'seed 146\'s bag replayed: 12-26 mm of position error through the stones with no '
        'slip to explain it, 2-6 mm with weighted)',
        choices=('weighted', 'average'))
    coarse_max_weight: float = param(
        20.0, 'weighted fusion: a voxel\'s observation count stops growing here, so it '
        'follows the newest coarse_max_weight captures (a changed or misplaced surface is '
        'forgotten; 1 = the newest capture replaces the voxel)', 1.0, 1e9)
    model_from: str = param('fine', 'cloud the coarse model is voxelised from: the full cloud '
                            '(voxel centroids of many samples, less bias) or the ICP sub-sample',
                            choices=('fine', 'coarse'))
    normal_source: str = param('height_grid', 'model normals from the slopes of the capture\'s '
                               '2.5-D height grid (fast) or from PCA of 3-D neighbours (Open3D)',
                               choices=('height_grid', 'pca'))
    normal_radius_m: float = param(0.03, 'normal neighbourhood [m]: half-width of the height-map '
                                   'differences, or the PCA radius', 0.002, 1.0)
    normal_max_nn: int = param(20, 'max neighbours for a PCA model normal', 3, 200)
    icp_method: str = param('point_to_plane', 'ICP error metric (point_to_point is kept for '
                            'comparison only)', choices=('point_to_plane', 'point_to_point'))
    icp_solver: str = param('constrained', 'point-to-plane solver: constrained = our '
                            'Gauss-Newton ICP that keeps the prior along the directions the '
                            'geometry does not constrain in every iteration (correspondences, '
                            'fitness and RMSE are those of the pose it returns); open3d = '
                            'Open3D\'s ICP to convergence, those directions reset to the prior '
                            'afterwards (its correspondences then belong to a pose it slid to)',
                            choices=('constrained', 'open3d'))
    max_correspondence_m: float = param(0.04, 'ICP correspondence distance [m]', 0.001, 1.0)
    max_iterations: int = param(30, 'ICP iterations', 1, 1000)
    relative_fitness: float = param(1e-7, 'ICP stops when fitness changes less than this',
                                    0.0, 1.0)
    relative_rmse: float = param(1e-7, 'ICP stops when RMSE changes less than this', 0.0, 1.0)
    robust_kernel: str = param('tukey', 'robust loss on point-to-plane residuals',
                               choices=('none', 'huber', 'tukey', 'cauchy', 'gm', 'l1'))
    kernel_scale_m: float = param(0.01, 'robust kernel scale [m]', 1e-5, 1.0)
    degeneracy_threshold: float = param(5e-4, 'keep the prior along directions whose normalised '
                                        'point-to-plane information is below this (0 = off)',
                                        0.0, 1.0)
    degeneracy_noise_gain: float = param(3.0, 'also keep the prior where the information is '
                                         'below this x (rmse / normal_radius_m)^2: the slope '
                                         'noise that height noise of the alignment\'s '
                                         'residual size puts into the model normals (0 = off)',
                                         0.0, 100.0)
    # ---- guards
    min_fitness: float = param(0.3, 'reject an alignment matching fewer source points than '
                               'this fraction', 0.0, 1.0)
    max_rmse_m: float = param(0.01, 'reject an alignment whose point-to-plane RMSE [m] exceeds '
                              'this', 1e-5, 1.0)
    max_rmse_ratio: float = param(3.0, 'reject an alignment whose RMSE exceeds this multiple of '
                                  'the median RMSE of recent accepted ones (0 = off)', 0.0, 100.0)
    rmse_floor_m: float = param(0.0015, 'the relative RMSE test never rejects below this [m]',
                                0.0, 1.0)
    max_correction_floor_m: float = param(0.01, 'correction [m] always allowed', 0.0, 10.0)
    max_correction_per_m: float = param(0.15, 'extra correction [m] allowed per metre walked '
                                        'since the last accepted capture', 0.0, 10.0)
    max_rotation_floor_deg: float = param(2.0, 'rotation correction [deg] always allowed',
                                          0.0, 180.0)
    max_rotation_per_m_deg: float = param(8.0, 'extra rotation correction [deg] allowed per '
                                          'metre walked', 0.0, 360.0)
    max_correction_disturbed_m: float = param(
        0.08, 'correction [m] allowed from the first capture after a disturbance (the IMU '
        'measured free fall: a slip or drop that leg odometry cannot see) until one is '
        'accepted: on FROG-I\'s stones (seed 131) the body slid 48 mm off a stone, the drift '
        'guard rejected the ICP\'s correction and after 10 rejections the model restarted at '
        'the wrong pose; 0 = no exception', 0.0, 10.0)
    max_rotation_disturbed_deg: float = param(
        5.0, 'rotation correction [deg] allowed after a disturbance (see '
        'max_correction_disturbed_m)', 0.0, 180.0)
    confirm_captures: int = param(
        3, 'a correction the drift guard refused is accepted when this many captures in a row '
        '(captures refused as misfits skipped) measured the same one (the shift and turn from '
        'the prior to ICP\'s pose, map frame, within confirm_tolerance_m / '
        'confirm_tolerance_deg), at their mean: a slip the IMU did not see as free fall leaves '
        'dead reckoning off by a constant that every later capture measures again, where a '
        'mismatch moves with the view; 0 = off', 0, 1000)
    confirm_tolerance_m: float = param(
        0.02, 'agreement of the confirming corrections [m]: replayed with a 5 cm slip, '
        'LittleDog\'s ICP put its y within 15 mm and its yaw within 1.7 deg from capture to '
        'capture (a y-yaw cost valley)', 0.0, 1.0)
    confirm_tolerance_deg: float = param(2.0, 'agreement of their rotations [deg]', 0.0, 180.0)
    confirm_min_travel_m: float = param(
        0.01, 'dead reckoning must have moved this far over the agreeing captures [m] (the run '
        'grows past confirm_captures until it has): a body standing still sees the same view, '
        'and a wrong minimum (a periodic pattern) repeats with it. FROG-I walks the stones at '
        '1.2 cm/s with 5 captures/s: 3 captures span 5 mm', 0.0, 10.0)
    max_correction_confirmed_m: float = param(0.10, 'largest correction [m] confirmation '
                                              'accepts', 0.0, 10.0)
    max_rotation_confirmed_deg: float = param(6.0, 'largest rotation correction [deg] '
                                              'confirmation accepts', 0.0, 180.0)
    relocalise_captures: int = param(
        5, 'after a correction the drift guard refused, a disturbance, or from a capture whose '
        'ICP from the prior is a misfit (fitness, residual), this many captures run the '
        'constrained ICP also from starts around the prior (multi_start_icp; rings of '
        'relocalise_radius_m / 2 and relocalise_radius_m): ICP\'s basin on the stones is about '
        '3 cm, and after a slide it measured once (FROG-I, stones seed 138) the next captures '
        'aligned near the wrong prior and were accepted; 0 = off', 0, 1_000_000)
    relocalise_radius_m: float = param(0.10, 'outer ring of the relocalisation starts [m]',
                                       0.0, 1.0)
    relocalise_directions: int = param(8, 'starts per ring', 1, 64)
    relocalise_max_iterations: int = param(20, 'ICP iterations (per phase) of a '
                                           'relocalisation start', 1, 1000)
    relocalise_max_points: int = param(600, 'source points the relocalisation starts align '
                                       '(evenly spread; the kept one is refined on all)',
                                       6, 1_000_000)
    relocalise_cost_ratio: float = param(
        0.7, 'a relocalisation start wins when its truncated residual cost on the points both '
        'match is below this fraction of the prior ICP\'s (choose_alignment)', 0.0, 1.0)
    relocalise_min_gain_m: float = param(
        0.002, '... and its residual RMS is lower by at least this [m] (flat ground fits every '
        'shift to micrometres)', 0.0, 1.0)
    max_consecutive_rejections: int = param(10, 'after this many rejections in a row the '
                                            'coarse model is restarted from the next capture '
                                            'at its prior (lost: nothing left to align to)',
                                            1, 1_000_000)
    fuse_rejected: bool = param(False, 'fuse captures whose alignment was rejected (at the '
                                'prior pose) into the maps')
    # ---- roll / pitch priors
    use_imu_rotation_prior: bool = param(
        True, "turn the prior by the IMU's attitude change since the last accepted capture "
        '(a slip the leg odometry misses turns the body but not its estimate); the position '
        'stays dead reckoning\'s')
    icp_yaw_gain: float = param(
        1.0, "with the IMU rotation prior: share of ICP's yaw correction kept (1 = ICP's yaw; "
        "0 = the IMU's yaw change alone); the translation follows ICP's cost valley to the "
        'kept yaw (a constant-gain filter of the two yaw sources, see blend_yaw)', 0.0, 1.0)
    imu_yaw_drift_window_s: float = param(
        30.0, 'with the IMU rotation prior: the IMU\'s yaw drift rate (a gyro bias; it has no '
        'absolute yaw) is the sum of the yaw corrections ICP made over about this many '
        'seconds of captures, divided by their span, and the prior\'s yaw is turned by the '
        'rate times the time since the last accepted capture. The estimate moves only at '
        'captures whose geometry constrained every direction, and the span starts at one '
        '(see _note_yaw_correction), so it holds while the view is flat and ICP '
        'keeps the yaw at the prior (FROG-I on the stones, seed 146: 70 s of flat view past '
        'the stones, the pose\'s yaw drifted 2.5 deg with the IMU\'s 0.045 deg/s); '
        'used from half a window of history; 0 = off', 0.0, 1e6)
    imu_yaw_drift_max_deg_s: float = param(0.5, 'largest yaw drift rate [deg/s] the estimate '
                                           'may take (a larger one is clipped)', 0.0, 180.0)
    odometry_scale_window_m: float = param(
        1.0, 'scale the dead reckoning\'s horizontal step in the prior by how far ICP found '
        'the body to move per metre of odometry over about this many metres of walking: '
        'between captures whose constrained directions hold the step (their positions along '
        'it are measurements), the ICP displacement along the odometry\'s, summed with a '
        'forgetting factor exp(-step / window), over the odometry\'s length. Dead reckoning follows the '
        'commanded trajectory and the feet lag it (FROG-I stones seed 104: 2-3 % too far), '
        'which ICP does not see where the view is flat (x, y and yaw kept at the prior: '
        '25 mm along x over 1.3 m past the stones); 0 = off', 0.0, 1e6)
    odometry_scale_min_m: float = param(
        0.3, 'the scale is used once this many metres (forgetting-weighted) of constrained '
        'odometry went into it', 0.0, 1e6)
    odometry_scale_max_error: float = param(
        0.1, 'the scale is clipped to 1 +- this', 0.0, 0.9)
    use_gravity_prior: bool = param(False, 'level the prior with a measured up vector (IMU)')
    use_ground_plane_prior: bool = param(False, 'level the prior with a RANSAC ground plane')
    ground_plane_threshold_m: float = param(0.01, 'RANSAC inlier distance [m]', 1e-4, 1.0)
    ground_plane_min_inliers: float = param(0.5, 'fraction of points the ground plane must '
                                            'hold to be used', 0.0, 1.0)
    max_level_error_deg: float = param(0.0, 'reject an alignment whose up axis differs from '
                                       'the roll/pitch prior by more [deg]; 0 = no check',
                                       0.0, 90.0)
    # ---- fine map
    fine_resolution_m: float = param(0.01, 'fine height-map cell size [m]', 0.001, 1.0)
    fine_size_m: float = param(3.0, 'edge length [m] of the square fine map around the robot',
                               0.1, 100.0)
    fine_stride_px: int = param(2, 'pixel stride of the organized cloud fused into the fine map',
                                1, 64)
    fine_estimator: str = param('plane', 'cell height: mean of samples, or the cell-centre '
                                'value of a per-cell least-squares plane',
                                choices=('mean', 'plane'))
    cell_outlier_gate_m: float = param(0.015, 'per capture, samples farther than this [m] from '
                                       'their cell\'s mean are dropped (0 = keep all)',
                                       0.0, 1.0)
    isolated_max_count: int = param(
        2, 'a published cell of at most this many samples whose observed 8-neighbours are '
        'fewer than isolated_min_neighbours, or whose height is more than isolated_gate_m from '
        'their median, is published as unobserved (a lone stereo mismatch; its samples are '
        'kept and count once more arrive); 0 = publish every cell', 0, 1000000)
    isolated_min_neighbours: int = param(2, 'see isolated_max_count', 0, 8)
    isolated_gate_m: float = param(0.05, 'see isolated_max_count [m]', 0.0, 100.0)
    isolated_island_cells: int = param(
        20, 'also published as unobserved: islands of fewer observed cells than this (cells '
        'at most one unobserved cell apart join), none with more than isolated_max_count '
        'samples: a cluster of mismatches vouches for itself through the neighbour rule; '
        '0 = off', 0, 1000000)
    line_of_sight_tolerance_m: float = param(
        0.1, 'a point is not fused when the ray from the camera to it passes more than this '
        '[m] below a cell the fine map has already observed, in the last half of its length: '
        'the ray could not have got through that ground (a stereo mismatch far below the '
        'terrain); 0 = no check', 0.0, 1.0)
    max_height_above_base_m: float = param(
        0.0, 'a point more than this [m] above the body origin (map z, gravity up) is not '
        'fused: what the robot steps on or passes under lies below its body, and points up at '
        'the camera\'s height are stereo mismatches at the near end of the disparity search '
        'in the top image rows, where the floor is far (phantom cells 12-20 cm high on '
        'LittleDog\'s rocks-6cm maps, 40-70 cm on FROG-I\'s stones); 100 = no check',
        -1.0, 100.0)
    recenter_distance_m: float = param(0.5, 'move the maps when the robot is this far [m] '
                                       'from the fine map centre', 0.0, 100.0)
    max_capture_poses: int = param(200, 'capture poses kept with the map', 1, 100000)
    stamp_tolerance_s: float = param(0.0, 'a cloud may be this much [s] older than the map',
                                     0.0, 100.0)


#: a capture's position counts as measured along a direction when the unit translation that
#: way keeps at least this norm projected onto the directions ICP constrained
_SCALE_OBSERVED = 0.95


@dataclass
class MapperUpdate:
    """What one capture did.

    Attributes:
        accepted: the ICP alignment passed every guard (the first capture is accepted as is).
        fused: the capture went into the maps.
        reason: '' when accepted, else why the alignment was rejected.
        T_map_base, T_map_camera: pose of the capture [4x4] (ICP's if accepted, else the prior).
        T_map_base_prior: the dead-reckoning prediction.
        T_map_odom: the correction after this capture.
        fitness: the ICP's fitness (share of source points with a correspondence at the
            returned pose); inlier_rmse_m: point-to-plane RMSE [m] over the
            correspondences (both NaN for the first capture).
        correction_m, correction_deg: ICP pose minus prior (body position [m], rotation [deg]).
        n_source, n_model: ICP source points and coarse-model points.
        n_degenerate: directions (of 6) the geometry did not constrain; kept at the prior
            (a partial update when 0 < n_degenerate < 6).
        min_information: smallest eigenvalue of the normalised point-to-plane information
            (see :func:`remove_degenerate_motion`); near 0 = a direction is unconstrained.
        T_map_base_icp: ICP's pose before the guards (None for a first capture): with
            ``T_map_base_prior`` it gives the correction a refused alignment measured.
        confirmed: accepted as a correction the drift guard refused but repeated captures
            confirmed (``MapperConfig.confirm_captures``).
        multi_start: -1 when ICP ran from the prior only; else the relocalisation start
            :func:`multi_start_icp` kept (0 = the prior's; ``relocalise_captures``).
        information_limit: the eigenvalue a direction needed to be corrected (the larger of
            ``degeneracy_threshold`` and the noise floor from the residual).
    """

    accepted: bool
    fused: bool
    reason: str
    T_map_base: np.ndarray
    T_map_camera: np.ndarray
    T_map_base_prior: np.ndarray
    T_map_odom: np.ndarray
    fitness: float = float('nan')
    inlier_rmse_m: float = float('nan')
    correction_m: float = 0.0
    correction_deg: float = 0.0
    n_source: int = 0
    n_model: int = 0
    n_degenerate: int = 0
    min_information: float = float('nan')
    information_limit: float = float('nan')
    T_map_base_icp: Optional[np.ndarray] = None
    confirmed: bool = False
    multi_start: int = -1


def map_frame_correction(T_map_base: np.ndarray, T_prior: np.ndarray) -> np.ndarray:
    """The shift and turn that take the pose ``T_prior`` to ``T_map_base``, in the map frame
    (4x4: rotation ``R_base R_prior^T``, translation the difference of the positions; the
    turn is about the body, not the map origin)."""
    C = np.eye(4)
    C[:3, :3] = T_map_base[:3, :3] @ T_prior[:3, :3].T
    C[:3, 3] = T_map_base[:3, 3] - T_prior[:3, 3]
    return C


def _check_T(T: np.ndarray, name: str) -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError(f'{name} must be a finite 4x4 transform')
    R = T[:3, :3]
    if np.abs(R.T @ R - np.eye(3)).max() > 1e-4 or np.linalg.det(R) < 0:
        raise ValueError(f'{name} has a rotation that is not orthonormal')
    return T


def valid_points(cloud: np.ndarray, min_range_m: float = 0.0, max_range_m: float = np.inf,
                 stride_px: int = 1) -> np.ndarray:
    """Finite points ``(N, 3)`` float64 of a camera-frame cloud within a z-depth window.

    Args: ``cloud`` ``(H, W, 3)`` organized (sub-sampled by ``stride_px``) or ``(N, 3)`` [m].
    Raises ValueError naming the problem for a wrong shape.
    """
    cloud = np.asarray(cloud)
    if cloud.ndim == 3 and cloud.shape[-1] == 3:
        view = cloud[::stride_px, ::stride_px]
    elif cloud.ndim == 2 and cloud.shape[-1] == 3:
        view = cloud[::stride_px] if stride_px > 1 else cloud
    else:
        raise ValueError(f'a cloud must be (H, W, 3) or (N, 3), got shape {cloud.shape}')
    if not np.issubdtype(cloud.dtype, np.floating):
        raise ValueError(f'cloud coordinates must be floating point, got {cloud.dtype}')
    k = _kernels
    if k is not None and view.dtype in (np.float32, np.float64):
        # one compiled pass over the (strided) view: the same points in the same order
        return k.valid_points(view if view.ndim == 3 else view[None], float(min_range_m),
                              float(max_range_m))
    # per coordinate on the (strided) input, then only the valid points are gathered and
    # widened; float64 bounds, so a float32 depth is compared as its float64 value
    x, y, z = view[..., 0], view[..., 1], view[..., 2]
    ok = (np.isfinite(x) & np.isfinite(y) & np.isfinite(z)
          & (z >= np.float64(min_range_m)) & (z <= np.float64(max_range_m)))
    return view[ok].astype(np.float64, copy=False)


def _rows(a: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``a[mask]`` without the copy when every row is selected."""
    return a if mask.all() else a[mask]


def level_rotation(R_map_camera: np.ndarray, up_camera: np.ndarray) -> np.ndarray:
    """Smallest rotation of ``R_map_camera`` that makes ``up_camera`` (the world's up seen in
    the camera frame) point along map +z; keeps the heading."""
    up = np.asarray(up_camera, dtype=np.float64)
    up = up / np.linalg.norm(up)
    a = R_map_camera @ up
    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(a, z)
    s = np.linalg.norm(axis)
    if s < 1e-12:
        return R_map_camera.copy()
    ang = np.arctan2(s, float(a @ z))
    return Rotation.from_rotvec(axis / s * ang).as_matrix() @ R_map_camera


def ground_plane_up(points_camera: np.ndarray, threshold_m: float, min_inlier_ratio: float,
                    seed: int = 0) -> Optional[np.ndarray]:
    """Up direction (unit, camera frame) of the dominant plane of a cloud by RANSAC (Shao's
    ground plane -> camera pitch), or None when the plane holds too few points."""
    if len(points_camera) < 3:
        return None
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points_camera))
    o3d.utility.random.seed(seed)
    plane, inliers = pc.segment_plane(threshold_m, 3, 200)
    if len(inliers) < min_inlier_ratio * len(points_camera):
        return None
    n = np.asarray(plane[:3], dtype=np.float64)
    n /= np.linalg.norm(n)
    # the camera (origin) is above the ground: n . 0 + d > 0 on the up side
    return n if plane[3] > 0 else -n


class PoseBuffer:
    """Recent stamped poses; interpolates the pose at a cloud's stamp.

    Args:
        max_len: poses kept.
        max_extrapolation_s: how far [s] past the newest pose a query may be answered (with the
            newest pose).
    """

    def __init__(self, max_len: int = 200, max_extrapolation_s: float = 0.2) -> None:
        self._t: Deque[float] = collections.deque(maxlen=max_len)
        self._T: Deque[np.ndarray] = collections.deque(maxlen=max_len)
        self.max_extrapolation_s = float(max_extrapolation_s)

    def __len__(self) -> int:
        return len(self._t)

    @property
    def latest(self) -> Optional[Tuple[float, np.ndarray]]:
        return (self._t[-1], self._T[-1]) if self._t else None

    def clear(self) -> None:
        self._t.clear()
        self._T.clear()

    def add(self, stamp_s: float, T: np.ndarray) -> None:
        """Append a pose; stamps must increase (ValueError otherwise)."""
        T = _check_T(T, 'odometry pose')
        if not np.isfinite(stamp_s):
            raise ValueError('odometry stamp is not finite')
        if self._t and stamp_s <= self._t[-1]:
            raise ValueError(f'odometry went back in time ({stamp_s:.3f} s after '
                             f'{self._t[-1]:.3f} s)')
        self._t.append(float(stamp_s))
        self._T.append(T)

    def at(self, stamp_s: float) -> np.ndarray:
        """Pose at ``stamp_s`` (linear / slerp between neighbours); ValueError if not covered."""
        if not self._t:
            raise ValueError('no odometry received yet')
        t = np.asarray(self._t)
        if stamp_s < t[0]:
            raise ValueError(f'no odometry as old as {stamp_s:.3f} s (oldest {t[0]:.3f} s)')
        if stamp_s >= t[-1]:
            if stamp_s - t[-1] > self.max_extrapolation_s:
                raise ValueError(f'odometry is stale: newest {t[-1]:.3f} s, cloud at '
                                 f'{stamp_s:.3f} s')
            return self._T[-1].copy()
        k = int(np.searchsorted(t, stamp_s, side='right'))
        t0, t1 = t[k - 1], t[k]
        T0, T1 = self._T[k - 1], self._T[k]
        a = (stamp_s - t0) / (t1 - t0)
        out = np.eye(4)
        out[:3, 3] = (1 - a) * T0[:3, 3] + a * T1[:3, 3]
        rots = Rotation.from_matrix(np.stack([T0[:3, :3], T1[:3, :3]]))
        out[:3, :3] = Slerp([0.0, 1.0], rots)([a]).as_matrix()[0]
        return out


class OdometryGate:
    """Rejects dead-reckoning samples that go back in time or jump.

    Args:
        max_speed_m_s: fastest plausible body speed [m/s] between consecutive samples.
        max_yaw_rate_deg_s: fastest plausible rotation rate [deg/s].
        jump_floor_m: position change [m] always allowed (covers stamp jitter).
    """

    def __init__(self, max_speed_m_s: float = 1.0, max_yaw_rate_deg_s: float = 180.0,
                 jump_floor_m: float = 0.02) -> None:
        self.max_speed_m_s = max_speed_m_s
        self.max_rate_rad_s = np.radians(max_yaw_rate_deg_s)
        self.jump_floor_m = jump_floor_m
        self._last: Optional[Tuple[float, np.ndarray]] = None

    def check(self, stamp_s: float, T_odom_base: np.ndarray) -> None:
        """Accept (and remember) a sample or raise ValueError naming the problem."""
        T = _check_T(T_odom_base, 'odometry pose')
        if not np.isfinite(stamp_s):
            raise ValueError('odometry stamp is not finite')
        if self._last is not None:
            t0, T0 = self._last
            dt = stamp_s - t0
            if dt <= 0.0:
                raise ValueError(f'odometry went back in time ({stamp_s:.3f} s after '
                                 f'{t0:.3f} s)')
            d = float(np.linalg.norm(T[:3, 3] - T0[:3, 3]))
            if d > self.jump_floor_m + self.max_speed_m_s * dt:
                raise ValueError(f'odometry jumped {d:.3f} m in {dt:.3f} s')
            ang = angle_between(T0[:3, :3], T[:3, :3])
            if ang > np.radians(2.0) + self.max_rate_rad_s * dt:
                raise ValueError(f'odometry turned {np.degrees(ang):.1f} deg in {dt:.3f} s')
        self._last = (float(stamp_s), T)


def depth_weights(z_m: np.ndarray, focal_baseline_px_m: Optional[float],
                  disparity_sigma_px: float, floor_m: float) -> np.ndarray:
    """Inverse variances [1/m^2] of points at z-depths ``z_m`` [m] of a stereo camera.

    Triangulation gives ``Z = f b / d``, so a disparity error ``sigma_d`` [px] becomes
    ``sigma_z = Z^2 sigma_d / (f b)``; ``floor_m`` is added in quadrature for the errors that
    do not grow with range. How much of a depth error becomes height error depends on the ray
    and on the local slope (unknown when fusing); it is left out (scaling the weights by the
    ray's vertical part alone over-trusts grazing rays on sloped ground). All weights are 1
    when ``focal_baseline_px_m`` is None or ``disparity_sigma_px`` is 0.
    """
    z = np.asarray(z_m, dtype=np.float64)
    if not focal_baseline_px_m or disparity_sigma_px <= 0:
        return np.ones(z.shape)
    sz = z * z * (disparity_sigma_px / focal_baseline_px_m)
    return 1.0 / (sz * sz + floor_m * floor_m)


def _information(T_prior: np.ndarray, points: np.ndarray, normals: np.ndarray,
                 weights: Optional[np.ndarray]) -> Tuple[np.ndarray, float]:
    """The normalised point-to-plane information ``H`` (6x6) about the prior's origin and the
    lever arm ``L`` that makes its rotation part unitless (see remove_degenerate_motion)."""
    c = T_prior[:3, 3]
    d = points - c
    w = np.ones(len(d)) if weights is None else np.asarray(weights, dtype=np.float64)
    w = w / w.sum()
    L = float(np.sqrt(w @ np.sum(d * d, axis=1))) or 1.0
    J = np.hstack([np.cross(d, normals) / L, normals])
    return (J * w[:, None]).T @ J, L


def _motion(T: np.ndarray, T_prior: np.ndarray, L: float) -> np.ndarray:
    """``T`` relative to ``T_prior`` as ``[rotation vector * L, translation]`` (map frame,
    rotation about the prior's origin)."""
    R_delta = T[:3, :3] @ T_prior[:3, :3].T
    return np.concatenate([Rotation.from_matrix(R_delta).as_rotvec() * L,
                           T[:3, 3] - T_prior[:3, 3]])


def _from_motion(x: np.ndarray, T_prior: np.ndarray, L: float) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = Rotation.from_rotvec(x[:3] / L).as_matrix() @ T_prior[:3, :3]
    out[:3, 3] = T_prior[:3, 3] + x[3:]
    return out


def blend_yaw(T_icp: np.ndarray, T_prior: np.ndarray, points: np.ndarray, normals: np.ndarray,
              gain: float, weights: Optional[np.ndarray] = None) -> np.ndarray:
    """Keep ``gain`` of ICP's yaw correction and move the rest of the pose along ICP's cost
    valley to match.

    With the prior's rotation from the IMU, two sources measure the yaw change since the last
    accepted capture: the IMU, to its noise and the drift of its yaw over one interval, and
    ICP, whose yaw is the least constrained direction on a narrow view of rough ground and
    whose errors are fused into the model it aligns the next capture to, so that they add up
    (a walk turning on the rocks ended 2.5 deg and 23 mm off). A constant gain is the steady
    state of the Kalman filter of the two; the IMU's yaw drift ``b`` leaves about
    ``b dt (1 - gain) / gain`` of lag.

    The point-to-plane cost near ICP's optimum is ``(x - x_icp)^T H (x - x_icp)`` in the
    coordinates of :func:`remove_degenerate_motion` (map-frame rotation about the prior's
    origin times ``L``, translation); with the yaw fixed at ``gain`` of ICP's, the other five
    take their conditional minimum ``x_o = x_icp,o - H_oo^+ H_oy dy``, so that a yaw change
    does not swing the aligned cloud off the model about the camera.

    Args:
        T_icp, T_prior: 4x4 poses of the same frame (map <- sensor); ``T_prior``'s rotation
            is the IMU's.
        points: ``(N, 3)`` aligned source points in the map frame [m]; normals: their model
            normals ``(N, 3)``; weights: ``(N,)`` or None (as remove_degenerate_motion).
        gain: share of ICP's yaw kept, in [0, 1].
    """
    if not 0.0 <= gain <= 1.0:
        raise ValueError(f'yaw gain must be in [0, 1], got {gain}')
    if gain == 1.0 or len(points) == 0:
        return T_icp
    H, L = _information(T_prior, points, normals, weights)
    x = _motion(T_icp, T_prior, L)
    dy = (gain - 1.0) * x[2]                  # the map z (yaw) part of the rotation
    other = [0, 1, 3, 4, 5]
    x = x.copy()
    x[2] += dy
    x[other] -= np.linalg.pinv(H[np.ix_(other, other)], rcond=1e-6) @ (H[other, 2] * dy)
    return _from_motion(x, T_prior, L)


def remove_degenerate_motion(T_icp: np.ndarray, T_prior: np.ndarray, points: np.ndarray,
                             normals: np.ndarray, threshold: float,
                             weights: Optional[np.ndarray] = None
                             ) -> Tuple[np.ndarray, np.ndarray, int]:
    """Keep only the part of an ICP correction that the geometry constrains.

    Point-to-plane ICP cannot see motion along directions where the surface has no normal
    component (flat ground: x, y, yaw), and the solver then drifts there freely. The correction
    ``T_icp`` relative to ``T_prior`` (rotation about the prior's origin, translation) is
    projected onto the eigenvectors of the point-to-plane information matrix
    ``H = sum(w_i J_i^T J_i) / sum(w_i)``, ``J_i = [((p_i - c) x n_i) / L, n_i]`` (rotation
    made unitless by the cloud's weighted RMS lever arm ``L``), whose eigenvalues reach
    ``threshold``; in the other directions the prior is kept (solution remapping, Zhang et al.,
    ICRA 2016). On a flat approach only z, roll and pitch survive.

    Args:
        T_icp, T_prior: 4x4 poses of the same frame (map <- sensor).
        points: ``(N, 3)`` aligned source points in the map frame [m]; normals: their model
            normals ``(N, 3)``.
        threshold: smallest eigenvalue [-] (H is normalised, eigenvalues in [0, 1]) a
            direction needs to be corrected.
        weights: ``(N,)`` per-point weights (inverse variances, :func:`depth_weights`), so
            that noisy far points do not fake constraints; None = equal.

    Returns:
        ``(T, eigenvalues (6,) ascending, number of directions left at the prior)``.
    """
    H, L = _information(T_prior, points, normals, weights)
    w, V = np.linalg.eigh(H)
    good = w >= threshold
    if good.all():
        return T_icp, w, 0
    Vg = V[:, good]
    x = _motion(T_icp, T_prior, L)
    return _from_motion(Vg @ (Vg.T @ x), T_prior, L), w, int((~good).sum())


# constrained_icp stops when a step (and the reset to the prior before it) moves the pose less
# than this in the normalised coordinates: 0.1 mm, or 0.1 mrad at the cloud's RMS lever arm
# (stereo noise is millimetres; with 1e-5 noisy stereo fits took 35 iterations in the median,
# the correspondences trading places, for the same pose to 0.1 mm)
_STEP_TOL = 1e-4

# constrained_icp's first phase ends when the mean squared residual changes by less than this
# share between two iterations: it only measures the noise level, and on flat ground it would
# go on sliding along the unconstrained directions (the second phase resets them) to the
# iteration cap, a fraction of a millimetre per step, for the same residual
_NOISE_REL_TOL = 0.01


@dataclass
class IcpResult:
    """What :func:`constrained_icp` found: the pose, and the fit at that pose."""

    T: np.ndarray                 # 4x4 map <- camera
    correspondences: np.ndarray   # (K, 2) int: source row, model row (at T)
    fitness: float                # K / source points
    rmse_m: float                 # point-to-plane RMSE over the correspondences [m]
    eigenvalues: np.ndarray       # (6,) ascending, normalised information (last iteration)
    n_degenerate: int             # directions kept at the prior
    information_limit: float      # the eigenvalue a direction needed
    iterations: int
    #: orthonormal basis (6, k) of the motion directions the last iteration constrained, in
    #: the coordinates of remove_degenerate_motion ([rotation vector * L, translation], map
    #: frame, about the prior's camera origin); (6, 0) when none was
    observed: np.ndarray = field(default_factory=lambda: np.zeros((6, 0)))


def _tukey_weights(r: np.ndarray, k: float) -> np.ndarray:
    """Open3D's TukeyLoss weight ``(1 - (r / k)^2)^2`` inside ``|r| <= k``, 0 outside."""
    u = np.clip(1.0 - (r / k) ** 2, 0.0, None)
    return u * u


def _robust_weights(r: np.ndarray, kernel: str, k: float) -> np.ndarray:
    """IRLS weights of Open3D's robust kernels (``_kernel``) for residuals ``r`` [m]."""
    a = np.abs(r)
    if kernel == 'tukey':
        return _tukey_weights(r, k)
    if kernel == 'huber':
        return np.where(a <= k, 1.0, k / np.maximum(a, 1e-300))
    if kernel == 'cauchy':
        return 1.0 / (1.0 + (r / k) ** 2)
    if kernel == 'gm':
        return k / (k + r * r) ** 2
    if kernel == 'l1':
        return 1.0 / np.maximum(a, 1e-12)
    return np.ones_like(r)


def fake_information(d: np.ndarray, w: np.ndarray, L: float) -> np.ndarray:
    """The normalised point-to-plane information (6x6, coordinates of
    :func:`remove_degenerate_motion`) that model normals tilted by unit-variance noise in
    map x and y would put into correspondences at lever arms ``d`` ``(N, 3)`` (point minus
    the prior's origin) with weights ``w`` ``(N,)`` summing to 1: ``sum_i w_i sum_a j_a j_a^T``,
    ``j_a = [(d_i x e_a) / L, e_a]``, a in {x, y}. Times the slope variance of the normals it
    is what noise alone contributes: horizontal-ish normals that fix x, y and yaw on flat
    ground, and (through the lever arm) a little roll and pitch, never z."""
    # Closed form from the weighted moments of d (~20 us instead of two (N, 6) products):
    # j_x = [0, dz/L, -dy/L, 1, 0, 0] and j_y = [-dz/L, 0, dx/L, 0, 1, 0].
    d = np.asarray(d, dtype=np.float64)
    w = np.asarray(w, dtype=np.float64)
    W = float(w.sum())
    m = (w @ d) / L                          # first moments / L
    S = (d.T @ (d * w[:, None])) / (L * L)   # second moments / L^2
    F = np.zeros((6, 6))
    F[0, 0] = F[1, 1] = S[2, 2]
    F[2, 2] = S[0, 0] + S[1, 1]
    F[1, 2] = F[2, 1] = -S[1, 2]
    F[0, 2] = F[2, 0] = -S[0, 2]
    F[1, 3] = F[3, 1] = m[2]
    F[2, 3] = F[3, 2] = -m[1]
    F[0, 4] = F[4, 0] = -m[2]
    F[2, 4] = F[4, 2] = m[0]
    F[3, 3] = F[4, 4] = W
    return F


def _observed_directions(H: np.ndarray, d: np.ndarray, w: np.ndarray, L: float,
                         threshold: float, noise_gain: float, noise_var: float
                         ) -> Tuple[np.ndarray, np.ndarray, int]:
    """Basis ``(6, k)`` of the motion directions a fit constrains, H's eigenvalues
    (ascending) and ``6 - k``. A direction needs an eigenvalue of ``H`` of at least
    ``threshold`` and, when ``noise_gain * noise_var`` > 0, ``noise_gain`` times the
    information noise of slope variance ``noise_var`` would fake there (the generalised
    eigenproblem ``H v = lambda noise_var F v``, :func:`fake_information`)."""
    eig, V = np.linalg.eigh(H)
    good = eig >= threshold if threshold > 0 else np.ones(6, bool)
    Vg = V[:, good]
    if noise_gain > 0 and noise_var > 0 and Vg.shape[1]:
        # inside the geometric subspace: signal-to-noise of each direction
        F = noise_var * fake_information(d, w, L)
        Hg, Fg = Vg.T @ H @ Vg, Vg.T @ F @ Vg
        Fg = Fg + 1e-12 * max(np.trace(Hg), 1e-12) * np.eye(len(Fg))
        from scipy.linalg import eigh as _geigh
        snr, U = _geigh(Hg, Fg)
        bad = U[:, snr < noise_gain]
        if bad.shape[1]:
            # keep what is orthogonal to every direction that noise could explain (the
            # generalised eigenvectors are not orthogonal: taking the good ones' span would
            # keep some of the bad ones in it)
            q = np.linalg.svd(bad, full_matrices=True)[0]
            Vg = Vg @ q[:, bad.shape[1]:]
    return Vg, eig, 6 - Vg.shape[1]


class ModelIndex:
    """The coarse model's nearest-point search for ICP correspondences: ``query(x, k=1,
    distance_upper_bound=d)`` as scipy's ``cKDTree`` answers it (the nearest model point
    strictly within ``d``: distances, inf and row M where none).

    ICP asks ~10 times per capture for the nearest of ~10k model points to each of ~2k source
    points within ``max_correspondence_m`` (4 cm); cKDTree spends ~1 us per point there (~20
    ms per capture). With the compiled kernels the model's points are sorted into x-y columns
    a little wider than ``bound_m / 2`` and a query scans the 5 x 5 columns around it nearest
    first, skipping those farther than its best match so far
    (:func:`terrain_perception._mapping_kernels.nearest_in_columns`; any bound: the columns
    within reach), ~3x faster than cKDTree with the same rows and bitwise the same distances
    (the squared distance summed as cKDTree sums it, the same strict bound), except that among
    equally near points the lowest row wins where cKDTree's order is its tree's. Non-finite
    queries are refused, as cKDTree refuses them. Without them
    (``TERRAIN_MAPPING_NUMBA=0``), or for ``k != 1`` or no bound, a cKDTree answers; so does
    a model with a non-finite point or whose columns would not fit a modest array (points
    spread over kilometres).
    """

    MAX_COLUMNS = 20_000_000

    def __init__(self, points: np.ndarray, bound_m: float):
        pts = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
        if not bound_m > 0:
            raise ValueError(f'ModelIndex: bound_m must be > 0, got {bound_m}')
        self.n = len(pts)
        self.data = pts
        self._tree: Optional[cKDTree] = None
        self._kern = _kernels
        self._cols = None
        if self._kern is None or self.n == 0 or not np.all(np.isfinite(pts)):
            return
        cell = 0.5 * float(bound_m) * (1.0 + 1e-6)
        lo = pts[:, :2].min(axis=0)
        ij = np.floor((pts[:, :2] - lo) / cell).astype(np.int64)
        nx, ny = int(ij[:, 0].max()) + 1, int(ij[:, 1].max()) + 1
        if nx * ny > self.MAX_COLUMNS:
            return
        col = ij[:, 0] * ny + ij[:, 1]
        order = np.argsort(col, kind='stable')
        starts = np.zeros(nx * ny + 1, dtype=np.int64)
        np.cumsum(np.bincount(col, minlength=nx * ny), out=starts[1:])
        self._cols = (np.ascontiguousarray(pts[order]), order.astype(np.int64), starts,
                      float(lo[0]), float(lo[1]), cell, nx, ny)

    @property
    def compiled(self) -> bool:
        """Whether queries run the compiled column search (else a cKDTree)."""
        return self._cols is not None

    def _kdtree(self) -> cKDTree:
        if self._tree is None:
            self._tree = cKDTree(self.data)
        return self._tree

    def query(self, x: np.ndarray, k: int = 1, distance_upper_bound: float = np.inf):
        if self._cols is None or k != 1 or not np.isfinite(distance_upper_bound):
            return self._kdtree().query(x, k=k, distance_upper_bound=distance_upper_bound)
        q = np.ascontiguousarray(x, dtype=np.float64)
        if q.ndim != 2 or q.shape[1] != 3:
            raise ValueError(f'ModelIndex.query: points must be (N, 3), got {q.shape}')
        if not np.isfinite(q).all():
            raise ValueError('ModelIndex.query: points must be finite (NaN or inf given)')
        dist = np.empty(len(q))
        idx = np.empty(len(q), dtype=np.int64)
        pts, order, starts, x0, y0, cell, nx, ny = self._cols
        self._kern.nearest_in_columns(pts, order, starts, x0, y0, cell, nx, ny, q,
                                      float(distance_upper_bound), dist, idx)
        return dist, idx


def _plane_matches(src: np.ndarray, model: np.ndarray, model_normals: np.ndarray,
                   tree: cKDTree, T: np.ndarray, max_dist_m: float):
    """The source points at pose ``T`` (map frame), the rows of those with a model point
    within ``max_dist_m``, their nearest model rows, its normals and the point-to-plane
    residuals ``n . (p - q)`` [m]."""
    p = transform_points(T, src)
    dist, idx = tree.query(p, k=1, distance_upper_bound=max_dist_m)
    ok = np.isfinite(dist)
    si = np.flatnonzero(ok)
    mi = idx[ok]
    n = model_normals[mi]
    r = np.einsum('ij,ij->i', p[si] - model[mi], n)
    return p, si, mi, n, r


def constrained_icp(src: np.ndarray, model: np.ndarray, model_normals: np.ndarray,
                    tree: cKDTree, T_prior: np.ndarray, config: 'MapperConfig',
                    depth_w: Optional[np.ndarray] = None) -> IcpResult:
    """Point-to-plane ICP that keeps the prior along the directions the geometry does not
    constrain, in every iteration.

    Each iteration takes the nearest model point within ``max_correspondence_m`` of every
    source point, the point-to-plane residuals ``r_i = n_i . (T s_i - q_i)`` and their robust
    weights (``robust_kernel``), then:

    1. the normalised information ``H`` of the correspondences (:func:`_information`, about
       the prior's origin, depth weights) and its eigenvectors; a direction counts when its
       eigenvalue reaches ``max(degeneracy_threshold, degeneracy_noise_gain (rmse /
       normal_radius_m)^2)`` (what height noise of the residual's size fakes through the model
       normals), as in :func:`remove_degenerate_motion`;
    2. the pose's offset from the prior is projected onto those directions (the others return
       to the prior) and one Gauss-Newton step of the robust point-to-plane cost is taken
       inside them.

    A phase ends when a step (and the reset before it) moves the pose less than
    ``_STEP_TOL``, or the pose comes back to where it was two steps before (a 2-cycle of
    correspondences trading places); the first phase also when its mean squared residual
    changes by less than ``_NOISE_REL_TOL`` (it is only there for the noise level).

    Open3D's ICP instead converges with all six directions free and the unconstrained ones
    are reset afterwards; on a view of mostly flat ground it slides along them by centimetres,
    and the fit it reports (and the correspondences the residual guard used) belongs to that
    slid pose: among box-shaped stones a slide puts the stones' sides on the wrong faces, and
    the reset pose is then rejected for an RMSE it does not have (stones-15cm, FROG-I, depth
    clouds: 11 rejections in a row at the stones' far edge, then lost).

    Args:
        src: ``(N, 3)`` source points, camera frame [m]; model, model_normals: ``(M, 3)`` map
            frame, with ``tree`` a :class:`ModelIndex` (or a cKDTree) of ``model``.
        T_prior: 4x4 ``T_map_camera`` prior (the start and the anchor of the kept directions).
        depth_w: ``(N,)`` per-point depth weights (:func:`depth_weights`) or None.
    """
    c = config
    n_src = len(src)
    T_prior = np.asarray(T_prior, dtype=np.float64)
    centre = T_prior[:3, 3]
    p_prior = transform_points(T_prior, src)
    d0 = p_prior - centre
    L = float(np.sqrt(np.mean(np.sum(d0 * d0, axis=1)))) or 1.0
    x = np.zeros(6)
    T = T_prior.copy()
    eig = np.full(6, np.nan)
    limit = float('nan')
    n_deg = 0
    Vg = np.zeros((6, 0))
    it = 0
    dw = np.ones(n_src) if depth_w is None else np.asarray(depth_w, dtype=np.float64)

    def match(T_cur):
        return _plane_matches(src, model, model_normals, tree, T_cur, c.max_correspondence_m)

    total = 0
    T_matched = None              # the pose of the last match's correspondences
    noise_var = 0.0
    # phase 0 converges with the geometric threshold alone; phase 1 then also needs each kept
    # direction to carry degeneracy_noise_gain x the information that normals tilted by noise
    # would fake (fake_information), the noise level taken once from phase 0's converged
    # residual (from the prior's residual, 2 cm off, every direction would look unobserved;
    # updated per iteration, a reset along one direction raises the residual, which resets
    # the next)
    for phase in (0, 1):
        x_before = None          # the pose two steps back (a 2-cycle's other end)
        last_ms = None
        settle = phase == 0 and c.degeneracy_noise_gain > 0   # phase 1 follows
        for it in range(1, c.max_iterations + 1):
            total += 1
            p, si, mi, n, r = match(T)
            T_matched = T
            if len(si) < 6:
                break
            ms = float(np.mean(r * r))
            if settle and last_ms is not None and abs(last_ms - ms) <= _NOISE_REL_TOL * ms:
                break            # the residual (all phase 0 is for) has settled
            last_ms = ms
            # 1. the directions the geometry constrains (about the prior's origin, scaled by L)
            d = p[si] - centre
            J = np.hstack([np.cross(d, n) / L, n])
            w_info = dw[si] / dw[si].sum()
            H = (J * w_info[:, None]).T @ J
            Vg, eig, n_deg = _observed_directions(H, d, w_info, L, c.degeneracy_threshold,
                                                  c.degeneracy_noise_gain, noise_var)
            # 2. back to the prior along the others, then a Gauss-Newton step inside these
            x_proj = Vg @ np.linalg.lstsq(Vg, x, rcond=None)[0] if Vg.shape[1] else 0.0 * x
            r_lin = r + J @ (x_proj - x)
            w = _robust_weights(r_lin, c.robust_kernel, c.kernel_scale_m) * dw[si]
            if Vg.shape[1] == 0 or not np.any(w > 0):
                x = x_proj
                T = _from_motion(x, T_prior, L)
                break
            Jg = J @ Vg
            A = (Jg * w[:, None]).T @ Jg
            b = -(Jg * w[:, None]).T @ r_lin
            try:
                y = np.linalg.solve(A, b)
            except np.linalg.LinAlgError:
                y = np.linalg.lstsq(A, b, rcond=None)[0]
            step = Vg @ y
            moved = float(np.linalg.norm(x_proj - x))
            x_two_back, x_before = x_before, x
            x = x_proj + step
            T = _from_motion(x, T_prior, L)
            if np.linalg.norm(step) < _STEP_TOL and moved < _STEP_TOL:
                break
            if x_two_back is not None and np.linalg.norm(x - x_two_back) < _STEP_TOL:
                break        # a 2-cycle: two correspondence sets trade places
        if c.degeneracy_noise_gain <= 0 or phase == 1:
            break
        if T is not T_matched:
            p, si, mi, n, r = match(T)
        if len(si) < 6:
            break
        noise_var = float(np.mean(r * r)) / c.normal_radius_m ** 2
    limit = max(c.degeneracy_threshold, c.degeneracy_noise_gain * noise_var)
    it = total
    if T is not T_matched:
        p, si, mi, n, r = match(T)
    corr = np.stack([si, mi], axis=1) if len(si) else np.zeros((0, 2), np.int64)
    rmse = float(np.sqrt(np.mean(r * r))) if len(si) else float('inf')
    return IcpResult(T, corr, len(si) / max(n_src, 1), rmse, eig, n_deg, limit, it, Vg)


def relocalisation_starts(radius_m: float, directions: int) -> np.ndarray:
    """x-y offsets [m] of :func:`multi_start_icp`'s extra starts: ``directions`` evenly spaced
    directions on rings of ``radius_m / 2`` and ``radius_m`` (``(2 directions, 2)``)."""
    a = np.arange(int(directions)) * 2.0 * np.pi / max(int(directions), 1)
    ring = np.stack([np.cos(a), np.sin(a)], axis=1)
    return np.concatenate([0.5 * radius_m * ring, radius_m * ring])


def _truncated_residuals(src: np.ndarray, model: np.ndarray, model_normals: np.ndarray,
                         tree: cKDTree, T: np.ndarray, max_dist_m: float) -> np.ndarray:
    """Point-to-plane residual [m] of every source point at pose ``T`` (NaN: no model point
    within ``max_dist_m``)."""
    _, si, _, _, r_matched = _plane_matches(src, model, model_normals, tree, T, max_dist_m)
    r = np.full(len(src), np.nan)
    r[si] = r_matched
    return r


def choose_alignment(results: 'list[IcpResult]', src: np.ndarray, model: np.ndarray,
                     model_normals: np.ndarray, tree: cKDTree, config: 'MapperConfig'
                     ) -> int:
    """Index of the alignment :func:`multi_start_icp` keeps; ``results[0]`` is the ICP from
    the prior.

    Fitness (the share of source points with a model point nearby) cannot choose: a start
    that shifts the view's unmapped part (the ground ahead) onto mapped ground matches more
    points, and on stones-15cm the best fit left a correct prior in 44 % of trials
    (``terrain-bench icp --basin``). Each alternative is instead compared with the prior's
    ICP on the points both match: their mean squared residual, truncated at
    ``max_correspondence_m / 2``. An alternative wins when its cost is below
    ``relocalise_cost_ratio`` of the prior's and its RMS is lower by at least
    ``relocalise_min_gain_m`` (flat ground fits every shift equally well, to micrometres).
    Of the winners within 10 % (or ``relocalise_min_gain_m``) of the lowest cost, the pose
    nearest the prior's ICP: a start offset along a direction the view does not constrain
    stays offset there and fits as well."""
    c = config
    k2 = (0.5 * c.max_correspondence_m) ** 2
    res = [_truncated_residuals(src, model, model_normals, tree, r.T, c.max_correspondence_m)
           for r in results]
    base = res[0]
    min_common = max(6, int(0.1 * len(src)))
    wins = []
    for i in range(1, len(results)):
        both = np.isfinite(base) & np.isfinite(res[i])
        if both.sum() < min_common:
            continue
        c0 = float(np.mean(np.minimum(base[both] ** 2, k2)))
        ci = float(np.mean(np.minimum(res[i][both] ** 2, k2)))
        if ci < c.relocalise_cost_ratio * c0 and \
                np.sqrt(c0) - np.sqrt(ci) > c.relocalise_min_gain_m:
            wins.append((i, np.sqrt(ci)))
    if not wins:
        return 0
    lowest = min(w for _, w in wins)
    near = [i for i, w in wins if w <= max(1.1 * lowest, lowest + c.relocalise_min_gain_m)]
    t0 = results[0].T[:3, 3]
    return min(near, key=lambda i: float(np.linalg.norm(results[i].T[:3, 3] - t0)))


def multi_start_icp(src: np.ndarray, model: np.ndarray, model_normals: np.ndarray,
                    tree: cKDTree, T_prior: np.ndarray, config: 'MapperConfig',
                    depth_w: Optional[np.ndarray] = None,
                    first: Optional[IcpResult] = None) -> Tuple[IcpResult, int]:
    """:func:`constrained_icp` from the prior and from the prior shifted by each of
    :func:`relocalisation_starts` (``relocalise_radius_m``, ``relocalise_directions``), the
    alignment :func:`choose_alignment` keeps and its index (0: the prior's). ``first``: the
    ICP from the prior if already run. ICP's basin on the stones is about 3 cm: from a prior
    10 cm off it never came back, the multi-start on every view that constrains x-y."""
    c = config
    runs = [first if first is not None else
            constrained_icp(src, model, model_normals, tree, T_prior, c, depth_w)]
    # the starts search on an evenly spread subset (the same for all), the winner is refined
    # on every point
    sub = np.arange(len(src))
    if len(src) > c.relocalise_max_points:
        sub = np.linspace(0, len(src) - 1, c.relocalise_max_points).astype(np.int64)
    w_sub = None if depth_w is None else np.asarray(depth_w)[sub]
    c_start = dataclasses.replace(c, max_iterations=min(c.max_iterations,
                                                        c.relocalise_max_iterations))
    for st in relocalisation_starts(c.relocalise_radius_m, c.relocalise_directions):
        T0 = np.array(T_prior, dtype=np.float64)
        T0[:2, 3] += st
        runs.append(constrained_icp(src[sub], model, model_normals, tree, T0, c_start, w_sub))
    i = choose_alignment(runs, src, model, model_normals, tree, c)
    if i == 0:
        return runs[0], 0
    return constrained_icp(src, model, model_normals, tree, runs[i].T, c, depth_w), i


def height_map_normals(h: np.ndarray, origin_xy: np.ndarray, resolution_m: float,
                       xy: np.ndarray, half_width_cells: int) -> np.ndarray:
    """Unit surface normals ``(N, 3)`` (z up) of a height grid ``h`` ``(nx, ny)`` [m] at world
    ``xy`` ``(N, 2)`` [m], from central differences over ``+-half_width_cells`` (narrowed where
    neighbours are unknown); NaN off the grid or where no difference exists."""
    nx, ny = h.shape
    ij = np.floor((xy - np.asarray(origin_xy)) / resolution_m).astype(np.int64)
    i = np.clip(ij[:, 0], 0, nx - 1)
    j = np.clip(ij[:, 1], 0, ny - 1)
    gx = np.full(len(xy), np.nan)
    gy = np.full(len(xy), np.nan)
    for k in range(max(1, int(half_width_cells)), 0, -1):
        ip, im = np.minimum(i + k, nx - 1), np.maximum(i - k, 0)
        jp, jm = np.minimum(j + k, ny - 1), np.maximum(j - k, 0)
        with np.errstate(invalid='ignore', divide='ignore'):
            ex = (h[ip, j] - h[im, j]) / ((ip - im) * resolution_m)
            ey = (h[i, jp] - h[i, jm]) / ((jp - jm) * resolution_m)
        gx = np.where(np.isnan(gx), ex, gx)
        gy = np.where(np.isnan(gy), ey, gy)
    outside = (ij[:, 0] < 0) | (ij[:, 0] >= nx) | (ij[:, 1] < 0) | (ij[:, 1] >= ny)
    gx[outside] = np.nan
    n = np.stack([-gx, -gy, np.ones_like(gx)], axis=1)
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def cloud_height_normals(points: np.ndarray, resolution_m: float,
                         half_width_cells: int) -> np.ndarray:
    """Normals ``(N, 3)`` of map-frame points ``(N, 3)`` [m] from their own 2.5-D height grid
    (mean z per ``resolution_m`` cell; see :func:`height_map_normals`). Terrain is a height
    field, so this matches PCA normals at a fraction of the cost."""
    if len(points) == 0:
        return np.zeros((0, 3))
    lo = points[:, :2].min(axis=0)
    k = _kernels
    if (k is not None and points.dtype == np.float64 and points.ndim == 2
            and points.shape[1] == 3 and len(points) and np.all(np.isfinite(lo))
            and np.all(np.isfinite(points[:, :2].max(axis=0)))):
        # one compiled pass (bitwise the numpy steps below; finite x-y only)
        return k.cloud_height_normals(np.ascontiguousarray(points), float(lo[0]),
                                      float(lo[1]), float(resolution_m), int(half_width_cells))
    ij = np.floor((points[:, :2] - lo) / resolution_m).astype(np.int64)
    shape = (int(ij[:, 0].max()) + 1, int(ij[:, 1].max()) + 1)
    lin = ij[:, 0] * shape[1] + ij[:, 1]
    n = np.bincount(lin, minlength=shape[0] * shape[1])
    with np.errstate(invalid='ignore', divide='ignore'):
        h = (np.bincount(lin, weights=points[:, 2], minlength=n.size) / n).reshape(shape)
    return height_map_normals(h, lo, resolution_m, points[:, :2], half_width_cells)


def _kernel(config: MapperConfig):
    k = config.kernel_scale_m
    return {'none': lambda: None, 'l1': _REG.L1Loss, 'huber': lambda: _REG.HuberLoss(k),
            'tukey': lambda: _REG.TukeyLoss(k), 'cauchy': lambda: _REG.CauchyLoss(k),
            'gm': lambda: _REG.GMLoss(k)}[config.robust_kernel]()


def make_estimation(config: MapperConfig):
    """Open3D transformation estimation for ``config.icp_method`` and its robust kernel."""
    kernel = _kernel(config)
    if config.icp_method == 'point_to_point':
        return _REG.TransformationEstimationPointToPoint()
    if kernel is None:
        return _REG.TransformationEstimationPointToPlane()
    return _REG.TransformationEstimationPointToPlane(kernel)


class FineHeightMap:
    """Per-cell statistics of height samples on a fixed-size window that moves by whole cells.

    Args:
        resolution_m: cell size [m].
        shape: (nx, ny) cells.
        origin_xy: world position [m] of the window's minimum corner (a multiple of the
            resolution keeps every cell on one global lattice).
        estimator: 'mean' (mean sample height) or 'plane' (per-cell least-squares plane
            ``z = h + gx dx + gy dy`` evaluated at the cell centre; falls back to the mean when a
            cell's samples do not span a plane).
        outlier_gate_m: samples of one :meth:`add` farther than this [m] from their cell's
            mean in that batch (computed twice, the second time without the first pass's
            outliers) are dropped (0 = keep all).

    Samples may carry weights (inverse variances, :func:`depth_weights`): the mean, the
    plane and the variance are then weighted (``w`` holds the sum of weights per cell); ``n``
    stays the sample count. Unit weights give the plain statistics.
    """

    _STATS = ('n', 'w', 'mean', 'm2', 'min', 'max', 'last', 'sx', 'sy', 'sxx', 'sxy', 'syy',
              'sxz', 'syz')

    def __init__(self, resolution_m: float, shape: Tuple[int, int],
                 origin_xy: Tuple[float, float], estimator: str = 'mean',
                 outlier_gate_m: float = 0.0) -> None:
        self.resolution_m = float(resolution_m)
        self.outlier_gate_m = float(outlier_gate_m)
        self.shape = (int(shape[0]), int(shape[1]))
        self.origin_xy = np.asarray(origin_xy, dtype=np.float64)
        self.estimator = estimator
        self.s: Dict[str, np.ndarray] = {}
        self.clear()

    def clear(self) -> None:
        for k in self._STATS:
            fill = {'min': np.inf, 'max': -np.inf, 'last': np.nan}.get(k, 0.0)
            self.s[k] = np.full(self.shape, fill, np.float64)

    @property
    def nbytes(self) -> int:
        return int(sum(a.nbytes for a in self.s.values()))

    def _flat_stats(self) -> Optional[Dict[str, np.ndarray]]:
        """1-D views of the statistics for the kernels (None if one is not a C-contiguous
        float64 array, so a view could not write through)."""
        out = {}
        for k, a in self.s.items():
            if a.dtype != np.float64 or not a.flags.c_contiguous or a.shape != self.shape:
                return None
            out[k] = a.reshape(-1)
        return out

    def add(self, points_map: np.ndarray, stamp_s: float,
            weights: Optional[np.ndarray] = None) -> int:
        """Fuse map-frame points ``(N, 3)`` [m] with optional weights ``(N,)`` (> 0, e.g.
        inverse height variances [1/m^2]; None = all 1); returns how many fell on the window.

        Runs the compiled kernels (:mod:`terrain_perception._mapping_kernels`) when loaded,
        else :meth:`_add_numpy`; the two give bitwise the same statistics."""
        k = _kernels
        s = self._flat_stats() if k is not None else None
        pts = np.asarray(points_map)
        if s is None or pts.ndim != 2 or pts.shape[1] < 3 or pts.dtype != np.float64:
            # (numpy keeps float32 heights in float32 arithmetic: the reference decides)
            return self._add_numpy(points_map, stamp_s, weights)
        pts = np.ascontiguousarray(pts)
        n = len(pts)
        wt = (np.ones(n) if weights is None
              else np.ascontiguousarray(weights, dtype=np.float64))
        if wt.shape != (n,):
            return self._add_numpy(points_map, stamp_s, weights)
        lin = np.empty(n, np.int64)
        keep = np.empty(n, bool)
        n_on = k.fine_gate(pts, wt, float(self.origin_xy[0]), float(self.origin_xy[1]),
                           self.resolution_m, self.shape[0], self.shape[1],
                           self.outlier_gate_m, lin, keep)
        if n_on == 0:
            return 0
        z = pts[keep, 2]
        if len(z) == 0:
            return 0
        z0 = float(np.mean(z))  # numpy's pairwise sum, as in _add_numpy
        k.fine_merge(pts, wt, lin, keep, float(self.origin_xy[0]), float(self.origin_xy[1]),
                     self.resolution_m, z0, float(stamp_s), s['n'], s['w'], s['mean'],
                     s['m2'], s['min'], s['max'], s['last'], s['sx'], s['sy'], s['sxx'],
                     s['sxy'], s['syy'], s['sxz'], s['syz'])
        return int(n_on)

    def _add_numpy(self, points_map: np.ndarray, stamp_s: float,
                   weights: Optional[np.ndarray] = None) -> int:
        """:meth:`add` in numpy (the reference of the compiled kernels)."""
        r = self.resolution_m
        f = (points_map[:, :2] - self.origin_xy) / r
        ij = np.floor(f).astype(np.int64)
        ok = ((ij[:, 0] >= 0) & (ij[:, 0] < self.shape[0])
              & (ij[:, 1] >= 0) & (ij[:, 1] < self.shape[1]))
        if not np.any(ok):
            return 0
        ij, f, z = ij[ok], f[ok], points_map[ok, 2]
        wt = np.ones(len(z)) if weights is None else np.asarray(weights, np.float64)[ok]
        lin = ij[:, 0] * self.shape[1] + ij[:, 1]
        size = self.shape[0] * self.shape[1]
        if self.outlier_gate_m > 0:
            # drop samples far from their cell's mean in this capture (stereo mismatches);
            # twice, so that a gross outlier's pull on the first mean is undone
            keep = np.ones(len(z), bool)
            for _ in range(2):
                cnt = np.bincount(lin, weights=wt * keep, minlength=size)
                with np.errstate(invalid='ignore', divide='ignore'):
                    mean = np.bincount(lin, weights=wt * z * keep, minlength=size) / cnt
                keep = np.abs(z - mean[lin]) <= self.outlier_gate_m
            lin, z, f, ij, wt = lin[keep], z[keep], f[keep], ij[keep], wt[keep]
            if len(z) == 0:
                return 0
        # full-length bincounts (no sort), then merge only the touched cells
        nb_all = np.bincount(lin, minlength=size).astype(np.float64)
        cells = np.flatnonzero(nb_all)
        nb = nb_all[cells]
        z0 = float(np.mean(z))  # reference height keeps the squared sums well conditioned
        zs = z - z0
        # offsets from the cell centre [m] for the per-cell plane
        dx = (f[:, 0] - ij[:, 0] - 0.5) * r
        dy = (f[:, 1] - ij[:, 1] - 0.5) * r
        S = np.stack([np.bincount(lin, weights=wt * v, minlength=size)[cells] for v in
                      (np.ones_like(zs), zs, zs * zs, dx, dy, dx * dx, dx * dy, dy * dy,
                       dx * zs, dy * zs)], 1)
        zmin_all = np.full(size, np.inf)
        zmax_all = np.full(size, -np.inf)
        np.minimum.at(zmin_all, lin, z)
        np.maximum.at(zmax_all, lin, z)
        zmin, zmax = zmin_all[cells], zmax_all[cells]
        wb = S[:, 0]
        mb_rel = S[:, 1] / wb
        mb = mb_rel + z0
        m2b = np.maximum(S[:, 2] - wb * mb_rel * mb_rel, 0.0)
        bx, by = S[:, 3], S[:, 4]
        # weighted sums of dx (z - batch mean), dy (z - batch mean)
        bxz = S[:, 8] - mb_rel * bx
        byz = S[:, 9] - mb_rel * by
        s = {k: a.reshape(-1) for k, a in self.s.items()}
        wa, ma = s['w'][cells], s['mean'][cells]
        w = wa + wb
        delta = mb - ma
        # plane sums are kept about the running mean: shift old sums to the new mean
        new_mean = ma + delta * wb / w
        shift_a = ma - new_mean
        shift_b = mb - new_mean
        s['sxz'][cells] += shift_a * s['sx'][cells] + bxz + shift_b * bx
        s['syz'][cells] += shift_a * s['sy'][cells] + byz + shift_b * by
        s['sx'][cells] += bx
        s['sy'][cells] += by
        s['sxx'][cells] += S[:, 5]
        s['sxy'][cells] += S[:, 6]
        s['syy'][cells] += S[:, 7]
        s['m2'][cells] += m2b + delta ** 2 * wa * wb / w
        s['mean'][cells] = new_mean
        s['w'][cells] = w
        s['n'][cells] += nb
        s['min'][cells] = np.minimum(s['min'][cells], zmin)
        s['max'][cells] = np.maximum(s['max'][cells], zmax)
        s['last'][cells] = stamp_s
        return int(ok.sum())

    def _plane_thresholds(self) -> Tuple[float, float]:
        r2 = (0.1 * self.resolution_m) ** 2
        return r2, 0.25 * r2 * r2

    def heights(self) -> np.ndarray:
        """Cell heights [m] (float64, NaN where empty) by the configured estimator."""
        k = _kernels
        s = self._flat_stats() if k is not None else None
        if s is not None:
            out = np.empty(self.shape)
            k.fine_heights(*(s[n] for n in self._STATS), self.estimator == 'plane',
                           *self._plane_thresholds(), out.reshape(-1))
            return out
        return self._heights_numpy()

    def _heights_numpy(self) -> np.ndarray:
        """:meth:`heights` in numpy (the reference of the compiled kernel)."""
        s = self.s
        n = s['n']
        seen = n > 0
        h = np.where(seen, s['mean'], np.nan)
        if self.estimator != 'plane':
            return h
        # normal equations of z - mean = c + gx dx + gy dy (c: offset from the mean)
        with np.errstate(divide='ignore', invalid='ignore'):
            nn = np.where(seen, s['w'], 1.0)
            mx, my = s['sx'] / nn, s['sy'] / nn
            cxx = s['sxx'] / nn - mx * mx
            cxy = s['sxy'] / nn - mx * my
            cyy = s['syy'] / nn - my * my
            cxz = s['sxz'] / nn  # mean of dz is 0 by construction
            cyz = s['syz'] / nn
            det = cxx * cyy - cxy * cxy
            gx = (cyy * cxz - cxy * cyz) / det
            gy = (cxx * cyz - cxy * cxz) / det
            # enough spread: samples cover at least ~1/4 of the cell along both axes
            r2, det_min = self._plane_thresholds()
            good = seen & (n >= 6) & (cxx > r2) & (cyy > r2) & (det > det_min)
            hp = s['mean'] - gx * mx - gy * my
        return np.where(good, hp, h)

    def rays_below(self, points: np.ndarray, origin: np.ndarray, tolerance_m: float,
                   fractions: np.ndarray = np.array([0.5, 0.65, 0.8, 0.95])) -> np.ndarray:
        """Which points ``(N, 3)`` are seen from ``origin`` ``(3,)`` along a ray that passes
        more than ``tolerance_m`` below the mean height of an observed cell at one of
        ``fractions`` of the way: a line of sight through known ground, so the point cannot be
        right. (A point only needs the test if the lowest tested spot of its ray lies below
        the highest observed cell minus the tolerance.)

        Runs the compiled kernel when loaded (bitwise the same answer as the numpy code)."""
        k = _kernels
        pts = np.asarray(points, dtype=np.float64)
        s = self._flat_stats() if k is not None else None
        if s is not None and pts.ndim == 2 and pts.shape[1] == 3 and np.size(fractions) > 0:
            out = np.zeros(len(pts), dtype=bool)
            if len(pts):
                k.rays_below(np.ascontiguousarray(pts),
                             np.ascontiguousarray(origin, dtype=np.float64).reshape(3),
                             np.ascontiguousarray(fractions, dtype=np.float64).reshape(-1),
                             float(tolerance_m), s['n'], s['mean'], float(self.origin_xy[0]),
                             float(self.origin_xy[1]), self.resolution_m, self.shape[0],
                             self.shape[1], out)
            return out
        return self._rays_below_numpy(pts, origin, tolerance_m, fractions)

    def _rays_below_numpy(self, points: np.ndarray, origin: np.ndarray, tolerance_m: float,
                          fractions: np.ndarray = np.array([0.5, 0.65, 0.8, 0.95])
                          ) -> np.ndarray:
        """:meth:`rays_below` in numpy (the reference of the compiled kernel)."""
        pts = np.asarray(points, dtype=np.float64)
        out = np.zeros(len(pts), dtype=bool)
        seen = self.s['n'] > 0
        if len(pts) == 0 or not np.any(seen):
            return out
        o = np.asarray(origin, dtype=np.float64)
        h = np.where(seen, self.s['mean'], np.nan).reshape(-1)
        ceiling = float(np.nanmax(h)) - tolerance_m
        f_hi = float(np.max(fractions))
        with np.errstate(invalid='ignore'):
            cand = np.flatnonzero(o[2] + f_hi * (pts[:, 2] - o[2]) < ceiling)
        if len(cand) == 0:
            return out
        d = pts[cand] - o
        r = self.resolution_m
        nx, ny = self.shape
        bad = np.zeros(len(cand), dtype=bool)
        for f in fractions:
            q = o + f * d
            i = np.floor((q[:, 0] - self.origin_xy[0]) / r).astype(np.int64)
            j = np.floor((q[:, 1] - self.origin_xy[1]) / r).astype(np.int64)
            inside = (i >= 0) & (i < nx) & (j >= 0) & (j < ny)
            hk = np.take(h, np.where(inside, i * ny + j, 0))
            with np.errstate(invalid='ignore'):
                bad |= inside & (q[:, 2] < hk - tolerance_m)      # (NaN cells: False)
        out[cand] = bad
        return out

    def normals_at(self, xy: np.ndarray, half_width_cells: int) -> np.ndarray:
        """Unit normals ``(N, 3)`` of the height map at world ``xy`` [m]
        (see :func:`height_map_normals`)."""
        return height_map_normals(self.heights(), self.origin_xy, self.resolution_m, xy,
                                  half_width_cells)

    def shift(self, di: int, dj: int) -> None:
        """Move the window by whole cells (``+di`` = origin moves +x); uncovered cells empty."""
        if di == 0 and dj == 0:
            return
        nx, ny = self.shape
        for k, a in self.s.items():
            fill = {'min': np.inf, 'max': -np.inf, 'last': np.nan}.get(k, 0.0)
            out = np.full_like(a, fill)
            si0, si1 = max(di, 0), min(nx + di, nx)
            sj0, sj1 = max(dj, 0), min(ny + dj, ny)
            if si1 > si0 and sj1 > sj0:
                out[si0 - di:si1 - di, sj0 - dj:sj1 - dj] = a[si0:si1, sj0:sj1]
            self.s[k] = out
        self.origin_xy = self.origin_xy + np.array([di, dj]) * self.resolution_m

    def to_grid(self, frame_id: str = 'map', stamp_s: float = 0.0) -> GridMap:
        """The window as a :class:`GridMap` with layers elevation, observed, variance, min, max,
        count, last_seen (NaN where empty; observed is 1/0)."""
        k = _kernels
        s = self._flat_stats() if k is not None else None
        if s is not None:
            names = (ELEVATION, OBSERVED, VARIANCE, MIN, MAX, COUNT, LAST_SEEN)
            layers = {n: np.empty(self.shape, np.float32) for n in names}
            k.fine_layers(*(s[n] for n in self._STATS), self.estimator == 'plane',
                          *self._plane_thresholds(), *(layers[n].reshape(-1) for n in names))
            return GridMap(self.resolution_m, tuple(self.origin_xy), self.shape, layers,
                           frame_id=frame_id, stamp_s=stamp_s)
        s = self.s
        seen = s['n'] > 0
        nn = np.where(seen, s['w'], 1.0)
        nan = np.float32(np.nan)
        layers = {
            ELEVATION: self.heights().astype(np.float32),
            OBSERVED: seen.astype(np.float32),
            VARIANCE: np.where(seen, s['m2'] / nn, nan).astype(np.float32),
            MIN: np.where(seen, s['min'], nan).astype(np.float32),
            MAX: np.where(seen, s['max'], nan).astype(np.float32),
            COUNT: s['n'].astype(np.float32),
            LAST_SEEN: np.where(seen, s['last'], nan).astype(np.float32),
        }
        return GridMap(self.resolution_m, tuple(self.origin_xy), self.shape, layers,
                       frame_id=frame_id, stamp_s=stamp_s)


def isolated_cells(grid: GridMap, max_count: int, min_neighbours: int,
                   gate_m: float, island_cells: int = 0) -> np.ndarray:
    """bool ``(nx, ny)``: observed cells of at most ``max_count`` samples (layer ``count``)
    with fewer than ``min_neighbours`` observed cells among their 8 neighbours, or whose
    height differs by more than ``gate_m`` from the median of those neighbours: lone stereo
    mismatches, which a per-cell gate cannot see (one sample has nothing to disagree with).
    With ``island_cells``, also every cell of an island of fewer than ``island_cells``
    observed cells (cells at most one unobserved cell apart are joined) none of which has more
    than ``max_count`` samples: a cluster of mismatches from one capture vouches for itself
    through the neighbour rule (four neighbouring single samples 0.67 m under the ground in a
    graph test). A cell with more samples is never flagged. The compiled kernel
    (``_mapping_kernels.isolated_cells``) gives the same cells."""
    h = np.asarray(grid[ELEVATION], np.float64)
    obs = (grid[OBSERVED] > 0.5) & np.isfinite(h) if OBSERVED in grid else np.isfinite(h)
    few = obs & (np.asarray(grid[COUNT]) <= max_count) if COUNT in grid else obs
    out = np.zeros(h.shape, bool)
    if not few.any():
        return out
    if _kernels is not None:
        _kernels.isolated_cells(np.ascontiguousarray(h), np.ascontiguousarray(obs),
                                np.ascontiguousarray(few), int(min_neighbours), float(gate_m),
                                int(island_cells), out)
        return out
    ii, jj = np.nonzero(few)
    hp = np.pad(np.where(obs, h, np.nan), 1, constant_values=np.nan)
    nb = np.stack([hp[ii + 1 + di, jj + 1 + dj] for di in (-1, 0, 1) for dj in (-1, 0, 1)
                   if di or dj], axis=1)
    n = np.sum(np.isfinite(nb), axis=1)
    med = np.full(len(ii), np.nan)
    has = n > 0
    if has.any():
        med[has] = np.nanmedian(nb[has], axis=1)
    with np.errstate(invalid='ignore'):
        out[ii, jj] = (n < min_neighbours) | (np.abs(h[ii, jj] - med) > gate_m)
    if island_cells > 1:
        labels, k = ndimage.label(ndimage.binary_dilation(obs, np.ones((3, 3), bool)),
                                  np.ones((3, 3), bool))
        labels = np.where(obs, labels, 0)
        size = np.bincount(labels.ravel(), minlength=k + 1)
        supported = np.bincount(labels[obs & ~few], minlength=k + 1)
        weak = (size < island_cells) & (supported == 0)
        weak[0] = False
        out |= few & weak[labels]
    return out


def _voxel_keys(points: np.ndarray, voxel_m: float) -> np.ndarray:
    """One int64 per point naming its voxel of a fixed grid (cell ``floor(p / voxel_m)``; 21
    bits per axis, so +-10 km at 1 cm)."""
    ijk = np.floor(points / voxel_m).astype(np.int64) + (1 << 20)
    if ijk.size and (ijk.min() < 0 or ijk.max() >= (1 << 21)):
        raise ValueError(f'coarse model point beyond +-{(1 << 20) * voxel_m:.0f} m of the map '
                         'origin')
    return (ijk[:, 0] << 42) | (ijk[:, 1] << 21) | ijk[:, 2]


def voxel_centroids(points: np.ndarray, voxel_m: float) -> np.ndarray:
    """The mean of the points in each voxel of the fixed grid ``floor(p / voxel_m)`` (one row
    per occupied voxel, in the order of the voxel keys)."""
    if len(points) == 0:
        return np.zeros((0, 3))
    uniq, inv, cnt = np.unique(_voxel_keys(points, voxel_m), return_inverse=True,
                               return_counts=True)
    return np.column_stack([np.bincount(inv, weights=points[:, k], minlength=len(uniq))
                            for k in range(3)]) / cnt[:, None]


def merge_voxels(model: o3d.geometry.PointCloud, points: np.ndarray, normals: np.ndarray,
                 stamp_s: float, voxel_m: float, max_weight: float) -> o3d.geometry.PointCloud:
    """The coarse model with one capture's points fused in: per voxel of a fixed grid, the
    weighted mean of the model's point (weight: its observation count, colour channel 1) and
    the capture's points in it (together weight 1), normals likewise (then unit length); the
    count grows by one per capture up to ``max_weight``; the stamp (colour channel 0) is the
    capture's where it has points. A model point is the mean of points of its voxel, so it stays
    in it: each voxel holds one point. Returns a new cloud."""
    p0 = np.asarray(model.points)
    n0 = np.asarray(model.normals) if model.has_normals() else np.zeros_like(p0)
    c0 = np.asarray(model.colors) if model.has_colors() else np.zeros_like(p0)
    w0 = c0[:, 1] if len(c0) else np.zeros(0)
    keys = np.concatenate([_voxel_keys(p0, voxel_m), _voxel_keys(points, voxel_m)])
    uniq, inv = np.unique(keys, return_inverse=True)
    # the capture's own points per voxel share one observation
    inv_new = inv[len(p0):]
    w_new = 1.0 / np.bincount(inv_new, minlength=len(uniq))[inv_new]
    w = np.concatenate([np.maximum(w0, 1.0), w_new])
    wsum = np.bincount(inv, weights=w, minlength=len(uniq))
    pts = np.concatenate([p0, points])
    nrm = np.concatenate([n0, normals])
    out_p = np.column_stack([np.bincount(inv, weights=w * pts[:, k], minlength=len(uniq))
                             for k in range(3)]) / wsum[:, None]
    out_n = np.column_stack([np.bincount(inv, weights=w * nrm[:, k], minlength=len(uniq))
                             for k in range(3)])
    out_n /= np.maximum(np.linalg.norm(out_n, axis=1, keepdims=True), 1e-12)
    seen = np.zeros(len(uniq), bool)
    seen[inv_new] = True
    stamp = np.zeros(len(uniq))
    stamp[inv[:len(p0)]] = c0[:, 0] if len(c0) else 0.0
    stamp[seen] = float(stamp_s)
    colors = np.column_stack([stamp, np.minimum(wsum, max_weight), np.zeros(len(uniq))])
    out = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(out_p))
    out.normals = o3d.utility.Vector3dVector(out_n)
    out.colors = o3d.utility.Vector3dVector(colors)
    return out


class IcpMapper:
    """Dead-reckoning-seeded point-to-plane ICP localisation with a coarse and a fine model.

    Args:
        config: parameters.
        T_base_camera: camera mount, ``T_base_link_camera_optical`` (4x4, robot profile).
        focal_baseline_px_m: the stereo camera's focal length [px] times its baseline [m]
            (robot profile); with ``config.disparity_sigma_px`` it sets each point's depth noise
            (:func:`depth_weights`). None: every point weighs the same (e.g. a range sensor).

    Typical use: ``update(cloud_camera, T_odom_base, stamp_s)`` per capture, then
    ``fine_grid()``, ``coarse_points()``, ``capture_poses()``; ``T_map_odom`` is the
    correction to re-anchor dead reckoning.
    """

    def __init__(self, config: MapperConfig, T_base_camera: np.ndarray,
                 focal_baseline_px_m: Optional[float] = None) -> None:
        self.config = config
        self.T_base_camera = _check_T(T_base_camera, 'T_base_camera')
        if focal_baseline_px_m is not None and not focal_baseline_px_m > 0:
            raise ValueError(f'focal_baseline_px_m must be positive, got {focal_baseline_px_m}')
        self.focal_baseline_px_m = focal_baseline_px_m
        self.T_map_odom = np.eye(4)
        self.counters: collections.Counter = collections.Counter()
        r = config.fine_resolution_m
        n = max(2, int(round(config.fine_size_m / r)))
        self.fine = FineHeightMap(r, (n, n), (0.0, 0.0), config.fine_estimator,
                                  config.cell_outlier_gate_m)
        self._fine_anchored = False
        self._model = o3d.geometry.PointCloud()
        # the coarse model's part of the last fusion, if deferred (see fuse)
        self._pending_model: Optional[Tuple[np.ndarray, np.ndarray, np.ndarray, float]] = None
        self._tree: Optional[ModelIndex] = None   # of the model's points (constrained ICP)
        self._poses: Deque[Tuple[float, np.ndarray]] = collections.deque(
            maxlen=config.max_capture_poses)
        self._last_stamp = -np.inf
        # the odometry's scale (see odometry_scale_window_m): T_odom_base at the last
        # accepted capture (the prior's step starts there), (odometry position, map position)
        # at the last accepted capture ICP measured along the step (_note_scale), the forgetting-
        # weighted sums of ICP's displacement along the odometry's and of the odometry's length
        self._last_accepted_odom: Optional[np.ndarray] = None
        self._scale_anchor: Optional[Tuple[np.ndarray, np.ndarray]] = None
        self._scale_icp_m = 0.0
        self._scale_odom_m = 0.0
        self._walked_since_accept_m = 0.0
        self._last_odom: Optional[np.ndarray] = None
        self._estimation = make_estimation(config)
        self._recent_rmse: Deque[float] = collections.deque(maxlen=20)
        self._rejections_in_a_row = 0
        self._disturbed_at: Optional[float] = None   # see note_disturbance
        self._relocalise_left = 0   # captures still aligned by multi_start_icp
        # (correction T_base T_prior^-1, T_odom_base) of the refused corrections in a row
        self._refused: Deque[Tuple[np.ndarray, np.ndarray]] = collections.deque(
            maxlen=max(config.confirm_captures, config.max_consecutive_rejections, 1))
        # (IMU attitude R_world_base, map pose) at the last accepted capture
        self._accepted_attitude: Optional[Tuple[np.ndarray, np.ndarray]] = None
        # the IMU's yaw drift: the sum of the yaw corrections [rad] ICP made from the
        # IMU-turned prior, (stamp, that sum) at the captures that knew their yaw (the
        # estimate's anchors), the rate [rad/s] and the last accepted capture's stamp (see
        # imu_yaw_drift_window_s and _note_yaw_correction)
        self._yaw_sum = 0.0
        self._yaw_anchors: Deque[Tuple[float, float]] = collections.deque()
        self._yaw_drift_rad_s = 0.0
        self._accepted_stamp: Optional[float] = None

    # ---- public state ----------------------------------------------------------------------
    @property
    def imu_yaw_drift_deg_s(self) -> float:
        """The estimated yaw drift rate of the IMU [deg/s] taken out of the prior (0 until
        half a window of history, or when off; see ``imu_yaw_drift_window_s``)."""
        return float(np.degrees(self._yaw_drift_rad_s))

    @property
    def odometry_scale(self) -> float:
        """The factor the prior applies to dead reckoning's horizontal step (1 until
        ``odometry_scale_min_m`` of constrained walking, or when off)."""
        c = self.config
        if c.odometry_scale_window_m <= 0 or self._scale_odom_m < max(c.odometry_scale_min_m,
                                                                      1e-6):
            return 1.0
        return float(np.clip(self._scale_icp_m / self._scale_odom_m,
                             1.0 - c.odometry_scale_max_error,
                             1.0 + c.odometry_scale_max_error))

    def _note_scale(self, T_map_base: np.ndarray, T_odom_base: np.ndarray,
                    observed: Optional[np.ndarray]) -> None:
        """An accepted capture: if ICP measured its position along the odometry's step since
        the scale's anchor (``observed`` None: every direction was constrained; else the basis
        (6, k) of the constrained ones, which must hold that horizontal direction), add the
        step to the scale's sums and make this capture the anchor; otherwise change nothing."""
        c = self.config
        if c.odometry_scale_window_m <= 0:
            return
        p_odom, p_map = T_odom_base[:2, 3].copy(), T_map_base[:2, 3].copy()
        step = length = None
        if self._scale_anchor is not None:
            odom0, map0 = self._scale_anchor
            step = self.T_map_odom[:2, :2] @ (p_odom - odom0)   # odometry's step, map frame
            length = float(np.linalg.norm(step))
        if observed is not None:
            dirs = np.zeros((6, 2))
            if step is None or length < 1e-9:
                dirs[3, 0] = dirs[4, 1] = 1.0    # no step yet: both horizontal directions
            else:
                dirs[3:5, 0] = dirs[3:5, 1] = step / length
            if np.min(np.linalg.norm(observed.T @ dirs, axis=0)) < _SCALE_OBSERVED:
                return
        if step is not None and length > 1e-9:
            keep = float(np.exp(-length / c.odometry_scale_window_m))
            self._scale_icp_m = keep * self._scale_icp_m + float((p_map - map0) @ step) / length
            self._scale_odom_m = keep * self._scale_odom_m + length
        self._scale_anchor = (p_odom, p_map)

    @property
    def n_captures(self) -> int:
        return int(self.counters['fused'])

    @property
    def stamp_s(self) -> float:
        """Stamp [s] of the newest fused capture (-inf before the first)."""
        return self._last_stamp

    def coarse_points(self) -> np.ndarray:
        """Coarse model points ``(N, 3)`` float64 in ``map`` [m]."""
        self.finish_model(build_tree=False)
        return np.asarray(self._model.points).copy()

    def coarse_normals(self) -> np.ndarray:
        """Unit normals ``(N, 3)`` of :meth:`coarse_points` (what the ICP's point-to-plane
        residuals use)."""
        self.finish_model(build_tree=False)
        return np.asarray(self._model.normals).copy()

    def capture_poses(self) -> Tuple[np.ndarray, np.ndarray]:
        """Stamps ``(K,)`` [s] and camera poses ``T_map_camera`` ``(K, 4, 4)`` kept with the
        map (oldest first)."""
        if not self._poses:
            return np.zeros(0), np.zeros((0, 4, 4))
        return (np.array([p[0] for p in self._poses]), np.stack([p[1] for p in self._poses]))

    def fine_grid(self, frame_id: str = 'map') -> GridMap:
        """The fine height map (see :meth:`FineHeightMap.to_grid`); capture poses ride along
        in ``metadata['capture_poses']`` as flat row-major 4x4 lists."""
        grid = self.fine.to_grid(frame_id, self._last_stamp if self._poses else 0.0)
        c = self.config
        if c.isolated_max_count > 0:
            lone = isolated_cells(grid, c.isolated_max_count, c.isolated_min_neighbours,
                                  c.isolated_gate_m, c.isolated_island_cells)
            if lone.any():
                self.counters['isolated_cells_hidden'] += int(lone.sum())
                for name in grid.layers:
                    layer = grid[name]
                    layer[lone] = 0.0 if name in (OBSERVED, COUNT) else np.nan
        stamps, poses = self.capture_poses()
        grid.metadata['capture_stamps'] = [float(t) for t in stamps]
        grid.metadata['capture_poses'] = [p.reshape(-1).tolist() for p in poses]
        return grid

    @property
    def memory_bytes(self) -> int:
        """Bytes held by the maps (fine statistics + coarse points/normals + poses)."""
        self.finish_model(build_tree=False)
        m = self._model
        return (self.fine.nbytes + 8 * 3 * (len(m.points) + len(m.normals) + len(m.colors))
                + len(self._poses) * 8 * 17)

    # ---- processing --------------------------------------------------------------------------
    def prepare(self, cloud_camera: np.ndarray, coarse_camera: Optional[np.ndarray] = None
                ) -> Tuple[np.ndarray, np.ndarray]:
        """Validate a capture; returns (fine points, ICP source points), camera frame, float64.

        Raises ValueError (naming the problem) for a malformed, empty or all-NaN cloud.
        """
        c = self.config
        cloud = np.asarray(cloud_camera)
        if cloud.size == 0:
            raise ValueError('empty cloud')
        fine = valid_points(cloud, c.min_range_m, c.max_range_m, c.fine_stride_px)
        if len(fine) == 0:
            raise ValueError('cloud has no finite point in range (all NaN or out of range)')
        if len(fine) < c.min_points:
            raise ValueError(f'cloud has only {len(fine)} valid points (min_points='
                             f'{c.min_points})')
        icp_max = min(c.max_range_m, c.icp_max_range_m)
        if coarse_camera is not None and np.asarray(coarse_camera).size > 0:
            src = valid_points(coarse_camera, c.min_range_m, icp_max)
        else:
            src = valid_points(cloud, c.min_range_m, icp_max, c.coarse_stride_px)
        if len(src) < 10:
            raise ValueError(f'coarse cloud has only {len(src)} valid points')
        return fine, src

    def rmse_limit(self) -> float:
        """Largest point-to-plane RMSE [m] an alignment may have now: ``max_rmse_m``, tightened
        to ``max_rmse_ratio`` x the median of recent accepted alignments (not below
        ``rmse_floor_m``) once three are known."""
        c = self.config
        if c.max_rmse_ratio <= 0 or len(self._recent_rmse) < 3:
            return c.max_rmse_m
        rel = c.max_rmse_ratio * float(np.median(self._recent_rmse))
        return min(c.max_rmse_m, max(c.rmse_floor_m, rel))

    def predict(self, T_odom_base: np.ndarray) -> np.ndarray:
        """Prior ``T_map_base`` from dead reckoning and the current correction."""
        return self.T_map_odom @ _check_T(T_odom_base, 'T_odom_base')

    def note_disturbance(self, stamp_s: float) -> None:
        """The body was disturbed at ``stamp_s`` in a way dead reckoning cannot see (the IMU
        measured free fall: a foot slipped off a stone, the body dropped). Until an alignment
        is accepted, corrections up to ``max_correction_disturbed_m`` /
        ``max_rotation_disturbed_deg`` pass the drift guard."""
        if not np.isfinite(stamp_s):
            raise ValueError('disturbance stamp is not finite')
        self._disturbed_at = float(stamp_s)
        self.counters['disturbances'] += 1
        self._relocalise_left = self.config.relocalise_captures

    def update(self, cloud_camera: np.ndarray, T_odom_base: np.ndarray, stamp_s: float,
               coarse_camera: Optional[np.ndarray] = None,
               up_camera: Optional[np.ndarray] = None,
               prepared: Optional[Tuple[np.ndarray, np.ndarray]] = None,
               attitude: Optional[np.ndarray] = None,
               defer_model: bool = False) -> MapperUpdate:
        """Localise and fuse one capture.

        Args:
            cloud_camera: ``(H, W, 3)`` organized or ``(N, 3)`` cloud [m], camera-optical frame,
                NaN = no measurement.
            T_odom_base: dead-reckoning body pose at the capture's stamp.
            stamp_s: capture time [s]; must not be older than the map (stamp_tolerance_s).
            coarse_camera: optional separate sparse cloud for ICP (else sub-sampled).
            up_camera: optional measured up direction in the camera frame (gravity prior).
            prepared: the result of :meth:`prepare` for this cloud, if the caller validated it
                already (saves the second pass).
            attitude: optional IMU attitude ``R_world_base`` (3x3) at the capture's stamp
                (``use_imu_rotation_prior``).
            defer_model: leave the coarse model's part of the fusion for
                :meth:`finish_model` (see :meth:`fuse`).

        Returns:
            :class:`MapperUpdate`. Raises ValueError for bad input; then nothing changes.
        """
        c = self.config
        if not np.isfinite(stamp_s):
            raise ValueError('cloud stamp is not finite')
        if stamp_s < self._last_stamp - c.stamp_tolerance_s:
            raise ValueError(f'cloud at {stamp_s:.3f} s is older than the map '
                             f'({self._last_stamp:.3f} s)')
        T_odom_base = _check_T(T_odom_base, 'T_odom_base')
        fine, src = prepared if prepared is not None else self.prepare(cloud_camera,
                                                                        coarse_camera)
        if up_camera is not None:
            up_camera = np.asarray(up_camera, dtype=np.float64).reshape(3)
            if not np.all(np.isfinite(up_camera)) or np.linalg.norm(up_camera) < 1e-6:
                raise ValueError('up vector must be finite and non-zero')
        if attitude is not None:
            attitude = np.asarray(attitude, dtype=np.float64).reshape(3, 3)
            if not np.all(np.isfinite(attitude)) or not np.allclose(
                    attitude @ attitude.T, np.eye(3), atol=1e-3):
                raise ValueError('IMU attitude must be a finite rotation matrix')
        result = self.align(src, T_odom_base, up_camera, attitude, stamp_s)
        if result.accepted or c.fuse_rejected:
            self.fuse(fine, src, result.T_map_camera, result.T_map_base, stamp_s,
                      defer_model=defer_model)
            result.fused = True
        return result

    def align(self, src_camera: np.ndarray, T_odom_base: np.ndarray,
              up_camera: Optional[np.ndarray] = None,
              attitude: Optional[np.ndarray] = None,
              stamp_s: Optional[float] = None) -> MapperUpdate:
        """ICP of camera-frame source points against the coarse model, with the guards.

        Updates ``T_map_odom`` when accepted; never touches the maps (a coarse-model fusion
        left pending by ``defer_model`` is done first). ``stamp_s`` (the
        capture's time) lets the IMU's yaw drift be estimated and taken out of the prior.
        """
        self.finish_model()
        c = self.config
        if self._last_odom is not None:
            self._walked_since_accept_m += float(
                np.linalg.norm(T_odom_base[:3, 3] - self._last_odom[:3, 3]))
        self._last_odom = T_odom_base.copy()
        T_prior = self.T_map_odom @ T_odom_base
        scale = self.odometry_scale
        if scale != 1.0 and self._last_accepted_odom is not None:
            # dead reckoning's horizontal step since the last accepted capture, rescaled
            step = self.T_map_odom[:3, :3] @ (T_odom_base[:3, 3] - self._last_accepted_odom[:3, 3])
            T_prior[:2, 3] += (scale - 1.0) * step[:2]
        imu_prior = (c.use_imu_rotation_prior and attitude is not None
                     and self._accepted_attitude is not None)
        if imu_prior:
            # the body's rotation since the last accepted capture, as the IMU measured it
            R_then, T_map_then = self._accepted_attitude
            T_prior[:3, :3] = T_map_then[:3, :3] @ (R_then.T @ attitude)
        R_imu_prior = T_prior[:3, :3].copy()
        track_yaw = imu_prior and stamp_s is not None and c.imu_yaw_drift_window_s > 0
        if track_yaw and self._yaw_drift_rad_s and self._accepted_stamp is not None:
            # the IMU's yaw has drifted by rate x time since the accepted capture: undo it
            T_prior[:3, :3] = rot_z(-self._yaw_drift_rad_s * (float(stamp_s)
                                                               - self._accepted_stamp)) \
                @ T_prior[:3, :3]
        T_cam_prior = T_prior @ self.T_base_camera
        up = up_camera if c.use_gravity_prior else None
        if up is None and c.use_ground_plane_prior:
            up = ground_plane_up(src_camera, c.ground_plane_threshold_m,
                                 c.ground_plane_min_inliers)
        if up is not None:
            T_cam_prior = T_cam_prior.copy()
            T_cam_prior[:3, :3] = level_rotation(T_cam_prior[:3, :3], up)
        n_model = len(self._model.points)
        if self._rejections_in_a_row >= c.max_consecutive_rejections:
            self._model = o3d.geometry.PointCloud()
            self._tree = None
            self._recent_rmse.clear()
            self._rejections_in_a_row = 0
            self._refused.clear()
            self._relocalise_left = 0
            self._scale_anchor = None        # the next positions are not tied to the last
            self.counters['model_restarted'] += 1
            n_model = 0
        if n_model == 0:
            self.counters['first_capture'] += 1
            T_base = T_cam_prior @ invert(self.T_base_camera)
            self._accept(T_base, T_odom_base, attitude)
            self._note_scale(T_base, T_odom_base, None)   # the map's origin: the anchor
            return MapperUpdate(True, False, '', T_base, T_cam_prior, T_prior,
                                self.T_map_odom.copy(), n_source=len(src_camera))
        src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(src_camera))
        src = src.voxel_down_sample(c.coarse_voxel_m)
        blend = imu_prior and c.icp_yaw_gain < 1.0
        degeneracy = c.degeneracy_threshold > 0 or c.degeneracy_noise_gain > 0
        n_degenerate = 0
        observed = None          # the directions ICP constrained (constrained solver)
        multi_start = -1
        min_info = info_limit = float('nan')
        if c.icp_solver == 'constrained' and c.icp_method == 'point_to_plane':
            src_np = np.asarray(src.points)
            model_pts = np.asarray(self._model.points)
            model_nrm = np.asarray(self._model.normals)
            if self._tree is None:
                self._tree = ModelIndex(model_pts, c.max_correspondence_m)
            dw = depth_weights(src_np[:, 2], self.focal_baseline_px_m, c.disparity_sigma_px,
                               c.depth_sigma_floor_m)
            res = constrained_icp(src_np, model_pts, model_nrm, self._tree, T_cam_prior, c, dw)
            if c.relocalise_captures > 0 and (res.fitness < c.min_fitness
                                              or res.rmse_m > self.rmse_limit()):
                # a misfit from the prior: the prior may be beyond ICP's basin (an unseen
                # slide); this capture and the next ones search around it
                self._relocalise_left = max(self._relocalise_left, c.relocalise_captures)
            if self._relocalise_left > 0:
                self._relocalise_left -= 1
                res, multi_start = multi_start_icp(src_np, model_pts, model_nrm, self._tree,
                                                   T_cam_prior, c, dw, first=res)
                self.counters['multi_start_alignments'] += 1
                if multi_start:
                    self.counters['multi_start_moved'] += 1
            T_cam, corr, fitness = res.T, res.correspondences, res.fitness
            if degeneracy:
                n_degenerate = res.n_degenerate
                min_info, info_limit = float(res.eigenvalues[0]), res.information_limit
                observed = res.observed
            if blend and len(corr) >= 6:
                src_pts = src_np[corr[:, 0]]
                T_cam = blend_yaw(T_cam, T_cam_prior, transform_points(T_cam, src_pts),
                                  model_nrm[corr[:, 1]], c.icp_yaw_gain,
                                  depth_weights(src_pts[:, 2], self.focal_baseline_px_m,
                                                c.disparity_sigma_px, c.depth_sigma_floor_m))
        else:
            crit = _REG.ICPConvergenceCriteria(c.relative_fitness, c.relative_rmse,
                                               c.max_iterations)
            reg = _REG.registration_icp(src, self._model, c.max_correspondence_m, T_cam_prior,
                                        self._estimation, crit)
            T_cam = np.asarray(reg.transformation).copy()
            fitness = float(reg.fitness)
            # Open3D's inlier_rmse is the point-to-point distance; the guard wants the residual
            # of the metric being minimised, so recompute point-to-plane over the
            # correspondences
            corr = np.asarray(reg.correspondence_set)
            if len(corr) >= 6 and (blend or degeneracy):
                src_pts = np.asarray(src.points)[corr[:, 0]]
                normals = np.asarray(self._model.normals)[corr[:, 1]]
                weights = depth_weights(src_pts[:, 2], self.focal_baseline_px_m,
                                        c.disparity_sigma_px, c.depth_sigma_floor_m)
                if blend:
                    T_cam = blend_yaw(T_cam, T_cam_prior, transform_points(T_cam, src_pts),
                                      normals, c.icp_yaw_gain, weights)
            if len(corr) >= 6 and degeneracy:
                # information below what noise alone puts into the normals is not geometry
                noise_slope = self._plane_rmse(src, T_cam, corr) / c.normal_radius_m
                info_limit = max(c.degeneracy_threshold,
                                 c.degeneracy_noise_gain * noise_slope ** 2)
                T_cam, eig, n_degenerate = remove_degenerate_motion(
                    T_cam, T_cam_prior, transform_points(T_cam, src_pts), normals, info_limit,
                    weights)
                min_info = float(eig[0])
        rmse = self._plane_rmse(src, T_cam, corr)
        T_base = T_cam @ invert(self.T_base_camera)
        corr_m = float(np.linalg.norm(T_base[:3, 3] - T_prior[:3, 3]))
        corr_rad = angle_between(T_base[:3, :3], T_prior[:3, :3])
        walked = self._walked_since_accept_m
        allowed_m = c.max_correction_floor_m + c.max_correction_per_m * walked
        allowed_rad = np.radians(c.max_rotation_floor_deg + c.max_rotation_per_m_deg * walked)
        disturbed = self._disturbed_at is not None
        if disturbed:
            allowed_m = max(allowed_m, c.max_correction_disturbed_m)
            allowed_rad = max(allowed_rad, np.radians(c.max_rotation_disturbed_deg))
        reason, drift = '', ''     # drift: the counter of a drift-guard refusal
        if fitness < c.min_fitness:
            reason = f'fitness {fitness:.2f} < {c.min_fitness:.2f}'
            self.counters['rejected_fitness'] += 1
        elif rmse > self.rmse_limit():
            reason = (f'point-to-plane rmse {rmse * 1e3:.1f} mm > '
                      f'{self.rmse_limit() * 1e3:.1f} mm')
            self.counters['rejected_rmse'] += 1
        elif corr_m > allowed_m:
            reason = (f'correction {corr_m * 1e3:.0f} mm exceeds the expected drift '
                      f'{allowed_m * 1e3:.0f} mm')
            drift = 'rejected_correction'
        elif corr_rad > allowed_rad:
            reason = (f'rotation correction {np.degrees(corr_rad):.1f} deg exceeds the expected '
                      f'drift {np.degrees(allowed_rad):.1f} deg')
            drift = 'rejected_rotation'
        level = self._level_error(T_cam, up) if not reason or drift else ''
        if level and not reason:
            reason = level
            self.counters['rejected_level'] += 1
        confirmed, T_icp = False, T_base
        if drift:
            confirmed = not level and self._confirmed(T_base, T_prior, T_odom_base, corr_m,
                                                      corr_rad)
            if confirmed:
                # the runs' corrections are measurements of one offset: their mean, on this
                # capture's prior, averages out ICP's scatter along its cost valleys
                reason = ''
                T_base = self._mean_correction(T_prior)
                T_cam = T_base @ self.T_base_camera
                corr_m = float(np.linalg.norm(T_base[:3, 3] - T_prior[:3, 3]))
                corr_rad = angle_between(T_base[:3, :3], T_prior[:3, :3])
            else:
                self.counters[drift] += 1
                # ICP measured a shift larger than dead reckoning explains: a slide the IMU
                # did not see, or a wrong minimum; the next captures also search around
                self._relocalise_left = c.relocalise_captures
        # a misfit (fitness, residual, level) says nothing about the correction: it neither
        # extends nor breaks a run of refused corrections; an accepted capture ends it
        upd = MapperUpdate(not reason, False, reason, T_base, T_cam, T_prior,
                           self.T_map_odom.copy(), float(fitness), rmse,
                           corr_m, float(np.degrees(corr_rad)), len(src.points), n_model,
                           n_degenerate, min_info, info_limit, T_icp, confirmed,
                           multi_start)
        if reason:
            upd.T_map_base, upd.T_map_camera = T_prior, T_prior @ self.T_base_camera
            self._rejections_in_a_row += 1
            return upd
        self._rejections_in_a_row = 0
        self.counters['accepted'] += 1
        self._refused.clear()
        if disturbed:
            self.counters['accepted_after_disturbance'] += 1
        if confirmed:
            self.counters['accepted_confirmed'] += 1
        if n_degenerate:
            # partial update: ICP only along the constrained directions, prior elsewhere
            self.counters['degenerate_alignments'] += 1
            self.counters['directions_kept_at_prior'] += n_degenerate
        self._recent_rmse.append(rmse)
        if track_yaw:
            self._note_yaw_correction(float(stamp_s), yaw_of(T_base[:3, :3] @ R_imu_prior.T),
                                      n_degenerate == 0)
        self._accept(T_base, T_odom_base, attitude)
        if not confirmed and not disturbed and (n_degenerate == 0 or observed is not None):
            # (Open3D's solver reports how many directions it kept, not which: such a
            # capture's position is not taken as measured along the step)
            self._note_scale(T_base, T_odom_base, None if n_degenerate == 0 else observed)
        if stamp_s is not None:
            self._accepted_stamp = float(stamp_s)
        upd.T_map_odom = self.T_map_odom.copy()
        return upd

    def _note_yaw_correction(self, stamp_s: float, yaw_rad: float, known: bool) -> None:
        """Add an accepted capture's yaw correction (from the IMU-turned prior, before the
        drift compensation) and, at a capture that knows its yaw (``known``: its geometry
        constrained every direction), re-estimate the IMU's yaw drift rate: the corrections
        since an earlier such capture, summed, over the time between the two. That capture is
        the oldest within the window (or, with none there, the newest before it); the rate is
        used from half a window.

        Each correction removes the IMU's drift since the previous accepted capture plus the
        change of ICP's own yaw error, so the sum between two captures is the drift plus the
        difference of their two ICP errors, not a sum of noise. Both ends are captures whose
        yaw was observed: a window that starts wherever 30 s ago falls may start just after a
        capture whose yaw error the next one took back, and then holds the return alone
        (rocks-6cm seed 130's replay: the rate froze at 0.009 instead of ~0.045 deg/s over
        the flat exit, and the yaw error grew to 2.5 deg)."""
        c = self.config
        self._yaw_sum += yaw_rad
        if not known:
            return
        q = self._yaw_anchors
        while len(q) > 1 and q[1][0] <= stamp_s - c.imu_yaw_drift_window_s:
            q.popleft()      # keep the newest anchor before the window
        if q and q[0][0] < stamp_s - c.imu_yaw_drift_window_s and len(q) > 1:
            q.popleft()      # the window has one of its own
        if q:
            t0, sum0 = q[0]
            span = stamp_s - t0
            if span >= 0.5 * c.imu_yaw_drift_window_s:
                limit = np.radians(c.imu_yaw_drift_max_deg_s)
                # ICP turned the IMU's yaw back by the drift: the rate is minus the sum's
                self._yaw_drift_rad_s = float(np.clip(-(self._yaw_sum - sum0) / span,
                                                      -limit, limit))
        q.append((stamp_s, self._yaw_sum))

    def _level_error(self, T_map_camera: np.ndarray, up: Optional[np.ndarray]) -> str:
        """The reason an alignment fails ``max_level_error_deg`` ('' when it passes or there
        is no roll/pitch prior)."""
        c = self.config
        if up is None or c.max_level_error_deg <= 0:
            return ''
        tilt = np.degrees(np.arccos(np.clip((T_map_camera[:3, :3] @ up)[2], -1.0, 1.0)))
        return (f'tilt {tilt:.1f} deg away from the roll/pitch prior'
                if tilt > c.max_level_error_deg else '')

    def _confirmed(self, T_map_base: np.ndarray, T_prior: np.ndarray, T_odom_base: np.ndarray,
                   corr_m: float, corr_rad: float) -> bool:
        """Record a correction the drift guard refused; True when at least
        ``confirm_captures`` in a row, spread over ``confirm_min_travel_m`` of dead reckoning,
        measured the same correction (see ``MapperConfig.confirm_captures``) and it is within
        the confirmed maxima.

        The correction is compared in the map frame (``T_map_base T_prior^-1``: the shift and
        turn that take the prior to ICP's pose), not as a map-from-odometry transform, whose
        translation a small turn swings by the odometry's distance from its origin."""
        c = self.config
        if c.confirm_captures <= 0:
            return False
        cand = map_frame_correction(T_map_base, T_prior)
        # the run: the latest refusals that all agree with this one
        keep = 0
        for T, _ in reversed(self._refused):
            if not self._agree(T, cand):
                break
            keep += 1
        while len(self._refused) > keep:
            self._refused.popleft()
        self._refused.append((cand, T_odom_base.copy()))
        if len(self._refused) < c.confirm_captures:
            return False
        travel = float(np.linalg.norm(self._refused[-1][1][:3, 3] - self._refused[0][1][:3, 3]))
        return (travel >= c.confirm_min_travel_m and corr_m <= c.max_correction_confirmed_m
                and corr_rad <= np.radians(c.max_rotation_confirmed_deg))

    def _mean_correction(self, T_prior: np.ndarray) -> np.ndarray:
        """``T_prior`` corrected by the mean of the recorded refused corrections: their mean
        shift added to its position, their mean turn (:meth:`Rotation.mean`) applied to its
        orientation (the body turns in place; a turn about the map origin would also move it
        by the turn times its distance from there)."""
        C = np.array([T for T, _ in self._refused])
        out = np.array(T_prior, dtype=np.float64)
        out[:3, :3] = Rotation.from_matrix(C[:, :3, :3]).mean().as_matrix() @ T_prior[:3, :3]
        out[:3, 3] = T_prior[:3, 3] + C[:, :3, 3].mean(axis=0)
        return out

    def _agree(self, A: np.ndarray, B: np.ndarray) -> bool:
        c = self.config
        return bool(np.linalg.norm(A[:3, 3] - B[:3, 3]) <= c.confirm_tolerance_m
                    and angle_between(A[:3, :3], B[:3, :3])
                    <= np.radians(c.confirm_tolerance_deg))

    def _plane_rmse(self, src: o3d.geometry.PointCloud, T_map_camera: np.ndarray,
                    corr: np.ndarray) -> float:
        if len(corr) == 0:
            return float('inf')
        p = transform_points(T_map_camera, np.asarray(src.points)[corr[:, 0]])
        q = np.asarray(self._model.points)[corr[:, 1]]
        n = np.asarray(self._model.normals)[corr[:, 1]]
        return float(np.sqrt(np.mean(np.einsum('ij,ij->i', p - q, n) ** 2)))

    def _accept(self, T_map_base: np.ndarray, T_odom_base: np.ndarray,
                attitude: Optional[np.ndarray] = None) -> None:
        self.T_map_odom = T_map_base @ invert(T_odom_base)
        self._last_accepted_odom = T_odom_base.copy()
        self._walked_since_accept_m = 0.0
        self._disturbed_at = None
        self._accepted_attitude = (None if attitude is None
                                   else (attitude.copy(), T_map_base.copy()))

    def fuse(self, fine_camera: np.ndarray, src_camera: np.ndarray, T_map_camera: np.ndarray,
             T_map_base: np.ndarray, stamp_s: float, defer_model: bool = False) -> None:
        """Add a capture at a known camera pose to both models (moving them if needed).

        With ``defer_model`` the fine map, the capture poses and the stamp are updated here and
        the coarse model's part (its voxels, normals, merge, crop and KD-tree: 10-20 ms late
        in a walk) waits for :meth:`finish_model`, which the next alignment or a read of the
        coarse model calls if nobody did: the ICP mapper node publishes the capture's pose
        and fine map first, so the fill and the planner need not wait for the model only the
        next capture uses. Either way the maps come out the same."""
        c = self.config
        self.finish_model(build_tree=False)
        self._recenter(T_map_base[:3, 3])
        # the capture in the map frame, once (rows are selected below, not re-transformed)
        fine_map = transform_points(T_map_camera, fine_camera)
        ok = None                 # rows that passed the height and line-of-sight tests
        high = fine_map[:, 2] > T_map_base[2, 3] + c.max_height_above_base_m
        if high.any():
            self.counters['points_above_body'] += int(high.sum())
            ok = ~high
        if c.line_of_sight_tolerance_m > 0:
            # before this capture is added: its own points do not vouch for each other
            bad = self.fine.rays_below(fine_map, T_map_camera[:3, 3],
                                       c.line_of_sight_tolerance_m)
            if bad.any():
                self.counters['points_below_line_of_sight'] += int(bad.sum())
                ok = ~bad if ok is None else ok & ~bad
        # rows are gathered once per use (by combined masks) from the camera depths
        z_cam = fine_camera[:, 2]
        near = z_cam <= c.fine_max_range_m
        if ok is not None:
            near &= ok
        near_map = _rows(fine_map, near)
        self.fine.add(near_map, stamp_s,
                      depth_weights(z_cam[near], self.focal_baseline_px_m, c.disparity_sigma_px,
                                    c.depth_sigma_floor_m))
        # coarse model: the capture's sparse points with normals from its own neighbourhood
        if c.model_from == 'fine':
            in_icp = z_cam <= c.icp_max_range_m
            if ok is not None:
                in_icp &= ok
            # (the default ranges are equal: the same rows, gathered once)
            model_map = near_map if np.array_equal(in_icp, near) else _rows(fine_map, in_icp)
        else:
            model_map = transform_points(T_map_camera, src_camera)
        self._poses.append((float(stamp_s), T_map_camera.copy()))
        self._last_stamp = max(self._last_stamp, float(stamp_s))
        self.counters['fused'] += 1
        self._pending_model = (model_map, T_map_camera, T_map_base, float(stamp_s))
        if not defer_model:
            self.finish_model(build_tree=False)

    @property
    def model_pending(self) -> bool:
        """True while a fusion's coarse-model part waits for :meth:`finish_model`."""
        return self._pending_model is not None

    def finish_model(self, build_tree: bool = True) -> None:
        """Do the coarse model's part of a fusion :meth:`fuse` deferred (nothing if none is
        pending) and, with ``build_tree``, build the model's KD-tree the next alignment
        searches."""
        if self._pending_model is not None:
            model_map, T_map_camera, T_map_base, stamp_s = self._pending_model
            self._pending_model = None
            self._fuse_model(model_map, T_map_camera, T_map_base, stamp_s)
        if build_tree and self._tree is None and len(self._model.points):
            self._tree = ModelIndex(np.asarray(self._model.points),
                                    self.config.max_correspondence_m)

    def _fuse_model(self, model_map: np.ndarray, T_map_camera: np.ndarray,
                    T_map_base: np.ndarray, stamp_s: float) -> None:
        c = self.config
        if len(model_map) == 0:
            # nothing of this capture may enter the model (a tumbling camera's view): the
            # model stays as it was
            self.counters['captures_without_model_points'] += 1
            return
        if c.coarse_fusion == 'weighted':
            # the voxels of the model's own fixed grid (Open3D's grid starts at the cloud's
            # corner: its voxels would straddle the model's)
            new = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(
                voxel_centroids(model_map, c.coarse_voxel_m)))
        else:
            new = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(model_map))
            new = new.voxel_down_sample(c.coarse_voxel_m)
        if c.normal_source == 'height_grid':
            pts = np.asarray(new.points)
            nrm = cloud_height_normals(pts, c.coarse_voxel_m,
                                       int(round(c.normal_radius_m / c.coarse_voxel_m)))
            good = np.isfinite(nrm[:, 0]) & np.isfinite(nrm[:, 1]) & np.isfinite(nrm[:, 2])
            if not good.all():
                # (numpy rows + a new cloud: select_by_index costs ~1 ms per call here)
                new = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts[good]))
            new.normals = o3d.utility.Vector3dVector(_rows(nrm, good))
        else:
            new.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(c.normal_radius_m,
                                                                      c.normal_max_nn))
            new.orient_normals_towards_camera_location(T_map_camera[:3, 3])
        if c.coarse_fusion == 'weighted':
            self._model = merge_voxels(self._model, np.asarray(new.points),
                                       np.asarray(new.normals), float(stamp_s),
                                       c.coarse_voxel_m, c.coarse_max_weight)
        else:
            # the stamp rides in the colour channel through voxel averaging (capping keeps
            # newest); re-voxelise so overlapping captures do not pile up
            new.colors = o3d.utility.Vector3dVector(
                np.column_stack([np.full(len(new.points), float(stamp_s)),
                                 np.ones(len(new.points)), np.zeros(len(new.points))]))
            model = (self._model + new).voxel_down_sample(c.coarse_voxel_m)
            nrm = np.asarray(model.normals)
            nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
            model.normals = o3d.utility.Vector3dVector(nrm)
            self._model = model
        self._tree = None
        self._crop_model(T_map_base[:3, 3])

    def _crop_model(self, center: np.ndarray) -> None:
        c = self.config
        pts = np.asarray(self._model.points)
        keep = np.linalg.norm(pts[:, :2] - center[:2], axis=1) <= c.coarse_radius_m
        if keep.sum() > c.coarse_max_points:
            stamp = np.asarray(self._model.colors)[:, 0]
            order = np.argsort(-np.where(keep, stamp, -np.inf), kind='stable')
            keep = np.zeros(len(pts), bool)
            keep[order[:c.coarse_max_points]] = True
        if not keep.all():
            # the kept rows of points, normals and colours (what select_by_index does, in
            # numpy: several times faster for the ~10-30k points of the model)
            m = self._model
            out = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts[keep]))
            if m.has_normals():
                out.normals = o3d.utility.Vector3dVector(np.asarray(m.normals)[keep])
            if m.has_colors():
                out.colors = o3d.utility.Vector3dVector(np.asarray(m.colors)[keep])
            self._model = out

    def _recenter(self, base_xyz: np.ndarray) -> None:
        f = self.fine
        r = f.resolution_m
        half = 0.5 * np.asarray(f.shape) * r
        if not self._fine_anchored:
            f.origin_xy = np.floor((base_xyz[:2] - half) / r) * r
            self._fine_anchored = True
            return
        centre = f.origin_xy + half
        if np.linalg.norm(base_xyz[:2] - centre) <= self.config.recenter_distance_m:
            return
        d = np.round((base_xyz[:2] - centre) / r).astype(int)
        f.shift(int(d[0]), int(d[1]))
        self.counters['recentred'] += 1
        lo, hi = f.origin_xy, f.origin_xy + 2 * half
        while self._poses:
            p = self._poses[0][1][:3, 3]
            if np.all(p[:2] >= lo - half) and np.all(p[:2] <= hi + half):
                break
            self._poses.popleft()
