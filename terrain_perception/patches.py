"""Contact patches: foot-sized paraboloid surface pieces found in an organized cloud.

Implements Kanoulas & Vona, "Bio-Inspired Rough Terrain Contact Patch Perception" (paper 003),
section III, steps 1-14:

* Stage I   - bilateral filter on the organized cloud (along the pixel rays) and a 2x2 median
  downsample (:func:`bilateral_filter_cloud`, :func:`median_downsample_2x2`). The pipeline runs
  both only on the image rows whose points can reach the seed region or the windows of steps 7
  and 11 (an exact depth bound, :func:`_seed_band`); the other rows' results would be unused.
* Stage II  - gravity from the IMU orientation, the fixation point ``f = l_d g + l_f (x x g)``
  and the seeds within ``R`` of it (:func:`gravity_in_camera`, :func:`fixation_point`).
* Stage III - normals at two scales from integral images, window ``2 r f / Z`` and ``r f / Z``
  (:func:`integral_normals`), Difference-of-Normals and Difference-of-Normal-Gravity filters.
* Stage IV  - random subsample to ``n_s`` seeds, neighbourhoods of at most ``n_f`` points within
  ``r`` by an organized (image-window) search, paraboloid fit (closed-form quadric least-squares
  start, Levenberg-Marquardt refinement batched over all patches, :func:`fit_paraboloids`), the
  curvature filter (``kappa_min``, ``kappa_max``) and the RMS residual filter (``d_max``).

Patch model (paper 003 eq. 1; ``terrain_msgs/ContactPatch``): in the patch frame
``z = 0.5 (kx x^2 + ky y^2)``, kx <= ky, the z axis is the surface normal at the vertex pointing
away from the terrain (against gravity), x and y are the principal directions. Positive
curvature therefore bends the surface *up*, away from the terrain: a dip / bowl (the paper's
"concave"); negative is a bump ("convex").

All geometry is in the frame of the input cloud (the camera's optical frame: x right, y down,
z forward) in metres unless a docstring says otherwise.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import math
import threading
from dataclasses import dataclass
from typing import Dict, Optional

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from terrain_perception.compiled import load_compiled
from terrain_perception.config import param

_LOG = logging.getLogger(__name__)


@dataclass(frozen=True)
class PatchConfig:
    """Contact-patch parameters. Defaults are paper 003's human-scale values (Stages II-IV)."""

    # Stage I
    bilateral_window_px: int = param(5, 'bilateral filter diameter at input resolution [px]',
                                     1, 15)
    bilateral_sigma_space_px: float = param(3.0, 'bilateral spatial sigma [px]', 0.1, 20.0)
    bilateral_sigma_depth_m: float = param(
        0.03, 'bilateral range sigma on depth [m]; depth jumps well above it are preserved',
        0.001, 1.0)
    # Stage II (DtFP)
    fixation_down_m: float = param(1.0, 'l_d: distance down (along gravity) from the camera to '
                                   'the fixation point [m]', 0.0, 5.0)
    fixation_forward_m: float = param(1.2, 'l_f: distance forward from the camera to the '
                                      'fixation point [m]', 0.0, 10.0)
    roi_radius_m: float = param(0.7, 'R: radius of the seed region around the fixation point '
                                '[m]', 0.01, 10.0)
    # Stage III (DoN, DoNG)
    patch_radius_m: float = param(0.10, 'r: patch neighbourhood radius [m]', 0.005, 1.0)
    max_don_deg: float = param(15.0, 'phi_d: max angle between the r and r/2 scale normals '
                               '[deg]', 0.0, 90.0)
    max_dong_deg: float = param(35.0, 'phi_g: max angle between the r-scale normal and -gravity '
                                '[deg]', 0.0, 180.0)
    # Stage IV
    max_seeds: int = param(100, 'n_s: max number of seeds (patches fitted per frame)', 1, 100000)
    max_neighbours: int = param(50, 'n_f: max points per patch neighbourhood', 6, 1000)
    min_neighbours: int = param(12, 'fewest neighbourhood points a patch is fitted to', 6, 1000)
    kappa_min_per_m: float = param(-13.6, 'kappa_min: smallest allowed min principal curvature '
                                   '[1/m]', -1000.0, 0.0)
    kappa_max_per_m: float = param(19.7, 'kappa_max: largest allowed max principal curvature '
                                   '[1/m]', 0.0, 1000.0)
    max_residual_m: float = param(0.01, 'd_max: max RMS Euclidean fit residual [m]', 0.0, 1.0)
    lm_iterations: int = param(6, 'most Levenberg-Marquardt iterations after the closed-form '
                               'start (stops early on convergence)', 0, 100)
    neighbour_draws: int = param(3, 'random pixel draws per neighbourhood slot (organized '
                                 'search; draws outside the r-ball are discarded)', 1, 20)
    random_seed: int = param(0, 'seed of the random subsampling (repeatable runs)', 0, 2**31 - 1)


# --------------------------------------------------------------------------------------------
# Stage I
# --------------------------------------------------------------------------------------------

