"""Per-tick trace of a simulated walk, and a report of how a traced walk fell.

A ground-truth walk that falls is deterministic, so the way to learn why is to record it: the
simulator's truth (base pose, whole-robot COM, foot centres, the normal force on each foot)
next to what the controller believed and did (its phase, its stance feet and body target
put in the map with its ``T_map_odom``, its torque-based foot-force estimates).
:class:`WalkTrace` records that every ``every`` physics steps of a
:class:`terrain_perception.sim.walk.WalkRunner`;
:func:`fall_report` reads a trace (or its ``.npz``) and says when the robot fell, when the COM
left the polygon of the feet that really carried it, and which stance feet hung in the air
before (the session-17 mechanism: a foot ending its swing 1-2 mm above the ground, then a body
shift tipping the robot over the diagonal of two others).

``terrain-bench sim --rocks-seeds N --trace DIR`` traces every ground-truth rocks walk.
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional, Union

import numpy as np

from terrain_perception import gait as gaitlib
from terrain_perception.robot_model import LEG_NAMES
from terrain_perception.transforms import transform_points

#: Phase codes of the ``phase`` column.
PHASES = ('stand', 'shift', 'swing', 'probe', 'verify')
#: A foot whose true normal force is below this carries nothing [N].
LOADED_N = 0.3
#: Base tilt [deg] taken as the moment of the fall (the runner's fall test is 30 deg).
FALL_TILT_DEG = 20.0


class WalkTrace:
    """Recorder: call :meth:`sample` from the walk loop (``WalkRunner(trace=...)`` does)."""

    def __init__(self, every: int = 5) -> None:
        if int(every) < 1:
            raise ValueError(f'WalkTrace: every must be >= 1 physics step, got {every}')
        self.every = int(every)
        self._rows: dict = {k: [] for k in (
            't', 'base_xyz', 'base_rpy', 'com', 'feet', 'force', 'other_force', 'phase',
            'swing_legs', 'steps_done', 'believed_feet', 'force_estimate', 'body_target',
            'q', 'tau')}
        self._n = 0

    def sample(self, t: float, client, robot, controller, masses: np.ndarray) -> None:
        """Record one row every ``every`` calls."""
        self._n += 1
        if (self._n - 1) % self.every:
            return
        from terrain_perception.sim.walk import com_world
        pos, quat = client.getBasePositionAndOrientation(robot.body_id)
        ph = controller.phase
        legs = np.zeros(4, bool)
        if ph is not None and ph.kind != 'verify':     # verifying: the legs stand (or hang)
            legs[list(ph.legs)] = True
        feet = controller.feet
        r = self._rows
        r['t'].append(float(t))
        r['base_xyz'].append(pos)
        r['base_rpy'].append(client.getEulerFromQuaternion(quat))
        r['com'].append(com_world(client, robot, masses))
        r['feet'].append(robot.foot_positions_world())
        feet_f, legs_f, body_f = robot.contact_forces_by_part()
        r['force'].append(feet_f)
        r['other_force'].append(np.append(legs_f, body_f))
        r['phase'].append(0 if ph is None else PHASES.index(ph.kind))
        r['swing_legs'].append(legs)
        r['steps_done'].append(controller.steps_done)
        r['believed_feet'].append(np.full((4, 3), np.nan) if feet is None
                                  else transform_points(controller.T_map_odom, feet))
        r['force_estimate'].append(np.asarray(controller.foot_loads, float))
        r['body_target'].append(controller.map_pose[:3, 3])
        q, _, tau = robot.joint_states()
        r['q'].append(q)
        r['tau'].append(tau)

    def __len__(self) -> int:
        return len(self._rows['t'])

    def arrays(self) -> dict:
        """Columns as arrays: t (n,), base_xyz, base_rpy [rad], com (n, 3); feet (foot-sphere
        centres), believed_feet (controller's stance contact points, in the map: its
        ``T_map_odom`` applied) (n, 4, 3);
        force (true normal force), force_estimate (n, 4) [N]; other_force (n, 5) [N]: the
        true normal force on each leg's other links (hip, thigh, shank) and on the body;
        phase (n,) index into :data:`PHASES`; swing_legs (n, 4) bool; steps_done (n,);
        body_target (n, 3); q, tau (n, 12): the measured joint angles [rad] and motor
        torques [N m]."""
        shapes = {'feet': (4, 3), 'believed_feet': (4, 3), 'force': (4,),
                  'other_force': (5,), 'force_estimate': (4,), 'swing_legs': (4,),
                  'base_xyz': (3,), 'base_rpy': (3,), 'com': (3,), 'body_target': (3,),
                  'q': (12,), 'tau': (12,)}
        out = {}
        for k, rows in self._rows.items():
            a = np.asarray(rows)
            if not len(rows) and k in shapes:
                a = a.reshape((0,) + shapes[k])
            out[k] = a
        return out

    def save(self, path: Union[str, Path], **meta) -> Path:
        """Write the columns (and ``meta`` values, e.g. seed, status) to ``path`` (.npz)."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(path, **self.arrays(),
                            **{f'meta_{k}': np.asarray(v) for k, v in meta.items()})
        return path


