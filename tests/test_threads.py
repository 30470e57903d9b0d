"""accelcal in a multi-threaded service: a step that runs another quietly (a held-fixed
calibration refitted for its attribution, a check fitted quietly) hides accelcal's warnings in
its own thread only, and never touches the process-wide warning filters, which
``warnings.catch_warnings`` swaps without a lock (before Python 3.14 two threads inside it at
once left an ``ignore`` filter installed for good: every later warning of the process lost)."""

from __future__ import annotations

import sys
import threading
import warnings
from collections.abc import Callable, Iterator
from typing import Any

import accelcal as ac
import numpy as np
import pytest
from accelcal import TimeStepWarning, WeakDesignWarning
from accelcal._quiet import quiet, recording
from accelcal.sim import field_session, static_dwell_means
from accelcal.static import fit_quietly


@pytest.fixture(scope="module")
def session() -> Any:
    return field_session(fs=2000.0, n_dwells=14, dwell_s=3.0, move_s=1.0, rng=0)


@pytest.fixture
def fast_switching() -> Iterator[None]:
    """Threads switched every 10 us, so that their quiet sections interleave."""
    old = sys.getswitchinterval()
    sys.setswitchinterval(1e-5)
    try:
        yield
    finally:
        sys.setswitchinterval(old)


def _in_threads(jobs: list[Callable[[], Any]], rounds: int) -> list[BaseException]:
    """Run every job ``rounds`` times, each in its own thread, all started together; the
    exceptions raised (a warning turned into an error among them)."""
    barrier = threading.Barrier(len(jobs))
    errors: list[BaseException] = []

    def run(job: Callable[[], Any]) -> None:
        try:
            barrier.wait()
            for _ in range(rounds):
                job()
        except BaseException as e:  # noqa: BLE001 - reported by the test
            errors.append(e)

    threads = [threading.Thread(target=run, args=(job,)) for job in jobs]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return errors


def _time_step_warning_arrives(s: Any) -> None:
    t = s.t.copy()
    t[20000:] -= 5.0  # the clock steps back
    with pytest.warns(TimeStepWarning):
        ac.detect_dwells(s.samples, fs=s.fs, t=t)


def test_concurrent_diagnoses_leave_the_warning_filters_alone(session: Any,
                                                              fast_switching: None) -> None:
    # The tester's service: a stored calibration checked on new data in two threads (its
    # attribution refitted quietly, with a bootstrap of quiet fits), a plain diagnosis in a
    # third, and fits made quietly in a fourth.
    s = session
    d = ac.detect_dwells(s.samples, fs=s.fs, t=s.t)
    m = ac.fit_static(d, s.g).to_model()
    stale = ac.TriadModel(m.K, m.bias + [0.003, -0.002, 0.004], g=m.g,
                          input_units=m.input_units)
    r = ac.diagnose(d, g=s.g, fit=stale)
    assert r.calibration_check is not None
    assert r.calibration_check["attribution"] == "refit"  # the quiet refit runs
    before = list(warnings.filters)
    errors = _in_threads([
        lambda: ac.diagnose(d, g=s.g, fit=stale),
        lambda: ac.diagnose(d, g=s.g, fit=stale),
        lambda: ac.diagnose(d, g=s.g),
        lambda: fit_quietly(d, s.g),
    ], rounds=15)
    assert errors == []
    assert warnings.filters == before
    _time_step_warning_arrives(s)


def test_a_quiet_thread_does_not_silence_another(session: Any) -> None:
    # One thread sits inside a quiet section while the main thread fits a weak design: the
    # main thread's warning arrives, and points at the caller's line.
    inside, done = threading.Event(), threading.Event()

    def quiet_thread() -> None:
        with quiet():
            inside.set()
            done.wait(30.0)

    t = threading.Thread(target=quiet_thread)
    t.start()
    try:
        assert inside.wait(30.0)
        s = static_dwell_means(20, rng=7)  # tilts within +-30 deg: weak
        with pytest.warns(WeakDesignWarning) as w:
            ac.fit_static(s.dwellset(), s.g_measured)
    finally:
        done.set()
        t.join()
    assert [x.filename for x in w] == [__file__]
    _time_step_warning_arrives(session)


def test_fit_quietly_says_nothing() -> None:
    s = static_dwell_means(20, rng=7)
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        f = fit_quietly(s.dwellset(), s.g_measured)
    assert f.weak and w == []
    with pytest.warns(WeakDesignWarning):  # the same fit, not quiet
        ac.fit_static(s.dwellset(), s.g_measured)


def test_recording_collects_instead_of_warning() -> None:
    s = static_dwell_means(20, rng=7)
    filters = list(warnings.filters)
    with recording() as rec:
        ac.fit_static(s.dwellset(), s.g_measured)  # no warning reaches the filters ("error")
    assert warnings.filters == filters
    assert [x.category for x in rec] == [WeakDesignWarning]
    assert rec[0].filename == __file__ and "bz" in str(rec[0].message)
    with quiet(TimeStepWarning), pytest.warns(WeakDesignWarning):  # other categories pass
        ac.fit_static(s.dwellset(), s.g_measured)
    with recording() as outer, quiet():  # the innermost section decides
        ac.fit_static(s.dwellset(), s.g_measured)
    assert outer == []


def test_a_long_apply_lets_signal_handlers_run() -> None:
    """Ctrl-C (a Python signal handler) runs between the blocks of a long apply instead of
    after it (12 s for 60 million rows): a handler called every millisecond runs several
    times during an 8-block call (once, after it, before)."""
    import signal

    from accelcal import _core

    x = np.ones((8 << 20, 3), dtype=np.float32)
    calls = [0]

    def tick(*_: object) -> None:
        calls[0] += 1

    old = signal.signal(signal.SIGALRM, tick)
    try:
        signal.setitimer(signal.ITIMER_REAL, 0.001, 0.001)
        y = _core.apply_triad_raw(x, [[2.0, 0, 0], [0, 2.0, 0], [0, 0, 2.0]], [0.0, 0.0, 1.0])
        during = calls[0]
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)
    assert during >= 4, during
    np.testing.assert_array_equal(y[[0, -1]], [[0.5, 0.5, 0.0], [0.5, 0.5, 0.0]])
