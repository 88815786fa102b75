"""MEMSIC MMC5983MA register map, constants and pure output decoding.

Source: MEMSIC MMC5983MA datasheet Rev A (4/3/2019), cited as [DS pN]; the fact sheet
`docs/spec/mmc5983ma.md` collects the numbers with their pages.

Output format [DS p12-16]: each axis is an 18-bit unsigned offset-binary count
    c18 = (Out0 << 10) | (Out1 << 2) | two bits of XYZout2   (X: b7:6, Y: b5:4, Z: b3:2),
a burst read from 0x00 returns X0 X1 Y0 Y1 Z0 Z1 XYZ2. The field is
    B[G] = (c18 - 131072) / 16384,   1 G = 1e-4 T,
over a +-8 G range [DS p2]. Axis signs are those printed on the package, which hold after a SET
pulse; readings taken in RESET polarity are sign-inverted [DS p18].
"""

from __future__ import annotations

from enum import IntEnum, IntFlag

import numpy as np

# --- constants ----------------------------------------------------------------------------------

PRODUCT_ID = 0x30
"""Content of register Product ID 1 (0x2F) [DS p13-16]."""

I2C_ADDRESS = 0x30
"""7-bit I2C address, 0110000b (write byte 0x60, read byte 0x61) [DS p1, p17]."""

SPI_READ = 0x80
"""First SPI byte: bit7 = 1 for a read, bits5:0 the address [DS p4-p8]."""

NULL_FIELD_18 = 131072
"""18-bit count at zero field [DS p2]."""
NULL_FIELD_16 = 32768
"""16-bit count at zero field [DS p2]."""
COUNTS_PER_GAUSS_18 = 16384
"""18-bit sensitivity, counts per gauss [DS p2]; the quoted "0.0625 mG/LSB" rounds 1/16384 G = 0.06104 mG."""
COUNTS_PER_GAUSS_16 = 4096
"""16-bit sensitivity, counts per gauss [DS p2]."""
COUNTS_MAX_18 = (1 << 18) - 1
"""Largest 18-bit count (262143); 0 and COUNTS_MAX_18 bound the +-8 G range."""
RANGE_G = 8
"""Full scale, +-8 G [DS p2]."""

TESLA_PER_GAUSS = 1e-4
TESLA_PER_COUNT_18 = TESLA_PER_GAUSS / COUNTS_PER_GAUSS_18
"""6.1035e-9 T (0.061035 mG) per 18-bit count."""

POWER_ON_TIME_S = 0.010
"""Power-on / soft-reset time, "Power on time is 10 ms" [DS p2, p13-16]."""
SET_RESET_PULSE_S = 500e-9
"""Duration of the SET/RESET coil current pulse [DS p13-16]."""
SET_RESET_SETTLE_S = 0.001
"""Wait after a SET/RESET pulse before TM_M. Not in the DS: SparkFun waits 1 ms and an ArduPilot
comment asks for >= 1 ms (fact sheet section 3)."""

TEMPERATURE_OFFSET_C = -75.0
"""Temperature at Tout = 0 [DS p2, p13-16]."""
TEMPERATURE_C_PER_LSB = 0.8
""""About 0.8 degC/LSB" [DS p13-16]; the stated -75...125 degC range would imply 200/255 = 0.784.
MEMSIC advised against using the sensor (fact sheet section 5)."""


# --- register map [DS p13-16] -------------------------------------------------------------------


class Register(IntEnum):
    """Register addresses [DS p13-16]. 0x09-0x0C are write-only: reading them returns garbage."""

    XOUT0 = 0x00  # X[17:10]
    XOUT1 = 0x01  # X[9:2]
    YOUT0 = 0x02  # Y[17:10]
    YOUT1 = 0x03  # Y[9:2]
    ZOUT0 = 0x04  # Z[17:10]
    ZOUT1 = 0x05  # Z[9:2]
    XYZOUT2 = 0x06  # b7:6 X[1:0], b5:4 Y[1:0], b3:2 Z[1:0]
    TOUT = 0x07  # temperature, unsigned
    STATUS = 0x08  # R/W: write 1 to a done bit to clear it
    INTERNAL_CONTROL_0 = 0x09  # W
    INTERNAL_CONTROL_1 = 0x0A  # W
    INTERNAL_CONTROL_2 = 0x0B  # W
    INTERNAL_CONTROL_3 = 0x0C  # W
    PRODUCT_ID_1 = 0x2F  # R, reads PRODUCT_ID


WRITE_ONLY_REGISTERS = frozenset(
    {
        Register.INTERNAL_CONTROL_0,
        Register.INTERNAL_CONTROL_1,
        Register.INTERNAL_CONTROL_2,
        Register.INTERNAL_CONTROL_3,
    }
)
"""The control registers [DS p13-16]; read-modify-write on them is the SparkFun <= 1.0.x bug."""

