"""Speed-ups give what the code they replaced gave (test/speedup_reference.py), on realistic
inputs: stereo clouds of simulator-rendered pairs (LittleDog on rocks-6cm, as in the demo),
plus the edge cases (NaN, inf, float64 and integer input, few valid points)."""

import numpy as np
import pytest

import speedup_reference as ref
import terrain_perception.fill as fillmod
from terrain_perception.bench.stereo import _body_pose, _course_scene, render_pair
from terrain_perception.fill import CONTACT, TerrainFiller
from terrain_perception.grid import COST, ELEVATION
from terrain_perception.ground_plane import GroundPlaneConfig, fit_ground_plane
from terrain_perception.robot_model import load_robot_model
from terrain_perception.stereo import StereoConfig, StereoPipeline, floor_disparity_range


@pytest.fixture(scope='module')
def littledog_views():
    """Two rendered LittleDog views of rocks-6cm (pybullet, as the simulator bridge renders):
    ``[(stereo, config, left, right, frame)]`` with the pipeline's frame of each pair."""
    rm = load_robot_model('littledog')
    views = []
    for seed in (3, 4):
        course, padded = _course_scene('rocks-6cm', seed, 0.005)
        x0 = float(padded.metadata['rough_extent_xy'][0]) - 0.25
        T = _body_pose(np.random.default_rng(seed), x0, rm.standing_height_m) \
            @ rm.T_base_camera
        cfg = StereoConfig(num_disparities=floor_disparity_range(rm.stereo, T))
        left, right, _ = render_pair('pybullet', course, padded, rm.stereo, T, seed)
        frame = StereoPipeline(cfg, rm.stereo).process(left, right)
        views.append((rm.stereo, cfg, left, right, frame))
    return views


def assert_same_plane(a, b):
    np.testing.assert_array_equal(a.normal, b.normal)
    assert (a.d, a.pitch_rad, a.height_m, a.inlier_ratio, a.inliers) == \
        (b.d, b.pitch_rad, b.height_m, b.inlier_ratio, b.inliers)


def plane_or_error(fit, pts, cfg):
    try:
        return fit(pts, cfg)
    except ValueError as exc:
        return str(exc)


@pytest.mark.parametrize('penalty', [2.0, 0.0])
def test_ground_plane_equals_the_previous_code_on_rendered_clouds(littledog_views, penalty):
    cfg = GroundPlaneConfig(below_penalty=penalty)
    for _, _, _, _, frame in littledog_views:
        pts = frame.points                                   # float32 (H, W, 3), NaN holes
        assert pts.dtype == np.float32 and np.isnan(pts).any()
        noisy = pts.copy()
        rng = np.random.default_rng(0)
        bad = rng.random(noisy.shape[:2]) < 0.02
        noisy[bad, rng.integers(0, 3, int(bad.sum()))] = \
            rng.choice([np.inf, -np.inf, np.nan], int(bad.sum()))
        for cloud in (pts, noisy, noisy.astype(np.float64), noisy.reshape(-1, 3)):
            assert_same_plane(fit_ground_plane(cloud, cfg), ref.fit_ground_plane(cloud, cfg))
        # fewer valid points than the sample size: every valid point is used, in order
        few = noisy.reshape(-1, 3)[::100]
        assert_same_plane(fit_ground_plane(few, cfg), ref.fit_ground_plane(few, cfg))


def test_ground_plane_equals_the_previous_code_on_edge_cases():
    cfg = GroundPlaneConfig(sample_points=50, iterations=20)
    rng = np.random.default_rng(1)
    ints = rng.integers(-5, 5, (200, 3))
    ints[:, 2] = 0
    cases = [ints, ints.tolist(), np.array([[0, 0, 1.0], [np.nan, 0, 0], [1, 1, 1]]),
             np.array([[0, 0, 1.0], [1, 0, 1.0], [2, 0, 1.0], [np.inf, 1, 1]]),
             rng.uniform(-1, 1, (300, 3)).astype(np.float32)]
    for pts in cases:
        a, b = plane_or_error(fit_ground_plane, pts, cfg), \
            plane_or_error(ref.fit_ground_plane, pts, cfg)
        if isinstance(b, str):
            assert a == b
        else:
            assert_same_plane(a, b)


# --- terrain fill ----------------------------------------------------------------------------
@pytest.fixture(scope='module')
def walk():
    """LittleDog walking over rocks-6cm with a range sensor: the 3 m x 1 cm moving fine maps
    and capture poses of the fill benchmark (12 captures), stance feet under the body."""
    from terrain_perception.bench.fill import walk_maps
    truth, seq = walk_maps(12)
    rm = load_robot_model('littledog')
    T_cam_base = np.linalg.inv(rm.T_base_camera)
    out = []
    for grid, T in seq:
        base = (T @ T_cam_base)[:3, 3]
        xy = base[:2] + np.array([[0.1, 0.07], [0.1, -0.07], [-0.1, 0.07], [-0.1, -0.07]])
        ij = truth.world_to_index(xy)
        z = np.asarray(truth[ELEVATION], np.float64)[ij[:, 0], ij[:, 1]]
        out.append((grid, T, np.c_[xy, z]))
    return out


