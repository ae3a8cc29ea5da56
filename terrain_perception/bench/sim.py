"""Simulator and walking controller: real-time factor with cameras, walking speed, foot placement.

* Real-time factor of the simulation as the bridge runs it (``SimSession``: physics at 500 Hz,
  state readings at 100 Hz, stereo pairs rendered at the profile's camera rate) per robot
  profile and image scale, on the ``rocks-6cm`` course.
* Walking on flat ground (LittleDog-like and FROG-I-like): straight-line crawl footsteps, the
  controller driving the simulator's PD at every physics step; speed from the ground-truth
  base displacement, foot-placement error = horizontal distance between each landed foot and
  its footstep.
* Walking over ``rocks-6cm`` (LittleDog-like) with ground-truth footsteps: the project's
  footstep planner on the true height map, replanned from the true pose and feet after every
  executed horizon (blind to perception, to separate control from perception), the
  controller's dead reckoning re-anchored before each plan with the correction a perfect ICP
  would give (``--no-localise``: not at all, as before the nineteenth session); baseline in
  the same run: the controller without touchdown sensing and IMU levelling (open loop).

JSON keys: rtf_littledog, rtf_frog (native camera resolution, cameras on), foot_err_flat_m,
foot_err_rocks6_m (mean, LittleDog), speed_flat_mps (LittleDog crawl), speed_flat_trot_mps,
rocks6_advanced_m, rocks6_open_loop_advanced_m, plus per-case details.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from typing import Optional

import numpy as np

from terrain_perception import gait as G
from terrain_perception.robot_model import load_robot_model
from terrain_perception.transforms import invert, make_T, transform_points

DT = 1.0 / 500.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument('--seed', type=int, default=0, help='rocks-6cm course seed')
    parser.add_argument('--rocks-seeds', type=int, default=0, metavar='N',
                        help='also walk rocks-6cm on seeds 0..N-1 with ground-truth footsteps, '
                        'with the default planner and controller and with the baseline '
                        f'{ROCKS_BASELINE_NAME!r}; reports crossings, falls and advance')
    parser.add_argument('--rocks-first-seed', type=int, default=0, metavar='S',
                        help='first seed of --rocks-seeds (seeds S..S+N-1): seeds 0-7 are the '
                        'ones the planner and controller defaults were chosen on, so 8 and up '
                        'are held out')
    parser.add_argument('--rocks-variant', type=str, default='', metavar='JSON',
                        help='also walk the rocks seeds with these overrides of the defaults, '
                        'e.g. \'{"planner": {"stride_centre": "rule"}, "controller": '
                        '{"shift_zmp_offset_m": 0.008}}\' (a third row, "variant"); '
                        '"sim": {...} changes the simulated world for a diagnosis '
                        '(friction, foot_contact_stiffness and _damping, position_gain, '
                        'velocity_gain, servo_kp_nm_per_rad and servo_kd_nm_s_per_rad), '
                        '"course": {"max_height_m": H} the terrain (the same rocks scaled to '
                        'peak H)')
    parser.add_argument('--no-baseline', action='store_true',
                        help='leave out the rocks walks\' baseline row (the defaults against '
                        'a --rocks-variant only)')
    parser.add_argument('--rocks-course', default='rocks-6cm',
                        choices=('rocks-6cm', 'rocks-12cm', 'stones-15cm'),
                        help='course class of the --rocks-only walks, by the closed-loop '
                        'benchmark\'s robot for it (stones-15cm: FROG-I); default rocks-6cm')
    parser.add_argument('--rocks-remember-refusals', action='store_true',
                        help='the rocks walks do not offer again a step the running controller '
                        'refused although the dry run accepted it (footsteps.RefusedSteps, as '
                        'the planner node does); by default the walk ends after 3 refusals in '
                        'a row')
    parser.add_argument('--control-rate', type=float, default=None, metavar='HZ',
                        help='the rocks walks update the controller HZ times per simulated '
                        'second and follow its previewed trajectory between updates, as the '
                        'walking controller node (50 Hz) and the bridge do; default: every '
                        'physics step (500 Hz). A --rocks-variant may set its own '
                        '"control_rate_hz"')
    parser.add_argument('--workers', type=int, default=1, metavar='N',
                        help='walk the rocks seeds in N processes at once (each walk is its own '
                        'simulator, so the outcomes are those of one process; 2 on this '
                        'machine halves the wall time of a screen); default 1')
    parser.add_argument('--rocks-only', action='store_true',
                        help='only the rocks walks (no real-time factor and flat walks)')
    parser.add_argument('--no-localise', action='store_true',
                        help='do not re-anchor the rocks walks\' dead reckoning: by default it '
                        'is, before each plan, with the correction a perfect ICP would give '
                        '(T_map_odom from the true base pose), as the closed loop does with its '
                        'ICP; without, the drift of the slipping feet goes uncorrected (odom = '
                        'world: the walks before the nineteenth session)')
    parser.add_argument('--trace', type=str, default='', metavar='DIR',
                        help='trace every rocks walk (the truth and the controller\'s belief '
                        'every 10 ms) to DIR/rocks6-seed<S>[-<row>].npz and print how each '
                        'fall happened (terrain_perception.sim.trace.fall_report)')


# The multi-seed rocks walk's baseline: the defaults before the fourth session, when hind feet
# could close up on a blocked front foot and the body stayed level.
ROCKS_BASELINE_NAME = 'level body, no stance-length limit'
ROCKS_BASELINE = ({'min_stance_length': 0.0}, {'body_tilt_gain': 0.0})


def _rtf(course, robot: str, scale: float, sim_s: float) -> dict:
    from terrain_perception.sim.session import (SimSession, SimSessionConfig,
                                                measure_realtime_factor)
    session = SimSession(SimSessionConfig(robot=robot, image_scale=scale, settle_s=0.1),
                         course=course)
    try:
        out = measure_realtime_factor(session, sim_s, cameras=True)
        out_nocam = measure_realtime_factor(session, min(sim_s, 1.0), cameras=False)
    finally:
        session.close()
    out['rtf_physics_only'] = out_nocam['rtf']
    out['camera_rate_hz'] = session.camera_rate_hz
    return out


def _flat_walk(robot: str, distance_m: float, gait: str = 'walk') -> dict:
    from terrain_perception.sim.walk import make_flat_world, spawn_standing, walk
    m = load_robot_model(robot)
    client, plane = make_flat_world(DT)
    try:
        r = spawn_standing(client, m, dt_s=DT)
        T0 = r.base_pose()
        legs, pos = G.straight_footsteps(m, T0, distance_m, gait=gait)
        wall = time.perf_counter()
        res = walk(client, r, legs, pos, gait, dt_s=DT, max_time_s=40.0 * distance_m / 0.02,
                   ground_id=plane)
        wall = time.perf_counter() - wall
    finally:
        client.disconnect()
    fwd = T0[:2, 0] / np.linalg.norm(T0[:2, 0])
    advanced = float((res.T_end[:2, 3] - T0[:2, 3]) @ fwd)
    end = T0[:2, 3] + distance_m * fwd
    return {'robot': robot, 'gait': gait, 'distance_m': distance_m, 'fell': res.fell,
            'steps': res.steps_done, 'sim_s': res.sim_time_s,
            'speed_mps': advanced / res.sim_time_s,
            'end_err_m': float(np.linalg.norm(res.T_end[:2, 3] - end)),
            'foot_err_mean_m': float(np.mean(res.foot_errors_m)),
            'foot_err_p95_m': float(np.percentile(res.foot_errors_m, 95)),
            'rtf_walk': res.sim_time_s / wall}


STALL_S = 60.0   # the closed loop's default --stall-time


def _walk_session(course, robot_name: str, start_x: float, seed: int,
                  sim_kw: Optional[dict] = None):
    """The :class:`SimSession` of a ground-truth walk, with ``sim_kw``'s changes of the world
    (:data:`SIM_VARIANT_KEYS`) applied: the friction when the world is built, the feet's
    contact, pybullet's position servo gains (the profile's ``position_gain``,
    ``velocity_gain``) or the joints' PD servos (:meth:`SimRobot.use_pd_servo`) once the
    session has settled the robot on its rigid feet and the profile's servos."""
    from terrain_perception.sim.session import SimSession, SimSessionConfig
    from terrain_perception.sim.world import WorldConfig
    sim_kw = dict(sim_kw or {})
    world_cfg = WorldConfig(**({'friction': float(sim_kw['friction'])} if 'friction' in sim_kw
                               else {}))
    session = SimSession(SimSessionConfig(robot=robot_name, start_x_m=start_x, settle_s=0.3,
                                          course_seed=seed), course=course,
                         world_cfg=world_cfg)
    if 'foot_contact_stiffness' in sim_kw:
        for link in session.robot.foot_links:
            session.client.changeDynamics(
                session.robot.body_id, int(link),
                contactStiffness=float(sim_kw['foot_contact_stiffness']),
                contactDamping=float(sim_kw['foot_contact_damping']))
    gains = {k: float(sim_kw[k]) for k in ('position_gain', 'velocity_gain') if k in sim_kw}
    if gains:
        session.robot.model = dataclasses.replace(session.robot.model, **gains)
    if 'servo_kp_nm_per_rad' in sim_kw:
        session.robot.use_pd_servo(sim_kw['servo_kp_nm_per_rad'],
                                   sim_kw['servo_kd_nm_s_per_rad'])
    return session


