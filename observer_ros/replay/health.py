# observer_ros.replay.health: a replay's innovation health, as the node judges it.
"""
The innovation health of each sensor of a replay, a block of estimates at a time.

The node's windowed judgement (:func:`observer_ros.core.innovation.sequence_health_blocks`)
over each sensor's whitened residuals, the initial transient of each epoch left out;
:data:`HEALTH_BLOCK` estimates are taken at a time, so no whole-replay temporaries.

"""

import numpy as np

from ..bag.spill import spill_folder, SpilledColumn
from ..core.innovation import sequence_health_blocks, transient_time
from ..core.vehicle_design import design_vehicle

__all__ = ['innovation_health']

HEALTH_BLOCK = 1 << 16        # estimates: the innovation health takes this many at a time


def innovation_health(rep, spill=None):
    """
    Return the innovation health of each sensor of a replay, as the node judges it.

    Parameters
    ----------
    rep : Replay
        From :func:`replay` (None figures for the live estimate).
    spill : True or path, optional
        Keep the judged rows' NIS (8 bytes a row, for its mean) in a temporary file.

    Returns
    -------
    health : dict
        Sensor name -> :func:`observer_ros.core.innovation.sequence_health` figures.

    """
    if rep.whitened is None and rep.noise_std is None:
        return {}
    veh = rep.vehicle
    plant = veh.plant
    # the initial transient of each epoch (the estimator restarts) is not judged
    transient = transient_time(design_vehicle(veh).observer_poles, veh.sample_time,
                               plant.is_discrete, rep.kalman)
    starts, t0 = _epoch_starts(rep) if transient > 0.0 else (None, None)
    counts = np.zeros(len(veh.sensors), dtype=np.int64)
    for b0 in range(0, len(rep), HEALTH_BLOCK):
        sens = rep.sensor[b0:b0 + HEALTH_BLOCK]
        counts += np.bincount(sens[sens >= 0], minlength=len(counts))[:len(counts)]
    out = {}
    for k, s in enumerate(veh.sensors):
        cols = list(plant.output_rows(s.outputs))
        nis = None if spill is None else SpilledColumn(np.float64, (), spill_folder(spill))
        out[s.name] = sequence_health_blocks(s.name, _health_blocks(rep, k, cols, starts, t0),
                                             rep.kalman, transient=transient,
                                             rows=int(counts[k]), nis=nis)
    return out


def _epoch_starts(rep):
    """Return the epochs of a replay and the stamp (s) of each one's first row."""
    first = {}
    for b0 in range(0, len(rep), HEALTH_BLOCK):
        ep, at = np.unique(rep.epoch[b0:b0 + HEALTH_BLOCK], return_index=True)
        for e, i in zip(ep.tolist(), at.tolist()):
            first.setdefault(e, b0 + i)
    starts = np.array(sorted(first), dtype=rep.epoch.dtype)
    idx = np.array([first[e] for e in starts.tolist()], dtype=np.int64)
    return starts, rep.stamp_ns[idx].astype(np.float64) * 1e-9


def _health_blocks(rep, k, cols, starts, t0):
    """Yield sensor k's whitened residuals and their seconds since the epoch's start."""
    for b0 in range(0, max(len(rep), 1), HEALTH_BLOCK):
        b1 = b0 + HEALTH_BLOCK
        mine = rep.sensor[b0:b1] == k
        E = rep.whitened_rows(b0, b1)[mine][:, cols]
        since = None
        if starts is not None:
            t = rep.stamp_ns[b0:b1][mine].astype(np.float64) * 1e-9
            since = t - t0[np.searchsorted(starts, rep.epoch[b0:b1][mine])]
        yield E, since
