"""Benchmark helpers: scoring on hand-made maps, ground-truth readers, the --left/--right mode."""

import argparse

import cv2
import numpy as np
import pytest

from terrain_perception.bench.stereo import (evaluable_mask, read_disparity, read_image,
                                             run, score_disparity)

N = np.nan


def test_score_counts_holes_as_bad():
    gt = np.array([[10, 10, 10, 10, N]], np.float32)
    est = np.array([[10.5, 13, N, 10, 10]], np.float32)
    mask = np.isfinite(gt)
    s = score_disparity(est, gt, mask)
    assert s['bad2'] == pytest.approx(2 / 4)          # one wrong, one hole
    assert s['bad2_est'] == pytest.approx(1 / 3)
    assert s['coverage'] == pytest.approx(3 / 4)


def test_evaluable_mask_drops_pixels_whose_match_is_off_the_right_image():
    gt = np.full((1, 6), 3.0, np.float32)
    gt[0, 5] = 70.0                                   # outside a 64-disparity search
    np.testing.assert_array_equal(evaluable_mask(gt, 0, 64)[0],
                                  [False, False, False, True, True, False])


def _write_pfm(path, arr):
    a = np.asarray(arr, '<f4')
    with open(path, 'wb') as f:
        f.write(b'Pf\n%d %d\n-1.0\n' % (a.shape[1], a.shape[0]))
        f.write(a[::-1].tobytes())


def test_ground_truth_readers_agree(tmp_path):
    gt = np.array([[1.5, 20.25, N], [0.0, 63.0, 7.75]], np.float32)
    _write_pfm(tmp_path / 'd.pfm', np.where(np.isfinite(gt), gt, np.inf))
    np.save(tmp_path / 'd.npy', gt)
    cv2.imwrite(str(tmp_path / 'd.png'),
                np.where(np.isfinite(gt), gt * 256, 0).astype(np.uint16))
    want = np.where(gt > 0, gt, np.nan)               # 0 means "none" in every format
    for name in ('d.pfm', 'd.npy', 'd.png'):
        np.testing.assert_array_equal(read_disparity(tmp_path / name), want)
    cv2.imwrite(str(tmp_path / 'bad.png'), np.zeros((2, 3), np.uint8))
    with pytest.raises(ValueError, match='16-bit'):
        read_disparity(tmp_path / 'bad.png')
    with pytest.raises(FileNotFoundError):
        read_disparity(tmp_path / 'missing.pfm')


def test_files_mode_scores_a_pair_from_disk(tmp_path):
    rng = np.random.default_rng(0)
    left = cv2.GaussianBlur((rng.random((120, 240)) * 255).astype(np.uint8), (3, 3), 0)
    right = np.roll(left, -11, axis=1)
    gt = np.full(left.shape, 11.0, np.float32)
    cv2.imwrite(str(tmp_path / 'l.png'), cv2.cvtColor(left, cv2.COLOR_GRAY2BGR))
    np.save(tmp_path / 'r.npy', right)
    np.save(tmp_path / 'gt.npy', gt)
    assert read_image(tmp_path / 'l.png').shape == (120, 240)
    args = argparse.Namespace(left=tmp_path / 'l.png', right=tmp_path / 'r.npy',
                              gt=tmp_path / 'gt.npy', num_disparities=32, block_size=9,
                              save_disparity=tmp_path / 'out.npy', quick=True)
    fig = run(args)
    # The rolled-in strip on the right border has no true match: only it may be wrong.
    assert fig['bad2_post'] < 0.1 and fig['bad2_post'] <= fig['bad2_raw']
    assert fig['methods']['post']['bad2_est'] < 0.06
    out = np.load(tmp_path / 'out.npy')
    assert np.nanmedian(out) == pytest.approx(11.0, abs=0.1)