def fill_library():
    from scipy import ndimage
    rng = np.random.default_rng(5)
    return [0.06 * ndimage.gaussian_filter(rng.normal(size=(100, 100)), 2.0) for _ in range(3)]


def run_filler(walk, feet_every=1):
    filler = TerrainFiller(fill_library(), 0.01)
    outs, poses = [], []
    for k, (grid, T, feet) in enumerate(walk):
        poses.append(T)
        out = filler.update(grid, np.array(poses), feet if k % feet_every == 0 else None)
        outs.append((dict(out.layers), filler.last_region, filler.last_refilled))
    return outs


def test_fill_updates_equal_the_previous_code_on_a_walk(walk, monkeypatch):
    new = run_filler(walk, feet_every=2)
    with monkeypatch.context() as m:
        m.setattr(fillmod, '_contact_support', ref.contact_support)
        m.setattr(fillmod, '_dilate', ref.dilate)
        old = run_filler(walk, feet_every=2)
    assert sum(o[2] for o in old) > 1000                    # cells refilled over the walk
    assert any(o[0][CONTACT].any() for o in old)            # the stance plane was used
    for (a, ra, na), (b, rb, nb) in zip(new, old):
        assert (ra, na) == (rb, nb)
        assert a.keys() == b.keys()
        for name in a:
            assert a[name].dtype == b[name].dtype
            np.testing.assert_array_equal(a[name], b[name], err_msg=name)   # NaN == NaN


def test_contact_support_equals_the_previous_code(walk):
    grid = walk[5][0]
    feet = walk[5][2]
    rng = np.random.default_rng(2)
    cases = [feet, feet + [[1.4, 0, 0]], feet + [[5.0, 0, 0]],      # partly, wholly off the grid
             feet + rng.normal(0, 0.3, feet.shape), feet[:3]]
    for f in cases:
        for radius in (0.0, 0.004, 0.06, 0.5, 4.0):
            mask, z = fillmod._contact_support(grid, f, radius)
            mask0, z0 = ref.contact_support(grid, f, radius)
            np.testing.assert_array_equal(mask, mask0)
            np.testing.assert_array_equal(z[mask], z0[mask])


def test_dilate_equals_binary_dilation():
    rng = np.random.default_rng(3)
    for shape, p in (((300, 300), 0.001), ((50, 70), 0.02), ((1, 9), 0.3), ((40, 40), 0.0)):
        mask = rng.random(shape) < p
        mask[0, -1] = True                                  # a corner: the border is False
        for m in (1, 3, 10) + ((80,) if mask.size < 5000 else ()):     # 80: beyond the grid
            np.testing.assert_array_equal(fillmod._dilate(mask, m), ref.dilate(mask, m))
        np.testing.assert_array_equal(fillmod._dilate(mask.T, 2), ref.dilate(mask.T, 2))


def test_fill_node_pose_conversion_equals_the_previous_code(ros_context, walk):
    from geometry_msgs.msg import Pose

    from terrain_fill_node.node import TerrainFillNode
    from terrain_ros.conversions import matrix_to_pose
    node = TerrainFillNode(context=ros_context)
    try:
        poses = [matrix_to_pose(T) for _, T, _ in walk]
        signed_zero = Pose()
        signed_zero.orientation.w = 1.0
        negative_zero = Pose()
        negative_zero.position.x = -0.0
        negative_zero.orientation.w = 1.0
        negative_zero.orientation.z = -0.0
        # growing lists as the mapper publishes them, a dropped pose, zeros of either sign
        for msg in (poses[:3], poses[:8], poses[2:12], [signed_zero] + poses,
                    [negative_zero] + poses, []):
            got = node._pose_matrices(msg)
            want = ref.pose_matrices(msg)
            assert got.shape == want.shape
            assert got.tobytes() == want.tobytes()          # -0.0 kept apart from 0.0
        bad = Pose()
        bad.orientation.w = 0.0                             # zero quaternion
        for msg in ([bad], poses[:4] + [bad]):
            with pytest.raises(ValueError, match='quaternion'):
                ref.pose_matrices(msg)
            with pytest.raises(ValueError, match='quaternion'):
                node._pose_matrices(msg)
        nan = matrix_to_pose(walk[0][1])
        nan.position.y = float('nan')
        with pytest.raises(ValueError, match='position'):
            node._pose_matrices(poses[:2] + [nan])
        assert node._pose_matrices(poses[:2]).tobytes() == ref.pose_matrices(poses[:2]).tobytes()
    finally:
        node.destroy_node()


