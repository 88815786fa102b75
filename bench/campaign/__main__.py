"""python -m bench.campaign: a campaign file's runs, or the table of a results file.

    python -m bench.campaign campaigns/tumble_dispersed.toml --workers 2 --results out.parquet
    python -m bench.campaign campaigns/tumble_dispersed.toml --scheduler tcp://HOST:8786 --results out.parquet
    python -m bench.campaign campaigns/tumble_dispersed.toml --results out.parquet --rerun r00007
    python -m bench.campaign report out.parquet [--plot out.png] [--json out.json]
    python -m bench.campaign scaling campaigns/calibration_hosts.toml [--runs N]   # docs/campaigns.md's figures
"""
from __future__ import annotations

import json
import sys

from bench.campaign import campaign_file as cf
from bench.campaign import options, report
from bench.campaign.results import ResultsError
from bench.campaign.scenarios import SCENARIOS
from fsw.argtypes import ArgumentParser, check_paths_or_exit
from fsw.files import write_atomic


def _report_main(argv: list[str]) -> int:
    ap = ArgumentParser(prog="python -m bench.campaign report", description="the table of a campaign's results file")
    ap.add_argument("results", metavar="FILE.parquet")
    ap.add_argument("--figures", default=None, help="comma-separated figures (default: the campaign file's)")
    ap.add_argument("--plot", metavar="FILE.png", help="a histogram per figure")
    ap.add_argument("--json", metavar="FILE", help="the statistics as JSON")
    args = ap.parse_args(argv)
    check_paths_or_exit(ap, inputs={"results": args.results}, outputs={"--plot": args.plot, "--json": args.json})
    figures = [f.strip() for f in args.figures.split(",") if f.strip()] if args.figures else None
    try:
        config, stats, values = report.from_file(args.results, figures)
    except ResultsError as e:
        print(f"{ap.prog}: {e}", file=sys.stderr)
        return 1
    print(f"campaign {config.get('campaign', config.get('benchmark', '?'))} ({args.results})")
    print(report.markdown(stats))
    if args.plot:
        report.plot(values, args.plot, str(config.get("campaign", "")))
        print(f"wrote {args.plot}")
    if args.json:
        write_atomic(args.json, json.dumps({"config": config, "figures": stats}, indent=1))
        print(f"wrote {args.json}")
    return 0


def _scaling_main(argv: list[str]) -> int:
    from bench.campaign import scaling
    from fsw.argtypes import int_range
    ap = ArgumentParser(prog="python -m bench.campaign scaling", description=scaling.__doc__.splitlines()[0])
    ap.add_argument("campaign", metavar="FILE.toml")
    ap.add_argument("--runs", type=int_range(2, 100000), default=None, help="its first N runs (default all)")
    ap.add_argument("--tasks", type=int_range(1, 100000), default=200, help="empty tasks at once (default 200)")
    args = ap.parse_args(argv)
    try:
        cf.load(args.campaign)
    except cf.CampaignFileError as e:
        ap.error(str(e))
    scaling.main(args.campaign, args.runs, args.tasks)
    return 0


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["report"]:
        return _report_main(argv[1:])
    if argv[:1] == ["scaling"]:
        return _scaling_main(argv[1:])
    ap = ArgumentParser(prog="python -m bench.campaign", description=__doc__.splitlines()[0],
                        epilog="python -m bench.campaign report FILE.parquet: the table of a results file")
    ap.add_argument("campaign", metavar="FILE.toml", help="the campaign file (scenarios: " + ", ".join(SCENARIOS) + ")")
    options.add_arguments(ap)
    args = ap.parse_args(argv)
    options.check(ap, args)
    check_paths_or_exit(ap, inputs={"campaign": args.campaign}, outputs=options.outputs(args))
    try:
        camp = cf.load(args.campaign)
    except cf.CampaignFileError as e:
        ap.error(str(e))
    runs = camp.run_specs()
    got = options.execute(ap, args, SCENARIOS[camp.scenario].task, runs, camp.config(), name=camp.name)
    if isinstance(got, int):
        return got
    stats = {f: report.statistics(report.np.array([_number(g.get(f)) for g in got], float)) for f in camp.figures}
    print(f"campaign {camp.name}: {len(runs)} runs of {camp.scenario}" +
          (f", results in {args.results}" if args.results else ""))
    print(report.markdown(stats))
    return 0


def _number(v) -> float:
    try:
        return float(v)
    except (TypeError, ValueError):
        return float("nan")


if __name__ == "__main__":
    from fsw.startup import exit_with

    exit_with(main)