def load_trace(path: Union[str, Path]) -> dict:
    """A saved trace's columns (see :meth:`WalkTrace.arrays`) plus its ``meta_*`` values."""
    with np.load(Path(path), allow_pickle=False) as d:
        return {k: d[k] for k in d.files}


def _tilt_deg(rpy: np.ndarray) -> np.ndarray:
    return np.degrees(np.arccos(np.clip(np.cos(rpy[:, 0]) * np.cos(rpy[:, 1]), -1.0, 1.0)))


def com_margin(trace: dict) -> np.ndarray:
    """Per row: signed distance [m] of the true COM to the edges of the polygon of the feet
    that really carry weight (normal force > :data:`LOADED_N`); NaN with fewer than 2 loaded
    feet. Positive inside."""
    com, feet, force = trace['com'], trace['feet'], trace['force']
    out = np.full(len(com), np.nan)
    for i in range(len(com)):
        on = force[i] > LOADED_N
        if on.sum() >= 2:
            out[i] = float(gaitlib.support_margin(com[i, :2], feet[i, on, :2]))
    return out


def hanging_runs(trace: dict, rows: np.ndarray, min_s: float = 0.1) -> dict:
    """Stance feet (not swinging) that carried nothing (true force below :data:`LOADED_N`)
    for at least ``min_s`` among ``rows`` (consecutive trace rows): ``{leg: (longest run [s],
    its first time [s], mean force estimate during it [N])}``."""
    t = trace['t'][rows]
    dt = float(np.median(np.diff(trace['t']))) if len(trace['t']) > 1 else 0.0
    free = (~trace['swing_legs'][rows]) & (trace['force'][rows] <= LOADED_N)
    out = {}
    for leg in range(4):
        best, start, run = (0, 0), 0, 0
        for i, f in enumerate(free[:, leg]):
            run = run + 1 if f else 0
            if run == 1:
                start = i
            if run > best[0]:
                best = (run, start)
        if best[0] * dt >= min_s:
            est = trace['force_estimate'][rows][best[1]:best[1] + best[0], leg]
            out[leg] = (best[0] * dt, float(t[best[1]]),
                        float(np.nanmean(est)) if np.isfinite(est).any() else float('nan'))
    return out