def test_fill_kernel_equals_the_numpy_choice_on_a_walk(walk):
    """The compiled fill (TERRAIN_FILL_NUMBA, the default: _fill_kernels.choose_block and
    viewshed_bounds) against the numpy code it replaces: the filler's layers over the whole
    walk, bitwise (the layers are float32; the float64 fills themselves: the next test),
    except the cost: the filler computes it from the float64 heights, which agree only
    within rounding, so a cost can differ in its last float32 bits (on an AVX-512 EPYC, 625
    of 90,000 cells by up to 1.5e-8, cancellation near zero included; none on the Xeon the
    test was written on)."""
    try:
        fillmod.use_compiled_kernels(True)
        new = run_filler(walk, feet_every=3)
        fillmod.use_compiled_kernels(False)
        old = run_filler(walk, feet_every=3)
    finally:
        fillmod.use_compiled_kernels(None)
    assert sum(o[2] for o in old) > 1000
    for (a, ra, na), (b, rb, nb) in zip(new, old):
        assert (ra, na) == (rb, nb)
        for name in a:
            if name == COST:
                np.testing.assert_array_equal(np.isnan(a[name]), np.isnan(b[name]))
                np.testing.assert_allclose(a[name], b[name], rtol=1e-6, atol=1e-7,
                                           err_msg=name)
            else:
                np.testing.assert_array_equal(a[name], b[name], err_msg=name)



def test_viewshed_kernel_equals_the_numpy_bounds(walk):
    """The compiled viewshed (bounds_from_captures' rays) against its numpy code: the walk's
    maps with each capture and with all captures so far, with and without the view cone, with
    a tolerance, a camera over the map's edge and one outside it: bitwise."""
    from terrain_perception.fill import bounds_from_captures
    cases = 0
    for k, (grid, T, _) in enumerate(walk):
        h = np.asarray(grid[ELEVATION], np.float64)
        poses = np.array([t for _, t, _ in walk[:k + 1]])
        cams, axes = poses[:, :3, 3], poses[:, :3, 2]
        edge = np.array([[grid.origin_xy[0], grid.origin_xy[1] + 0.5, 0.3],
                         [grid.origin_xy[0] - 0.4, grid.origin_xy[1] + 1.0, 0.25]])
        for cam, ax, kw in ((cams[-1:], axes[-1:], {}), (cams, axes, dict(tol_m=0.003)),
                            (cams[-1:], None, {}),
                            (np.r_[cams[-1:], edge], np.r_[axes[-1:], [[1, 0, -1]] * 2],
                             dict(angular_step_rad=0.01))):
            fov = np.radians(fillmod.RayConfig().fov_half_angle_deg)
            args = (h, grid.resolution_m, grid.origin_xy, cam, 1.0)
            kwargs = dict(kw, camera_axes=ax, fov_half_angle_rad=fov if ax is not None
                          else np.pi)
            try:
                fillmod.use_compiled_kernels(True)
                new = bounds_from_captures(*args, **kwargs)
                fillmod.use_compiled_kernels(False)
                old = bounds_from_captures(*args, **kwargs)
            finally:
                fillmod.use_compiled_kernels(None)
            assert new.tobytes() == old.tobytes()
            cases += int(np.isfinite(old).sum() > 100)
    assert cases >= 30


def test_compiled_fill_chooses_the_numpy_samples_on_a_walk(walk):
    """fill_terrain with the compiled choice (choose_block: one pass over each window's known
    cells, straight from the patch bank) against numpy's _choose (BLAS sums of an expansion):
    the arithmetic differs, so the float64 heights agree within rounding, and on the walk's
    maps under their captures' bounds every filled cell takes the same library sample."""
    from terrain_perception.fill import PatchLibrary, bounds_from_captures, fill_terrain
    lib = PatchLibrary(fill_library(), 5)
    filled = bounded = 0
    for k, (grid, T, _) in enumerate(walk):
        h = np.asarray(grid[ELEVATION], np.float64)
        poses = np.array([t for _, t, _ in walk[:k + 1]])
        ub = bounds_from_captures(h, grid.resolution_m, grid.origin_xy, poses[:, :3, 3], 1.0,
                                  camera_axes=poses[:, :3, 2],
                                  fov_half_angle_rad=np.radians(40.0))
        mask = np.zeros(h.shape, bool)
        mask[60:240, 60:240] = True
        try:
            fillmod.use_compiled_kernels(True)
            new = fill_terrain(h, ub, lib, fill_mask=mask)
            fillmod.use_compiled_kernels(False)
            old = fill_terrain(h, ub, lib, fill_mask=mask)
        finally:
            fillmod.use_compiled_kernels(None)
        np.testing.assert_array_equal(new.filled, old.filled)
        assert new.rounds == old.rounds
        f = old.filled
        np.testing.assert_array_equal(new.choice[f], old.choice[f])
        np.testing.assert_allclose(new.heights[f], old.heights[f], rtol=0, atol=1e-12)
        filled += int(f.sum())
        bounded += int((f & np.isfinite(ub)).sum())
    assert filled > 20000 and bounded > 2000