OUTPUT_BYTES = 7
"""Burst length from XOUT0 for the three 18-bit outputs [DS p13-16]."""


class Status(IntFlag):
    """Register 0x08 [DS p13-16]. Reset value 0."""

    MEAS_M_DONE = 0x01  # field measurement finished; 0 while one runs
    MEAS_T_DONE = 0x02  # temperature measurement finished
    OTP_READ_DONE = 0x10  # OTP read successfully at power-on / soft reset


class InternalControl0(IntFlag):
    """Register 0x09 [DS p13-16]. TM_M, TM_T, SET, RESET and OTP_READ clear themselves."""

    TM_M = 0x01  # start one field measurement
    TM_T = 0x02  # start one temperature measurement (never together with TM_M)
    INT_MEAS_DONE_EN = 0x04  # INT pin pulses when a measurement is done
    SET = 0x08  # 500 ns SET coil pulse
    RESET = 0x10  # 500 ns RESET coil pulse
    AUTO_SR_EN = 0x20  # automatic SET/RESET (behaviour undocumented)
    OTP_READ = 0x40  # reload OTP into the shadow registers


class InternalControl1(IntFlag):
    """Register 0x0A [DS p13-16]."""

    BW0 = 0x01
    BW1 = 0x02
    X_INHIBIT = 0x04
    YZ_INHIBIT = 0x18  # two bits, always written together
    SW_RST = 0x80  # soft reset, like power-on; POWER_ON_TIME_S to complete


BW_MASK = 0x03
"""BW field of Internal Control 1."""


class InternalControl2(IntFlag):
    """Register 0x0B [DS p13-16]."""

    CM_FREQ0 = 0x01
    CM_FREQ1 = 0x02
    CM_FREQ2 = 0x04
    CMM_EN = 0x08  # continuous mode on (Cm_freq must not be 000)
    PRD_SET0 = 0x10
    PRD_SET1 = 0x20
    PRD_SET2 = 0x40
    EN_PRD_SET = 0x80  # periodic SET; needs AUTO_SR_EN and CMM_EN


CM_FREQ_MASK = 0x07
"""Cm_freq field of Internal Control 2."""
PRD_SET_MASK = 0x70
PRD_SET_SHIFT = 4


class InternalControl3(IntFlag):
    """Register 0x0C [DS p13-16]."""

    ST_ENP = 0x02  # self-test current, positive
    ST_ENM = 0x04  # self-test current, negative
    SPI_3W = 0x40  # 3-wire SPI


class Bandwidth(IntEnum):
    """BW[1:0] of Internal Control 1: decimation filter length [DS p2, p13-16].

    X, Y and Z are converted in parallel; `measurement_time_s` is the TM_M-to-done time of the
    register table (DS p12 also says 10 ms for BW=00, the table 8 ms: the table is used).
    """

    BW_100HZ = 0b00
    BW_200HZ = 0b01
    BW_400HZ = 0b10
    BW_800HZ = 0b11

    @property
    def measurement_time_s(self) -> float:
        return _MEASUREMENT_TIME_S[self]

    @property
    def noise_rms_T(self) -> float:
        """RMS noise per axis [DS p2]: 0.4 / 0.6 / 0.8 / 1.2 mG."""
        return _NOISE_RMS_MG[self] * 1e-3 * TESLA_PER_GAUSS

    @property
    def max_odr_hz(self) -> float:
        """Maximum single-measurement output data rate [DS p2]: 50 / 100 / 225 / 580 Hz."""
        return _MAX_ODR_HZ[self]


_MEASUREMENT_TIME_S = {0b00: 8e-3, 0b01: 4e-3, 0b10: 2e-3, 0b11: 0.5e-3}
_NOISE_RMS_MG = {0b00: 0.4, 0b01: 0.6, 0b10: 0.8, 0b11: 1.2}
_MAX_ODR_HZ = {0b00: 50.0, 0b01: 100.0, 0b10: 225.0, 0b11: 580.0}


class ContinuousFrequency(IntEnum):
    """Cm_freq[2:0] of Internal Control 2 [DS p13-16], rates stated for BW=00.

    200 Hz needs BW=01 and 1000 Hz needs BW=11: a measurement cannot complete faster than the
    BW's measurement time, see `fits`.
    """

    OFF = 0b000
    HZ_1 = 0b001
    HZ_10 = 0b010
    HZ_20 = 0b011
    HZ_50 = 0b100
    HZ_100 = 0b101
    HZ_200 = 0b110
    HZ_1000 = 0b111

    @property
    def rate_hz(self) -> float:
        return _CM_RATE_HZ[self]

    def fits(self, bandwidth: Bandwidth) -> bool:
        """True if the BW's measurement time fits in one period (1000 Hz only with BW=11)."""
        return self is not ContinuousFrequency.OFF and (
            bandwidth.measurement_time_s <= 1.0 / self.rate_hz
        )


