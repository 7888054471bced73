# observer_ros.evaluation.plots: PNG plots of an evaluation (matplotlib, Agg).
"""Plots of an evaluation: states, error norm, residuals (one PNG each)."""

import math

import numpy as np

from ..bag.spill import decimated_rows

__all__ = ['PLOT_MAX_POINTS', 'decimate', 'pyplot', 'save_figure', 'write_plots', 'plot_t0',
           'plot_autocovariances', 'plot_search']

PLOT_MAX_POINTS = 5_000         # per line in the plots (decimated beyond)


def decimate(n, limit):
    """Return a slice keeping at most about ``limit`` of ``n`` evenly spaced items."""
    if n <= limit:
        return slice(None)
    return slice(None, None, int(math.ceil(n / limit)))


def pyplot():
    """Return matplotlib.pyplot on the Agg backend (files only, no display)."""
    import matplotlib
    matplotlib.use('Agg', force=True)
    import matplotlib.pyplot as plt
    return plt


def save_figure(fig, path):
    """Lay out a figure, write it to ``path`` (PNG, 100 dpi) and close it; return ``path``."""
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    pyplot().close(fig)
    return path


def write_plots(result, out):
    """Write states.png, error_norm.png (with ground truth), residuals.png; return the files."""
    plt = pyplot()
    files = []
    names = result.state_names
    t0 = plot_t0(result)
    colors = plt.rcParams['axes.prop_cycle'].by_key().get('color', ['C0'])
    fig, axes = plt.subplots(len(names), 1, sharex=True, squeeze=False,
                             figsize=(10, 2.2 * len(names) + 1))
    if result.truth is not None:
        t_ns, values, _ = result.truth
        d = decimate(t_ns.size, PLOT_MAX_POINTS)
        for i, ax in enumerate(axes[:, 0]):
            ax.plot((t_ns[d] - t0) * 1e-9, values[d, i], color='k', lw=2.0, label='true')
    for c, (name, vr) in enumerate(result.variants.items()):
        rep = vr.replay
        d = decimate(len(rep), PLOT_MAX_POINTS)
        style = {'ls': '--', 'lw': 1.2, 'color': '0.4'} if name == 'live' else \
            {'lw': 1.0, 'color': colors[c % len(colors)]}
        for i, ax in enumerate(axes[:, 0]):
            ax.plot((rep.stamp_ns[d] - t0) * 1e-9, rep.x_hat[d, i], label=name, **style)
    for i, ax in enumerate(axes[:, 0]):
        ax.set_ylabel(names[i])
        ax.grid(True, alpha=0.3)
    axes[0, 0].legend(loc='best', fontsize='small')
    axes[0, 0].set_title(f'{result.vehicle.name}: true and estimated states')
    axes[-1, 0].set_xlabel('time since the start of the bag [s]')
    files.append(save_figure(fig, out / 'states.png'))
    if result.truth is not None:
        fig, ax = plt.subplots(figsize=(10, 4))
        for c, (name, vr) in enumerate(result.variants.items()):
            if vr.error is None:
                continue
            # the matched rows, decimated first (a block at a time)
            ok = decimated_rows(len(vr.matched), PLOT_MAX_POINTS, vr.matched)
            norm = np.linalg.norm(vr.error[ok], axis=1)
            ts = (vr.replay.stamp_ns[ok] - t0) * 1e-9
            style = {'ls': '--', 'color': '0.4'} if name == 'live' else \
                {'color': colors[c % len(colors)]}
            ax.semilogy(ts, np.maximum(norm, 1e-16), label=name, **style)
        ax.set_xlabel('time since the start of the bag [s]')
        ax.set_ylabel('|x_hat - x|')
        ax.set_title('estimation error norm')
        ax.grid(True, which='both', alpha=0.3)
        ax.legend(loc='best', fontsize='small')
        files.append(save_figure(fig, out / 'error_norm.png'))
    outputs = result.output_names
    fig, axes = plt.subplots(len(outputs), 1, sharex=True, squeeze=False,
                             figsize=(10, 2.2 * len(outputs) + 1))
    for c, (name, vr) in enumerate(result.variants.items()):
        rep = vr.replay
        for j, ax in enumerate(axes[:, 0]):
            # the rows with this output, decimated first (a block at a time)
            ok = decimated_rows(len(rep), PLOT_MAX_POINTS,
                                lambda lo, hi: np.isfinite(rep.residual[lo:hi, j]))
            if not ok.size:
                continue
            style = {'ls': '--', 'color': '0.4'} if name == 'live' else \
                {'color': colors[c % len(colors)]}
            ax.plot((rep.stamp_ns[ok] - t0) * 1e-9, rep.residual[ok, j], lw=0.8,
                    label=name, **style)
    for j, ax in enumerate(axes[:, 0]):
        ax.set_ylabel(f'residual {outputs[j]}')
        ax.grid(True, alpha=0.3)
    axes[0, 0].legend(loc='best', fontsize='small')
    axes[0, 0].set_title('residuals y - (C x_prior + D u)')
    axes[-1, 0].set_xlabel('time since the start of the bag [s]')
    files.append(save_figure(fig, out / 'residuals.png'))
    return files


