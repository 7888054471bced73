# observer_ros.tools.design_report: `observer-design VEHICLE.yaml [--json]`.
"""
Design report of a vehicle file, and its robust redesign.

Observability and detectability (modes named), gains, observer, controller and
closed-loop poles, the separation check, D(s), the robustness review (margins at the
plant input and output, transient growth, pole sensitivity, the fundamental limit of the
outputs) and warnings. ``--sensors``: every subset of the outputs. ``--robust``: a new
vehicle file with the observer (and controller) of the smallest peak sensitivity.

Exits 2 with one ``error: ...`` line for a file that is invalid, undetectable or
otherwise unusable; ``--robust`` exits 1 when it found nothing better than the file.

"""

import argparse
import json
from pathlib import Path
import shlex
import sys
import warnings

import numpy as np

from .robust_file import default_output, figure_lines, write_robust_vehicle
from ..core.design_review import review_design
from ..core.errors import error_text, ObserverDesignWarning, ObserverError, \
    quiet_on_closed_pipe
from ..core.robust_design import robust_design
from ..core.sensor_subsets import format_sensor_subsets, sensor_subsets
from ..core.vehicle_design import design_vehicle
from ..core.vehicle_report import format_report, to_json_dict
from ..vehicle import apply_overrides, load_vehicle, parse_override, \
    vehicle_from_parameters, vehicle_to_parameters

__all__ = ['main']


@quiet_on_closed_pipe
def main(argv=None):
    """Entry point of ``observer-design``."""
    parser = argparse.ArgumentParser(
        prog='observer-design',
        description='Observer and compensator design report for a vehicle file.')
    parser.add_argument('vehicle', help='vehicle parameter file (config/<vehicle>.yaml)')
    parser.add_argument('--json', action='store_true', help='print one JSON object')
    parser.add_argument('-p', '--param', action='append', default=[], metavar='NAME:=VALUE',
                        help='override a parameter, e.g. "observer.poles:=[-1.0,-2.0]"')
    parser.add_argument('--sensors', action='store_true',
                        help='instead of the design: for every subset of the outputs, '
                             'observable/detectable, the unobservable modes, and the '
                             'steady-state Kalman error variance per state')
    parser.add_argument('--robust', action='store_true',
                        help='search the observer (Kalman weights, loop transfer recovery, '
                             'or its poles) for the smallest peak sensitivity at the plant '
                             'input within the settling-time bound, and write a new '
                             'vehicle file with the figures before and after')
    parser.add_argument('--controller', action='store_true',
                        help='with --robust: search the controller too (LQR, then its poles)')
    parser.add_argument('--settling-time', type=float, default=None, metavar='SECONDS',
                        help='with --robust: bound on the settling time (4 time constants '
                             "of the slowest closed-loop pole); default twice the file's")
    parser.add_argument('--out', default=None, metavar='FILE',
                        help='with --robust: the new vehicle file (default '
                             '<vehicle>_robust.yaml beside it); never overwritten')
    args = parser.parse_args(argv)
    if (args.controller or args.settling_time is not None or args.out) and not args.robust:
        parser.error('--controller, --settling-time and --out go with --robust')
    if args.robust and args.sensors:
        parser.error('--robust and --sensors are separate reports')
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter('always')
            vehicle = load_vehicle(args.vehicle)
            if args.param:
                vehicle = vehicle_from_parameters(
                    apply_overrides(vehicle_to_parameters(vehicle), args.param),
                    source=args.vehicle)
            if args.sensors:
                return _sensors(vehicle, args.json)
            design = design_vehicle(vehicle)
            review = review_design(design, vehicle)
            if args.robust:
                return _robust(args, vehicle, design, review, argv)
        extra = [_own_words(w) for w in caught
                 if not issubclass(w.category, DeprecationWarning)]
    except (ObserverError, OSError) as err:
        print(f'error: {error_text(err)}', file=sys.stderr)
        return 2
    if args.json:
        out = to_json_dict(design)
        out['vehicle'] = vehicle.name
        out['robustness'] = review.to_json()
        out['warnings'] = (list(out.get('warnings', [])) + list(review.warnings)
                           + list(vehicle.warnings) + extra)
        print(json.dumps(out, indent=2))
    else:
        print(format_report(design, vehicle, review))
        for text in list(vehicle.warnings) + extra:
            print(f'warning: {text}')
    return 0


def _own_words(w):
    """Return a warning raised during the design, said as the report says its own."""
    if issubclass(w.category, ObserverDesignWarning):
        return str(w.message)
    first = str(w.message).splitlines()[0][:120]
    return (f'a numerical warning was raised while designing the gains ({w.category.__name__}'
            f': {first}); every gain above passed its verification regardless')


def _robust(args, vehicle, design, review, argv):
    out = Path(args.out) if args.out else default_output(args.vehicle)
    if out.exists() or out.is_symlink():
        raise ObserverError(f'{out} exists; the robust vehicle file is never overwritten '
                            '(give another --out)')
    with warnings.catch_warnings():
        warnings.simplefilter('ignore')      # candidates' warnings: the result is verified
        result = robust_design(vehicle, args.settling_time, args.controller, design, review)
    written = None
    if result.vehicle is not None:
        command = 'observer-design ' + ' '.join(shlex.quote(a) for a in
                                                (sys.argv[1:] if argv is None else argv))
        overrides = dict(parse_override(text) for text in args.param)
        written = write_robust_vehicle(result, args.vehicle, out, command, overrides,
                                       args.controller)
    if args.json:
        print(json.dumps({'vehicle': vehicle.name, 'written': None if written is None else
                          str(written), 'settling_bound': result.settling_bound,
                          'ms_bound': result.ms_bound if result.ms_bound < 1e300 else None,
                          'before': _jsonable(result.before),
                          'after': _jsonable(result.after), 'message': result.message},
                         indent=2))
    else:
        print(f'Robust redesign of {args.vehicle} ({"; ".join(result.searched)}):')
        print(f'  {result.message}')
        for line in figure_lines(result):
            print(f'  {line}')
        print(f'  written: {written}' if written else '  no file written')
    return 0 if written else 1


def _jsonable(d):
    if d is None:
        return None
    out = {}
    for k, v in d.items():
        if isinstance(v, tuple):
            v = [None if not np.isfinite(x) else float(x) for x in v]
        elif v is not None:
            v = None if not np.isfinite(v) else float(v)
        out[k] = v
    return out


def _sensors(vehicle, as_json):
    names = vehicle.plant.state_names
    subsets = sensor_subsets(vehicle)
    if as_json:
        print(json.dumps({'vehicle': vehicle.name,
                          'sensor_subsets': [s.to_json(names) for s in subsets]}, indent=2))
    else:
        print(format_sensor_subsets(subsets, names))
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
