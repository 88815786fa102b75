"""A campaign as data: a TOML file naming the scenario, its fixed parameters, the parameters to disperse and
their distributions, the number of runs, the seed and the figures to tabulate.

    name = "tumble-dispersed"
    scenario = "accuracy"            # one of bench.campaign.scenarios.SCENARIOS
    runs = 40
    seed = 7
    figures = ["boer_perp_rms_dps", "auto_full_rms_dps"]

    [fixed]                          # every run's
    mode = "undirected"
    dt_s = 1.0

    [disperse]                       # drawn per run
    sigma_uT = {dist = "uniform", low = 0.5, high = 1.5}
    Jx_kgm2 = {dist = "normal", mean = 175.0, sd = 10.0}
    body = {dist = "choice", values = ["asymmetric", "near_symmetric"]}

Distributions: ``uniform`` (low, high), ``normal`` (mean, sd), ``lognormal`` (median, sigma: of the
logarithm), ``loguniform`` (low, high), ``choice`` (values), ``integers`` (low, high: both included).
Run ``i`` is ``r00000``…; its seed is derive_seed(seed, id), its dispersed parameters are drawn from that seed
(stream 1; the scenario's own random numbers use stream 0), so that a run's parameters and results depend on
the campaign's seed and the run's id only.
"""
from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from bench.campaign.runs import Run, derive_seed

DISTRIBUTIONS = {"uniform": ("low", "high"), "normal": ("mean", "sd"), "lognormal": ("median", "sigma"),
                 "loguniform": ("low", "high"), "choice": ("values",), "integers": ("low", "high")}
KEYS = {"name", "scenario", "runs", "seed", "figures", "fixed", "disperse", "description"}
#: the stream of a run's seed its dispersed parameters are drawn from (the scenario uses the seed as it is)
PARAM_STREAM = 1


class CampaignFileError(Exception):
    """A campaign file that cannot be used: one line naming the file and the key."""


@dataclass(frozen=True)
class Dispersion:
    name: str
    dist: str
    args: dict

    def draw(self, rng: np.random.Generator):
        a = self.args
        if self.dist == "uniform":
            return float(rng.uniform(a["low"], a["high"]))
        if self.dist == "normal":
            return float(rng.normal(a["mean"], a["sd"]))
        if self.dist == "lognormal":
            return float(a["median"] * math.exp(rng.normal(0.0, a["sigma"])))
        if self.dist == "loguniform":
            return float(math.exp(rng.uniform(math.log(a["low"]), math.log(a["high"]))))
        if self.dist == "choice":
            return a["values"][int(rng.integers(len(a["values"])))]
        return int(rng.integers(a["low"], a["high"], endpoint=True))  # integers


@dataclass(frozen=True)
class CampaignFile:
    name: str
    scenario: str
    runs: int
    seed: int
    figures: tuple[str, ...]
    fixed: dict = field(default_factory=dict)
    disperse: tuple[Dispersion, ...] = ()
    description: str = ""

    def run_specs(self) -> list[Run]:
        """The campaign's runs: ids, seeds and parameters (fixed, then the drawn ones)."""
        out = []
        for i in range(self.runs):
            rid = f"r{i:05d}"
            seed = derive_seed(self.seed, rid)
            rng = np.random.default_rng(list(seed) + [PARAM_STREAM])
            params = dict(self.fixed)
            params.update({d.name: d.draw(rng) for d in self.disperse})
            out.append(Run(rid, seed, params))
        return out

    def config(self) -> dict:
        """What decides the results besides each run's seed and parameters (stored in the results file)."""
        return {"campaign": self.name, "scenario": self.scenario, "seed": self.seed, "figures": list(self.figures)}