def test_select_round_kernel_equals_the_numpy_rounds():
    """The compiled round selection against the OpenCV box filter and dilation: every round
    of whole fills (the selected cells then known, the box carried from round to round as
    fill_terrain does), with and without a todo mask, holes at the map's edges, windows 3-7:
    the same cells in the same order."""
    rng = np.random.default_rng(6)
    rounds = 0
    for shape, w, p in (((60, 80), 5, 0.5), ((300, 300), 5, 0.02), ((40, 40), 3, 0.7),
                        ((50, 30), 7, 0.3)):
        from scipy import ndimage
        holes = ndimage.binary_dilation(rng.random(shape) < p * 0.05, iterations=3)
        holes[:, :4] |= rng.random((shape[0], 4)) < 0.5                  # at the edge
        rank = rng.permutation(holes.size).reshape(shape)
        for todo in (None, rng.random(shape) < 0.7):
            known_new, known_old = ~holes, ~holes.copy()
            box = np.array([0, shape[0], 0, shape[1]], np.int64)
            while True:
                try:
                    fillmod.use_compiled_kernels(True)
                    new = fillmod.select_round(known_new, rank, w, todo, box)
                    fillmod.use_compiled_kernels(False)
                    old = fillmod.select_round(known_old, rank, w, todo)
                finally:
                    fillmod.use_compiled_kernels(None)
                np.testing.assert_array_equal(new, old)
                if old.size == 0:
                    break
                rounds += 1
                known_new.ravel()[new] = True
                known_old.ravel()[old] = True
            want = ~known_old if todo is None else todo & ~known_old
            assert not want.any() or todo is not None          # only masked, contextless left
    assert rounds > 100


def _adversarial_block():
    """``(W, A, B, C, Abar)`` of 40 cells x 30 samples x 5 x 5 windows that make the choice
    step's corner cases: coarse patch values (ties in s), a cell whose samples are all equal,
    unbounded cells (0-9), a NaN bound (10), all bounds NaN (11), a -inf bound (12), nothing
    feasible (13)."""
    rng = np.random.default_rng(4)
    S, n, q = 40, 30, 25
    W = fillmod.gaussian_weights(5, 1.5).ravel()
    A = rng.normal(0, 0.01, (S, q))
    B = rng.random((S, q)) < 0.6
    B[:, 0] = True
    C = np.round(rng.normal(0, 0.01, (S, n, q)), 3)        # coarse values: ties in s
    C[5] = C[5, :1]                                         # one cell: all samples equal
    Abar = np.where(rng.random((S, q)) < 0.3, rng.normal(0.01, 0.01, (S, q)), np.inf)
    Abar[:10] = np.inf                                      # unbounded cells
    Abar[10, 3] = np.nan
    Abar[11, :] = np.nan
    Abar[12, 7] = -np.inf
    Abar[13] = -1.0                                         # nothing feasible
    return W, A, B, C, Abar


def _block_inputs(A, B, Abar, C):
    """A block of _choose's inputs laid out as choose_block reads them (one window per cell
    in a flat 'padded map', one bank row per sample)."""
    S, n, q = C.shape
    return (np.ascontiguousarray(np.where(B, A, 0.0)).ravel(), np.ascontiguousarray(B).ravel(),
            np.ascontiguousarray(Abar).ravel(), np.arange(S, dtype=np.int64) * q,
            np.arange(q, dtype=np.int64), np.ascontiguousarray(C).reshape(S * n, q),
            np.arange(S * n, dtype=np.int64).reshape(S, n))


def test_choose_block_kernel_on_ties_nan_and_inf():
    """choose_block against numpy's _choose on the adversarial block of the previous test
    (ties in s, NaN/-inf bounds, cells with no feasible sample): the same sample where
    numpy's least error is unique by more than rounding, else a sample tied with it within
    rounding (and feasible where one is); the heights within rounding where the sample is
    the same; NaN rows as numpy's argmin takes them."""
    from terrain_perception import _fill_kernels
    W, A, B, C, Abar = _adversarial_block()
    S = len(A)
    h = np.empty(S)
    k = np.empty(S, np.int64)
    _fill_kernels.choose_block(*_block_inputs(A, B, Abar, C), W, h, k)
    try:
        fillmod.use_compiled_kernels(False)
        h0, k0 = fillmod._choose(A, B, Abar, C, W)
    finally:
        fillmod.use_compiled_kernels(None)
    # numpy's errors and feasibility, to judge ties
    Bf = B.astype(float)
    Az = np.where(B, A, 0.0)
    b = (Az.sum(1)[:, None] - np.einsum('snq,sq->sn', C, Bf)) / Bf.sum(1)[:, None]
    s = np.einsum('q,sq,snq->sn', W, Bf, (C - Az[:, None, :] + b[..., None]) ** 2)
    with np.errstate(invalid='ignore'):
        bounded = np.isfinite(Abar).any(1)
        ok = ~bounded[:, None] | ((C - Abar[:, None, :]).max(2) + b <= 0.0)
    same = k == k0
    for i in np.flatnonzero(~same):
        assert ok[i].any(), i                     # infeasible cells: same excess argmin
        assert ok[i, k[i]]
        assert abs(s[i, k[i]] - s[i, k0[i]]) <= 1e-15, (i, s[i, k[i]], s[i, k0[i]])
    np.testing.assert_allclose(h[same], h0[same], rtol=0, atol=1e-15)
    assert same.sum() >= S - 5 and (~ok[13]).all() and k[13] == k0[13]
    # inf / NaN heights in a window: NaN errors, numpy's first-NaN argmin
    A2 = A.copy()
    A2[14, 2] = np.inf
    A2[15, 0] = np.nan
    _fill_kernels.choose_block(*_block_inputs(A2[14:16], B[14:16], Abar[14:16], C[14:16]),
                               W, h[:2], k[:2])
    with np.errstate(invalid='ignore', over='ignore'):
        try:
            fillmod.use_compiled_kernels(False)
            _, k1 = fillmod._choose(A2[14:16], B[14:16], Abar[14:16], C[14:16], W)
        finally:
            fillmod.use_compiled_kernels(None)
    np.testing.assert_array_equal(k[:2], k1)


