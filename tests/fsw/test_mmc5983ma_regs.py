"""MMC5983MA register map and decoding against the datasheet vectors of docs/spec/mmc5983ma.md section 6."""

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from fsw.drivers.mmc5983ma_regs import (
    COUNTS_MAX_18,
    COUNTS_PER_GAUSS_18,
    I2C_ADDRESS,
    NULL_FIELD_18,
    POWER_ON_TIME_S,
    PRODUCT_ID,
    RANGE_G,
    WRITE_ONLY_REGISTERS,
    Bandwidth,
    ContinuousFrequency,
    InternalControl0,
    InternalControl1,
    InternalControl2,
    InternalControl3,
    Register,
    Status,
    counts16_to_tesla,
    counts_to_gauss,
    counts_to_tesla,
    decode_field_T,
    decode_xyz16,
    decode_xyz18,
    encode_xyz18,
    set_reset_solve,
    tout_to_celsius,
)

# (bytes X0 X1 Y0 Y1 Z0 Z1 XYZ2, c18, gauss, microtesla, c16, gauss from c16), spec section 6
VECTORS = {
    "V1": (
        "80 00 80 00 80 00 00",
        (131072, 131072, 131072),
        (0.0, 0.0, 0.0),
        (0.0, 0.0, 0.0),
        (32768, 32768, 32768),
        (0.0, 0.0, 0.0),
    ),
    "V2": (
        "83 33 7F 33 87 33 54",
        (134349, 130253, 138445),
        (0.200012, -0.049988, 0.450012),
        (20.0012, -4.9988, 45.0012),
        (33587, 32563, 34611),
        (0.199951, -0.050049, 0.449951),
    ),
    "V3": (
        "FF FF 00 00 40 00 C0",
        (262143, 0, 65536),
        (7.999939, -8.0, -4.0),
        (799.9939, -800.0, -400.0),
        (65535, 0, 16384),
        (7.999756, -8.0, -4.0),
    ),
}


@pytest.mark.parametrize("name", VECTORS)
def test_datasheet_vectors_decode_exactly(name):
    hexbytes, c18, gauss, micro_T, c16, gauss16 = VECTORS[name]
    raw = bytes.fromhex(hexbytes)
    assert decode_xyz18(raw) == c18
    assert decode_xyz16(raw[:6]) == c16
    assert [counts_to_gauss(c) for c in c18] == pytest.approx(gauss, abs=5e-7)
    assert [counts_to_tesla(c) * 1e6 for c in c18] == pytest.approx(micro_T, abs=5e-5)
    assert [counts16_to_tesla(c) * 1e4 for c in c16] == pytest.approx(gauss16, abs=5e-7)
    out = np.full(3, np.nan)
    assert decode_field_T(raw, out) is out
    np.testing.assert_allclose(out * 1e6, micro_T, atol=5e-5)
    assert encode_xyz18(*c18) == raw


def test_v2_x_worked_example():
    # 0x83 << 10 = 134144; 0x33 << 2 = 204; XYZ2 b7:6 = 01 -> 134349
    assert (0x83 << 10) + (0x33 << 2) + 0b01 == 134349 == decode_xyz18(bytes.fromhex(VECTORS["V2"][0]))[0]


def test_set_reset_example_exactly():
    # X after SET: 83 5C, bits 01; after RESET: 7C F5, bits 11 (Y, Z at null)
    c_set = decode_xyz18(bytes.fromhex("835C80008000" + "40"))[0]
    c_reset = decode_xyz18(bytes.fromhex("7CF580008000" + "C0"))[0]
    assert (c_set, c_reset) == (134513, 127959)
    h, off = set_reset_solve(c_set, c_reset)
    assert (h, off) == (3277, 131236)
    assert off - NULL_FIELD_18 == 164
    assert h / COUNTS_PER_GAUSS_18 == pytest.approx(0.200012, abs=5e-7)
    assert counts_to_gauss(off) == pytest.approx(0.010010, abs=5e-7)
    # the same in tesla from the decoded fields: H = (S - R)/2, offset = (S + R)/2
    s, r = np.zeros(3), np.zeros(3)
    decode_field_T(bytes.fromhex("835C8000800040"), s)
    decode_field_T(bytes.fromhex("7CF580008000C0"), r)
    h_T, off_T = set_reset_solve(s, r)
    np.testing.assert_allclose(h_T, [0.200012e-4, 0, 0], atol=5e-11)
    np.testing.assert_allclose(off_T, [0.010010e-4, 0, 0], atol=5e-11)


