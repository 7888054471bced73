# observer_ros.vehicle.doc: the tables of docs/vehicle_schema.md, made from the schema.
"""
Write the key tables of docs/vehicle_schema.md from the schema.

Each table in that page stands between ``<!-- schema: SECTION -->`` and
``<!-- /schema -->``; :func:`render` replaces each with the table made from
:mod:`.schema`, so the page cannot say another type, default, unit or bound than the
loader and the nodes' descriptors use. test/vehicle/test_vehicle_schema.py checks that the
page is up to date; ``python -m observer_ros.vehicle.doc docs/vehicle_schema.md``
rewrites it.

"""

import re
import sys

from .schema import interval_text, KNOWN_KEYS, NODE_KEYS, SENSOR_KEYS

__all__ = ['SECTIONS', 'table', 'render', 'main']

SECTIONS = ('vehicle', 'model', 'sensors', 'observer', 'controller', 'simulator', 'node')

_TYPES = {'STRING': 'string', 'STRING_ARRAY': 'string[]', 'DOUBLE': 'double',
          'DOUBLE_ARRAY': 'double[]', 'INTEGER': 'int', 'BOOL': 'bool'}
_BLOCK = re.compile(r'(<!-- schema: (\w+) -->\n)(.*?)(<!-- /schema -->)', re.S)


def _default(spec):
    if spec.required:
        return 'required'
    if spec.default is None:
        return '—'
    if isinstance(spec.default, bool):
        return f'`{str(spec.default).lower()}`'
    if spec.default == '':
        return "`''`"
    return f'`{spec.default}`'


def _range(spec):
    parts = []
    if spec.choices:
        parts.append('one of ' + ', '.join(f'`{c}`' for c in spec.choices))
    bound = interval_text(spec, unit=False)
    if bound:
        parts.append(bound)
    if spec.rule:
        parts.append(spec.rule)
    return '; '.join(parts)


def _meaning(spec):
    text = spec.description
    return f'{text}; {spec.details}' if spec.details else text


def _specs(section):
    if section == 'node':
        return [(name, spec) for name, spec in NODE_KEYS.items()]
    if section == 'sensors':
        return [('sensors.names', KNOWN_KEYS['sensors.names'])] + \
            [(f'sensors.<s>.{name}', spec) for name, spec in SENSOR_KEYS.items()]
    return [(name, spec) for name, spec in KNOWN_KEYS.items()
            if name.split('.', 1)[0] == section]


def table(section):
    """Return the markdown table of one section (``model``, ..., ``node``)."""
    lines = ['| key | type | default | unit | range | meaning |',
             '|---|---|---|---|---|---|']
    for name, spec in _specs(section):
        cells = [f'`{name}`', _TYPES[spec.param_type], _default(spec), spec.unit,
                 _range(spec), _meaning(spec)]
        lines.append('| ' + ' | '.join(cells) + ' |')
    return '\n'.join(lines) + '\n'


def render(text):
    """Return the page with every marked table made again from the schema."""
    def block(match):
        return match.group(1) + table(match.group(2)) + match.group(4)
    return _BLOCK.sub(block, text)


def main(argv=None):
    """Rewrite the tables of the page named on the command line; return the exit status."""
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) != 1:
        print('usage: python -m observer_ros.vehicle.doc docs/vehicle_schema.md',
              file=sys.stderr)
        return 2
    with open(argv[0], encoding='utf-8') as f:
        text = f.read()
    new = render(text)
    if new != text:
        with open(argv[0], 'w', encoding='utf-8') as f:
            f.write(new)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
