"""The identification benchmark (bench.inertia): a short seeded Monte-Carlo through the command line,
its JSON and table; the full run (README table) is `python -m bench.inertia`."""
import json

import numpy as np
import pytest

from bench import inertia as ib
from support import flight_assumptions


def pin_flight_assumptions(monkeypatch):
    """The benchmark's scenarios loaded with the flight side's assumptions (tests/support.py)."""
    load = ib.scenarios.load
    monkeypatch.setattr(ib.scenarios, "load", lambda name="isoi": flight_assumptions(load(name)))


@pytest.mark.parametrize("offset_s, shift", [(2.0, 0), (-3.0, 3)])
def test_truth_record_is_on_the_box_s_clock_with_a_clock_table(monkeypatch, offset_s, shift):
    """[clock]: the samples are stamped with the box's clock (from its first reading, as in SITL), the truth
    is the world's at the true time they mean, the pulses are on the box's clock."""
    import dataclasses

    from hil.box_clock import BoxClock

    load = ib.scenarios.load
    plain = ib.truth_record("aist2d", 100.0)
    monkeypatch.setattr(ib.scenarios, "load",
                        lambda name: dataclasses.replace(load(name), clock=BoxClock(offset_s=offset_s)))
    tr = ib.truth_record("aist2d", 100.0)
    start = max(0.0, offset_s)
    np.testing.assert_allclose(tr.t_s, start + plain.t_s, atol=1e-12)
    n = len(tr.t_s) - shift
    np.testing.assert_allclose(tr.b_T[:n], plain.b_T[shift:shift + n], atol=1e-15)   # the world at true time
    np.testing.assert_allclose(tr.omega_radps[:n], plain.omega_radps[shift:shift + n], atol=1e-15)
    assert ib.pulses(tr)[0] == (60.0 + offset_s, 120.0 + offset_s)
    np.testing.assert_allclose(tr.action.moment_at(np.array([61.0 + offset_s]))[0], [0.2, 0, 0])
    np.testing.assert_allclose(tr.action.moment_at(np.array([59.0 + offset_s]))[0], [0, 0, 0])


def test_truth_record_is_the_simulators_and_noise_is_seeded():
    tr = ib.truth_record("aist2d", 100.0)
    assert tr.t_s[0] == 0.5 and np.allclose(np.diff(tr.t_s), 1.0)
    assert tr.sigma_b_T == pytest.approx(np.hypot(1.5e-6, 0.04e-6))
    # the moment column is the scenario's schedule: 0.2 N·m on x from 60 s
    assert not np.any(tr.moment_Nm[tr.t_s < 60])
    assert np.allclose(tr.moment_Nm[(tr.t_s > 60) & (tr.t_s < 100)], [0.2, 0, 0])
    a = ib.noisy(tr, 2, np.random.default_rng(3))
    b = ib.noisy(tr, 2, np.random.default_rng(3))
    np.testing.assert_array_equal(a, b)
    assert np.std(a - tr.b_T) == pytest.approx(tr.sigma_b_T, rel=0.1)
    mask = ib.free_interval(ib.truth_record("cellular_debris", 400.0))
    assert mask.sum() == 215                          # before the impulse at 215 s (the longer side here)


def test_command_line_short_run(tmp_path, capsys, monkeypatch):
    out = tmp_path / "bench.json"
    # the fits on their own terms: a calibrated magnetometer (the calibration takes an orbit)
    pin_flight_assumptions(monkeypatch)
    assert ib.main(["--runs", "2", "--duration", "420", "--scenarios", "aist2d", "--no-linear", "--fits", "full",
                    "--json", str(out)]) == 0
    text = capsys.readouterr().out
    assert "== aist2d" in text and "== targets" in text and "Aist-2D diagonal within ±1 %" in text
    assert "sedelnikov2023" in text                 # the paper's numbers are printed alongside
    r = json.loads(out.read_text())["results"][0]
    f = r["full"]
    assert r["runs"] == 2 and r["samples"] == 420
    np.testing.assert_allclose(f["truth"], [175.0, 200.0, 285.0, 0.0, 0.0, 0.0])
    assert max(f["max_abs_err_pct_of_own"][:3]) < 2.0
    assert all(0.0 <= c <= 1.0 for c in f["coverage95"] + f["coverage99"])
    assert all(a <= b for a, b in zip(f["coverage95"], f["coverage99"]))
    assert 0.7 < f["chi2_per_dof_mean"] < 1.3
    # the field model's error fitted by default: a linear offset over 420 s, the host's drift and soft iron
    assert r["field_error"] == "fit" and f["field_error"]["degree"] == 1
    assert f["field_error"]["rms_uT_mean"] < 0.5                  # the ideal world: |B| shows (almost) none