def _rocks_walk(course, start_x: float, goal_x: float, seed: int, sensing: bool = True,
                planner_kw: Optional[dict] = None, walking_kw: Optional[dict] = None,
                trace_path=None, localise: bool = True, robot_name: str = 'littledog',
                remember_refusals: bool = False, control_rate_hz: Optional[float] = None,
                sim_kw: Optional[dict] = None, odom_error_m_per_plan: float = 0.0) -> dict:
    """Robot ``robot_name`` walks ``course`` from ``start_x`` towards ``goal_x`` on footsteps
    planned on the true terrain (receding horizon, every plan dry-run through the controller's
    checks).
    ``planner_kw``/``walking_kw`` override :class:`PlannerConfig`/:class:`WalkingConfig`
    defaults (the planner's after the robot's overlay, ``config/footstep_planner.ROBOT.yaml``,
    as the launched node has it). With ``trace_path`` the walk is traced
    (:mod:`terrain_perception.sim.trace`) to that .npz, and a fall's report is returned as
    ``fall_report``.

    The controller's dead reckoning drifts from the truth (the feet slip); without
    ``localise`` nothing corrects it (odom = world), so footsteps planned on the true
    terrain land where the drift puts them. ``localise`` re-anchors it before each plan with
    the correction a perfect ICP would give, ``T_map_odom = T_true_base inv(T_odom_base)``
    (the mapper's formula), and plans in the map (world) frame as the closed loop does.

    With ``remember_refusals`` a step the running controller refused although the planner's
    dry run accepted it is not offered again from that stance (:class:`RefusedSteps`, as the
    planner node does); without it the same plan is offered again and the walk ends after 3
    refusals in a row. ``control_rate_hz``: :class:`WalkRunner`'s (None: every physics
    step). ``sim_kw`` changes the simulated world for a diagnosis (:data:`SIM_VARIANT_KEYS`):
    ``friction`` of the terrain and floor, ``foot_contact_stiffness`` [N/m] and
    ``foot_contact_damping`` [N s/m] of the feet (pybullet's compliant contact; rigid without).
    ``odom_error_m_per_plan`` (tests): without ``localise``, the dead reckoning is also wrong
    by this much more to the left before each plan, as a slip the feet's contacts do not
    show (a short walk's natural drift is chaotic: the same walk drifts differently by machine)."""
    from terrain_perception.sim.trace import WalkTrace, fall_report
    from terrain_perception.footsteps import PlannerConfig, FootstepPlanner, RefusedSteps
    from terrain_perception.sim.walk import WalkRunner
    m = load_robot_model(robot_name)
    session = _walk_session(course, robot_name, start_x, seed, sim_kw)
    try:
        client, robot, world = session.client, session.robot, session.world
        height = world.height_at
        from terrain_perception.controller import WalkingConfig, check_footsteps
        wkw = {'plan_timeout_s': 1e6, **(walking_kw or {})}
        if not sensing:
            wkw.update(contact_force_n=0.0, attitude_gain=0.0)
        cfg = WalkingConfig(**wkw)
        trace = WalkTrace() if trace_path is not None else None
        runner = WalkRunner(client, robot, cfg, dt_s=DT, height=height,
                            ground_id=(world.floor_id, world.terrain_id), trace=trace,
                            control_rate_hz=control_rate_hz)
        # Walk gait only: LittleDog's profile has no trot (the controller's trot is Shao's
        # quasi-static one, COG on the diagonal). trot_threshold_m keeps its default: it is also
        # the flatness test of stride_centre 'adaptive'.
        from terrain_perception.bench.plan import robot_planner_overrides
        planner = FootstepPlanner(m, PlannerConfig(**{'cost_source': 'kolter', 'horizon_steps': 4,
                                                      **robot_planner_overrides(robot_name),
                                                      **(planner_kw or {})}))
        bad = planner.set_map(course)
        if bad is not None:
            raise ValueError(f'planner refused the course: {bad.status_text}')
        goal = np.array([goal_x, 0.0])
        next_leg, status, wall = None, 'ok', time.perf_counter()
        refused = 0
        memory = RefusedSteps() if remember_refusals else None
        best_x, best_t = -np.inf, 0.0
        injected = 0.0
        for _ in range(400):
            T = robot.base_pose()
            if T[0, 3] >= goal_x - 0.05 or runner.fell:
                break
            # As the closed loop's walk end (terrain-demo --stall-time 60): no 1 cm of progress
            # in 60 s of simulated time is a stall (stepping in place for the 400 plans took
            # 20 simulated minutes).
            if T[0, 3] >= best_x + 0.01:
                best_x, best_t = float(T[0, 3]), runner.t
            elif runner.t - best_t >= STALL_S:
                status = f'stalled: no 1 cm of progress in {STALL_S:.0f} s ({status})'
                break
            # As the planner node does: from the controller's own stance and body pose (its
            # /walking/stance, put in the map with its T_map_odom; the identity unless
            # localised), only the steps its own checks accept.
            ctl = runner.controller
            if localise:
                ctl.apply_correction(T @ invert(ctl.odom_pose))
            elif odom_error_m_per_plan:
                injected += odom_error_m_per_plan
                ctl.apply_correction(make_T(np.eye(3), [0.0, injected, 0.0]))
            feet, _ = ctl.upcoming_stance()
            feet = transform_points(ctl.T_map_odom, feet)
            T_chk = ctl.T_map_odom @ ctl.upcoming_body()
            done0, now = ctl.steps_done, runner.t

            def check(legs, pos, feet=feet, T_chk=T_chk, done0=done0, now=now):
                if memory is not None and len(legs):
                    why = memory.refusal(done0, legs[0], pos[0], now)
                    if why is not None:
                        return 0, f'the controller refused this step before: {why}'
                return check_footsteps(m, cfg, feet, legs, pos, 'walk', height, T_body=T_chk)
            plan = planner.plan_checked(T, goal, feet, check, first_leg=next_leg)
            if not plan.ok:
                status = f'planner: {plan.status_text}'
                break
            legs = np.array([f.leg for f in plan.footsteps])
            pos = np.array([f.position for f in plan.footsteps])
            gait = 'trot' if plan.gait == 2 else 'walk'
            done_before = runner.controller.steps_done
            if memory is not None and len(legs):
                memory.offered(done0, int(legs[0]), pos[0], now)
            ran = runner.run(legs, pos, gait, max_time_s=30.0, frame='map')
            if memory is not None:
                memory.report(ctl.steps_done, '' if ran else ctl.last_error, runner.t)
            if not ran:
                # A refused step: replan from where the robot stands (receding horizon);
                # give up after 3 refusals in a row.
                status = f'controller: {runner.controller.last_error or "timeout"}'
                refused += 1
                if refused >= 3 or runner.fell:
                    break
                if runner.controller.steps_done == done_before:
                    continue
                last = legs[runner.controller.steps_done - done_before - 1]
            else:
                refused, status, last = 0, 'ok', legs[-1]
            order = list(G.CRAWL_ORDER)
            next_leg = order[(order.index(int(last)) + 1) % 4]
        wall = time.perf_counter() - wall
        res = runner.result()
    finally:
        session.close()
    advanced = float(res.T_end[0, 3] - res.T_start[0, 3])
    extra = {}
    if trace is not None:
        trace.save(trace_path, seed=seed, status=status, fell=res.fell,
                   planner_kw=json.dumps(planner_kw or {}), walking_kw=json.dumps(wkw))
        # Only a walk the runner counted fallen: one can survive a 20 deg wobble.
        extra = {'trace': str(trace_path),
                 'fall_report': fall_report(trace.arrays()) if res.fell else None}
    return {**extra, 'robot': robot_name,
            'course': str(course.metadata.get('class', 'rocks-6cm')), 'seed': seed,
            'start_x_m': start_x,
            'sensing': sensing,
            'goal_x_m': goal_x, 'reached': bool(res.T_end[0, 3] >= goal_x - 0.05),
            'status': status, 'fell': res.fell, 'steps': res.steps_done,
            'advanced_m': advanced, 'sim_s': res.sim_time_s,
            'speed_mps': advanced / max(res.sim_time_s, 1e-9),
            'foot_err_mean_m': float(np.mean(res.foot_errors_m)) if len(res.foot_errors_m)
            else float('nan'),
            'foot_err_p95_m': float(np.percentile(res.foot_errors_m, 95))
            if len(res.foot_errors_m) else float('nan'),
            'max_tilt_deg': res.max_tilt_deg,
            'leg_ground_checks': int(res.extra.get('leg_ground_steps', 0)),
            'rtf_walk': res.sim_time_s / wall}


