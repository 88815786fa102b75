"""ground.lifetime: the decay against analytic truth (King-Hele's circular and eccentric rates, J2's
node rate), lapkhanov2019 Table 2, the attitude modes' areas, the atmosphere without downloads, bad
input, the command line end to end. The full-equations check is test_lifetime_reference.py (slow)."""
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.special import iv

from ground.lifetime import activity as act
from ground.lifetime import atmosphere as atm
from ground.lifetime import paper
from ground.lifetime.__main__ import main
from ground.lifetime.craft import Craft, CraftError
from ground.lifetime.decay import MU_EARTH_M3S2, OMEGA_EARTH_RADPS, Orbit, decay, j2_rates_radps, rates

ROOT = Path(__file__).resolve().parents[2]
TLE = ["1 99991U 25001A   25182.50000000  .00000000  00000-0  10000-3 0    05",
       "2 99991  97.5000  40.0000 0012000  90.0000   0.0000 15.26928705    01"]


# --- the decay's rates against analytic truth ------------------------------------------------------------

def test_circular_rate_is_king_hele():
    """e = 0, equatorial, no rotation factor at i = 90°: da/dt = −ρ B √(μ a), de/dt = 0."""
    a, rho0, b = atm.R_EARTH_M + 600e3, 1e-13, 0.05
    da, de = rates(a, 0.0, 0.0, b, lambda h: np.full_like(h, rho0))
    assert da == pytest.approx(-rho0 * b * math.sqrt(MU_EARTH_M3S2 * a), rel=1e-12)
    assert abs(de) < 1e-20


def test_rotating_atmosphere_factor():
    """Prograde equatorial circular orbit: the air moves with it, drag × (1 − ω r / v)²."""
    a, rho0, b = atm.R_EARTH_M + 600e3, 1e-13, 0.05
    v = math.sqrt(MU_EARTH_M3S2 / a)
    da, _ = rates(a, 0.0, 1.0, b, lambda h: np.full_like(h, rho0))
    assert da == pytest.approx(-rho0 * b * math.sqrt(MU_EARTH_M3S2 * a) * (1 - OMEGA_EARTH_RADPS * a / v) ** 2,
                               rel=1e-9)


@pytest.mark.parametrize("e", [0.002, 0.01, 0.03])
def test_eccentric_rates_match_king_hele_series(e):
    """Exponential atmosphere (H = 60 km), polar: King-Hele's series in x = ae/H (Vallado eq. 9-34),
    da/dt = −B ρp √(μa) e^−x [I0 + 2e I1 + ¾e²(I0 + I2)], de/dt = −B ρp √(μ/a) e^−x [I1 + ½e(I0 + I2)]
    to O(e²)."""
    a, b, rho_p, H = atm.R_EARTH_M + 700e3, 0.05, 1e-13, 60.0
    hp = (a * (1 - e) - atm.R_EARTH_M) / 1e3
    da, de = rates(a, e, 0.0, b, lambda h: rho_p * np.exp(-(h - hp) / H))
    x = a * e / (H * 1e3)
    i0, i1, i2 = iv(0, x), iv(1, x), iv(2, x)
    da_kh = -b * rho_p * math.sqrt(MU_EARTH_M3S2 * a) * math.exp(-x) * (i0 + 2 * e * i1 + 0.75 * e * e * (i0 + i2))
    de_kh = -b * rho_p * math.sqrt(MU_EARTH_M3S2 / a) * math.exp(-x) * (i1 + 0.5 * e * (i0 + i2))
    assert da == pytest.approx(da_kh, rel=2e-3)
    assert de == pytest.approx(de_kh, rel=2e-2)


def test_j2_node_rate_sun_synchronous():
    """A 98.19° orbit at 700 km is sun-synchronous: dΩ/dt = 360° per 365.2422 days (±1 %)."""
    dn, _ = j2_rates_radps(atm.R_EARTH_M + 700e3, 0.0, 98.19)
    assert math.degrees(dn) * 86400 == pytest.approx(360 / 365.2422, rel=0.01)


def test_lifetime_scales_with_ballistic_coefficient():
    sched = act.constant(act.LEVELS["moderate"])
    o = Orbit.from_heights(450, 450, 51.6)
    t1 = decay(o, 0.01, sched).lifetime_days
    t2 = decay(o, 0.02, sched).lifetime_days
    assert t1 / t2 == pytest.approx(2.0, rel=0.005)


