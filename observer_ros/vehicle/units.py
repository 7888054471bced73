# observer_ros.vehicle.units: the unit of each state, input and output of a vehicle.
"""
Read ``model.state_units``, ``model.input_units`` and ``model.output_units``.

Units are stated, not converted: the numbers of a file stay those of its source (the
submarine's heave velocity in ft/s, the aircraft's actuators in degrees), and the units
go with them into the reports. Where a message field has a ROS convention (REP 103: an
Imu's ``angular_velocity`` in rad/s, a JointState ``position`` in rad or m), the unit of
the output read from it must be one the convention allows; an output's unit, when not
given, is that of the state it measures alone, else the one its field allows.

"""

import numpy as np

from ..sensors import field_units

__all__ = ['read_units']


def _selected_state(plant, i):
    """Return the state output i measures alone (C row e_j, D row 0), or None."""
    row = plant.C[i]
    nonzero = np.flatnonzero(row)
    if nonzero.size == 1 and row[nonzero[0]] == 1.0 and not np.any(plant.D[i]):
        return int(nonzero[0])
    return None


def read_units(check, plant, sensors):
    """
    Return the units of the states, inputs and outputs ('' where unknown).

    Parameters
    ----------
    check : Checker
        The flat parameters being loaded.
    plant : Plant
        The model (its names, C and D).
    sensors : sequence of SensorSpec
        Which field each output is read from.

    Returns
    -------
    state_units, input_units, output_units : tuple of str

    Raises
    ------
    VehicleFileError
        A list of the wrong length, or an output unit its field's convention refuses.

    """
    given = {}
    for kind, names in (('state', plant.state_names), ('input', plant.input_names),
                        ('output', plant.output_names)):
        key = f'model.{kind}_units'
        units = check.string_array(key, unique=False)
        if units is not None and len(units) != len(names):
            check.fail(key, f'has {len(units)} units; expected {len(names)} (one per {kind}: '
                       f'{", ".join(names)})')
        given[kind] = units
    states = given['state'] or ('',) * plant.n
    field_of = {out: (s, field) for s in sensors for out, field in zip(s.outputs, s.fields)}
    outputs = []
    for i, name in enumerate(plant.output_names):
        sensor, field = field_of[name]
        allowed = field_units(sensor.msg_type, field)
        j = _selected_state(plant, i)
        if given['output'] is not None:
            unit, key = given['output'][i], 'model.output_units'
            if j is not None and states[j] and unit != states[j]:
                check.fail(key, f'{name} is {unit} but measures state {plant.state_names[j]} '
                           f'alone (its row of C), which is {states[j]} in '
                           'model.state_units')
        elif j is not None and states[j]:
            unit, key = states[j], 'model.state_units'
        else:
            unit, key = (allowed[0] if len(allowed) == 1 else ''), None
        if unit and allowed and unit not in allowed:
            what = f'{plant.state_names[j]} is {unit}' if key == 'model.state_units' else \
                f'{name} is {unit}'
            check.fail(key, f'{what}, but output {name} is read from {sensor.msg_type} '
                       f'{field} (sensor {sensor.name}), which ROS gives in '
                       f'{" or ".join(allowed)} (REP 103)')
        outputs.append(unit)
    return states if given['state'] else (), given['input'] or (), tuple(outputs)
