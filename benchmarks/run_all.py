# benchmarks/run_all.py: run every benchmark (make bench), or their smoke form (--smoke).
"""
Run the observer_ros benchmarks P1..P5 and M1 and print each figure as a ratio to its baseline.

Each benchmark runs in its own process (``benchmarks/p*.py``, also runnable alone) with
the benchmarks' ROS domain (``ROS_DOMAIN_ID`` 47, or ``$BENCH_ROS_DOMAIN_ID``); every
figure is printed on a line starting ``RATIO <id>``. ``--smoke`` runs each for a few
seconds, only to check that it still runs (CI: test/system/test_benchmarks_smoke.py); the
targets are then not judged.

Exit status: 0 when every benchmark ran (targets met or not: these are measurements),
1 when one failed, or with ``--strict`` when a target was missed.

"""

import argparse
import json
from pathlib import Path
import subprocess
import sys
import tempfile
import time

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import machine_info, ros_env  # noqa: E402

HERE = Path(__file__).resolve().parent
BENCHMARKS = {
    'P1': ('p1_latency.py', 'observer node latency vs a bare relay (DDS, 3 processes)'),
    'P2': ('p2_closed_loop.py', 'closed loop at 1 kHz in free-running real time'),
    'P3': ('p3_replay.py', 'observer-eval on a synthetic Imu bag vs rosbags / control'),
    'P4': ('p4_design.py', 'gain design accuracy vs python-control place'),
    'P5': ('p5_rewind.py', 'a late measurement: rewind over 100 ms at 1 kHz vs in order'),
    'M1': ('m1_memory.py', 'memory per message of the offline tools, spilled vs in memory'),
}
TIMEOUT = {'P1': 900, 'P2': 1800, 'P3': 3600, 'P4': 900, 'P5': 600, 'M1': 900}
SMOKE_TIMEOUT = {'P1': 120, 'P2': 240, 'P3': 120, 'P4': 120, 'P5': 120,   # P2: six loops
                 'M1': 120}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[1])
    parser.add_argument('--smoke', action='store_true',
                        help='seconds per benchmark: check that each runs (not judged)')
    parser.add_argument('--only', help='comma-separated ids, e.g. P1,P3')
    parser.add_argument('--big', action='store_true',
                        help='P3: also the 10^7-message bag (peak memory within 1 GiB)')
    parser.add_argument('--json', metavar='PATH', help='write all figures and the machine')
    parser.add_argument('--strict', action='store_true',
                        help='exit 1 when a target is missed')
    args = parser.parse_args(argv)
    ids = [i.strip().upper() for i in args.only.split(',')] if args.only else list(BENCHMARKS)
    unknown = [i for i in ids if i not in BENCHMARKS]
    if unknown:
        parser.error(f'unknown benchmark(s) {unknown}; choose from {list(BENCHMARKS)}')
    machine = machine_info()
    print(f'observer_ros benchmarks{" (smoke)" if args.smoke else ""}: '
          f'{machine["nproc"]} cores, {machine["cpu_model"]}, python {machine["python"]}, '
          f'load average {machine["loadavg_at_start"][0]:.2f}; '
          + ', '.join(f'{k} {v}' for k, v in machine['versions'].items()), flush=True)
    env = ros_env()
    results, failed = {}, []
    started = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix='bench_') as tmp:
        for bench_id in ids:
            script, what = BENCHMARKS[bench_id]
            out = Path(tmp) / f'{bench_id}.json'
            cmd = [sys.executable, '-W', 'ignore::DeprecationWarning', str(HERE / script),
                   '--json', str(out)]
            if args.smoke:
                cmd.append('--smoke')
            if args.big and bench_id == 'P3':
                cmd.append('--big')
            print(f'\n== {bench_id}: {what}', flush=True)
            t0 = time.perf_counter()
            try:
                limit = (SMOKE_TIMEOUT if args.smoke else TIMEOUT)[bench_id]
                proc = subprocess.run(cmd, env=env, timeout=limit)
                code = proc.returncode
            except subprocess.TimeoutExpired:
                code = 'timeout'
            seconds = time.perf_counter() - t0
            if code != 0 or not out.exists():
                failed.append(bench_id)
                print(f'{bench_id} FAILED ({code}) after {seconds:.0f} s', flush=True)
                continue
            data = json.loads(out.read_text())
            data['seconds'] = seconds
            results[bench_id] = data
            print(f'({bench_id} took {seconds:.0f} s)', flush=True)
    missed = [f'{b} {f["name"]}' for b, d in results.items() for f in d['figures']
              if f.get('met') is False]
    print(f'\n== summary ({time.perf_counter() - started:.0f} s)')
    for b, d in results.items():
        for f in d['figures']:
            verdict = {True: 'met', False: 'MISSED', None: 'info' if f['target'] is None
                       else 'smoke'}[f.get('met')]
            unit = f.get('unit', 'x')
            print(f'  {b} {f["name"]:<50} {f["value"]:>10.4g}{unit:<1} '
                  f'[{f["min"]:.4g}..{f["max"]:.4g}]  {verdict}')
    for b in failed:
        print(f'  {b} FAILED')
    if args.json:
        Path(args.json).write_text(json.dumps({'machine': machine, 'smoke': args.smoke,
                                               'results': results, 'failed': failed},
                                              indent=2, default=float))
    if failed:
        return 1
    if args.strict and missed:
        return 1
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
