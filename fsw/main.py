"""Run the flight software on target: `python -m fsw.main --mag-i2c|--mag-spi|--mag-serial DEVICE [options]`.

The MMC5983MA driver talks to the chip on a Linux I2C adapter (`--mag-i2c /dev/i2c-1`, smbus2), a Linux
SPI device (`--mag-spi /dev/spidev0.0`, spidev: the `target` extra) or through a serial register bridge
(`--mag-serial PORT`; the emulator can stand behind a pty: `python -m hil.pty_link`), on the monotonic
clock (`fsw.drivers.mag_bus`). `--sitl` (against the simulator) and
`--replay` (a recording as the magnetometer) are compositions of their own that live with what they
compose: this command hands over to `python -m hil.sitl` and `python -m ground.replay`, with the other
arguments.

Start-up: every option is checked by argparse (finite numbers in range, link ports, output paths:
`fsw.argtypes`, `fsw.files`) and a loop slower than the magnetometer's samples is refused before
anything is built. Ctrl-C at any moment before the loop runs ends the program with one line,
"interrupted" (exit status 130); during the loop it stops the loop and prints the summary.
"""
from __future__ import annotations

if __name__ == "__main__":
    from fsw.startup import interrupt_quietly

    interrupt_quietly()

import importlib  # noqa: E402
import os  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402

from argparse import ArgumentTypeError  # noqa: E402

from .argtypes import ArgumentParser, check_paths_or_exit, finite_float, int_range  # noqa: E402
from .box_config import BoxConfigError, KitLines, load_box_config  # noqa: E402
from .config import RunConfig, add_run_options, check_loop_rate, run_config  # noqa: E402
from .drivers.gpio import GpioError  # noqa: E402
from .drivers.gpiod_lines import require_gpiod  # noqa: E402
from .drivers.mag_bus import KINDS, MagBus, bus_counters_line, open_register_bus  # noqa: E402
from .drivers.spi_bus import MissingLibrary, require_spidev, spidev_numbers  # noqa: E402
from .runner import run_loop, run_program, status_line, summary  # noqa: E402
from .persist import BoxState  # noqa: E402
from .sd_notify import Notifier  # noqa: E402
from .telemetry.dialect import FSW_SYSID  # noqa: E402
from .telemetry.signing import KeyFileError, load_key  # noqa: E402

#: compositions that live outside the flight software, by the option that selects them
HAND_OVER = {"--sitl": "hil.sitl", "--replay": "ground.replay"}


