"""``TermsCache``: a key is computed by one thread at a time; a reader of a key being computed takes that
result (the shell's refresher and every outlet reading the same new view no longer compute it side by
side; docs/design/fleet.md, "Hosted outlets")."""

from __future__ import annotations

import threading
import time
from typing import Any

from service.estimate.growthterms import TermsCache

CTX = object()  # the growth context the terms were computed with (current: they are kept)


def _wait_for(cond: Any, what: str, timeout_s: float = 10.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not cond():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.001)


class _Blocking:
    """A compute that says it started and returns only when released (or raises, if told to)."""

    def __init__(self, result: object, *, fail: bool = False) -> None:
        self.result = result
        self.fail = fail
        self.started = threading.Event()
        self.release = threading.Event()
        self.calls = 0

    def __call__(self) -> tuple[Any, object]:
        self.calls += 1
        self.started.set()
        assert self.release.wait(10.0)
        if self.fail:
            raise RuntimeError("eigen-solve failed")
        return self.result, CTX


def _in_thread(fn: Any) -> tuple[threading.Thread, dict[str, object]]:
    out: dict[str, object] = {}

    def run() -> None:
        try:
            out["value"] = fn()
        except Exception as err:
            out["error"] = err

    t = threading.Thread(target=run, daemon=True)
    t.start()
    return t, out


def _second_reader_waits(
    cache: TermsCache, first: _Blocking, second: Any
) -> tuple[dict[str, object], dict[str, object]]:
    """``first`` computes key "k" in one thread; a second reader asks for "k" meanwhile (``second`` its
    compute) and is seen waiting; then ``first`` is released. Both readers' outcomes."""
    ta, a = _in_thread(lambda: cache.get("k", first, lambda: CTX))
    assert first.started.wait(10.0)
    tb, b = _in_thread(lambda: cache.get("k", second, lambda: CTX))
    _wait_for(lambda: cache.joined == 1, "the second reader to wait for the first")
    first.release.set()
    ta.join(10.0)
    tb.join(10.0)
    return a, b


def test_a_reader_of_a_key_being_computed_takes_that_result() -> None:
    cache = TermsCache()
    first, second = _Blocking("terms"), _Blocking("again")
    a, b = _second_reader_waits(cache, first, second)
    assert a == {"value": "terms"} and b == {"value": "terms"}
    assert second.calls == 0 and cache.computed == 1
    assert cache.get("k", second, lambda: CTX) == "terms" and second.calls == 0  # cached


def test_other_keys_are_computed_beside_it() -> None:
    cache = TermsCache()
    slow = _Blocking("slow")
    ta, a = _in_thread(lambda: cache.get("k1", slow, lambda: CTX))
    assert slow.started.wait(10.0)
    assert cache.get("k2", lambda: ("fast", CTX), lambda: CTX) == "fast"  # not held up by k1
    slow.release.set()
    ta.join(10.0)
    assert a == {"value": "slow"} and cache.joined == 0 and cache.computed == 2


def test_a_failed_computation_is_retried_by_the_reader_that_waited() -> None:
    cache = TermsCache()
    failing, retry = _Blocking("never", fail=True), _Blocking("terms")
    retry.release.set()
    a, b = _second_reader_waits(cache, failing, retry)
    assert isinstance(a["error"], RuntimeError)
    assert b == {"value": "terms"} and retry.calls == 1
    assert cache.get("k", _Blocking("unused"), lambda: CTX) == "terms"  # kept


def test_terms_computed_with_a_replaced_context_are_computed_again_by_the_waiting_reader() -> None:
    cache = TermsCache()
    current = {"ctx": CTX}
    old = _Blocking("old terms")
    ta, a = _in_thread(lambda: cache.get("k", old, lambda: current["ctx"]))
    assert old.started.wait(10.0)
    new_ctx = object()
    tb, b = _in_thread(lambda: cache.get("k", lambda: ("new terms", new_ctx), lambda: current["ctx"]))
    _wait_for(lambda: cache.joined == 1, "the second reader to wait for the first")
    current["ctx"] = new_ctx  # a commissioning replaced the operators meanwhile: the old terms are not kept
    old.release.set()
    ta.join(10.0)
    tb.join(10.0)
    assert a == {"value": "old terms"} and b == {"value": "new terms"} and cache.computed == 2


def test_many_readers_of_one_new_key_compute_it_once() -> None:
    readers = 3  # the shell's refresher, the OPC UA server and the MQTT sampler on the same new view
    cache = TermsCache()
    first = _Blocking("terms")
    others = [_Blocking("again") for _ in range(readers - 1)]
    ta, a = _in_thread(lambda: cache.get("k", first, lambda: CTX))
    assert first.started.wait(10.0)
    rest = [_in_thread(lambda c=c: cache.get("k", c, lambda: CTX)) for c in others]
    _wait_for(lambda: cache.joined == readers - 1, "every other reader to wait")
    first.release.set()
    for t, _ in [(ta, a), *rest]:
        t.join(10.0)
    assert [out["value"] for _, out in rest] == ["terms"] * (readers - 1)
    assert cache.computed == 1 and all(c.calls == 0 for c in others)
