"""The simulated world: a course as a textured pybullet heightfield, stereo rendering, an IMU.

* :class:`SimWorld` puts a course (:class:`~terrain_perception.grid.GridMap`, layer
  ``elevation``) into a caller-owned ``BulletClient``: a ``GEOM_HEIGHTFIELD`` collision shape
  whose vertices sit exactly at the grid's cell centres, a flat collision plane at z = 0 beyond
  it, and a separate visual mesh with a seeded procedural rock/soil texture (stereo block
  matching needs texture; pybullet's heightfield visual has no world-scaled UVs).
* :func:`render_stereo` renders a rectified pair with pybullet's TinyRenderer from pinhole
  intrinsics (optical frame: z forward, x right, y down) and returns the metric z-depth of the
  left camera.
* :class:`ImuModel` turns base poses and velocities into IMU readings (specific force, gyro,
  orientation) with seeded noise and bias.

Nothing here reads a clock or uses the global pybullet connection.
"""

from __future__ import annotations

import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import List, Optional, Tuple

import numpy as np

from terrain_perception.camera import PinholeCamera, StereoCamera
from terrain_perception.config import param
from terrain_perception.grid import ELEVATION, GridMap
from terrain_perception.transforms import R_to_quat, invert, make_T, quat_to_R

GRAVITY_MPS2 = 9.81

# optical (x right, y down, z forward) -> OpenGL camera (x right, y up, z backward)
_T_GL_OPTICAL = np.diag([1.0, -1.0, -1.0, 1.0])


# ---------------------------------------------------------------------------------------------
# texture
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class WorldConfig:
    """Look and extent of the simulated ground."""

    texture_size_px: int = param(1024, 'edge of the square, tiling ground texture [px]',
                                 64, 8192)
    texture_tile_m: float = param(2.0, 'ground length one texture tile covers [m]; tile / '
                                  'size is the texel size (2 mm: about a pixel footprint of '
                                  'both robots\' cameras at mid range; TinyRenderer has no '
                                  'mipmaps, so finer texels alias differently in the two '
                                  'views)', 0.01, 100.0)
    ground_margin_m: float = param(4.0, 'textured flat ground drawn around the course [m]',
                                   0.0, 100.0)
    ground_cell_m: float = param(0.1, 'triangle size of flat ground [m]: flat, so coarse (the '
                                 'texture carries the detail), but TinyRenderer scans each '
                                 'triangle\'s screen box, so not huge', 0.005, 10.0)
    friction: float = param(1.0, 'lateral friction of the terrain and the floor', 0.0, 10.0)


def rock_texture(seed: int, size_px: int = 1024) -> np.ndarray:
    """A seeded, seamlessly tiling rock/soil texture ``(size, size, 3)`` uint8 RGB.

    Multi-scale noise: a 1/f fractal (patches of soil and rock at every scale) blended between
    a soil and a rock palette, plus fine grain so block matching finds texture at pixel scale.
    Built in the Fourier domain, so it is periodic and tiles without seams.
    """
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x746578]))
    f = np.fft.fftfreq(size_px).astype(np.float32)
    fr = np.sqrt(f[:, None] ** 2 + f[None, :] ** 2)
    fr[0, 0] = 1.0
    log_fr = np.log(fr)

    def fractal(exponent: float, lo_cut: float = 0.0) -> np.ndarray:
        noise = rng.standard_normal(fr.shape, dtype=np.float32) \
            + 1j * rng.standard_normal(fr.shape, dtype=np.float32)
        spec = noise * np.exp(-exponent * log_fr)      # amplitude ~ 1 / f^exponent
        spec[fr < lo_cut] = 0.0
        spec[0, 0] = 0.0
        img = np.fft.ifft2(spec).real
        return (img - img.mean()) / (img.std() + 1e-12)

    mix = fractal(1.6)                      # large patches: soil vs rock
    detail = fractal(0.9)                   # mid-scale mottling
    grain = fractal(0.2, lo_cut=0.05)       # fine grain, at a few texels
    w = 1.0 / (1.0 + np.exp(-2.0 * mix))    # 0 = soil, 1 = rock
    soil = np.array([120.0, 95.0, 70.0])
    rock = np.array([150.0, 148.0, 140.0])
    base = (1 - w)[..., None] * soil + w[..., None] * rock
    shade = 1.0 + 0.22 * detail + 0.16 * grain
    img = base * shade[..., None]
    return np.clip(img, 0, 255).astype(np.uint8)