@given(st.integers(0, COUNTS_MAX_18), st.integers(0, COUNTS_MAX_18), st.integers(0, COUNTS_MAX_18))
def test_encode_decode_round_trip(cx, cy, cz):
    raw = encode_xyz18(cx, cy, cz)
    assert len(raw) == 7 and raw[6] & 0x03 == 0
    assert decode_xyz18(raw) == (cx, cy, cz)


def test_encode_rejects_out_of_range():
    with pytest.raises(ValueError):
        encode_xyz18(COUNTS_MAX_18 + 1, 0, 0)


def test_register_map_and_constants():
    assert (PRODUCT_ID, I2C_ADDRESS, NULL_FIELD_18, COUNTS_PER_GAUSS_18, RANGE_G) == (0x30, 0x30, 131072, 16384, 8)
    assert POWER_ON_TIME_S == 0.010
    assert [int(r) for r in Register] == [*range(0x00, 0x0D), 0x2F]
    assert WRITE_ONLY_REGISTERS == {0x09, 0x0A, 0x0B, 0x0C}
    assert (Status.MEAS_M_DONE, Status.MEAS_T_DONE, Status.OTP_READ_DONE) == (0x01, 0x02, 0x10)
    assert [int(b) for b in InternalControl0] == [0x01, 0x02, 0x04, 0x08, 0x10, 0x20, 0x40]
    # SW_RST is bit 7 of Internal Control 1 (0x0A); 0x80 in 0x0B would be En_prd_set
    assert Register.INTERNAL_CONTROL_1 == 0x0A and InternalControl1.SW_RST == 0x80
    assert InternalControl2.EN_PRD_SET == 0x80 and InternalControl2.CMM_EN == 0x08
    assert InternalControl1.YZ_INHIBIT == 0x18 and InternalControl3.SPI_3W == 0x40
    # 18-bit full scale is +-8 G
    assert counts_to_gauss(0) == -RANGE_G and counts_to_gauss(COUNTS_MAX_18 + 1) == RANGE_G


def test_bandwidth_table():
    assert [b.measurement_time_s for b in Bandwidth] == [8e-3, 4e-3, 2e-3, 0.5e-3]
    assert [b.noise_rms_T * 1e7 for b in Bandwidth] == pytest.approx([0.4, 0.6, 0.8, 1.2])  # mG
    assert [b.max_odr_hz for b in Bandwidth] == [50, 100, 225, 580]


def test_continuous_frequency_limits():
    assert [f.rate_hz for f in ContinuousFrequency] == [0, 1, 10, 20, 50, 100, 200, 1000]
    assert [b for b in Bandwidth if ContinuousFrequency.HZ_1000.fits(b)] == [Bandwidth.BW_800HZ]
    assert not ContinuousFrequency.HZ_200.fits(Bandwidth.BW_100HZ)
    assert ContinuousFrequency.HZ_200.fits(Bandwidth.BW_200HZ)
    assert ContinuousFrequency.HZ_100.fits(Bandwidth.BW_100HZ)
    assert not ContinuousFrequency.OFF.fits(Bandwidth.BW_800HZ)


def test_temperature_formula():
    assert tout_to_celsius(0) == -75.0
    assert tout_to_celsius(125) == pytest.approx(25.0)
