"""Seeded, reproducible rough terrains: Kolter's rock fields, Shao's stone scenes, and courses.

* **Kolter's generator** (paper 000, footnote 2): random convex bodies -- convex hulls of points
  drawn from a 3-D Gaussian with a random covariance -- are dropped into a walled square area in
  pybullet and simulated until they come to rest. The resting pile's height is sampled on a fine
  grid, convolved with a random 20x20 kernel ("to add noise") and scaled to a height range.
* **Shao's scenes** (paper 002, section IV): a flat floor with scattered stone blocks up to about
  0.15 m x 0.15 m x 0.15 m. The blocks are convex hulls of a box with a flat base and a jittered
  top, so they rest on their base where they are placed and need no simulation.
* **Courses**: flat approach, one rough section, flat exit, along +x. Classes:

  ============  =========  ======================================================
  class         generator  meaning
  ============  =========  ======================================================
  rocks-6cm     kolter     max height differential 6 cm (paper 000, Fig. 8, left)
  rocks-12cm    kolter     max height differential 12 cm (paper 000, Fig. 8, right)
  stones-15cm   stones     stone blocks up to 0.15 m (paper 002, FROG-I scale)
  ============  =========  ======================================================

Heights [m] are in the ``map`` frame, floor at z = 0. Every function takes an explicit seed; the
same seed gives the same array (the pybullet drop uses deterministic overlapping pairs).

Height sampling: pybullet's ray test against convex hulls costs ~30 us per ray, far too slow for
a 1 mm grid (1e6 rays). Since every body is convex, its top surface is exactly the lower envelope
of its upward-facing hull planes, so the resting bodies are rasterised from their hull planes and
world poses (vectorised per body). The tests check this raster against ``rayTestBatch``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, Iterable, List, Optional, Tuple

import numpy as np
from scipy.ndimage import map_coordinates
from scipy.signal import fftconvolve
from scipy.spatial import ConvexHull

from terrain_perception.config import load_config, param
from terrain_perception.grid import ELEVATION, GridMap
from terrain_perception.transforms import quat_to_R

CONFIG_PATH = Path(__file__).resolve().parents[1] / 'config' / 'terrain.yaml'


# ---------------------------------------------------------------------------------------------
# configuration
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class KolterConfig:
    """Kolter's rock-pile generator (paper 000, footnote 2)."""

    bodies_per_m2: float = param(200.0, 'convex bodies dropped per square metre of area '
                                 '(paper: 200 in 1 m^2)', 1.0, 2000.0)
    points_per_body: int = param(10, 'Gaussian points whose convex hull makes one body', 4, 64)
    body_scale_m: float = param(0.03, 'largest axis std-dev of a body\'s Gaussian [m]; bodies '
                                'are a few times this across', 0.002, 0.3)
    min_axis_ratio: float = param(0.35, 'smallest / largest axis std-dev of a body; keeps '
                                  'bodies rock-like rather than needles', 0.01, 1.0)
    sample_resolution_m: float = param(0.001, 'height sampling step before convolution [m] '
                                       '(paper: 1 mm)', 0.0005, 0.02)
    kernel_size_px: int = param(20, 'edge of the random convolution kernel [samples] '
                                '(paper: 20x20 at 1 mm)', 1, 200)
    time_step_s: float = param(1.0 / 120.0, 'physics step of the drop simulation [s]',
                               1e-4, 0.05)
    solver_iterations: int = param(5, 'contact solver iterations per step', 1, 100)
    damping: float = param(0.8, 'linear and angular damping of the falling bodies [1/s]; '
                           'shortens the time to rest', 0.0, 10.0)
    friction: float = param(0.9, 'lateral friction coefficient of bodies and floor', 0.0, 5.0)
    max_settle_time_s: float = param(2.0, 'simulated time limit of the drop [s]', 0.1, 60.0)
    rest_speed_mps: float = param(0.02, 'the pile is at rest when no body moves faster [m/s]',
                                  1e-5, 1.0)
    drop_layer_spacing_m: float = param(0.02, 'extra vertical gap between drop layers [m]',
                                        0.0, 1.0)


