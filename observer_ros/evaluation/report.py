# observer_ros.evaluation.report: the evaluation's table, CSV, JSON and results bag.
"""
Report files of an evaluation: table, CSV, JSON, plots and a results bag.

The plots themselves are in :mod:`observer_ros.evaluation.plots`.

"""

import json
import math
import re

import numpy as np

from .metrics import WHITENESS_LAGS
from .plots import write_plots
from ..bag.reader import jazzy_typestore
from ..bag.spill import decimated_rows
from ..core.innovation import WINDOW as INNOVATION_WINDOW
from ..outputs.staging import StagedOutput
from ..replay.replay import SKIPPED

__all__ = ['BAG_MAX_MESSAGES', 'fmt', 'text_table', 'format_table',
           'write_results', 'write_results_bag', 'csv_cell', 'write_csv', 'write_json']

BAG_MAX_MESSAGES = 100_000      # per topic in the results bag (decimated beyond)


def fmt(value, digits=4):
    """Format a number for a table: ``-`` for None/NaN, ``never`` for inf."""
    if value is None:
        return '-'
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    v = float(value)
    if math.isnan(v):
        return '-'
    if math.isinf(v):
        return 'never'
    if v == 0.0:
        return '0'
    if 1e-3 <= abs(v) < 1e5:
        return f'{v:.{digits}g}'
    return f'{v:.{digits - 1}e}'


def text_table(header, rows):
    """Return rows as aligned text columns under a header (numbers right-aligned)."""
    widths = [max(len(str(h)), *(len(str(r[i])) for r in rows)) if rows else len(str(h))
              for i, h in enumerate(header)]
    right = [i > 0 and all(_numeric(r[i]) for r in rows) for i in range(len(header))]

    def line(cells):
        return '  '.join(str(c).rjust(w) if r else str(c).ljust(w)
                         for c, w, r in zip(cells, widths, right)).rstrip()
    return '\n'.join([line(header), line(['-' * w for w in widths])] +
                     [line(r) for r in rows])


def _unit(result, kind, name):
    """Return the unit of a state or output as the vehicle file states it ('-' if not)."""
    return result.vehicle.unit(kind, name) or '-'


def _numeric(text):
    return bool(re.match(r'^[-+0-9.e]+$|^-$|^never$', str(text)))


def format_table(result):
    """Return the readable comparison (what ``observer-eval`` prints)."""
    info = result.recording.info
    dur = (info.end_ns - info.start_ns) * 1e-9 if info.message_count else 0.0
    lines = [f'bag {result.bag_path} ({info.storage}, {info.message_count} messages, '
             f'{dur:.1f} s); vehicle {result.vehicle.name}, namespace '
             f'{result.namespace or "/"}']
    rows = []
    for name, vr in result.variants.items():
        c = vr.replay.counts
        skipped = sum(c.get(k, 0) for k in SKIPPED)
        rows.append([name, vr.kind, len(vr.replay), c.get('commands', '-'),
                     c.get('estimator_resets', c.get('clock_jumps', 0)), skipped,
                     ' '.join(vr.overrides) if vr.overrides else '-'])
    lines += ['', text_table(['variant', 'observer', 'estimates', 'commands', 'resets',
                              'skipped', 'overrides'], rows)]
    if result.truth is not None:
        tol = ', '.join(f'{k} {fmt(v)}' for k, v in result.tolerance.items())
        lines += ['', f'errors against state/true ({result.truth[0].size} samples); '
                      f'settling band: {result.tolerance_rule} ({tol})']
        rows = []
        for name, vr in result.variants.items():
            for state, m in vr.states.items():
                rows.append([name, state, _unit(result, 'state', state), fmt(m['rmse']),
                             fmt(m['max_abs_error']), fmt(m['settling_time']),
                             fmt(m['ss_std']), fmt(m['ss_mean'])])
        lines += ['', text_table(['variant', 'state', 'unit', 'rmse', 'max|err|', 'settle[s]',
                                  'ss_std', 'ss_mean'], rows)]
    else:
        lines += ['', 'no state/true in the bag: residuals only']
    rows = []
    for name, vr in result.variants.items():
        for output, m in vr.outputs.items():
            if not m['samples']:
                continue
            rows.append([name, output, _unit(result, 'output', output), m['samples'],
                         fmt(m['residual_rms']), fmt(m['ljung_box_q']),
                         fmt(m['acf_outside'], 3)])
    if rows:
        lines += ['', 'residual autocorrelation over the run (Ljung-Box statistic over lags '
                      f'1..{WHITENESS_LAGS}, fraction of those lags outside +-1.96/sqrt(N), '
                      'about 0.05 if white): figures; the verdict is the innovation health',
                  '', text_table(['variant', 'output', 'unit', 'N', 'rms', 'LB_Q', 'acf_out'],
                                 rows)]
    rows = [[name, sensor, h['samples'], h.get('transient', 0), fmt(h['nis_mean']),
             f"{h['windows_inconsistent']}/{h['windows']}", h.get('windows_allowed', 0),
             fmt(h['whiteness_p'], 3), fmt(h.get('false_alarm', math.nan), 2),
             'WARN' if not h['consistent'] else 'ok' if h['windows'] else 'unjudged']
            for name, vr in result.variants.items()
            for sensor, h in getattr(vr, 'sensors', {}).items()]
    if rows:
        lines += ['', 'innovation health per sensor (NIS and whiteness over windows of '
                      f'{INNOVATION_WINDOW}, as the node judges them; the initial transient '
                      'of observers other than Kalman, one settling time of the slowest '
                      'pole, is not judged). WARN when more windows are flagged than '
                      "'allowed' or one is far outside; 'false_alarm' is the probability "
                      "that a consistent Kalman filter's run is called WARN",
                  '', text_table(['variant', 'sensor', 'N', 'transient', 'NIS',
                                  'bad_windows', 'allowed', 'white_p', 'false_alarm',
                                  'health'], rows)]
    return '\n'.join(lines)


