"""Unknown (NaN) rows of a sampled moment: never zero; held, fitted as unknown constants or left out."""
import numpy as np
import pytest

from fsw.estimation import euler_fit as ef
from fsw.estimation import sampled_moment as sm

NAN = np.nan


def pulse_record():
    """1 Hz, a 0.2 N·m pulse on x over rows 10–29, a −0.1 N·m pulse on y over rows 40–49."""
    t = np.arange(60.0)
    m = np.zeros((60, 3))
    m[10:30, 0] = 0.2
    m[40:50, 1] = -0.1
    return t, m


def test_runs_are_cut_into_pieces():
    mask = np.zeros(20, bool)
    mask[[0, 1]] = True
    mask[5:17] = True
    assert sm.runs(mask) == [(0, 2), (5, 17)]
    assert sm.runs(mask, 5) == [(0, 2), (5, 10), (10, 15), (15, 17)]


@pytest.mark.parametrize("hold, expect", [("centered", ((57.5, 59.0),)), ("forward", ((58.0, 59.0),))])
def test_an_unknown_moment_never_counts_as_zero(hold, expect):
    t, m = pulse_record()
    m[15:17] = NAN                       # inside the x pulse: held
    m[58] = NAN
    m[59, 2] = NAN                       # one NaN axis makes the row unknown; at the end: fitted free
    a = ef.KnownAction.from_samples(t, m, hold=hold)
    assert a.unknown_intervals == expect and np.all(np.isinf(a.unknown_sigma_Nm))
    assert a.moment_at(np.array([16.0]))[0, 0] == 0.2                     # held, not zero
    assert sm.samples_in(t, a.unknown_intervals) == 2


def test_short_gaps_are_held_or_fitted_about_their_switch_the_others_free():
    t, m = pulse_record()
    assert sm.shortest_hold_s(t, m) == 9.0           # rows 30–39 (zero) and 40–49 (y); the ends do not count
    m[[3, 20, 21, 10, 45]] = NAN                     # 10: the switch on, its neighbours differ
    m[51:59] = NAN                                   # 50 → 59: 9 s, not shorter than the shortest hold
    p = sm.plan(t, m)
    assert (p.unknown, p.held, p.switch, p.free, p.shortest_hold_s) == (13, 4, 1, 8, 9.0)
    np.testing.assert_array_equal(p.moment_Nm[[3, 20, 21, 45, 10, 55]],
                                  [[0, 0, 0], [0.2, 0, 0], [0.2, 0, 0], [0, -0.1, 0], [0.1, 0, 0], [0, 0, 0]])
    assert p.intervals == ((9.5, 10.5), (50.5, 55.5), (55.5, 58.5))    # the free run cut at RUN_MAX_SAMPLES
    np.testing.assert_allclose(p.sigma_Nm[0], [0.2 / np.sqrt(12), 2e-4, 2e-4])  # uniform switch time
    assert np.all(np.isinf(p.sigma_Nm[1])) and np.all(np.isinf(p.sigma_Nm[2]))
    a = ef.KnownAction.from_samples(t, m)
    assert a.unknown_intervals == p.intervals and a.unknown_sigma_Nm == p.sigma_Nm
    assert a.moment_at(np.array([10.0]))[0, 0] == 0.1


def test_the_ends_are_left_out():
    _, m = pulse_record()
    m[:3] = NAN
    m[-2:] = NAN
    assert sm.known_span(m) == (3, 58)
    assert sm.known_span(np.full((4, 3), NAN)) == (0, 0)


def test_unknown_intervals_merge_with_given_ones():
    iv, sig = sm.merged([(10.0, 20.0)], [(15.5, 16.5), (19.5, 21.0), (30.0, 31.0)], [(1, 1, 1)] * 3)
    assert iv == ((10.0, 21.0), (30.0, 31.0))
    assert np.all(np.isinf(sig[0])) and sig[1] == (1, 1, 1)
