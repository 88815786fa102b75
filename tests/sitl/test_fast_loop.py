"""The loop at the sensor's ceiling: the SITL magnetometer at up to 1000 Hz, the compiled estimator
kernels loaded before the first tick, and the run's cycle-time report."""
import io

import numpy as np
import pytest

from hil import sitl
from fsw.drivers.mmc5983ma_regs import Bandwidth, ContinuousFrequency
from fsw.estimation import rate_formulas, rate_kf


@pytest.mark.parametrize("rate_hz,bw,cm", [
    (None, Bandwidth.BW_100HZ, ContinuousFrequency.OFF),          # the scenario's own (1 Hz, single)
    (1000.0, Bandwidth.BW_800HZ, ContinuousFrequency.HZ_1000),    # 0.5 ms measurement, DS p13-16
    (100.0, Bandwidth.BW_200HZ, ContinuousFrequency.HZ_100),      # 8 ms would not fit half of 10 ms
    (50.0, Bandwidth.BW_100HZ, ContinuousFrequency.HZ_50),
    (30.0, Bandwidth.BW_100HZ, ContinuousFrequency.OFF),          # no such continuous rate: single
    (500.0, Bandwidth.BW_800HZ, ContinuousFrequency.OFF),
])
def test_sitl_sensor_mode_for_a_sample_rate(rate_hz, bw, cm):
    got = sitl.sitl_sensor(1.0, Bandwidth.BW_100HZ, rate_hz)
    assert got == ((rate_hz or 1.0), bw, cm)
    assert bw.measurement_time_s <= 0.5 / got[0] or rate_hz is None


@pytest.mark.parametrize("rate_hz", [-1.0, 2000.0])
def test_sitl_sample_rate_out_of_range_is_refused(rate_hz):
    with pytest.raises(ValueError, match="sample-rate"):
        sitl.sitl_sensor(1.0, Bandwidth.BW_100HZ, rate_hz)


@pytest.fixture(scope="module")
def run_1khz():
    args = sitl.parse_args(["--rate", "1000", "--sample-rate", "1000", "--duration", "2",
                                "--speed", "0", "--quiet", "--link", "udpout:127.0.0.1:9"])
    return sitl.run(args, out=io.StringIO())


def test_1khz_sitl_samples_every_tick_and_the_filter_follows(run_1khz):
    fsw = run_1khz.fsw
    # 2 s at 1 kHz, less the start-up (the SET/RESET calibrations come 10 s apart)
    assert 1900 <= fsw.samples <= 2001
    assert fsw.source.bus_errors == 0 and fsw.source.timeouts == 0
    kf = fsw.estimators["kalman"]
    assert not kf.flags & kf.NO_ESTIMATE
    assert np.all(np.isfinite(kf.omega_radps)) and np.all(kf.sigma_radps < np.radians(10.0))
    # the perpendicular part, with 1000 samples a second, within a few °/s of the truth after 2 s
    tr = run_1khz.fsw.truth(fsw.sample_t_s)
    err = sitl.perpendicular(kf.omega_radps - tr.omega_radps, tr.b_body_T)
    assert np.degrees(np.linalg.norm(err)) < 2.0


def test_summary_has_the_cycle_time_histogram(run_1khz):
    text = sitl.summary(run_1khz)
    line = next(x for x in text.splitlines() if x.startswith("step time histogram:"))
    counts = [int(part.rsplit(" ", 1)[1]) for part in line.split(": ", 1)[1].split(", ")]
    assert sum(counts) == run_1khz.fsw.scheduler.stats.ticks == 2001
    assert "Kalman filter (full vector)" in text
    assert "schedule:" not in text          # as fast as possible: no wall-clock schedule to keep


def test_real_time_run_reports_its_schedule():
    args = sitl.parse_args(["--rate", "100", "--duration", "0.3", "--speed", "1", "--quiet",
                                "--link", "udpout:127.0.0.1:9"])
    r = sitl.run(args, out=io.StringIO())
    assert r.real_time
    assert "ticks started more than one period late" in sitl.summary(r)


def test_compiled_kernels_are_loaded_before_the_first_tick(run_1khz):
    for kernel in (rate_kf.predict, rate_kf.update, rate_formulas.boer_rows, rate_formulas.derivative_rows):
        assert kernel.signatures, kernel