def test_choose_block_equals_its_sample_by_sample_form(walk, monkeypatch):
    """choose_block evaluating four samples at a time against the kernel before
    (ref.choose_block: one sample at a time): each sample's sums over the known cells in the
    same order, so heights and samples bitwise the same, on every block of fills of the walk's
    maps under their captures' bounds, of n not a multiple of 4, and of the adversarial block
    (ties, NaN / -inf bounds, nothing feasible, inf / NaN heights)."""
    from terrain_perception import _fill_kernels
    from terrain_perception.fill import FillConfig, PatchLibrary, bounds_from_captures, \
        fill_terrain
    from terrain_perception.config import make_config
    live = _fill_kernels.choose_block
    blocks = []

    def both(*args):
        live(*args)
        h, k = np.empty_like(args[-2]), np.empty_like(args[-1])
        ref.choose_block(*args[:-2], h, k)
        assert h.tobytes() == args[-2].tobytes() and k.tobytes() == args[-1].tobytes()
        blocks.append(len(h))

    monkeypatch.setattr(_fill_kernels, 'choose_block', both)
    lib = PatchLibrary(fill_library(), 5)
    bounded = 0
    for grid, _, _ in walk[::3]:
        h = np.asarray(grid[ELEVATION], np.float64)
        poses = np.array([t for _, t, _ in walk])
        ub = bounds_from_captures(h, grid.resolution_m, grid.origin_xy, poses[:, :3, 3], 1.0,
                                  camera_axes=poses[:, :3, 2],
                                  fov_half_angle_rad=np.radians(40.0))
        bounded += int(np.isfinite(ub).sum())
        fill_terrain(h, ub, lib)
    assert sum(blocks) > 5000 and bounded > 1000
    n0 = sum(blocks)
    fill_terrain(h, ub, lib, make_config(FillConfig, {'samples': 7}))   # 4 + 3 samples
    assert sum(blocks) > n0
    W, A, B, C, Abar = _adversarial_block()
    A[14, 2] = np.inf
    A[15, 0] = np.nan
    for sl in (slice(None), slice(0, 10), slice(10, None)):
        for n in (30, 5, 3):
            args = _block_inputs(A[sl], B[sl], Abar[sl], np.ascontiguousarray(C[sl, :n]))
            m = len(A[sl])
            h1, k1 = np.empty(m), np.empty(m, np.int64)
            h0, k0 = np.empty(m), np.empty(m, np.int64)
            live(*args, W, h1, k1)
            ref.choose_block(*args, W, h0, k0)
            assert h1.tobytes() == h0.tobytes() and k1.tobytes() == k0.tobytes()


def test_fill_kernel_equals_the_numpy_choice_on_nan_and_inf():
    """Blocks of cells with no bound, some bounds, NaN/-inf bounds, NaN/inf errors, ties and
    cells where no sample is feasible: same heights and sample indices."""
    W, A, B, C, Abar = _adversarial_block()
    A[14, 2] = np.inf                                       # s, h inf/NaN
    A[15, 0] = np.nan
    cases = [(A, B, Abar, C), (A[:10], B[:10], Abar[:10], C[:10]),
             (A[10:], B[10:], Abar[10:], C[10:])]
    with np.errstate(invalid='ignore', over='ignore'):
        for a, bb, ab, c in cases:
            try:
                fillmod.use_compiled_kernels(True)
                h1, k1 = fillmod._choose(a, bb, ab, c, W)
                fillmod.use_compiled_kernels(False)
                h0, k0 = fillmod._choose(a, bb, ab, c, W)
            finally:
                fillmod.use_compiled_kernels(None)
            np.testing.assert_array_equal(k1, k0)
            np.testing.assert_array_equal(h1, h0)


def numpy_feasible_argmin(C, Abar, b, s):
    """The numpy lines of fill._choose that _fill_kernels.feasible_argmin replaces."""
    ok = np.ones(b.shape, bool)
    bounded = np.isfinite(Abar).any(1)
    if bounded.all():
        ok = (C - Abar[:, None, :]).max(2) + b <= 0.0
    elif bounded.any():
        excess = (C[bounded] - Abar[bounded][:, None, :]).max(2)
        ok[bounded] = excess + b[bounded] <= 0.0
    return np.argmin(np.where(ok, s, np.inf), 1), ok.any(1)