def test_fit_options_of_the_field_error():
    t = np.arange(0.5, 1500.0, 1.0)
    o = ib.fit_options(t, "fit", mode="shape")
    assert o.mode == "shape" and o.field_error_degree == 2 and o.soft_iron_sigma == pytest.approx(0.002)
    o = ib.fit_options(t, "none")
    assert o.field_error_degree is None and o.soft_iron_sigma is None
    with pytest.raises(ValueError):
        ib.fit_options(t, "guess")


def test_binomial_interval_and_shape_data():
    lo, hi = ib.wilson(19, 20)                        # Wilson score interval, z = 1.96
    assert (lo, hi) == (pytest.approx(0.7639, abs=1e-4), pytest.approx(0.9911, abs=1e-4))
    lo, hi = ib.wilson(570, 600)
    assert lo < 0.95 < hi and hi - lo < 0.04
    tr = ib.truth_record("cellular_debris", 400.0)
    sel, unknown = ib.shape_data(tr, "all")
    assert sel.all() and unknown == [(215.0, 216.0)]
    sel, unknown = ib.shape_data(tr, "free")
    assert sel.sum() == 215 and unknown == []
    with pytest.raises(ValueError):
        ib.shape_data(tr, "some")


def test_shape_command_line_reports_the_cramer_rao_bound(tmp_path, capsys, monkeypatch):
    """The shape fit of the whole record (pulses as unknown moments) against its Cramér–Rao bound."""
    out = tmp_path / "bench.json"
    # the fits on their own terms: a calibrated magnetometer (the calibration takes an orbit)
    pin_flight_assumptions(monkeypatch)
    assert ib.main(["--runs", "2", "--duration", "330", "--scenarios", "aist2d", "--no-linear", "--fits", "shape",
                    "--field-error", "none", "--json", str(out)]) == 0
    text = capsys.readouterr().out
    assert "fitted as unknown moments" in text and "Cramér–Rao" in text and "shape ratios within 0.5 %" in text
    r = json.loads(out.read_text())["results"][0]
    s, k = r["shape"], r["kappa"]
    assert s["data"] == "all" and s["samples"] == 330 and len(s["unknown_moments_s"]) == 3
    # the scale from the known torque: signed, checked against the start at the truth like the fits
    assert k["local_minimum_runs"] == 0 and 0.95 < k["ratio_min"] <= k["ratio_max"] < 1.05
    crb = np.array(s["ratio_crb_pct"])
    assert np.all(crb > 0.05) and np.all(crb < 2.0)
    # each fit's own σ is the bound (white noise); no run stopped in another minimum than the truth's
    np.testing.assert_allclose(s["ratio_sd_fit_pct_mean"], crb, rtol=0.15)
    assert s["local_minimum_runs"] == 0 and s["chi2_above_truth_start_max"] < 1.0
    assert max(s["ratio_err_pct_max"]) < 5 * max(crb)


def test_a_prefix_of_a_longer_truth_is_the_shorter_simulation():
    short, long_ = ib.truth_record("aist2d", 330.0), ib.truth_record("aist2d", 660.0)
    p = long_.prefix(330.0)
    for name in ("t_s", "b_T", "omega_radps", "q", "moment_Nm"):
        np.testing.assert_array_equal(getattr(p, name), getattr(short, name))
    with pytest.raises(ValueError):
        short.prefix(660.0)


def test_record_design_picks_the_shortest_record_that_reaches_the_bound():
    ladder = (330.0, 660.0)
    longest = ib.truth_record("aist2d", 660.0)
    loose = ib.design_record(longest, ladder, bound_pct=100.0)
    assert loose["chosen_s"] == 330.0 and len(loose["tried"]) == 1
    tight = ib.design_record(longest, ladder, bound_pct=1e-6)
    assert tight["chosen_s"] == 660.0 and len(tight["tried"]) == 2  # none reaches it: the longest
    short, long_ = (np.array(t["crb_pct"]) for t in tight["tried"])
    assert np.all(long_ < short)  # more record, more information
    between = float(np.max(long_)) * 1.01
    assert ib.design_record(longest, ladder, bound_pct=between)["chosen_s"] == 660.0


def test_duration_must_be_seconds_or_auto():
    for bad in ("soon", "60"):
        with pytest.raises(SystemExit):
            ib.main(["--duration", bad, "--scenarios", "aist2d"])
