"""An --out that ends in "/" names a folder, there or not yet: the commands that write one file
(`experiments.export`, `lab.diagnostics.best_of`) write their default file name into it, never a
file named like the folder."""

from __future__ import annotations

import json
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
HEADLINE = ROOT / "results/restaurant/mpc-pearl-eps0.2"


def test_export_into_a_new_folder_named_with_a_slash(tmp_path, capsys):
    from experiments import export as cli

    folder = tmp_path / "exports"
    assert cli.main([str(HEADLINE), "--out", f"{folder}/", "--platforms", "cpu"]) == 0
    assert folder.is_dir(), "a file named like the folder"
    assert sorted(p.name for p in folder.iterdir()) == ["policy.export", "policy.export.json"]
    assert not (tmp_path / "exports.json").exists()
    assert str(folder / "policy.export") in capsys.readouterr().out


def test_best_of_into_a_new_folder_named_with_a_slash(tmp_path):
    from lab.diagnostics import best_of

    runs = [{"seed": s, "val": {"SR": 0.5 + s / 10}, "test_SR": 0.4} for s in range(3)]
    report = tmp_path / "screen.json"
    report.write_text(json.dumps({"pass": 0.3, "arms": {"a": {"runs": runs}}}))
    folder = tmp_path / "out"
    argv = ["--report", str(report), "--arm", "a", "--n", "1", "--out", f"{folder}/"]
    assert best_of.main(argv) == 0
    assert folder.is_dir() and [p.name for p in folder.iterdir()] == [best_of.OUT.name]
