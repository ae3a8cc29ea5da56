"""``terrain-course``: generate a seeded course and save it as a GridMap ``.npz``.

Examples::

    terrain-course --class rocks-6cm --seed 3 -o course.npz --png preview.png
    terrain-course --class stones-15cm --seed 1 --resolution 0.01 -o stones.npz
    terrain-course --class rocks-12cm --seed 2 --config my_terrain.yaml -o c.npz

The file loads with ``GridMap.load`` (layer ``elevation`` [m], metadata: class, seed,
resolution, origin, rough-section extent) and feeds ``sim_bridge`` (``course_file``).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from terrain_perception.config import load_config
from terrain_perception.grid import ELEVATION
from terrain_perception.terrain import (COURSE_CLASSES, KolterConfig, StonesConfig,
                                        course_config, make_course)


def preview_image(elevation: np.ndarray) -> np.ndarray:
    """Hill-shaded, height-coloured BGR preview (x to the right, y up) of an elevation array."""
    import cv2
    h = np.nan_to_num(elevation.astype(np.float64))
    span = float(h.max() - h.min()) or 1.0
    norm = ((h - h.min()) / span * 255).astype(np.uint8)
    colour = cv2.applyColorMap(norm, cv2.COLORMAP_VIRIDIS).astype(np.float64)
    gx, gy = np.gradient(h)
    shade = np.clip(0.75 + 12.0 * (gx + gy), 0.35, 1.25)   # light from -x, -y
    img = np.clip(colour * shade[..., None], 0, 255).astype(np.uint8)
    return np.ascontiguousarray(np.transpose(img, (1, 0, 2))[::-1])   # rows = -y, cols = +x


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog='terrain-course', description=__doc__.split('\n')[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('--class', dest='cls', required=True, choices=sorted(COURSE_CLASSES),
                   help='difficulty class of the course')
    p.add_argument('--seed', type=int, default=0, help='random seed (default 0)')
    p.add_argument('-o', '--output', required=True, type=Path, help='output .npz file')
    p.add_argument('--resolution', type=float, default=0.005,
                   help='cell size [m] (default 0.005)')
    p.add_argument('--png', type=Path, help='also write a shaded preview image')
    p.add_argument('--config', type=Path,
                   help='terrain YAML (like config/terrain.yaml) overriding the built-ins')
    return p


def main(argv: Optional[Sequence[str]] = None) -> int:
    """Console entry point; returns the exit code (2 on a bad argument or config)."""
    args = build_parser().parse_args(argv)
    try:
        if args.seed < 0:
            raise ValueError(f'--seed must be >= 0, got {args.seed}')
        if not np.isfinite(args.resolution) or args.resolution <= 0:
            raise ValueError(f'--resolution must be a positive number of metres, '
                             f'got {args.resolution}')
        kw = {}
        if args.config is not None:
            if not args.config.is_file():
                raise ValueError(f'--config {args.config} does not exist')
            kw = dict(cfg=course_config(args.cls, args.config),
                      kolter=load_config(KolterConfig, args.config, 'kolter_generator'),
                      stones=load_config(StonesConfig, args.config, 'stone_generator'))
        t0 = time.perf_counter()
        grid = make_course(args.cls, args.seed, args.resolution, **kw)
        dt = time.perf_counter() - t0
        out = grid.save(args.output)
        if args.png is not None:
            import cv2
            args.png.parent.mkdir(parents=True, exist_ok=True)
            if not cv2.imwrite(str(args.png), preview_image(grid[ELEVATION])):
                raise ValueError(f'could not write the preview image {args.png}')
    except ValueError as exc:
        print(f'terrain-course: {exc}', file=sys.stderr)
        return 2
    e = grid[ELEVATION]
    x0, x1, y0, y1 = grid.metadata['rough_extent_xy']
    print(f'{args.cls} seed {args.seed}: {grid.shape[0]}x{grid.shape[1]} cells at '
          f'{grid.resolution_m:g} m, heights {e.min():.3f}..{e.max():.3f} m, rough section '
          f'x {x0:.2f}..{x1:.2f} m, y {y0:.2f}..{y1:.2f} m ({dt:.1f} s) -> {out}')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