def fall_report(trace: Union[dict, str, Path], window_s: float = 2.0,
                table_every_s: float = 0.1, tilt_deg: float = FALL_TILT_DEG
                ) -> Optional[str]:
    """How a traced walk fell, or None if its base tilt never exceeded ``tilt_deg``, its body
    never touched the terrain (the walk runner's other fall: the belly on a rock) and its
    ``meta_fell`` (saved by the bench) does not say it fell. A walk that fell and was
    beyond ``tilt_deg`` before, then back, is reported at the start of the excursion it
    ended in (with when it first was beyond), not at its first.

    The text names the fall time and place, the phase, the last moment the COM was inside the
    polygon of the feet that carried weight and which feet those were, the stance feet (not
    swinging) that carried nothing for at least 0.1 s in the ``window_s`` before the fall
    (hanging; with the controller's force estimate meanwhile), swing feet that met the ground
    with more than the robot's weight, and the believed-vs-true foot offset; then a table of
    the window every ``table_every_s`` and of its last 0.3 s at every row."""
    tr = load_trace(trace) if isinstance(trace, (str, Path)) else trace
    t = tr['t']
    if not len(t):
        raise ValueError('fall_report: the trace is empty')
    tilt = _tilt_deg(tr['base_rpy'])
    other = tr.get('other_force')          # traces before session 34 lack it
    if other is not None and not len(other):
        other = None
    # the walk runner's other fall: the body touching the terrain (the belly on a rock)
    belly = other[:, 4] > LOADED_N if other is not None else np.zeros(len(t), bool)
    down = (tilt > tilt_deg) | belly
    over = np.flatnonzero(down)
    fell = bool(tr.get('meta_fell', False))
    dt = float(np.median(np.diff(t))) if len(t) > 1 else 0.0
    earlier, i_fall = '', None
    if len(over):
        i_fall = int(over[0])
        if fell and not down[i_fall:].all():
            # The walk went on after that row (the runner's fall is a 30 deg tilt or the body
            # touching): a robot that walks tilted beyond tilt_deg on steep rocks and recovers
            # has not fallen there; report the excursion it ended in, or its last row
            # (rocks-12cm ground truth seed 0: 20 deg at 48.4 s, fallen at 55.2 s).
            first = i_fall
            i_fall = int(np.flatnonzero(~down)[-1]) + 1 if down[-1] else None
            seen = down[:i_fall] if i_fall is not None else down
            earlier = (f'; beyond {tilt_deg:g} deg before, first at t = {t[first]:.2f} s, '
                       f'{seen.sum() * dt:.1f} s in all')
    if i_fall is not None:
        how = (f'tilt {tilt[i_fall]:.1f} deg' if tilt[i_fall] > tilt_deg else
               f'the body on the terrain with {other[i_fall, 4]:.1f} N, tilt '
               f'{tilt[i_fall]:.1f} deg') + earlier
    elif fell:
        # the runner saw the body touch between the last sampled row and its stop
        i_fall = len(t) - 1
        how = (f'the body touched the terrain just after this row (the walk runner\'s test), '
               f'tilt {tilt[i_fall]:.1f} deg') + earlier
    else:
        return None
    t_fall = float(t[i_fall])
    win = np.flatnonzero((t >= t_fall - window_s) & (t <= t_fall))
    margin = com_margin(tr)
    loaded = tr['force'] > LOADED_N
    phase = [PHASES[int(p)] for p in tr['phase']]

    def legs_of(mask) -> str:
        return '+'.join(LEG_NAMES[k] for k in range(4) if mask[k]) or '-'

    lines = [f'fell at t = {t_fall:.2f} s, x = {tr["base_xyz"][i_fall, 0]:.3f} m ({how}), '
             f'step {int(tr["steps_done"][i_fall])}, during a {phase[i_fall]} of '
             f'{legs_of(tr["swing_legs"][i_fall])}']
    inside = win[np.nan_to_num(margin[win], nan=-1.0) > 0.0]
    if len(inside):
        j = int(inside[-1])
        k = j + 1 if j + 1 < len(t) else j
        lines.append(f'COM last inside the loaded feet at t = {t[j]:.2f} s ({phase[j]} '
                     f'{legs_of(tr["swing_legs"][j])}, margin {margin[j] * 1000:.1f} mm over '
                     f'{legs_of(loaded[j])}); next row: loaded {legs_of(loaded[k])}, tilt '
                     f'{tilt[k]:.1f} deg, {t_fall - t[j]:.2f} s before the fall')
    else:
        lines.append(f'COM outside the loaded feet during the whole {window_s:.1f} s window')
    before = win[win <= inside[-1]] if len(inside) else win
    hang = hanging_runs(tr, before)
    lines.append('stance feet carrying nothing before the support was lost, longest run: ' + (
        ', '.join(f'{LEG_NAMES[k]} {d:.2f} s from t = {t0:.2f} ('
                  + (f'estimate {e:+.1f} N' if np.isfinite(e) else 'no estimate') + ')'
                  for k, (d, t0, e) in sorted(hang.items())) if hang else 'none'))
    weight = float(np.median(tr['force'][tr['phase'] == PHASES.index('shift')].sum(axis=1))) \
        if np.any(tr['phase'] == PHASES.index('shift')) else np.inf
    hits = []
    for leg in range(4):
        f = np.where(tr['swing_legs'][win, leg], tr['force'][win, leg], 0.0)
        if f.max() > weight:
            j = int(win[np.argmax(f)])
            hits.append(f'{LEG_NAMES[leg]} {f.max():.0f} N at t = {t[j]:.2f}')
    lines.append(f'swing feet that met the ground with more than the robot\'s weight '
                 f'({weight:.0f} N): ' + (', '.join(hits) if hits else 'none'))
    if other is not None:
        parts = [f'{n} leg' for n in LEG_NAMES] + ['body']
        touch = other[win] > LOADED_N
        said = [f'{parts[k]} {touch[:, k].mean() * 100:.0f} % of the time (peak '
                f'{other[win, k].max():.0f} N)' for k in range(5) if touch[:, k].any()]
        lines.append(f'legs (hip, thigh, shank) and body on the terrain in the {window_s:.1f} s '
                     f'before the fall: ' + (', '.join(said) if said else 'none'))
    off = np.linalg.norm(tr['feet'][i_fall, :, :2] - tr['believed_feet'][i_fall, :, :2], axis=1)
    lines.append('believed vs true foot x-y offset at the fall [mm]: ' + ', '.join(
        f'{LEG_NAMES[k]} {off[k] * 1000:.0f}' for k in range(4)))
    lines.append(f'{"t":>7} {"x":>6} {"roll":>6} {"pitch":>6} {"phase":<11} '
                 f'{"true force LF RF LH RH [N]":<27} {"estimate [N]":<27} {"COM marg mm":>11}'
                 + (f' {"legs+body on terrain [N]":>30}' if other is not None else ''))
    step = max(1, int(round(table_every_s / dt))) if dt > 0 else 1
    rows = sorted(set(win[::step].tolist()) | set(win[t[win] >= t_fall - 0.3].tolist()))
    for i in rows:
        rpy = np.degrees(tr['base_rpy'][i])
        m = margin[i]
        lines.append(f'{t[i]:7.2f} {tr["base_xyz"][i, 0]:6.3f} {rpy[0]:+6.1f} {rpy[1]:+6.1f} '
                     f'{phase[i] + " " + legs_of(tr["swing_legs"][i]):<11} '
                     + ' '.join(f'{f:6.1f}' for f in tr['force'][i]) + ' '
                     + ' '.join(f'{f:6.1f}' for f in tr['force_estimate'][i])
                     + (f' {m * 1000:+11.1f}' if np.isfinite(m) else f' {"-":>11}')
                     + (' ' + ' '.join(f'{f:5.1f}' for f in other[i]) if other is not None
                        else ''))
    return '\n'.join(lines)


