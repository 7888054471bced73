# observer_ros.core.vehicle_report: what observer-design prints of a VehicleDesign.
"""Design report of a vehicle: the console text and the JSON summary."""

import numpy as np

from ._lazy import control
from .analysis import format_complex
from .delay_compensation import loop_delay_margin

__all__ = ['to_json_dict', 'format_report']


# ---------------------------------------------------------------- output


def _matrix(M):
    return None if M is None else [[float(x) for x in row] for row in np.atleast_2d(M)]


def _cvec(v):
    return [[float(np.real(x)), float(np.imag(x))] for x in np.asarray(v).reshape(-1)]


def to_json_dict(design):
    """
    Summarise a VehicleDesign as a JSON-serialisable dict.

    Parameters
    ----------
    design : VehicleDesign
        The design.

    Returns
    -------
    dict
        Matrices are lists of rows; poles (real ones too) are ``[re, im]`` pairs.
        Keys: kind, discrete, sample_time, state_names, input_names, output_names,
        observable, detectable, observability_rank, unobservable_modes,
        controllable, stabilizable, uncontrollable_modes, L, K, observer_poles,
        controller_poles, closed_loop_poles (the union of eig(A - B K) and the observer
        poles), separation_ok, separation_error (largest distance of an eigenvalue of the
        full closed-loop matrix from that union) and separation_allowed (what rounding
        allows there), compensator_poles,
        placement {observer, controller} (each None, or the achieved-versus-requested
        summary of :class:`~observer_ros.core.verify.PlacementCheck`), warnings, and
        when they apply reduced {F, G, H, L, rest}, P, Kd, reference,
        tracking_residual, noise_gain.

    """
    d = {
        'kind': design.kind,
        'discrete': design.discrete,
        'sample_time': design.sample_time,
        'state_names': list(design.state_names),
        'input_names': list(design.input_names),
        'output_names': list(design.output_names),
        'observable': bool(design.observability.observable),
        'detectable': bool(design.observability.detectable),
        'observability_rank': int(design.observability.rank),
        'unobservable_modes': list(design.observability.unobservable_modes),
        'controllable': bool(design.controllability.controllable),
        'stabilizable': bool(design.controllability.stabilizable),
        'uncontrollable_modes': list(design.controllability.uncontrollable_modes),
        'L': _matrix(design.L),
        'K': _matrix(design.K),
        'observer_poles': _cvec(design.observer_poles),
        'controller_poles': _cvec(design.controller_poles),
        'closed_loop_poles': _cvec(design.closed_loop_poles),
        'separation_ok': design.separation_ok,
        'separation_error': design.separation_error,
        'separation_allowed': design.separation_allowed,
        'compensator_poles': _cvec(design.compensator_poles),
        'placement': {
            'observer': None if design.observer_placement is None else
            design.observer_placement.to_json(),
            'controller': None if design.controller_placement is None else
            design.controller_placement.to_json(),
            'sampled': None if design.sampled is None else design.sampled.to_json()},
        'warnings': list(design.warnings),
    }
    if design.reduced is not None:
        r = design.reduced
        d['reduced'] = {'F': _matrix(r.F), 'G': _matrix(r.G), 'H': _matrix(r.H),
                        'L': _matrix(r.L), 'rest': [design.state_names[i] for i in r.rest]}
    if design.P is not None:
        d['P'] = _matrix(design.P)
    if design.Kd is not None:
        d['Kd'] = _matrix(design.Kd)
        d['reference'] = [float(x) for x in design.reference]
        d['tracking_residual'] = [float(x) for x in design.tracking_residual]
    if design.noise_gain is not None:
        d['noise_gain'] = [None if not np.isfinite(x) else float(x) for x in design.noise_gain]
    return d