_CSV_COLUMNS = ['variant', 'observer', 'kind', 'name', 'samples', 'rmse', 'max_abs_error',
                'settling_time', 'ss_std', 'ss_mean', 'tolerance', 'residual_rms',
                'ljung_box_q', 'ljung_box_p', 'acf_outside', 'unit']


def _csv_rows(result):
    rows = []
    for name, vr in result.variants.items():
        for state, m in vr.states.items():
            rows.append(dict(variant=name, observer=vr.kind, kind='state', name=state,
                             tolerance=result.tolerance.get(state),
                             unit=result.vehicle.unit('state', state), **m))
        for output, m in vr.outputs.items():
            rows.append({'variant': name, 'observer': vr.kind, 'kind': 'output', 'name': output,
                         'samples': m['samples'], 'residual_rms': m['residual_rms'],
                         'ljung_box_q': m['ljung_box_q'], 'ljung_box_p': m['ljung_box_p'],
                         'acf_outside': m['acf_outside'],
                         'unit': result.vehicle.unit('output', output)})
    return rows


def csv_cell(v):
    """Format a value for a CSV cell (empty for None/NaN)."""
    if v is None:
        return ''
    if isinstance(v, (float, np.floating)):
        f = float(v)
        if math.isnan(f):
            return ''
        return 'inf' if math.isinf(f) else repr(f)
    return str(v)


def write_csv(path, header, rows):
    """Write a CSV file: the header, then one line per row of cells (text); return path."""
    with open(path, 'w') as f:
        f.write(','.join(header) + '\n')
        for cells in rows:
            f.write(','.join(cells) + '\n')
    return path


def write_json(path, data):
    """Write ``data`` as JSON indented by 2, with a final newline; return path."""
    with open(path, 'w') as f:
        json.dump(data, f, indent=2)
        f.write('\n')
    return path


