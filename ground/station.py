"""The ground station: one or several links decoded live, every frame archived, a live web view per box.

    python -m ground.station LINK [LINK …] [--key FILE | --box SYSID:KEYFILE …] [--web HOST:PORT]
                             [--archive FILE | --no-archive] [--method M] [--window MIN] [--duration S]

LINK is a pymavlink connection string as for `ground.decode` (``udpin:0.0.0.0:14550``, ``tcp:…``, a serial
device); each is read by its own thread (`ground.live_link.LiveLink`) and the frames of all of them go through
one queue to the ingest thread, which archives every intact frame (`ground.archive`, default
`ground.archive.default_path`) and hands it to the fleet (`ground.web.fleet`): per system id a view with its
own key, plots, state and events. The web view (`ground.web.server`, aiohttp) is served at ``--web``
(default 127.0.0.1:8080: this machine only; another address only when given, and then anyone who reaches it
sees the telemetry — never a key: no key, passphrase or key file name is ever in a page or a message).
It is read-only: nothing is sent to a box from the station.

Keys: ``--box SYSID:KEYFILE`` (repeatable) gives a box its own key; ``--key FILE`` the key of every other
box. Frames are checked with their box's key; refused ones are counted on the box's page by reason (a frame
signed with another box's key is a bad signature there). Without any key nothing is verified and the page
says so.

The station runs until SIGINT / SIGTERM or ``--duration``; then it prints, per box, the frames, the losses and
the refusals, and what it archived. A queue of `MAX_QUEUED` frames between the links and the ingest thread
bounds the memory: frames beyond it are counted as dropped (shown on the page), never silently lost.
"""
from __future__ import annotations

if __name__ == "__main__":
    from fsw.startup import interrupt_quietly

    interrupt_quietly()

import asyncio  # noqa: E402
import queue  # noqa: E402
import signal  # noqa: E402
import sys  # noqa: E402
import threading  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Callable  # noqa: E402

from fsw.argtypes import ArgumentParser, check_paths_or_exit, finite_float, int_range, link_url  # noqa: E402
from fsw.telemetry.signing import KeyFileError, load_key  # noqa: E402

from fsw.telemetry.framing import Deframer  # noqa: E402

from .archive.bulk import decode_frames  # noqa: E402
from .archive.store import ArchiveFeed, default_path  # noqa: E402
from .live_link import LiveLink  # noqa: E402
from .web.boxview import ONBOARD_METHODS, RATE_METHOD_NAMES  # noqa: E402
from .web.fleet import Fleet  # noqa: E402

#: frames waiting between the links and the ingest thread
MAX_QUEUED = 200_000
#: frames the ingest thread takes from the queue at once (those waiting, up to this many)
INGEST_BATCH = 2000
#: batches waiting for the archive's thread (beyond: the ingest waits for it)
ARCHIVE_BATCHES_QUEUED = 256
#: the terminal's summary line every this many seconds
LINE_PERIOD_S = 10.0


