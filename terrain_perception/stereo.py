"""Stereo disparity with Shao et al.'s post-processing, reprojection and the coarse cloud.

Pipeline (paper 002, Shao, Yang, Wang, section II-A/B; paper 000, Kolter et al., section II):

1. **Normalisation** of both images (:func:`normalise`) to reduce the luminance difference
   between the cameras before matching. ``'meanstd'`` (default) maps each image to a fixed mean
   and standard deviation, which cancels any gain and offset difference exactly; ``'minmax'``
   stretches to [0, 255]; ``'equalize'`` is histogram equalisation; ``'none'`` skips it.
2. **SAD block matching** (eq. 1) over ``[min_disparity, min_disparity + num_disparities)``
   with OpenCV's ``StereoBM`` (:class:`StereoMatcher`), which *is* winner-take-all SAD over a
   square ``m x m`` window on pre-filtered images. Its own validity filters (texture threshold,
   uniqueness ratio, speckle filter) default to off, so that the paper's post-processing is what
   removes mismatches; each can be switched back on from the config. Two matching details are
   ours: the images are padded on the left so that the first ``num_disparities`` columns, which
   StereoBM never matches, are matched too (``pad_left``), and StereoBM's left-right check
   (``lr_check_px``, nearly free inside StereoBM) refuses the pixels whose true match is not in
   the right image (that band, and occlusions), where SAD otherwise returns confident garbage.
3. **Row outlier removal** (section II-B-1, :func:`remove_row_outliers`): for every row, count
   how often each disparity value occurs; the pixels whose value occurs fewer than
   ``outlier_min_count`` times in their row are mismatches and are blanked (NaN). Disparities
   are sub-pixel, so "value" means the disparity rounded to the nearest integer pixel.
4. **Area filling** (section II-B-2, :func:`fill_rows`): every blank pixel ``A`` is classified
   by the relation of Fig. 3 with its left and right neighbours in the same row and Rules 1-4
   are applied (see below).
5. **Fattening guard** (ours, :func:`drop_fattened`; ``fattening_radius_px`` 0 = off): a SAD
   window straddling a depth edge is dominated by the nearer surface, so the ground just behind
   a rock takes the rock's disparity and its points float above the ground at the rock's range.
   Pixels whose disparity exceeds the smallest one within ``fattening_radius_px`` by more than
   ``fattening_jump_px`` are blanked (both sides of strong steps; the ground's own disparity
   gradient stays below the jump). ``terrain-bench stereo`` measures it against steps 1-4.
6. **Reprojection** (:func:`disparity_to_points`) to an organized ``(H, W, 3)`` cloud in the
   left camera's optical frame, NaN where there is no disparity, and a **coarse cloud**
   (:func:`coarse_subsample`) that keeps every ``step``-th pixel in both image directions,
   the uniformly sampled low-resolution model paper 000 aligns with ICP.

Our reading of Fig. 3 (the figure is not in the text we have)
--------------------------------------------------------------
The prose says: ``A`` is the blank pixel of interest, ``A1`` and ``A2`` are two other blank
pixels, ``B``, ``B1`` and ``B2`` are pixels with a valid disparity; (a) and (b) are for a blank
pixel at the beginning of the row, (c) and (d) at its end, (e)-(h) in the middle. Rules:
(a), (c), (e) leave ``A`` alone; (b), (f) take the right pixel; (d), (g) take the left pixel;
(h) takes the mean of left and right. The only assignment of neighbour patterns consistent with
those names and rules is (row drawn left to right, ``|`` = image border)::

    (a)  | A  A1        first pixel, right neighbour blank      -> Rule 1: leave alone
    (b)  | A  B         first pixel, right neighbour valid      -> Rule 2: take right (B)
    (c)  A1 A  |        last pixel, left neighbour blank        -> Rule 1: leave alone
    (d)  B  A  |        last pixel, left neighbour valid        -> Rule 3: take left (B)
    (e)  A1 A  A2       both neighbours blank                   -> Rule 1: leave alone
    (f)  A1 A  B        left blank, right valid                 -> Rule 2: take right (B)
    (g)  B  A  A1       left valid, right blank                 -> Rule 3: take left (B)
    (h)  B1 A  B2       both neighbours valid                   -> Rule 4: (B1 + B2) / 2

(e) uses the two other blank pixels ``A1``, ``A2`` and (h) the two valid pixels ``B1``, ``B2``,
which is why the paper names them. All blank pixels are classified first and the rules are then
applied at once (a Jacobi step, not a left-to-right scan): with a sequential scan the left
neighbour of every middle pixel would already be filled and cases (e) and (f) could never occur,
so the paper's rules only make sense on the classification of the unfilled row. One pass thus
fills gaps of one and two pixels completely and shrinks longer gaps by one pixel at each end;
``fill_passes`` > 1 repeats the step (the paper does one). The paper's per-row count ``N_i`` of
blank pixels only lets it skip rows without any; the vectorised form needs no such shortcut.

Image convention: pixel ``(u, v)`` = (column, row); disparity ``d = u_left - u_right`` [px].
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Tuple

import cv2
import numpy as np

from terrain_perception.camera import PinholeCamera, StereoCamera
from terrain_perception.config import param

NORMALISATIONS = ('none', 'meanstd', 'minmax', 'equalize')
PREFILTERS = ('xsobel', 'normalized_response')


class StereoInputError(ValueError):
    """A stereo pair the pipeline refuses; ``key`` names the problem for counters."""

    def __init__(self, key: str, message: str) -> None:
        super().__init__(message)
        self.key = key


@dataclass(frozen=True)
class StereoConfig:
    """Parameters of the stereo pipeline (matching, post-processing, reprojection)."""

    num_disparities: int = param(96, 'disparity search range [px]; a multiple of 16; must '
                                 'cover the nearest ground (littledog 96, frog 112)', 16, 512)
    min_disparity: int = param(0, 'smallest disparity searched [px]', -128, 256)
    block_size_px: int = param(15, 'SAD window size m [px], odd', 5, 51)
    pad_left: bool = param(True, 'pad the images on the left by the search range so that '
                           'StereoBM also matches the first num_disparities columns')
    normalisation: str = param('meanstd', 'image normalisation before matching',
                               choices=NORMALISATIONS)
    prefilter: str = param('xsobel', 'StereoBM pre-filter', choices=PREFILTERS)
    prefilter_cap: int = param(31, 'StereoBM pre-filter clip value [grey levels]', 1, 63)
    texture_threshold: int = param(
        10, 'StereoBM: minimum window texture, 0 = off. A uniform region (a saturated sky) has '
        'no match, yet SAD returns one: FROG-I pitched 5 deg nose-up saw white sky in its top '
        '64 rows, and 11 % of its points landed 0.4-0.7 m above the stones (the loop mapped '
        'them at its camera\'s height and stalled on them); at 10 they are gone and rendered '
        'views with truth keep bad2 and coverage unchanged', 0, 10000)
    uniqueness_ratio: int = param(0, 'StereoBM: best-vs-second margin [%], 0 = off', 0, 100)
    speckle_window_px: int = param(0, 'StereoBM speckle filter: blobs of fewer pixels are '
                                   'dropped [px], 0 = off', 0, 10000)
    speckle_range_px: int = param(2, 'StereoBM speckle filter disparity range [px]', 0, 64)
    lr_check_px: int = param(1, 'StereoBM left-right consistency tolerance [px], -1 = off',
                             -1, 64)
    outlier_removal: bool = param(True, 'row-histogram outlier removal (Shao II-B-1)')
    outlier_min_count: int = param(
        8, 'a disparity value (rounded to 1 px) occurring fewer times than this in its row '
        'marks its pixels as mismatches [px]', 1, 10000)
    area_filling: bool = param(True, 'eight-relation row area filling (Shao II-B-2)')
    fill_passes: int = param(1, 'repetitions of the area-filling step (paper: 1)', 1, 64)
    fattening_radius_px: int = param(
        4, 'foreground-fattening guard: a pixel whose disparity exceeds the smallest valid '
        'disparity within this many pixels (square window) by more than fattening_jump_px is '
        'dropped; SAD windows straddling a depth edge give the background the foreground\'s '
        'disparity, points floating above the ground behind every rock (0 = off)', 0, 64)
    fattening_jump_px: float = param(
        3.0, 'see fattening_radius_px: the disparity step [px] taken for a depth edge (above '
        'the ground plane\'s own change across the window)', 0.0, 512.0)
    max_depth_m: float = param(3.0, 'points farther than this along z are dropped [m] '
                               '(paper 002 senses within 2 m)', 0.01, 1000.0)
    coarse_step_px: int = param(8, 'pixel stride of the coarse cloud in both directions [px]',
                                1, 256)
    min_contrast: float = param(2.0, 'images whose grey-level standard deviation is below '
                                'this are refused as blank [grey levels]', 0.0, 128.0)
    max_clipped_fraction: float = param(0.95, 'images with more than this share of pixels at '
                                        '0 or 255 are refused as black/saturated', 0.0, 1.0)

    def __post_init__(self) -> None:
        if self.num_disparities % 16:
            raise ValueError(f'StereoConfig.num_disparities must be a multiple of 16, '
                             f'got {self.num_disparities}')
        if self.block_size_px % 2 == 0:
            raise ValueError(f'StereoConfig.block_size_px must be odd, got {self.block_size_px}')


@dataclass(frozen=True)
class StereoFrame:
    """Result of :meth:`StereoPipeline.process`.

    Attributes:
        disparity: ``(H, W)`` float32 [px], NaN where invalid.
        points: ``(H, W, 3)`` float32 organized cloud in the left camera optical frame [m],
            NaN where invalid.
        coarse: organized coarse cloud ``(ceil(H/s), ceil(W/s), 3)`` float32 [m].
    """

    disparity: np.ndarray
    points: np.ndarray
    coarse: np.ndarray


# --------------------------------------------------------------------------- input checks

def to_gray(image: np.ndarray, channel_order: str = 'rgb') -> np.ndarray:
    """``(H, W)`` uint8 grey image from a uint8 mono ``(H, W)`` / ``(H, W, 1)`` or colour
    ``(H, W, 3)`` image whose channels are in ``channel_order`` ('rgb' or 'bgr').

    Raises:
        StereoInputError: ``bad_encoding`` for any other dtype or shape.
    """
    img = np.asarray(image)
    if img.dtype != np.uint8:
        raise StereoInputError('bad_encoding', f'stereo images must be 8-bit, got dtype '
                                               f'{img.dtype}')
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[..., 0]
    if img.ndim == 2:
        return np.ascontiguousarray(img)
    if img.ndim == 3 and img.shape[2] == 3:
        if channel_order not in ('rgb', 'bgr'):
            raise ValueError(f'channel_order must be rgb or bgr, got {channel_order!r}')
        code = cv2.COLOR_RGB2GRAY if channel_order == 'rgb' else cv2.COLOR_BGR2GRAY
        return cv2.cvtColor(np.ascontiguousarray(img), code)
    raise StereoInputError('bad_encoding', f'stereo images must be (H, W) or (H, W, 3), '
                                           f'got shape {img.shape}')


def check_pair(left: np.ndarray, right: np.ndarray, config: StereoConfig) -> None:
    """Refuse a grey pair that cannot give a meaningful disparity.

    Raises:
        StereoInputError: ``size_mismatch`` (different shapes), ``too_small`` (narrower than
            the search range plus a window), ``blank_image`` (no contrast, e.g. all black),
            ``saturated_image`` / ``black_image`` (mostly clipped pixels).
    """
    if left.shape != right.shape:
        raise StereoInputError('size_mismatch', f'left image is {left.shape}, right image is '
                                                f'{right.shape}')
    h, w = left.shape[:2]
    need = config.num_disparities + max(config.min_disparity, 0) + config.block_size_px
    if w < need or h < config.block_size_px:
        raise StereoInputError('too_small', f'image {w}x{h} px is too small for '
                                            f'{config.num_disparities} disparities and a '
                                            f'{config.block_size_px} px window')
    for side, img in (('left', left), ('right', right)):
        # An 8x subsample is plenty to decide whether an image is blank or clipped.
        sub = img[::8, ::8]
        n = sub.size
        black = np.count_nonzero(sub == 0) / n
        white = np.count_nonzero(sub == 255) / n
        if white > config.max_clipped_fraction:
            raise StereoInputError('saturated_image', f'{side} image is saturated: '
                                                      f'{100 * white:.0f}% of pixels at 255')
        if black > config.max_clipped_fraction:
            raise StereoInputError('black_image', f'{side} image is black: '
                                                  f'{100 * black:.0f}% of pixels at 0')
        std = float(sub.std())
        if std < config.min_contrast:
            raise StereoInputError('blank_image', f'{side} image has no contrast (grey-level '
                                                  f'std {std:.2f} < {config.min_contrast})')


# --------------------------------------------------------------------------- pipeline steps

def normalise(image: np.ndarray, method: str = 'meanstd') -> np.ndarray:
    """Normalised uint8 grey image (``method`` in ``NORMALISATIONS``)."""
    if method == 'none':
        return image
    if method == 'meanstd':
        mean, std = cv2.meanStdDev(image)
        alpha = 48.0 / max(float(std[0, 0]), 1e-3)
        beta = 128.0 - alpha * float(mean[0, 0])
        # addWeighted saturates to [0, 255], unlike a numpy cast.
        return cv2.addWeighted(image, alpha, image, 0.0, beta, dtype=cv2.CV_8U)
    if method == 'minmax':
        return cv2.normalize(image, None, 0, 255, cv2.NORM_MINMAX, dtype=cv2.CV_8U)
    if method == 'equalize':
        return cv2.equalizeHist(image)
    raise ValueError(f'unknown normalisation {method!r} (known: {", ".join(NORMALISATIONS)})')


class StereoMatcher:
    """SAD block matching (Shao eq. 1) by ``cv2.StereoBM`` configured from a StereoConfig."""

    def __init__(self, config: StereoConfig) -> None:
        self.config = config
        bm = cv2.StereoBM.create(config.num_disparities, config.block_size_px)
        bm.setMinDisparity(config.min_disparity)
        bm.setPreFilterType(cv2.STEREO_BM_PREFILTER_XSOBEL if config.prefilter == 'xsobel'
                            else cv2.STEREO_BM_PREFILTER_NORMALIZED_RESPONSE)
        bm.setPreFilterCap(config.prefilter_cap)
        bm.setTextureThreshold(config.texture_threshold)
        bm.setUniquenessRatio(config.uniqueness_ratio)
        bm.setSpeckleWindowSize(config.speckle_window_px)
        bm.setSpeckleRange(config.speckle_range_px * 16)
        bm.setDisp12MaxDiff(config.lr_check_px)
        self._bm = bm
        self.pad_px = config.num_disparities + max(config.min_disparity, 0) \
            if config.pad_left else 0

    def match_fixed(self, left: np.ndarray, right: np.ndarray) -> np.ndarray:
        """StereoBM's int16 output (disparity x 16; ``(min_disparity - 1) * 16`` = none).

        StereoBM leaves the first ``min_disparity + num_disparities`` columns unmatched. With
        ``pad_left`` both images get that many constant columns on the left, so a pixel in
        that band is matched over the disparities whose right-image column exists (the
        padding's flat cost never beats a textured true match); the padding is cropped again.
        """
        p = self.pad_px
        if p == 0:
            return self._bm.compute(left, right)
        fill = float(np.mean(left[:, :8]))
        lp = cv2.copyMakeBorder(left, 0, 0, p, 0, cv2.BORDER_CONSTANT, value=fill)
        rp = cv2.copyMakeBorder(right, 0, 0, p, 0, cv2.BORDER_CONSTANT, value=fill)
        return self._bm.compute(lp, rp)[:, p:]

    def match_checked(self, left: np.ndarray, right: np.ndarray
                      ) -> Tuple[np.ndarray, np.ndarray]:
        """``(disp16, invalid)``: StereoBM's fixed-point output and the mask of pixels without
        a disparity, including those whose match would lie left of the right image (``d > u``:
        geometrically impossible, only produced in the padding)."""
        disp16 = self.match_fixed(left, right)
        invalid = disp16 < self.config.min_disparity * 16
        if self.pad_px:
            invalid |= disp16 > self._columns16(disp16.shape[1])
        return disp16, invalid

    def match(self, left: np.ndarray, right: np.ndarray) -> np.ndarray:
        """Disparity ``(H, W)`` float32 [px] of two grey uint8 images, NaN where none (see
        :meth:`match_checked`)."""
        return fixed_to_float(*self.match_checked(left, right))

    def _columns16(self, width: int) -> np.ndarray:
        cols = getattr(self, '_cols16', None)
        if cols is None or cols.shape[1] != width:
            dtype = np.int16 if width < 2048 else np.int32
            cols = self._cols16 = (np.arange(width) * 16).astype(dtype)[None, :]
        return cols


def fixed_to_float(disp16: np.ndarray, invalid: 'np.ndarray | int' = 0) -> np.ndarray:
    """OpenCV's 4-bit fixed-point disparity to float32 [px] with NaN for 'no match'.

    ``invalid`` is a boolean mask of pixels without a disparity, or the matcher's
    ``min_disparity`` (then ``disp16 < 16 * min_disparity`` is invalid, OpenCV's convention).
    """
    if not isinstance(invalid, np.ndarray):
        invalid = disp16 < int(invalid) * 16
    d = disp16.astype(np.float32)
    d *= np.float32(1.0 / 16.0)
    d[invalid] = np.nan
    return d


def remove_row_outliers(disparity: np.ndarray, min_count: int,
                        min_disparity: Optional[int] = None,
                        num_disparities: Optional[int] = None) -> np.ndarray:
    """Shao II-B-1: blank the pixels whose (rounded) disparity is rare in their row.

    Args:
        disparity: ``(H, W)`` float [px], NaN = blank.
        min_count: a value occurring fewer than this many times in its row is a mismatch.
        min_disparity, num_disparities: the value range (taken from the data if omitted).

    Returns:
        A float32 copy with the mismatches set to NaN.
    """
    d = np.asarray(disparity, dtype=np.float32)
    if d.ndim != 2:
        raise ValueError(f'disparity must be (H, W), got shape {d.shape}')
    if min_disparity is None or num_disparities is None:
        if not np.isfinite(d).any():
            return d.copy()
        lo = int(np.floor(np.nanmin(d)))
        n_values = int(np.floor(np.nanmax(d) + 0.5)) - lo + 1
    else:
        lo, n_values = int(min_disparity), int(num_disparities) + 1
    # Bin 0 collects the blanks, bins 1..n_values the values rounded half up:
    # bin = floor(d + 0.5) - lo + 1, computed as a truncating cast of a positive float.
    b = d + np.float32(1.5 - lo)
    np.nan_to_num(b, copy=False, nan=0.0)
    np.clip(b, 0.0, n_values + 0.5, out=b)
    out = d.copy()
    out[_rare_in_row(b.astype(np.int32), n_values, min_count)] = np.nan
    return out


def row_outliers_fixed(disp16: np.ndarray, invalid: np.ndarray, min_count: int,
                       min_disparity: int, num_disparities: int) -> np.ndarray:
    """:func:`remove_row_outliers` on StereoBM's fixed-point output (same rounding, same
    result; the pipeline's fast path). Returns the boolean mask of the rare pixels."""
    # bin = floor(d + 0.5) - lo + 1 = (disp16 + 8 + 16 (1 - lo)) >> 4 in integers; StereoBM's
    # 'no match' value 16 (lo - 1) lands in bin 0, the other blanks are put there explicitly.
    key = disp16 + np.int16(8 + 16 * (1 - min_disparity))
    key >>= 4
    key *= np.logical_not(invalid).view(np.uint8)
    return _rare_in_row(key, num_disparities + 1, min_count)


def _rare_in_row(bins: np.ndarray, n_values: int, min_count: int) -> np.ndarray:
    """Mask of the pixels whose bin (1..n_values; 0 = blank) holds fewer than ``min_count``
    pixels of the same row: one bincount over (row, bin) pairs."""
    h = bins.shape[0]
    nb = n_values + 1
    # intp keys: bincount and take would convert narrower ones anyway.
    key = np.add(bins, (np.arange(h, dtype=np.intp) * nb)[:, None], dtype=np.intp)
    rare = np.bincount(key.ravel(), minlength=h * nb) < min_count
    rare[::nb] = False                         # the blanks are not outliers
    return np.take(rare, key)


_NEIGHBOURS = np.array([[1.0, 0.0, 1.0]], dtype=np.float32)


def fill_rows(disparity: np.ndarray, passes: int = 1) -> np.ndarray:
    """Shao II-B-2: area filling of blank (NaN) pixels by the eight relations of Fig. 3.

    See the module docstring for the cases. Rules 1-4 say together: a blank pixel takes the
    mean of those of its two row neighbours that are valid (both: Rule 4; only the right one,
    including the row's first pixel: Rule 2; only the left one, including the last pixel:
    Rule 3; none: Rule 1, left alone). That is how it is computed, with two 1x3 filters over the
    row as it was at the start of the pass (sum of valid neighbours / their count).

    Returns:
        A float32 copy of ``disparity`` ``(H, W)`` [px] with the filled pixels set.
    """
    d = np.array(disparity, dtype=np.float32)
    if d.ndim != 2:
        raise ValueError(f'disparity must be (H, W), got shape {d.shape}')
    for _ in range(int(passes)):
        blank = np.isnan(d)
        valid = (~blank).astype(np.float32)
        # Zero outside the row = no neighbour there (cases a-d at the row's ends).
        total = cv2.filter2D(np.where(blank, np.float32(0.0), d), -1, _NEIGHBOURS,
                             borderType=cv2.BORDER_CONSTANT)
        count = cv2.filter2D(valid, -1, _NEIGHBOURS, borderType=cv2.BORDER_CONSTANT)
        with np.errstate(invalid='ignore', divide='ignore'):
            mean = total / count                # 0 / 0 = NaN: Rule 1
        d = np.where(blank, mean, d)
    return d


def fill_first_pass_fixed(disp16: np.ndarray, invalid: np.ndarray) -> np.ndarray:
    """One pass of :func:`fill_rows` on StereoBM's fixed-point output, returning float32
    disparity [px] (NaN = blank): ``fill_rows(fixed_to_float(disp16, invalid))`` with fewer
    passes over the image (the pipeline's fast path; the sums are exact in int16)."""
    blank = invalid.view(np.uint8)
    valid = blank ^ np.uint8(1)
    zeroed = disp16 * valid                         # blanks -> 0 (masks as 0/1 factors:
    total = _row_neighbour_sum(zeroed)              # far cheaper than np.where)
    count = _row_neighbour_sum(valid)
    num = zeroed + total * blank                    # valid: own value; blank: neighbour sum
    den = (count * blank + valid) * np.uint8(16)    # valid: 16; blank: 16 x neighbours
    with np.errstate(invalid='ignore', divide='ignore'):
        return np.divide(num, den, dtype=np.float32)   # 0 / 0 = NaN: Rule 1


def _row_neighbour_sum(a: np.ndarray) -> np.ndarray:
    """``a[v, u - 1] + a[v, u + 1]`` with zero outside the row."""
    out = np.zeros_like(a)
    out[:, 1:] = a[:, :-1]
    out[:, :-1] += a[:, 1:]
    return out


def disparity_to_points(disparity: np.ndarray, stereo: StereoCamera,
                        max_depth_m: float = np.inf,
                        rays: Optional[np.ndarray] = None) -> np.ndarray:
    """Organized cloud ``(H, W, 3)`` float32 in the left camera optical frame [m].

    ``Z = fx * baseline / d``, ``X = (u - cx) Z / fx``, ``Y = (v - cy) Z / fy``. Pixels with
    NaN or non-positive disparity, or farther than ``max_depth_m``, are NaN.

    Args:
        disparity: ``(H, W)`` [px] matching ``stereo.left``'s size.
        stereo: the rectified pair.
        max_depth_m: range cut-off along z [m].
        rays: optional cached :func:`ray_planes` of ``stereo.left`` (saves time per frame).
    """
    d = np.asarray(disparity, dtype=np.float32)
    cam = stereo.left
    if d.shape != (cam.height, cam.width):
        raise ValueError(f'disparity is {d.shape}, camera is {cam.height}x{cam.width}')
    if rays is None:
        rays = ray_planes(cam)
    fb = np.float32(cam.fx * stereo.baseline_m)
    with np.errstate(divide='ignore', invalid='ignore'):
        z = fb / d
    # z <= max_depth  <=>  d >= fx B / max_depth (> 0); NaN stays NaN.
    np.copyto(z, np.float32(np.nan), where=d < np.float32(max(fb / max_depth_m, 1e-6)))
    # Single-channel OpenCV products and one merge: ~3x faster than numpy broadcasting.
    return cv2.merge([cv2.multiply(rays[0], z), cv2.multiply(rays[1], z), z])


def ray_planes(camera: PinholeCamera) -> np.ndarray:
    """``(2, H, W)`` float32: ``(u - cx) / fx`` and ``(v - cy) / fy`` per pixel (X/Z, Y/Z)."""
    r = camera.rays()
    return np.ascontiguousarray(np.moveaxis(r[..., :2], -1, 0), dtype=np.float32)


def floor_disparity_range(stereo: StereoCamera, T_floor_cam: np.ndarray,
                          margin: float = 1.25) -> int:
    """The ``num_disparities`` [px] a camera at pose ``T_floor_cam`` (4x4, optical frame in a
    frame whose z = 0 plane is the floor, z up) needs: the disparity of the floor at the bottom
    image row, the nearest ground it sees, times ``margin`` (obstacles nearer than the floor,
    body motion), rounded up to a multiple of 16. Nearer than the search range reaches, SAD
    matches the wrong pixel instead of leaving it empty: FROG-I's camera, 0.65 m up with a
    12 cm baseline, needs 112 px (the loop ran it with LittleDog's 96, short of a stone top near
    the bottom rows). Raises ValueError when the bottom row does not look down at the floor."""
    cam = stereo.left
    T = np.asarray(T_floor_cam, dtype=np.float64)
    ray = T[:3, :3] @ np.array([0.0, (cam.height - 1 - cam.cy) / cam.fy, 1.0])
    if ray[2] >= 0 or T[2, 3] <= 0:
        raise ValueError('the camera does not see the floor at its bottom image row')
    if not np.isfinite(margin) or margin < 1.0:
        raise ValueError(f'disparity margin must be >= 1, got {margin}')
    z = T[2, 3] / -ray[2]           # z-depth of the floor hit (the ray has optical z = 1)
    d = cam.fx * stereo.baseline_m / z * margin
    return int(np.ceil(d / 16.0) * 16)


def coarse_subsample(points: np.ndarray, step: int) -> np.ndarray:
    """Uniform subsample of an organized cloud: every ``step``-th pixel in rows and columns,
    starting half a step in (paper 000, section II: the coarse model for ICP alignment).

    Args:
        points: ``(H, W, 3)`` organized cloud [m], NaN = invalid.
        step: stride [px] >= 1.

    Returns:
        ``(ceil((H - step//2)/step), ceil((W - step//2)/step), 3)`` float32, still organized
        and NaN where the sampled pixel is invalid.
    """
    pts = np.asarray(points)
    if pts.ndim != 3 or pts.shape[2] != 3:
        raise ValueError(f'points must be an organized (H, W, 3) cloud, got shape {pts.shape}')
    step = int(step)
    if step < 1:
        raise ValueError(f'coarse step must be >= 1 px, got {step}')
    o = step // 2
    return np.ascontiguousarray(pts[o::step, o::step], dtype=np.float32)


class StereoPipeline:
    """Normalise, match, post-process and reproject one rectified pair.

    Args:
        config: the pipeline parameters.
        stereo: the rectified camera pair (left intrinsics + baseline).
    """

    def __init__(self, config: StereoConfig, stereo: StereoCamera) -> None:
        self.config = config
        self.stereo = stereo
        self.matcher = StereoMatcher(config)
        self._rays = ray_planes(stereo.left)

    def prepare(self, left: np.ndarray, right: np.ndarray,
                channel_order: str = 'rgb') -> Tuple[np.ndarray, np.ndarray]:
        """Grey, checked, normalised pair; raises :class:`StereoInputError` on a bad pair."""
        gl, gr = to_gray(left, channel_order), to_gray(right, channel_order)
        check_pair(gl, gr, self.config)
        cam = self.stereo.left
        if gl.shape != (cam.height, cam.width):
            raise StereoInputError('size_mismatch', f'images are {gl.shape[1]}x{gl.shape[0]}, '
                                                    f'camera model is {cam.width}x{cam.height}')
        method = self.config.normalisation
        return normalise(gl, method), normalise(gr, method)

    def disparity(self, left: np.ndarray, right: np.ndarray,
                  channel_order: str = 'rgb') -> np.ndarray:
        """Post-processed disparity ``(H, W)`` float32 [px], NaN where invalid."""
        c = self.config
        nl, nr = self.prepare(left, right, channel_order)
        # Outlier removal on the fixed-point output (the same result as postprocess() on the
        # float disparity, with fewer passes over the image).
        disp16, invalid = self.matcher.match_checked(nl, nr)
        if c.outlier_removal:
            invalid |= row_outliers_fixed(disp16, invalid, c.outlier_min_count,
                                          c.min_disparity, c.num_disparities)
        if not c.area_filling:
            d = fixed_to_float(disp16, invalid)
        else:
            d = fill_first_pass_fixed(disp16, invalid)
            if c.fill_passes > 1:
                d = fill_rows(d, c.fill_passes - 1)
        return drop_fattened(d, c.fattening_radius_px, c.fattening_jump_px)

    def process(self, left: np.ndarray, right: np.ndarray,
                channel_order: str = 'rgb') -> StereoFrame:
        """Disparity, organized fine cloud and coarse cloud of one pair."""
        d = self.disparity(left, right, channel_order)
        pts = disparity_to_points(d, self.stereo, self.config.max_depth_m, self._rays)
        return StereoFrame(d, pts, coarse_subsample(pts, self.config.coarse_step_px))


def postprocess(disparity: np.ndarray, config: StereoConfig) -> np.ndarray:
    """The switchable post-processing of a float disparity map (outliers, filling, then the
    fattening guard)."""
    d = disparity
    if config.outlier_removal:
        d = remove_row_outliers(d, config.outlier_min_count, config.min_disparity,
                                config.num_disparities)
    if config.area_filling:
        d = fill_rows(d, config.fill_passes)
    return drop_fattened(d, config.fattening_radius_px, config.fattening_jump_px)


def drop_fattened(disparity: np.ndarray, radius_px: int, jump_px: float) -> np.ndarray:
    """Foreground-fattening guard (ours; not in Shao et al.): NaN where a pixel's disparity
    exceeds the smallest valid disparity within ``radius_px`` (a square window) by more than
    ``jump_px``.

    A SAD window that straddles a depth edge is dominated by the nearer surface's texture, so
    background pixels up to half a window from the edge take the foreground's disparity: their
    points float above the ground behind every rock, at the rock's range, and a height map
    fuses them as a ledge that is not there. This drops both sides of strong disparity steps
    within the radius (some true foreground goes too). NaN pixels do not count as small.
    ``radius_px`` 0 returns ``disparity`` unchanged.
    """
    r = int(radius_px)
    if r <= 0:
        return disparity
    d = np.asarray(disparity, dtype=np.float32)
    if d.ndim != 2:
        raise ValueError(f'disparity must be (H, W), got shape {d.shape}')
    valid = np.isfinite(d)
    low = cv2.erode(np.where(valid, d, np.float32(np.inf)),
                    cv2.getStructuringElement(cv2.MORPH_RECT, (2 * r + 1, 2 * r + 1)),
                    borderType=cv2.BORDER_REPLICATE)
    out = np.array(d, dtype=np.float32)
    with np.errstate(invalid='ignore'):
        out[valid & (d - low > np.float32(jump_px))] = np.nan
    return out
