"""Body path: where the body can pass over the terrain, before the footsteps are placed.

Kolter et al.'s LittleDog controller (paper 000 sec. IV, after [4]) plans a path for the body
over the terrain first and the footsteps along it. Here that path serves one purpose the
footstep search cannot see from its few steps of horizon: the **belly**. A LittleDog-sized robot
standing 14.5 cm tall carries the underside of its body 11.5 cm above its feet; on the 12 cm
rock fields (``rocks-12cm``) a body walking straight ahead lands its belly on a 10-12 cm rock
while all four feet stand between the rocks (the ground-truth walks of session 27: 5 of 11
traced walks ended so). Every such course still has straight lines where the body clears
every rock by 2.5 cm or more (``terrain-bench sim --rocks-course rocks-12cm``); they are
usually beside the centre line.

The search is Dijkstra over body positions on a coarse lattice (``resolution_m``), the body
oriented along the walking direction. A position is **blocked** where the body's underside at
its standing height over the ground under its nominal feet (per foot the lowest map cell of
five around it: a foot may end up between two rocks) would come within ``clearance_m`` of the
highest map cell under the body box; where the body or a foot would leave the map; and outside
an optional corridor around the route. Elsewhere a metre of path costs ``1 + weight *
shortfall``, ``shortfall`` in [0, 1] being how far the headroom under the belly falls short
of ``preferred_headroom_m`` (so the path keeps away from tall rocks where it can), plus
``unknown_cost`` where the map does not know the ground. The goal may lie beyond the map or
on a blocked position: the path ends at the reachable position minimising path cost plus the
straight distance to the goal charged at the highest cost per metre, then goes straight on.
The lattice path's first metre is straightened (string pulling) where that crosses nothing
blocked or dearer.

Everything is in the map frame; heights [m], z up. Pure numpy/scipy.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Optional, Tuple

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra

from terrain_perception.compiled import load_compiled
from terrain_perception.features import max_filter
from terrain_perception.grid import ELEVATION, GridMap
from terrain_perception.robot_model import RobotModel

_LOG = logging.getLogger(__name__)


def _load_kernel():
    """The compiled headroom gathers (terrain_perception._body_path_kernel), or None for the
    numpy code (``TERRAIN_BODY_PATH_NUMBA=0``, or numba missing: logged once)."""
    return load_compiled('_body_path_kernel', 'TERRAIN_BODY_PATH_NUMBA', 'body path', _LOG)


_kernel = _load_kernel()


def use_compiled_kernel(enabled: Optional[bool] = True) -> bool:
    """Select the compiled headroom kernel (``True``), the numpy code (``False``) or the
    default (``None``) for the following :func:`plan_body_path` calls, process-wide; returns
    whether the compiled kernel is now used."""
    global _kernel
    if enabled is None:
        _kernel = _load_kernel()
    elif enabled:
        from terrain_perception import _body_path_kernel
        _kernel = _body_path_kernel
    else:
        _kernel = None
    return _kernel is not None


@dataclass(frozen=True)
class BodyPathSettings:
    """Parameters of :func:`plan_body_path` (the planner's ``body_path_*`` parameters)."""

    resolution_m: float = 0.025
    clearance_m: float = 0.015
    preferred_headroom_m: float = 0.04
    weight: float = 3.0
    unknown_cost: float = 0.5
    pull_m: float = 1.0


@dataclass
class BodyPath:
    """A body path. ``points`` ``(n, 2)`` from the start towards the goal [m, map];
    ``reaches_goal``: its last point is within a lattice step of the goal; ``blocked``: share of
    lattice positions the body cannot stand on; ``text``: what was found."""

    points: np.ndarray
    reaches_goal: bool
    blocked: float
    text: str

    def lookahead(self, distance_m: float, goal_xy: np.ndarray) -> np.ndarray:
        """The point ``distance_m`` along the path (arc length), or the goal past its end."""
        p = self.points
        if len(p) < 2:
            return np.asarray(goal_xy, dtype=np.float64)
        seg = np.linalg.norm(np.diff(p, axis=0), axis=1)
        s = np.concatenate([[0.0], np.cumsum(seg)])
        if distance_m >= s[-1]:
            # Past the path's end: straight on to the goal (or along the last segment).
            rest = np.asarray(goal_xy, dtype=np.float64) - p[-1]
            if np.hypot(*rest) > 1e-6:
                return p[-1] + rest * min(1.0, (distance_m - s[-1]) / np.hypot(*rest))
            return p[-1]
        k = int(np.searchsorted(s, distance_m, side='right')) - 1
        t = (distance_m - s[k]) / max(seg[k], 1e-12)
        return p[k] + t * (p[k + 1] - p[k])


def belly_samples(robot: RobotModel, spacing_m: float = 0.02) -> Tuple[np.ndarray, float]:
    """The body box's underside sampled every <= ``spacing_m``: ``(points (k, 3) in base_link,
    actual spacing [m])``. Max-filtering a height map over the spacing makes the samples'
    maximum the maximum under the whole box."""
    length, width, thick = (float(v) for v in robot.body_size_m)
    nu = max(int(np.ceil(length / spacing_m)) + 1, 2)
    nv = max(int(np.ceil(width / spacing_m)) + 1, 2)
    U, V = np.meshgrid(np.linspace(-0.5 * length, 0.5 * length, nu),
                       np.linspace(-0.5 * width, 0.5 * width, nv), indexing='ij')
    pts = np.c_[U.ravel(), V.ravel(), np.full(U.size, -0.5 * thick)]
    return pts, max(length / (nu - 1), width / (nv - 1))


def top_field(grid: GridMap, spacing_m: float) -> np.ndarray:
    """The grid's elevation max-filtered over ``spacing_m`` (unknown cells: -inf)."""
    h = np.where(np.isfinite(grid[ELEVATION]), grid[ELEVATION], -np.inf).astype(np.float64)
    w = int(np.ceil(spacing_m / grid.resolution_m)) + 1
    return max_filter(h, w, 'nearest')


def _lookup(grid: GridMap, field: np.ndarray, xy: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    ij = grid.world_to_index(xy)
    inside = grid.inside(ij)
    ij = np.where(inside[..., None], ij, 0)
    return field[ij[..., 0], ij[..., 1]], inside


def _belly_and_ground(grid: GridMap, top: np.ndarray, nodes: np.ndarray, bxy: np.ndarray,
                      fxy: np.ndarray, ring: int) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Numpy reference of ``_body_path_kernel.belly_and_ground``: per body position the
    highest ``top`` under the belly samples ``bxy``, the mean over the feet of each foot's
    lowest cell of its ``ring`` samples in ``fxy`` (NaN if any is unknown), and whether every
    sample is on the map."""
    tops, t_in = _lookup(grid, top, nodes[:, None, :] + bxy[None])
    fz, f_in = _lookup(grid, grid[ELEVATION], nodes[:, None, :] + fxy[None])
    # Per foot the lowest of its samples (the foot may end up in the gap between two rocks),
    # then the mean over the feet (the body follows the feet's plane); NaN if any is unknown.
    fz = fz.astype(np.float64).reshape(len(nodes), -1, ring)
    with np.errstate(invalid='ignore'):
        ground = np.min(fz, axis=2).mean(axis=1)
    return tops.max(axis=1), ground, t_in.all(axis=1) & f_in.all(axis=1)


def plan_body_path(grid: GridMap, robot: RobotModel, start_xy: np.ndarray,
                   goal_xy: np.ndarray, heading: float,
                   settings: BodyPathSettings = BodyPathSettings(),
                   top: Optional[np.ndarray] = None,
                   corridor: Optional[Tuple[np.ndarray, np.ndarray, float]] = None) -> BodyPath:
    """Cheapest body path from ``start_xy`` towards ``goal_xy`` over ``grid``, the body
    oriented along ``heading`` [rad] (see the module doc). ``top``: :func:`top_field` of the
    grid at the belly samples' spacing, if already computed. ``corridor``: ``(a, b, half
    width)``, the body stays within that distance of the segment a-b (the route the robot was
    sent along: going round a rock field is not crossing it). Raises ValueError on non-finite
    input."""
    start = np.asarray(start_xy, dtype=np.float64).reshape(2)
    goal = np.asarray(goal_xy, dtype=np.float64).reshape(2)
    if not (np.all(np.isfinite(start)) and np.all(np.isfinite(goal)) and np.isfinite(heading)):
        raise ValueError(f'body path needs finite start, goal and heading, got {start_xy}, '
                         f'{goal_xy}, {heading}')
    s = settings
    r = max(float(s.resolution_m), grid.resolution_m)
    lo = np.asarray(grid.origin_xy, dtype=np.float64)
    n = np.maximum(np.floor(np.asarray(grid.length_xy) / r).astype(int), 1)
    xs = lo[0] + (np.arange(n[0]) + 0.5) * r
    ys = lo[1] + (np.arange(n[1]) + 0.5) * r
    X, Y = np.meshgrid(xs, ys, indexing='ij')
    nodes = np.stack([X, Y], axis=-1).reshape(-1, 2)
    c, sn = np.cos(heading), np.sin(heading)
    R = np.array([[c, -sn], [sn, c]])

    # Only positions the body may take need their headroom: with a corridor, the lattice
    # positions within it (and the start); the rest are blocked whatever lies under them.
    k_start = int(np.argmin(np.sum((nodes - start) ** 2, axis=1)))
    outside = np.zeros(len(nodes), dtype=bool)
    if corridor is not None:
        a, b, half = (np.asarray(corridor[0], float), np.asarray(corridor[1], float),
                      float(corridor[2]))
        ab = b - a
        t = np.clip((nodes - a) @ ab / max(float(ab @ ab), 1e-12), 0.0, 1.0)
        outside = np.hypot(*(nodes - a - t[:, None] * ab).T) > half
    live = ~outside
    live[k_start] = True
    live_nodes = nodes[live]

    belly, spacing = belly_samples(robot)
    if top is None:
        top = top_field(grid, spacing)
    bxy = belly[:, :2] @ R.T
    # Ground under the feet: five points around each nominal foot.
    ring = float(robot.foot_radius_m) * np.array(
        [[0, 0], [1, 0], [-1, 0], [0, 1], [0, -1]], dtype=np.float64)
    feet = np.asarray(robot.nominal_feet)[:, None, :2] + ring[None]
    fxy = feet.reshape(-1, 2) @ R.T
    if _kernel is not None:
        top_max = np.empty(len(live_nodes))
        ground = np.empty(len(live_nodes))
        on_map = np.empty(len(live_nodes), dtype=bool)
        _kernel.belly_and_ground(
            np.ascontiguousarray(live_nodes), np.ascontiguousarray(bxy),
            np.ascontiguousarray(fxy), len(ring), float(lo[0]), float(lo[1]),
            float(grid.resolution_m), np.ascontiguousarray(top, dtype=np.float64),
            np.ascontiguousarray(grid[ELEVATION], dtype=np.float64), top_max, ground, on_map)
    else:
        top_max, ground, on_map = _belly_and_ground(grid, top, live_nodes, bxy, fxy, len(ring))
    underside = robot.standing_height_m - 0.5 * float(robot.body_size_m[2])
    headroom = np.full(len(nodes), np.nan)
    headroom[live] = ground + underside - top_max    # NaN where no foot ground is known
    off_map = np.zeros(len(nodes), dtype=bool)
    off_map[live] = ~on_map
    headroom[off_map] = np.nan
    rock = (np.isfinite(headroom) & (headroom < s.clearance_m)) | outside
    blocked = rock | off_map
    short = np.clip((s.preferred_headroom_m - headroom) / max(s.preferred_headroom_m, 1e-9),
                    0.0, 1.0)
    cost = 1.0 + s.weight * np.where(np.isfinite(headroom), short, 0.0) \
        + s.unknown_cost * (~np.isfinite(headroom) & ~off_map)

    blocked[k_start] = False
    idx = np.arange(len(nodes)).reshape(n[0], n[1])
    rows, cols, w = [], [], []
    for di, dj in ((1, 0), (0, 1), (1, 1), (1, -1)):
        a, b = _pairs(idx, di, dj)
        ok = ~blocked[a] & ~blocked[b]
        length = r * np.hypot(di, dj)
        rows += [a[ok], b[ok]]
        cols += [b[ok], a[ok]]
        wk = length * 0.5 * (cost[a[ok]] + cost[b[ok]])
        w += [wk, wk]
    G = coo_matrix((np.concatenate(w), (np.concatenate(rows), np.concatenate(cols))),
                   shape=(len(nodes), len(nodes))).tocsr()
    dist, pred = dijkstra(G, directed=True, indices=k_start, return_predecessors=True)
    # Beyond the reachable part, the rest of the way is charged at the highest cost per metre,
    # so that the path never stops short of the goal to save cost.
    to_goal = dist + (1.0 + s.weight + s.unknown_cost) * np.hypot(*(nodes - goal).T)
    k_end = int(np.argmin(to_goal))
    path = [k_end]
    while path[-1] != k_start and pred[path[-1]] >= 0:
        path.append(int(pred[path[-1]]))
    pts = np.vstack([start, nodes[path[::-1]][1:]]) if len(path) > 1 else start[None]
    reaches = bool(np.hypot(*(nodes[k_end] - goal)) <= r)
    if reaches and len(pts) > 1:
        pts[-1] = goal
    elif not reaches:
        pts = np.vstack([pts, goal])    # the rest of the way: straight on
    # Straightening may cross the map's border band (blocked for the search, which must not
    # put a body or foot off the map) only on the last, straight leg to a goal beyond it.
    pts = _pull_string(pts, lo, r, n, rock.reshape(n[0], n[1]), cost.reshape(n[0], n[1]),
                       s.pull_m)
    frac = float(np.mean(blocked))
    text = (f'body path {len(pts)} points, {"to the goal" if reaches else "towards the goal"}, '
            f'{100 * frac:.0f} % of body positions blocked')
    return BodyPath(pts, reaches, frac, text)


def _pairs(idx: np.ndarray, di: int, dj: int) -> Tuple[np.ndarray, np.ndarray]:
    """Flat indices of lattice neighbours ``(i, j)`` and ``(i + di, j + dj)``."""
    ni, nj = idx.shape
    i0, i1 = max(0, -di), ni - max(0, di)
    j0, j1 = max(0, -dj), nj - max(0, dj)
    a = idx[i0:i1, j0:j1]
    b = idx[i0 + di:i1 + di, j0 + dj:j1 + dj]
    return a.ravel(), b.ravel()


def _pull_string(pts: np.ndarray, lo: np.ndarray, r: float, n: np.ndarray, blocked: np.ndarray,
                 cost: np.ndarray, upto_m: float) -> np.ndarray:
    """The lattice path ``pts`` with its first ``upto_m`` straightened: from each kept point,
    the farthest later point (within ``upto_m``) whose straight segment crosses no blocked
    lattice position and none dearer than the dearest on the path it replaces. Removes the
    lattice's zig-zag (a heading wobble of a few degrees on open ground) but not a detour."""
    if len(pts) < 3:
        return pts

    def cells(a, b):
        m = max(int(np.ceil(np.hypot(*(b - a)) / (0.5 * r))), 1)
        q = a + np.linspace(0.0, 1.0, m + 1)[:, None] * (b - a)
        ij = np.floor((q - lo) / r).astype(int)
        ij = ij[np.all((ij >= 0) & (ij < n), axis=1)]    # off the lattice: unknown, free
        return ij[:, 0], ij[:, 1]

    out, i, walked = [pts[0]], 0, 0.0
    while i < len(pts) - 1 and walked < upto_m:
        far = [j for j in range(i + 1, len(pts) - 1) if np.hypot(*(pts[j] - pts[i])) <= upto_m]
        far.append(len(pts) - 1)        # and the goal, straight
        nxt = i + 1
        for j in reversed(far):
            if j == i + 1:
                break
            ci, cj = cells(pts[i], pts[j])
            ri, rj = np.clip(np.floor((pts[i:j + 1] - lo) / r).astype(int), 0, n - 1).T
            if not len(ci) or (not blocked[ci, cj].any()
                               and cost[ci, cj].max() <= cost[ri, rj].max() + 1e-9):
                nxt = j
                break
        walked += float(np.hypot(*(pts[nxt] - pts[i])))
        out.append(pts[nxt])
        i = nxt
    return np.vstack([out, pts[i + 1:]])
