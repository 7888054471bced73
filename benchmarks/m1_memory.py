# benchmarks/m1_memory.py: M1, what the offline tools keep per message, spilled and in memory.
"""
M1: the memory the offline tools keep and peak at per message, spilled and in memory.

P3's synthesised Imu bags of the submarine (``p3_replay.generate``: one Imu message a
step, a command and a true state every 10 steps) at two sizes, N and 2N messages; each
figure is the growth from the small bag to the large one per message (or per variant),
traced by ``tracemalloc`` in this process, after one run that takes the first run's
one-off allocations. Except for finding runs, the replay's blocks are 2^12 rows, so both
bags are many blocks long. The baseline, measured in the same run, is the same work in
memory (``spill=None``): what the spilled path keeps must be a small fraction of it.

- **reader**: ``read_recording`` of the bag, spilled against in memory (the columns
  themselves: 29 B per Imu message, about 37 with the commands and true states).
- **eval**: ``evaluate_bag`` (observer-eval's work), spilled against in memory: kept and
  peak per estimate.
- **search**: the gain search (``score_variants``: each variant's rows dropped once it is
  scored) with 1, 2 and 4 scales on the small bag, spilled and in memory: the peak per
  message with 4 scales against 1; observer-eval keeping its 4 variants' rows in memory
  is the measure's check (it must grow by about 50 B per message and variant).
- **variants**: observer-eval spilled, 4 variants against 1: what each further variant
  keeps per estimate (its matched flags, about a byte).
- **finding runs**: the replay's bulk stretches found in blocks of 256 steps (its own
  other blocks): the growth of the transient memory (peak above what is kept) from the
  small bag to the large against that of one whole-bag block; what is kept (the
  measurements' event indices, 8 B each, and the pieces) doubles.

Targets (bytes are per message, from the figures' tracemalloc): spilled / in memory
<= 0.1 for the reader's and the evaluation's kept and peak growth; the reader in memory
below 38 B kept and 40 B at the peak; spilled below 1 B kept and 2 B at the peak
(reader), 4 B kept and 6 B at the peak (eval); the search's peak with 4 scales within
10 B of 1 scale's, spilled and in memory (and within 2 B of 2 scales' spilled), its
kept bytes within 3 B; observer-eval's in-memory variants growing by more than 3 x 40 B;
a further spilled variant under 3 B per estimate; finding runs in blocks, the transient's
growth <= 0.1x of one whole-bag block's and the kept within 2.6x from the small bag to
the large. ``--smoke``: bags of 8000 and 16000 messages, figures printed, targets not
judged.

"""

from pathlib import Path
import sys
import tracemalloc

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import common_parser, log, ratio_line, REPO, report  # noqa: E402
import p3_replay  # noqa: E402

VEHICLE = REPO / 'config' / 'submarine.yaml'
SCALES = (0.5, 0.8, 1.25, 2.0)
BLOCK = 1 << 12          # the replay's blocks, so that the bags are many blocks long


def _small_blocks():
    """Set every block of the replay at BLOCK rows."""
    from observer_ros.replay import bulk_runs, health, rows
    for module, name in ((bulk_runs, 'RUN_BLOCK'), (bulk_runs, 'MAX_RUN'),
                         (rows, 'SPILL_BLOCK'), (health, 'HEALTH_BLOCK')):
        setattr(module, name, BLOCK)


def _traced(func):
    """Return func()'s result, the bytes it left allocated and its peak (tracemalloc)."""
    tracemalloc.start()
    try:
        out = func()
        kept, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    return out, kept, peak


def _growth(small, large, count):
    """Return (kept, peak) growth per message from two (_, kept, peak) triples."""
    return (large[1] - small[1]) / count, (large[2] - small[2]) / count


def reader(bags, count, veh):
    """Return {spill: (kept, peak) per Imu message} of read_recording."""
    from observer_ros.bag.reader import read_recording
    out = {}
    for spill in (True, None):
        read_recording(bags[0], veh, spill=spill)          # one-off allocations
        runs = [_traced(lambda b=b: read_recording(b, veh, spill=spill)) for b in bags]
        assert len(runs[1][0].sensors['gyro']) - len(runs[0][0].sensors['gyro']) == count
        out[spill] = _growth(*runs, count)
    return out