#: The ``sim`` section of ``--rocks-variant``: changes of the simulated world, for diagnoses.
SIM_VARIANT_KEYS = ('friction', 'foot_contact_stiffness', 'foot_contact_damping',
                    'servo_kp_nm_per_rad', 'servo_kd_nm_s_per_rad', 'position_gain',
                    'velocity_gain')
#: The ``course`` section of ``--rocks-variant``: the course class's terrain changed for the
#: variant row (same seeds, so the same rock layout, scaled): how outcomes depend on it.
COURSE_VARIANT_KEYS = ('max_height_m',)


def parse_rocks_variant(text: str) -> Optional[dict]:
    """``--rocks-variant``: ``{"planner": {...}, "controller": {...}, "sim": {...},
    "course": {...}, "control_rate_hz": HZ}`` (any of them) or None if empty; ValueError
    naming the problem otherwise (unknown sections or parameters included). ``sim``
    (:data:`SIM_VARIANT_KEYS`) changes the simulated world, not the robot's software: a
    diagnosis, e.g. whether more friction or compliant feet change the outcome. ``course``
    (:data:`COURSE_VARIANT_KEYS`) changes the terrain: the same seeds' rocks scaled to another
    peak height, for how the outcome depends on the terrain's height."""
    if not text:
        return None
    try:
        v = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ValueError(f'--rocks-variant is not JSON: {exc}') from None
    sections = {'planner', 'controller', 'sim', 'course'}
    if not isinstance(v, dict) or not v or set(v) - sections - {'control_rate_hz'} or \
            not all(isinstance(v[k], dict) for k in sections & set(v)):
        raise ValueError('--rocks-variant must be an object with "planner", "controller", '
                         '"sim" and/or "course" objects of parameters and/or a '
                         f'"control_rate_hz", got {text!r}')
    sim = dict(v.get('sim', {}))
    unknown = set(sim) - set(SIM_VARIANT_KEYS)
    if unknown:
        raise ValueError(f'--rocks-variant: "sim" has no parameter(s) {sorted(unknown)}; '
                         f'known: {list(SIM_VARIANT_KEYS)}')
    for key, val in sim.items():
        if isinstance(val, bool) or not (isinstance(val, (int, float)) and np.isfinite(val)
                                         and val > 0):
            raise ValueError(f'--rocks-variant: sim {key} must be a positive number, got '
                             f'{val!r}')
    if ('foot_contact_stiffness' in sim) != ('foot_contact_damping' in sim):
        raise ValueError('--rocks-variant: sim foot_contact_stiffness and '
                         'foot_contact_damping go together (pybullet needs both)')
    if ('servo_kp_nm_per_rad' in sim) != ('servo_kd_nm_s_per_rad' in sim):
        raise ValueError('--rocks-variant: sim servo_kp_nm_per_rad and servo_kd_nm_s_per_rad '
                         'go together (the PD servo needs both)')
    course = dict(v.get('course', {}))
    unknown = set(course) - set(COURSE_VARIANT_KEYS)
    if unknown:
        raise ValueError(f'--rocks-variant: "course" has no parameter(s) {sorted(unknown)}; '
                         f'known: {list(COURSE_VARIANT_KEYS)}')
    peak = course.get('max_height_m')
    if peak is not None and (isinstance(peak, bool) or not isinstance(peak, (int, float))
                             or not 0.0 < peak <= 0.5):
        raise ValueError(f'--rocks-variant: course max_height_m must be a height in (0, 0.5] '
                         f'm, got {peak!r}')
    rate = v.get('control_rate_hz')
    if rate is not None and not (isinstance(rate, (int, float)) and np.isfinite(rate)
                                 and rate > 0):
        raise ValueError(f'--rocks-variant: control_rate_hz must be a positive number, got '
                         f'{rate!r}')
    from terrain_perception.controller import WalkingConfig
    from terrain_perception.footsteps import PlannerConfig
    for key, cls in (('planner', PlannerConfig), ('controller', WalkingConfig)):
        unknown = set(v.get(key, {})) - set(cls.__dataclass_fields__)
        if unknown:
            raise ValueError(f'--rocks-variant: {cls.__name__} has no parameter(s) '
                             f'{sorted(unknown)}')
    out = {'planner': dict(v.get('planner', {})), 'controller': dict(v.get('controller', {})),
           'sim': sim, 'course': course}
    if rate is not None:
        out['control_rate_hz'] = float(rate)
    return out


