# observer_ros.tuning.report: observer-tune's report (text, JSON, CSV, PNG).
"""
The report of :func:`observer_ros.tuning.tune.tune`.

``tune.txt`` (what ``observer-tune`` prints: the identification, the whiteness verdicts, the
search tables with a column per bag, their mean and each bag's best), ``tune.json``
(every number), ``search.csv`` (the common-scale grid), ``pole_search.csv`` (each
evaluation of ``--search each-pole`` with its poles) and the PNGs (autocovariances, the
metric against the scale and per evaluation).

"""

import math

import numpy as np

from ..core.innovation import ALPHA as INNOVATION_ALPHA, WINDOW as INNOVATION_WINDOW
from ..evaluation.plots import plot_autocovariances, plot_search
from ..evaluation.report import csv_cell, fmt, text_table, write_csv, write_json

__all__ = ['format_report', 'write_report']


def format_report(result):
    """Return the readable report (what ``observer-tune`` prints)."""
    lines = []
    ident = result.identification
    if ident is not None:
        r = ident.result
        lines += [f'noise identification (autocovariance least squares) of '
                  f'{ident.vehicle.name} on {len(ident.bags)} bag(s): '
                  f'{sum(ident.samples.values())} samples at dt {ident.dt:.6g} s (median), '
                  f'first {ident.burn} of each dropped, '
                  f'{"full" if r.full else "diagonal"} covariances',
                  f'reference: {ident.reference}; lags {_lags_text(ident)}; condition number '
                  f'{fmt(r.condition)} (rank {r.rank} of {r.unknowns}); fit chi2/dof '
                  f'{fmt(r.residual / max(r.dof, 1), 3)} over {r.dof}']
        lines += _irregular_lines(ident) + ['']
        rows = []
        for i, p in enumerate(ident.passes):
            for kind, name, value, std in p.entries():
                what = 'Qd' if kind == 'Q' else 'Rd'
                rows.append([i + 1, f'{what} {name}', fmt(value), fmt(std),
                             '+-2sd reaches 0' if (2 * std >= abs(value) or not value > 0)
                             else 'ok'])
        lines += ['identified entries with their standard errors (1 sigma, from the '
                  'covariance of the weighted least squares)', '',
                  text_table(['pass', 'entry', 'value', 'std_err', 'determined'], rows), '']
        rows = []
        for label, w in (('reference', ident.whiteness_before),
                         ('tuned kalman', ident.whiteness_after)):
            for name, m in w.items():
                rows.append([label, name, m['samples'], fmt(m['residual_rms']),
                             f"{m['flagged']}/{m['windows']}", m['allowed'],
                             fmt(m['min_p'], 3), fmt(m['level'], 2),
                             {True: 'yes', False: 'no'}.get(m['white'], '-')])
        lines += [f'whiteness of the innovations (the test of the node and observer-eval: '
                  f'the cumulative periodogram of windows of {INNOVATION_WINDOW}, each flagged '
                  f'with probability {INNOVATION_ALPHA:g} if white; not white when more than '
                  "'allowed' are flagged or one is far outside; 'false_alarm' is the "
                  'probability that white innovations are called not white)', '',
                  text_table(['filter', 'output', 'N', 'rms', 'flagged', 'allowed',
                              'min_p', 'false_alarm', 'white'], rows), '']
        if ident.warnings:
            lines += ['warnings:'] + [f'- {w}' for w in ident.warnings] + ['']
    sr = result.search
    if sr is not None:
        grid = getattr(sr, 'grid', sr)          # a per-pole search starts with a grid
        lines += _grid_lines(grid)
        if grid is not sr:
            lines += _pole_lines(sr)
    lines.append(f'tuned vehicle file: {result.vehicle_file}')
    return '\n'.join(lines)


def _lags_text(ident):
    r = ident.result
    how = 'given' if ident.lags_given else 'chosen from the plant'
    text = f'{r.lags} ({how}'
    text += f'; the slowest mode the noise excites decays in {r.decay}'
    return text + ')'


def _irregular_lines(ident):
    """Return what the bags lack: outputs missing, steps of other lengths."""
    out = []
    for bag, info in ident.irregular.items():
        gone = ', '.join(f'{k} {v:.1%}' for k, v in info['missing'].items() if v > 0.0)
        low, high = info['step_range']
        jitter = not (abs(low - 1.0) <= 1e-6 and abs(high - 1.0) <= 1e-6)
        if gone or jitter:
            text = f'{bag}: '
            if gone:
                text += f'measurements missing at some samples ({gone}; autocovariances over '
                text += 'the pairs that exist)'
            if jitter:
                text += ('; ' if gone else '') + (f'steps {low:.3g}..{high:.3g} x the median '
                                                  '(the filter and the model at the actual '
                                                  'stamps)')
            out.append(text)
    return out