def _table(M, row_names, col_names, digits=6):
    M = np.atleast_2d(M)
    cells = [[f'{x:.{digits}g}' for x in row] for row in M]
    w0 = max([len(r) for r in row_names] + [1])
    w = max([len(c) for c in col_names] + [len(c) for row in cells for c in row] + [1])
    lines = ['  ' + ' ' * w0 + '  ' + '  '.join(c.rjust(w) for c in col_names)]
    for name, row in zip(row_names, cells):
        lines.append('  ' + name.ljust(w0) + '  ' + '  '.join(c.rjust(w) for c in row))
    return lines


def _poles_line(poles):
    if len(poles) == 0:
        return 'none'
    order = sorted(np.asarray(poles).reshape(-1), key=lambda z: (z.real, -abs(z.imag)))
    return ', '.join(format_complex(z, 6) for z in order)


def _rate(rate):
    """Return a decay rate (ln of the spectral radius per s, negative) as said: 0.6/s."""
    return 'deadbeat' if rate == -float('inf') else f'{-rate:.3g}/s'


def _placement_lines(check):
    if check is None or not check.requested.size:
        return []
    w = check.worst
    return [f' placement ({check.field}): achieved poles within {check.max_error:.2g} of '
            f'those asked (relative {check.relative_error:.2g}); at the worst pole '
            f'{format_complex(check.requested[w])} the conditioning allows '
            f'{check.bound[w]:.2g}']


def _delay_margin_lines(design, vehicle):
    """Return the report's lines on the delay margin at the plant input (SISO, continuous)."""
    plant = None if vehicle is None else vehicle.plant
    if plant is None or design.discrete or design.compensator is None or \
            plant.m != 1 or plant.p != 1:
        return []
    try:
        tau, wc = loop_delay_margin(control.ss(plant.A, plant.B, plant.C, plant.D),
                                    design.compensator, points=20001)
    except Exception:   # noqa: BLE001 - the report must not fail on the printout
        return []
    if not np.isfinite(tau):
        return ['Delay margin at the plant input: no gain crossover (none needed)']
    lines = [f'Delay margin at the plant input: {tau * 1e3:.3g} ms (at {wc:.3g} rad/s)']
    dt = vehicle.sample_time
    if tau < dt:
        lines.append(f'  less than one sample ({dt * 1e3:g} ms): a realtime loop needs '
                     'controller.delay_compensation (a command that misses its step '
                     'destabilises it)')
    return lines


