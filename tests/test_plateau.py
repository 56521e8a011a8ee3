"""`lab.diagnostics.plateau` on a tiny synthetic run folder: parsing of metrics.jsonl,
lift-off, the episode counts by start, the validation outcomes and the statistics."""

from __future__ import annotations

import json

import numpy as np
import pytest

from lab.diagnostics import plateau


def _row(it: int, success: float, explore_rows: float = 0.5, explore_success: float = 0.0):
    return {
        "iteration": it,
        "train_success": success,
        "train_explore_rows": explore_rows,
        "train_explore_success": explore_success,
        "train_collision_free": 0.5,
        "q_mean": -10.0 * it,
        "log_pi": -1.0 + 0.1 * it,
        "alpha": 1.0 / it,
        "mpc_reasons": {"solved": 3, "unsafe": 1},
    }


def _run(folder, rows, val=None):
    folder.mkdir(parents=True)
    train = {"tasks_per_iteration": 8, "posterior_episodes": 1, "updates_per_iteration": 500}
    (folder / "config.json").write_text(json.dumps({"seed": 3, "train": train}))
    lines = [json.dumps(r) for r in rows]
    lines.insert(1, "")  # a blank line is skipped
    (folder / "metrics.jsonl").write_text("\n".join(lines) + "\n")
    if val is not None:
        (folder / plateau.VAL8).parent.mkdir(parents=True)
        (folder / plateau.VAL8).write_text(json.dumps(val))


def test_run_summary_reads_a_synthetic_run(tmp_path):
    # 8 posterior rows per iteration, half from exploring starts: 4 from the task's start
    rows = [_row(1, 0.0, explore_success=0.25), _row(2, 0.0), _row(3, 0.5), _row(4, 0.25)]
    val = {
        "pooled": {"SR": {"mean": 0.25}},
        "records": [
            {
                "per_task": {
                    "SR": [[1.0, 0.0, 0.0, 0.0]],
                    "MGD": [[10.0, 20.0, 30.0, 40.0]],
                    "contact_step": [[-1, 5, 7, -1]],
                    "contact_person": [[0.0, 1.0, 0.0, 0.0]],
                    "reached_after_contact": [[0.0, 0.0, 0.0, 0.0]],
                }
            }
        ],
    }
    _run(tmp_path / "r", rows, val)
    s = plateau.run_summary(tmp_path / "r")
    assert s["seed"] == 3 and s["iterations"] == 4 and s["rows_per_iteration"] == 8
    assert s["liftoff_iteration"] == 3 and s["liftoff_grad_steps"] == 1500
    assert s["before"]["rows"] == {
        "task_start": 8,
        "task_start_success": 0,
        "explore": 8,
        "explore_success": 1,
    }
    assert s["after"]["rows"]["task_start_success"] == 3  # 2 of 4, then 1 of 4
    assert s["successes_from_start"] == 3 and s["iterations_with_success"] == 2
    assert s["after"]["train_success"] == pytest.approx(0.375)
    assert s["at_liftoff"]["q_mean"] == pytest.approx(-30.0)
    assert s["early"]["alpha_min"] == pytest.approx(0.25)
    assert s["early"]["alpha_min_iteration"] == 4
    assert s["mpc_reasons_before"] == {"calls": 8, "share_solved": 0.75, "share_unsafe": 0.25}
    v = s["val"]
    assert (v["goal"], v["person"], v["table"], v["timeout"]) == (1, 1, 1, 1)
    assert v["MGD_timeout"] == pytest.approx(40.0)
    assert v["median_first_contact_step"] == pytest.approx(6.0)
    assert s["val_SR"] == pytest.approx(0.25)
    assert plateau.window_success(s, 3, 4) == pytest.approx(0.375)
    assert plateau.window_success(s, 3, 5) is None  # the run stopped before iteration 5


