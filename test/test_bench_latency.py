"""terrain-bench latency: each variant's launch file is the demo's with exactly its node
parameters changed, and it starts the nodes with them (parsed as terrain-launch parses it)."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from terrain_perception.bench import latency
from terrain_ros.tools.launch import load_launch_file


def _params(spec) -> dict:
    cmd = spec.command
    return dict(cmd[i + 1].split(':=', 1) for i, a in enumerate(cmd) if a == '-p')


@pytest.mark.parametrize('name', list(latency.VARIANTS))
def test_variant_launch_sets_its_parameters_and_nothing_else(tmp_path: Path, name: str):
    f = tmp_path / f'{name}.yaml'
    f.write_text(latency.variant_launch(name))
    got = {s.name: (_params(s), s.nice) for s in load_launch_file(f, {})}
    want = {s.name: (_params(s), s.nice) for s in load_launch_file(latency.LAUNCH, {})}
    for node, change in latency.VARIANTS[name].items():
        if node == '-demo':
            continue
        for k, v in change.get('parameters', {}).items():
            assert got[node][0][k] == (str(v).lower() if isinstance(v, bool) else str(v))
            want[node][0][k] = got[node][0][k]
        if 'nice' in change:
            assert got[node][1] == change['nice']
            want[node] = (want[node][0], change['nice'])
    assert got == want


def test_baseline_is_the_earlier_settings_and_shipped_the_defaults():
    # The baseline undoes the fifteenth and sixteenth sessions' latency changes, 'fifteenth'
    # the sixteenth's; 'shipped' changes nothing.
    before = latency.VARIANTS[latency.BASELINE]
    assert before['stereo_node'] == {'parameters': {'process_on_arrival': False,
                                                    'rate_clock': 'node'}}
    bridge = yaml.safe_load((latency.LAUNCH.parent.parent / 'sim_bridge.yaml').read_text())
    shipped = bridge['sim_bridge']['ros__parameters']
    stereo = yaml.safe_load((latency.LAUNCH.parent.parent / 'stereo_node.yaml').read_text())
    assert stereo['stereo_node']['ros__parameters']['process_on_arrival'] is True
    assert stereo['stereo_node']['ros__parameters']['rate_clock'] == 'steady'
    launch = {n['name']: n for n in yaml.safe_load(latency.LAUNCH.read_text())['nodes']}
    assert launch['sim_bridge'].get('nice', 0) > 0
    for name in (latency.BASELINE, 'fifteenth'):
        change = latency.VARIANTS[name]
        params = change['sim_bridge']['parameters']
        assert params['tick_period_s'] != shipped['tick_period_s']
        assert change['sim_bridge']['nice'] == 0
        assert change['-demo'] == ['--recorder-nice', '0']
    assert before['sim_bridge']['parameters']['clock_rate_hz'] != shipped['clock_rate_hz']
    assert 'clock_rate_hz' not in latency.VARIANTS['fifteenth']['sim_bridge']['parameters']
    assert latency.VARIANTS['shipped'] == {}
    assert set(latency.DEFAULT_VARIANTS) <= set(latency.VARIANTS)


def test_unknown_node_in_a_variant_is_refused(monkeypatch):
    monkeypatch.setitem(latency.VARIANTS, 'bad', {'no_such_node': {'parameters': {'x': 1}}})
    with pytest.raises(ValueError, match="no node 'no_such_node'"):
        latency.variant_launch('bad')
