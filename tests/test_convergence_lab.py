"""lab.convergence: its statistics against plain references, and the recorded-problems part end to
end on two problems."""

from __future__ import annotations

import json
import math
from types import SimpleNamespace

import numpy as np
import pytest

from lab import convergence


def test_wilson_interval_matches_its_formula_and_contains_the_rate():
    for k, n in ((0, 10), (3, 10), (180, 205), (205, 205)):
        lo, hi = convergence.wilson(k, n)
        p, z = k / n, 1.96
        centre = (p + z * z / (2 * n)) / (1 + z * z / n)
        half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
        assert lo == pytest.approx(max(0.0, centre - half))
        assert hi == pytest.approx(min(1.0, centre + half))
        assert lo <= p <= hi


def test_longest_run_of_fallbacks():
    rng = np.random.default_rng(0)
    for _ in range(50):
        flags = rng.random(30) < 0.4
        ref = max((len(s) for s in "".join("1" if f else "0" for f in flags).split("0")), default=0)
        assert convergence._longest_run(flags) == ref


def test_problems_part_records_the_gap_to_the_reference(tmp_path, monkeypatch):
    """The merit gap of each setting to the best plan known is >= 0 up to the QPs' accuracy on
    these problems, the converged SQP's is at most the 2-QP one's, and a second `--only` run adds
    its setting to the record instead of replacing it."""
    monkeypatch.setattr(convergence, "OUT", tmp_path)
    args = SimpleNamespace(count=2, only=["2 it", "converged"])
    convergence.part_problems(args)
    rec = json.loads((tmp_path / "problems.json").read_text())
    assert rec["count"] == 2 and len(rec["reference"]["merit"]) == 2
    two, conv = rec["settings"]["2 it"], rec["settings"]["converged"]
    assert all(g >= -0.01 for g in two["gap"] + conv["gap"])
    assert conv["gap_median"] <= two["gap_median"] + 1e-9
    convergence.part_problems(SimpleNamespace(count=2, only=["3 it"]))
    rec = json.loads((tmp_path / "problems.json").read_text())
    assert set(rec["settings"]) == {"2 it", "converged", "3 it"}