def evaluation(bags, count, veh):
    """Return {spill: (kept, peak) per estimate} of evaluate_bag."""
    from observer_ros.evaluation import evaluator
    out = {}
    evaluator.evaluate_bag(bags[0], veh, spill=True)       # one-off allocations
    for spill in (True, None):
        runs = [_traced(lambda b=b: evaluator.evaluate_bag(b, veh, spill=spill))
                for b in bags]
        rows = [len(r[0].variants['design'].replay) for r in runs]
        assert rows[1] - rows[0] == count, rows
        out[spill] = _growth(*runs, count)
    return out


def _eval_variants(bag, veh, scales, spill):
    from observer_ros.evaluation import evaluator
    from observer_ros.tuning.gain_search import search_overrides
    variants = {f's{i}': search_overrides(veh, 'poles', s) for i, s in enumerate(scales)}
    return evaluator.evaluate_bag(bag, veh, variants, include_design=False,
                                  include_live=False, spill=spill)


def search(bag, count, veh):
    """Return the search's {(spill, scales): (kept, peak) per message} and eval's growth."""
    from observer_ros.tuning.gain_search import score_variants, search_overrides

    def run(k, spill):
        overrides = [search_overrides(veh, 'poles', s) for s in SCALES[:k]]
        return score_variants([bag], VEHICLE, overrides, 0, spill=spill)
    run(1, True)                                            # one-off allocations
    figures, first = {}, None
    for spill, counts in ((True, (1, 2, 4)), (None, (1, 4))):
        for k in counts:
            (got, _), kept, peak = _traced(lambda: run(k, spill))
            first = first or got[str(bag)][0]
            assert got[str(bag)][0] == first                # the same first scale's metric
            figures[spill, k] = (kept / count, peak / count)
    one = _traced(lambda: _eval_variants(bag, veh, SCALES[:1], None))
    four = _traced(lambda: _eval_variants(bag, veh, SCALES, None))
    return figures, _growth(one, four, count)


def variants(bag, veh):
    """Return what each further spilled variant of observer-eval keeps per estimate."""
    _eval_variants(bag, veh, SCALES[:1], True)              # one-off allocations
    one, kept1, _ = _traced(lambda: _eval_variants(bag, veh, SCALES[:1], True))
    _, kept4, _ = _traced(lambda: _eval_variants(bag, veh, SCALES, True))
    return (kept4 - kept1) / (len(SCALES) - 1) / len(one.variants['s0'].replay)


def _finding_runs(rec, veh, block):
    """Return the transient peak of finding the replay's runs above what it keeps, and that."""
    from observer_ros.core.estimators import make_estimator
    from observer_ros.replay.bulk_runs import find_runs
    from observer_ros.replay.events import Events
    counts = dict.fromkeys(('bad_stamps', 'bad_messages', 'bad_commands'), 0)
    events = Events(rec, list(veh.sensors), veh.plant, counts)
    est = make_estimator(veh.plant, veh.observer)
    tracemalloc.start()
    try:
        tracemalloc.reset_peak()
        base = tracemalloc.get_traced_memory()[0]
        runs = find_runs(events, events.streams, events.command, est, 0.5, 10.0, block=block)
        kept, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert runs.pieces
    return peak - kept, kept - base


def finding_runs(bags, veh):
    """Return {block: ((transient, kept) small bag, (transient, kept) large bag)}."""
    from observer_ros.bag.reader import read_recording
    recs = [read_recording(bag, veh) for bag in bags]
    return {block: [_finding_runs(rec, veh, block) for rec in recs]
            for block in (256, 1 << 40)}


