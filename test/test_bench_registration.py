"""bench/bench_registration.py --corpus --case: one case of the corpus run, drawn as in the full
run, and clear errors for a bad selection."""
from __future__ import annotations

import importlib
import sys
from pathlib import Path

import numpy as np
import pytest

BENCH = Path(__file__).resolve().parent.parent / 'bench'


@pytest.fixture
def bench(monkeypatch):
    monkeypatch.syspath_prepend(str(BENCH))
    mod = importlib.import_module('bench_registration')
    full = mod.corpus_case
    # small cases and no peers: the selection, not the registration, is under test
    monkeypatch.setattr(mod, 'corpus_case', lambda S, rng, hard: full(S, rng, hard, n=1500))
    monkeypatch.setattr(mod, 'peers_rigid', lambda src, tgt: [])
    yield mod
    sys.modules.pop('bench_registration', None)


def _shape(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    u, v = rng.uniform(-1, 1, (2, 4000))
    X = np.stack([u, 0.8 * v, 0.3 * (u ** 2 - 0.6 * v ** 2) + 0.2 * u * v], 1)
    X -= X.mean(0)
    return X / np.linalg.norm(X.max(0) - X.min(0))


def test_case_selects_one_draw_of_the_full_run(bench):
    items = [('a', _shape(0)), ('b', _shape(1))]
    full = bench.run_corpus(3, items, False)
    assert len(full) == 2 * 2 * 3                       # shapes x conditions x trials
    picked = bench.parse_cases(['b:hard:2', 'a:clean:0'], ['a', 'b'])
    assert picked == {('b', True): {2}, ('a', False): {0}}
    some = bench.run_corpus(3, items, False, picked)
    assert [(r['shape'], r['condition']) for r in some] == \
        [('a', 'clean'), ('b', '30% missing + 50% outliers')]
    # the same draws: rows of the full run are b hard at index 3*3 + 3 + 2, a clean at 0
    for r, ref in zip(some, (full[0], full[3 * 2 + 3 + 2])):
        assert r['error'] == ref['error'] and r['fitness'] == ref['fitness']


@pytest.mark.parametrize('spec, match', [
    ('nope:hard:1', "shape 'nope' is not in the corpus"),
    ('a:noisy:1', "condition 'noisy'"),
    ('a:hard:-1', "trial '-1'"),
    ('a:hard', 'expected SHAPE:CONDITION:TRIAL')])
def test_case_rejects_a_bad_selection(bench, spec, match):
    with pytest.raises(ValueError, match=match):
        bench.parse_cases([spec], ['a', 'b'])
