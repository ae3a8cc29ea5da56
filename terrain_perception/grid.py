"""Layered 2.5-D terrain grid: the core's one map container.

Convention (used by every module of the core and by ``terrain_ros.conversions``):

* A grid is axis-aligned in its frame (``frame_id``, usually ``map``), z up.
* ``origin_xy`` is the world position [m] of the *outer corner* of cell ``[0, 0]``, i.e. the
  minimum x and minimum y of the grid.
* Every layer is a float32 array of shape ``(nx, ny)`` indexed ``[i, j]``: ``i`` grows along +x,
  ``j`` along +y. Cell ``[i, j]`` has its centre at
  ``(origin_x + (i + 0.5) * res, origin_y + (j + 0.5) * res)``.
* Unknown values are NaN.

The message form (grid_map order) is produced only by ``terrain_ros.conversions``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, Iterable, Mapping, Optional, Tuple

import numpy as np

# Layer names used across the project (see msg/TerrainGrid.msg for units).
ELEVATION = 'elevation'
OBSERVED = 'observed'
UPPER_BOUND = 'upper_bound'
FILLED = 'filled'
COST = 'cost'
VARIANCE = 'variance'


@dataclass
class GridMap:
    """A stack of named float32 layers over one regular grid.

    Attributes:
        resolution_m: cell edge length [m/cell].
        origin_xy: world (x, y) of the grid's minimum corner [m], in ``frame_id``.
        shape: (nx, ny) cells.
        layers: name -> float32 array of ``shape``; NaN = unknown.
        frame_id: frame the grid lives in.
        stamp_s: time of the newest data [s] (0 when unknown).
        metadata: free-form, JSON-serialisable facts (seed, terrain class, ...).
    """

    resolution_m: float
    origin_xy: Tuple[float, float]
    shape: Tuple[int, int]
    layers: Dict[str, np.ndarray] = field(default_factory=dict)
    frame_id: str = 'map'
    stamp_s: float = 0.0
    metadata: Dict[str, object] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not np.isfinite(self.resolution_m) or self.resolution_m <= 0.0:
            raise ValueError(f'grid resolution must be a positive number, got {self.resolution_m}')
        nx, ny = (int(v) for v in self.shape)
        if nx <= 0 or ny <= 0:
            raise ValueError(f'grid shape must be positive, got {self.shape}')
        self.shape = (nx, ny)
        self.origin_xy = (float(self.origin_xy[0]), float(self.origin_xy[1]))
        self.resolution_m = float(self.resolution_m)
        for name, arr in list(self.layers.items()):
            self.layers[name] = self._checked(name, arr)

    # ---- construction -------------------------------------------------------------------
    @classmethod
    def from_layers(cls, resolution_m: float, origin_xy: Iterable[float],
                    layers: Mapping[str, np.ndarray], **kwargs) -> 'GridMap':
        """Build a grid whose shape is taken from the (equal-shaped) layers."""
        if not layers:
            raise ValueError('a grid needs at least one layer to infer its shape')
        shape = np.asarray(next(iter(layers.values()))).shape
        if len(shape) != 2:
            raise ValueError(f'layers must be 2-D (nx, ny), got shape {shape}')
        return cls(resolution_m, tuple(origin_xy), shape, dict(layers), **kwargs)

    @classmethod
    def empty(cls, resolution_m: float, origin_xy: Iterable[float], shape: Tuple[int, int],
              layer_names: Iterable[str] = (ELEVATION,), **kwargs) -> 'GridMap':
        """A grid with the named layers all NaN."""
        grid = cls(resolution_m, tuple(origin_xy), shape, {}, **kwargs)
        for name in layer_names:
            grid.layers[name] = np.full(grid.shape, np.nan, np.float32)
        return grid

    def _checked(self, name: str, arr: np.ndarray) -> np.ndarray:
        arr = np.asarray(arr, dtype=np.float32)
        if arr.shape != self.shape:
            raise ValueError(f'layer {name!r} has shape {arr.shape}, the grid is {self.shape}')
        return arr

    def __setitem__(self, name: str, arr: np.ndarray) -> None:
        self.layers[name] = self._checked(name, arr)

    def __getitem__(self, name: str) -> np.ndarray:
        try:
            return self.layers[name]
        except KeyError:
            raise KeyError(f'grid has no layer {name!r} (layers: {sorted(self.layers)})') from None

    def __contains__(self, name: str) -> bool:
        return name in self.layers

    def copy(self) -> 'GridMap':
        return GridMap(self.resolution_m, self.origin_xy, self.shape,
                       {k: v.copy() for k, v in self.layers.items()}, self.frame_id,
                       self.stamp_s, dict(self.metadata))

    # ---- geometry -----------------------------------------------------------------------
    @property
    def length_xy(self) -> Tuple[float, float]:
        """Extent [m] along x and y."""
        return self.shape[0] * self.resolution_m, self.shape[1] * self.resolution_m

    @property
    def center_xy(self) -> Tuple[float, float]:
        """World position [m] of the grid's centre."""
        lx, ly = self.length_xy
        return self.origin_xy[0] + 0.5 * lx, self.origin_xy[1] + 0.5 * ly

    def cell_centers(self) -> Tuple[np.ndarray, np.ndarray]:
        """1-D arrays of cell-centre x (length nx) and y (length ny) [m]."""
        r = self.resolution_m
        xs = self.origin_xy[0] + (np.arange(self.shape[0]) + 0.5) * r
        ys = self.origin_xy[1] + (np.arange(self.shape[1]) + 0.5) * r
        return xs, ys

    def world_to_index(self, xy: np.ndarray) -> np.ndarray:
        """Integer cell indices ``(..., 2)`` of world points ``(..., 2)`` [m]; may be outside.
        A NaN or infinite coordinate gives an index outside the grid (-1): casting it to an
        integer directly is undefined (it warns, and the value depends on the CPU)."""
        xy = np.asarray(xy, dtype=np.float64)
        org = np.asarray(self.origin_xy)
        f = np.floor((xy - org) / self.resolution_m)
        big = ~(np.abs(f) < 2.0 ** 62)
        if np.any(big):
            f = np.where(np.isfinite(f), np.clip(f, -2.0 ** 62, 2.0 ** 62), -1.0)
        return f.astype(np.int64)

    def index_to_world(self, ij: np.ndarray) -> np.ndarray:
        """World centres ``(..., 2)`` [m] of cell indices ``(..., 2)``."""
        ij = np.asarray(ij, dtype=np.float64)
        return np.asarray(self.origin_xy) + (ij + 0.5) * self.resolution_m

    def inside(self, ij: np.ndarray) -> np.ndarray:
        """Boolean mask: which indices ``(..., 2)`` lie on the grid."""
        ij = np.asarray(ij)
        return ((ij[..., 0] >= 0) & (ij[..., 0] < self.shape[0])
                & (ij[..., 1] >= 0) & (ij[..., 1] < self.shape[1]))

    def sample(self, name: str, xy: np.ndarray) -> np.ndarray:
        """Nearest-cell values of layer ``name`` at world points ``(..., 2)``; NaN off the grid."""
        ij = self.world_to_index(xy)
        ok = self.inside(ij)
        out = np.full(ij.shape[:-1], np.nan, np.float32)
        out[ok] = self[name][ij[ok][:, 0], ij[ok][:, 1]]
        return out

    # ---- files --------------------------------------------------------------------------
    def save(self, path: 'str | Path') -> Path:
        """Write the grid to an ``.npz`` file (layers + geometry + JSON metadata)."""
        import json
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        arrays = {f'layer__{k}': v for k, v in self.layers.items()}
        np.savez_compressed(
            path, resolution_m=self.resolution_m, origin_xy=np.asarray(self.origin_xy),
            shape=np.asarray(self.shape), frame_id=self.frame_id, stamp_s=self.stamp_s,
            metadata=json.dumps(self.metadata), **arrays)
        return path if path.suffix == '.npz' else path.with_name(path.name + '.npz')

    @classmethod
    def load(cls, path: 'str | Path') -> 'GridMap':
        """Read a grid written by :meth:`save`."""
        import json
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f'no grid file at {path}')
        try:
            with np.load(path, allow_pickle=False) as z:
                layers = {k[len('layer__'):]: z[k] for k in z.files if k.startswith('layer__')}
                return cls(float(z['resolution_m']), tuple(z['origin_xy']),
                           tuple(int(v) for v in z['shape']), layers, str(z['frame_id']),
                           float(z['stamp_s']), json.loads(str(z['metadata'])))
        except (KeyError, ValueError, OSError) as exc:
            raise ValueError(f'{path} is not a grid file written by GridMap.save: {exc}') from exc