@dataclass(frozen=True)
class StonesConfig:
    """Shao's scattered stone blocks (paper 002, section IV)."""

    stones_per_m2: float = param(6.0, 'stone blocks per square metre of rough area', 0.1, 50.0)
    size_min_m: float = param(0.05, 'smallest block edge [m]', 0.005, 1.0)
    size_max_m: float = param(0.15, 'largest block edge [m] (paper: about 0.15 m)', 0.005, 1.0)
    min_gap_m: float = param(0.10, 'minimum free gap between neighbouring blocks [m]', 0.0, 2.0)
    top_jitter: float = param(0.2, 'top corners sink by up to this fraction of the block '
                              'height, giving irregular tops', 0.0, 0.9)
    side_jitter: float = param(0.12, 'corner jitter in x-y as a fraction of the block edge',
                               0.0, 0.4)
    sample_resolution_m: float = param(0.002, 'raster step of the block heights [m]',
                                       0.0005, 0.02)


@dataclass(frozen=True)
class CourseConfig:
    """One course class: flat approach, rough section, flat exit along +x."""

    generator: str = param('kolter', 'rough-section generator', choices=('kolter', 'stones'))
    max_height_m: float = param(0.06, 'maximum height differential of the rough section [m]',
                                0.0, 1.0)
    approach_m: float = param(1.0, 'flat approach before the rough section [m]', 0.0, 20.0)
    rough_length_m: float = param(1.0, 'rough section length along x [m]', 0.05, 20.0)
    exit_m: float = param(1.0, 'flat exit after the rough section [m]', 0.0, 20.0)
    width_m: float = param(1.0, 'course (and rough section) width along y [m]', 0.05, 20.0)
    edge_taper_m: float = param(0.05, 'the rough heights fade to the floor over this distance '
                                'at the section border [m] (0: a step at the border)', 0.0, 1.0)


COURSE_CLASSES: Dict[str, CourseConfig] = {
    'rocks-6cm': CourseConfig('kolter', 0.06, 1.0, 1.0, 1.0, 1.0, 0.05),
    'rocks-12cm': CourseConfig('kolter', 0.12, 1.0, 1.0, 1.0, 1.0, 0.05),
    'stones-15cm': CourseConfig('stones', 0.15, 1.5, 2.0, 1.5, 2.0, 0.0),
}


def course_config(cls_name: str, path: 'str | Path | None' = None) -> CourseConfig:
    """The :class:`CourseConfig` of a class, from ``path`` (a terrain YAML) or the built-ins."""
    if cls_name not in COURSE_CLASSES:
        raise ValueError(f'unknown terrain class {cls_name!r}; known: {sorted(COURSE_CLASSES)}')
    if path is None:
        return COURSE_CLASSES[cls_name]
    return load_config(CourseConfig, path, cls_name)


# ---------------------------------------------------------------------------------------------
# convex bodies
# ---------------------------------------------------------------------------------------------
def random_convex_body(rng: np.random.Generator, n_points: int, scale_m: float,
                       min_axis_ratio: float = 0.35) -> np.ndarray:
    """Hull vertices ``(k, 3)`` [m] of Gaussian points with a random covariance, centred.

    The covariance is ``R diag(s^2) R^T`` with a uniformly random rotation R and axis std-devs
    ``s`` drawn from ``[min_axis_ratio, 1] * scale_m``: random in shape and orientation, but
    without the needle-like hulls a near-singular covariance gives (one standing needle would
    set the whole terrain's height scale).
    """
    q = rng.normal(size=4)
    R = quat_to_R(q / np.linalg.norm(q))
    s = rng.uniform(min_axis_ratio, 1.0, size=3) * scale_m
    pts = (rng.normal(size=(n_points, 3)) * s) @ R.T
    verts = pts[ConvexHull(pts).vertices]
    return verts - verts.mean(axis=0)


def _hull_planes(verts: np.ndarray) -> np.ndarray:
    """Half-space planes ``(F, 4)`` (n, d) with ``n . p + d <= 0`` inside, of a convex hull."""
    return ConvexHull(verts).equations


