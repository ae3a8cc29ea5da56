"""Core stereo pipeline on hand-made data: Fig. 3 relations, row outliers, reprojection."""

import cv2
import numpy as np
import pytest

from terrain_perception.camera import PinholeCamera, StereoCamera
from terrain_perception.config import make_config
from terrain_perception.stereo import (StereoConfig, StereoInputError, StereoMatcher,
                                       StereoPipeline, check_pair, coarse_subsample,
                                       disparity_to_points, drop_fattened, fill_rows,
                                       fixed_to_float, normalise, remove_row_outliers, to_gray)

N = np.nan


def row(*vals):
    return np.array([vals], dtype=np.float32)


def assert_row(got, *want):
    np.testing.assert_array_equal(got, row(*want))


# ----------------------------------------------------------------- fattening guard


def test_fattening_guard_drops_both_sides_of_a_depth_edge_and_keeps_the_ground_ramp():
    # ground: disparity growing 0.2 px per row (a plane seen from above); a rock (40 px) whose
    # disparity the SAD window spread 3 px into the ground to its right (columns 40-42)
    v = np.arange(60, dtype=np.float32)[:, None]
    d = np.broadcast_to(10.0 + 0.2 * v, (60, 80)).copy()
    d[20:40, 20:43] = 40.0
    out = drop_fattened(d, 4, 3.0)
    assert np.isnan(out[30, 39:43]).all()            # the fattened strip and the rock's rim
    assert np.isnan(out[30, 20:24]).all()            # the rim on the other side
    assert np.isfinite(out[30, 24:39]).all()         # the rock top more than 4 px from the edge
    np.testing.assert_array_equal(out[30, 24:39], d[30, 24:39])
    ground = np.ones_like(d, bool)
    ground[16:44, 16:47] = False                     # farther than 4 px from the rock
    np.testing.assert_array_equal(out[ground], d[ground])   # a 0.8 px change per window stays
    assert drop_fattened(d, 0, 3.0) is d             # off


def test_fattening_guard_ignores_holes_and_refuses_a_cloud():
    d = np.full((20, 20), 30.0, np.float32)
    d[5:15, 5:15] = np.nan                            # a hole is no small disparity
    out = drop_fattened(d, 3, 2.0)
    np.testing.assert_array_equal(np.isnan(out), np.isnan(d))
    with pytest.raises(ValueError, match=r'\(H, W\)'):
        drop_fattened(np.zeros((4, 4, 3), np.float32), 3, 2.0)


# ----------------------------------------------------------------- area filling (Fig. 3)

def test_case_a_first_pixel_with_blank_right_neighbour_is_left_alone():
    # (a) | A A1 ...: A stays blank; A1 has a blank left and a valid right neighbour -> (f).
    assert_row(fill_rows(row(N, N, 5, 5)), N, 5, 5, 5)


def test_case_b_first_pixel_takes_its_right_neighbour():
    assert_row(fill_rows(row(N, 7, 8, 9)), 7, 7, 8, 9)


def test_case_c_last_pixel_with_blank_left_neighbour_is_left_alone():
    # (c) ... A1 A |: A stays blank; A1 has a valid left and a blank right neighbour -> (g).
    assert_row(fill_rows(row(3, 5, N, N)), 3, 5, 5, N)


def test_case_d_last_pixel_takes_its_left_neighbour():
    assert_row(fill_rows(row(3, 4, 6, N)), 3, 4, 6, 6)


def test_case_e_blank_between_blanks_is_left_alone():
    # Middle of a 3-gap is (e); its ends are (g) and (f).
    assert_row(fill_rows(row(1, N, N, N, 9)), 1, 1, N, 9, 9)


def test_case_f_left_blank_right_valid_takes_right():
    assert_row(fill_rows(row(2, N, N, 8)), 2, 2, 8, 8)


def test_case_g_left_valid_right_blank_takes_left():
    # Same 2-gap: the first blank is (g) (takes 2), the second (f) (takes 8).
    out = fill_rows(row(2, N, N, 8))
    assert out[0, 1] == 2 and out[0, 2] == 8


def test_case_h_both_neighbours_valid_takes_the_mean():
    assert_row(fill_rows(row(2, N, 6, N, 7)), 2, 4, 6, 6.5, 7)


def test_rows_are_independent_and_valid_pixels_untouched():
    d = np.array([[1, 2, 3], [N, N, N], [4, N, 6]], dtype=np.float32)
    out = fill_rows(d)
    np.testing.assert_array_equal(out[0], [1, 2, 3])
    assert np.isnan(out[1]).all()            # an all-blank row has nothing to copy from
    np.testing.assert_array_equal(out[2], [4, 5, 6])
    assert np.isnan(d[2, 1])                 # input not modified


