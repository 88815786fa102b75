"""The typed run configuration of the flight software: one dataclass, built from the command line once.

`RunConfig` holds what every run of the flight software needs — loop, link, key, buffers, sample
rate, the estimators' field noise — in SI units. The target (`fsw.main`), SITL (`hil.sitl`) and the
replay of a recording (`ground.replay`) add their own options to the same parser
(:func:`add_run_options`) and build their configuration from :func:`run_config`; benchmarks and the
soak build a `RunConfig` directly. `fsw.system.build_flight` composes the flight software from it.
"""
from __future__ import annotations

import argparse
from dataclasses import dataclass, replace

from .argtypes import finite_float, int_range, link_url
from .estimation.flown_filter import DEFAULT_FILTER, FILTERS
from .telemetry.dialect import FSW_SYSID
from .telemetry.signing import KeyFileError, load_key
from .telemetry.store_forward import DEFAULT_CAPACITY

DEFAULT_LINK = "udpout:127.0.0.1:14550"
#: largest store-and-forward ring (--buffer-frames): about 0.8 kB of memory a frame, 0.8 GB at most
MAX_BUFFER_FRAMES = 1_000_000
#: the loop's ceiling (--rate) and the MMC5983MA's (--sample-rate)
MAX_RATE_HZ = 1000.0
#: the largest field error σ an estimator may be told, µT: the MMC5983MA's full scale is ±800 µT
MAX_SIGMA_UT = 1000.0


@dataclass(frozen=True)
class RunConfig:
    """One run of the flight software."""

    rate_hz: float = 50.0
    #: stop after this much loop time (None: until SIGINT/SIGTERM)
    duration_s: float | None = None
    #: pacing of a lockstep run: 1 = real time, 0 = as fast as possible (the target always runs in real time)
    speed: float = 1.0
    link: str = DEFAULT_LINK
    baud: int = 57600
    #: mission key file (None: state-changing commands are refused, telemetry unsigned)
    key_file: str | None = None
    #: where commands arrive (None: on `link`)
    uplink: str | None = None
    buffer_frames: int = DEFAULT_CAPACITY
    #: file that keeps the numbered samples across a restart (None: in memory)
    sample_store: str | None = None
    #: magnetometer sample rate (None: the source's own: 1 Hz on target, the scenario's in SITL)
    sample_rate_hz: float | None = None
    #: lower the sample rate to one the loop can hold (`fsw.sample_rate`); False: keep it whatever the load
    adapt_sample_rate: bool = True
    #: 1-σ field error per axis the estimators assume, T (SITL takes the scenario's instead)
    sigma_T: float = 1.5e-6
    max_sample_tlm_hz: float = 20.0
    quiet: bool = False
    #: file that keeps the TLE in force across a restart (None: in memory only)
    tle_file: str | None = None
    #: a TLE older than this is refused and, once on board, no longer used (parameter TLE_MAX_AGE_D)
    tle_max_age_d: float = 14.0
    #: the box's MAVLink system id (fsw.telemetry.dialect.FSW_SYSID unless the box's configuration says)
    system_id: int = FSW_SYSID
    #: what survives a restart on target (fsw.persist; None: nothing beyond --tle-file / --sample-store)
    state_dir: str | None = None
    #: the rate filter flown (`fsw.estimation.flown_filter`): fixed, orbit, euler (default) or mm; the orbit
    #: filters fly once the field along the orbit is on board, the fixed-field filter until then
    rate_filter: str = DEFAULT_FILTER


