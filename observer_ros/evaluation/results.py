# observer_ros.evaluation.results: what an evaluation computed (one bag, its variants).
"""
The results of evaluating a bag: one :class:`VariantResult` per observer configuration.

:class:`EvalResult` holds the recording, the truth and the variants (numpy arrays, for
the plots and the results bag); :meth:`EvalResult.to_dict` gives plain JSON-ready data.

"""

from dataclasses import dataclass, field
import math
from pathlib import Path
from typing import Dict, List, Optional, Tuple

import numpy as np

__all__ = ['VariantResult', 'EvalResult', 'ScoredReplay', 'jsonable']


@dataclass
class VariantResult:
    """
    One configuration's replay and its metrics.

    ``states`` maps a state name to ``rmse``, ``max_abs_error``, ``settling_time`` (s;
    ``inf`` if the error is outside the tolerance at the end), ``ss_std``, ``ss_mean``
    and ``samples`` (matched with the truth); empty without ground truth. ``outputs`` maps
    an output name to ``samples``, ``residual_rms``, ``ljung_box_q``, ``ljung_box_p``,
    ``lags`` and ``acf_outside``. ``summary`` has ``error_rms`` (RMS of the error norm)
    and ``settling_time`` (the largest over the states). ``sensors`` maps a sensor name to
    its innovation health, judged by windows as the node does
    (:func:`~observer_ros.replay.replay.innovation_health`).

    """

    name: str
    kind: str
    overrides: Tuple[str, ...]
    replay: object
    states: Dict[str, dict] = field(default_factory=dict)
    outputs: Dict[str, dict] = field(default_factory=dict)
    summary: Dict[str, object] = field(default_factory=dict)
    sensors: Dict[str, dict] = field(default_factory=dict)
    # (N, n) x_hat - x_true, NaN where unmatched: a metrics.StateError, rows on demand
    error: Optional[object] = None
    matched: Optional[np.ndarray] = None     # (N,) bool: rows with every state finite

    @property
    def t(self):
        """Stamps of the estimates in seconds."""
        return self.replay.t

    @property
    def stamp_ns(self):
        """Stamps of the estimates in integer nanoseconds."""
        return self.replay.stamp_ns

    @property
    def x_hat(self):
        """Return the estimates, (N, n)."""
        return self.replay.x_hat

    @property
    def residual(self):
        """Return the residuals, (N, p), NaN for outputs a message did not carry."""
        return self.replay.residual


@dataclass
class ScoredReplay:
    """
    What stays of a replay once it is scored and its rows dropped (``keep_rows=False``).

    The row count and the counters the tables and JSON give; no rows, so a search over
    many variants holds one replay's rows at a time.

    """

    name: str
    rows: int
    counts: Dict[str, int]
    bulk_steps: int = 0
    warnings: list = field(default_factory=list)

    @classmethod
    def of(cls, rep):
        """Return the scored summary of a replay."""
        return cls(rep.name, len(rep), dict(rep.counts), int(getattr(rep, 'bulk_steps', 0)),
                   list(rep.warnings))

    def __len__(self):
        """Return the number of estimates the replay had."""
        return self.rows


@dataclass
class EvalResult:
    """Everything :func:`evaluate_bag` computed."""

    bag_path: Path
    vehicle: object
    recording: object
    variants: Dict[str, VariantResult]
    truth: Optional[Tuple[np.ndarray, np.ndarray, np.ndarray]]   # stamp_ns, values, epoch
    tolerance: Dict[str, float]
    tolerance_rule: str
    warnings: List[str] = field(default_factory=list)
    seconds: float = 0.0
    truth_at: Optional[object] = field(default=None, repr=False)  # metrics.TruthAt, shared

    @property
    def state_names(self):
        """Return the vehicle's state names."""
        return tuple(self.vehicle.plant.state_names)

    @property
    def output_names(self):
        """Return the vehicle's output names."""
        return tuple(self.vehicle.plant.output_names)

    @property
    def namespace(self):
        """Return the vehicle's namespace in the bag."""
        return self.recording.namespace

    def to_dict(self):
        """Return the results as JSON-ready data (inf and NaN as None)."""
        info = self.recording.info
        out = {
            'bag': str(self.bag_path),
            'storage': info.storage,
            'messages': info.message_count,
            'duration_s': (info.end_ns - info.start_ns) * 1e-9 if info.message_count else 0.0,
            'vehicle': self.vehicle.name,
            'namespace': self.namespace or '/',
            'topics': {k: v for k, v in vars(self.recording.topics).items()
                       if k != 'namespace'},
            'ground_truth': self.truth is not None,
            'tolerance': dict(self.tolerance),
            'tolerance_rule': self.tolerance_rule,
            'units': {kind: {name: self.vehicle.unit(kind, name) for name in names}
                      for kind, names in (('state', self.vehicle.plant.state_names),
                                          ('input', self.vehicle.plant.input_names),
                                          ('output', self.vehicle.plant.output_names))},
            'variants': {},
            'warnings': list(self.warnings),
        }
        for name, v in self.variants.items():
            out['variants'][name] = {
                'observer_type': v.kind,
                'overrides': list(v.overrides),
                'estimates': len(v.replay),
                'bulk_steps': int(getattr(v.replay, 'bulk_steps', 0)),
                'counts': dict(v.replay.counts),
                'summary': dict(v.summary),
                'states': v.states,
                'outputs': v.outputs,
                'sensors': v.sensors,
            }
        return jsonable(out)


def jsonable(obj):
    """Return obj with numpy values as Python ones, inf and NaN as None, paths as str."""
    if isinstance(obj, dict):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        f = float(obj)
        return f if math.isfinite(f) else None
    if isinstance(obj, np.ndarray):
        return jsonable(obj.tolist())
    if isinstance(obj, Path):
        return str(obj)
    return obj
