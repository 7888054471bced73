# test/evaluation/test_bag_variants_memory.py: many variants of one bag in the memory of one.
"""
An evaluation scores each variant as soon as its replay ends.

The gain search (``score_variants``) and the batch jobs drop each variant's rows once it
is scored, so their memory does not grow with the number of variants (tracemalloc's
peak with 4 scales against 1 on P3's synthesised Imu bag, spilled and in memory, while
observer-eval's in-memory replays of 4 variants do grow by their rows: the test can
fail); observer-eval's spilled variants keep about a byte per estimate each (the matched
flags). The metrics are the same whether the rows are kept, spilled or dropped, and
``observer-eval-batch --in-memory`` writes the same tables as its spilled default.

"""

import tracemalloc

from bag_cases import numbers, p3_benchmark, spy_on_spill
from bag_synth import CONFIG
from observer_ros.evaluation import batch, evaluator as evaluate
from observer_ros.evaluation.jobs import make_jobs, run_jobs
from observer_ros.evaluation.results import ScoredReplay
from observer_ros.replay import bulk_runs, health as replay_health, rows as replay_outputs
from observer_ros.tuning.gain_search import score_variants, search_overrides
from observer_ros.vehicle import load_vehicle
import pytest

SAMPLES = CONFIG.parent / 'bags' / 'samples'
ROWS = 70_000
SCALES = (0.5, 0.8, 1.25, 2.0)


@pytest.fixture(scope='module')
def p3_bag(tmp_path_factory):
    """Return P3's synthesised Imu bag of 70000 messages (submarine, with state/true)."""
    data = tmp_path_factory.mktemp('p3')
    return p3_benchmark().generate(ROWS, data=data, log=lambda *a: None)


@pytest.fixture
def small_blocks(monkeypatch):
    # every block of the replay at 2^12 rows, so that the bag is many blocks long
    for module, name in ((bulk_runs, 'RUN_BLOCK'), (bulk_runs, 'MAX_RUN'),
                         (replay_outputs, 'SPILL_BLOCK'), (replay_health, 'HEALTH_BLOCK')):
        monkeypatch.setattr(module, name, 1 << 12)


def _peak(func):
    tracemalloc.start()
    try:
        out = func()
        kept, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    return out, kept, peak


def _search(bag, veh, scales, spill):
    overrides = [search_overrides(veh, 'poles', s) for s in scales]
    return score_variants([bag], CONFIG / 'submarine.yaml', overrides, 0, spill=spill)


def _eval(bag, scales, spill, keep_rows=True):
    veh = load_vehicle(CONFIG / 'submarine.yaml')
    variants = {f's{i}': search_overrides(veh, 'poles', s) for i, s in enumerate(scales)}
    return evaluate.evaluate_bag(bag, veh, variants, include_design=False,
                                 include_live=False, spill=spill, keep_rows=keep_rows)


def test_search_memory_does_not_grow_with_the_scales(p3_bag, small_blocks):
    veh = load_vehicle(CONFIG / 'submarine.yaml')
    _search(p3_bag, veh, SCALES[:1], True)           # the first run's one-off allocations
    figures = {}                                     # (spill, scales): bytes per message
    for spill, counts in ((True, (1, 2, 4)), (None, (1, 4))):
        first = None
        for k in counts:
            (got, _), kept, peak = _peak(lambda: _search(p3_bag, veh, SCALES[:k], spill))
            first = first or got[str(p3_bag)][0]
            assert got[str(p3_bag)][0] == first                      # the same first scale
            figures[spill, k] = (kept / ROWS, peak / ROWS)
    (_, kept1, peak1) = _peak(lambda: _eval(p3_bag, SCALES[:1], None))
    (_, kept4, peak4) = _peak(lambda: _eval(p3_bag, SCALES, None))
    eval_growth = ((kept4 - kept1) / ROWS, (peak4 - peak1) / ROWS)
    print('bytes per message (kept, peak): search %s; observer-eval in memory, 4 variants '
          'minus 1: %.1f, %.1f' % ({k: tuple(round(x, 1) for x in v)
                                    for k, v in figures.items()}, *eval_growth))
    # measured (2^12-row blocks): spilled, peaks of 210.9, 217.3, 218.0 with 1, 2, 4
    # scales (the second scale's +6: the truth's sorted copy, made once when the first
    # is scored, shared by the others), 3.2-3.9 kept; in memory 253.9 and 260.8 with 1
    # and 4. observer-eval keeping 3 more in-memory replays adds ~3 x 50.
    for spill in (True, None):
        assert figures[spill, 4][1] - figures[spill, 1][1] < 10.0, figures
        assert abs(figures[spill, 4][0] - figures[spill, 1][0]) < 3.0, figures
    assert figures[True, 4][1] - figures[True, 2][1] < 2.0, figures
    assert eval_growth[0] > 3 * 40.0 and eval_growth[1] > 3 * 40.0, eval_growth


def test_spilled_variants_keep_about_a_byte_per_estimate(p3_bag, small_blocks):
    _eval(p3_bag, SCALES[:1], True)
    (one, kept1, _) = _peak(lambda: _eval(p3_bag, SCALES[:1], True))
    (four, kept4, _) = _peak(lambda: _eval(p3_bag, SCALES, True))
    per_variant = (kept4 - kept1) / 3 / len(one.variants['s0'].replay)
    print('observer-eval, spilled: %.2f bytes kept per estimate and variant' % per_variant)
    # the matched flags (1 byte) and the spilled columns' file objects; the truth's
    # sorted copy is shared by the variants
    assert per_variant < 3.0, per_variant


@pytest.mark.parametrize('name', ['submarine', 'cart_pendulum'])
def test_dropped_rows_give_the_kept_rows_metrics(name):
    veh = load_vehicle(CONFIG / f'{name}.yaml')
    variants = {'openloop': ['observer.type:=open_loop']}
    kept = evaluate.evaluate_bag(SAMPLES / name, veh, variants).to_dict()
    for spill in (True, None):
        result = evaluate.evaluate_bag(SAMPLES / name, veh, variants, spill=spill,
                                       keep_rows=False)
        assert all(isinstance(v.replay, ScoredReplay) and v.error is None and
                   v.matched is None for v in result.variants.values())
        assert list(result.variants) == ['design', 'openloop', 'live']
        assert result.to_dict() == kept


def test_jobs_spill_by_default_with_the_same_rows(tmp_path, monkeypatch):
    jobs = make_jobs([SAMPLES / 'submarine'], CONFIG / 'submarine.yaml',
                     {'openloop': ['observer.type:=open_loop']})
    spills = spy_on_spill(monkeypatch)
    assert numbers(run_jobs(jobs, 'serial')) == numbers(run_jobs(jobs, 'serial', spill=None))
    assert spills == [True, True, None, None]
    tables = []
    for extra in ([], ['--in-memory']):
        out = tmp_path / f'out{len(tables)}'
        argv = [str(SAMPLES / 'submarine'), '--vehicle', str(CONFIG / 'submarine.yaml'),
                '--out', str(out), '--serial', '--no-plots', *extra]
        assert batch.main(argv) == 0
        tables.append([(out / f).read_text() for f in ('results.txt', 'summary.csv')])
    assert spills[4:] == [True, None]
    assert tables[0] == tables[1]
