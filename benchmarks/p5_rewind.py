# benchmarks/p5_rewind.py: the cost of a late measurement (one rewind of the history).
"""
P5: a rewind over 100 ms of 1 kHz data against the same corrections made in order.

The two-sensor submarine (a gyro q at 1 kHz, a pitch sensor theta) with a Kalman and a
full-order observer, through the core's ``History`` (0.25 s). After 1 s of gyro data in
order, each repetition adds 100 gyro messages (1 kHz) in order, then a pitch message
stamped 100 ms before the newest stamp: the history restores the state before it and
applies it and the 100 later messages again (one rewind). The baseline, timed in the
same repetition (alternated A B B A), is a plain estimator making those 101 corrections
in stamp order: what the rewind must redo anyway. Figures: rewind / baseline, and the
per-message cost of the in-order path through the history / the plain estimator (what
the history adds to every message, P1's path).

"""

from pathlib import Path
import sys

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from _common import common_parser, log, ratio_line, report, Timer  # noqa: E402
import numpy as np  # noqa: E402
from observer_ros.core.estimators import (FullOrderEstimator, History,  # noqa: E402
                                          KalmanEstimator)
from observer_ros.core.model import Plant  # noqa: E402

A = [[0.0, 0.0, 1.0], [0.0135, -0.322, -0.7102], [-0.036, 0.126, -0.7395]]
B = [[0.0], [0.0322], [-0.0857]]
C = [[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]
DT = 0.001          # 1 kHz
LATE = 100          # messages re-applied by the rewind (100 ms)


def make(kind):
    """Return an estimator of the two-sensor submarine."""
    plant = Plant(A, B, C, None, state_names=('theta', 'w', 'q'), output_names=('q', 'theta'))
    if kind == 'kalman':
        return KalmanEstimator(plant, np.diag([1e-6, 1e-4, 1e-4]), np.diag([1e-6, 1e-4]))
    return FullOrderEstimator(plant, poles=[-2.0, -2.1, -2.2])


def run_kind(kind, reps, records, smoke):
    """Time ``reps`` rewinds of one observer kind; append the figures to records."""
    rng = np.random.default_rng(0)
    history = History(make(kind), length=0.25)
    plain = make(kind)
    t = 1.0
    for k in range(1000):                      # 1 s of data: the history is full
        y = [1e-3 * rng.standard_normal()]
        history.correct(t + k * DT, y, (0,))
        plain.correct(t + k * DT, y, (0,))
    t += 1000 * DT
    rewind, inorder, ratios, per_msg = [], [], [], []
    for rep in range(reps):
        stamps = t + DT * np.arange(LATE)
        ys = 1e-3 * rng.standard_normal(LATE)
        late_t, late_y = float(stamps[0]) - 1e-4, [0.01 * rng.standard_normal()]
        # A: in order through the history (100 messages), then the late one (a rewind)
        # B: the plain estimator: the late one and the 100 messages in stamp order
        order = (0, 1) if rep % 2 == 0 else (1, 0)
        for which in order:
            if which == 0:
                with Timer() as a_in:
                    for s, y in zip(stamps, ys):
                        history.correct(float(s), [y], (0,))
                before = history.rewinds
                with Timer() as a_late:
                    history.correct(late_t, late_y, (1,))
                assert history.rewinds == before + 1
            else:
                with Timer() as b:
                    plain.correct(late_t, late_y, (1,))
                    for s, y in zip(stamps, ys):
                        plain.correct(float(s), [y], (0,))
        t += LATE * DT
        rewind.append(a_late.seconds)
        inorder.append(b.seconds)
        ratios.append(a_late.seconds / b.seconds)
        per_msg.append(a_in.seconds / (b.seconds * LATE / (LATE + 1)))
        assert np.allclose(history.x_hat, plain.x_hat, rtol=0.0, atol=1e-9)
    med = float(np.median(rewind)) * 1e6
    base = float(np.median(inorder)) * 1e6
    records.append(ratio_line('P5', f'rewind_100ms_at_1kHz/in_order[{kind}]', ratios, '<=',
                              2.0, smoke=smoke,
                              note=f'rewind {med:.0f} us, the same 101 corrections in '
                                   f'order {base:.0f} us'))
    records.append(ratio_line('P5', f'in_order_message_with_history/plain[{kind}]', per_msg,
                              '<=', 1.5, smoke=smoke))


def run(smoke=False):
    """Run P5; return its figures."""
    reps = 5 if smoke else 60
    records = []
    for kind in ('kalman', 'full'):
        log(f'  P5        {kind}: {reps} rewinds over {LATE} messages at 1 kHz')
        run_kind(kind, reps, records, smoke)
    return {'id': 'P5', 'figures': records}


def main(argv=None):
    """Run P5 (``--smoke``: a few repetitions)."""
    parser = common_parser(__doc__.splitlines()[1])
    args = parser.parse_args(argv)
    print('P5: rewind of the history for a late measurement', flush=True)
    return report(args.json, run(smoke=args.smoke))


if __name__ == '__main__':
    raise SystemExit(main())