def plot_t0(result):
    """Return the earliest stamp (ns) of the estimates and the truth: the plots' time zero."""
    starts = [int(vr.replay.stamp_ns.min()) for vr in result.variants.values()
              if len(vr.replay)]
    if result.truth is not None and result.truth[0].size:
        starts.append(int(result.truth[0].min()))
    return min(starts) if starts else 0


def plot_autocovariances(path, output_names, fits, title):
    """
    Plot empirical against fitted innovation autocovariances, with +-2 sigma bands.

    Parameters
    ----------
    path : Path
        The PNG to write.
    output_names : sequence of str
        One row of panels per output (the diagonal autocovariances).
    fits : sequence of (label, empirical, fitted, sigma)
        One column per fit (e.g. per reference filter): the autocovariances (lags, p, p)
        of the data and of the identified model, and the standard deviation (lags, p) of
        each empirical one.
    title : str
        Figure title.

    """
    plt = pyplot()
    fig, axes = plt.subplots(len(output_names), len(fits), squeeze=False,
                             figsize=(6 * len(fits), 2.6 * len(output_names) + 0.8))
    for c, (label, empirical, fitted, sigma) in enumerate(fits):
        empirical, fitted, sigma = (np.asarray(a, float) for a in (empirical, fitted, sigma))
        lags = np.arange(empirical.shape[0])
        for i, ax in enumerate(axes[:, c]):
            f = fitted[:, i, i]
            ax.fill_between(lags, f - 2 * sigma[:, i], f + 2 * sigma[:, i], color='C0',
                            alpha=0.2, label='fitted +-2 sigma')
            ax.plot(lags, f, 'C0-', label='fitted (identified Q, R)')
            ax.plot(lags, empirical[:, i, i], 'ko', ms=3, label='empirical')
            ax.axhline(0.0, color='0.5', lw=0.5)
            ax.set_ylabel(f'C_j[{output_names[i]}]')
            ax.grid(True, alpha=0.3)
        axes[0, c].set_title(label, fontsize='medium')
        axes[-1, c].set_xlabel('lag j [samples]')
    axes[0, 0].legend(loc='best', fontsize='small')
    fig.suptitle(title)
    return save_figure(fig, path)


def plot_search(path, parameter, scales, metrics, metric_name, best=None, log=True):
    """Plot a gain search's metric against the parameter (one line per bag, and the mean)."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(8, 4))
    scales = np.asarray(scales, float)
    for name, values in metrics.items():
        style = {'color': 'k', 'lw': 2.0, 'marker': 'o'} if name == 'mean' else \
            {'lw': 1.0, 'marker': '.', 'alpha': 0.7}
        ax.plot(scales, values, label=name, **style)
    if best is not None:
        ax.axvline(best, color='C3', ls='--', lw=1.0, label=f'best {best:g}')
    if log:
        ax.set_xscale('log')
    ax.set_xlabel(parameter)
    ax.set_ylabel(metric_name)
    ax.grid(True, which='both', alpha=0.3)
    ax.legend(loc='best', fontsize='small')
    return save_figure(fig, path)
