# benchmarks/p1_instructions.py: the callback's instructions per message, under callgrind.
"""
Instructions per message of the observer node's measurement callback, per code version.

The CPU time of ``p1_callback.py`` moves with the load of a shared host by more than a
change of the callback does; the number of instructions does not. Each version (a
directory holding an ``observer_ros`` package: a ``git archive`` of a commit) runs
``p1_callback.py``'s in-process driver under ``valgrind --tool=callgrind`` twice, with
``--short`` and ``--long`` timed messages after the same warm-up. Callgrind counts each
thread apart (``--separate-threads=yes``): only the main thread's instructions (Ir) are
kept, not those of the middleware's own threads. The callback's instructions per message
are the difference of the two runs divided by the difference of their message counts: the
interpreter's start, the imports and the node's construction cancel out. ``PYTHONHASHSEED``
is fixed so that both runs lay their dictionaries out alike.

Printed per version: Ir per message and its ratio to the first version's.

Usage: ``python benchmarks/p1_instructions.py NAME=DIR [NAME=DIR ...]``.

"""

from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
import shutil
import subprocess
import sys
import tempfile

from p1_callback import driver_command, parse_versions, version_parser


def main_thread_ir(out_dir):
    """Return the instructions (Ir) of the main thread's callgrind file in ``out_dir``."""
    files = sorted(Path(out_dir).glob('callgrind.out*-01'))
    if len(files) != 1:
        raise RuntimeError(f'expected one main-thread callgrind file in {out_dir}, '
                           f'found {[f.name for f in files]}')
    for line in files[0].read_text().splitlines():
        if line.startswith(('totals:', 'summary:')):
            return int(line.split()[1])
    raise RuntimeError(f'{files[0]}: no totals line')


def count_instructions(directory, count):
    """Run the driver on one version under callgrind; return its main thread's Ir."""
    env, argv = driver_command(directory, count, 1)
    env['PYTHONHASHSEED'] = '0'
    out_dir = tempfile.mkdtemp(prefix='p1_instructions_')
    try:
        subprocess.run(['valgrind', '--tool=callgrind', '--separate-threads=yes',
                        f'--callgrind-out-file={out_dir}/callgrind.out.%p'] + argv,
                       env=env, cwd=str(directory), check=True,
                       stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        return main_thread_ir(out_dir)
    finally:
        shutil.rmtree(out_dir, ignore_errors=True)


def main(argv=None):
    parser = version_parser(__doc__)
    parser.add_argument('--short', type=int, default=1000, help='messages of the short run')
    parser.add_argument('--long', type=int, default=3000, help='messages of the long run')
    parser.add_argument('--jobs', type=int, default=2, help='callgrind runs at once')
    args, versions = parse_versions(parser, argv)
    if versions is None:
        return 2
    if args.long <= args.short or args.short < 1:
        print('error: --long must exceed --short, both positive', file=sys.stderr)
        return 2
    if shutil.which('valgrind') is None:
        print('error: valgrind: not found on PATH', file=sys.stderr)
        return 2
    runs = [(d, n) for _, d in versions for n in (args.short, args.long)]
    with ThreadPoolExecutor(max_workers=max(1, args.jobs)) as pool:
        ir = list(pool.map(lambda run: count_instructions(*run), runs))
    per_message = {}
    for i, (name, _) in enumerate(versions):
        short, long = ir[2 * i], ir[2 * i + 1]
        per_message[name] = (long - short) / (args.long - args.short)
        print(f'  {name}: {short} Ir ({args.short} messages), {long} Ir ({args.long})')
    first = per_message[versions[0][0]]
    for name, value in per_message.items():
        print(f'INSTRUCTIONS {name}: {value:.0f} Ir per message, {value / first:.3f}x '
              f'{versions[0][0]}')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