def add_run_options(ap: argparse.ArgumentParser) -> None:
    """The options every run of the flight software takes."""
    ap.add_argument("--duration", type=finite_float(0, min_exclusive=True), default=None, metavar="S",
                    help="stop after S seconds of loop time (default: run until Ctrl-C)")
    ap.add_argument("--rate", type=finite_float(0, MAX_RATE_HZ, min_exclusive=True), default=50.0, metavar="HZ",
                    help="loop rate, up to 1000 Hz and at least the magnetometer's sample rate (default 50 Hz)")
    ap.add_argument("--link", type=link_url, default=DEFAULT_LINK, metavar="URL",
                    help=f"telemetry link: udpout:HOST:PORT, udpin:HOST:PORT, tcp:HOST:PORT or a serial device "
                         f"(default {DEFAULT_LINK})")
    ap.add_argument("--baud", type=int_range(1), default=57600, help="baud rate when --link is a serial port")
    ap.add_argument("--key", metavar="FILE",
                    help="mission key file (python -m ground.keys new FILE): commands must be signed with it, "
                         "telemetry is signed with it; without a key every state-changing command is refused")
    ap.add_argument("--uplink", type=link_url, metavar="URL", default=None,
                    help="where commands arrive (default: the --link itself; e.g. udpin:0.0.0.0:14551 to command "
                         "over UDP while ground.decode listens on --link)")
    ap.add_argument("--buffer-frames", type=int_range(0, MAX_BUFFER_FRAMES), default=DEFAULT_CAPACITY, metavar="N",
                    help=f"store-and-forward ring: telemetry frames kept while the link is down "
                         f"(default {DEFAULT_CAPACITY}; 0 = none; at most {MAX_BUFFER_FRAMES:,}, ~0.8 kB each)")
    ap.add_argument("--sample-store", metavar="FILE", default=None,
                    help="keep the numbered samples the ground may ask for again in this file, so that they and "
                         "their numbering survive a restart (default: in memory)")
    ap.add_argument("--sample-rate", type=finite_float(0, MAX_RATE_HZ, min_exclusive=True), default=None,
                    metavar="HZ", help="magnetometer sample rate, up to 1000 Hz (default: the source's own)")
    ap.add_argument("--fixed-sample-rate", action="store_true",
                    help="keep the sample rate even when the loop cannot hold it (default: the box lowers it to the "
                         "highest rate its measured work per sample fits, and says so; bench.speed uses this)")
    ap.add_argument("--sigma-uT", type=finite_float(0, MAX_SIGMA_UT, min_exclusive=True), default=1.5,
                    help="1-sigma field error per axis used by the estimators (default 1.5 uT, at most 1000)")
    ap.add_argument("--max-sample-tlm-hz", type=finite_float(0.01, MAX_RATE_HZ), default=20.0,
                    help="at most this many magnetometer samples per second go out on the link "
                         "(0.01 to 1000, default 20)")
    ap.add_argument("--rate-filter", choices=tuple(FILTERS), default=DEFAULT_FILTER,
                    help="the rate filter flown: euler (default: attitude, rate and the inertia shape with the field "
                         "along the orbit, the best onboard method of the accuracy table's tumbling rows), mm (a bank "
                         "of rate models: a slow libration), orbit (attitude and a random-walk rate), fixed (the "
                         "fixed-field filter, no orbit needed); until the box has a UTC and a TLE (or a known "
                         "field) the fixed-field filter flies and the status line says so")
    ap.add_argument("--quiet", action="store_true", help="no status line each second, only the summary")


def run_config(args: argparse.Namespace, **overrides) -> RunConfig:
    """The `RunConfig` of parsed options (see :func:`add_run_options`)."""
    cfg = RunConfig(rate_hz=args.rate, duration_s=args.duration, speed=getattr(args, "speed", 1.0),
                    link=args.link, baud=args.baud, key_file=args.key, uplink=args.uplink,
                    buffer_frames=args.buffer_frames, sample_store=args.sample_store,
                    sample_rate_hz=args.sample_rate, sigma_T=args.sigma_uT * 1e-6,
                    adapt_sample_rate=not getattr(args, "fixed_sample_rate", False),
                    max_sample_tlm_hz=args.max_sample_tlm_hz, quiet=args.quiet,
                    rate_filter=getattr(args, "rate_filter", DEFAULT_FILTER))
    return replace(cfg, **overrides)


def check_key_or_exit(ap: argparse.ArgumentParser, key_file: str | None) -> None:
    """Read the mission key at start (mode, length, not all zero): a bad key is a usage error before any
    device is opened, never a failure once the loop is being built."""
    if key_file is not None:
        try:
            load_key(key_file)
        except KeyFileError as e:
            ap.error(f"--key {e}")


def check_loop_rate(rate_hz: float, sample_rate_hz: float) -> str | None:
    """Refuse (ValueError) a loop slower than the magnetometer's samples: it takes one sample a tick at
    most, so it would drop samples all the time. At an equal rate: a warning line (a tick that starts
    late, the driver's start-up and each SET/RESET calibration then cost samples); None otherwise."""
    if rate_hz < sample_rate_hz * (1 - 1e-9):
        raise ValueError(f"--rate {rate_hz:g} Hz is below the magnetometer's sample rate {sample_rate_hz:g} Hz: "
                         "the loop must run at least as fast as samples arrive, or it drops them "
                         f"(give --rate {min(MAX_RATE_HZ, 2 * sample_rate_hz):g} or more)")
    if rate_hz < sample_rate_hz * (1 + 1e-9):
        return (f"warning: --rate {rate_hz:g} Hz equals the sample rate: samples are lost at start-up, at each "
                "SET/RESET calibration (every 1000 samples, at most every 10 s) and whenever a tick starts late; "
                "a faster loop loses fewer")
    return None
