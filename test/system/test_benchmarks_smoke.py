# test_benchmarks_smoke: the benchmarks still run (their short form); figures not judged.
"""`benchmarks/run_all.py --smoke` exits 0 and every benchmark prints its ratio lines."""

import os
from pathlib import Path
import re
import subprocess
import sys

import pytest

pytestmark = pytest.mark.ros      # processes or DDS participants

REPO = Path(__file__).resolve().parents[2]


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
