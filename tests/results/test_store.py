"""The results store under concurrent writers, and numbering its rows in the sampler's order."""

from __future__ import annotations

import random
import threading
import tomllib
from dataclasses import replace

import pytest

from falsify.errors import FalsifyError
from falsify.results.samples import CAR_SCORING, sample_key
from falsify.results.store import STORE_NAME, Store, read_frame
from falsify.world.space import parse_space
from tests.runfixture import SMOKE, synthetic_result


def space():
    return parse_space(tomllib.loads(SMOKE.read_text()), source=str(SMOKE))


def test_threads_add_to_one_store_and_renumber_fixes_the_order(tmp_path):
    sp = space()
    samples = sp.grid()
    parts = [samples[k::3] for k in range(3)]   # three callers, one sample at a time each
    store = Store(tmp_path / STORE_NAME, sp)
    fresh = []

    def caller(part):
        for s in part:
            fresh.append(store.add([synthetic_result(s, 0.5, 0)], "m", "c"))
            fresh.append(store.add([synthetic_result(s, 0.5, 0)], "m", "c"))  # a duplicate
            assert s in store and store.score(s) == store.score(s)
            threading.Event().wait(random.random() / 200)

    threads = [threading.Thread(target=caller, args=(p,)) for p in parts]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert sorted(fresh) == [0] * len(samples) + [1] * len(samples) and len(store) == len(samples)
    order = [s for p in parts for s in p]           # the sampler's order: caller by caller
    assert store.renumber(order + order[:2]) > 0    # repeats keep their first place
    assert store.renumber(order) == 0               # already in order: nothing changes
    store.close()
    frame = read_frame(tmp_path)
    assert list(frame["eval_index"]) == list(range(len(samples)))
    assert list(frame["sample_key"]) == [sample_key(s) for s in order]


def test_renumber_puts_rows_not_asked_for_last_in_their_order(tmp_path):
    sp = space()
    samples = sp.grid()[:5]
    store = Store(tmp_path / STORE_NAME, sp)
    store.add([synthetic_result(s, 0.5, 0) for s in samples], "m", "c")
    assert store.renumber([samples[3], samples[1]]) == 3   # 3, 1, then 0, 2, 4: 1 and 4 stay
    store.close()
    keys = list(read_frame(tmp_path)["sample_key"])
    assert keys == [sample_key(samples[i]) for i in (3, 1, 0, 2, 4)]


def test_a_store_written_without_the_parts_columns_is_refused_by_name(tmp_path):
    sp = space()
    old = Store(tmp_path / STORE_NAME, sp)   # four-class car scoring, as runs were stored before
    old.add([synthetic_result(sp.grid()[0], 0.5, 0)], "m", "c")
    old.close()
    before = (tmp_path / STORE_NAME).read_bytes()
    with pytest.raises(FalsifyError, match="lacks the columns inserted_iou, inserted_recall, "
                       "real_iou, real_recall .* new --out"):
        Store(tmp_path / STORE_NAME, sp, replace(CAR_SCORING, parts=True))
    assert (tmp_path / STORE_NAME).read_bytes() == before   # nothing written to it
    assert len(read_frame(tmp_path / STORE_NAME)) == 1
