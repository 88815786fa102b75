"""Monte-Carlo campaigns on dask.distributed: every run a task with its own seed and parameters.

- :mod:`bench.campaign.runs` — a run (id, seed, parameters); seeds derived from the campaign's seed and the
  run's id only, never from which worker ran it or when, so that the results do not depend on the number of
  workers (bit-identical per run);
- :mod:`bench.campaign.results` — the per-run results file (Parquet through pyarrow): appended as runs
  complete, resumable, the payloads exact;
- :mod:`bench.campaign.runner` — the runs on a local cluster (one worker process per core, embedded) or on an
  existing cluster by address; a progress bar; a lost worker's runs retried elsewhere; ``--rerun ID``;
- :mod:`bench.campaign.options` — the ``--workers/--scheduler/--results/--rerun`` options every benchmark takes;
- :mod:`bench.campaign.campaign_file` — a campaign as data (TOML): scenario, dispersions, runs, figures;
- :mod:`bench.campaign.scenarios` — the scenarios a campaign file can name;
- :mod:`bench.campaign.report` — the table of a results file's figures.

``python -m bench.campaign FILE.toml --workers 2 --results out.parquet`` runs a campaign file;
``python -m bench.campaign report out.parquet`` tabulates it. docs/campaigns.md has the rest.
"""
from bench.campaign.runs import Run, derive_seed
from bench.campaign.runner import CampaignError, run_campaign, rerun

__all__ = ["Run", "derive_seed", "run_campaign", "rerun", "CampaignError"]
