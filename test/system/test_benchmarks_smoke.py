# test_benchmarks_smoke: the benchmarks still run (their short form); figures not judged.
"""`benchmarks/run_all.py --smoke` exits 0 and every benchmark prints its ratio lines."""

import os
from pathlib import Path
import re
import subprocess
import sys

import pytest

REPO = Path(__file__).resolve().parents[2]


def test_p2_runs_again_a_run_its_driver_did_not_hear(monkeypatch):
    # one_process starts its run at once: a driver that discovers it late hears nothing
    sys.path.insert(0, str(REPO / 'benchmarks'))
    import p2_closed_loop as p2
    calls, said = [], []

    def late_twice(*args, **kwargs):
        calls.append(args)
        if len(calls) <= p2.DISCOVERY_RETRIES:
            raise p2.DiscoveryLate('P2: not heard')
        return {'on_time': 1.0}
    monkeypatch.setattr(p2, '_one_run', late_twice)
    assert p2._one_run_heard(said.append, 'node', 'state') == {'on_time': 1.0}
    assert len(calls) == p2.DISCOVERY_RETRIES + 1 and len(said) == p2.DISCOVERY_RETRIES
    assert said[0] == f'  P2: not heard: run again (2 of {p2.DISCOVERY_RETRIES + 1})'
    # never heard: the last run's error, after DISCOVERY_RETRIES runs again
    calls.clear()

    def never(*args, **kwargs):
        calls.append(args)
        raise p2.DiscoveryLate('P2: not heard')
    monkeypatch.setattr(p2, '_one_run', never)
    with pytest.raises(p2.DiscoveryLate):
        p2._one_run_heard(said.append, 'node', 'state')
    assert len(calls) == p2.DISCOVERY_RETRIES + 1


@pytest.mark.ros
def test_run_all_smoke_prints_every_ratio():
    env = dict(os.environ)
    env['BENCH_ROS_DOMAIN_ID'] = '46'        # apart from a full benchmark run (47)
    env['ROS_DOMAIN_ID'] = '46'
    script = REPO / 'benchmarks' / 'run_all.py'
    proc = subprocess.run(
        [sys.executable, '-W', 'ignore::DeprecationWarning', str(script), '--smoke'],
        cwd=REPO, env=env, capture_output=True, text=True, timeout=480)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, out[-4000:]
    for bench, names in {
        'P1': ['median_latency_observer/relay', 'p99_latency_observer/relay'],
        'P2': [f'on_time_fraction_at_1kHz[{layout}]'
               for layout in ('processes', 'container', 'one_process')] + [
            'on_time_fraction_at_1kHz[processes,bare]',
            'on_time_fraction_nodes-bare_at_1kHz[processes]',
            'highest_rate_on_time_nodes/bare[processes]'],
        'P3': ['eval/rosbags_read_deserialise', 'eval/control_forced_response'],
        'P4': ['placement_error_ours/place_worst_single_output',
               'placement_error_ours/place_worst_multi_output',
               'acker_chosen_where_it_loses_digits'],
        'P5': [f'rewind_100ms_at_1kHz/in_order[{kind}]' for kind in ('kalman', 'full')],
        'M1': [f'{what}_{figure}_per_message_spilled/in_memory' for what in ('reader', 'eval')
               for figure in ('kept', 'peak')] + ['search_peak_4_scales-1_scale_spilled',
                                                  'eval_spilled_kept_per_further_variant'],
    }.items():
        for name in names:
            assert re.search(rf'^RATIO {bench} {re.escape(name)} = \S+', out, re.M), \
                f'{bench} {name} missing:\n{out[-4000:]}'
    assert 'FAILED' not in out