# ---------------------------------------------------------------------------------------------
# the world
# ---------------------------------------------------------------------------------------------
def _grid_normals(xs: np.ndarray, ys: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Unit vertex normals ``(nx, ny, 3)`` of a height grid on (possibly uneven) axes."""
    gx = np.gradient(z, xs, axis=0) if len(xs) > 1 else np.zeros_like(z)
    gy = np.gradient(z, ys, axis=1) if len(ys) > 1 else np.zeros_like(z)
    n = np.stack([-gx, -gy, np.ones_like(z)], axis=-1)
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def _grid_mesh(xs: np.ndarray, ys: np.ndarray, z: np.ndarray) -> Tuple[np.ndarray, np.ndarray,
                                                                         np.ndarray]:
    """Vertices ``(nx*ny, 3)``, triangle indices and vertex normals of a height grid."""
    nx, ny = z.shape
    X, Y = np.meshgrid(xs, ys, indexing='ij')
    verts = np.stack([X, Y, z], axis=-1).reshape(-1, 3)
    normals = _grid_normals(xs, ys, z).reshape(-1, 3)
    I, J = np.meshgrid(np.arange(nx - 1), np.arange(ny - 1), indexing='ij')
    a = (I * ny + J).ravel()
    b, c, d = a + ny, a + 1, a + ny + 1
    # counter-clockwise seen from above (+z): a -> b -> d, a -> d -> c
    idx = np.stack([a, b, d, a, d, c], axis=1).ravel()
    return verts, idx, normals


def _rect_mesh(x0: float, x1: float, y0: float, y1: float, cell: float, z: float = 0.0
               ) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A flat rectangle at height ``z`` tessellated into cells of at most ``cell`` [m]."""
    nx = max(1, int(np.ceil((x1 - x0) / cell)))
    ny = max(1, int(np.ceil((y1 - y0) / cell)))
    return _grid_mesh(np.linspace(x0, x1, nx + 1), np.linspace(y0, y1, ny + 1),
                      np.full((nx + 1, ny + 1), float(z)))


def terrain_mesh_parts(xs: np.ndarray, ys: np.ndarray, z: np.ndarray, block: int,
                       margin_m: float, ground_cell_m: float, floor_z: float = 0.0
                       ) -> List[Tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Visual mesh pieces ``(vertices, indices, normals)`` of a height grid plus flat ground.

    The grid (vertices at ``xs`` x ``ys``) is cut into blocks of ``block`` x ``block`` quads;
    a block whose vertices are all at 0 becomes part of a flat rectangle (runs of flat blocks
    merged along x, tessellated at ``ground_cell_m``), any other block keeps every vertex.
    Flat ground of ``margin_m`` at ``floor_z`` surrounds the grid in four strips. Flat and
    fine pieces meet only where heights are 0, so the surface has no cracks (only T-junctions
    on flat lines).
    """
    nx, ny = z.shape
    normals_all = _grid_normals(xs, ys, z)
    parts = []
    bi = list(range(0, nx - 1, block))
    bj = list(range(0, ny - 1, block))
    for j0 in bj:
        j1 = min(j0 + block, ny - 1)
        run_start = None
        for k, i0 in enumerate(bi + [None]):
            flat = False
            if i0 is not None:
                i1 = min(i0 + block, nx - 1)
                sub = z[i0:i1 + 1, j0:j1 + 1]
                flat = not np.any(sub)
            if flat and run_start is None:
                run_start = i0
            if (not flat or i0 is None) and run_start is not None:
                end = i0 if i0 is not None else nx - 1
                parts.append(_rect_mesh(xs[run_start], xs[end], ys[j0], ys[j1], ground_cell_m))
                run_start = None
            if i0 is not None and not flat:
                v, idx, _ = _grid_mesh(xs[i0:i1 + 1], ys[j0:j1 + 1], sub)
                parts.append((v, idx, normals_all[i0:i1 + 1, j0:j1 + 1].reshape(-1, 3)))
    if margin_m > 0:
        X0, X1, Y0, Y1 = xs[0], xs[-1], ys[0], ys[-1]
        m, c = margin_m, ground_cell_m
        parts += [_rect_mesh(X0 - m, X0, Y0 - m, Y1 + m, c, floor_z),
                  _rect_mesh(X1, X1 + m, Y0 - m, Y1 + m, c, floor_z),
                  _rect_mesh(X0, X1, Y0 - m, Y0, c, floor_z),
                  _rect_mesh(X0, X1, Y1, Y1 + m, c, floor_z)]
    return parts


def _merge_parts(parts, max_vertices: int):
    """Concatenate mesh pieces into bodies of at most ``max_vertices`` vertices each."""
    out, cur, n = [], [], 0
    for part in parts:
        if cur and n + len(part[0]) > max_vertices:
            out.append(cur)
            cur, n = [], 0
        cur.append(part)
        n += len(part[0])
    if cur:
        out.append(cur)
    merged = []
    for group in out:
        offs = np.cumsum([0] + [len(p[0]) for p in group[:-1]])
        merged.append((np.concatenate([p[0] for p in group]),
                       np.concatenate([p[1] + o for p, o in zip(group, offs)]),
                       np.concatenate([p[2] for p in group])))
    return merged


_MAX_BODY_VERTICES = 40000   # pybullet caps a mesh's vertices and indices per shape
_BLOCK_QUADS = 16            # fine / flat decision granularity of the visual mesh


class SimWorld:
    """A course loaded into a pybullet world as a heightfield with a textured visual mesh.

    The heightfield's vertex ``[i, j]`` is at the centre of grid cell ``[i, j]`` with height
    ``elevation[i, j]``; between centres pybullet interpolates linearly (two triangles per
    cell). NaN heights are set to 0. Beyond the course: a collision plane and a flat textured
    visual ground of ``ground_margin_m`` at z = 0 (or at the course's lowest height if that is
    below 0, so the floor never fills a pit).

    Attributes:
        client: the caller's ``BulletClient``.
        course: the loaded grid (a copy).
        terrain_id, floor_id: pybullet body ids.
    """

    def __init__(self, client, course: GridMap, cfg: WorldConfig = WorldConfig(),
                 texture_seed: Optional[int] = None) -> None:
        if ELEVATION not in course:
            raise ValueError(f'course grid has no {ELEVATION!r} layer '
                             f'(layers: {sorted(course.layers)})')
        if min(course.shape) < 2:
            raise ValueError(f'course grid must be at least 2x2 cells, got {course.shape}')
        self.client = client
        self.cfg = cfg
        self.course = course.copy()
        z = np.nan_to_num(self.course[ELEVATION].astype(np.float64), nan=0.0)
        self.course[ELEVATION] = z
        self.texture_seed = int(course.metadata.get('seed', 0)) if texture_seed is None \
            else int(texture_seed)
        # the floor never rises into a pit of the course (courses are >= 0 with the floor at 0)
        self.floor_z = min(0.0, float(z.min()))
        self.floor_id = self._add_floor()
        self.terrain_id = self._add_heightfield(z)
        self._add_visual(z)

    # -- construction -----------------------------------------------------------------------
    def _no_visual(self) -> int:
        """A visual shape nobody sees: a tiny sphere far below the floor."""
        if getattr(self, '_hidden_visual', None) is None:
            self._hidden_visual = self.client.createVisualShape(
                self.client.GEOM_SPHERE, radius=1e-4, visualFramePosition=[0.0, 0.0, -100.0])
        return self._hidden_visual

    def _add_floor(self) -> int:
        c = self.client
        shape = c.createCollisionShape(c.GEOM_PLANE)
        body = c.createMultiBody(0, shape, self._no_visual(), basePosition=[0, 0, self.floor_z])
        c.changeDynamics(body, -1, lateralFriction=self.cfg.friction, restitution=0.0)
        return body

    def _add_heightfield(self, z: np.ndarray) -> int:
        c = self.client
        res = self.course.resolution_m
        # one replicated vertex ring so rays on the outermost cell centres still hit
        zp = np.pad(z, 1, mode='edge')
        nx, ny = zp.shape
        # Bullet's heightfield: rows along x (fast index), columns along y; the shape is
        # centred on its AABB, i.e. x and y on the vertex span, z on (min + max) / 2.
        data = zp.T.ravel()   # index i + j * nx
        shape = c.createCollisionShape(
            c.GEOM_HEIGHTFIELD, meshScale=[res, res, 1.0], heightfieldData=data.tolist(),
            numHeightfieldRows=nx, numHeightfieldColumns=ny)
        xs, ys = self.course.cell_centers()
        centre = [0.5 * (xs[0] + xs[-1]), 0.5 * (ys[0] + ys[-1]),
                  0.5 * (float(zp.min()) + float(zp.max()))]
        # the collision shape must not be drawn (pybullet draws bodies without a visual shape
        # from their collision shape): the textured mesh is the terrain's look
        body = c.createMultiBody(0, shape, self._no_visual(), basePosition=centre)
        c.changeDynamics(body, -1, lateralFriction=self.cfg.friction, restitution=0.0)
        return body

    def _add_visual(self, z: np.ndarray) -> None:
        c = self.client
        cfg = self.cfg
        res = self.course.resolution_m
        xs, ys = self.course.cell_centers()
        texture = rock_texture(self.texture_seed, cfg.texture_size_px)
        with tempfile.TemporaryDirectory() as tmp:
            import cv2
            path = Path(tmp) / 'ground.png'
            cv2.imwrite(str(path), texture[:, :, ::-1])
            tex_id = c.loadTexture(str(path))
        parts = terrain_mesh_parts(xs, ys, z, _BLOCK_QUADS, cfg.ground_margin_m,
                                   cfg.ground_cell_m, self.floor_z)
        self.visual_ids = []
        for verts, idx, normals in _merge_parts(parts, _MAX_BODY_VERTICES):
            uvs = verts[:, :2] / cfg.texture_tile_m
            visual = c.createVisualShape(c.GEOM_MESH, vertices=verts.tolist(),
                                         indices=idx.astype(int).tolist(), uvs=uvs.tolist(),
                                         normals=normals.tolist())
            body = c.createMultiBody(0, -1, visual)
            c.changeVisualShape(body, -1, textureUniqueId=tex_id, rgbaColor=[1, 1, 1, 1],
                                specularColor=[0.05, 0.05, 0.05])
            self.visual_ids.append(body)

    # -- queries ----------------------------------------------------------------------------
    def height_at(self, xy: np.ndarray) -> np.ndarray:
        """Ground truth terrain height [m] at world points ``(..., 2)``, bilinear between cell
        centres like the heightfield's triangles on axis-aligned samples; 0 off the course."""
        xy = np.asarray(xy, dtype=np.float64)
        g = self.course
        f = (xy.reshape(-1, 2) - np.asarray(g.origin_xy)) / g.resolution_m - 0.5
        from scipy.ndimage import map_coordinates
        out = map_coordinates(g[ELEVATION].astype(np.float64), [f[:, 0], f[:, 1]], order=1,
                              mode='constant', cval=0.0)
        return out.reshape(xy.shape[:-1])

    def ray_heights(self, xy: np.ndarray, z_top: float = 10.0, z_bottom: float = -10.0
                    ) -> np.ndarray:
        """Heights [m] found by pybullet ray casts straight down at world points ``(N, 2)``;
        NaN where nothing is hit."""
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        out = np.full(len(xy), np.nan)
        batch = 16000   # pybullet caps a batch at 16384 rays
        for k in range(0, len(xy), batch):
            sl = xy[k:k + batch]
            src = np.column_stack([sl, np.full(len(sl), z_top)])
            dst = np.column_stack([sl, np.full(len(sl), z_bottom)])
            for n, hit in enumerate(self.client.rayTestBatch(src.tolist(), dst.tolist())):
                if hit[0] >= 0:
                    out[k + n] = hit[3][2]
        return out


# ---------------------------------------------------------------------------------------------
# rendering
# ---------------------------------------------------------------------------------------------
def view_matrix(T_world_cam: np.ndarray) -> list:
    """pybullet (OpenGL, column-major) view matrix of an optical-frame camera pose."""
    V = _T_GL_OPTICAL @ invert(np.asarray(T_world_cam, dtype=np.float64))
    return V.T.ravel().tolist()


def projection_matrix(cam: PinholeCamera, near: float, far: float) -> list:
    """OpenGL projection (column-major) reproducing pinhole intrinsics exactly.

    Pixel (u, v) of the returned image sees the ray ``((u - cx) / fx, (v - cy) / fy, 1)``
    (pixel centres at integer coordinates, row 0 at the top).
    """
    if not (0 < near < far):
        raise ValueError(f'need 0 < near < far, got near={near} far={far}')
    W, H = cam.width, cam.height
    P = np.zeros((4, 4))
    P[0, 0] = 2.0 * cam.fx / W
    # Pixel-centre offsets of TinyRenderer (x: u, y: v + 1 rather than the textbook + 0.5),
    # measured with tilted and rolled cameras over a flat floor against the analytic depth
    # (residual 5e-7 relative; test_sim_world checks it).
    P[0, 2] = 1.0 - 2.0 * cam.cx / W
    P[1, 1] = 2.0 * cam.fy / H
    P[1, 2] = 2.0 * (cam.cy + 1.0) / H - 1.0
    P[2, 2] = -(far + near) / (far - near)
    P[2, 3] = -2.0 * far * near / (far - near)
    P[3, 2] = -1.0
    return P.T.ravel().tolist()


def linearize_depth(zbuf: np.ndarray, near: float, far: float) -> np.ndarray:
    """Metric z-depth [m] from an OpenGL depth buffer in [0, 1]; NaN at the far plane (sky)."""
    zbuf = np.asarray(zbuf, dtype=np.float64)
    depth = far * near / (far - (far - near) * zbuf)
    return np.where(zbuf < 1.0 - 1e-7, depth, np.nan).astype(np.float32)


@dataclass(frozen=True)
class LightConfig:
    """TinyRenderer lighting (sun direction points from the scene towards the light)."""

    direction: Tuple[float, float, float] = (0.4, 0.25, 1.0)
    ambient: float = 0.45
    diffuse: float = 0.6
    specular: float = 0.05
    shadow: bool = True


def render_camera(client, T_world_cam: np.ndarray, cam: PinholeCamera, near: float,
                  far: float, light: LightConfig = LightConfig()) -> Tuple[np.ndarray,
                                                                           np.ndarray]:
    """Render one pinhole camera: ``(rgb (H, W, 3) uint8, z-depth (H, W) float32 [m])``.

    ``T_world_cam``: 4x4 pose of the optical frame (z forward, x right, y down) in the world.
    Depth is NaN where nothing is within ``far``.
    """
    _, _, rgba, zbuf, _ = client.getCameraImage(
        cam.width, cam.height, view_matrix(T_world_cam), projection_matrix(cam, near, far),
        lightDirection=list(light.direction), lightAmbientCoeff=light.ambient,
        lightDiffuseCoeff=light.diffuse, lightSpecularCoeff=light.specular,
        shadow=int(light.shadow), renderer=client.ER_TINY_RENDERER,
        flags=client.ER_NO_SEGMENTATION_MASK)
    rgb = np.asarray(rgba, dtype=np.uint8).reshape(cam.height, cam.width, 4)[:, :, :3]
    depth = linearize_depth(np.asarray(zbuf).reshape(cam.height, cam.width), near, far)
    return np.ascontiguousarray(rgb), depth


def right_camera_pose(T_world_left: np.ndarray, stereo: StereoCamera) -> np.ndarray:
    """Pose of the rectified right camera: +baseline along the left camera's x axis."""
    return np.asarray(T_world_left) @ make_T(t=[stereo.baseline_m, 0.0, 0.0])


def render_stereo(client, T_world_cam: np.ndarray, stereo: StereoCamera, near: float = 0.05,
                  far: float = 10.0, light: LightConfig = LightConfig()
                  ) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Render a rectified stereo pair.

    Args:
        client: a ``BulletClient``.
        T_world_cam: 4x4 pose of the left camera's optical frame in the world.
        stereo: intrinsics (shared by both cameras) and baseline [m]; the right camera sits
            at +baseline along the left camera's x axis, same orientation.
        near, far: clipping distances [m].

    Returns:
        ``(left_rgb (H, W, 3) uint8, right_rgb (H, W, 3) uint8, depth (H, W) float32)``, the
        depth being the left camera's metric z-depth [m] (NaN where nothing is hit).
    """
    left, depth = render_camera(client, T_world_cam, stereo.left, near, far, light)
    right, _ = render_camera(client, right_camera_pose(T_world_cam, stereo), stereo.left,
                             near, far, light)
    return left, right, depth


def ground_truth_disparity(stereo: StereoCamera, depth: np.ndarray) -> np.ndarray:
    """Left-image disparity d = fx * B / Z [px] from the rendered z-depth; NaN where invalid."""
    return stereo.depth_to_disparity(depth)


# ---------------------------------------------------------------------------------------------
# IMU
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class ImuConfig:
    """Noise and bias of the simulated IMU (per axis, IMU frame)."""

    gyro_noise_std_rad_s: float = param(0.002, 'white noise of each gyro sample [rad/s]',
                                        0.0, 10.0)
    gyro_bias_std_rad_s: float = param(0.001, 'std-dev of the constant gyro bias drawn at '
                                       'start [rad/s]', 0.0, 10.0)
    accel_noise_std_mps2: float = param(0.02, 'white noise of each accelerometer sample '
                                        '[m/s^2]', 0.0, 100.0)
    accel_bias_std_mps2: float = param(0.01, 'std-dev of the constant accelerometer bias '
                                       'drawn at start [m/s^2]', 0.0, 100.0)
    orientation_noise_std_rad: float = param(0.001, 'white noise of the reported orientation, '
                                             'per axis [rad]', 0.0, 1.0)
    yaw_drift: bool = param(True, 'the reported yaw integrates the gyro bias\'s vertical part, '
                            'as an attitude filter without a magnetometer does (gravity holds '
                            'roll and pitch, nothing holds yaw): about 3 deg/min at the default '
                            'bias')


@dataclass(frozen=True)
class ImuSample:
    """One IMU reading (IMU frame; orientation of the IMU frame in the world, z up).

    Attributes:
        stamp_s: time [s].
        orientation_xyzw: quaternion (x, y, z, w) of ``R_world_imu``.
        angular_velocity: (3,) [rad/s].
        linear_acceleration: (3,) specific force [m/s^2] (reads +9.81 along the up axis at
            rest, like a real accelerometer).
        covariances: (orientation, angular velocity, linear acceleration) diagonals.
    """

    stamp_s: float
    orientation_xyzw: np.ndarray
    angular_velocity: np.ndarray
    linear_acceleration: np.ndarray
    covariances: Tuple[np.ndarray, np.ndarray, np.ndarray]


class ImuModel:
    """Simulated IMU rigidly mounted on the base at ``T_base_imu``.

    Acceleration is the finite difference of the IMU point's world velocity between
    successive :meth:`update` calls (the first call assumes no acceleration); the biases are
    drawn once from the seed. The reported orientation is the true one with white noise and,
    with ``yaw_drift``, a yaw error that grows by the gyro bias's vertical part (world frame)
    integrated over time: consecutive readings agree to the noise, the absolute yaw wanders.
    """

    def __init__(self, cfg: ImuConfig = ImuConfig(), seed: int = 0,
                 T_base_imu: Optional[np.ndarray] = None) -> None:
        self.cfg = cfg
        self.T_base_imu = np.eye(4) if T_base_imu is None else np.asarray(T_base_imu, float)
        self._rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x696D75]))
        self.gyro_bias = self._rng.normal(0.0, cfg.gyro_bias_std_rad_s, 3)
        self.accel_bias = self._rng.normal(0.0, cfg.accel_bias_std_mps2, 3)
        self._prev: Optional[Tuple[float, np.ndarray]] = None
        self._last_stamp: Optional[float] = None
        self.yaw_error_rad = 0.0     # the reported yaw minus the true one (without the noise)

    def reset(self) -> None:
        """Forget the velocity history (e.g. after teleporting the robot)."""
        self._prev = None

    def update(self, stamp_s: float, T_world_base: np.ndarray, v_world: np.ndarray,
               w_world: np.ndarray) -> ImuSample:
        """One reading from the base pose and its world-frame twist.

        Args:
            stamp_s: time [s]; must increase between calls.
            T_world_base: 4x4 base pose.
            v_world: base-origin linear velocity [m/s], world frame.
            w_world: angular velocity [rad/s], world frame.
        """
        T_world_base = np.asarray(T_world_base, dtype=np.float64)
        v_world = np.asarray(v_world, dtype=np.float64).reshape(3)
        w_world = np.asarray(w_world, dtype=np.float64).reshape(3)
        if not (np.all(np.isfinite(T_world_base)) and np.all(np.isfinite(v_world))
                and np.all(np.isfinite(w_world))):
            raise ValueError('IMU input pose or velocity is not finite')
        T_world_imu = T_world_base @ self.T_base_imu
        R = T_world_imu[:3, :3]
        lever = T_world_imu[:3, 3] - T_world_base[:3, 3]
        v_imu = v_world + np.cross(w_world, lever)
        acc = np.zeros(3)
        if self._prev is not None:
            t_prev, v_prev = self._prev
            dt = float(stamp_s) - t_prev
            if dt <= 0:
                raise ValueError(f'IMU stamps must increase: {stamp_s} after {t_prev}')
            acc = (v_imu - v_prev) / dt
        self._prev = (float(stamp_s), v_imu)
        cfg, rng = self.cfg, self._rng
        if cfg.yaw_drift and self._last_stamp is not None:
            self.yaw_error_rad += float((R @ self.gyro_bias)[2]) * (float(stamp_s)
                                                                     - self._last_stamp)
        self._last_stamp = float(stamp_s)
        specific_force = R.T @ (acc + np.array([0.0, 0.0, GRAVITY_MPS2]))
        accel = specific_force + self.accel_bias + rng.normal(0, cfg.accel_noise_std_mps2, 3)
        gyro = R.T @ w_world + self.gyro_bias + rng.normal(0, cfg.gyro_noise_std_rad_s, 3)
        dtheta = rng.normal(0, cfg.orientation_noise_std_rad, 3)
        quat = R_to_quat(_small_rotation(np.array([0.0, 0.0, self.yaw_error_rad]))
                         @ R @ _small_rotation(dtheta))
        cov = (np.full(3, cfg.orientation_noise_std_rad ** 2),
               np.full(3, cfg.gyro_noise_std_rad_s ** 2 + cfg.gyro_bias_std_rad_s ** 2),
               np.full(3, cfg.accel_noise_std_mps2 ** 2 + cfg.accel_bias_std_mps2 ** 2))
        return ImuSample(float(stamp_s), quat, gyro, accel, cov)


def _small_rotation(rotvec: np.ndarray) -> np.ndarray:
    angle = float(np.linalg.norm(rotvec))
    if angle < 1e-12:
        return np.eye(3)
    axis = rotvec / angle
    half = 0.5 * angle
    return quat_to_R(np.concatenate([axis * np.sin(half), [np.cos(half)]]))