_CM_RATE_HZ = {0: 0.0, 1: 1.0, 2: 10.0, 3: 20.0, 4: 50.0, 5: 100.0, 6: 200.0, 7: 1000.0}

PERIODIC_SET_MEASUREMENTS = (1, 25, 75, 100, 250, 500, 1000, 2000)
"""Prd_set[2:0] -> measurements between automatic SET pulses [DS p13-16]."""


# --- pure decoding ------------------------------------------------------------------------------


def decode_xyz18(raw7: bytes) -> tuple[int, int, int]:
    """18-bit unsigned counts (X, Y, Z) from the 7-byte burst X0 X1 Y0 Y1 Z0 Z1 XYZ2 [DS p13-16]."""
    b2 = raw7[6]
    return (
        (raw7[0] << 10) | (raw7[1] << 2) | ((b2 >> 6) & 0x3),
        (raw7[2] << 10) | (raw7[3] << 2) | ((b2 >> 4) & 0x3),
        (raw7[4] << 10) | (raw7[5] << 2) | ((b2 >> 2) & 0x3),
    )


def decode_xyz16(raw6: bytes) -> tuple[int, int, int]:
    """16-bit counts (bits 17:2) from X0 X1 Y0 Y1 Z0 Z1 [DS p12]."""
    return (raw6[0] << 8) | raw6[1], (raw6[2] << 8) | raw6[3], (raw6[4] << 8) | raw6[5]


def encode_xyz18(cx: int, cy: int, cz: int) -> bytes:
    """Inverse of `decode_xyz18`: the 7 output bytes holding three 18-bit counts (XYZ2 b1:0 = 0)."""
    for c in (cx, cy, cz):
        if not 0 <= c <= COUNTS_MAX_18:
            raise ValueError(f"count {c} outside 0..{COUNTS_MAX_18}")
    return bytes(
        (
            cx >> 10,
            (cx >> 2) & 0xFF,
            cy >> 10,
            (cy >> 2) & 0xFF,
            cz >> 10,
            (cz >> 2) & 0xFF,
            ((cx & 0x3) << 6) | ((cy & 0x3) << 4) | ((cz & 0x3) << 2),
        )
    )


def counts_to_gauss(c18):
    """B[G] = (c18 - 131072) / 16384 [DS p2]; works on ints, floats and numpy arrays."""
    return (c18 - NULL_FIELD_18) / COUNTS_PER_GAUSS_18


def counts_to_tesla(c18):
    """B[T] = (c18 - 131072) / 16384 * 1e-4 [DS p2]; works on ints, floats and numpy arrays."""
    return (c18 - NULL_FIELD_18) * TESLA_PER_COUNT_18


def counts16_to_tesla(c16):
    """B[T] = (c16 - 32768) / 4096 * 1e-4 [DS p2]."""
    return (c16 - NULL_FIELD_16) * (TESLA_PER_GAUSS / COUNTS_PER_GAUSS_16)


def decode_field_T(raw: bytes, out: np.ndarray) -> np.ndarray:
    """Decode the 7-byte burst into the field in tesla, written into `out` (shape (3,)), returned.

    Allocation-free apart from Python scalars: the flight loop calls it at up to 1 kHz.
    """
    b2 = raw[6]
    out[0] = (((raw[0] << 10) | (raw[1] << 2) | ((b2 >> 6) & 0x3)) - NULL_FIELD_18) * TESLA_PER_COUNT_18
    out[1] = (((raw[2] << 10) | (raw[3] << 2) | ((b2 >> 4) & 0x3)) - NULL_FIELD_18) * TESLA_PER_COUNT_18
    out[2] = (((raw[4] << 10) | (raw[5] << 2) | ((b2 >> 2) & 0x3)) - NULL_FIELD_18) * TESLA_PER_COUNT_18
    return out


def tout_to_celsius(tout: int) -> float:
    """T[degC] = -75 + 0.8 * Tout [DS p13-16] (unreliable per MEMSIC)."""
    return TEMPERATURE_OFFSET_C + TEMPERATURE_C_PER_LSB * tout


def set_reset_solve(c_set, c_reset):
    """SET/RESET offset removal [DS p18]: Out1 = +H + Off after SET, Out2 = -H + Off after RESET.

    Returns (H, Off) = ((Out1 - Out2) / 2, (Out1 + Out2) / 2), in the units given.
    """
    return (c_set - c_reset) / 2, (c_set + c_reset) / 2