#: A swing foot whose true normal force exceeds this has met the ground [N].
CONTACT_N = 1.0


def landings(trace: Union[dict, str, Path], after_fraction: float = 0.4,
             peak_window_s: float = 0.1) -> dict:
    """Every swing's touchdown in a trace: the first row after ``after_fraction`` of the swing
    (its rows with the leg swinging) whose true normal force exceeds :data:`CONTACT_N`, up to
    0.3 s after the swing ended. Per touchdown (arrays, one entry each): ``leg``, ``t`` [s],
    ``descent_m_s`` (the foot centre's true downward speed over the row before the one in
    which it touched: > 0 descending), ``swing_fraction`` (where in the swing's rows it came),
    ``peak_n`` (the largest true force in the ``peak_window_s`` from it). A min-jerk lowering
    that ends on the ground meets it at ~zero speed; one that meets it early hits it at the
    lowering's speed."""
    tr = load_trace(trace) if isinstance(trace, (str, Path)) else trace
    t, z, force, swing = tr['t'], tr['feet'][:, :, 2], tr['force'], tr['swing_legs']
    dt = float(np.median(np.diff(t))) if len(t) > 1 else 0.0
    extra = int(round(0.3 / dt)) if dt > 0 else 0
    peak_rows = max(1, int(round(peak_window_s / dt))) if dt > 0 else 1
    out = {k: [] for k in ('leg', 't', 'descent_m_s', 'swing_fraction', 'peak_n')}
    for leg in range(4):
        s = np.concatenate([[0], swing[:, leg].astype(np.int8), [0]])
        starts = np.flatnonzero(np.diff(s) == 1)
        ends = np.flatnonzero(np.diff(s) == -1)          # exclusive
        for a, b in zip(starts, ends):
            lo = a + int(after_fraction * (b - a))
            hit = np.flatnonzero(force[lo:min(b + extra, len(t)), leg] > CONTACT_N)
            if not len(hit) or lo + hit[0] < 2:
                continue
            k = lo + int(hit[0])
            # the contact came between rows k-1 and k: the speed over the row before that
            j = k - 1
            out['leg'].append(leg)
            out['t'].append(float(t[k]))
            out['descent_m_s'].append(float((z[j - 1, leg] - z[j, leg]) / (t[j] - t[j - 1]))
                                      if t[j] > t[j - 1] else float('nan'))
            out['swing_fraction'].append((k - a) / max(b - a, 1))
            out['peak_n'].append(float(force[k:k + peak_rows, leg].max()))
    return {k: np.asarray(v, dtype=np.int64 if k == 'leg' else np.float64)
            for k, v in out.items()}


def landing_summary(traces, weight_n: float) -> dict:
    """Pooled :func:`landings` of several traces: ``count``, ``descent_m_s_median`` / ``_p90``,
    ``swing_fraction_median``, ``peak_n_median`` / ``_p90`` and ``share_over_weight`` (the
    touchdowns whose peak force exceeded ``weight_n``, the robot's weight)."""
    pooled = [landings(tr) for tr in traces]
    v, f, pk = (np.concatenate([p[k] for p in pooled] + [np.zeros(0)])
                for k in ('descent_m_s', 'swing_fraction', 'peak_n'))
    if not len(v):
        return {'count': 0}
    return {'count': int(len(v)),
            'descent_m_s_median': float(np.nanmedian(v)),
            'descent_m_s_p90': float(np.nanpercentile(v, 90)),
            'swing_fraction_median': float(np.median(f)),
            'peak_n_median': float(np.median(pk)), 'peak_n_p90': float(np.percentile(pk, 90)),
            'share_over_weight': float(np.mean(pk > weight_n))}
