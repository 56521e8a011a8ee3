"""`lab.diagnostics.best_of`: the validation-best seed of every N-subset of a screen arm's seeds,
checked against a brute-force reference on a synthetic report."""

from __future__ import annotations

import itertools
import json

import numpy as np
import pytest

from lab.diagnostics import best_of

SEEDS = {0: (0.41, 0.33), 1: (0.0, 0.0), 2: (0.55, 0.5), 3: (0.31, 0.25), 4: (0.55, 0.1)}


def test_n_one_is_the_arm_itself_and_larger_n_picks_by_validation():
    one = best_of.best_of(SEEDS, 1, 0.3)
    assert one["subsets"] == 5 and one["pass_share"] == pytest.approx(2 / 5)
    assert one["test_SR_mean"] == pytest.approx(np.mean([t for _, t in SEEDS.values()]))
    # every pair: the higher validation SR wins; the tie 2 / 4 (0.55) goes to the lower seed
    two = best_of.best_of(SEEDS, 2, 0.3)
    ref = []
    for a, b in itertools.combinations(range(5), 2):
        pick = a if SEEDS[a][0] >= SEEDS[b][0] else b
        ref.append(SEEDS[pick][1])
    assert two["subsets"] == 10
    assert two["test_SR_mean"] == pytest.approx(np.mean(ref))
    assert two["test_SR_lowest"] == min(ref)
    everything = best_of.best_of(SEEDS, 5, 0.3)
    assert everything["subsets"] == 1 and everything["test_SR_mean"] == 0.5  # seed 2, not 4
    with pytest.raises(ValueError, match="n = 6"):
        best_of.best_of(SEEDS, 6, 0.3)


def test_command_reads_a_screen_report_and_names_a_missing_arm(tmp_path, capsys):
    runs = [{"seed": s, "val": {"SR": v}, "test_SR": t} for s, (v, t) in SEEDS.items()]
    report = tmp_path / "screen.json"
    report.write_text(json.dumps({"pass": 0.3, "arms": {"a": {"runs": runs}}}))
    out = tmp_path / "bo.json"
    assert (
        best_of.main(["--report", str(report), "--arm", "a", "--n", "1", "3", "--out", str(out)])
        == 0
    )
    rec = json.loads(out.read_text())
    assert [r["n"] for r in rec["best_of"]] == [1, 3] and rec["seeds"]["2"]["val_SR"] == 0.55
    assert best_of.main(["--report", str(report), "--arm", "b", "--out", str(out)]) == 2
    assert "arm 'b'" in capsys.readouterr().err