def write_results(result, out, force=False, plots=True, results_bag=True,
                  bag_max_messages=BAG_MAX_MESSAGES):
    """
    Write the evaluation to a new folder, whole: the earlier output, or all of the new one.

    The files are written beside ``out`` and put in its place at the end
    (:class:`~observer_ros.outputs.staging.StagedOutput`): an interrupted evaluation leaves
    ``out`` as it was.

    Parameters
    ----------
    result : EvalResult
        The evaluation, from :func:`evaluate_bag`.
    out : str or Path
        The folder; it must not exist unless ``force`` (then an earlier observer-eval
        output there is replaced).
    force : bool
        Replace an earlier observer-eval output folder at ``out``.
    plots : bool
        Write ``states.png``, ``error_norm.png`` (with ground truth) and
        ``residuals.png``.
    results_bag : bool
        Write ``results_bag/`` (mcap): ``/eval/<variant>/state/estimate`` (JointState),
        ``/eval/<variant>/state/error`` and ``/eval/state/true`` when there is ground truth.
    bag_max_messages : int
        At most this many messages per topic in the results bag (evenly decimated).

    Returns
    -------
    files : list of Path

    Raises
    ------
    BagToolError
        The folder exists (without ``force``), or exists and is not an earlier output.

    """
    with StagedOutput(out, force, 'observer-eval') as staged:
        stage = staged.path         # written aside, put in place whole (outputs/staging.py)
        files = []
        table = format_table(result)
        (stage / 'results.txt').write_text(table + '\n')
        files.append(stage / 'results.txt')
        files.append(write_csv(stage / 'results.csv', _CSV_COLUMNS,
                               ([csv_cell(row.get(c)) for c in _CSV_COLUMNS]
                                for row in _csv_rows(result))))
        files.append(write_json(stage / 'results.json', result.to_dict()))
        if plots:
            files += write_plots(result, stage)
        if results_bag:
            files.append(write_results_bag(result, stage / 'results_bag', bag_max_messages))
        return staged.commit(files)


def _joint_state_bytes(names, stamp_ns, values):
    """Serialize JointState messages (name, position) for many stamps at once."""
    from ..bag.joint_state_cdr import joint_state_layout   # the walk the decoder uses
    store = jazzy_typestore()
    js = store.types['sensor_msgs/msg/JointState']
    hdr = store.types['std_msgs/msg/Header']
    tm = store.types['builtin_interfaces/msg/Time']
    k = len(names)
    msg = js(header=hdr(stamp=tm(sec=0, nanosec=0), frame_id=''), name=list(names),
             position=np.zeros(k), velocity=np.zeros(0), effort=np.zeros(0))
    template = np.frombuffer(bytes(store.serialize_cdr(msg, js.__msgtype__)), np.uint8)
    off, count = joint_state_layout(template.tobytes()).arrays['position']
    assert count == k
    N = stamp_ns.size
    rows = np.tile(template, (N, 1))
    rows[:, 4:8] = (stamp_ns // 1_000_000_000).astype('<i4').view(np.uint8).reshape(N, 4)
    rows[:, 8:12] = (stamp_ns % 1_000_000_000).astype('<u4').view(np.uint8).reshape(N, 4)
    rows[:, off:off + 8 * k] = np.ascontiguousarray(values, dtype='<f8').view(
        np.uint8).reshape(N, 8 * k)
    return rows


def write_results_bag(result, path, limit):
    """Write the truth, estimates and errors as JointState topics to a new mcap bag."""
    from rosbags.rosbag2 import StoragePlugin

    from ..bag.integrity import CrcWriter
    store = jazzy_typestore()
    js = 'sensor_msgs/msg/JointState'
    topics = []
    names = list(result.state_names)
    if result.truth is not None:
        t_ns, values, _ = result.truth
        topics.append(('/eval/state/true', t_ns, values, names))
    for name, vr in result.variants.items():
        rep = vr.replay
        topics.append((f'/eval/{name}/state/estimate', rep.stamp_ns, rep.x_hat, names))
        if vr.error is not None:        # the matched rows, taken once decimated
            topics.append((f'/eval/{name}/state/error', rep.stamp_ns, vr.error, names,
                           vr.matched))
    with CrcWriter(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        for topic, ns, values, comp, *matched in topics:
            conn = writer.add_connection(topic, js, typestore=store)
            d = decimated_rows(len(ns), limit, *matched)      # a block at a time
            ns, values = np.asarray(ns[d], dtype=np.int64), values[d]
            if not ns.size:
                continue
            rows = _joint_state_bytes(comp, ns, values)
            write = writer.write
            for stamp, row in zip(ns.tolist(), rows):
                write(conn, stamp, row.tobytes())
    return path