def _trace_path(trace_dir: str, seed: int, row: str = '', course_class: str = 'rocks-6cm'):
    """Where a rocks walk's trace goes (None without ``--trace``)."""
    from pathlib import Path
    if not trace_dir:
        return None
    stem = 'rocks6' if course_class == 'rocks-6cm' else course_class
    return Path(trace_dir) / f'{stem}-seed{seed}{"-" + row if row else ""}.npz'


def _print_fall_reports(walks) -> None:
    for name, r in walks:
        if r.get('fall_report'):
            print(f'\n--- {name}, seed {r["seed"]}: how it fell (trace {r["trace"]})\n'
                  + r['fall_report'])


def _rocks_job(args: tuple) -> dict:
    """One :func:`_rocks_walk` of ``(course class, start x, goal x, seed, keyword
    arguments[, course overrides])``, the course made here (a worker process's job); the
    overrides (:data:`COURSE_VARIANT_KEYS`) replace fields of the class's CourseConfig."""
    from terrain_perception.terrain import course_config, make_course
    course_class, start_x, goal_x, seed, walk_kw = args[:5]
    changes = args[5] if len(args) > 5 else None
    cfg = dataclasses.replace(course_config(course_class), **changes) if changes else None
    return _rocks_walk(make_course(course_class, seed, 0.005, cfg), start_x, goal_x, seed,
                       **walk_kw)