def test_more_passes_close_longer_gaps():
    d = row(1, N, N, N, N, N, 9)
    assert np.isnan(fill_rows(d, 1)).sum() == 3
    assert np.isnan(fill_rows(d, 2)).sum() == 1
    assert np.isfinite(fill_rows(d, 3)).all()


# ----------------------------------------------------------------- row outliers

def test_row_outliers_blank_rare_values_only():
    d = np.full((2, 20), 10.0, dtype=np.float32)
    d[0, 3] = 30.2           # a single mismatch
    d[0, 10:13] = 20.0       # three pixels of a real object: kept at min_count 3
    d[1, 5] = N
    out = remove_row_outliers(d, min_count=3, min_disparity=0, num_disparities=64)
    assert np.isnan(out[0, 3])
    np.testing.assert_array_equal(out[0, 10:13], 20.0)
    assert np.isnan(out).sum() == 2          # the mismatch and the pre-existing blank
    out4 = remove_row_outliers(d, min_count=4, min_disparity=0, num_disparities=64)
    assert np.isnan(out4[0, 10:13]).all()


def test_row_outliers_bin_subpixel_values_by_rounding():
    d = np.array([[9.8, 10.1, 10.4, 12.0]], dtype=np.float32)
    out = remove_row_outliers(d, min_count=2)
    assert np.isnan(out[0, 3]) and np.isfinite(out[0, :3]).all()


def test_row_outliers_count_per_row_not_per_image():
    d = np.array([[5, 5, 5, 7], [7, 7, 7, 5]], dtype=np.float32)
    out = remove_row_outliers(d, min_count=2, min_disparity=0, num_disparities=16)
    assert np.isnan(out[0, 3]) and np.isnan(out[1, 3])
    assert np.isfinite(out[:, :3]).all()


# ----------------------------------------------------------------- reprojection

def stereo_cam(w=64, h=48, f=50.0, b=0.1):
    return StereoCamera(PinholeCamera(w, h, f, f, (w - 1) / 2, (h - 1) / 2), b)


def test_disparity_to_points_known_values():
    cam = stereo_cam()
    d = np.full((48, 64), N, dtype=np.float32)
    d[10, 20] = 5.0           # Z = 50 * 0.1 / 5 = 1 m
    d[30, 60] = 2.5           # Z = 2 m
    d[0, 0] = 0.0             # infinitely far: invalid
    pts = disparity_to_points(d, cam)
    assert pts.shape == (48, 64, 3) and pts.dtype == np.float32
    cx, cy = 31.5, 23.5
    np.testing.assert_allclose(pts[10, 20], [(20 - cx) / 50, (10 - cy) / 50, 1.0], rtol=1e-6)
    np.testing.assert_allclose(pts[30, 60], [(60 - cx) * 2 / 50, (30 - cy) * 2 / 50, 2.0],
                               rtol=1e-6)
    assert np.isfinite(pts).all(axis=2).sum() == 2
    assert np.isnan(disparity_to_points(d, cam, max_depth_m=1.5)[30, 60]).all()
    # Round trip through the camera model.
    np.testing.assert_allclose(cam.left.project(pts[10, 20]), [20, 10], atol=1e-4)


def test_disparity_to_points_rejects_wrong_size():
    with pytest.raises(ValueError, match='disparity is'):
        disparity_to_points(np.zeros((10, 10), np.float32), stereo_cam())


def test_coarse_subsample_is_uniform_and_organized():
    pts = np.arange(48 * 64 * 3, dtype=np.float32).reshape(48, 64, 3)
    c = coarse_subsample(pts, 8)
    assert c.shape == (6, 8, 3)
    np.testing.assert_array_equal(c[1, 2], pts[12, 20])
    np.testing.assert_array_equal(coarse_subsample(pts, 1), pts)
    with pytest.raises(ValueError):
        coarse_subsample(pts.reshape(-1, 3), 4)


# ----------------------------------------------------------------- matching

def textured(h=120, w=200, seed=0):
    rng = np.random.default_rng(seed)
    return cv2.GaussianBlur((rng.random((h, w)) * 255).astype(np.uint8), (3, 3), 0)