def rasterize_convex(height: np.ndarray, origin_xy: Tuple[float, float], res_m: float,
                     verts_world: np.ndarray) -> None:
    """Raise ``height`` ``(nx, ny)`` to the top surface of a convex body, in place.

    Args:
        height: grid [m], ``[i, j]`` at cell centre ``origin + (i + 0.5, j + 0.5) * res``.
        origin_xy: min corner of the grid [m].
        res_m: cell size [m].
        verts_world: the body's vertices in the grid frame [m].
    """
    lo = np.floor((verts_world[:, :2].min(0) - origin_xy) / res_m - 0.5).astype(int)
    hi = np.ceil((verts_world[:, :2].max(0) - origin_xy) / res_m - 0.5).astype(int) + 1
    lo = np.maximum(lo, 0)
    hi = np.minimum(hi, height.shape)
    if np.any(hi <= lo):
        return
    xs = origin_xy[0] + (np.arange(lo[0], hi[0]) + 0.5) * res_m
    ys = origin_xy[1] + (np.arange(lo[1], hi[1]) + 0.5) * res_m
    X, Y = np.meshgrid(xs, ys, indexing='ij')
    eq = _hull_planes(verts_world)
    n, d = eq[:, :3], eq[:, 3]
    lin = n[:, 0, None, None] * X + n[:, 1, None, None] * Y + d[:, None, None]   # (F, nx, ny)
    nz = n[:, 2]
    up, down, side = nz > 1e-9, nz < -1e-9, np.abs(nz) <= 1e-9
    # inside: nz*z <= -lin for every face -> z <= top (upward faces), z >= bottom (downward)
    top = np.min(-lin[up] / nz[up, None, None], axis=0)
    bottom = np.max(-lin[down] / nz[down, None, None], axis=0) if down.any() else -np.inf
    inside = top >= bottom
    if side.any():
        inside &= np.all(lin[side] <= 1e-12, axis=0)
    block = height[lo[0]:hi[0], lo[1]:hi[1]]
    np.maximum(block, np.where(inside, top, -np.inf), out=block)


def _pose_vertices(verts: np.ndarray, pos, quat) -> np.ndarray:
    return verts @ quat_to_R(np.asarray(quat)).T + np.asarray(pos)