def run(smoke=False, data=None):
    """Run M1; return its figures."""
    from observer_ros.vehicle import load_vehicle
    n = 8_000 if smoke else 70_000
    data = Path(data or p3_replay.DATA)
    bags = [p3_replay.generate(m, data=data, log=lambda *a: None) for m in (n, 2 * n)]
    veh = load_vehicle(VEHICLE)
    log(f"  M1        finding the replay's runs: bags of {n} and {2 * n} Imu messages")
    runs = finding_runs(bags, veh)                 # the replay's own blocks
    _small_blocks()
    records = []

    def line(name, ratios, op, target, unit='x', note=''):
        records.append(ratio_line('M1', name, ratios, op, target, unit=unit, smoke=smoke,
                                  note=note))

    log(f'  M1        reader and evaluation: bags of {n} and {2 * n} Imu messages')
    read_figures = reader(bags, n, veh)
    for what, figures in (('reader', read_figures), ('eval', evaluation(bags, n, veh))):
        (ks, ps), (km, pm) = figures[True], figures[None]
        note = f'B per message: spilled {ks:.2f} kept, {ps:.2f} peak; in memory ' \
               f'{km:.1f} kept, {pm:.1f} peak'
        line(f'{what}_kept_per_message_spilled/in_memory', [ks / km], '<=', 0.1, note=note)
        line(f'{what}_peak_per_message_spilled/in_memory', [ps / pm], '<=', 0.1)
        limits = {'reader': (1.0, 2.0), 'eval': (4.0, 6.0)}[what]
        line(f'{what}_kept_per_message_spilled', [ks], '<=', limits[0], unit='B')
        line(f'{what}_peak_per_message_spilled', [ps], '<=', limits[1], unit='B')
    # in memory, an Imu message is seq 4 + receive time 8 + stamp 8 + value 8 + valid 1 =
    # 29 B; a command and a true state every 10 messages add 2.9 and 4.5
    km, pm = read_figures[None]
    line('reader_kept_per_message_in_memory', [km], '<=', 38.0, unit='B')
    line('reader_peak_per_message_in_memory', [pm], '<=', 40.0, unit='B')
    (t1, k1), (t2, k2) = runs[256]
    (w1, _), (w2, _) = runs[1 << 40]
    line('finding_runs_transient_growth_blocks_of_256/one_block', [(t2 - t1) / (w2 - w1)],
         '<=', 0.1, note=f'transient {t1 / 1024:.0f} -> {t2 / 1024:.0f} KiB in blocks, '
                         f'{w1 / 1024:.0f} -> {w2 / 1024:.0f} KiB in one block; kept '
                         f'{k1 / 1024:.0f} -> {k2 / 1024:.0f} KiB')
    line('finding_runs_kept_large/small_bag[block 256]', [k2 / k1], '<=', 2.6)
    log(f'  M1        gain search over 1, 2 and 4 scales: {n} Imu messages')
    figures, eval_growth = search(bags[0], n, veh)
    for spill, name in ((True, 'spilled'), (None, 'in_memory')):
        peaks = {k: figures[key][1] for key in figures if key[0] is spill
                 for k in (key[1],)}
        line(f'search_peak_4_scales-1_scale_{name}', [peaks[4] - peaks[1]], '<=', 10.0,
             unit='B', note='B per message: ' + ', '.join(
                 f'{k} scale(s) {figures[spill, k][1]:.1f} peak, {figures[spill, k][0]:.1f} '
                 f'kept' for k in sorted(peaks)))
        line(f'search_kept_4_scales-1_scale_{name}',
             [abs(figures[spill, 4][0] - figures[spill, 1][0])], '<=', 3.0, unit='B')
    line('search_peak_4_scales-2_scales_spilled',
         [figures[True, 4][1] - figures[True, 2][1]], '<=', 2.0, unit='B')
    line('eval_in_memory_4_variants-1_kept', [eval_growth[0]], '>=', 120.0, unit='B')
    line('eval_in_memory_4_variants-1_peak', [eval_growth[1]], '>=', 120.0, unit='B')
    line('eval_spilled_kept_per_further_variant', [variants(bags[0], veh)], '<=', 3.0,
         unit='B')
    return {'id': 'M1', 'figures': records}


def main(argv=None):
    """Run M1 (``--smoke``: small bags, targets not judged)."""
    parser = common_parser(__doc__.splitlines()[1])
    parser.add_argument('--data', help='where the bags are written '
                        "(default: P3's, ~/.cache/observer_ros/benchmarks)")
    args = parser.parse_args(argv)
    print('M1: memory per message of the offline tools, spilled and in memory', flush=True)
    return report(args.json, run(smoke=args.smoke, data=args.data))


if __name__ == '__main__':
    raise SystemExit(main())