def parse_args(argv=None) -> tuple[RunConfig, MagBus, KitLines | None]:
    """(configuration, the magnetometer's bus, the de-orbit kit's lines or None): the box's configuration
    file (--config) first, the command line over it."""
    argv = sys.argv[1:] if argv is None else list(argv)
    ap = ArgumentParser(
        prog="python -m fsw.main", description=__doc__.splitlines()[0],
        epilog="--sitl ...: the same options and the simulator's (python -m hil.sitl --help); "
               "--replay INPUT.csv ...: a recording as the magnetometer (python -m ground.replay --help)")
    ap.add_argument("--config", metavar="BOX.toml",
                    help="the box's configuration file (fsw/box_config.py, deploy/box.toml): system id, key, "
                         "state directory, buses, kit lines, radio, rates; options given here override it")
    mag = ap.add_mutually_exclusive_group()
    mag.add_argument("--mag-i2c", metavar="DEVICE",
                     help="the MMC5983MA on this Linux I2C adapter at address 0x30 (e.g. /dev/i2c-1)")
    mag.add_argument("--mag-spi", metavar="DEVICE", type=spi_device,
                     help="the MMC5983MA on this Linux SPI device, mode 3 at 4 MHz (e.g. /dev/spidev0.0; needs "
                          "the spidev package: pip install '.[target]')")
    mag.add_argument("--mag-serial", metavar="PORT",
                     help="the MMC5983MA behind a serial register bridge (e.g. the pty of python -m hil.pty_link)")
    add_run_options(ap)
    ap.add_argument("--tle-file", metavar="FILE", default=None,
                    help="keep the TLE in force in this file (written atomically at each upload, read at start) so "
                         "that it survives a restart (default: in memory only; STATE_DIR/tle.txt with --state-dir)")
    ap.add_argument("--tle-max-age", type=finite_float(0.1, 365.0), default=14.0, metavar="DAYS",
                    help="a TLE older than this is refused and no longer used once on board (0.1 to 365 days, "
                         "default 14; parameter TLE_MAX_AGE_D in flight)")
    ap.add_argument("--system-id", type=int_range(1, 255), default=FSW_SYSID, metavar="ID",
                    help=f"the box's MAVLink system id, 1 to 255 (default {FSW_SYSID})")
    ap.add_argument("--state-dir", metavar="DIR", default=None,
                    help="keep what survives a restart in this directory: the command streams' signing "
                         "timestamps (signing.json), the time (time.json), the TLE (tle.txt) and the numbered "
                         "samples (samples.store) unless --tle-file / --sample-store say otherwise")
    box = None
    args = ap.parse_args(argv)
    if args.config is not None:  # the file's values as the options' defaults, the command line parsed again over them
        try:
            box = load_box_config(args.config)
        except BoxConfigError as e:
            ap.error(str(e))
        ap.set_defaults(**box.defaults())
        args = ap.parse_args(argv)
    given = next(((k, d) for k in KINDS if (d := getattr(args, f"mag_{k}")) is not None), None)
    if given is not None:
        mag_bus = MagBus(*given)
    elif box is not None and box.mag is not None:
        mag_bus = box.mag
    else:
        ap.error("the magnetometer's bus: one of --mag-i2c, --mag-spi, --mag-serial, or [magnetometer] in --config")
    if mag_bus.kind == "spi":
        try:
            require_spidev()
        except MissingLibrary as e:
            ap.error(f"--mag-spi: {e}")
    kit = box.kit if box is not None else None
    if kit is not None:
        try:
            require_gpiod()
        except GpioError as e:
            ap.error(f"{box.path}: [kit]: {e}")
    if args.state_dir is not None:
        if not os.path.isdir(args.state_dir):
            ap.error(f"--state-dir {args.state_dir}: not a directory")
        args.tle_file = args.tle_file or os.path.join(args.state_dir, "tle.txt")
        args.sample_store = args.sample_store or os.path.join(args.state_dir, "samples.store")
    check_paths_or_exit(ap, inputs={"--key": args.key, f"--mag-{mag_bus.kind}": mag_bus.device},
                        outputs={"--sample-store": args.sample_store, "--tle-file": args.tle_file})
    key_from_file = box is not None and args.key == box.key_file and not any(a.startswith("--key") for a in argv)
    try:
        check_key(args.key)
    except KeyFileError as e:
        ap.error(f"{box.path}: key_file {e}" if key_from_file else f"--key {e}")
    return run_config(args, sample_rate_hz=args.sample_rate or 1.0, tle_file=args.tle_file,
                      tle_max_age_d=args.tle_max_age, system_id=args.system_id, state_dir=args.state_dir), \
        mag_bus, kit


def check_key(key_file: str | None) -> None:
    """Read the mission key at start (mode, length, not all zero; KeyFileError), before any device is opened."""
    if key_file is not None:
        load_key(key_file)


def spi_device(text: str) -> str:
    """argparse type of --mag-spi: a path /dev/spidevB.D."""
    try:
        spidev_numbers(text)
    except ValueError as e:
        raise ArgumentTypeError(str(e)) from None
    return text


