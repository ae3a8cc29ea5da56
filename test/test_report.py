"""The demo report: latency figures (per-capture stamps in, per-node wall times out) and the
localisation errors against ground truth."""

from __future__ import annotations

import numpy as np
import pytest

from terrain_ros.report import CourseInfo, RunData, compute_summary, format_summary
from terrain_ros.tools.demo import STAGE_NAMES, STAGE_TOPICS, stage_latencies


def _walls():
    # captures 1..3; capture 3 never reached the planner, capture 2 skipped by the mapper
    image = {(1, 0): 10.0, (2, 0): 20.0, (3, 0): 30.0}
    stages = {'/stereo/points': {(1, 0): 10.1, (2, 0): 20.2, (3, 0): 30.1},
              '/map/fine': {(1, 0): 10.4, (3, 0): 30.5},
              '/map/filled': {(1, 0): 10.5, (3, 0): 30.6},
              '/footstep_plan': {(1, 0): 10.8}}
    return image, stages


def test_stage_latencies_follow_each_stamp_from_node_to_node():
    assert STAGE_TOPICS[-1] == '/footstep_plan' and len(STAGE_NAMES) == len(STAGE_TOPICS)
    lat = stage_latencies(*_walls())
    assert list(lat) == list(STAGE_NAMES)
    assert lat['stereo'] == pytest.approx([100.0, 200.0, 100.0])
    assert lat['icp_mapper'] == pytest.approx([300.0, 400.0])     # capture 2 never fused
    assert lat['terrain_fill'] == pytest.approx([100.0, 100.0])
    assert lat['footstep_planner'] == pytest.approx([300.0])


def test_summary_reports_the_per_node_latency_with_the_total():
    d = RunData(CourseInfo('rocks-6cm', 0, 0.4, 1.0, 1.75, 2.15), 'littledog')
    d.latencies_ms = [800.0]
    d.latency_stages_ms = stage_latencies(*_walls())
    s = compute_summary(d)
    assert s['capture_to_plan_ms_median'] == 800.0
    st = s['latency_stages_ms']
    assert st['icp_mapper'] == {'median': 350.0, 'p95': pytest.approx(395.0), 'captures': 2}
    assert st['footstep_planner']['captures'] == 1
    assert 'icp_mapper 350' in format_summary(s)


def _pose(x, y, yaw_deg):
    c, s_ = np.cos(np.radians(yaw_deg)), np.sin(np.radians(yaw_deg))
    T = np.eye(4)
    T[:2, :2] = [[c, -s_], [s_, c]]
    T[:2, 3] = x, y
    return T


def test_summary_reports_the_heading_error_a_slip_leaves():
    # The robot pivots 11 deg in place at t = 2 s (a slip); the estimate keeps the old
    # heading and ends 3 mm off in position: the position error alone would hide it.
    d = RunData(CourseInfo('rocks-6cm', 0, 0.4, 1.0, 1.75, 2.15), 'littledog')
    t = np.arange(0.0, 4.0, 0.5)
    d.gt_t = t
    d.gt_T = np.stack([_pose(0.4 + 0.01 * k, 0.0, 0.0 if k < 4 else 11.0)
                       for k in range(len(t))])
    d.dr_t = t
    d.dr_T = np.stack([_pose(0.4 + 0.01 * k + (0.003 if k == len(t) - 1 else 0.0), 0.0, 179.0
                             if k == 0 else 0.0) for k in range(len(t))])
    s = compute_summary(d)
    assert s['final_localisation_error_m'] == pytest.approx(0.003, abs=1e-6)
    assert s['final_heading_error_deg'] == pytest.approx(11.0, abs=1e-6)
    # wrapped: 179 deg against 0 is 179 deg off, not 181
    assert s['max_heading_error_deg'] == pytest.approx(179.0, abs=1e-6)
    assert 'heading 11.0 deg (max 179.0 deg)' in format_summary(s)


def test_the_summary_of_a_run_that_crossed_is_written_as_json():
    """Run AB lost its report: a numpy bool in the summary (crossed, computed from the first
    crossing and the first fall) was not JSON-serialisable. Any flag numpy computes must be
    written as a JSON boolean."""
    import json
    from terrain_ros.report import _jsonable
    d = RunData(CourseInfo('rocks-6cm', 0, 0.4, 1.0, 1.75, 2.15), 'littledog')
    t = np.arange(0.0, 20.0, 0.5)
    d.gt_t = t
    d.gt_T = np.stack([_pose(0.4 + 0.1 * k, 0.0, 0.0) for k in range(len(t))])
    d.dr_t, d.dr_T = t, d.gt_T.copy()
    s = compute_summary(d)
    out = json.loads(json.dumps(s, default=_jsonable))
    assert out['crossed'] is True and out['falls'] == 0
    assert json.loads(json.dumps({'flag': np.bool_(False)}, default=_jsonable)) == {'flag': False}