def _check_dispersion(where: str, name: str, spec) -> Dispersion:
    if not isinstance(spec, dict) or "dist" not in spec:
        raise CampaignFileError(f"{where}: disperse.{name} needs a table with dist = one of {', '.join(DISTRIBUTIONS)}")
    dist = spec["dist"]
    if dist not in DISTRIBUTIONS:
        raise CampaignFileError(f"{where}: disperse.{name}: unknown dist {dist!r} (one of {', '.join(DISTRIBUTIONS)})")
    args = {k: v for k, v in spec.items() if k != "dist"}
    want = DISTRIBUTIONS[dist]
    if set(args) != set(want):
        raise CampaignFileError(f"{where}: disperse.{name}: {dist} takes {', '.join(want)} "
                                f"(got {', '.join(args) or 'none'})")
    if dist == "choice":
        if not isinstance(args["values"], list) or not args["values"]:
            raise CampaignFileError(f"{where}: disperse.{name}: values must be a non-empty list")
        return Dispersion(name, dist, args)
    for k, v in args.items():
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise CampaignFileError(f"{where}: disperse.{name}.{k} must be a finite number, not {v!r}")
    bad = (dist in ("uniform", "loguniform", "integers") and args["low"] >= args["high"]) or \
        (dist == "normal" and args["sd"] < 0) or (dist == "lognormal" and (args["median"] <= 0 or args["sigma"] < 0)) \
        or (dist == "loguniform" and args["low"] <= 0)
    if bad:
        raise CampaignFileError(f"{where}: disperse.{name}: {dist} with {args} is not a distribution "
                                "(low < high, sd and sigma >= 0, median and loguniform's low > 0)")
    if dist == "integers" and not all(isinstance(v, int) for v in args.values()):
        raise CampaignFileError(f"{where}: disperse.{name}: integers takes whole low and high")
    return Dispersion(name, dist, args)


def load(path) -> CampaignFile:
    """The campaign file at `path`, every key checked (CampaignFileError names the file and the key)."""
    from bench.campaign.scenarios import SCENARIOS
    where = str(path)
    try:
        data = tomllib.loads(Path(path).read_text(encoding="utf-8"))
    except OSError as e:
        raise CampaignFileError(f"{where}: {e.strerror or e}") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise CampaignFileError(f"{where}: not TOML ({e})") from None
    unknown = set(data) - KEYS
    if unknown:
        raise CampaignFileError(f"{where}: unknown key(s) {', '.join(sorted(unknown))} "
                                f"(known: {', '.join(sorted(KEYS))})")
    scenario = data.get("scenario")
    if scenario not in SCENARIOS:
        raise CampaignFileError(f"{where}: scenario must be one of {', '.join(SCENARIOS)}, not {scenario!r}")
    runs, seed = data.get("runs"), data.get("seed", 0)
    if isinstance(runs, bool) or not isinstance(runs, int) or not 1 <= runs <= 1_000_000:
        raise CampaignFileError(f"{where}: runs must be a whole number in 1 … 1,000,000, not {runs!r}")
    if isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed < 2 ** 63:
        raise CampaignFileError(f"{where}: seed must be a whole number in [0, 2^63), not {seed!r}")
    fixed, disperse = data.get("fixed", {}), data.get("disperse", {})
    if not isinstance(fixed, dict) or not isinstance(disperse, dict):
        raise CampaignFileError(f"{where}: fixed and disperse must be tables")
    both = set(fixed) & set(disperse)
    if both:
        raise CampaignFileError(f"{where}: {', '.join(sorted(both))} both fixed and dispersed")
    scn = SCENARIOS[scenario]
    unknown = (set(fixed) | set(disperse)) - set(scn.params)
    if unknown:
        raise CampaignFileError(f"{where}: scenario {scenario} has no parameter(s) {', '.join(sorted(unknown))} "
                                f"(it takes {', '.join(scn.params)})")
    figures = data.get("figures", list(scn.figures))
    if not isinstance(figures, list) or not figures or not all(isinstance(f, str) for f in figures):
        raise CampaignFileError(f"{where}: figures must be a non-empty list of names")
    name = data.get("name", Path(path).stem)
    if not isinstance(name, str) or not name:
        raise CampaignFileError(f"{where}: name must be a non-empty string")
    return CampaignFile(name, scenario, runs, seed, tuple(figures), dict(fixed),
                        tuple(_check_dispersion(where, k, v) for k, v in disperse.items()),
                        str(data.get("description", "")))