def format_report(design, vehicle=None, review=None):
    """
    Console report of a VehicleDesign (what ``observer-design`` prints).

    Parameters
    ----------
    design : VehicleDesign
        The design.
    vehicle : observer_ros.core.spec.Vehicle, optional
        Adds the vehicle's name, description and source.
    review : DesignReview, optional
        Adds its robustness section (``core/design_review.py``, which then gives the
        delay margins) and its warnings.

    Returns
    -------
    str

    """
    lines = []
    if vehicle is not None:
        lines.append(f'Vehicle: {vehicle.name}' + (f' - {vehicle.description}'
                                                   if vehicle.description else ''))
        if vehicle.source:
            lines.append(f'Source: {vehicle.source}')
    plane = 'z-plane' if design.discrete else 's-plane'
    time = f'discrete, dt = {design.sample_time:g} s' if design.discrete else 'continuous'
    lines.append(f'Plant ({time}): states {list(design.state_names)}, inputs '
                 f'{list(design.input_names)}, outputs {list(design.output_names)}')
    lines.append('')
    lines.append(f'Observability: {design.observability.summary()}')
    for res in design.observability.pbh:
        lines.append(f'  PBH eigenvalue {format_complex(res.eigenvalue)}: rank {res.rank}/'
                     f'{res.n} ({"observable" if res.passed else "UNOBSERVABLE"}, '
                     f'{"stable" if res.stable else "not stable"})')
    lines.append(f'Controllability: {design.controllability.summary()}')
    lines.append('')
    lines.append(f'Observer ({design.kind}), poles ({plane}): '
                 f'{_poles_line(design.observer_poles)}')
    lines.extend(_placement_lines(design.observer_placement))
    if design.sampled is not None:
        sc = design.sampled
        lines.append(f' sampled gains (sensors {list(sc.sensors)}, period {sc.period:.6g} s, '
                     f'{len(sc.corrections)} corrections): verified; error map over one period '
                     f'has spectral radius {sc.spectral_radius:.4g} (decays at '
                     f'{_rate(sc.decay_rate)}, designed {_rate(sc.designed_rate)})')
    if design.reduced is not None:
        r = design.reduced
        est = [design.state_names[i] for i in r.rest]
        lines.append(f'  estimates {est} from {list(design.output_names)}; x_hat2 = L y + z, '
                     "z' = F z + G y + H u")
        for label, M, cols in (('L', r.L, design.output_names), ('F', r.F, est),
                               ('G', r.G, design.output_names), ('H', r.H, design.input_names)):
            lines.append(f' {label}:')
            lines.extend(_table(M, est, list(cols)))
    else:
        lines.append(' L:')
        lines.extend(_table(design.L, list(design.state_names), list(design.output_names)))
    if design.P is not None:
        lines.append(' P (steady-state error covariance):')
        lines.extend(_table(design.P, list(design.state_names), list(design.state_names)))
    if design.noise_gain is not None:
        parts = [f'{nm} {g:.3g}' for nm, g in zip(design.output_names, design.noise_gain)
                 if np.isfinite(g)]
        if parts:
            lines.append(' noise gain (estimate std / sensor std): ' + ', '.join(parts))
    lines.append('')
    if design.K is None:
        lines.append('Controller: none')
    else:
        lines.append(f'Controller u = K (x_d - x_hat) - Kd x_d, poles ({plane}): '
                     f'{_poles_line(design.controller_poles)}')
        lines.extend(_placement_lines(design.controller_placement))
        lines.append(' K:')
        lines.extend(_table(design.K, list(design.input_names), list(design.state_names)))
        if design.reference is not None and np.any(design.reference):
            lines.append(f' reference x_d: {np.array2string(design.reference, precision=4)}')
        lines.append('')
        lines.append(f'Closed loop poles: {_poles_line(design.closed_loop_poles)}')
        lines.append('Separation principle (eig = eig(A - BK) + observer poles): '
                     + ('ok' if design.separation_ok else 'FAILED')
                     + f' (closed-loop matrix off by {design.separation_error:.2g}; '
                     f'rounding allows {design.separation_allowed:.2g})')
        sens = None if review is None else review.sensitivity
        if sens is not None and sens.poles.size:
            lines.append(f'  one rounding of the closed-loop matrix moves its pole '
                         f'{format_complex(sens.poles[sens.worst], 5)} by up to '
                         f'{sens.rounding_move[sens.worst]:.2g} (relative '
                         f'{sens.relative_move:.2g}; condition number '
                         f'{sens.condition[sens.worst]:.3g})')
        lines.append(f'Compensator poles: {_poles_line(design.compensator_poles)}')
        if review is None:
            lines.extend(_delay_margin_lines(design, vehicle))
        lines.append('Compensator D(s), u = -D(s) y:' if not design.discrete else
                     'Compensator D(z), u = -D(z) y:')
        try:
            tf = control.ss2tf(design.compensator)
            text = str(tf).split('\n')
            lines.extend('  ' + t for t in text if t.strip() and not t.startswith(
                ('<', 'Inputs', 'Outputs')))
        except Exception:   # noqa: BLE001 - the report must not fail on the printout
            lines.append('  (transfer function not available)')
    lines.append('')
    if review is not None and vehicle is not None:
        lines.extend(review.lines(design, vehicle.sample_time))
        lines.append('')
    warns = list(design.warnings) + (list(review.warnings) if review is not None else [])
    if warns:
        lines.append('Warnings:')
        lines.extend(f'  - {w}' for w in warns)
    else:
        lines.append('Warnings: none')
    return '\n'.join(lines)