def test_feasible_argmin_kernel_on_exact_ties_nan_and_inf():
    """Values on a 1/8 lattice, so that excess + b == 0 and ties in s happen often; NaN and
    inf in the patches, bounds and errors; all-bounded, unbounded and mixed blocks."""
    from terrain_perception import _fill_kernels
    rng = np.random.default_rng(6)
    S, n, q = 200, 20, 9
    special = np.array([np.nan, np.inf, -np.inf])
    for trial in range(20):
        C = rng.integers(-4, 5, (S, n, q)) / 8.0
        Abar = rng.integers(-2, 5, (S, q)) / 8.0
        b = rng.integers(-4, 5, (S, n)) / 8.0
        s = rng.integers(0, 6, (S, n)) / 8.0
        for arr, p in ((C, 0.002), (Abar, 0.05), (s, 0.02)):
            hit = rng.random(arr.shape) < p
            arr[hit] = rng.choice(special, int(hit.sum()))
        if trial % 3 == 1:
            Abar[rng.random(S) < 0.5] = np.inf                  # mixed blocks
        elif trial % 3 == 2:
            Abar[:] = np.inf                                    # no bound at all
        k = np.empty(S, np.int64)
        any_ok = np.empty(S, bool)
        with np.errstate(invalid='ignore'):
            _fill_kernels.feasible_argmin(C, Abar, b, s, k, any_ok)
            k0, any0 = numpy_feasible_argmin(C, Abar, b, s)
        np.testing.assert_array_equal(any_ok, any0)
        np.testing.assert_array_equal(k, k0)


# --- the planner's dry run of the walking controller (check_footsteps) -----------------------
def _rock_grid(seed, n=150, res=0.01):
    """A seeded field of flat-topped and conical rocks up to 5 cm, as test_footsteps'."""
    from terrain_perception.grid import GridMap
    rng = np.random.default_rng(seed)
    X, Y = np.mgrid[0:n, 0:n]
    h = np.zeros((n, n))
    for _ in range(70):
        cx, cy = rng.integers(0, n, 2)
        r = rng.integers(3, 12)
        d = np.hypot(X - cx, Y - cy)
        top = rng.uniform(0.01, 0.05)
        h = np.maximum(h, np.where(d < r, top, 0.0) if rng.random() < 0.5
                       else np.clip(top * (1 - d / r), 0, None))
    h[rng.random(h.shape) < 0.01] = np.nan                 # unknown cells
    return GridMap(res, (-0.75, -0.75), h.shape, {ELEVATION: h.astype(np.float32)})


