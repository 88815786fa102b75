"""The options every Monte-Carlo benchmark takes, and their campaign run:

``--workers N`` (local cluster size; default one per core), ``--scheduler ADDRESS`` (an existing cluster:
tcp://HOST:8786), ``--results FILE`` (the per-run results, Parquet: resumable), ``--rerun ID`` (one run alone,
compared with its stored row), ``--no-progress``.
"""
from __future__ import annotations

import argparse
import re
import sys
from collections.abc import Callable

from bench.campaign.runner import CampaignError, default_workers, rerun, run_campaign
from bench.campaign.runs import Run
from fsw.argtypes import int_range

_ADDRESS = re.compile(r"^(tcp|tls|inproc|ucx|ws|wss)://\S+$")


def _address(text: str) -> str:
    if not _ADDRESS.match(text):
        raise argparse.ArgumentTypeError(f"{text!r} is not a scheduler address such as tcp://HOST:8786")
    return text


def add_arguments(ap: argparse.ArgumentParser) -> None:
    g = ap.add_argument_group("campaign (docs/campaigns.md)")
    g.add_argument("--workers", type=int_range(1, 1024), default=None, metavar="N",
                   help=f"worker processes of the local cluster (default: one per core, {default_workers()} here; "
                        "1: the runs in this process)")
    g.add_argument("--scheduler", type=_address, default=None, metavar="ADDRESS",
                   help="run on the existing Dask cluster at ADDRESS (tcp://HOST:8786) instead")
    g.add_argument("--results", metavar="FILE.parquet", default=None,
                   help="keep every run's seed, parameters and result in FILE as it completes; a run already "
                        "in FILE is not run again (resume)")
    g.add_argument("--rerun", metavar="ID", default=None,
                   help="run ID alone, here, and show it matches its row in --results FILE")
    g.add_argument("--no-progress", action="store_true", help="no progress bar")


def outputs(args: argparse.Namespace) -> dict:
    """The campaign's output (the results file), for the benchmark's check_paths_or_exit with its own."""
    return {"--results": args.results}


def check(ap: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """The campaign options' usage errors (exit status 2); the results file's path is checked by the benchmark
    with its other outputs (`outputs`)."""
    if args.scheduler and args.workers is not None:
        ap.error("--workers sizes the local cluster; with --scheduler the cluster's own workers run the campaign")
    if args.rerun is not None and args.results is None:
        ap.error("--rerun needs the --results FILE that holds the run")


def execute(ap: argparse.ArgumentParser, args: argparse.Namespace, fn: Callable, runs: list[Run], config: dict,
            *, name: str, on_result: Callable | None = None, elapsed_s: dict | None = None) -> list | int:
    """The campaign of `runs` as the options ask: the results in the order of `runs`, or, for --rerun or a
    failure, the exit status (the message printed)."""
    try:
        if args.rerun is not None:
            same, line = rerun(fn, runs, args.rerun, config=config, results=args.results)
            print(line)
            return 0 if same else 1
        return run_campaign(fn, runs, config=config, name=name, workers=args.workers, scheduler=args.scheduler,
                            results=args.results, progress=not args.no_progress and sys.stderr.isatty(),
                            on_result=on_result, elapsed_s=elapsed_s)
    except CampaignError as e:
        print(f"{ap.prog}: {e}", file=sys.stderr)
        return 1
