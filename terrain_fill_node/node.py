"""terrain_fill_node: the mapper's fine grid -> filled grid with bounds and foothold cost.

Subscriptions (reliable, transient local):
    /map/fine            terrain_msgs/TerrainGrid: layers ``elevation`` and (optionally)
                         ``observed`` (1 = measured) and ``upper_bound`` [m]
    /map/capture_poses   geometry_msgs/PoseArray: camera (optical frame) poses in the grid's
                         frame; each capture bounds the cells in its view cone
    /walking/stance      terrain_msgs/Stance: the feet the robot stands on (``map``); blind
                         cells near them take the plane through them (layer ``contact``)
Publications:
    /map/filled          terrain_msgs/TerrainGrid (reliable, transient local), layers
                         ``elevation`` (observed + filled) [m], ``observed`` [0/1],
                         ``upper_bound`` [m] (NaN = none), ``filled`` [0/1], ``cost`` [-],
                         ``contact`` [0/1] (height from the stance feet)
    ~/diagnostics        diagnostic_msgs/DiagnosticArray: counters of refused input

The core (:class:`terrain_perception.fill.TerrainFiller`) keeps a running-minimum bound layer
that moves with the grid and casts only the new captures' rays, refills only near a change and
recomputes the cost only around changed heights. Never-observed cells that no line of sight
crossed (the blind area behind and under the robot) are left unknown by default
(``filler.blind_area``). A cell is never marked observed because it was filled.

Coalescing: callbacks only keep the newest message (converted when processed), so grids that
queue up while an update runs are skipped. The mapper publishes the grid and the poses of a
capture with one stamp (the poses first): when both have arrived the update runs at once;
otherwise the timer (``process_period_s``) processes whatever is pending, except that poses
newer than the grid held wait one more period for their own grid.

The terrain library is either a folder of ``.npz`` GridMaps (``library_dir``) or generated with
Kolter's generator (``terrain_perception.terrain.library_terrains``) at the grid's resolution
when the first grid arrives. Bad input (a grid with no observed cell, bounds below observed
heights, NaN/inf in observed cells, a missing or empty library, a resolution the library does
not have): counted, logged once with its reason, and the last good output stays published.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import List, Optional

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray  # noqa: F401  (type published by Counters)
from geometry_msgs.msg import PoseArray
from rclpy.node import Node
from terrain_msgs.msg import Stance, TerrainGrid

from terrain_perception.config import param
from terrain_perception.features import CostConfig
from terrain_perception.fill import (BoundsConfig, FillConfig, FillerConfig, RayConfig,
                                     TerrainFiller)
from terrain_perception.grid import ELEVATION, GridMap
from terrain_ros.conversions import (grid_to_msg, msg_to_grid, msg_to_stance,
                                     pose_matrices_once, stamp_to_sec)
from terrain_ros.node import Counters, run_node
from terrain_ros.params import declare_config
from terrain_ros.qos import LATCHED_QOS


@dataclass(frozen=True)
class TerrainFillNodeConfig:
    """Node-level parameters (the algorithms' own are Fill/Cost/Bounds/RayConfig)."""

    library_dir: str = param('', 'folder of .npz GridMaps (elevation layer, fully known) used as '
                             'the terrain library; empty = generate with Kolter\'s generator')
    library_count: int = param(10, 'generated library: number of 1 m x 1 m terrains '
                               '(paper 000: 10)', 1, 100)
    library_seed: int = param(0, 'generated library: generator seed', 0)
    library_height_range_m: float = param(0.06, 'generated library: height range [m] '
                                          '(rocks-6cm)', 0.005, 1.0)
    library_cache_dir: str = param('', 'generated library: folder to keep and reuse the '
                                   'terrains in; empty = no cache', )
    process_period_s: float = param(0.1, 'how often pending input is processed when the grid '
                                    'and poses of one capture did not both arrive [s]',
                                    0.01, 60.0)
    diagnostics_period_s: float = param(1.0, 'period of ~/diagnostics [s]', 0.05, 3600.0)


def load_library_dir(path: str) -> tuple:
    """(list of float64 height arrays, resolution [m]) from a folder of .npz GridMaps."""
    folder = Path(path).expanduser()
    if not folder.is_dir():
        raise ValueError(f'terrain library folder {folder} does not exist')
    files = sorted(folder.glob('*.npz'))
    if not files:
        raise ValueError(f'terrain library folder {folder} holds no .npz grids (empty library)')
    maps, res = [], set()
    for f in files:
        g = GridMap.load(f)
        if ELEVATION not in g:
            raise ValueError(f'library grid {f} has no {ELEVATION!r} layer')
        maps.append(np.asarray(g[ELEVATION], np.float64))
        res.add(round(g.resolution_m, 12))
    if len(res) != 1:
        raise ValueError(f'library grids in {folder} have different resolutions {sorted(res)}')
    return maps, res.pop()


class TerrainFillNode(Node):
    """Fine grid + capture poses -> filled grid; see the module docstring."""

    def __init__(self, **kwargs) -> None:
        super().__init__('terrain_fill', **kwargs)
        self.node_cfg: TerrainFillNodeConfig = declare_config(
            self, TerrainFillNodeConfig, on_change=self._on_cfg)
        self.fill_cfg: FillConfig = declare_config(self, FillConfig, 'fill',
                                                   on_change=self._on_cfg)
        self.cost_cfg: CostConfig = declare_config(self, CostConfig, 'cost',
                                                   on_change=self._on_cfg)
        self.bounds_cfg: BoundsConfig = declare_config(self, BoundsConfig, 'bounds',
                                                       on_change=self._on_cfg)
        self.ray_cfg: RayConfig = declare_config(self, RayConfig, 'rays', on_change=self._on_cfg)
        self.filler_cfg: FillerConfig = declare_config(self, FillerConfig, 'filler',
                                                       on_change=self._on_cfg)
        self.counters = Counters(self)
        self.filler: Optional[TerrainFiller] = None
        self._library: Optional[tuple] = None
        self._grid: Optional[GridMap] = None
        self._grid_msg: Optional[TerrainGrid] = None   # newest, not yet converted
        self._poses_msg: Optional[PoseArray] = None
        self._poses_held = False    # pending poses kept one timer period for their grid
        self._cams: np.ndarray = np.zeros((0, 4, 4))   # capture poses T_map_camera
        self._cams_frame: Optional[str] = None
        self._pose_cache = pose_matrices_once()   # capture pose -> its 4x4, once
        self._dirty = False
        self._stance: Optional[tuple] = None           # (feet (4, 3), frame)
        self.last_output: Optional[GridMap] = None
        self.published = 0
        self.skipped = 0            # grids superseded by a newer one before being processed
        self.update_cpu_s: List[float] = []   # CPU time of each update (last 100)
        self._load_library()

        self.pub = self.create_publisher(TerrainGrid, '/map/filled', LATCHED_QOS)
        self.create_subscription(TerrainGrid, '/map/fine', self._on_grid, LATCHED_QOS)
        self.create_subscription(PoseArray, '/map/capture_poses', self._on_poses, LATCHED_QOS)
        self.create_subscription(Stance, '/walking/stance', self._on_stance, LATCHED_QOS)
        self.create_timer(self.node_cfg.process_period_s, self._on_timer)
        self.create_timer(self.node_cfg.diagnostics_period_s, self.counters.publish)

    # ------------------------------------------------------------------ configuration
    def _on_cfg(self, _cfg) -> None:
        from terrain_ros.params import current_config
        self.node_cfg = current_config(self, TerrainFillNodeConfig)
        self.fill_cfg = current_config(self, FillConfig, 'fill')
        self.cost_cfg = current_config(self, CostConfig, 'cost')
        self.bounds_cfg = current_config(self, BoundsConfig, 'bounds')
        self.ray_cfg = current_config(self, RayConfig, 'rays')
        self.filler_cfg = current_config(self, FillerConfig, 'filler')
        self._library = None
        self.filler = None
        self._load_library()
        self._dirty = self._grid is not None

    def _load_library(self) -> None:
        """Load the library folder now; a generated library waits for the first grid."""
        if not self.node_cfg.library_dir:
            return
        try:
            self._library = load_library_dir(self.node_cfg.library_dir)
        except ValueError as exc:
            self._library = None
            self.counters.bump('bad_library', str(exc), self.get_logger().error)

    def _ensure_filler(self, resolution_m: float) -> bool:
        if self.filler is not None and abs(self.filler.library_resolution_m
                                           - resolution_m) < 1e-9:
            return True
        if self._library is None and not self.node_cfg.library_dir:
            from terrain_perception.terrain import library_terrains
            self.get_logger().info(
                f'generating {self.node_cfg.library_count} library terrains at '
                f'{resolution_m:g} m (Kolter generator, seed {self.node_cfg.library_seed})')
            tiles = library_terrains(self.node_cfg.library_count, self.node_cfg.library_seed,
                                     resolution_m, self.node_cfg.library_height_range_m,
                                     cache_dir=self.node_cfg.library_cache_dir or None)
            self._library = ([np.asarray(t[ELEVATION], np.float64) for t in tiles],
                             resolution_m)
        if self._library is None:
            self.counters.bump('no_library', 'no usable terrain library (see bad_library); '
                               'keeping the last output', self.get_logger().error)
            return False
        try:
            self.filler = TerrainFiller(self._library[0], self._library[1], self.fill_cfg,
                                        self.cost_cfg, self.bounds_cfg, self.ray_cfg,
                                        self.filler_cfg)
        except ValueError as exc:
            self.counters.bump('bad_library', str(exc), self.get_logger().error)
            return False
        return True

    # ------------------------------------------------------------------ input
    def _on_grid(self, msg: TerrainGrid) -> None:
        if self._grid_msg is not None:
            self.skipped += 1
        self._grid_msg = msg
        self._dirty = True
        self._process_if_paired()

    def _on_poses(self, msg: PoseArray) -> None:
        self._poses_msg = msg
        self._poses_held = False
        self._dirty = True
        self._process_if_paired()

    def _on_timer(self) -> None:
        """The ``process_period_s`` timer: process what did not pair. Poses newer than the grid
        held, with no grid pending, belong to a capture whose grid is on its way (the mapper
        publishes a capture's poses first): they wait one period for it. Processed at once,
        they redid the fill on the previous grid (and the planner its plan), and, taken, left
        their own grid unpaired until the next period, ~0.6 s of wall at the loop's real-time
        factor (session 52 traces: a capture's plan 370-540 ms late, 2-3 times a minute)."""
        p = self._poses_msg
        if (p is not None and self._grid_msg is None and self._grid is not None
                and stamp_to_sec(p.header.stamp) > self._grid.stamp_s + 1e-9
                and not self._poses_held):
            self._poses_held = True
            return
        self._poses_held = False
        self._process()

    def _on_stance(self, msg: Stance) -> None:
        try:
            feet, _ = msg_to_stance(msg)
        except ValueError as exc:
            self.counters.bump('bad_stance', f'{exc}; ignored')
            return
        self._stance = (feet, msg.header.frame_id)

    def _process_if_paired(self) -> None:
        """Update at once when the newest grid and poses come from the same capture."""
        g, p = self._grid_msg, self._poses_msg
        if g is not None and p is not None and g.header.stamp == p.header.stamp:
            self._process()

    def _take_input(self) -> bool:
        """Convert the newest pending messages (older ones were dropped unconverted); False
        when the pending grid was refused."""
        if self._poses_msg is not None:
            msg, self._poses_msg = self._poses_msg, None
            try:
                poses = self._pose_matrices(msg.poses)
            except ValueError as exc:
                self.counters.bump('bad_poses', f'capture poses refused: {exc}')
            else:
                self._cams = poses
                self._cams_frame = msg.header.frame_id
        if self._grid_msg is not None:
            msg, self._grid_msg = self._grid_msg, None
            try:
                self._grid = msg_to_grid(msg)
            except ValueError as exc:
                self.counters.bump('bad_grid', str(exc))
                self._grid = None
                return False
        return True

    def _pose_matrices(self, poses) -> np.ndarray:
        """(K, 4, 4) matrices of the capture poses, each converted once (the mapper
        republishes every kept pose with each capture: ~130, ~6 ms); ValueError on a bad pose,
        as pose_to_matrix."""
        return np.array(self._pose_cache(poses)).reshape(-1, 4, 4)

    # ------------------------------------------------------------------ work
    def _process(self) -> None:
        if not self._dirty:
            return
        self._dirty = False
        if not self._take_input() or self._grid is None:
            return
        grid = self._grid
        if not self._ensure_filler(grid.resolution_m):
            return
        cams: List = self._cams
        if len(cams) and self._cams_frame and self._cams_frame != grid.frame_id:
            self.counters.bump('frame_mismatch', f'capture poses are in {self._cams_frame!r}, '
                               f'the grid in {grid.frame_id!r}; poses ignored')
            cams = np.zeros((0, 4, 4))
        feet = None
        if self._stance is not None:
            if self._stance[1] in ('', grid.frame_id):
                feet = self._stance[0]
            else:
                self.counters.bump('frame_mismatch', f'stance is in {self._stance[1]!r}, the '
                                   f'grid in {grid.frame_id!r}; stance ignored')
        c0 = time.process_time()
        try:
            out = self.filler.update(grid, cams, feet)
        except ValueError as exc:
            self.counters.bump('bad_grid', f'{exc}; keeping the last output')
            self._grid = None               # new poses alone do not retry a refused grid
            return
        self.update_cpu_s = self.update_cpu_s[-99:] + [time.process_time() - c0]
        self.last_output = out
        self.pub.publish(grid_to_msg(out, basic_layers=(ELEVATION,)))
        self.published += 1


def main(args=None) -> int:
    return run_node(TerrainFillNode, args=args)


if __name__ == '__main__':
    main()