@pytest.mark.parametrize('shift', [7, 23])
def test_matcher_recovers_a_known_shift(shift):
    left = textured()
    right = np.roll(left, -shift, axis=1)     # right[u] = left[u + shift]: d = shift
    cfg = StereoConfig(num_disparities=32, block_size_px=9)
    d = StereoMatcher(cfg).match(left, right)
    inner = d[10:-10, 32 + 10:-10 - shift]
    assert np.isfinite(inner).mean() > 0.99
    assert np.nanmax(np.abs(inner - shift)) < 0.5


def test_normalisation_cancels_gain_and_offset():
    img = textured()
    dark = cv2.convertScaleAbs(img, alpha=0.5, beta=10)
    a, b = normalise(img, 'meanstd').astype(int), normalise(dark, 'meanstd').astype(int)
    assert np.abs(a - b).mean() < 2.0
    assert np.abs(img.astype(int) - dark).mean() > 30


def test_pipeline_on_a_brightness_mismatched_pair():
    left = textured(seed=3)
    right = cv2.convertScaleAbs(np.roll(left, -12, axis=1), alpha=0.6, beta=30)
    cam = stereo_cam(w=200, h=120)
    frame = StereoPipeline(StereoConfig(num_disparities=32, block_size_px=9), cam).process(
        left, right)
    inner = frame.disparity[10:-10, 45:-20]
    assert np.mean(np.abs(inner - 12) < 1) > 0.99
    z = frame.points[10:-10, 45:-20, 2]
    np.testing.assert_allclose(np.nanmedian(z), 50 * 0.1 / 12, rtol=1e-3)
    assert frame.coarse.shape == (15, 25, 3)


def test_fixed_to_float_marks_no_match():
    d = fixed_to_float(np.array([[-16, 0, 16, 40]], np.int16))
    assert np.isnan(d[0, 0])
    np.testing.assert_array_equal(d[0, 1:], [0, 1, 2.5])


# ----------------------------------------------------------------- bad input

def test_to_gray_accepts_mono_rgb_bgr_and_refuses_others():
    rgb = np.zeros((4, 5, 3), np.uint8)
    rgb[..., 0] = 255
    assert to_gray(rgb, 'rgb')[0, 0] == 76 and to_gray(rgb, 'bgr')[0, 0] == 29
    assert to_gray(np.ones((4, 5, 1), np.uint8)).shape == (4, 5)
    for bad, what in ((np.zeros((4, 5), np.uint16), 'dtype'),
                      (np.zeros((4, 5), np.float32), 'dtype'),
                      (np.zeros((4, 5, 4), np.uint8), 'shape')):
        with pytest.raises(StereoInputError, match=what) as e:
            to_gray(bad)
        assert e.value.key == 'bad_encoding'


@pytest.mark.parametrize('key,left,right', [
    ('size_mismatch', textured(), textured(h=100)),
    ('black_image', np.zeros((120, 200), np.uint8), textured()),
    ('saturated_image', textured(), np.full((120, 200), 255, np.uint8)),
    ('blank_image', np.full((120, 200), 90, np.uint8), textured()),
    ('too_small', textured(w=40), textured(w=40)),
])
def test_check_pair_refuses_bad_pairs(key, left, right):
    with pytest.raises(StereoInputError) as e:
        check_pair(left, right, StereoConfig())
    assert e.value.key == key


def test_config_validation():
    with pytest.raises(ValueError, match='multiple of 16'):
        make_config(StereoConfig, {'num_disparities': 40})
    with pytest.raises(ValueError, match='odd'):
        make_config(StereoConfig, {'block_size_px': 10})
    with pytest.raises(ValueError, match='not one of'):
        make_config(StereoConfig, {'normalisation': 'magic'})


@pytest.mark.parametrize('outliers,filling', [(True, True), (True, False), (False, True)])
def test_pipeline_fast_path_equals_the_float_steps(outliers, filling):
    from terrain_perception.stereo import postprocess
    rng = np.random.default_rng(5)
    left = textured(seed=5)
    right = np.roll(left, -9, axis=1)
    right[40:60, 100:140] = rng.integers(0, 255, (20, 40))    # a patch of mismatches
    cfg = StereoConfig(num_disparities=32, block_size_px=9, outlier_removal=outliers,
                       area_filling=filling, outlier_min_count=6)
    pipe = StereoPipeline(cfg, stereo_cam(w=200, h=120))
    fast = pipe.disparity(left, right)
    slow = postprocess(pipe.matcher.match(*pipe.prepare(left, right)), cfg)
    np.testing.assert_array_equal(fast, slow)
    assert np.isnan(fast).sum() > 0