def _rocks_seeds(n: int, start_x: float, goal_x: float, first: int = 0,
                 variant: Optional[dict] = None, trace_dir: str = '',
                 localise: bool = True, course_class: str = 'rocks-6cm',
                 baseline: bool = True, remember_refusals: bool = False,
                 control_rate_hz: Optional[float] = None, workers: int = 1) -> dict:
    """The ground-truth-footstep walk over ``course_class`` (by the closed-loop benchmark's
    robot for it: LittleDog on the rocks, FROG-I on the stones) on seeds first..first+n-1,
    defaults against the baseline (and a variant of the defaults, if given); traced to
    ``trace_dir`` if given, localised (:func:`_rocks_walk`) if asked; ``workers`` walks at
    once, each in its own process (the same outcomes: every walk has its own simulator)."""
    from terrain_perception.bench.closed_loop import COURSES
    robot_name = COURSES[course_class]
    rows = {'default': [], 'baseline': []} if baseline else {'default': []}
    if variant is not None:
        rows['variant'] = []
    seeds = list(range(first, first + n))
    kw = dict(localise=localise, robot_name=robot_name,
              remember_refusals=remember_refusals, control_rate_hz=control_rate_hz)
    jobs = []          # (row, seed, keyword arguments of _rocks_walk, course overrides)

    def add(row: str, seed: int, course=None, **extra) -> None:
        jobs.append((row, seed, {**kw, **extra, 'trace_path': _trace_path(
            trace_dir, seed, row, course_class)}, course or None))
    for seed in seeds:
        add('default', seed)
        if baseline:
            add('baseline', seed, planner_kw=ROCKS_BASELINE[0], walking_kw=ROCKS_BASELINE[1])
        if variant is not None:
            add('variant', seed, planner_kw=variant['planner'],
                walking_kw=variant['controller'], sim_kw=variant.get('sim') or None,
                control_rate_hz=variant.get('control_rate_hz', control_rate_hz),
                course=variant.get('course'))
    args = [(course_class, start_x, goal_x, seed, walk_kw, course)
            for _, seed, walk_kw, course in jobs]
    if workers > 1 and len(jobs) > 1:
        import multiprocessing
        # spawn: a fresh interpreter per worker, nothing of this process's state (a pybullet
        # client) inherited
        with multiprocessing.get_context('spawn').Pool(min(workers, len(jobs))) as pool:
            results = pool.map(_rocks_job, args, chunksize=1)
    else:
        results = [_rocks_job(a) for a in args]
    for (row, _, _, _), r in zip(jobs, results):
        rows[row].append(r)
    print(f'\n{course_class} ({robot_name}), ground-truth footsteps'
          f'{", localised" if localise else ""}'
          f'{", refused steps remembered" if remember_refusals else ""}'
          f'{f", controller at {control_rate_hz:g} Hz" if control_rate_hz else ""}, '
          f'x {start_x} -> {goal_x} m, seeds '
          f'{seeds[0]}-{seeds[-1]}{" (held out: defaults chosen on 0-7)" if first >= 8 else ""} '
          '(F = fell, X = crossed)'
          + (f'; baseline: {ROCKS_BASELINE_NAME} (planner {ROCKS_BASELINE[0]}, controller '
             f'{ROCKS_BASELINE[1]})' if baseline else '')
          + (f'; variant: the defaults with planner {variant["planner"]}, controller '
             f'{variant["controller"]}'
             + (f', controller at {variant["control_rate_hz"]:g} Hz'
                if variant.get('control_rate_hz') else '')
             + (f', simulated world {variant["sim"]}' if variant.get('sim') else '')
             + (f', course {variant["course"]}' if variant.get('course') else '')
             if variant is not None else ''))
    summary = {}
    for name, rs in rows.items():
        crossed = [r['reached'] and not r['fell'] for r in rs]
        marks = ' '.join(f'{r["advanced_m"]:.2f}' + ('F' if r['fell'] else '')
                         + ('X' if c else '') for r, c in zip(rs, crossed))
        summary[name] = {
            'crossed': int(sum(crossed)),
            'falls': int(sum(r['fell'] for r in rs)),
            'advanced_m_mean': float(np.mean([r['advanced_m'] for r in rs])),
            # simulated time of the walks that crossed: how fast, where it worked
            'crossing_sim_s_median': float(np.median([r['sim_s'] for r, c in zip(rs, crossed)
                                                      if c])) if any(crossed) else None,
            'seeds': n, 'first_seed': first}
        t = summary[name]['crossing_sim_s_median']
        print(f'{name:<9} {marks}  | crossed {summary[name]["crossed"]}/{n}, falls '
              f'{summary[name]["falls"]}, mean advance {summary[name]["advanced_m_mean"]:.2f} m'
              + (f', crossing time median {t:.0f} s sim' if t is not None else ''))
    if trace_dir:
        # how the swing feet met the ground, every touchdown of the row's traced walks
        from terrain_perception.robot_model import load_robot_model
        from terrain_perception.sim.trace import landing_summary
        weight = load_robot_model(robot_name).total_mass_kg * 9.81
        for name, rs in rows.items():
            ls = landing_summary([r['trace'] for r in rs if r.get('trace')], weight)
            summary[name]['landings'] = ls
            if ls['count']:
                print(f'{name:<9} touchdowns {ls["count"]}: descent at contact '
                      f'{ls["descent_m_s_median"]:.2f} m/s median (p90 '
                      f'{ls["descent_m_s_p90"]:.2f}), at {ls["swing_fraction_median"]:.2f} '
                      f'of the swing; peak force {ls["peak_n_median"]:.0f} N median (p90 '
                      f'{ls["peak_n_p90"]:.0f}), {100 * ls["share_over_weight"]:.0f} % above '
                      f'the robot\'s weight ({weight:.0f} N)')
    _print_fall_reports((name, r) for name, rs in rows.items() for r in rs)
    # the keys keep their rocks-6cm names (the results of earlier sessions); 'course' and
    # 'robot' say what was walked
    return {'rocks6_seeds': summary, 'rocks6_seed_rows': rows, 'rocks_localised': localise,
            'course': course_class, 'robot': robot_name, 'variant': variant}


