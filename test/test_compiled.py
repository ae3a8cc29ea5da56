"""The optional-kernel loader: the environment switch and a missing module fall back to numpy."""

import logging

from terrain_perception.compiled import load_compiled

LOG = logging.getLogger('test_compiled')


def test_the_switch_and_a_failed_import_select_the_numpy_code(monkeypatch, caplog):
    monkeypatch.setenv('TERRAIN_TEST_NUMBA', '1')
    mod = load_compiled('_ik_kernel', 'TERRAIN_TEST_NUMBA', 'leg IK', LOG)
    assert mod is not None and hasattr(mod, 'solve_legs')
    for off in ('0', 'false', ' OFF ', 'no'):
        monkeypatch.setenv('TERRAIN_TEST_NUMBA', off)
        assert load_compiled('_ik_kernel', 'TERRAIN_TEST_NUMBA', 'leg IK', LOG) is None
    monkeypatch.delenv('TERRAIN_TEST_NUMBA')
    with caplog.at_level(logging.WARNING, logger='test_compiled'):
        assert load_compiled('_no_such_kernels', 'TERRAIN_TEST_NUMBA', 'a stage', LOG,
                             'using the slow path') is None
    assert 'a stage: numba is not available' in caplog.text and 'the slow path' in caplog.text