class _Workspace:
    """Work arrays of one thread, reused from frame to frame (scratch memory only: results
    never depend on it, and no array of it leaves the call that filled it).

    A 640x480 frame's large temporaries (band planes, integral images: ~10 MB) are otherwise
    fresh allocations every call; when the allocator hands that memory back to the OS between
    frames (a process doing little else), first touching it again costs ~1000 page faults,
    ~2 ms CPU per frame. Where the process keeps a large heap anyway (the benchmark's ray
    casting) it makes no measurable difference."""

    def __init__(self) -> None:
        self._bufs: Dict[str, np.ndarray] = {}

    def array(self, name: str, shape, dtype=np.float32) -> np.ndarray:
        buf = self._bufs.get(name)
        if buf is not None:
            try:
                return np.ndarray(shape, dtype, buf)    # (a frame asks for ~40 of them)
            except TypeError:                           # buffer too small
                pass
        n = math.prod(shape) * np.dtype(dtype).itemsize
        buf = self._bufs[name] = np.empty(n + n // 4, np.uint8)   # headroom for growth
        return np.ndarray(shape, dtype, buf)


_THREAD_LOCAL = threading.local()


def _workspace() -> _Workspace:
    ws = getattr(_THREAD_LOCAL, 'workspace', None)
    if ws is None:
        ws = _THREAD_LOCAL.workspace = _Workspace()
    return ws


def _array(ws: Optional[_Workspace], name: str, shape, dtype=np.float32) -> np.ndarray:
    return ws.array(name, shape, dtype) if ws is not None else np.empty(shape, dtype)


# --------------------------------------------------------------------------------------------
# Compiled kernels (numba) or the numpy reference steps
# --------------------------------------------------------------------------------------------
#
# find_patches (and fit_paraboloids) run the 2x2 median, the integral images, the neighbourhood
# search and the paraboloid fit as compiled kernels (terrain_perception._patch_kernels) when
# numba imports; the numpy / OpenCV steps below stay the reference they are tested against
# (median, integral images and search bitwise identical, the fit within rounding). TERRAIN_PATCHES_NUMBA=0 in the environment, or
# use_compiled_kernels(False), selects the numpy steps. The kernels are loaded when this module
# is imported (~0.6 s with numba's import; ~9 s once if numba's cache is cold), so that no
# frame pays for it.

_kernels_lock = threading.Lock()


def _load_kernels():
    """The compiled kernels module, or None (numba missing: logged once, numpy steps used)."""
    return load_compiled('_patch_kernels', 'TERRAIN_PATCHES_NUMBA', 'contact patches', _LOG,
                         'using the numpy reference steps, ~40 % slower')


_kernels = _load_kernels()


def _get_kernels():
    """The kernels module find_patches uses now, or None for the numpy steps."""
    return _kernels


def use_compiled_kernels(enabled: Optional[bool] = True) -> bool:
    """Select the compiled kernels (``True``), the numpy reference steps (``False``) or the
    default (``None``: compiled unless numba is missing or ``TERRAIN_PATCHES_NUMBA=0``) for
    the following calls (process-wide). Returns whether the compiled kernels are now used
    (``True`` needs numba: ``ImportError`` otherwise)."""
    global _kernels
    with _kernels_lock:
        if enabled is None:
            _kernels = _load_kernels()
        elif enabled:
            from terrain_perception import _patch_kernels
            _kernels = _patch_kernels
        else:
            _kernels = None
        return _kernels is not None


def compiled_kernels_active() -> bool:
    """Whether find_patches currently runs the compiled kernels."""
    return _get_kernels() is not None


def _check_cloud(cloud: np.ndarray) -> np.ndarray:
    cloud = np.asarray(cloud)
    if cloud.ndim != 3 or cloud.shape[2] != 3:
        raise ValueError(f'contact patches need an organized (H, W, 3) cloud, got shape '
                         f'{cloud.shape}')
    if cloud.shape[0] < 4 or cloud.shape[1] < 4:
        raise ValueError(f'organized cloud {cloud.shape[:2]} is too small (need >= 4x4)')
    return np.asarray(cloud, dtype=np.float32)


def _bilateral_scale(z: np.ndarray, cfg: PatchConfig, ws: Optional[_Workspace] = None,
                     all_valid: bool = False) -> np.ndarray:
    """Step 3 on the depth image ``z`` ``(H, W)`` as a per-pixel factor: filtered depth / raw
    depth.

    Only the depth image (z) is filtered; multiplying a point by its factor moves it along its
    pixel ray to the new depth. Invalid (NaN or z <= 0) points are set to 0 m before filtering,
    far outside the range sigma, so they do not bleed into valid ones. Their factor is then
    (filtered depth >= 0) / 0, inf or NaN, and so is their scaled z (NaN, 0 or negative times
    it): a scaled point is valid exactly when its z is finite, all that the later steps test.
    ``all_valid``: the caller knows every depth to be valid (then ``z`` is the filter's input)."""
    if all_valid:
        z0 = z
    else:
        z0 = _array(ws, 'z0', z.shape)
        cv2.threshold(z, 0.0, 0.0, cv2.THRESH_TOZERO, dst=z0)   # z if z > 0 else 0 (NaN kept)
        cv2.patchNaNs(z0, 0.0)
    zf = cv2.bilateralFilter(z0, cfg.bilateral_window_px, cfg.bilateral_sigma_depth_m,
                             cfg.bilateral_sigma_space_px, dst=_array(ws, 'scale', z.shape))
    with np.errstate(invalid='ignore', divide='ignore', over='ignore'):
        np.divide(zf, z0, out=zf)
    return zf


def bilateral_filter_cloud(cloud: np.ndarray, cfg: PatchConfig) -> np.ndarray:
    """Step 3: discontinuity-preserving bilateral filter of an organized cloud ``(H, W, 3)``.

    The depth image (z) is filtered; each point moves along its pixel ray to the new depth, so
    the pixel-to-point correspondence is kept. Invalid (NaN or z <= 0) points stay NaN and do not
    bleed into valid ones: they are set to 0 m before filtering, far outside the range sigma.
    """
    cloud = _check_cloud(cloud)
    z = np.ascontiguousarray(cloud[..., 2])
    with np.errstate(invalid='ignore'):
        out = cloud * _bilateral_scale(z, cfg)[..., None]
        out[~(z > 0)] = np.nan
    return out


def _median_2x2(cloud: np.ndarray, scale: Optional[np.ndarray] = None,
                ws: Optional[_Workspace] = None, finite_z: bool = False):
    """2x2 block medians of the points ``cloud * scale[..., None]`` (``(h, w, 3)``, h and w
    even; ``scale=None``: of ``cloud`` itself) as x, y, z planes ``(h/2, w/2)``; a point is
    valid when its z is finite, a block's median is over its valid points (NaN if none).

    Median of 4 = (max of the pair minima + min of the pair maxima) / 2 for any pairing; pairing
    the columns lets one ``cv2.split`` of the (h, w/2, 6) view separate even and odd columns of
    all three coordinates, and every later operation is an OpenCV call on contiguous or
    row-strided planes. ``finite_z``: the caller knows every point's z to be finite (then no
    block needs the median of its valid points only)."""
    h, w = cloud.shape[:2]
    cols = cv2.split(np.ascontiguousarray(cloud).reshape(h, w // 2, 6),
                     [_array(ws, f'col{k}', (h, w // 2)) for k in range(6)])
    if scale is not None:
        s_even, s_odd = cv2.split(scale.reshape(h, w // 2, 2),
                                  [_array(ws, f'scol{k}', (h, w // 2)) for k in range(2)])
        for k in range(3):
            cv2.multiply(cols[k], s_even, dst=cols[k])
            cv2.multiply(cols[k + 3], s_odd, dst=cols[k + 3])
    lo = _array(ws, 'lo', (h, w // 2))
    hi = _array(ws, 'hi', (h, w // 2))
    out = []
    for k in range(3):
        even, odd = cols[k], cols[k + 3]
        cv2.min(even, odd, dst=lo)
        cv2.max(even, odd, dst=hi)
        m = cv2.max(lo[0::2], lo[1::2], dst=_array(ws, f'D{k}', (h // 2, w // 2)))
        m += cv2.min(hi[0::2], hi[1::2], dst=_array(ws, 'him', (h // 2, w // 2)))
        m *= np.float32(0.5)
        out.append(m)
    if finite_z:
        return out
    # Blocks with an invalid point (NaN z): median of their valid points (NaN when none).
    zs = cv2.add(cols[2], cols[5], dst=lo)
    part = ~np.isfinite(cv2.add(zs[0::2], zs[1::2], dst=_array(ws, 'him', (h // 2, w // 2))))
    if np.any(part):
        r, c = np.nonzero(part)
        i = 2 * r * (w // 2) + c
        i = np.stack([i, i + w // 2])                  # top and bottom row of each block
        # (4, 3, k): the blocks' points (even column top, bottom, odd column top, bottom)
        v = np.stack([np.concatenate([np.take(cols[k], i), np.take(cols[k + 3], i)])
                      for k in range(3)], 1)
        bad = ~np.isfinite(v[:, 2])
        n = 4 - bad.sum(0)
        half = np.float32(0.5)
        regular = (np.isfinite(v) | bad[:, None]).all()   # valid points finite in x, y too
        np.copyto(v, np.float32(np.inf), where=bad[:, None])   # invalid points sort last
        if regular:
            # Sorting network on the four points: s0 <= s1 <= s2 <= s3 per coordinate.
            a, b = np.minimum(v[0], v[1]), np.maximum(v[0], v[1])
            c_, d = np.minimum(v[2], v[3]), np.maximum(v[2], v[3])
            s0, t1 = np.minimum(a, c_), np.maximum(a, c_)
            t2 = np.minimum(b, d)
            s1, s2 = np.minimum(t1, t2), np.maximum(t1, t2)
            med = np.where(n == 1, s0, np.where(n == 2, half * (s0 + s1),
                                                np.where(n == 3, s1, half * (s1 + s2))))
        else:   # a valid z with a non-finite x or y: sort, NaN last
            v[np.broadcast_to(bad[:, None], v.shape)] = np.nan
            srt = np.sort(v, axis=0)
            m_lo = np.take_along_axis(srt, np.maximum((n - 1) // 2, 0)[None, None], 0)[0]
            m_hi = np.take_along_axis(srt, (n // 2)[None, None], 0)[0]
            med = half * (m_lo + m_hi)
        med[:, n == 0] = np.nan
        for k in range(3):
            out[k][r, c] = med[k]
    return out


def median_downsample_2x2(cloud: np.ndarray) -> np.ndarray:
    """Step 4: ``(H, W, 3)`` -> ``(H // 2, W // 2, 3)`` by the per-coordinate median of each 2x2
    block over its valid points (NaN where the block has none)."""
    cloud = _check_cloud(cloud)
    h, w = cloud.shape[0] // 2 * 2, cloud.shape[1] // 2 * 2
    return np.stack(_median_2x2(cloud[:h, :w]), -1)


def _filter_and_downsample(cloud: np.ndarray, z: np.ndarray, cfg: PatchConfig,
                           ws: Optional[_Workspace] = None, all_valid: bool = False,
                           kernels=None):
    """Steps 3-4 without materialising the filtered full-resolution cloud: returns ``D`` as x,
    y, z planes and the step-3 factor (filtered cloud = ``cloud * scale[..., None]``, needed
    only at step 11). ``z``: the cloud's depth plane, contiguous. ``all_valid``: every depth is
    known to be finite and > 0 with a max / min ratio below 1e30; a filtered depth, a convex
    combination of its neighbours, then stays in that range too, so every scaled z is finite."""
    scale = _bilateral_scale(z, cfg, ws, all_valid)
    h, w = cloud.shape[0] // 2 * 2, cloud.shape[1] // 2 * 2
    if kernels is not None:     # (compiled: the same medians, bitwise)
        D = [_array(ws, f'D{k}', (h // 2, w // 2)) for k in range(3)]
        kernels.median_2x2_scaled(cloud, scale, *D)
        return D, scale
    return _median_2x2(cloud[:h, :w], scale[:h, :w], ws, all_valid), scale


# --------------------------------------------------------------------------------------------
# Stage II
# --------------------------------------------------------------------------------------------

def gravity_in_camera(q_world_imu: np.ndarray, R_imu_camera: np.ndarray) -> np.ndarray:
    """Step 2: unit gravity vector (pointing down) in the camera frame.

    Args:
        q_world_imu: absolute IMU orientation quaternion (x, y, z, w), world z up.
        R_imu_camera: 3x3 rotation of the camera frame in the IMU frame.
    """
    from terrain_perception.transforms import quat_to_R
    q = np.asarray(q_world_imu, dtype=np.float64)
    if q.shape != (4,) or not np.all(np.isfinite(q)) or np.linalg.norm(q) < 1e-6:
        raise ValueError(f'IMU orientation must be a finite non-zero quaternion, got {q}')
    R_world_camera = quat_to_R(q) @ np.asarray(R_imu_camera, dtype=np.float64)
    return R_world_camera.T @ np.array([0.0, 0.0, -1.0])


def fixation_point(gravity_cam: np.ndarray, cfg: PatchConfig) -> np.ndarray:
    """Step 5: ``f = l_d g + l_f ([1 0 0]^T x g)`` in the camera frame [m]."""
    return _fixation(_unit_gravity(gravity_cam), cfg)


def _fixation(g: np.ndarray, cfg: PatchConfig) -> np.ndarray:
    """:func:`fixation_point` given the unit gravity ``g``."""
    # [1 0 0]^T x g = (0, -g_z, g_y), written out (np.cross costs ~60 us)
    return cfg.fixation_down_m * g + cfg.fixation_forward_m * np.array([0.0, -g[2], g[1]])


def _unit_gravity(gravity_cam: np.ndarray) -> np.ndarray:
    g = np.asarray(gravity_cam, dtype=np.float64).reshape(-1)
    n = np.linalg.norm(g) if g.shape == (3,) else 0.0
    if not np.isfinite(n) or n < 1e-6:
        raise ValueError(f'gravity must be a finite non-zero 3-vector, got {gravity_cam}')
    return g / n


# --------------------------------------------------------------------------------------------
# Stage III
# --------------------------------------------------------------------------------------------

def smallest_eigenvectors(C: np.ndarray) -> np.ndarray:
    """Unit eigenvectors of the smallest eigenvalue of symmetric 3x3 matrices ``(..., 3, 3)``.

    Closed form (trigonometric eigenvalue, then the largest cross product of two rows of
    ``C - lambda I``), vectorised; much faster than a batched ``eigh`` on many small matrices.
    """
    C = np.asarray(C, dtype=np.float64)
    v = _smallest_eigenvector_parts(C[..., 0, 0], C[..., 0, 1], C[..., 0, 2], C[..., 1, 1],
                                    C[..., 1, 2], C[..., 2, 2])
    return np.stack(v, -1)


def _smallest_eigenvector_parts(a00, a01, a02, a11, a12, a22):
    """:func:`smallest_eigenvectors` on the six distinct entries of the matrices (arrays of one
    shape); returns the eigenvectors' x, y, z components. Works on separate arrays so that the
    callers need not build ``(..., 3, 3)`` stacks (small batches are bound by numpy's per-call
    cost, not by arithmetic)."""
    q = (a00 + a11 + a22) / 3.0
    p1 = a01 * a01 + a02 * a02 + a12 * a12
    b00, b11, b22 = a00 - q, a11 - q, a22 - q
    p2 = b00 * b00 + b11 * b11 + b22 * b22 + 2.0 * p1
    p = np.sqrt(np.maximum(p2 / 6.0, 1e-300))
    det = (b00 * (b11 * b22 - a12 * a12) - a01 * (a01 * b22 - a12 * a02)
           + a02 * (a01 * a12 - b11 * a02))
    r = np.minimum(np.maximum(det / (2.0 * p ** 3), -1.0), 1.0)
    lam = q + 2.0 * p * np.cos(np.arccos(r) / 3.0 + 2.0 * np.pi / 3.0)
    d0, d1, d2 = a00 - lam, a11 - lam, a22 - lam
    # Cross products of the rows (d0 a01 a02), (a01 d1 a12), (a02 a12 d2) of C - lambda I; the
    # longest one is the best-conditioned eigenvector estimate. Three of the nine components
    # repeat (up to sign, exactly): r1 x r2 = (d1 d2 - a12^2, -c10, c00), r0 x r2 has z = -c01.
    c00, c01, c02 = a01 * a12 - a02 * d1, a02 * a01 - d0 * a12, d0 * d1 - a01 * a01  # r0 x r1
    c10, c11, c20 = a01 * d2 - a02 * a12, a02 * a02 - d0 * d2, d1 * d2 - a12 * a12
    c = ((c00, c01, c02), (c10, c11, -c01), (c20, -c10, c00))
    s00, s01, s10 = c00 * c00, c01 * c01, c10 * c10
    n0 = (s00 + c02 * c02) + s01             # (x^2 + z^2) + y^2: the order einsum sums in
    n1 = (s10 + s01) + c11 * c11
    n2 = (c20 * c20 + s00) + s10
    use0 = (n0 >= n1) & (n0 >= n2)          # the first longest, as argmax would pick
    use1 = ~use0 & (n1 >= n2)
    vn = np.sqrt(np.where(use0, n0, np.where(use1, n1, n2)))
    iso = vn == 0                           # isotropic: any direction
    s = np.where(iso, 1.0, vn)
    v = [np.where(use0, c[0][k], np.where(use1, c[1][k], c[2][k])) / s for k in range(3)]
    v[2] = np.where(iso, 1.0, v[2])
    return v


class IntegralMoments:
    """Integral images of point count, sums and second moments of an organized cloud, giving the
    covariance (hence the normal) of any axis-aligned pixel window in O(1) (paper 003, [31])."""

    def __init__(self, cloud: np.ndarray) -> None:
        cloud = _check_cloud(cloud)
        self._build(cloud[..., 0], cloud[..., 1], cloud[..., 2], None)

    @classmethod
    def _from_planes(cls, x: np.ndarray, y: np.ndarray, z: np.ndarray,
                     ws: Optional[_Workspace] = None, kernels=None) -> 'IntegralMoments':
        """The same from x, y, z planes ``(h, w)``, its images in the workspace ``ws``;
        ``kernels``: built by the compiled kernel (the same images, bitwise)."""
        self = cls.__new__(cls)
        self._build(x, y, z, ws, kernels)
        return self

    def _build(self, x, y, z, ws, kernels=None) -> None:
        valid = np.isfinite(z)
        h, w = valid.shape
        # Centre on the mean point to keep the second moments well conditioned; the centred
        # float32 products lose nothing that matters (relative 1e-7 of ~0.1 m coordinates), and
        # the integrals themselves are summed in float64.
        # Any point near the data will do: the mean of a 1/16 subsample (all points if that has
        # none) saves a gather of every valid point. (Summed in order, as a mean over the rows
        # of an (n, 3) array is.)
        vs = valid[::4, ::4]
        sub = [c[::4, ::4][vs] for c in (x, y, z)] if vs.any() else [c[valid] for c in (x, y, z)]
        self.offset = (np.array([np.cumsum(c, dtype=np.float64)[-1] for c in sub]) / len(sub[0])
                       if len(sub[0]) else np.zeros(3))
        self.shape = (h, w)
        if kernels is not None:
            self.ii = [_array(ws, f'ii_{k}', (h + 1, w + 1, 1 if k == 0 else 3),
                              np.int32 if k == 0 else np.float64) for k in range(4)]
            kernels.integral_moments(x, y, z, *np.float32(self.offset), *self.ii)
            return
        # P: the centred points, 0 where invalid (z not finite).
        P = cv2.merge([x, y, z], dst=_array(ws, 'ii_P', (h, w, 3)))
        cv2.subtract(P, tuple(np.float32(self.offset).tolist()) + (0.0,), dst=P)
        if not valid.all():
            P[~valid] = 0.0
        # OpenCV's integral is one C pass per image, ~20x numpy's two cumsums. The squares are
        # exact in float64, as integral2 would form them, but integral2's second output costs
        # more than this second image. The products are float32: x y, y z, z x.
        Pr = _array(ws, 'ii_Pr', (h, w, 3))
        cv2.mixChannels([P], [Pr], [0, 2, 1, 0, 2, 1])       # (y, z, x)
        Q = cv2.multiply(P, P, dtype=cv2.CV_64F, dst=_array(ws, 'ii_Q', (h, w, 3), np.float64))
        images = (valid.view(np.uint8), P, Q, cv2.multiply(P, Pr, dst=Pr))
        # channels: [n] (int32), [x, y, z], [xx, yy, zz], [xy, yz, zx]
        self.ii = [cv2.integral(a, sdepth=cv2.CV_32S if k == 0 else cv2.CV_64F,
                                sum=_array(ws, f'ii_{k}', (h + 1, w + 1, 1 if k == 0 else 3),
                                           np.int32 if k == 0 else np.float64))
                   for k, a in enumerate(images)]

    def window_normals(self, rows: np.ndarray, cols: np.ndarray, half: np.ndarray,
                       min_points: int = 6):
        """Normals (unit, sign arbitrary) and point counts of the windows centred at
        ``(rows, cols)`` with half-size ``half`` [px] (clipped at the image border).
        Windows with fewer than ``min_points`` valid points get a NaN normal. (Centres inside the
        image, ``half >= 0``.)"""
        h, w = self.shape
        r0 = np.maximum(rows - half, 0)          # (clipped at the border; half >= 0)
        r1 = np.minimum(rows + half + 1, h)
        c0 = np.maximum(cols - half, 0)
        c1 = np.minimum(cols + half + 1, w)
        corners = np.stack([r1 * (w + 1) + c1, r0 * (w + 1) + c0,
                            r0 * (w + 1) + c1, r1 * (w + 1) + c0])
        # The corners of all images side by side (counts as float64: exact), then the box sums.
        v = np.empty(corners.shape + (10,))
        for ii, ch in zip(self.ii, (slice(0, 1), slice(1, 4), slice(4, 7), slice(7, 10))):
            v[..., ch] = np.take(ii.reshape(-1, ii.shape[-1]), corners, axis=0)
        s = v[0] + v[1] - v[2] - v[3]
        n = s[:, 0]
        m = s / np.maximum(n, 1.0)[:, None]   # n, x, y, z, xx, yy, zz, xy, yz, zx
        mx, my, mz = m[:, 1], m[:, 2], m[:, 3]
        normals = np.stack(_smallest_eigenvector_parts(
            m[:, 4] - mx * mx, m[:, 7] - mx * my, m[:, 9] - mx * mz,
            m[:, 5] - my * my, m[:, 8] - my * mz, m[:, 6] - mz * mz), -1)
        normals[n < min_points] = np.nan
        return normals, n


def _integral_normals(pts: np.ndarray, rows: np.ndarray, cols: np.ndarray, focal_px: float,
                      radius_m: float, moments: IntegralMoments):
    """:func:`integral_normals` given the points ``pts`` ``(k, 3)`` at ``(rows, cols)``; both
    scales in one window query."""
    pts = pts.astype(np.float64)
    z = pts[:, 2]
    half_large = np.maximum(np.rint(radius_m * focal_px / z), 1).astype(np.int64)
    half_small = np.maximum(np.rint(0.5 * radius_m * focal_px / z), 1).astype(np.int64)
    k = len(rows)
    nrm, _ = moments.window_normals(np.concatenate([rows, rows]), np.concatenate([cols, cols]),
                                    np.concatenate([half_large, half_small]))
    flip = np.einsum('ij,ij->i', nrm, np.concatenate([pts, pts])) > 0
    nrm[flip] *= -1.0
    return nrm[:k], nrm[k:]


def integral_normals(cloud_ds: np.ndarray, rows: np.ndarray, cols: np.ndarray,
                     focal_px: float, radius_m: float, moments: Optional[IntegralMoments] = None):
    """Step 7 at the given pixels of the downsampled cloud ``(h, w, 3)``: the r-scale normal
    ``N`` (window side ``2 r f / Z``) and the r/2-scale normal ``N_s`` (side ``r f / Z``), both
    oriented towards the camera (``n . p < 0``). Returns ``(N, N_s)``, ``(k, 3)`` each."""
    if moments is None:
        moments = IntegralMoments(cloud_ds)
    return _integral_normals(cloud_ds[rows, cols], rows, cols, focal_px, radius_m, moments)


def saliency(N: np.ndarray, Ns: np.ndarray, gravity_cam: np.ndarray, cfg: PatchConfig):
    """Steps 8-9 on normals ``N`` (r scale) and ``N_s`` (r/2 scale), ``(k, 3)`` each.

    Returns ``(don, dong, keep)``: the DoN angle between N and N_s [rad], the DoNG angle between
    N and -gravity [rad] (NaN where a normal is missing), and the points passing both
    ``N . N_s >= cos(phi_d)`` and ``-N . g >= cos(phi_g)``."""
    return _saliency(N, Ns, _unit_gravity(gravity_cam), cfg)


def _saliency(N: np.ndarray, Ns: np.ndarray, g: np.ndarray, cfg: PatchConfig):
    """:func:`saliency` given the unit gravity ``g``."""
    cdon = np.einsum('ij,ij->i', N, Ns)
    cdong = -N @ g
    with np.errstate(invalid='ignore'):
        keep = ((cdon >= math.cos(math.radians(cfg.max_don_deg)))
                & (cdong >= math.cos(math.radians(cfg.max_dong_deg))))
    return (np.arccos(np.minimum(np.maximum(cdon, -1.0), 1.0)),
            np.arccos(np.minimum(np.maximum(cdong, -1.0), 1.0)), keep)


def patch_filters(kx: np.ndarray, ky: np.ndarray, residual: np.ndarray, cfg: PatchConfig):
    """Steps 13-14: ``(curvature_ok, residual_ok)`` masks for fitted patches: min principal
    curvature >= kappa_min and max <= kappa_max [1/m]; RMS Euclidean residual <= d_max [m]."""
    kmin, kmax = np.minimum(kx, ky), np.maximum(kx, ky)
    return ((kmin >= cfg.kappa_min_per_m) & (kmax <= cfg.kappa_max_per_m),
            residual <= cfg.max_residual_m)


# --------------------------------------------------------------------------------------------
# Stage IV: paraboloid fit
# --------------------------------------------------------------------------------------------

@dataclass
class ParaboloidFit:
    """Batched paraboloid fits ``z = 0.5 (kx x^2 + ky y^2)`` in each patch frame.

    Attributes (P patches):
        vertex: (P, 3) patch frame origin [m].
        R: (P, 3, 3) patch frame axes as columns (x, y principal directions, z normal).
        kx, ky: (P,) principal curvatures [1/m], kx <= ky.
        rms_algebraic: (P,) RMS of ``0.5 (kx x^2 + ky y^2) - z`` in the patch frame [m].
        rms_euclidean: (P,) RMS first-order (Sampson) point-to-surface distance [m].
        radius: (P,) radius [m] of the disc (in the patch x-y plane) holding 95 % of the points.
        count: (P,) number of points fitted.
    """

    vertex: np.ndarray
    R: np.ndarray
    kx: np.ndarray
    ky: np.ndarray
    rms_algebraic: np.ndarray
    rms_euclidean: np.ndarray
    radius: np.ndarray
    count: np.ndarray


def _rotvec_kernels():
    """scipy's compiled rotation-vector -> quaternion -> matrix kernels behind ``Rotation``, or
    None. ``Rotation.from_rotvec(w).as_matrix()`` spends ~25 us of its ~35 us per call on
    array-API dispatch; the fit calls it ~8 times a frame. The kernels are private, so they are
    used only if they exist and reproduce ``Rotation`` exactly on a sample."""
    try:
        from scipy.spatial.transform import _rotation_cy as cy
        w = np.array([[0.1, -0.2, 0.3], [0.0, 0.0, 0.0], [1e-5, 2e-6, -3e-5]])
        if np.array_equal(np.asarray(cy.as_matrix(cy.from_rotvec(w))),
                          Rotation.from_rotvec(w).as_matrix()):
            return cy.from_rotvec, cy.as_matrix
    except Exception:   # any change of the private API: use the public one
        pass
    return None


_ROTVEC_KERNELS = _rotvec_kernels()


def _raise_singular(err, flag):
    raise np.linalg.LinAlgError('Singular matrix')


try:   # np.linalg.solve's LAPACK gufunc (its checks and dispatch are ~10 us of ~20 us a call)
    from numpy.linalg._umath_linalg import solve as _solve_gufunc
except ImportError:    # pragma: no cover
    _solve_gufunc = None


def _solve(A: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``np.linalg.solve(A, b)`` for float64 stacks ``A`` (..., m, m) and ``b`` (..., m, k):
    the same gufunc call and error handling, without the argument checks (the fit solves ~8
    small batches a frame)."""
    if _solve_gufunc is None:
        return np.linalg.solve(A, b)
    with np.errstate(call=_raise_singular, invalid='call', over='ignore', divide='ignore',
                     under='ignore'):
        return _solve_gufunc(A, b, signature='dd->d')


def _expmap(w: np.ndarray) -> np.ndarray:
    """Rodrigues: rotation matrices ``(N, 3, 3)`` of rotation vectors ``(N, 3)`` (scipy's
    compiled conversion: a numpy version is ~40 calls, which dominate for small batches)."""
    if _ROTVEC_KERNELS is not None:
        to_quat, to_matrix = _ROTVEC_KERNELS
        return np.asarray(to_matrix(to_quat(w)))
    return Rotation.from_rotvec(w).as_matrix()


def _rot_z(theta: np.ndarray) -> np.ndarray:
    c, s = np.cos(theta), np.sin(theta)
    R = np.zeros((len(theta), 3, 3))
    R[:, 0, 0], R[:, 0, 1], R[:, 1, 0], R[:, 1, 1], R[:, 2, 2] = c, -s, s, c, 1.0
    return R


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross products of (N, 3) arrays (np.cross spends most of its time on axes)."""
    return np.stack([a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1], a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2],
                     a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]], -1)


def _to_frames(R: np.ndarray, d: np.ndarray, out: np.ndarray) -> np.ndarray:
    """``R^T d`` for frames ``R`` ``(P, 3, 3)`` and points ``d`` as x, y, z planes ``(3, P, n)``,
    written to the planes ``out`` ``(3, P, n)``: one matmul (a BLAS call per patch)."""
    np.matmul(R.transpose(0, 2, 1), d.transpose(1, 0, 2), out=out.transpose(1, 0, 2))
    return out


def _gram(A: np.ndarray) -> np.ndarray:
    """``A_p A_p^T`` ``(P, k, k)`` of the rows ``A`` given as planes ``(k, P, n)``."""
    return np.matmul(A.transpose(1, 0, 2), A.transpose(1, 2, 0))


_K_STEP = np.array([0, 1, 5])          # the (kx, ky, h) entries of an LM step


def _finish_residuals(X: np.ndarray, K: np.ndarray, tmp: np.ndarray) -> None:
    """Rows 0, 1 (``q_x^2 / 2``, ``q_y^2 / 2``) and 6 (the masked residuals
    ``(0.5 (kx q_x^2 + ky q_y^2) - (q_z - h)) W``) of the LM planes ``X`` (10, P, n) (see
    :func:`_fit_paraboloids`) from its frame coordinates (rows 7-9) and mask (row 5), for the
    per-patch ``K = (kx, ky, h)`` (3, P); ``tmp``: scratch planes (2, P, n)."""
    np.multiply(X[7:9], X[7:9], out=X[0:2])
    X[0:2] *= 0.5
    np.multiply(X[0:2], K[:2, :, None], out=tmp)
    np.add(tmp[0], tmp[1], out=X[6])
    np.subtract(X[9], K[2, :, None], out=tmp[0])
    X[6] -= tmp[0]
    X[6] *= X[5]


def _planes(buf: np.ndarray, rows: int, na: int, n: int) -> np.ndarray:
    """The first ``rows * na * n`` elements of the flat buffer ``buf`` as contiguous planes
    ``(rows, na, n)``."""
    return buf[:rows * na * n].reshape(rows, na, n)


def fit_paraboloids(points: np.ndarray, mask: np.ndarray, up: np.ndarray,
                    iterations: int = 6) -> ParaboloidFit:
    """Fit one paraboloid per neighbourhood, all neighbourhoods at once.

    Args:
        points: (P, n, 3) neighbourhood points [m] (padding rows are ignored via ``mask``).
        mask: (P, n) bool, True for real points (each patch needs >= 6).
        up: (3,) or (P, 3) direction the patch normals should point to (e.g. ``-gravity``).
        iterations: at most this many Levenberg-Marquardt iterations after the closed-form start
            (it stops once no patch's squared residual drops by more than 0.1 % of itself).

    Closed-form start: PCA frame at the centroid, linear least squares of the general quadric
    ``z = a x^2 + b xy + c y^2 + d x + e y + f``; its tangent tilt, height and Hessian give the
    initial pose and curvatures. LM then minimises the algebraic residual
    ``0.5 (kx x^2 + ky y^2) - z`` over (kx, ky, rotation, offset h along the normal), the vertex
    constrained to ``centroid + h * normal`` so the patch stays centred on its data.
    """
    P = np.asarray(points, dtype=np.float64)
    M = np.asarray(mask, dtype=bool)
    if P.ndim != 3 or P.shape[2] != 3 or M.shape != P.shape[:2]:
        raise ValueError(f'points must be (P, n, 3) with a (P, n) mask, got {P.shape} and '
                         f'{M.shape}')
    cnt = M.sum(axis=1)
    if np.any(cnt < 6):
        raise ValueError(f'every neighbourhood needs >= 6 points, the smallest has {cnt.min()}')
    D = np.empty((4,) + M.shape)
    D[:3] = P.transpose(2, 0, 1)
    np.copyto(D[:3], 0.0, where=~M)
    D[3] = M
    kernels = _get_kernels()
    if kernels is not None:
        return _fit_paraboloids_compiled(kernels, D, up, iterations)
    return _fit_paraboloids(D, M, cnt, up, iterations)


def _fit_paraboloids_compiled(kernels, D: np.ndarray, up: np.ndarray,
                              iterations: int) -> ParaboloidFit:
    """:func:`_fit_paraboloids` by the compiled kernel (one patch at a time; the same fits up to
    rounding) on the planes ``D`` ``(4, P, n)`` (x, y, z, mask as 0/1; not modified)."""
    npatch = D.shape[1]
    up_p = np.empty((npatch, 3))
    up_p[:] = np.asarray(up, dtype=np.float64)               # (3,) or (P, 3)
    vertex, R = np.empty((npatch, 3)), np.empty((npatch, 3, 3))
    kx, ky, rms_alg, rms_euc, radius = np.empty((5, npatch))
    cnt = np.empty(npatch, np.int64)
    kernels.fit_paraboloids(np.ascontiguousarray(D, dtype=np.float64), up_p, int(iterations),
                            vertex, R, kx, ky, rms_alg, rms_euc, radius, cnt)
    return ParaboloidFit(vertex, R, kx, ky, rms_alg, rms_euc, radius, cnt)


def _fit_paraboloids(D: np.ndarray, M: np.ndarray, cnt: np.ndarray, up: np.ndarray,
                     iterations: int, ws: Optional[_Workspace] = None) -> ParaboloidFit:
    """:func:`fit_paraboloids` on the planes ``D`` ``(4, P, n)``: x, y, z with padding points
    zeroed, and the mask as 0/1 (D is overwritten); ``cnt``: points per patch."""
    # A frame has ~100 patches of ~50 points, so numpy's per-call cost, not arithmetic, sets the
    # time. Per-point quantities are therefore kept as contiguous planes (quantity, patch,
    # point), on which every operation is one flat loop, and sums over a patch's points are
    # matmuls (one BLAS call per patch).
    npatch, n = M.shape
    # D: x, y, z relative to the patch centroid, and the mask W (0/1). Padding points are
    # zeroed, so they sit at 0 in every frame below and only constant terms need W.
    d, W = D[:3], D[3]
    c = d.sum(2) / cnt
    d -= c[:, :, None]
    d *= W
    c = c.T
    cov = _gram(d) / cnt[:, None, None]
    n0 = np.stack(_smallest_eigenvector_parts(cov[:, 0, 0], cov[:, 0, 1], cov[:, 0, 2],
                                              cov[:, 1, 1], cov[:, 1, 2], cov[:, 2, 2]), -1)
    n0[(n0 * np.asarray(up, dtype=np.float64)).sum(1) < 0] *= -1.0
    # PCA frame with z = normal, x = helper x normal (normalised) with the helper e_x, or e_y
    # when the normal is near e_x.
    nx, ny, nz = n0.T
    zero = np.zeros(npatch)
    x0 = np.where((np.abs(nx) < 0.9)[:, None], np.stack([zero, -nz, ny], -1),
                  np.stack([nz, zero, -nx], -1))
    x0 /= np.sqrt(np.einsum('pi,pi->p', x0, x0))[:, None]
    y0 = _cross(n0, x0)
    Rp = np.stack([x0, y0, n0], axis=-1)
    # Normal equations of the quadric from one Gram matrix of [design rows; right-hand side].
    A = np.empty((7, npatch, n))
    qx, qy, qz = _to_frames(Rp, d, A[3:6])                 # x, y, then z (moved below)
    A[6] = qz
    np.multiply(qx, qx, out=A[0])
    np.multiply(qx, qy, out=A[1])
    np.multiply(qy, qy, out=A[2])
    A[5] = W
    G = _gram(A)
    diag = G.reshape(-1, 49)[:, 0:42:8]                     # (of the 6x6 block A^T A)
    diag += 1e-9 * np.maximum(diag.sum(1), 1e-12)[:, None]
    sol = _solve(G[:, :6, :6], G[:, :6, 6:])[..., 0]
    a, b, cc, dx, dy, f0 = sol.T
    # Tilt the normal to the quadric's normal at the origin t = (-dx, -dy, 1) / |.| (Rt: the
    # rotation about e_z x t that takes e_z to t, Rodrigues' formula written out), then align x,
    # y with the principal directions of the quadric's Hessian [[2a, b], [b, 2c]]: its
    # eigenvalues along them are a + c +- sqrt((a - c)^2 + b^2).
    t = np.stack([-dx, -dy, np.ones(npatch)], -1)
    t /= np.sqrt(1.0 + dx * dx + dy * dy)[:, None]
    Rt = np.empty((npatch, 3, 3))
    txy = t[:, :2]
    np.multiply(txy[:, :, None], (-1.0 / (1.0 + t[:, 2]))[:, None, None] * txy[:, None, :],
                out=Rt[:, :2, :2])
    Rt[:, 0, 0] += 1.0
    Rt[:, 1, 1] += 1.0
    Rt[:, :2, 2] = txy
    Rt[:, 2, :2] = -txy
    Rt[:, 2, 2] = t[:, 2]
    amc = a - cc
    theta = 0.5 * np.arctan2(b, amc)
    R = Rp @ (Rt @ _rot_z(theta))
    rho = np.sqrt(amc * amc + b * b)
    K = np.stack([(a + cc) + rho, (a + cc) - rho, f0 * t[:, 2]])    # kx, ky, h

    # LM on each patch until its own squared residual stops dropping by more than 0.1 % (or
    # `iterations`); converged patches leave the batch (their state is written back then), so
    # later iterations are cheap.
    #
    # The active patches' per-point planes live in one block X (10, na, n), rows
    #   0-4  J: d r / d (kx, ky, omega) (rows 0, 1 = q_x^2 / 2, q_y^2 / 2 are part of the state,
    #        rows 2-4 are recomputed each iteration)
    #   5    W, the d r / d h row (padding points have q = 0, so only this row needs W)
    #   6    r, the residuals
    #   7-9  q: the points in the patch frame before the offset h, R^T (p - c)
    # so that rows 0-6 are [J; r] and one Gram matrix gives the Gauss-Newton matrix J^T J and
    # the gradient J^T r. A step's candidate state is computed into a second block Y; accepting
    # it swaps the blocks (rejected patches copy their old state over), so no iteration allocates
    # or copies whole planes. Q: the final planes r, q_x, q_y, q_z of every patch.
    Q = np.empty((4, npatch, n))
    bufs = [_array(ws, f'lm{k}', (10 * npatch * n,), np.float64) for k in range(2)]
    tbuf = _array(ws, 'lmt', (2 * npatch * n,), np.float64)
    X, Y = _planes(bufs[0], 10, npatch, n), _planes(bufs[1], 10, npatch, n)
    X[5] = Y[5] = W
    T = _planes(tbuf, 2, npatch, n)
    _to_frames(R, d, X[7:10])
    _finish_residuals(X, K, T)
    cur = np.einsum('pn,pn->p', X[6], X[6])
    lam = np.full(npatch, 1e-3)
    act = np.arange(npatch)
    Ra, Ka = R, K
    for _ in range(iterations):
        qx, qy, qz = X[7:10]
        # With g = d r / d q = (gx, gy, -1) = (kx qx, ky qy, -1), d r / d omega = (g x q)^T:
        # rows 2-4 = (gy qz + qy, -qx - gx qz, gx qy - gy qx).
        g = np.multiply(Ka[:2, :, None], X[7:9], out=T)
        np.multiply(g[1], qz, out=X[2])
        X[2] += qy
        np.multiply(g[0], qz, out=X[3])
        X[3] += qx
        np.negative(X[3], out=X[3])                        # -(qx + gx qz) = -qx - gx qz exactly
        np.multiply(g[0], qy, out=X[4])
        np.multiply(g[1], qx, out=g[0])
        X[4] -= g[0]
        G = _gram(X[:7])
        # LM damping lam * diag(H), in place on the Gram matrix (H is its 6x6 block)
        diag = G.reshape(-1, 49)[:, 0:42:8]
        diag *= 1.0 + lam[:, None]
        diag += 1e-12 * lam[:, None]
        step = _solve(G[:, :6, :6], G[:, :6, 6:])[..., 0]   # (the step is minus this)
        E = _expmap(-step[:, 2:5])
        R_new = Ra @ E
        K_new = Ka - step.T[_K_STEP]
        _to_frames(E, X[7:10], Y[7:10])                    # R_new^T (p - c) = E^T R^T (p - c)
        _finish_residuals(Y, K_new, T)
        new = np.einsum('pn,pn->p', Y[6], Y[6])
        ok = new < cur
        go = (cur - new > 1e-3 * cur) | ~ok                # rejected steps retry with more damping
        lam = np.minimum(np.maximum(lam * np.where(ok, 0.1, 10.0), 1e-9), 1e9)
        go &= lam < 1e9
        if not ok.all():                                   # keep the old state where rejected
            rej = np.flatnonzero(~ok)
            Y[:, rej] = X[:, rej]
            R_new[rej] = Ra[rej]
            K_new[:, rej] = Ka[:, rej]
            new[rej] = cur[rej]
        X, Y, Ra, Ka, cur = Y, X, R_new, K_new, new
        bufs.reverse()
        if not go.all():
            done = np.flatnonzero(~go)
            R[act[done]], K[:, act[done]], Q[:, act[done]] = Ra[done], Ka[:, done], X[6:, done]
            if len(done) == len(act):
                break
            keep = np.flatnonzero(go)
            act, Ra, Ka, lam, cur = act[keep], Ra[keep], Ka[:, keep], lam[keep], cur[keep]
            na = len(keep)
            X = np.take(X, keep, axis=1, out=_planes(bufs[1], 10, na, n))
            bufs.reverse()
            Y = _planes(bufs[1], 10, na, n)
            Y[5] = X[5]
            T = _planes(tbuf, 2, na, n)
    else:
        R[act], K[:, act], Q[:, act] = Ra, Ka, X[6:]
    r, qx, qy, qz = Q
    kx, ky, h = K
    gn = np.sqrt((kx[:, None] * qx) ** 2 + (ky[:, None] * qy) ** 2 + 1.0)
    # Order kx <= ky: swap by a +90 deg turn about the normal (x' = y, y' = -x; the residuals,
    # gn and the radii below do not change).
    swap = kx > ky
    R[swap, :, 0], R[swap, :, 1] = R[swap, :, 1], -R[swap, :, 0]
    K[0, swap], K[1, swap] = K[1, swap], K[0, swap]
    rms_alg = np.sqrt(np.einsum('pn,pn->p', r, r) / cnt)
    r /= gn
    rms_euc = np.sqrt(np.einsum('pn,pn->p', r, r) / cnt)
    rad = np.sort(np.where(M, np.sqrt(qx * qx + qy * qy), np.inf), axis=1)
    radius = np.take_along_axis(rad, np.floor(0.95 * (cnt - 1)).astype(np.int64)[:, None],
                                axis=1)[:, 0]
    vertex = c + h[:, None] * R[:, :, 2]
    return ParaboloidFit(vertex, R, kx, ky, rms_alg, rms_euc, radius, cnt)


# --------------------------------------------------------------------------------------------
# The whole pipeline
# --------------------------------------------------------------------------------------------

@dataclass
class PatchSet:
    """Contact patches found in one frame (all in the cloud's frame).

    Attributes (N patches):
        vertex (N, 3) [m], R (N, 3, 3) (columns x, y, normal), kx, ky (N,) [1/m] (kx <= ky),
        radius (N,) [m], residual (N,) RMS Euclidean residual [m], don, dong (N,) [rad],
        fixation_distance (N,) [m], support_points (N,) int.
        gravity: (3,) unit gravity used; fixation: (3,) fixation point [m].
        counts: how many candidates survived each step (for diagnostics and benchmarks).
    """

    vertex: np.ndarray
    R: np.ndarray
    kx: np.ndarray
    ky: np.ndarray
    radius: np.ndarray
    residual: np.ndarray
    don: np.ndarray
    dong: np.ndarray
    fixation_distance: np.ndarray
    support_points: np.ndarray
    gravity: np.ndarray
    fixation: np.ndarray
    counts: Dict[str, int] = dataclasses.field(default_factory=dict)
    timings_ms: Dict[str, float] = dataclasses.field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.vertex.shape[0])

    @property
    def normal(self) -> np.ndarray:
        """(N, 3) unit patch normals (away from the terrain)."""
        return self.R[:, :, 2]

    def subset(self, keep: np.ndarray) -> 'PatchSet':
        keep = np.asarray(keep)
        fields = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        for k in ('vertex', 'R', 'kx', 'ky', 'radius', 'residual', 'don', 'dong',
                  'fixation_distance', 'support_points'):
            fields[k] = fields[k][keep]
        fields['counts'] = dict(self.counts)
        fields['timings_ms'] = dict(self.timings_ms)
        return PatchSet(**fields)

    def transformed(self, T: np.ndarray) -> 'PatchSet':
        """The same patches with poses mapped by the 4x4 transform ``T`` (e.g. ``T_map_cam``)."""
        T = np.asarray(T, dtype=np.float64)
        out = self.subset(np.arange(len(self)))
        out.vertex = self.vertex @ T[:3, :3].T + T[:3, 3]
        out.R = T[:3, :3] @ self.R
        out.gravity = T[:3, :3] @ self.gravity
        out.fixation = T[:3, :3] @ self.fixation + T[:3, 3]
        return out

    def boundary(self, n: int = 16) -> np.ndarray:
        """(N, n, 3) points on each patch's rim (radius ``radius`` in the patch x-y plane)."""
        a = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
        x = self.radius[:, None] * np.cos(a)
        y = self.radius[:, None] * np.sin(a)
        z = 0.5 * (self.kx[:, None] * x * x + self.ky[:, None] * y * y)
        loc = np.stack([x, y, z], -1)
        return np.einsum('pij,pnj->pni', self.R, loc) + self.vertex[:, None]


def _empty_patches(gravity, fixation, counts, timings) -> PatchSet:
    z = np.zeros(0)
    return PatchSet(np.zeros((0, 3)), np.zeros((0, 3, 3)), z, z, z, z, z, z, z,
                    np.zeros(0, np.int64), gravity, fixation, counts, timings)


def _seed_band(z: np.ndarray, fix: np.ndarray, fx: float, fy: float, cfg: PatchConfig,
               depth_range: bool = False):
    """Of the depth image ``z`` (even height), the full-resolution rows ``[a, b)`` (even) that
    steps 3-11 can read, and which of the downsampled rows in them can hold a seed; ``None``
    when no row can. ``depth_range``: also the least and the largest depth in the rows (NaN
    ignored, depths <= 0 included).

    Exact, not a heuristic: a filtered depth is a convex combination of the valid raw depths in
    its bilateral window and a 2x2 median lies between its block's values, so downsampled row
    ``i`` can hold a point within R of ``f`` (hence with ``|z - f_z| <= R``) only if the raw
    depths of rows ``2i - k .. 2i + 1 + k`` (k = bilateral radius) reach ``[f_z - R, f_z + R]``.
    Around those rows steps 7 and 11 read windows of ``r f / z`` rows (largest at the nearest
    depth a seed there can have), plus k rows so the filter is exact where it is read. Rows the
    robot's camera sees far beyond the fixation point are thus never filtered."""
    H = z.shape[0]
    # Depth range of each row pair (as one row of the (H/2, 2W) view).
    pairs = z.reshape(H // 2, -1)
    with np.errstate(invalid='ignore'):
        pmin = np.fmin.reduce(pairs, axis=1, initial=np.inf)   # NaN (invalid) ignored
        pmax = np.fmax.reduce(pairs, axis=1, initial=0.0)      # (z <= 0 is invalid as well)
    # Downsampled row i reads full rows 2i - k .. 2i + 1 + k: row pairs i - m .. i + m.
    wmin, wmax = pmin.copy(), pmax.copy()
    k = cfg.bilateral_window_px // 2
    for j in range(1, (k + 1) // 2 + 1):
        np.minimum(wmin[j:], pmin[:-j], out=wmin[j:])
        np.minimum(wmin[:-j], pmin[j:], out=wmin[:-j])
        np.maximum(wmax[j:], pmax[:-j], out=wmax[j:])
        np.maximum(wmax[:-j], pmax[j:], out=wmax[:-j])
    R = cfg.roi_radius_m * (1.0 + 1e-6) + 1e-6     # float32 rounding
    cand = (wmax >= fix[2] - R) & (wmin <= fix[2] + R)
    i = np.nonzero(cand)[0]
    if len(i) == 0:
        return None
    zlo = np.maximum(np.maximum(wmin[i], fix[2] - R), 1e-3)
    margin = np.ceil(cfg.patch_radius_m * max(fx, fy) / zlo).astype(np.int64) + 2
    a = max(int((2 * i - margin).min()) - k, 0) // 2 * 2
    b = min(int((2 * i + 2 + margin).max()) + k + 1, H) // 2 * 2
    if depth_range:
        return a, b, cand[a // 2:b // 2], pmin[a // 2:b // 2].min(), pmax[a // 2:b // 2].max()
    return a, b, cand[a // 2:b // 2]


def _sample_neighbourhoods(cloud: np.ndarray, scale: np.ndarray, seeds_rc_full: np.ndarray,
                           seed_pts: np.ndarray, fx: float, fy: float, cfg: PatchConfig,
                           rng: np.random.Generator, ws: Optional[_Workspace] = None,
                           kernels=None):
    """Step 11: organized search in the filtered cloud ``cloud * scale[..., None]``. For each
    seed draw random pixels in the image window that bounds its r-ball, keep those whose points
    lie within r, at most n_f of them. Returns the neighbourhoods as x, y, z planes and the
    mask as 0/1 ``(4, n_s, n_f)`` (in draw order, unused slots 0; the planes
    :func:`_fit_paraboloids` takes) and the mask ``(n_s, n_f)``; with ``kernels`` (compiled,
    the same draws and planes) the points per seed ``(n_s,)`` instead of the mask."""
    h, w = cloud.shape[:2]
    ns, nf = len(seed_pts), cfg.max_neighbours
    k = nf * cfg.neighbour_draws
    r = cfg.patch_radius_m
    # Column and row offsets of the draws as one (2, n_s, k) array (the same random stream as
    # drawing the column offsets first, then the row offsets), scaled to the half-windows, then
    # the drawn pixels' columns and rows (rint, clipped to the image: exact integers).
    cr = rng.random(out=_array(ws, 'draws', (2, ns, k), np.float64))
    if kernels is not None:     # (compiled: the same neighbourhoods, bitwise)
        nb = np.empty((4, ns, nf))
        n_nb = kernels.sample_neighbourhoods(
            cloud, scale, np.ascontiguousarray(seeds_rc_full, dtype=np.float64),
            np.ascontiguousarray(seed_pts, dtype=np.float64), cr, float(fx), float(fy), float(r),
            nb)
        return nb, n_nb
    cr *= 2.0
    cr -= 1.0
    cr *= np.maximum(np.array([[r * fx], [r * fy]]) / seed_pts[:, 2], 1.0)[:, :, None]
    cr += seeds_rc_full.T[::-1, :, None]
    np.rint(cr, out=cr)
    np.clip(cr, 0.0, np.array([w - 1.0, h - 1.0])[:, None, None], out=cr)
    flat = cr[1] * w
    flat += cr[0]
    flat = flat.astype(np.intp)
    s = np.take(scale.reshape(-1), flat).astype(np.float64)
    drawn = np.take(cloud.reshape(-1, 3), flat, axis=0,
                    out=_array(ws, 'drawn', (ns, k, 3)))          # (float32 points)
    # The drawn points (float64, as x, y, z planes) and their squared distances to the seeds.
    pts = []
    d2 = np.zeros((ns, k))
    for c in (0, 2, 1):                         # (the order einsum sums x^2 + y^2 + z^2 in)
        p = np.multiply(drawn[..., c], s)
        d = p - seed_pts[:, c, None]
        d *= d
        d2 += d
        pts.append(p)
    pts[1], pts[2] = pts[2], pts[1]
    ok = d2 <= r * r                                   # False for NaN
    # The first n_f accepted draws of every row, in draw order: one stable sort of the flat
    # keys 2 row + rejected puts every row's draws in its own k slots, accepted ones first;
    # slots beyond a row's count are masked and zeroed.
    key = np.arange(0, 2 * ns, 2, dtype=np.int16 if 2 * ns < 2 ** 15 else np.int64)[:, None] + ~ok
    j = np.argsort(key.reshape(-1), kind='stable').reshape(ns, k)[:, :nf]
    mask = np.take(ok, j)
    nb = np.empty((4, ns, nf))
    for c, p in enumerate(pts):
        np.take(p, j, out=nb[c])
    np.copyto(nb[:3], 0.0, where=~mask)
    nb[3] = mask
    return nb, mask


@functools.lru_cache(maxsize=8)
def _seed_sequence(seed: int) -> np.random.SeedSequence:
    """The SeedSequence ``default_rng(seed)`` builds (hashing the seed costs ~20-100 us a frame;
    generating state from it does not change it)."""
    return np.random.SeedSequence(seed)


def find_patches(cloud: np.ndarray, fx: float, fy: float, gravity_cam: np.ndarray,
                 cfg: PatchConfig = PatchConfig(), rng: Optional[np.random.Generator] = None,
                 timing: bool = False) -> PatchSet:
    """Run steps 3-14 on one organized cloud.

    Args:
        cloud: (H, W, 3) points in the camera optical frame [m], NaN = invalid (step 2's ``C``).
        fx, fy: focal lengths of the cloud's camera at its resolution [px].
        gravity_cam: (3,) gravity direction (down) in the camera frame (see
            :func:`gravity_in_camera`).
        cfg: parameters.
        rng: random generator for steps 10-11 (default: seeded from ``cfg.random_seed``).
        timing: record per-stage CPU times of this process in ``PatchSet.timings_ms``
            (benchmark instrumentation only; off by default).

    Returns:
        The accepted patches in the camera frame. No valid seeds is not an error: the result is
        empty and ``counts`` says which step removed them.
    """
    import time
    clock = time.process_time if timing else (lambda: 0.0)
    t0 = clock()
    if not (np.isfinite(fx) and np.isfinite(fy)) or fx <= 0 or fy <= 0:
        raise ValueError(f'focal lengths must be positive, got fx={fx}, fy={fy}')
    g = _unit_gravity(gravity_cam)
    rng = rng if rng is not None else np.random.Generator(np.random.PCG64(
        _seed_sequence(cfg.random_seed)))                      # = default_rng(random_seed)
    g_sal = _unit_gravity(g)     # (g normalised again: what fixation_point and saliency use)
    fix = _fixation(g_sal, cfg)
    counts: Dict[str, int] = {}
    times: Dict[str, float] = {}
    # Stage I, on the rows that the later steps can read (see _seed_band)
    ws = _workspace()
    kernels = _get_kernels()
    cloud = _check_cloud(cloud)
    if kernels is not None:     # (the kernels take C-contiguous arrays; most clouds are)
        cloud = np.ascontiguousarray(cloud)
    h_even = cloud.shape[0] // 2 * 2
    z = cv2.extractChannel(cloud[:h_even], 2, dst=ws.array('z', (h_even, cloud.shape[1])))
    band = _seed_band(z, fix, fx, fy, cfg, depth_range=True)
    if band is None:
        counts['valid_points'] = counts['dtfp'] = counts['seeds'] = 0
        times.update(stage1_ms=1e3 * (clock() - t0), stage23_ms=0.0, stage4_ms=0.0)
        return _empty_patches(g, fix, counts, times)
    a, b, cand, zlo, zhi = band
    cloud, zb = cloud[a:b], z[a:b]
    # (Most frames have invalid depths only in rows far beyond the band.)
    all_valid = 0.0 < zlo and float(zhi) < 1e30 * float(zlo) and not np.isnan(zb).any()
    (Dx, Dy, Dz), scale = _filter_and_downsample(cloud, zb, cfg, ws, all_valid, kernels)
    t1 = clock()
    times['stage1_ms'] = 1e3 * (t1 - t0)
    # Stage II: seeds within R of the fixation point
    f32 = fix.astype(np.float32)
    d2 = np.subtract(Dx, f32[0], out=ws.array('d2', Dz.shape))
    d2 *= d2
    for p, f in ((Dy, f32[1]), (Dz, f32[2])):
        t = np.subtract(p, f, out=ws.array('d2t', Dz.shape))
        t *= t
        d2 += t
    with np.errstate(invalid='ignore'):
        in_roi = np.less_equal(d2, np.float32(cfg.roi_radius_m ** 2),
                               out=ws.array('in_roi', Dz.shape, bool))
    in_roi &= cand[:, None]
    # The seed candidates as flat indices; rows and columns only where needed.
    flat = np.flatnonzero(in_roi)
    w2 = Dz.shape[1]
    if all_valid:                                   # (then every median is finite)
        counts['valid_points'] = int(np.count_nonzero(cand)) * w2
    else:
        finite = np.isfinite(Dz, out=ws.array('finite', Dz.shape, bool))
        counts['valid_points'] = int(np.count_nonzero(finite[cand]))
    counts['dtfp'] = int(len(flat))
    # Stage III + step 10. Filtering every candidate and then keeping a uniform random n_s of
    # the survivors has the same outcome distribution as visiting the candidates in uniformly
    # random order and keeping the first n_s survivors; the latter evaluates the normals of only
    # about n_s / (survival rate) candidates instead of all of them. Chunks are sized from the
    # survival rate so far.
    n_cand = len(flat)
    order = rng.choice(n_cand, min(n_cand, int(1.5 * cfg.max_seeds) + 16), replace=False)
    kept, n_kept, n_eval, n_don, n_dong = [], 0, 0, 0, 0
    if n_cand:
        # (points in the seed region are valid, so a plain min; float32 as numpy's min is)
        zmin = np.float32(cv2.minMaxLoc(Dz, in_roi.view(np.uint8))[0])
        half = int(np.ceil(cfg.patch_radius_m * 0.5 * fx / zmin)) + 1
        cols_in = np.flatnonzero(in_roi.any(0))                 # (flat is sorted: rows from it)
        r0, r1 = max(flat[0] // w2 - half, 0), min(flat[-1] // w2 + half + 1, Dz.shape[0])
        c0, c1 = max(cols_in[0] - half, 0), min(cols_in[-1] + half + 1, w2)
        box = np.s_[r0:r1, c0:c1]
        moments = IntegralMoments._from_planes(Dx[box], Dy[box], Dz[box], ws, kernels)
    while n_eval < n_cand and n_kept < cfg.max_seeds:
        if n_eval == len(order):      # first draw used up: the rest in random order
            rest = np.ones(n_cand, bool)
            rest[order] = False
            rest = np.flatnonzero(rest)                         # (sorted, as setdiff1d's)
            order = np.concatenate([order, rng.permutation(rest)])
        rate = max(n_dong / n_eval, 0.05) if n_eval else 1.0
        size = int(1.5 * (cfg.max_seeds - n_kept) / rate) + 16
        sel = flat[order[n_eval:n_eval + size]]
        n_eval += len(sel)
        rs, cs = np.divmod(sel, w2)
        N, Ns = _integral_normals(np.stack([np.take(p, sel) for p in (Dx, Dy, Dz)], -1),
                                  rs - r0, cs - c0, 0.5 * fx, cfg.patch_radius_m, moments)
        don, dong, ok = _saliency(N, Ns, g_sal, cfg)
        n_don += int(np.count_nonzero(don <= np.radians(cfg.max_don_deg)))
        n_ok = int(np.count_nonzero(ok))
        n_dong += n_ok
        n_kept += n_ok
        kept.append((sel[ok], don[ok], dong[ok]))
    if kept:
        idx, seed_don, seed_dong = [np.concatenate(k)[:cfg.max_seeds] for k in zip(*kept)]
    else:
        idx = np.zeros(0, np.int64)
    counts['normals_evaluated'] = int(n_eval)
    counts['don'] = n_don
    counts['dong'] = n_dong
    t2 = clock()
    times['stage23_ms'] = 1e3 * (t2 - t1)
    # Stage IV
    counts['seeds'] = int(len(idx))
    if len(idx) == 0:
        times['stage4_ms'] = 0.0
        return _empty_patches(g, fix, counts, times)
    rs, cs = np.divmod(idx, w2)
    seed_pts = np.stack([np.take(p, idx) for p in (Dx, Dy, Dz)], -1).astype(np.float64)
    # Seed pixel of the downsampled image -> centre of its 2x2 block at full resolution (in the
    # band's rows).
    seeds_full = np.stack([2 * rs + 0.5, 2 * cs + 0.5], -1)
    if kernels is not None:
        nb, n_nb = _sample_neighbourhoods(cloud, scale, seeds_full, seed_pts, fx, fy, cfg, rng,
                                          ws, kernels)
    else:
        nb, mask = _sample_neighbourhoods(cloud, scale, seeds_full, seed_pts, fx, fy, cfg, rng,
                                          ws)
        n_nb = mask.sum(1)
    enough = n_nb >= cfg.min_neighbours
    counts['neighbourhoods'] = int(enough.sum())
    seed_don, seed_dong = seed_don[enough], seed_dong[enough]
    sel = idx[enough]
    if len(sel) == 0:
        times['stage4_ms'] = 1e3 * (clock() - t2)
        return _empty_patches(g, fix, counts, times)
    if kernels is not None:
        if not enough.all():
            nb = nb[:, enough]
        fit = _fit_paraboloids_compiled(kernels, nb, -g, cfg.lm_iterations)
    else:
        if not enough.all():
            nb, mask, n_nb = nb[:, enough], mask[enough], n_nb[enough]
        fit = _fit_paraboloids(nb, mask, n_nb, -g, cfg.lm_iterations, ws)
    curv_ok, res_ok = patch_filters(fit.kx, fit.ky, fit.rms_euclidean, cfg)
    keep = curv_ok & res_ok
    counts['curvature'] = int(curv_ok.sum())
    counts['patches'] = int(keep.sum())
    don, dong = seed_don[keep], seed_dong[keep]
    times['stage4_ms'] = 1e3 * (clock() - t2)
    return PatchSet(fit.vertex[keep], fit.R[keep], fit.kx[keep], fit.ky[keep],
                    fit.radius[keep], fit.rms_euclidean[keep], don, dong,
                    np.linalg.norm(fit.vertex[keep] - fix, axis=1), fit.count[keep], g, fix,
                    counts, times)