@pytest.fixture(scope='module')
def dry_run_cases():
    """``(grid, feet, legs, positions, T_body)``: the crawl plans the planner makes on three
    rock fields from several poses, and jittered copies of them (refused at every stage: reach,
    margin, belly, shanks)."""
    from terrain_perception import footsteps as fs
    from terrain_perception.features import cost_map
    rm = load_robot_model('littledog')
    rng = np.random.default_rng(11)
    cases = []
    for seed in (0, 1, 2):
        g = _rock_grid(seed)
        g['cost'] = cost_map(np.asarray(g[ELEVATION], np.float64), g.resolution_m)
        planner = fs.FootstepPlanner(rm, fs.PlannerConfig(horizon_steps=8))
        assert planner.set_map(g) is None
        for x0, yaw in ((-0.2, 0.0), (0.0, 0.3), (0.1, -0.4), (-0.3, 0.1)):
            T = np.eye(4)
            T[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
            T[:3, 3] = [x0, 0.0, rm.standing_height_m]
            plan = planner.plan(T)
            if not plan.ok or not plan.footsteps:
                continue
            legs = np.array([s.leg for s in plan.footsteps])
            pos = np.array([s.position for s in plan.footsteps])
            feet = plan.initial_feet.copy()
            T_body = T.copy()
            T_body[2, 3] = feet[:, 2].mean() + rm.standing_height_m + rng.normal(0, 0.01)
            cases.append((g, feet, legs, pos, T_body))
            for _ in range(4):
                jit = pos + rng.normal(0.0, [0.03, 0.03, 0.015], pos.shape)
                cases.append((g, feet, legs, jit, T_body if rng.random() < 0.7 else None))
    return cases


def run_dry(cases, monkeypatch=None):
    """check_footsteps over ``cases``: its answers and the state after every segment."""
    from terrain_perception.controller import WalkingConfig, WalkingController, check_footsteps
    rm = load_robot_model('littledog')
    log = []
    finish = WalkingController._finish_segment

    def record(self, *a, **kw):
        seg = self._seg
        log.append((seg.kind, seg.duration, seg.q_end, seg.roll, seg.body_end, seg.feet_end))
        return finish(self, *a, **kw)
    out = []
    with pytest.MonkeyPatch.context() as m:
        m.setattr(WalkingController, '_finish_segment', record)
        for cfg in (WalkingConfig(), WalkingConfig(belly_clearance_m=0.03)):
            for g, feet, legs, pos, T_body in cases:
                out.append(check_footsteps(rm, cfg, feet, legs, pos, 'walk', g, T_body=T_body))
    return out, log


def test_check_footsteps_equals_the_previous_code(dry_run_cases):
    """The controller's dry run with its memo, cached belly samples and standing COM, the
    first swing height's IK on its own and project_into_support's single margin: the same
    answers and every segment's end state bitwise as the code before (633dc8f)."""
    from terrain_perception import controller as ctlmod
    from terrain_perception import gait as gaitmod
    new, new_log = run_dry(dry_run_cases)
    with pytest.MonkeyPatch.context() as m:
        for name in ('_shift_body', '_shanks_clear', '_body_z', '_belly_z', '_apex'):
            m.setattr(ctlmod.WalkingController, name, getattr(ref, 'ctl' + name))
        m.setattr(gaitmod, 'project_into_support', ref.project_into_support)
        old, old_log = run_dry(dry_run_cases)
    why = [w for _, w in old]
    assert len(old) >= 60 and why.count('') >= 10 and len(why) - why.count('') >= 10, why
    kinds = ('shank', 'margin', 'reach')
    assert all(any(k in w for w in why) for k in kinds), why     # refused for each reason
    assert new == old
    assert len(new_log) == len(old_log) > 200
    for a, b in zip(new_log, old_log):
        assert a[:2] == b[:2]
        for x, y in zip(a[2:], b[2:]):
            np.testing.assert_array_equal(x, y)



# --- the footstep planner's search (footsteps.py) --------------------------------------------
def test_unsafe_cells_equal_the_previous_code(walk):
    """OpenCV's separable filter instead of scipy's correlate1d: the same cells flagged on the
    fill walk's moving maps (mostly unknown), on rock fields with unknown cells, and on the
    foot's resting surface of both, for the planner's windows and thresholds."""
    from terrain_perception.footsteps import foot_surface, unsafe_cells
    maps = [np.asarray(g[ELEVATION], np.float64) for g, _, _ in walk[::2]]
    maps += [np.asarray(_rock_grid(seed)[ELEVATION], np.float64) for seed in (0, 1, 2)]
    maps += [foot_surface(h, 0.01, 0.012) for h in maps]
    flagged = 0
    for h in maps:
        for radius, slope, frac, window in ((0.012, 30.0, 0.5, 0.0), (0.012, 25.5, 0.425, 0.0),
                                            (0.025, 30.0, 0.5, 0.02), (0.004, 20.0, 0.3, 0.0)):
            new = unsafe_cells(h, 0.01, radius, slope, frac, window)
            old = ref.unsafe_cells(h, 0.01, radius, slope, frac, window)
            np.testing.assert_array_equal(new, old)
            flagged += int(old.sum())
    assert flagged > 1000                      # the comparison covers flagged cells


def _patched_planner_methods(m):
    from terrain_perception.footsteps import FootstepPlanner
    for name in ('_area', '_area_flat', '_area_cells', '_candidates', '_heading_error',
                 '_body_in_reach'):
        m.setattr(FootstepPlanner, name, getattr(ref, 'fs' + name))


def _plans(cases, planner_config):
    from terrain_perception import footsteps as fs
    from terrain_perception.features import cost_map
    rm = load_robot_model('littledog')
    out = []
    for seed, poses, patches in cases:
        g = _rock_grid(seed)
        g['cost'] = cost_map(np.asarray(g[ELEVATION], np.float64), g.resolution_m)
        planner = fs.FootstepPlanner(rm, planner_config)
        assert planner.set_map(g) is None
        for T in poses:
            plan = planner.plan(T, patches=patches)
            out.append((plan.status, plan.status_text, plan.gait,
                        [(s.leg, s.position.tolist(), s.cost, s.step_index, s.patch_index,
                          s.body_xy.tolist(), s.body_height_m) for s in plan.footsteps]))
    return out


@pytest.mark.parametrize('centre', ['adaptive', 'rule'])
def test_planner_search_equals_the_previous_code(centre):
    """The beam search's helpers after session 49's speed-ups (the search area's cells found
    once for the flatness test and the candidates, a stance's heading without per-candidate
    copies, patches boxed to the area before the distance test, the crouch levels cached): the
    same plans, footstep by footstep, bitwise, on rock fields from several poses and headings,
    with and without contact patches."""
    from terrain_perception import footsteps as fs
    rm = load_robot_model('littledog')
    rng = np.random.default_rng(12)
    cases = []
    for seed in (0, 1, 2):
        poses = []
        for x0, y0, yaw in ((-0.3, 0.0, 0.0), (0.0, 0.05, 0.3), (0.1, -0.1, -0.4),
                            (-0.2, 0.1, 3.0)):
            T = np.eye(4)
            T[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
            T[:3, 3] = [x0, y0, rm.standing_height_m]
            poses.append(T)
        # patches: everywhere on the field (most far from any search area), radii 5-15 mm
        pv = np.c_[rng.uniform(-0.75, 0.75, (300, 2)), rng.uniform(0.0, 0.05, 300)]
        pr = rng.uniform(0.005, 0.015, 300)
        cases.append((seed, poses, None))
        cases.append((seed, poses, (pv, pr)))
    cfg = fs.PlannerConfig(horizon_steps=8, stride_centre=centre)
    new = _plans(cases, cfg)
    with pytest.MonkeyPatch.context() as m:
        _patched_planner_methods(m)
        old = _plans(cases, cfg)
    assert new == old
    steps = [s for _, _, _, st in old for s in st]
    assert sum(st[0] == fs.STATUS_OK for st in old) >= 16 and len(steps) >= 100
    assert sum(s[4] >= 0 for s in steps) >= 10          # footholds on patches compared too



def test_max_filter_equals_scipy_maximum_filter():
    """features.max_filter (OpenCV dilation; the belly's top field and Kolter's height
    differential) against scipy's maximum_filter it replaced: bitwise, both border modes, odd
    and even sizes, -inf cells, maps smaller than the window."""
    from scipy import ndimage

    from terrain_perception.features import max_filter
    rng = np.random.default_rng(9)
    for shape in ((300, 300), (57, 91), (5, 3), (1, 40)):
        h = rng.normal(0, 0.02, shape)
        h[rng.random(shape) < 0.2] = -np.inf
        for size in (1, 2, 3, 4, 5, 9, 21):
            for mode in ('nearest', 'constant'):
                want = ndimage.maximum_filter(h, size=size, mode=mode, cval=-np.inf)
                assert max_filter(h, size, mode).tobytes() == want.tobytes(), (shape, size, mode)
    with pytest.raises(ValueError, match='nearest'):
        max_filter(h, 3, 'reflect')

# --- terrain features ------------------------------------------------------------------------
def test_kolter_features_equal_the_previous_code(walk):
    """The plane fitted only under cells of known height: every feature as before on the fill
    walk's moving maps (mostly unknown) as observed and as filled, with either NaN policy and
    window, plus maps with nothing or almost nothing known and a flat one (singular planes).
    Bitwise, except the slope: its normal equations are solved in closed form now (cofactors,
    not LAPACK's solve), equal within rounding (the same cells NaN; flat windows 0 or ~1e-17)."""
    from terrain_perception.features import CostConfig, kolter_features
    filled = run_filler(walk[:6])
    maps = [np.asarray(g[ELEVATION], np.float64) for g, _, _ in walk[::3]]
    maps += [o[0][ELEVATION] for o in filled]
    assert all(0.05 < np.isfinite(h).mean() < 0.9 for h in maps)
    rng = np.random.default_rng(8)
    sparse = np.full((60, 50), np.nan)
    sparse[rng.random(sparse.shape) < 0.05] = 0.01
    flat = np.zeros((40, 40))
    flat[:, 5] = np.nan
    line = np.full((30, 30), np.nan)
    line[10, :] = np.linspace(0.0, 0.1, 30)                   # collinear: no plane
    maps += [sparse, flat, line, np.full((20, 20), np.nan)]
    for cfg in (CostConfig(), CostConfig(nan_policy='propagate'),
                CostConfig(foot_window_m=0.09, nan_policy='ignore')):
        for h in maps:
            a = kolter_features(h, 0.01, cfg)
            b = ref.kolter_features(h, 0.01, cfg)
            assert a.keys() == b.keys()
            for name in a:
                if name == 'slope':
                    np.testing.assert_array_equal(np.isnan(a[name]), np.isnan(b[name]))
                    np.testing.assert_allclose(a[name], b[name], rtol=1e-9, atol=1e-12)
                else:
                    assert a[name].tobytes() == b[name].tobytes(), name


# --- the ICP mapper (mapping.py) -------------------------------------------------------------
def test_fake_information_closed_form_equals_the_sum_over_points(walk):
    """The noise information of the degeneracy test from the weighted moments of the lever arms
    instead of the per-point Jacobians: equal within rounding on lever arms of the fill walk's
    terrain (map cells seen from the body) and on a few points."""
    from terrain_perception.mapping import fake_information
    rng = np.random.default_rng(3)
    cases = []
    for g, _, _ in walk[::4]:
        h = np.asarray(g[ELEVATION], np.float64)
        ii, jj = np.nonzero(np.isfinite(h))
        pts = np.c_[ii * 0.01, jj * 0.01, h[ii, jj]]
        cases.append(pts - pts.mean(axis=0) + [0.3, 0.0, -0.15])
    cases += [rng.normal(0.0, 0.2, (7, 3)), np.array([[0.2, -0.1, -0.14]])]
    for d in cases:
        w = rng.random(len(d))
        for L in (0.5, 0.12):
            a, b = fake_information(d, w / w.sum(), L), ref.fake_information(d, w / w.sum(), L)
            np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-14 * np.abs(b).max())
            np.testing.assert_array_equal(a, a.T)