def run(cfg: RunConfig, mag: MagBus, kit: KitLines | None = None, out=sys.stdout):
    """Build the flight software on the chip on `mag` (and the de-orbit kit on the GPIO lines of `kit`) and
    run the loop on the monotonic clock; (flight software, loop result, the bus's failures for the summary).
    Whatever ends the run (its duration, SIGTERM or SIGINT, an exception) leaves the kit's lines at their
    safe levels and released (`fsw.drivers.gpiod_lines`)."""
    from .drivers.mmc5983ma import FLIGHT_SCHEDULE, Mmc5983ma
    from .ident import AnnouncedTug, IdentExperiment
    from .system import build_flight
    from .timeorbit import TimeOrbit

    warning = check_loop_rate(cfg.rate_hz, cfg.sample_rate_hz)
    bus = open_register_bus(mag)
    lines = None
    state = BoxState(cfg.state_dir, monotonic=time.monotonic, boot_id=boot_id()) if cfg.state_dir else None
    try:
        source = Mmc5983ma(bus, sample_period_s=1.0 / cfg.sample_rate_hz, **FLIGHT_SCHEDULE)
        timeorbit = TimeOrbit(tle_file=cfg.tle_file, max_tle_age_d=cfg.tle_max_age_d)
        # the identification experiment: its field along the orbit from the TLE and UTC on board (refused
        # without them), the tug commanded on its own (the START command announces its moment)
        ident = IdentExperiment(sigma_b_T=cfg.sigma_T, b_inertial=timeorbit, tug=AnnouncedTug())
        apps = [ident]
        notes = []
        if kit is not None:
            from .deorbit.kit import DeorbitKit
            from .deorbit.onboard_attitude import EstimatedAttitude
            from .drivers.gpiod_lines import GpiodLines

            lines = GpiodLines(kit.chip, kit.lines, burst_period_s=1.0 / DeorbitKit.rate_hz, debounce_s=kit.debounce_s)
            deorbit = DeorbitKit(lines, EstimatedAttitude(cfg.sigma_T))
            apps.append(deorbit)
            notes.append(f"de-orbit kit: {len(kit.lines)} lines on {kit.chip}; controller attitude from the "
                         "onboard estimate (the design's spacecraft model)")
            if kit.mission_inertia_guess_kgm2 is not None:  # [kit.mission]: the whole mission on the kit
                from .deorbit.mission import over_kit
                apps.append(over_kit(deorbit, ident, kit.mission_inertia_guess_kgm2))
                notes.append("mission: from a tumble to a stabilised sail on the kit, the box's guess of the "
                             f"moments {', '.join(f'{x:g}' for x in kit.mission_inertia_guess_kgm2)} kg·m² "
                             "(the identification's magnets are the kit's)")
        flight = build_flight(cfg, source, sigma_b_T=cfg.sigma_T, sample_rate_hz=cfg.sample_rate_hz, apps=apps,
                              timeorbit=timeorbit)
        fsw = flight.fsw
        if state is not None:
            state.restore(fsw.uplink.verifier if fsw.uplink is not None else None, timeorbit)
            state.restore_apps(cfg.system_id, calibration=fsw.calibration, kit_field=fsw.kit_field, ident=ident)
            notes += state.notes
        print("\n".join([f"target: MMC5983MA on {mag.describe()}, loop {cfg.rate_hz:g} Hz, link {cfg.link}",
                         *flight.notes, *notes, *([warning] if warning else [])]), file=out, flush=True)
        notifier = Notifier()  # systemd: READY at the first tick, the watchdog fed by every tick after it
        after = ([notifier.heartbeat] if notifier.enabled else []) + ([state.tick] if state is not None else [])

        def after_tick(t: float) -> None:
            for f in after:
                f(t)
        try:
            res = run_loop(fsw, duration_s=cfg.duration_s, lockstep=False,
                           status=None if cfg.quiet else (lambda t: status_line(t, fsw)), out=out,
                           after_tick=after_tick if after else None)
        finally:
            notifier.stopping()
            notifier.close()
            flight.close()
    finally:
        if lines is not None:
            lines.close()
        if state is not None:
            state.close()
        bus.close()
    extra = [line for line in (bus_counters_line(bus), state.summary_line() if state else None) if line]
    return fsw, res, extra


def boot_id() -> str | None:
    """This boot's id (Linux), which tells a restart of the service from a reboot; None elsewhere."""
    try:
        with open("/proc/sys/kernel/random/boot_id") as f:
            return f.read().strip() or None
    except OSError:
        return None


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    for option, module in HAND_OVER.items():
        if option in argv:  # the composition lives with what it composes (a runtime hand-over, not an import)
            rest = [a for a in argv if a != option] if option == "--sitl" else argv[argv.index(option) + 1:] \
                + argv[:argv.index(option)]
            return importlib.import_module(module).main(rest)
    def body() -> str:
        cfg, mag, kit = parse_args(argv)
        return summary(*run(cfg, mag, kit))

    return run_program(body)


if __name__ == "__main__":
    from fsw.startup import exit_with

    exit_with(main)