def _grid_lines(sr):
    names = list(sr.per_bag)
    head = ['scale', 'mean'] + [f'bag{i + 1}' for i in range(len(names))]
    rows = [[fmt(c) for c in row] for row in sr.rows()]
    return [f'gain search: {sr.kind} scale; metric {sr.metric} (mean over the bags); best '
            f'{fmt(sr.best)}', ''] + [f'  bag{i + 1}: {n}' for i, n in enumerate(names)] + \
        ['', text_table(head, rows), ''] + _per_bag_best(sr.per_bag, sr.scales, 'scale')


def _per_bag_best(per_bag, points, what):
    """Return the summary: each bag's best point and metric."""
    lines = []
    for i, values in enumerate(per_bag.values()):
        v = np.array(values, dtype=float)
        if np.isfinite(v).any():
            k = int(np.nanargmin(np.where(np.isfinite(v), v, np.nan)))
            lines.append(f'  bag{i + 1}: best {what} {fmt(points[k])}, metric {fmt(v[k])}')
    return ['summary per bag:'] + lines + [''] if len(per_bag) > 1 else []


def _pole_lines(sr):
    names = list(sr.per_bag)
    head = ['eval', 'mean'] + [f'bag{i + 1}' for i in range(len(names))] + ['poles']
    rows = [[str(r[0])] + [fmt(c) for c in r[1:-1]] + [r[-1]] for r in sr.rows()]
    grid_best = min((m for m in sr.grid.mean if math.isfinite(m)), default=math.nan)
    return ['per-pole search (scipy.optimize Nelder-Mead, each real pole and each '
            "conjugate pair's real part and |imag|, from the poles times "
            f'{fmt(sr.start_scale)}): metric {sr.metric} (mean over the bags)', '',
            text_table(head, rows), '',
            f'best: evaluation {sr.best}, metric {fmt(sr.best_metric)} (best common scale '
            f'{fmt(grid_best)}), poles {rows[sr.best][-1]}', ''] + \
        _per_bag_best(sr.per_bag, list(range(len(sr.mean))), 'evaluation')


def write_report(result, out, plots):
    """Write tune.txt, tune.json, the search tables and the plots; return the files."""
    files = []
    (out / 'tune.txt').write_text(format_report(result) + '\n')
    files.append(out / 'tune.txt')
    files.append(write_json(out / 'tune.json', result.to_dict()))
    sr = result.search
    grid = getattr(sr, 'grid', sr)
    if sr is not None:
        files.append(write_csv(out / 'search.csv', ['scale', 'mean'] + list(grid.per_bag),
                               ([csv_cell(float(c)) for c in row] for row in grid.rows())))
    if grid is not sr:
        files.append(write_csv(
            out / 'pole_search.csv', ['evaluation', 'mean'] + list(sr.per_bag) + ['poles'],
            ([str(row[0])] + [csv_cell(float(c)) for c in row[1:-1]] + [row[-1]]
             for row in sr.rows())))
    if plots and result.identification is not None:
        ident = result.identification
        fits = [(f'pass {i + 1}: ' + (ident.reference if i == 0 else
                                      'Kalman filter of the previous pass'),
                 p.empirical, p.fitted, p.sigma) for i, p in enumerate(ident.passes)]
        files.append(plot_autocovariances(
            out / 'autocovariance.png', ident.vehicle.plant.output_names, fits,
            f'{ident.vehicle.name}: innovation autocovariances, empirical and fitted'))
    if plots and sr is not None:
        metrics = dict(grid.per_bag) if len(grid.per_bag) > 1 else {}
        metrics['mean'] = grid.mean
        files.append(plot_search(out / 'search.png', f'{grid.kind} scale', grid.scales,
                                 metrics, grid.metric, grid.best))
    if plots and grid is not sr:
        metrics = dict(sr.per_bag) if len(sr.per_bag) > 1 else {}
        metrics['mean'] = sr.mean
        files.append(plot_search(out / 'pole_search.png', 'evaluation (scipy.optimize)',
                                 list(range(len(sr.mean))), metrics, sr.metric, sr.best,
                                 log=False))
    return files