def test_a_run_that_never_lifts_off(tmp_path):
    _run(tmp_path / "r", [_row(1, 0.0), _row(2, 0.0)])
    s = plateau.run_summary(tmp_path / "r")
    assert s["liftoff_iteration"] is None and s["after"] is None and s["val"] is None
    assert s["before"]["rows"]["task_start"] == 8
    assert plateau.liftoff_steps(s) == 1500  # counted after its budget of 2 x 500


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ('{"iteration": 1}\nnot json\n', "metrics.jsonl:2: not JSON"),
        ('{"iteration": "1"}\n', "metrics.jsonl:1: a row needs an integer 'iteration'"),
        ('{"iteration": 2}\n{"iteration": 1}\n', "iterations not strictly increasing"),
        ("\n", "no rows"),
    ],
)
def test_malformed_metrics_name_the_file_and_line(tmp_path, text, message):
    p = tmp_path / "metrics.jsonl"
    p.write_text(text)
    with pytest.raises(plateau.PlateauError, match=message):
        plateau.read_metrics(p)


def test_missing_records_give_a_one_line_error(tmp_path, capsys):
    assert plateau.main(["--root", str(tmp_path), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and "config.json: no such file" in err
    assert len(err.splitlines()) == 1


def test_statistics():
    up = plateau.spearman([1, 2, 3, 4, 5], [2, 4, 6, 8, 10], reps=200)
    assert up["rho"] == pytest.approx(1.0) and up["p"] < 0.05
    down = plateau.spearman([1, 2, 3, 4, 5], [5, 4, 3, 2, 1], reps=200)
    assert down["rho"] == pytest.approx(-1.0)
    # within strata: each stratum perfectly increasing although the pooled values are not
    strat = plateau.spearman(
        [1, 2, 3, 10, 11, 12], [30, 31, 32, 1, 2, 3], ["a"] * 3 + ["b"] * 3, reps=200
    )
    assert strat["rho"] == pytest.approx(1.0)
    assert plateau.spearman([1, 2, 3], [1, 2, 3]) is None  # too few seeds
    less = plateau.prob_less([1, 2], [3, 4, 4], reps=200)
    assert less["p_less"] == 1.0 and less["n"] == [2, 3]
    assert plateau.prob_less([1, 3], [3, 1], reps=200)["p_less"] == 0.5
    st = plateau.seed_stats([1.0, None, 3.0])
    assert st["n"] == 2 and st["mean"] == 2.0 and st["se"] == pytest.approx(1.0)
    assert plateau._ranks(np.array([5.0, 1.0, 5.0])).tolist() == [1.5, 0.0, 1.5]


def test_records_with_only_sr_and_cfr_per_task(tmp_path):
    # the committed evaluation records keep the per-task SR and CFR only: no outcomes, SR still read
    val = {
        "pooled": {"SR": {"mean": 0.25}},
        "records": [{"per_task": {"SR": [[1.0, 0.0, 0.0, 0.0]], "CFR": [[1.0, 0.0, 1.0, 1.0]]}}],
    }
    _run(tmp_path / "r", [_row(1, 0.0), _row(2, 0.5)], val)
    s = plateau.run_summary(tmp_path / "r")
    assert s["val"] is None and s["val_SR"] == pytest.approx(0.25)
    report = plateau.analyse(tmp_path, {"default": ["r"]})
    assert report["groups"]["default"]["val_SR"]["mean"] == pytest.approx(0.25)
    names = [f.name for f in plateau.write(report, tmp_path / "out")]
    assert "summary.json" in names and "outcomes.png" not in names
    assert not (tmp_path / "out" / "outcomes.png").exists()


def test_a_record_with_some_outcome_arrays_is_an_error(tmp_path):
    per_task = {"SR": [[1.0, 0.0]], "MGD": [[1.0, 2.0]], "contact_step": [[-1, 3]]}
    with pytest.raises(plateau.PlateauError, match="per_task lacks 'contact_person'"):
        plateau.val_outcomes({"records": [{"per_task": per_task}]})
