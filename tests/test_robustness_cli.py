"""lab.robustness: which evaluations it runs (`mpcpearl_jax.evaluate`'s arguments), which
records it keeps, and its errors."""

from __future__ import annotations

from pathlib import Path

from lab import robustness

ROOT = Path(__file__).resolve().parents[1]
HEADLINE = ROOT / "results" / "restaurant" / "mpc-pearl-eps0.2"


def test_runs_each_missing_record_once_in_order(tmp_path, monkeypatch, capsys):
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.json").write_text((HEADLINE / "config.json").read_text())
    kept = run / "eval" / "policy-val-delay3-seeds1-8"
    kept.mkdir(parents=True)
    (kept / "results.json").write_text("{}")
    calls = []
    monkeypatch.setattr(robustness, "evaluate", lambda *a: calls.append(a) or True)
    monkeypatch.chdir(tmp_path)
    perturbs = ["--perturb", "none", "--perturb", "delay=3", "--perturb", "speed=1.3"]
    assert robustness.main([str(run), *perturbs, "--gp-mpc"]) == 0
    outs = [a[2] for a in calls]
    assert outs == [
        run / "eval" / "policy-val-seeds1-8",
        run / "eval" / "policy-val-speed1.3-seeds1-8",
        Path("results") / "gp_mpc" / "perturbed" / "val-delay3-seeds1-8",
        Path("results") / "gp_mpc" / "perturbed" / "val-speed1.3-seeds1-8",
    ]
    assert calls[0] == (run, "none", outs[0], False)
    assert calls[2] == (None, "delay=3", outs[2], False)
    out = (
        capsys.readouterr().out
    )  # the run's delay 3 exists; GP-MPC's unperturbed is the main table's
    assert out.count("kept") == 2
    calls.clear()
    assert robustness.main([str(run), "--perturb", "delay=3", "--overwrite"]) == 0
    assert len(calls) == 1


def test_errors(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(robustness, "evaluate", lambda *a: False)
    assert robustness.main([str(HEADLINE), "--perturb", "delay=x"]) == 2
    assert "delay must be an int" in capsys.readouterr().err
    assert robustness.main([]) == 2
    assert robustness.main([str(tmp_path)]) == 2
    assert "not a run directory" in capsys.readouterr().err
    out = tmp_path / "o"
    monkeypatch.setattr(robustness, "record_path", lambda run, text: out / "results.json")
    assert robustness.main([str(HEADLINE), "--perturb", "delay=1"]) == 1
    assert "1 evaluation(s) failed" in capsys.readouterr().err


def test_a_failed_evaluation_is_one_line_naming_it(tmp_path, capsys):
    """The library's error (here: a bad perturbation reaching it) as one line on stderr."""
    assert not robustness.evaluate(HEADLINE, "delay=x", tmp_path / "o", False)
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"error: {HEADLINE} delay=x: ") and "\n" not in err
    assert not (tmp_path / "o").exists()


def test_all_lists_every_committed_policy_by_a_relative_path(monkeypatch):
    monkeypatch.chdir(ROOT)
    runs = robustness.committed_runs(ROOT / "results")
    assert Path("results/restaurant/mpc-pearl-eps0.2") in runs
    assert all(not r.is_absolute() for r in runs)
    assert Path("results/restaurant/grbal") not in runs  # a model, not a policy