# ---------------------------------------------------------------------------------------------
# Kolter's rock piles
# ---------------------------------------------------------------------------------------------
def _drop_bodies(bodies: List[np.ndarray], size_xy: Tuple[float, float], cfg: KolterConfig,
                 rng: np.random.Generator) -> Tuple[List[np.ndarray], Dict[str, float]]:
    """Drop convex bodies into a walled ``size_xy`` box at the origin.

    Returns:
        (world vertices of every body at rest, ``{'settle_time_s', 'max_speed_mps'}``: the
        simulated time the drop took and the fastest body's speed at the end).
    """
    import pybullet
    from pybullet_utils.bullet_client import BulletClient

    client = BulletClient(pybullet.DIRECT)
    try:
        client.setGravity(0.0, 0.0, -9.81)
        client.setPhysicsEngineParameter(fixedTimeStep=cfg.time_step_s,
                                         numSolverIterations=cfg.solver_iterations,
                                         numSubSteps=0, deterministicOverlappingPairs=1)
        floor = client.createMultiBody(0, client.createCollisionShape(pybullet.GEOM_PLANE))
        client.changeDynamics(floor, -1, lateralFriction=cfg.friction, restitution=0.0)
        lx, ly = size_xy
        wall_h, wall_t = 2.0, 0.05
        for pos, half in (([-wall_t, ly / 2, wall_h], [wall_t, ly / 2 + 2 * wall_t, wall_h]),
                          ([lx + wall_t, ly / 2, wall_h], [wall_t, ly / 2 + 2 * wall_t, wall_h]),
                          ([lx / 2, -wall_t, wall_h], [lx / 2 + 2 * wall_t, wall_t, wall_h]),
                          ([lx / 2, ly + wall_t, wall_h], [lx / 2 + 2 * wall_t, wall_t, wall_h])):
            shape = client.createCollisionShape(pybullet.GEOM_BOX, halfExtents=half)
            wall = client.createMultiBody(0, shape, basePosition=pos)
            client.changeDynamics(wall, -1, lateralFriction=cfg.friction, restitution=0.0)
        # drop lattice: cells one typical body diameter apart, layered upwards so that no two
        # bodies overlap at spawn (overlaps would make them explode apart)
        diams = np.array([2.0 * np.max(np.linalg.norm(v, axis=1)) for v in bodies])
        pitch = float(np.percentile(diams, 75))
        nx_l, ny_l = max(1, int(lx / pitch)), max(1, int(ly / pitch))
        per_layer = nx_l * ny_l
        n_layers = -(-len(bodies) // per_layer)
        layer_diam = [float(diams[L * per_layer:(L + 1) * per_layer].max())
                      for L in range(n_layers)]
        layer_z = np.cumsum([0.5 * layer_diam[0]] + [
            0.5 * (layer_diam[L - 1] + layer_diam[L]) + cfg.drop_layer_spacing_m
            for L in range(1, n_layers)])
        ids = []
        for k, verts in enumerate(bodies):
            layer, cell = divmod(k, per_layer)
            ci, cj = divmod(cell, ny_l)
            x = (ci + 0.5) * lx / nx_l + rng.uniform(-0.25, 0.25) * lx / nx_l
            y = (cj + 0.5) * ly / ny_l + rng.uniform(-0.25, 0.25) * ly / ny_l
            z = layer_z[layer] + 0.01
            q = rng.normal(size=4)
            q /= np.linalg.norm(q)
            shape = client.createCollisionShape(pybullet.GEOM_MESH, vertices=verts.tolist())
            body = client.createMultiBody(1.0, shape, basePosition=[x, y, z],
                                          baseOrientation=q.tolist())
            client.changeDynamics(body, -1, linearDamping=cfg.damping,
                                  angularDamping=cfg.damping, lateralFriction=cfg.friction,
                                  restitution=0.0)
            ids.append(body)
        n_steps = int(np.ceil(cfg.max_settle_time_s / cfg.time_step_s))
        check_every = max(1, int(round(0.1 / cfg.time_step_s)))
        speed, step = float('inf'), 0
        for step in range(1, n_steps + 1):
            client.stepSimulation()
            if step % check_every == 0 or step == n_steps:
                speed = max(np.linalg.norm(client.getBaseVelocity(b)[0]) for b in ids)
                if speed < cfg.rest_speed_mps:
                    break
        info = {'settle_time_s': step * cfg.time_step_s, 'max_speed_mps': float(speed)}
        out = []
        for body, verts in zip(ids, bodies):
            pos, quat = client.getBasePositionAndOrientation(body)
            out.append(_pose_vertices(verts, pos, quat))
        return out, info
    finally:
        client.disconnect()


def _random_kernel(rng: np.random.Generator, size: int) -> np.ndarray:
    k = rng.uniform(0.0, 1.0, size=(size, size))
    return k / k.sum()


def _convolve_same(height: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    """``same``-size convolution with edge replication (no dark border)."""
    k0, k1 = kernel.shape
    padded = np.pad(height, ((k0 // 2, k0 - 1 - k0 // 2), (k1 // 2, k1 - 1 - k1 // 2)),
                    mode='edge')
    return fftconvolve(padded, kernel, mode='valid')


def kolter_heights(size_xy: Tuple[float, float], seed: int, height_range_m: float,
                   cfg: KolterConfig = KolterConfig(), info: Optional[dict] = None
                   ) -> Tuple[np.ndarray, float]:
    """Kolter's rock pile over ``[0, lx] x [0, ly]``, floor at 0, max height = range.

    Args:
        info: if given, receives the drop's ``settle_time_s`` and final ``max_speed_mps``.

    Returns:
        (heights ``(nx, ny)`` float64 [m] at ``cfg.sample_resolution_m``, that resolution).
    """
    lx, ly = (float(v) for v in size_xy)
    if lx <= 0 or ly <= 0:
        raise ValueError(f'terrain area must be positive, got {size_xy} m')
    if not np.isfinite(height_range_m) or height_range_m < 0:
        raise ValueError(f'height range must be >= 0, got {height_range_m} m')
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x6B6F6C]))
    n_bodies = max(1, int(round(cfg.bodies_per_m2 * lx * ly)))
    bodies = [random_convex_body(rng, cfg.points_per_body, cfg.body_scale_m, cfg.min_axis_ratio)
              for _ in range(n_bodies)]
    resting, drop = _drop_bodies(bodies, (lx, ly), cfg, rng)
    if info is not None:
        info.update(drop)
    res = cfg.sample_resolution_m
    shape = (max(1, int(round(lx / res))), max(1, int(round(ly / res))))
    h = np.zeros(shape)
    for verts in resting:
        rasterize_convex(h, (0.0, 0.0), res, verts)
    h = np.maximum(h, 0.0)
    h = _convolve_same(h, _random_kernel(rng, cfg.kernel_size_px))
    h[h < 1e-9] = 0.0   # FFT round-off: keep the bare floor exactly at 0
    peak = h.max()
    h = h * (height_range_m / peak) if peak > 0 else h
    return h, res


# ---------------------------------------------------------------------------------------------
# Shao's stone blocks
# ---------------------------------------------------------------------------------------------
def stone_blocks(size_xy: Tuple[float, float], seed: int, max_height_m: float,
                 cfg: StonesConfig = StonesConfig()) -> List[np.ndarray]:
    """World vertices of non-overlapping stone blocks resting on the floor in ``[0,lx]x[0,ly]``.

    The first block is exactly ``max_height_m`` tall so the class height is met; the others draw
    their edges from ``[size_min_m, size_max_m]`` (heights capped at ``max_height_m``).
    """
    if cfg.size_min_m > cfg.size_max_m:
        raise ValueError(f'stone size_min_m {cfg.size_min_m} > size_max_m {cfg.size_max_m}')
    lx, ly = (float(v) for v in size_xy)
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x73746F]))
    n = max(1, int(round(cfg.stones_per_m2 * lx * ly)))
    placed: List[Tuple[float, float, float]] = []   # x, y, radius
    blocks = []
    for k in range(n):
        ex, ey = rng.uniform(cfg.size_min_m, cfg.size_max_m, size=2)
        ez = max_height_m if k == 0 else min(rng.uniform(cfg.size_min_m, cfg.size_max_m),
                                             max_height_m)
        radius = 0.5 * np.hypot(ex, ey) * (1.0 + cfg.side_jitter)
        for _ in range(200):
            x = rng.uniform(radius, lx - radius) if lx > 2 * radius else lx / 2
            y = rng.uniform(radius, ly - radius) if ly > 2 * radius else ly / 2
            if all(np.hypot(x - px, y - py) >= radius + pr + cfg.min_gap_m
                   for px, py, pr in placed):
                break
        else:
            continue   # area full: fewer blocks than asked
        placed.append((x, y, radius))
        corners = np.array([[sx * ex / 2, sy * ey / 2] for sx in (-1, 1) for sy in (-1, 1)])
        base = corners + rng.uniform(-1, 1, size=(4, 2)) * cfg.side_jitter * np.array([ex, ey])
        topc = corners * rng.uniform(0.75, 1.0, size=(4, 1)) \
            + rng.uniform(-1, 1, size=(4, 2)) * cfg.side_jitter * np.array([ex, ey]) * 0.5
        top_z = ez * (1.0 - cfg.top_jitter * rng.uniform(0.0, 1.0, size=4))
        verts = np.vstack([np.column_stack([base, np.zeros(4)]),
                           np.column_stack([topc, top_z]),
                           [[0.0, 0.0, ez]]])   # the block's peak: exactly ez tall
        yaw = rng.uniform(-np.pi, np.pi)
        c, s = np.cos(yaw), np.sin(yaw)
        R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
        blocks.append(verts @ R.T + np.array([x, y, 0.0]))
    return blocks