def test_higher_activity_shorter_life_and_reentry_height():
    o = Orbit.from_heights(450, 450, 51.6)
    life = {n: decay(o, 0.02, act.constant(lv)).lifetime_days for n, lv in act.LEVELS.items()}
    assert life["low"] > life["moderate"] > life["high"]
    d = decay(o, 0.02, act.constant(act.LEVELS["moderate"]), reentry_km=120.0)
    assert d.perigee_km[-1] == pytest.approx(120.0) and d.lifetime_days == d.t_days[-1]
    d180 = decay(o, 0.02, act.constant(act.LEVELS["moderate"]), reentry_km=180.0)
    assert 0 < d.lifetime_days - d180.lifetime_days < 2.0          # the last 60 km: within two days


def test_eccentric_orbit_circularises():
    d = decay(Orbit.from_heights(400, 700, 80), 0.02, act.constant(act.LEVELS["high"]))
    assert d.lifetime_days is not None
    e = (d.apogee_km - d.perigee_km)
    assert e[-1] < e[0] / 5                  # apogee falls to meet the perigee
    k = np.searchsorted(d.t_days, d.lifetime_days / 2)       # half-way: the apogee has come down most
    assert d.apogee_km[0] - d.apogee_km[k] > 3 * (d.perigee_km[0] - d.perigee_km[k])


def test_still_in_orbit_after_max_years():
    d = decay(Orbit.from_heights(900, 900, 98), 0.005, act.constant(act.LEVELS["low"]), max_years=5)
    assert d.lifetime_days is None and d.t_days[-1] == pytest.approx(5 * 365.25)


def test_solar_cycle_between_its_extremes():
    o = Orbit.from_heights(500, 500, 51.6)
    lo = decay(o, 0.02, act.constant(atm.Activity(70, 70, 6))).lifetime_days
    hi = decay(o, 0.02, act.constant(atm.Activity(190, 190, 16))).lifetime_days
    cyc = decay(o, 0.02, act.cycle(0.25, 60)).lifetime_days
    assert hi < cyc < lo


# --- areas ---------------------------------------------------------------------------------------------

def test_mode_areas():
    c = Craft(180, 5.0, 0.58)
    assert c.area_m2("tumbling") == pytest.approx(2.5 + 0.58)
    assert c.area_m2("stabilised") == pytest.approx(5.58)
    # passive: undamped 1-rad swings in yaw and pitch; ⟨cos(θ0 sin ωt)⟩² by quadrature over a period
    ph = (np.arange(100_000) + 0.5) * 2 * math.pi / 100_000
    assert c.area_m2("passive") == pytest.approx(5 * np.cos(1.0 * np.sin(ph)).mean() ** 2 + 0.58, rel=1e-9)
    assert Craft(180, 5.0, 0.58, passive_swing_rad=0.0).area_m2("passive") == pytest.approx(5.58)
    assert Craft(180, 5.0, 0.58, body_surface_m2=3.48).area_m2("tumbling") == pytest.approx(2.5 + 0.87)


def test_random_tumble_mean_area_of_a_plate_is_half():
    """Independent truth: the mean |cos| of a uniformly random normal is 1/2 (seeded Monte Carlo)."""
    n = np.random.default_rng(7).normal(size=(200_000, 3))
    n /= np.linalg.norm(n, axis=1)[:, None]
    assert np.abs(n[:, 0]).mean() == pytest.approx(Craft(1, 1.0, 0.0).area_m2("tumbling"), abs=0.005)


@pytest.mark.parametrize("kw", [dict(mass_kg=-1), dict(mass_kg=0), dict(sail_m2=-0.1), dict(body_m2=-1),
                                dict(cd=0), dict(sail_m2=0, body_m2=0)])
def test_craft_refuses_bad_numbers(kw):
    with pytest.raises(CraftError):
        Craft(**{**dict(mass_kg=180, sail_m2=5, body_m2=0.58), **kw}).check()


# --- atmosphere -----------------------------------------------------------------------------------------

def test_atmosphere_downloads_nothing(monkeypatch):
    """pymsis is given F10.7, F10.7a and Ap: no file is fetched (any URL opened fails the test)."""
    import urllib.request

    def no_net(*a, **k):
        raise AssertionError("pymsis tried to download")
    monkeypatch.setattr(urllib.request, "urlopen", no_net)
    monkeypatch.setattr(urllib.request, "urlretrieve", no_net)
    lr = atm.log_density_profile(atm.Activity(133.3, 121.7, 11.0), 42.0)       # not cached before
    rho400 = float(atm.density_kgm3(lr, 400.0))
    # NRLMSIS at 400 km for moderate activity: a few 1e-12 kg/m³ (CIRA/ISO 14222 tables: 1e-12 to 1e-11)
    assert 1e-12 < rho400 < 1e-11
    assert np.all(np.diff(lr) < 0)            # density falls with height