def crop_or_pad(grid: GridMap, origin_xy: Iterable[float], shape: Tuple[int, int],
                fill: float = np.nan) -> GridMap:
    """Resample ``grid`` onto a same-resolution window; origins must differ by whole cells."""
    r = grid.resolution_m
    off = (np.asarray(tuple(origin_xy)) - np.asarray(grid.origin_xy)) / r
    off_i = np.round(off).astype(int)
    if np.any(np.abs(off - off_i) > 1e-6):
        raise ValueError('crop_or_pad needs origins that differ by whole cells')
    out = GridMap.empty(r, origin_xy, shape, (), frame_id=grid.frame_id, stamp_s=grid.stamp_s,
                        metadata=dict(grid.metadata))
    src_i0, src_j0 = max(off_i[0], 0), max(off_i[1], 0)
    src_i1 = min(off_i[0] + shape[0], grid.shape[0])
    src_j1 = min(off_i[1] + shape[1], grid.shape[1])
    for name, arr in grid.layers.items():
        dst = np.full(shape, fill, np.float32)
        if src_i1 > src_i0 and src_j1 > src_j0:
            dst[src_i0 - off_i[0]:src_i1 - off_i[0], src_j0 - off_i[1]:src_j1 - off_i[1]] = \
                arr[src_i0:src_i1, src_j0:src_j1]
        out.layers[name] = dst
    return out


def optional_layer(grid: GridMap, name: str) -> Optional[np.ndarray]:
    """The layer if present, else None."""
    return grid.layers.get(name)
