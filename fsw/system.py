"""The one place the flight software is composed: links, key, signing clock, telemetry with its
store-and-forward ring, the sample store, the estimators, the applications and the task table, from a
`fsw.config.RunConfig` and a field source.

Used by the target (`fsw.main`), SITL (`hil.sitl`), the replay of a recording (`ground.replay`), the
benchmarks and the soak (which hand in their own link and key instead of opening them). What it opens
it closes (:meth:`Flight.close`).
"""
from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from typing import Callable, Iterable

from .app import App
from .config import RunConfig
from .estimation.flown_filter import CalibratedField, FlownFilter
from .flight import FieldSource, FlightSoftware
from .telemetry.dialect import FSW_COMPID, FSW_SYSID, mavlink
from .telemetry.sample_store import SampleStore
from .telemetry.signing import SigningClock, key_fingerprint, load_key
from .telemetry.store_forward import StoreForward
from .telemetry.telemetry import Telemetry
from .telemetry.udp_link import open_box_link
from .timeorbit import TimeOrbit


class NullLink:
    """A telemetry connection that packs with the flight software's ids, counts the bytes and drops them:
    for runs of the whole flight software with no ground (benchmarks, tests)."""

    def __init__(self) -> None:
        self.mav = mavlink.MAVLink(self, srcSystem=FSW_SYSID, srcComponent=FSW_COMPID)
        self.bytes = 0

    def write(self, b: bytes) -> None:
        self.bytes += len(b)


@dataclass
class Flight:
    """The composed flight software and what it owns."""

    fsw: FlightSoftware
    tlm: Telemetry
    link: object
    uplink: object | None
    store: SampleStore
    key: bytes | None
    #: time, orbit and field on board
    timeorbit: TimeOrbit | None = None
    #: lines for the run's header: key, command link, sample store
    notes: list[str] = field(default_factory=list)
    _opened: list = field(default_factory=list)

    def close(self) -> None:
        for conn in self._opened:
            try:
                conn.close()
            except OSError:
                pass
        self._opened.clear()
        self.store.close()


def build_flight(cfg: RunConfig, source: FieldSource, *, sigma_b_T: float, sample_rate_hz: float,
                 truth: Callable[[float], object] | None = None, apps: Iterable[App] = (),
                 link=None, uplink=None, key: bytes | None = None, clock: SigningClock | None = None,
                 run_id: int | None = None, rate_filter=None, timeorbit: TimeOrbit | None = None,
                 field=None) -> Flight:
    """The flight software for `source` from `cfg`.

    `link` / `uplink`: connections to use instead of opening `cfg.link` / `cfg.uplink` (the soak's
    radio model; `uplink` defaults to `link`); `key`: the mission key instead of `cfg.key_file`; `clock`:
    the signing clock (default: the wall clock, this being the program's edge — a SITL run faster than
    real time still signs with real time, which the ground compares with its own clock); `run_id`: the
    sample store's run id (default: random, a new one at every start, so that the ground tells runs
    apart); `timeorbit`: the time/orbit application (default: one from `cfg.tle_file` and
    `cfg.tle_max_age_d`), always the first application; `field`: a field along the orbit known for the
    whole run, for the host-magnetics calibration and the flown rate filter (None: both take the
    time/orbit application's, once time and a usable TLE are on board); `rate_filter`: the filter sent
    as DEBRIS_RATE_METHOD_KALMAN instead of `cfg.rate_filter`'s (`fsw.estimation.flown_filter`)."""
    opened = []
    try:
        if key is None and cfg.key_file:
            key = load_key(cfg.key_file)  # KeyFileError is a ValueError
        if link is None:
            link = open_box_link(cfg.link, source_system=cfg.system_id, source_component=FSW_COMPID, baud=cfg.baud)
            opened.append(link)
            if cfg.uplink:
                uplink = open_box_link(cfg.uplink, source_system=cfg.system_id, source_component=FSW_COMPID,
                                       baud=cfg.baud, input=True)
                opened.append(uplink)
        uplink = link if uplink is None else uplink
        clock = clock if clock is not None else SigningClock(clock_set=True, unix_time=time.time)
        tlm = Telemetry(link, store=StoreForward(cfg.buffer_frames) if cfg.buffer_frames > 0 else None, key=key,
                        clock=clock)
        if run_id is None:
            run_id = int.from_bytes(os.urandom(4), "little")
        store = SampleStore(run_id=run_id, path=cfg.sample_store)
    except BaseException:
        for conn in opened:
            conn.close()
        raise
    if timeorbit is None:
        timeorbit = TimeOrbit(tle_file=cfg.tle_file, max_tle_age_d=cfg.tle_max_age_d)
    flown = None
    if rate_filter is None:
        rate_filter = flown = FlownFilter(sigma_b_T, cfg.rate_filter)
    fsw = FlightSoftware(source, tlm, rate_hz=cfg.rate_hz, sigma_b_T=sigma_b_T, truth=truth,
                         max_sample_tlm_hz=cfg.max_sample_tlm_hz, sample_rate_hz=sample_rate_hz, uplink=uplink,
                         key=key, apps=(timeorbit, *apps), rate_filter=rate_filter, sample_store=store,
                         field=field, field_provider=timeorbit, adapt_sample_rate=cfg.adapt_sample_rate)
    if flown is not None:  # the orbit filters fly on the calibration's field, once it calibrates the samples
        flown.provider = CalibratedField(fsw.calibration.provider, fsw.calibration)
    for app in fsw.apps.values():  # the de-orbit kit's attitude estimate: the same field, on the same condition
        source = getattr(app, "attitude", None)
        if source is not None and hasattr(source, "provider") and source.provider is None:
            source.provider = CalibratedField(fsw.calibration.provider, fsw.calibration)
    mission = fsw.apps.get("mission")  # the mission reads its rates from the flown rate filter
    if mission is not None and mission.rates is None:
        mission.rates = fsw.estimators["kalman"]
    notes = [f"mission key {key_fingerprint(key)}: commands must be signed, telemetry is signed" if key else
             "no mission key: commands that change state are refused"]
    if uplink is not link:
        notes[0] += f"; commands on {cfg.uplink or 'their own link'}"
    if field is None:
        notes.append("host-magnetics calibration: from the onboard TLE and UTC once both are set")
    if flown is not None:
        notes.append(f"rate filter: {cfg.rate_filter}" + (
            "" if cfg.rate_filter == "fixed" else "; the fixed-field filter flies until the field along the "
            "orbit is on board and the host-magnetics calibration applied"))
    if store.reset_reason:
        notes.append(f"sample store: {store.reset_reason}")
    notes += timeorbit.notes
    return Flight(fsw, tlm, link, uplink, store, key, timeorbit, notes, opened)