@pytest.mark.parametrize("a", [atm.Activity(50, 150, 10), atm.Activity(150, 350, 10), atm.Activity(150, 150, -1),
                               atm.Activity(150, 150, 500), atm.Activity(float("nan"), 150, 10)])
def test_activity_outside_the_model(a):
    with pytest.raises(atm.ActivityError, match="outside NRLMSIS"):
        a.check()


def test_activity_file(tmp_path):
    p = tmp_path / "act.csv"
    p.write_text("f107_sfu,f107a_sfu,ap\n150,140,12\n160,145,9\n")
    s = act.from_file(str(p))
    assert s.month(0) == 0 and s.month(45) == 1 and s.month(1e5) == 1 and list(s.ap) == [12, 9]
    p.write_text("150,140,12\n999,140,12\n")
    with pytest.raises(atm.ActivityError, match=":2: F10.7 = 999"):
        act.from_file(str(p))


# --- lapkhanov2019 Table 2 -------------------------------------------------------------------------------

CIRCULAR = [r for r in paper.ROWS if r.apogee_km == r.perigee_km]
ELLIPTIC = [r for r in paper.ROWS if r.apogee_km != r.perigee_km]
PAPER_SCHEDULE = act.constant(paper.PAPER_ACTIVITY)


@pytest.mark.parametrize("row", CIRCULAR, ids=lambda r: f"{r.perigee_km:.0f}km")
def test_table2_stabilised_circular_rows_within_10pct(row):
    got = paper.lifetimes(row, PAPER_SCHEDULE)
    assert got["stabilised"] == pytest.approx(row.stabilised_years, rel=0.10)


@pytest.mark.xfail(strict=True, reason="the paper's tumbling times imply the sail shows ~75 % of its area "
                                       "unstabilised; a random tumble shows 50 % (docs/lifetime.md)")
@pytest.mark.parametrize("row", CIRCULAR[:1], ids=lambda r: f"{r.perigee_km:.0f}km")
def test_table2_tumbling_within_10pct(row):
    got = paper.lifetimes(row, PAPER_SCHEDULE)
    assert got["tumbling"] == pytest.approx(row.tumbling_years, rel=0.10)


@pytest.mark.xfail(strict=True, reason="a random tumble gives a 45 % gain, the paper 19-25 % (docs/lifetime.md)")
def test_table2_gain_within_3_points():
    row = paper.ROWS[0]
    got = paper.lifetimes(row, PAPER_SCHEDULE)
    assert abs((1 - got["stabilised"] / got["tumbling"]) - row.gain) <= 0.03


@pytest.mark.xfail(strict=True, reason="the e = 0.01 rows decay about 1.9× slower than the paper says at the "
                                       "activity that reproduces the circular rows (docs/lifetime.md)")
@pytest.mark.parametrize("row", ELLIPTIC[:1], ids=lambda r: f"{r.perigee_km:.0f}x{r.apogee_km:.0f}km")
def test_table2_stabilised_elliptic_rows_within_10pct(row):
    got = paper.lifetimes(row, PAPER_SCHEDULE)
    assert got["stabilised"] == pytest.approx(row.stabilised_years, rel=0.10)


def test_table2_gain_is_the_area_ratio_at_constant_activity():
    row = paper.ROWS[0]
    got = paper.lifetimes(row, PAPER_SCHEDULE)
    c = paper.craft(row)
    assert 1 - got["stabilised"] / got["tumbling"] == pytest.approx(
        1 - c.area_m2("tumbling") / c.area_m2("stabilised"), abs=0.002)


# --- command line ---------------------------------------------------------------------------------------

def test_cli_end_to_end(tmp_path, capsys):
    js, png = tmp_path / "out.json", tmp_path / "out.png"
    assert main(["--perigee-km", "420", "--apogee-km", "450", "--inclination-deg", "51.6", "--quiet",
                 "--modes", "tumbling", "stabilised", "passive", "--json", str(js), "--plot", str(png)]) == 0
    out = capsys.readouterr().out
    assert "tumbling:" in out and "stabilised:" in out and "gain:" in out
    d = json.loads(js.read_text())
    assert set(d) >= {"orbit", "craft", "activity", "reentry_km", "lifetime_years", "gain", "modes"}
    life = d["lifetime_years"]
    assert life["stabilised"] < life["passive"] < life["tumbling"]
    assert d["gain"] == pytest.approx(1 - life["stabilised"] / life["tumbling"])
    h = d["modes"]["tumbling"]["history"]
    assert len(h["t_years"]) <= 400 and h["perigee_km"][0] == pytest.approx(420) and h["perigee_km"][-1] == 120
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_cli_tle_and_deorbit_json(tmp_path, capsys):
    js = tmp_path / "tle.json"
    assert main(["--tle", *TLE, "--quiet", "--activity", "high", "--json", str(js),
                 "--deorbit-json", str(ROOT / "docs" / "deorbit_bench.json")]) == 0
    d = json.loads(js.read_text())
    assert 470 < d["orbit"]["perigee_km"] < d["orbit"]["apogee_km"] < 530
    assert d["orbit"]["inclination_deg"] == pytest.approx(97.5)
    bench = json.loads((ROOT / "docs" / "deorbit_bench.json").read_text())
    assert d["craft"]["pointing_cos"] == pytest.approx(
        math.cos(bench["yaw_err_max_rad"]) * math.cos(bench["pitch_err_max_rad"]))


