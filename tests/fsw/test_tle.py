"""TLE checks (format, modulo-10 checksums, epoch) and SGP4 against Vallado's published verification."""
import numpy as np
import pytest

from fsw.estimation import tle as tles
from fsw.estimation.tle import TleError, check_epoch, parse_tle

# Vallado et al., "Revisiting Spacetrack Report #3" (AIAA 2006-6753), SGP4-VER.TLE, satellite 00005,
# and its published TEME state at t = 0 (tcppver.out): km, km/s
L1 = "1 00005U 58002B   00179.78495062  .00000023  00000-0  28098-4 0  4753"
L2 = "2 00005  34.2682 348.7242 1859667 331.7664  19.3264 10.82419157413667"
R0_KM = (7022.46529266, -1400.08296755, 0.03995155)
V0_KMS = (1.893841015, 6.405893759, 4.534807250)
EPOCH_UTC_S = 962131819.733568  # 2000-06-27T18:50:19.733568Z (day 179.78495062 of 2000)


def test_sgp4_matches_vallados_published_state_at_epoch():
    t = parse_tle(L1, L2)
    assert t.satnum == "5" or t.satnum == "00005"
    sat = t.satrec()
    err, r, v = sat.sgp4(sat.jdsatepoch, sat.jdsatepochF)
    assert err == 0
    np.testing.assert_allclose(r, R0_KM, atol=1e-6)      # 1 mm
    np.testing.assert_allclose(v, V0_KMS, atol=1e-9)
    assert t.epoch_utc_s == pytest.approx(EPOCH_UTC_S, abs=1e-3)


def test_checksum_is_modulo_10_with_minus_as_one():
    assert tles.checksum(L1) == 3 and tles.checksum(L2) == 7
    assert tles.checksum("1" + " " * 66 + "-" + "0") == 2  # '1' + '-'


@pytest.mark.parametrize("l1, l2, reason", [
    (L1[:-1] + "4", L2, tles.CHECKSUM),
    (L1, L2[:-1] + "0", tles.CHECKSUM),
    (L1[:30] + "9" + L1[31:], L2, tles.CHECKSUM),            # a changed digit
    (L1[:-1], L2, tles.FORMAT),                              # 68 characters
    (L1, L2 + "5", tles.FORMAT),
    (L2, L1, tles.FORMAT),                                   # lines swapped
    (L1, "2 00006" + L2[7:-1] + str((tles.checksum(L2) + 1) % 10), tles.FORMAT),  # another satellite
    (L1[:-1] + "x", L2, tles.FORMAT),
    ("", "", tles.FORMAT),
    (L1.replace(" ", "é", 1), L2, tles.FORMAT),
])
def test_bad_tles_are_refused_with_their_reason(l1, l2, reason):
    with pytest.raises(TleError) as e:
        parse_tle(l1, l2)
    assert e.value.reason == reason


def test_trailing_line_ends_are_ignored():
    assert parse_tle(L1 + "\r\n", L2 + "\n").line1 == L1


def test_epoch_checks():
    t = parse_tle(L1, L2)
    check_epoch(t, EPOCH_UTC_S + 3600.0, 86400.0)  # an hour old, limit a day: fine
    with pytest.raises(TleError) as e:
        check_epoch(t, EPOCH_UTC_S - 1.0, 86400.0)
    assert e.value.reason == tles.FUTURE_EPOCH
    with pytest.raises(TleError) as e:
        check_epoch(t, EPOCH_UTC_S + 2 * 86400.0, 86400.0)
    assert e.value.reason == tles.TOO_OLD
