"""A campaign's run: its id, its seed and its parameters.

The seed is the entropy of a :class:`numpy.random.SeedSequence`: a list of non-negative integers. A
benchmark may keep the seeds it always had (bench.accuracy: the row's position and the run's number), a
campaign file's runs get :func:`derive_seed` of the campaign's seed and the run's id. Either way the seed is
a function of the campaign and the run alone: which worker runs it, and when, does not enter.
"""
from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field


@dataclass(frozen=True)
class Run:
    """One task of a campaign: `id` unique in the campaign, `seed` the entropy of its random numbers,
    `params` what the task needs besides (JSON-able: numbers, strings, booleans, lists, dicts)."""

    id: str
    seed: tuple[int, ...]
    params: dict = field(default_factory=dict)

    def __post_init__(self):
        if not self.id:
            raise ValueError("a run needs an id")
        if not self.seed or not all(isinstance(s, int) and s >= 0 for s in self.seed):
            raise ValueError(f"run {self.id}: the seed must be non-negative integers: {self.seed!r}")

    def seed_json(self) -> str:
        """The seed as JSON (a list of integers of any size): what the results file stores and compares."""
        return json.dumps(list(self.seed))

    def params_json(self) -> str:
        """The parameters as canonical JSON (sorted keys): what the results file stores and compares."""
        return json.dumps(self.params, sort_keys=True, allow_nan=True)


def derive_seed(campaign_seed: int, run_id: str) -> tuple[int, ...]:
    """The seed of run `run_id` of a campaign seeded `campaign_seed`: the campaign's seed and four 32-bit words
    of the id's SHA-256 (stable across Python versions and machines, unlike hash())."""
    digest = hashlib.sha256(run_id.encode()).digest()
    return (int(campaign_seed),) + tuple(int.from_bytes(digest[i:i + 4], "little") for i in range(0, 16, 4))
