"""terrain-bench icp: the map's error by terrain region and the --stereo-variant option (the
bench itself renders a walk, too slow for the suite; docs/BENCHMARKS.md has its output)."""

import argparse

import numpy as np
import pytest

from terrain_perception.bench import icp
from terrain_perception.grid import ELEVATION, GridMap


def _box_course():
    """A 1 cm grid with one 8 cm box rock (cells 20..39 in x and y) on a flat floor."""
    h = np.zeros((60, 60))
    h[20:40, 20:40] = 0.08
    return GridMap.from_layers(0.01, (0.0, 0.0), {ELEVATION: h})


def test_map_error_is_split_into_floor_near_flank_flank_and_top():
    course = _box_course()
    truth = course[ELEVATION].astype(float)
    box = truth > 0.04
    err = np.full(truth.shape, np.nan)
    # flanks: the cells either side of the box's edge (a 4-neighbour across the step)
    edge = np.zeros_like(box)
    edge[1:, :] |= box[1:, :] != box[:-1, :]
    edge[:-1, :] |= box[:-1, :] != box[1:, :]
    edge[:, 1:] |= box[:, 1:] != box[:, :-1]
    edge[:, :-1] |= box[:, :-1] != box[:, 1:]
    err[edge] = 0.020
    err[21:39, 21:39] = -0.004                      # the top, inside the edge ring
    for i in (18, 41):                              # floor one cell beyond the outer ring
        err[i, 20:40] = 0.008
        err[20:40, i] = 0.008
    far = np.ones_like(box)
    far[14:46, 14:46] = False                       # floor at least 6 cm from the box
    err[far] = 0.001
    err[-1, :] = err[:, -1] = np.nan                # the truth's last cells are not meshed
    grid = GridMap.from_layers(0.01, (0.0, 0.0), {ELEVATION: truth + err})

    out = icp.map_error_by_region(grid, course)

    assert list(out) == list(icp.REGIONS)
    expect = {'floor': (0.001, int(np.sum(far[:-1, :-1]))),
              'floor_near_flank': (0.008, 4 * 20),
              'flank': (0.020, int(edge.sum())),
              'top': (-0.004, 18 * 18)}
    for name, (e, cells) in expect.items():
        assert out[name]['cells'] == cells, name
        assert out[name]['mean_m'] == pytest.approx(e, abs=1e-6), name
        assert out[name]['rmse_m'] == pytest.approx(abs(e), abs=1e-6), name


def test_an_empty_region_has_no_error_figure():
    course = GridMap.from_layers(0.01, (0.0, 0.0), {ELEVATION: np.zeros((20, 20))})
    out = icp.map_error_by_region(course, course)
    assert out['floor']['cells'] > 0 and out['floor']['rmse_m'] == 0.0
    for name in ('floor_near_flank', 'flank', 'top'):
        assert out[name]['cells'] == 0 and np.isnan(out[name]['rmse_m'])


def test_stereo_variant_parses_name_and_checked_overrides():
    name, over = icp.parse_stereo_variant(
        'wide={"fattening_radius_px": 7, "fattening_jump_px": 2}')
    assert name == 'wide' and over == {'fattening_radius_px': 7, 'fattening_jump_px': 2}
    for bad, msg in [('wide', 'NAME=JSON'), ('default={}', 'other than'),
                     ('shao={}', 'other than'), ('default_icp={}', 'other than'),
                     ('w={"fattening_radius_px": ', 'not JSON'),
                     ('w=[1]', 'must be an object'), ('w={"radius": 3}', 'radius')]:
        with pytest.raises(argparse.ArgumentTypeError, match=msg):
            icp.parse_stereo_variant(bad)
    parser = argparse.ArgumentParser()
    icp.add_arguments(parser)
    args = parser.parse_args(['--stereo-variant', 'a={"block_size_px": 9}',
                              '--stereo-variant', 'b={}'])
    assert dict(args.stereo_variant) == {'a': {'block_size_px': 9}, 'b': {}}


def test_the_basin_mode_finds_the_truth_from_it_and_the_multi_start_beats_the_single_icp():
    """--basin: starting at the true pose the ICP stays within 1 cm of it; from a prior
    10 cm off, the best of the starts around it comes back at least as often as the single
    ICP from the prior (which cannot reach that far on rocks: its correspondences end at
    a few centimetres)."""
    p = argparse.ArgumentParser()
    icp.add_arguments(p)
    args = p.parse_args(['--terrain', 'rocks-6cm', '--start-x', '0.7', '--distance', '0.8',
                         '--basin'])
    args.quick = True                    # the runner's option: half-size images, 10 cm steps
    seq = icp.build_sequence(args)
    rows = {r['offset_m']: r for r in icp.icp_basin(seq, offsets=(0.0, 0.10), first=3,
                                                    every=2, trials=2)['rows']}
    assert rows[0.0]['trials'] >= 4 and rows[0.10]['trials'] == rows[0.0]['trials']
    assert rows[0.0]['single_within_1cm'] == 1.0
    assert rows[0.10]['multi_within_1cm'] >= rows[0.10]['single_within_1cm']
    assert rows[0.10]['multi_within_1cm'] > 0.0
