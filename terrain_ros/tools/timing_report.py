"""Where capture-to-plan wall time goes, from a ``TERRAIN_TIMING_DIR`` trace.

``python -m terrain_ros.tools.timing_report DIR [--json F]``: ``DIR`` holds the JSON lines
that :mod:`terrain_ros.timing` wrote for each node of a run (``terrain-demo`` with
``TERRAIN_TIMING_DIR=DIR`` in its environment passes it to every node). For each stage of the
chain (the left image -> stereo -> ``/stereo/points`` -> ICP mapper -> ``/map/fine`` -> fill
-> ``/map/filled`` -> planner -> ``/footstep_plan``) it joins the upstream publish, the node's
take and callback, and its own publish on the message stamp, and prints the medians of:

* ``wait``: from the end of the upstream ``publish()`` to the start of the take (middleware
  delivery plus the time the node's executor was busy or not scheduled);
* ``take``: deserialisation (wall; CPU beside it);
* ``cb``: the callback up to the start of its output's ``publish()`` (wall; CPU of the whole
  callback beside it: the callback's wall minus CPU is time the process was runnable but not
  running, or blocked);
* ``runq``: time the callback's thread waited on a CPU run queue (runnable, another process
  on the core) during the whole callback;
* ``pub``: the output's ``publish()`` (serialisation, hand-over);
* ``stage``: end of the upstream publish to end of the output publish.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path
from typing import Dict, List, Optional, Tuple

CHAIN = (('stereo', '/stereo/left/image_rect', '/stereo/points'),
         ('icp_mapper', '/stereo/points', '/map/fine'),
         ('terrain_fill', '/map/fine', '/map/filled'),
         ('footstep_planner', '/map/filled', '/footstep_plan'))
PARTS = ('wait', 'take', 'take_cpu', 'cb', 'cb_cpu', 'runq', 'pub', 'stage')


def load(directory: Path) -> Dict[str, List[dict]]:
    """node name -> its records (every ``*.jsonl`` in ``directory``)."""
    out: Dict[str, List[dict]] = {}
    for f in sorted(directory.glob('*.jsonl')):
        name = f.name.split('.')[0]
        with open(f) as fh:
            out.setdefault(name, []).extend(json.loads(line) for line in fh if line.strip())
    if not out:
        raise FileNotFoundError(f'no *.jsonl timing trace in {directory}')
    return out


def stage_parts(records: Dict[str, List[dict]]) -> Dict[str, Dict[str, List[float]]]:
    """stage -> part -> ms per capture, joined on (topic, stamp)."""
    pubs: Dict[Tuple[str, float], Tuple[str, dict]] = {}
    takes: Dict[str, List[dict]] = {}
    for node, recs in records.items():
        for r in recs:
            if r['k'] == 'take':
                takes.setdefault(node, []).append(r)
            elif r.get('stamp') is not None:
                pubs.setdefault((r['topic'], r['stamp']), (node, r))  # the first publish
    for recs in takes.values():
        recs.sort(key=lambda r: r['t2'])
    out: Dict[str, Dict[str, List[float]]] = {}
    for stage, topic_in, topic_out in CHAIN:
        parts: Dict[str, List[float]] = {p: [] for p in PARTS}
        for (topic, stamp), (_, up) in pubs.items():
            if topic != topic_in or (topic_out, stamp) not in pubs:
                continue
            node, down = pubs[(topic_out, stamp)]
            # the callback of that node during which the output was published
            t = next((r for r in takes.get(node, ())
                      if r['t2'] <= down['t0'] <= r['t3'] + 1e-6), None)
            if t is None:
                continue
            ms = 1000.0
            parts['wait'].append(ms * (t['t0'] - up['t1']))
            parts['take'].append(ms * (t['t1'] - t['t0']))
            parts['take_cpu'].append(ms * t['take_cpu'])
            parts['cb'].append(ms * (down['t0'] - t['t2']))
            parts['cb_cpu'].append(ms * t['cb_cpu'])
            parts['runq'].append(ms * t.get('cb_runq', 0.0))
            parts['pub'].append(ms * (down['t1'] - down['t0']))
            parts['stage'].append(ms * (down['t1'] - up['t1']))
        out[stage] = parts
    return out


def _median(v: List[float]) -> Optional[float]:
    return round(statistics.median(v), 1) if v else None


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog='timing_report', description=__doc__.split('\n')[0])
    p.add_argument('dir', type=Path, help='TERRAIN_TIMING_DIR of a run')
    p.add_argument('--json', type=Path, default=None, help='write the medians here')
    args = p.parse_args(argv)
    try:
        parts = stage_parts(load(args.dir))
    except (OSError, ValueError) as exc:
        print(f'timing_report: {exc}', file=sys.stderr)
        return 2
    print(f'{"stage":18s}{"n":>5s}' + ''.join(f'{k:>10s}' for k in PARTS) + '   (ms, medians)')
    summary = {}
    for stage, d in parts.items():
        med = {k: _median(v) for k, v in d.items()}
        summary[stage] = dict(med, n=len(d['stage']))
        print(f'{stage:18s}{len(d["stage"]):5d}'
              + ''.join(f'{"-" if med[k] is None else med[k]:>10}' for k in PARTS))
    if args.json:
        args.json.write_text(json.dumps(summary, indent=1))
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