def stones_heights(size_xy: Tuple[float, float], seed: int, max_height_m: float,
                   cfg: StonesConfig = StonesConfig()) -> Tuple[np.ndarray, float]:
    """Shao-style floor with stone blocks over ``[0, lx] x [0, ly]``; (heights [m], res [m])."""
    lx, ly = (float(v) for v in size_xy)
    if lx <= 0 or ly <= 0:
        raise ValueError(f'terrain area must be positive, got {size_xy} m')
    res = cfg.sample_resolution_m
    shape = (max(1, int(round(lx / res))), max(1, int(round(ly / res))))
    h = np.zeros(shape)
    for verts in stone_blocks((lx, ly), seed, max_height_m, cfg):
        rasterize_convex(h, (0.0, 0.0), res, verts)
    return np.maximum(h, 0.0), res


# ---------------------------------------------------------------------------------------------
# resampling, courses, tile sets
# ---------------------------------------------------------------------------------------------
def resample(heights: np.ndarray, src_res_m: float, size_xy: Tuple[float, float],
             dst_res_m: float) -> np.ndarray:
    """Resample a ``[0,lx]x[0,ly]`` height array to ``dst_res_m`` cells.

    Down-sampling by an integer factor averages blocks (area-correct); any other ratio uses
    bilinear interpolation at the new cell centres.
    """
    lx, ly = size_xy
    nx, ny = int(round(lx / dst_res_m)), int(round(ly / dst_res_m))
    ratio = dst_res_m / src_res_m
    k = int(round(ratio))
    if abs(ratio - k) < 1e-9 and k >= 1 and heights.shape == (nx * k, ny * k):
        return heights.reshape(nx, k, ny, k).mean(axis=(1, 3))
    ci = (np.arange(nx) + 0.5) * dst_res_m / src_res_m - 0.5
    cj = (np.arange(ny) + 0.5) * dst_res_m / src_res_m - 0.5
    I, J = np.meshgrid(ci, cj, indexing='ij')
    return map_coordinates(heights, [I, J], order=1, mode='nearest')


