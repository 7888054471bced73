# observer_ros.evaluation.evaluate: `observer-eval BAG --vehicle V.yaml`: replay and compare.
"""
``observer-eval``: the command line of the offline evaluation.

The bag is replayed through the vehicle file's design, each ``--variant`` and each
``--compare`` file (:func:`~observer_ros.evaluation.evaluator.evaluate_bag`), the table is
printed and the folder written whole (:func:`~observer_ros.evaluation.report.write_results`).

"""
import argparse
from pathlib import Path
import sys
import time
import warnings

from .cli import (default_out, IN_MEMORY_HELP, Progress, stop_on_sigterm, tool_done,
                  tool_error)
from .evaluator import evaluate_bag, parse_compare, parse_options
from .report import BAG_MAX_MESSAGES, format_table, write_results
from ..bag.errors import BagToolError
from ..core.errors import ObserverError, quiet_on_closed_pipe
from ..outputs.folders import check_output

__all__ = ['main']


_EPILOG = """\
variants:
  --variant NAME:KEY:=VALUE[,KEY:=VALUE...]   (repeatable; the same NAME adds overrides)
  KEY is a vehicle-file parameter (docs/vehicle_schema.md) and VALUE is YAML, as in a ROS
  -p override. Commas inside [...] belong to the value. Quote the whole argument.
    --variant 'slow:observer.poles:=[-0.1,-0.11,-0.12]'
    --variant 'kalman:observer.type:=kalman,observer.Rd:=[1.0e-6]'
    --variant 'kalman:observer.Qd:=[1.0e-4,0.0,0.0, 0.0,1.0e-4,0.0, 0.0,0.0,1.0e-4]'
                                                       (the same name: merged with the above)
    --variant 'openloop:observer.type:=open_loop'
  The vehicle file's own design is always the variant "design"; the estimate recorded on
  state/estimate is scored as "live".
  --compare [NAME=]FILE  (repeatable) replays another vehicle file as a variant, e.g. the
  one observer-tune wrote: observer-eval BAG --vehicle V.yaml --compare V_tuned.yaml

output (folder --out; default <bag>_eval next to the bag directory, e.g. runs/sub1 ->
runs/sub1_eval, wherever the command is run from; never overwritten without --force):
  the table on stdout and in results.txt, results.csv, results.json, states.png,
  error_norm.png, residuals.png, and results_bag/ (mcap) with /eval/<variant>/state/estimate,
  /eval/<variant>/state/error and /eval/state/true for PlotJuggler or Foxglove.

exit status: 0 done; 2 the bag, the vehicle file or the arguments cannot be used (one line
'error: ...' on stderr).
"""


def _parser():
    parser = argparse.ArgumentParser(
        prog='observer-eval',
        description="Replay a bag's recorded measurements and commands through observer "
                    'configurations (the same estimator code as the observer node) and '
                    'compare them with the true state (state/true) or, without it, by '
                    'their residuals.',
        epilog=_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('bag', help='bag directory, or one .mcap or .db3 file')
    parser.add_argument('--vehicle', required=True, help='vehicle file (config/<name>.yaml)')
    parser.add_argument('--variant', action='append', default=[],
                        metavar='NAME:KEY:=VALUE[,...]',
                        help='an observer configuration to compare (see below)')
    parser.add_argument('--compare', action='append', default=[], metavar='[NAME=]FILE',
                        help='another vehicle file to replay as a variant (e.g. the file '
                        'observer-tune wrote); NAME defaults to the file name')
    parser.add_argument('--out', help='output folder (default: <bag>_eval next to the bag '
                        'directory)')
    parser.add_argument('--namespace', help="the vehicle's namespace in the bag, e.g. /sub1 "
                        '(default: detected from the sensor topics)')
    parser.add_argument('--tolerance', help="settling band: a percentage of each state's "
                        'range ("5%%") or an absolute value (default 2%%)')
    parser.add_argument('--force', action='store_true',
                        help='replace an existing output folder of observer-eval')
    parser.add_argument('--no-plots', action='store_true', help='do not write PNG plots')
    parser.add_argument('--no-bag', action='store_true', help='do not write the results bag')
    parser.add_argument('--bag-max', type=int, default=BAG_MAX_MESSAGES, metavar='N',
                        help='at most N messages per topic in the results bag '
                             f'(default {BAG_MAX_MESSAGES}; decimated beyond)')
    parser.add_argument('--exact', action='store_true',
                        help='call the estimator for every message (no bulk replay)')
    parser.add_argument('--in-memory', action='store_true', help=IN_MEMORY_HELP)
    parser.add_argument('--progress', action='store_true',
                        help='show progress even when stderr is not a terminal')
    return parser


@quiet_on_closed_pipe
def main(argv=None):
    """Entry point of ``observer-eval``; returns the exit status."""
    args = _parser().parse_args(argv)
    stop_on_sigterm()
    started = time.perf_counter()
    progress = Progress(args.progress or sys.stderr.isatty())
    try:
        variants = parse_options(args.variant, args.tolerance)
        compare = dict(parse_compare(text) for text in args.compare)
        if not Path(args.bag).exists():
            raise BagToolError(f'{args.bag}: no such file or directory')
        out = Path(args.out) if args.out else default_out(args.bag)
        check_output(out, args.force, 'observer-eval')
        with warnings.catch_warnings():
            warnings.simplefilter('ignore')
            result = evaluate_bag(args.bag, args.vehicle, variants, args.namespace,
                                  args.tolerance, exact=args.exact, progress=progress,
                                  compare=compare, spill=None if args.in_memory else True)
            progress.finish()
            files = write_results(result, out, force=args.force, plots=not args.no_plots,
                                  results_bag=not args.no_bag, bag_max_messages=args.bag_max)
    except (ObserverError, OSError, KeyboardInterrupt) as err:
        return tool_error(progress, err)
    return tool_done(format_table(result), result.warnings, out, files,
                     time.perf_counter() - started)


if __name__ == '__main__':
    raise SystemExit(main())
