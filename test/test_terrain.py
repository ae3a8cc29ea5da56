"""Terrain generators: determinism, class height ranges, course layout, raster vs. ray casts."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from terrain_perception import terrain as T
from terrain_perception.config import load_config
from terrain_perception.grid import ELEVATION, GridMap

CONFIG = Path(__file__).resolve().parents[1] / 'config' / 'terrain.yaml'
FAST_KOLTER = T.KolterConfig(bodies_per_m2=40.0, sample_resolution_m=0.004, kernel_size_px=5)


@pytest.fixture(scope='module')
def rocks6():
    return T.make_course('rocks-6cm', 3)


def test_course_is_deterministic_for_a_seed(rocks6):
    again = T.make_course('rocks-6cm', 3)
    np.testing.assert_array_equal(rocks6[ELEVATION], again[ELEVATION])
    other = T.make_course('rocks-6cm', 4, kolter=FAST_KOLTER)
    first = T.make_course('rocks-6cm', 3, kolter=FAST_KOLTER)
    assert not np.array_equal(first[ELEVATION], other[ELEVATION])


@pytest.mark.parametrize('cls_name', ['rocks-6cm', 'rocks-12cm', 'stones-15cm'])
def test_height_range_matches_class_name(cls_name, rocks6):
    grid = rocks6 if cls_name == 'rocks-6cm' else T.make_course(cls_name, 7)
    expected = {'rocks-6cm': 0.06, 'rocks-12cm': 0.12, 'stones-15cm': 0.15}[cls_name]
    elev = grid[ELEVATION]
    x0, x1, y0, y1 = grid.metadata['rough_extent_xy']
    xs, ys = grid.cell_centers()
    rough = (xs[:, None] > x0) & (xs[:, None] < x1) & (ys[None, :] > y0) & (ys[None, :] < y1)
    assert np.all(np.isfinite(elev))
    assert elev[rough].max() - elev[rough].min() == pytest.approx(expected, abs=1e-6)
    assert np.all(elev[~rough] == 0.0)            # flat approach and exit at floor level
    covered = {'rocks-6cm': 0.2, 'rocks-12cm': 0.2, 'stones-15cm': 0.03}[cls_name]
    assert (elev[rough] > 0.2 * expected).mean() > covered   # the section is really rough
    assert grid.metadata['class'] == cls_name and grid.metadata['seed'] in (3, 7)


def test_course_layout_and_save_roundtrip(rocks6, tmp_path):
    cfg = T.course_config('rocks-6cm')
    res = rocks6.resolution_m
    assert rocks6.shape == (round((cfg.approach_m + cfg.rough_length_m + cfg.exit_m) / res),
                            round(cfg.width_m / res))
    assert rocks6.origin_xy == pytest.approx((0.0, -cfg.width_m / 2))
    assert rocks6.metadata['rough_extent_xy'] == pytest.approx(
        [cfg.approach_m, cfg.approach_m + cfg.rough_length_m, -0.5, 0.5])
    loaded = GridMap.load(rocks6.save(tmp_path / 'course.npz'))
    np.testing.assert_array_equal(loaded[ELEVATION], rocks6[ELEVATION])
    assert loaded.metadata['seed'] == 3 and loaded.metadata['class'] == 'rocks-6cm'


def test_yaml_matches_builtin_defaults():
    assert load_config(T.KolterConfig, CONFIG, 'kolter_generator') == T.KolterConfig()
    assert load_config(T.StonesConfig, CONFIG, 'stone_generator') == T.StonesConfig()
    for name, cfg in T.COURSE_CLASSES.items():
        assert T.course_config(name, CONFIG) == cfg


def test_bad_input_is_refused():
    with pytest.raises(ValueError, match='unknown terrain class'):
        T.make_course('lava-1m', 0)
    with pytest.raises(ValueError, match='resolution'):
        T.make_course('stones-15cm', 0, resolution_m=0.0)
    with pytest.raises(ValueError, match='area'):
        T.kolter_heights((0.0, 1.0), 0, 0.06)


def test_raster_matches_pybullet_ray_casts():
    """The hull-plane raster of resting bodies equals pybullet's own ray casts against them."""
    import pybullet
    from pybullet_utils.bullet_client import BulletClient
    rng = np.random.default_rng(5)
    bodies = [T.random_convex_body(rng, 10, 0.02) + [rng.uniform(0.1, 0.4),
                                                     rng.uniform(0.1, 0.4), 0.0]
              for _ in range(6)]
    bodies += T.stone_blocks((0.5, 0.5), 2, 0.15, T.StonesConfig(stones_per_m2=8.0))
    res = 0.004
    h = np.zeros((125, 125))
    for v in bodies:
        T.rasterize_convex(h, (0.0, 0.0), res, v)
    h = np.maximum(h, 0.0)
    client = BulletClient(pybullet.DIRECT)
    try:
        for v in bodies:
            shape = client.createCollisionShape(pybullet.GEOM_MESH, vertices=v.tolist())
            client.createMultiBody(0, shape)
        xs = (np.arange(125) + 0.5) * res
        X, Y = np.meshgrid(xs, xs, indexing='ij')
        src = np.column_stack([X.ravel(), Y.ravel(), np.full(X.size, 1.0)])
        dst = src * [1, 1, 0] - [0, 0, 0.5]
        hits = []
        for k in range(0, len(src), 8000):
            hits += client.rayTestBatch(src[k:k + 8000].tolist(), dst[k:k + 8000].tolist())
        ray_h = np.array([max(hit[3][2], 0.0) if hit[0] >= 0 else 0.0 for hit in hits])
    finally:
        client.disconnect()
    ray_h = ray_h.reshape(h.shape)
    assert (h > 0.005).mean() > 0.05
    # pybullet's convex collision margin rounds edges: compare away from steep edges
    err = np.abs(ray_h - h)
    assert np.median(err) < 1e-4
    assert np.mean(err < 2e-3) > 0.97