def _rescale_peak(h: np.ndarray, peak_m: float) -> np.ndarray:
    """Scale heights (floor 0) so the maximum is exactly ``peak_m`` after resampling."""
    top = float(np.max(h))
    return h * (peak_m / top) if top > 0 else h


def _taper(shape: Tuple[int, int], res_m: float, taper_m: float) -> np.ndarray:
    """Smooth-step window: 0 at the border, 1 from ``taper_m`` inwards."""
    if taper_m <= 0:
        return np.ones(shape)

    def ramp(n):
        d = (np.minimum(np.arange(n), np.arange(n)[::-1]) + 0.5) * res_m / taper_m
        t = np.clip(d, 0.0, 1.0)
        return t * t * (3 - 2 * t)

    return np.minimum(ramp(shape[0])[:, None], ramp(shape[1])[None, :])


def make_course(cls_name: str, seed: int, resolution_m: float = 0.005,
                cfg: Optional[CourseConfig] = None,
                kolter: KolterConfig = KolterConfig(),
                stones: StonesConfig = StonesConfig()) -> GridMap:
    """A course of class ``cls_name``: flat approach, rough section, flat exit along +x.

    The grid's origin is ``(0, -width/2)``: the course starts at x = 0 and is centred on y = 0.
    Layer ``elevation`` [m] (floor at 0). Metadata: ``class``, ``seed``, ``resolution_m``,
    ``origin_xy``, ``rough_extent_xy`` ``[x0, x1, y0, y1]`` [m], ``max_height_m``, ``generator``.
    """
    cfg = cfg if cfg is not None else course_config(cls_name)
    if not np.isfinite(resolution_m) or resolution_m <= 0:
        raise ValueError(f'course resolution must be positive, got {resolution_m} m')
    rough_xy = (cfg.rough_length_m, cfg.width_m)
    drop: dict = {}
    if cfg.generator == 'kolter':
        fine, fine_res = kolter_heights(rough_xy, seed, cfg.max_height_m, kolter, drop)
    else:
        fine, fine_res = stones_heights(rough_xy, seed, cfg.max_height_m, stones)
    rough = resample(fine, fine_res, rough_xy, resolution_m)
    rough *= _taper(rough.shape, resolution_m, cfg.edge_taper_m)
    rough = _rescale_peak(rough, cfg.max_height_m)
    length = cfg.approach_m + cfg.rough_length_m + cfg.exit_m
    nx = int(round(length / resolution_m))
    ny = rough.shape[1]
    elev = np.zeros((nx, ny), np.float32)
    i0 = int(round(cfg.approach_m / resolution_m))
    i1 = min(i0 + rough.shape[0], nx)
    elev[i0:i1] = rough[:i1 - i0]
    origin = (0.0, -0.5 * ny * resolution_m)
    meta = {
        'class': cls_name, 'seed': int(seed), 'generator': cfg.generator,
        'resolution_m': float(resolution_m), 'origin_xy': list(origin),
        'rough_extent_xy': [i0 * resolution_m, i1 * resolution_m,
                            origin[1], origin[1] + ny * resolution_m],
        'max_height_m': float(cfg.max_height_m),
        'course_config': dataclasses.asdict(cfg),
    }
    if drop:
        meta['drop'] = drop
    return GridMap(resolution_m, origin, (nx, ny), {ELEVATION: elev}, metadata=meta)


