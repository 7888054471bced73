# test/evaluation/test_bag_variants_memory.py: many variants of one bag in the memory of one.
"""
An evaluation scores each variant as soon as its replay ends.

The gain search (``score_variants``) and the batch jobs drop each variant's rows once it
is scored, so their memory does not grow with the number of variants (measured by
benchmarks/m1_memory.py, with what observer-eval's spilled variants keep per estimate).
The metrics are the same whether the rows are kept, spilled or dropped, and
``observer-eval-batch --in-memory`` writes the same tables as its spilled default.

"""

import json

from bag_cases import numbers, spy_on_spill
from bag_synth import CONFIG
from observer_ros.evaluation import batch, evaluator as evaluate
from observer_ros.evaluation.jobs import make_jobs, run_jobs
from observer_ros.evaluation.results import ScoredReplay
from observer_ros.tuning import gain_search
from observer_ros.vehicle import load_vehicle
import pytest

SAMPLES = CONFIG.parent / 'bags' / 'samples'
SCALES = (0.5, 0.8, 1.25, 2.0)


def test_the_search_drops_each_variants_rows_with_the_same_metrics(monkeypatch):
    # score_variants asks evaluate_bag to drop the rows once scored (keep_rows=False), in
    # temporary files by default; the metrics are those of the rows kept in memory
    calls = []
    evaluate_bag = gain_search.evaluate_bag

    def recorded(*args, **kwargs):
        result = evaluate_bag(*args, **kwargs)
        calls.append((kwargs.get('spill'), kwargs.get('keep_rows'),
                      {type(v.replay) for v in result.variants.values()}))
        return result
    monkeypatch.setattr(gain_search, 'evaluate_bag', recorded)
    veh = load_vehicle(CONFIG / 'submarine.yaml')
    overrides = [gain_search.search_overrides(veh, 'poles', s) for s in SCALES]
    bag = SAMPLES / 'submarine'
    spilled = gain_search.score_variants([bag], CONFIG / 'submarine.yaml', overrides, 0)
    kept = gain_search.score_variants([bag], CONFIG / 'submarine.yaml', overrides, 0,
                                      spill=None)
    assert calls == [(True, False, {ScoredReplay}), (None, False, {ScoredReplay})]
    assert json.dumps(spilled, sort_keys=True) == json.dumps(kept, sort_keys=True)
    assert len(set(spilled[0][str(bag)])) == len(SCALES)       # four different observers


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