@pytest.mark.parametrize("argv, words", [
    (["--perigee-km", "600", "--sail-m2", "-1"], "--sail-m2"),
    (["--perigee-km", "600", "--body-m2", "-0.5"], "--body-m2"),
    (["--perigee-km", "600", "--mass-kg", "-180"], "--mass-kg"),
    (["--perigee-km", "600", "--mass-kg", "0"], "--mass-kg"),
    (["--perigee-km", "600", "--sail-m2", "0", "--body-m2", "0"], "both 0"),
    (["--perigee-km", "110"], "below the re-entry height"),
    (["--perigee-km", "150", "--reentry-km", "180"], "below the re-entry height"),
    (["--tle", "1 garbage", "2 garbage"], "--tle"),
    (["--tle", TLE[0], TLE[1][:-1] + "7"], "checksum"),
    (["--perigee-km", "600", "--f107", "400", "--f107a", "150", "--ap", "10"], "F10.7 = 400"),
    (["--perigee-km", "600", "--f107", "150", "--f107a", "150", "--ap", "-3"], "Ap = -3"),
    (["--perigee-km", "600", "--f107", "150"], "go together"),
    (["--perigee-km", "600", "--apogee-km", "500"], "below --perigee-km"),
    (["--perigee-km", "600", "--plot", "x.nope"], "--plot"),
    (["--perigee-km", "600", "--activity", "cycle", "--cycle-phase", "2"], "phase"),
    ([], "give the orbit"),
])
def test_cli_bad_input_one_line_exit_2(argv, words, capsys):
    with pytest.raises(SystemExit) as e:
        main([*argv, "--quiet"])
    assert e.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert words in err[-1] and "Traceback" not in "\n".join(err)


def test_cli_output_may_not_overwrite_input(tmp_path, capsys):
    f = tmp_path / "act.csv"
    f.write_text("150,150,15\n")
    with pytest.raises(SystemExit) as e:
        main(["--perigee-km", "600", "--activity-file", str(f), "--json", str(f), "--quiet"])
    assert e.value.code == 2 and "overwrite an input" in capsys.readouterr().err
    assert f.read_text() == "150,150,15\n"


def test_cli_process_bad_input_no_traceback():
    p = subprocess.run([sys.executable, "-m", "ground.lifetime", "--perigee-km", "600", "--sail-m2", "-2"],
                       cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert p.returncode == 2 and "Traceback" not in p.stderr and "--sail-m2" in p.stderr.strip().splitlines()[-1]


@pytest.mark.slow
def test_cli_paper_table(tmp_path):
    js = tmp_path / "table.json"
    p = subprocess.run([sys.executable, "-m", "ground.lifetime", "--paper-table", "--json", str(js), "--quiet"],
                       cwd=ROOT, capture_output=True, text=True, timeout=900)
    assert p.returncode == 0, p.stderr
    rows = json.loads(js.read_text())["rows"]
    assert [(r["altitude_km"], r["apogee_km"], r["inclination_deg"]) for r in rows] == [
        (r.perigee_km, r.apogee_km, r.inclination_deg) for r in paper.ROWS]
    for r in rows:
        assert {"tumbling_years", "stabilised_years", "spread"} <= set(r)
        s = {k: math.inf if v["stabilised"] is None else v["stabilised"] for k, v in r["spread"].items()}
        assert s["high"] < s["moderate"] < s["low"]


def test_steps_converged():
    """The default steps against steps 8× shorter in a and ≤ 1 day: the same lifetime to 1e-5."""
    row = paper.ROWS[0]
    o, b = paper.orbit(row), paper.craft(row).ballistic_m2kg("stabilised")
    coarse = decay(o, b, PAPER_SCHEDULE).lifetime_days
    fine = decay(o, b, PAPER_SCHEDULE, max_step_days=1.0, max_da_m=250.0).lifetime_days
    assert coarse == pytest.approx(fine, rel=1e-5)


def test_cli_help(capsys):
    with pytest.raises(SystemExit) as e:
        main(["--help"])
    assert e.value.code == 0 and capsys.readouterr().out.startswith("usage:")