class Ingest:
    """The link threads, the ingest thread and the archive's thread: frames from `urls` into `fleet` and the
    archive at `archive` (None: none). The ingest thread decodes the frames waiting, hands them to the archive's
    thread (its own SQLite connection: a commit's fsync never holds the view up) and to the fleet."""

    def __init__(self, fleet: Fleet, urls: list[str], *, archive: str | Path | None, baud: int = 115200,
                 say: Callable[[str], None] = print, clock: Callable[[], float] = time.time) -> None:
        self.fleet, self.urls, self.archive_path, self.baud, self.say, self.clock = \
            fleet, urls, archive, baud, say, clock
        self.queue: queue.Queue = queue.Queue(maxsize=MAX_QUEUED)
        #: batches (messages, receive times) for the archive's thread; None: the end
        self.to_archive: queue.Queue = queue.Queue(maxsize=ARCHIVE_BATCHES_QUEUED)
        self.stop_event = threading.Event()
        # opened now: an error before any thread starts; frames come raw, decoded by the ingest thread in bulk
        self.links = [LiveLink(url, baud, say, raw=True) for url in urls]
        self.threads: list[threading.Thread] = []
        self.archiver: threading.Thread | None = None
        self.feed: ArchiveFeed | None = None
        self.error: BaseException | None = None

    def start(self) -> None:
        if self.archive_path is not None:
            ready = threading.Event()
            self.archiver = threading.Thread(target=self._archive, args=(ready,), name="station-archive", daemon=True)
            self.archiver.start()
            ready.wait()
            if self.error is not None:
                raise self.error
        ingest = threading.Thread(target=self._ingest, name="station-ingest", daemon=True)
        ingest.start()
        self.threads.append(ingest)
        for link in self.links:
            th = threading.Thread(target=self._read, args=(link,), name=f"station-link {link.url}", daemon=True)
            th.start()
            self.threads.append(th)

    def _read(self, link: LiveLink) -> None:
        while not self.stop_event.is_set():
            batch = link.read()
            now_s = self.clock()
            for msg in batch:
                try:
                    self.queue.put_nowait((msg, now_s))
                except queue.Full:
                    with self.fleet.lock:
                        self.fleet.dropped += 1
        for msg in link.flush():
            self.queue.put((msg, self.clock()))

    def _archive(self, ready: threading.Event) -> None:
        try:
            self.feed = feed = ArchiveFeed(self.archive_path, self.say)
        except Exception as e:  # the archive cannot be opened: raised by start(), nothing read yet
            self.error = e
            ready.set()
            return
        ready.set()
        while True:
            try:
                batch = self.to_archive.get(timeout=0.1)
            except queue.Empty:
                batch = ()
            if batch is None:
                break
            if batch:
                feed.add_many(*batch)
            feed.tick()
            self.fleet.archive = {"frames": feed.frames, "error": feed.error, "lost": feed.lost}
        feed.close()
        self.fleet.archive = {"frames": feed.frames, "error": feed.error, "lost": feed.lost}

    def _ingest(self) -> None:
        decode = Deframer().decode
        archiving = self.archiver is not None
        done = False
        while not done:
            batch: list = []
            try:
                batch.append(self.queue.get(timeout=0.1))
                while len(batch) < INGEST_BATCH:     # and every frame waiting: decoded together
                    batch.append(self.queue.get_nowait())
            except queue.Empty:
                if not batch and self.stop_event.is_set() and not any(t.is_alive() for t in self.threads[1:]):
                    done = True  # the links have stopped: what they put last is taken below, then the end
                    while not self.queue.empty():
                        batch.append(self.queue.get_nowait())
            msgs = decode_frames([item for item, _ in batch], decode)
            if archiving and batch:  # every intact frame archived, whatever the view makes of it
                intact = [(m, t) for m, (_, t) in zip(msgs, batch) if m.get_type() != "BAD_DATA"]
                self.to_archive.put(([m for m, _ in intact], [t for _, t in intact]))
            for msg, (_, now_s) in zip(msgs, batch):
                try:
                    self.fleet.handle(msg, now_s)
                except Exception as e:  # noqa: BLE001 - a frame the view cannot take must not stop the station
                    self.fleet.failed(msg, e, self.say)
        if archiving:
            self.to_archive.put(None)

    def stop(self) -> None:
        """Stop reading; every frame read is still archived and handed to the fleet (the queue drained)."""
        self.stop_event.set()
        for th in self.threads[1:]:
            th.join()
        if self.threads:
            waiting = self.queue.qsize()
            if waiting > 10_000:
                self.say(f"archiving the {waiting} frames still waiting")
            self.threads[0].join()
        if self.archiver is not None:
            self.archiver.join()
        for link in self.links:
            link.close()


def parse_box(text: str) -> tuple[int, str]:
    """``SYSID:KEYFILE`` → (sysid, path); argparse type."""
    import argparse

    sysid, sep, path = text.partition(":")
    try:
        n = int(sysid)
    except ValueError:
        n = 0
    if not sep or not path or not 1 <= n <= 255:
        raise argparse.ArgumentTypeError(f"{text!r}: expected SYSID:KEYFILE with SYSID 1..255")
    return n, path


def parse_web(text: str) -> tuple[str, int]:
    """``HOST:PORT`` (port 0: any free one) → (host, port); argparse type."""
    import argparse

    host, sep, port = text.rpartition(":")
    if not sep or not host or not port.isdigit() or int(port) > 65535:
        raise argparse.ArgumentTypeError(f"{text!r}: expected HOST:PORT, e.g. 127.0.0.1:8080")
    return host.strip("[]"), int(port)


def summary_lines(fleet: Fleet) -> list[str]:
    out = []
    with fleet.lock:
        for sysid, box in sorted(fleet.boxes.items()):
            s = box.status()
            refused = ", ".join(f"{k} {n}" for k, n in sorted(box.rejected.items())) or "none"
            out.append(f"box {sysid}: {box.frames} frames, {box.authentic} authentic, lost {s['link']['lost']} "
                       f"({100 * (s['link']['loss_fraction'] or 0):.2f} %); refused: {refused}")
        if fleet.other_frames:
            out.append(f"frames of other system ids (not shown): {sum(fleet.other_frames.values())} from "
                       f"{', '.join(map(str, sorted(fleet.other_frames)))}")
        if fleet.dropped:
            out.append(f"frames dropped, the station could not keep up: {fleet.dropped}")
    return out