def test_kolter_tile_sets_are_disjoint_and_square():
    lib = T.library_terrains(2, 11, resolution_m=0.02, kolter=FAST_KOLTER)
    tst = T.test_terrains(1, 11, resolution_m=0.02, kolter=FAST_KOLTER)
    for tile in lib + tst:
        assert tile.shape == (50, 50) and tile.length_xy == pytest.approx((1.0, 1.0))
        assert float(tile[ELEVATION].max()) == pytest.approx(0.06)
    seeds = {t.metadata['seed'] for t in lib} | {t.metadata['seed'] for t in tst}
    assert len(seeds) == 3
    again = T.library_terrains(2, 11, resolution_m=0.02, kolter=FAST_KOLTER)
    np.testing.assert_array_equal(again[1][ELEVATION], lib[1][ELEVATION])
    assert dataclasses.asdict(FAST_KOLTER)['bodies_per_m2'] == 40.0


def test_cli_writes_the_course_and_a_preview(tmp_path, capsys):
    from terrain_perception.terrain_cli import main
    out, png = tmp_path / 'course.npz', tmp_path / 'preview.png'
    assert main(['--class', 'stones-15cm', '--seed', '3', '-o', str(out), '--png', str(png),
                 '--resolution', '0.01']) == 0
    grid = GridMap.load(out)
    np.testing.assert_array_equal(grid[ELEVATION],
                                  T.make_course('stones-15cm', 3, 0.01)[ELEVATION])
    import cv2
    img = cv2.imread(str(png))
    assert img.shape == (grid.shape[1], grid.shape[0], 3)
    assert 'stones-15cm seed 3' in capsys.readouterr().out
    assert main(['--class', 'stones-15cm', '--seed', '3', '-o', str(out),
                 '--resolution', '-1']) == 2
    assert 'resolution' in capsys.readouterr().err