def run(args: argparse.Namespace) -> dict:
    from terrain_perception.terrain import make_course
    quick = bool(getattr(args, 'quick', False))
    seed = int(getattr(args, 'seed', 0))
    n_rocks = int(getattr(args, 'rocks_seeds', 0) or 0)
    variant = parse_rocks_variant(getattr(args, 'rocks_variant', '') or '')
    trace_dir = str(getattr(args, 'trace', '') or '')
    localise = not bool(getattr(args, 'no_localise', False))
    rocks_course = str(getattr(args, 'rocks_course', '') or 'rocks-6cm')
    if rocks_course != 'rocks-6cm' and not getattr(args, 'rocks_only', False):
        raise ValueError(f'--rocks-course {rocks_course} needs --rocks-only (the full run walks '
                         'rocks-6cm)')
    if getattr(args, 'rocks_only', False):
        if n_rocks <= 0:
            raise ValueError('--rocks-only needs --rocks-seeds N (N >= 1)')
        # from 0.6 m before the rough section to 0.4 m past it (rocks-6cm: x 0.4 -> 2.4 m;
        # stones-15cm, 1.5 m of approach and 2 m of stones: 0.9 -> 3.9 m)
        from terrain_perception.terrain import course_config
        cc = course_config(rocks_course)
        return _rocks_seeds(n_rocks, cc.approach_m - 0.6, cc.approach_m + cc.rough_length_m + 0.4,
                            int(getattr(args, 'rocks_first_seed', 0)), variant, trace_dir,
                            localise, rocks_course, not getattr(args, 'no_baseline', False),
                            bool(getattr(args, 'rocks_remember_refusals', False)),
                            getattr(args, 'control_rate', None),
                            max(1, int(getattr(args, 'workers', 1) or 1)))
    course = make_course('rocks-6cm', seed, 0.005)

    rtf_rows = []
    scales = (1.0,) if quick else (0.5, 1.0)
    for robot in ('littledog', 'frog'):
        for scale in scales:
            r = _rtf(course, robot, scale, 1.5 if quick else 6.0)
            r.update(robot=robot, scale=scale)
            rtf_rows.append(r)
    print('\nReal-time factor, SimSession on rocks-6cm (physics 500 Hz, states 100 Hz, '
          'stereo pairs at the camera rate)')
    print(f'{"robot":<10} {"image":>9} {"cam Hz":>7} {"RTF":>7} {"RTF no cam":>11} '
          f'{"ms/pair":>8}')
    for r in rtf_rows:
        print(f'{r["robot"]:<10} {r["image"]:>9} {r["camera_rate_hz"]:>7.1f} {r["rtf"]:>7.2f} '
              f'{r["rtf_physics_only"]:>11.2f} {r["render_ms_per_pair"]:>8.1f}')

    flat = [_flat_walk('littledog', 0.6 if quick else 2.0),
            _flat_walk('littledog', 0.6 if quick else 2.0, 'trot')]
    if not quick:
        flat.append(_flat_walk('frog', 2.0))
        flat.append(_flat_walk('frog', 2.0, 'trot'))
    rocks = _rocks_walk(course, 0.8 if quick else 0.4, 1.3 if quick else 2.4, seed,
                        trace_path=_trace_path(trace_dir, seed), localise=localise)
    # baseline: the same controller without touchdown sensing and levelling (open loop)
    rocks_blind = _rocks_walk(course, 0.8 if quick else 0.4, 1.3 if quick else 2.4, seed,
                              sensing=False, localise=localise)
    print('\nWalking (controller at every physics step, ground truth from the simulator)')
    print(f'{"case":<22} {"dist m":>7} {"sim s":>7} {"speed m/s":>10} {"foot err mean":>14} '
          f'{"p95":>7} {"end err":>8} {"fell":>5} {"RTF":>5}')
    for r in flat:
        case = f'{r["robot"]} flat {r["gait"]}'
        print(f'{case:<22} {r["distance_m"]:>7.2f} {r["sim_s"]:>7.1f} '
              f'{r["speed_mps"]:>10.4f} {r["foot_err_mean_m"]:>14.4f} {r["foot_err_p95_m"]:>7.4f}'
              f' {r["end_err_m"]:>8.4f} {str(r["fell"]):>5} {r["rtf_walk"]:>5.2f}')
    for name, r in (('littledog rocks-6cm', rocks), ('  open loop (baseline)', rocks_blind)):
        print(f'{name:<22} {r["advanced_m"]:>7.2f} {r["sim_s"]:>7.1f} '
              f'{r["speed_mps"]:>10.4f} {r["foot_err_mean_m"]:>14.4f} '
              f'{r["foot_err_p95_m"]:>7.4f} {"-":>8} {str(r["fell"]):>5} {r["rtf_walk"]:>5.2f}')
    for what, r in (('touchdown sensing + levelling', rocks), ('open loop', rocks_blind)):
        print(f'rocks-6cm {what}: x {r["start_x_m"]} -> {r["goal_x_m"]} m, '
              f'reached={r["reached"]}, status: {r["status"]}, steps {r["steps"]}, max tilt '
              f'{r["max_tilt_deg"]:.1f} deg')
    _print_fall_reports([('littledog rocks-6cm', rocks)])

    native = {row['robot']: row for row in rtf_rows if row['scale'] == 1.0}
    out = {
        'rtf_littledog': native['littledog']['rtf'],
        'rtf_frog': native['frog']['rtf'],
        'foot_err_flat_m': flat[0]['foot_err_mean_m'],
        'foot_err_rocks6_m': rocks['foot_err_mean_m'],
        'speed_flat_mps': flat[0]['speed_mps'],
        'speed_flat_trot_mps': flat[1]['speed_mps'],
        'rtf_rows': rtf_rows,
        'flat': flat,
        'rocks6': rocks,
        'rocks6_open_loop': rocks_blind,
        'rocks6_advanced_m': rocks['advanced_m'],
        'rocks6_open_loop_advanced_m': rocks_blind['advanced_m'],
        'quick': quick,
        'rocks_localised': localise,
    }
    if n_rocks > 0:
        out.update(_rocks_seeds(n_rocks, 0.4, 2.4, int(getattr(args, 'rocks_first_seed', 0)),
                                variant, trace_dir, localise,
                                baseline=not getattr(args, 'no_baseline', False),
                                workers=max(1, int(getattr(args, 'workers', 1) or 1))))
    return out