async def serve(fleet: Fleet, ingest: Ingest, host: str, port: int, *, duration_s: float | None,
                say: Callable[[str], None], quiet: bool) -> None:
    from aiohttp import web

    from .web.server import WebView

    ingest.start()  # the archive opened first: a failure stops the station before the page is served
    view = WebView(fleet)
    runner = web.AppRunner(view.app(), access_log=None)
    await runner.setup()
    site = web.TCPSite(runner, host, port)
    try:
        await site.start()
    except OSError as e:
        await runner.cleanup()
        raise OSError(f"--web {host}:{port}: {e.strerror or e}") from None
    bound = runner.addresses[0]
    say(f"web view: http://{host if ':' not in host else f'[{host}]'}:{bound[1]}/")
    if host not in ("127.0.0.1", "localhost", "::1"):
        say(f"the web view listens on {host}: anyone who reaches it sees the telemetry (read-only)")
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    start = loop.time()
    try:
        while not stop.is_set():
            left = LINE_PERIOD_S if duration_s is None else min(LINE_PERIOD_S, start + duration_s - loop.time())
            if left <= 0:
                break
            try:
                await asyncio.wait_for(stop.wait(), timeout=left)
            except asyncio.TimeoutError:
                if not quiet:
                    for line in summary_lines(fleet):
                        say(line)
    finally:
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.remove_signal_handler(sig)
        await runner.cleanup()


def main(argv: list[str] | None = None) -> int:
    methods = {name: value for value, name in RATE_METHOD_NAMES.items() if name in ONBOARD_METHODS}
    ap = ArgumentParser(prog="python -m ground.station", description=__doc__.splitlines()[0])
    ap.add_argument("links", nargs="+", type=link_url, metavar="LINK",
                    help="pymavlink connection strings: udpin:0.0.0.0:14550, tcp:HOST:PORT, a serial device")
    ap.add_argument("--baud", type=int_range(1), default=115200, help="serial baud rate (default 115200)")
    ap.add_argument("--key", metavar="FILE", help="mission key of every box not given its own with --box")
    ap.add_argument("--box", action="append", type=parse_box, default=[], metavar="SYSID:KEYFILE",
                    help="a box (system id) and its own key file; repeat for a fleet")
    ap.add_argument("--web", type=parse_web, default=("127.0.0.1", 8080), metavar="HOST:PORT",
                    help="where the web view listens (default 127.0.0.1:8080, this machine only; port 0: any)")
    archiving = ap.add_mutually_exclusive_group()
    archiving.add_argument("--archive", metavar="FILE",
                           help=f"archive every intact frame in this SQLite file (default {default_path()})")
    archiving.add_argument("--no-archive", action="store_true", help="do not archive the frames")
    ap.add_argument("--method", choices=sorted(methods, key=methods.get), default="kalman",
                    help="the onboard rate estimate plotted (default kalman: the flown filter)")
    ap.add_argument("--window", type=finite_float(0.5, 240), default=10.0, metavar="MIN",
                    help="minutes of telemetry the plots keep (default 10)")
    ap.add_argument("--duration", type=finite_float(0, min_exclusive=True), metavar="S",
                    help="stop after this many seconds")
    ap.add_argument("--quiet", action="store_true", help="no summary lines while running")
    args = ap.parse_args(argv)
    signal.signal(signal.SIGINT, signal.default_int_handler)  # modules loaded: Ctrl-C stops the station cleanly
    sysids = [s for s, _ in args.box]
    if len(set(sysids)) != len(sysids):
        ap.error("--box: a system id is given twice")
    archive = None if args.no_archive else (args.archive or default_path())
    if archive is not None and args.archive is None:
        try:
            Path(archive).parent.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            ap.error(f"--archive {archive}: cannot make its directory ({e.strerror or e}); --no-archive to run "
                     "without one")
    key_files = {"--key": args.key, **{f"--box {s}": p for s, p in args.box}}
    check_paths_or_exit(ap, inputs={**key_files, **{f"input {u}": u for u in args.links if Path(u).exists()}},
                        outputs={"--archive": archive})
    for url in args.links:
        if Path(url).is_file():
            ap.error(f"{url}: a file; the station reads live links (a .tlog: python -m ground.decode FILE)")
    try:
        default_key = load_key(args.key) if args.key else None
        keys = {s: load_key(p) for s, p in args.box}
    except KeyFileError as e:
        print(f"ground.station: {e}", file=sys.stderr)
        return 1
    fleet = Fleet(keys, default_key, method=methods[args.method], window_s=args.window * 60.0)

    def say(line: str) -> None:
        print(line, flush=True)

    try:
        ingest = Ingest(fleet, args.links, archive=archive, baud=args.baud, say=say)
    except (OSError, ValueError) as e:
        print(f"ground.station: {e}", file=sys.stderr)
        return 1
    try:
        asyncio.run(serve(fleet, ingest, *args.web, duration_s=args.duration, say=say, quiet=args.quiet))
    except (OSError, ValueError) as e:
        print(f"ground.station: {e}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        pass
    finally:
        signal.signal(signal.SIGINT, signal.SIG_IGN)  # every frame read is archived before the end
        ingest.stop()
    for line in summary_lines(fleet):
        print(line)
    if archive is not None:
        a = fleet.archive
        print(f"archived {a.get('frames', 0)} frames: {archive}")
        if a.get("error"):
            print(f"archive failed ({a['error']}): {a['lost']} frames not archived")
    return 0


if __name__ == "__main__":
    from fsw.startup import exit_with

    exit_with(main)