def kolter_tile(seed: int, resolution_m: float = 0.01, height_range_m: float = 0.06,
                size_m: float = 1.0, kolter: KolterConfig = KolterConfig()) -> GridMap:
    """One ``size_m`` square Kolter terrain (origin (0, 0)) as a GridMap with ``elevation``."""
    fine, fine_res = kolter_heights((size_m, size_m), seed, height_range_m, kolter)
    elev = _rescale_peak(resample(fine, fine_res, (size_m, size_m), resolution_m),
                         height_range_m).astype(np.float32)
    meta = {'class': 'kolter-tile', 'seed': int(seed), 'generator': 'kolter',
            'resolution_m': float(resolution_m), 'origin_xy': [0.0, 0.0],
            'rough_extent_xy': [0.0, size_m, 0.0, size_m], 'max_height_m': height_range_m}
    return GridMap(resolution_m, (0.0, 0.0), elev.shape, {ELEVATION: elev}, metadata=meta)


def _tile_seeds(n: int, seed: int, stream: int) -> Iterable[int]:
    ss = np.random.SeedSequence([int(seed), stream])
    return [int(s.generate_state(1)[0]) for s in ss.spawn(int(n))]


def _tiles(n: int, seed: int, stream: int, resolution_m: float, height_range_m: float,
           cache_dir: 'str | Path | None', kolter: KolterConfig) -> List[GridMap]:
    if n < 0:
        raise ValueError(f'number of terrains must be >= 0, got {n}')
    out = []
    for s in _tile_seeds(n, seed, stream):
        path = None
        if cache_dir is not None:
            key = abs(hash(tuple(dataclasses.astuple(kolter)))) % 10**8
            path = Path(cache_dir) / f'kolter_{s}_{resolution_m:g}_{height_range_m:g}_{key}.npz'
            if path.is_file():
                out.append(GridMap.load(path))
                continue
        tile = kolter_tile(s, resolution_m, height_range_m, kolter=kolter)
        if path is not None:
            tile.save(path)
        out.append(tile)
    return out


def library_terrains(n: int, seed: int, resolution_m: float = 0.01, height_range_m: float = 0.06,
                     cache_dir: 'str | Path | None' = None,
                     kolter: KolterConfig = KolterConfig()) -> List[GridMap]:
    """``n`` 1 m x 1 m Kolter terrains for a fill library (disjoint from :func:`test_terrains`).

    ``cache_dir``: optional folder where generated tiles are kept as ``.npz`` and reused.
    """
    return _tiles(n, seed, 1, resolution_m, height_range_m, cache_dir, kolter)


def test_terrains(n: int, seed: int, resolution_m: float = 0.01, height_range_m: float = 0.06,
                  cache_dir: 'str | Path | None' = None,
                  kolter: KolterConfig = KolterConfig()) -> List[GridMap]:
    """``n`` 1 m x 1 m Kolter terrains for evaluation, never equal to a library terrain."""
    return _tiles(n, seed, 2, resolution_m, height_range_m, cache_dir, kolter)


test_terrains.__test__ = False   # not a pytest test despite its name
