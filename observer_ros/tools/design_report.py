# observer_ros.tools.design_report: `observer-design VEHICLE.yaml [--json]`.
"""
Design report of a vehicle file.

Observability and detectability (modes named), gains, observer, controller and
closed-loop poles, the separation check, D(s) and warnings.

Exits 2 with one ``error: ...`` line for a file that is invalid, undetectable or
otherwise unusable.

"""

import argparse
import json
import sys
import warnings

from ..core.errors import error_text, ObserverError, quiet_on_closed_pipe
from ..core.sensor_subsets import format_sensor_subsets, sensor_subsets
from ..core.vehicle_design import design_vehicle
from ..core.vehicle_report import format_report, to_json_dict
from ..vehicle import apply_overrides, load_vehicle, vehicle_from_parameters, \
    vehicle_to_parameters

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
    args = parser.parse_args(argv)
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
        extra = [str(w.message) for w in caught
                 if not issubclass(w.category, DeprecationWarning)]
    except (ObserverError, OSError) as err:
        print(f'error: {error_text(err)}', file=sys.stderr)
        return 2
    if args.json:
        out = to_json_dict(design)
        out['vehicle'] = vehicle.name
        out['warnings'] = list(out.get('warnings', [])) + list(vehicle.warnings) + extra
        print(json.dumps(out, indent=2))
    else:
        print(format_report(design, vehicle))
        for text in list(vehicle.warnings) + extra:
            print(f'warning: {text}')
    return 0


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
