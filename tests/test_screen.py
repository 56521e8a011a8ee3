"""lab.screen: a screen file's arms over its seeds, trained through the campaign, and its
report (lift-off, seed statistics, IQM and probability of improvement) from the run folders;
`screen.render_screen`: its table."""

from __future__ import annotations

import json
import math
import re
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.stats import trim_mean

from lab import campaign, screen
from lab.tables.statistics import Records

VAL = "eval/policy-val-seeds1-8"
EVALUATE = [
    ["--split", "val", "--task-seeds", "1-8", "--figures", "none", "--out", "{results}/" + VAL]
]


@pytest.fixture(autouse=True)
def _quick(monkeypatch):
    """Few bootstrap samples (the statistics are checked against references, not the samples);
    an idle machine for the campaign; no training process is ever started."""
    monkeypatch.setattr(screen, "REPS", 200)
    monkeypatch.setattr(campaign.os, "getloadavg", lambda: (0.0, 0.0, 0.0))

    def no_child(cmd):
        raise AssertionError(f"a process was started: {cmd}")

    monkeypatch.setattr(campaign, "run_child", no_child)


def make_run(
    folder: Path,
    success: list[float],
    val_sr: float,
    test_sr: float = 0.5,
    updates: int = 10,
    wall: list[float] | None = None,
    spl: float | None = None,
    evaluated: bool = True,
) -> Path:
    """A finished run folder: config.json, one metrics.jsonl row per iteration (`success` its
    train_success, `wall` its wall_s, 30 s per iteration by default), results.json and the
    pooled validation record (if `evaluated`)."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "config.json").write_text(json.dumps({"train": {"updates_per_iteration": updates}}))
    wall = wall or [30.0 * (i + 1) for i in range(len(success))]
    rows = [
        {"iteration": i + 1, "train_success": s, "wall_s": w, "train_s": w - 1}
        for i, (s, w) in enumerate(zip(success, wall, strict=True))
    ]
    (folder / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    (folder / "results.json").write_text(json.dumps({"test_adapt": {"SR": test_sr}}))
    pooled = {
        "SR": val_sr,
        "CFR": 0.9,
        "TT": 80 - 10 * val_sr,
        "SPL": val_sr / 2 if spl is None else spl,
    }
    if not evaluated:
        return folder
    rec = folder / VAL / "results.json"
    rec.parent.mkdir(parents=True, exist_ok=True)
    rec.write_text(json.dumps({"pooled": {k: {"mean": v, "se": 0.0} for k, v in pooled.items()}}))
    return folder


def write_screen(path: Path, arms: dict, seeds=(0, 1), **over) -> Path:
    raw = {
        "name": "t",
        "results": "res/screen",
        "seeds": list(seeds),
        "trainer": "restaurant",
        "common_argv": ["--no-progress"],
        "evaluate": EVALUATE,
        "baseline": next(iter(arms), "base"),
        "arms": arms,
        **over,
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(raw))
    return path


# ---------------------------------------------------------------- lift-off


def test_liftoff_is_the_first_iteration_with_a_training_success():
    rows = [{"iteration": i + 1, "train_success": s, "wall_s": 60.0 * (i + 1)} for i, s in
            enumerate([0.0, 0.0, 0.25, 0.0, 0.5])]  # fmt: skip
    lifted, budget = screen.liftoff(rows, 500)
    assert lifted == {"iteration": 3, "grad_steps": 1500, "minutes": 3.0}
    assert budget == {"iteration": 5, "grad_steps": 2500, "minutes": 5.0}


def test_a_run_that_never_lifts_off_is_censored_at_its_budget():
    rows = [{"iteration": i + 1, "train_success": 0.0, "wall_s": 30.0 * (i + 1)} for i in range(4)]
    lifted, budget = screen.liftoff(rows, 100)
    assert lifted is None
    assert budget == {"iteration": 4, "grad_steps": 400, "minutes": 2.0}


def test_wall_time_is_cumulative_and_a_restarted_clock_adds_up():
    """wall_s runs on from the run's start; in old records a resumed process restarted it."""
    rows = [
        {"iteration": 1, "train_success": 0.0, "wall_s": 60.0},
        {"iteration": 2, "train_success": 0.0, "wall_s": 120.0},
        {"iteration": 3, "train_success": 0.0, "wall_s": 30.0},  # resumed: a new clock
        {"iteration": 4, "train_success": 1.0, "wall_s": 90.0},
    ]
    lifted, budget = screen.liftoff(rows, 10)
    assert lifted["minutes"] == pytest.approx((120 + 90) / 60)
    assert lifted["grad_steps"] == 40 and budget["iteration"] == 4


def test_liftoff_curve_counts_censored_runs_as_not_lifted_off():
    curve = screen.liftoff_curve([None, 300, 100, None, 100, 200])
    assert curve == [[100, 2 / 6], [200, 3 / 6], [300, 4 / 6]]
    assert screen.curve_median(curve) == 200  # half of the six by step 200
    assert screen.curve_median(screen.liftoff_curve([None, None, 5])) is None
    assert screen.liftoff_curve([None, None]) == []


# ---------------------------------------------------------------- rliable statistics


def test_iqm_is_the_quartile_trimmed_mean_with_a_reproducible_interval():
    x = [0.0, 0.1, 0.55, 0.3, 0.9, 0.05, 0.0, 0.6]  # 8 runs: the IQM is the middle 4's mean
    state = np.random.get_state()  # noqa: NPY002 (rliable draws from the global generator)
    r = screen.iqm(x, reps=300)
    assert r["value"] == pytest.approx(trim_mean(x, 0.25))
    assert r["value"] == pytest.approx(np.mean(sorted(x)[2:6]))
    lo, hi = r["ci"]
    assert lo <= r["value"] <= hi and 0.0 <= lo and hi <= 0.9
    assert screen.iqm(x, reps=300) == r  # the same samples every time
    assert screen.iqm(x, reps=300, seed=1)["ci"] != r["ci"]
    after = np.random.get_state()  # noqa: NPY002
    assert np.all(after[1] == state[1])  # the global generator is left as it was


def test_probability_of_improvement_is_the_pairwise_win_rate():
    x = [0.5, 0.2, 0.2, 0.9, 0.0]
    y = [0.2, 0.3, 0.0, 0.0, 0.6, 0.1]  # another number of runs; ties count half
    ref = np.mean([(a > b) + 0.5 * (a == b) for a in x for b in y])
    r = screen.improvement(x, y, reps=300)
    assert r["value"] == pytest.approx(ref)
    lo, hi = r["ci"]
    assert 0.0 <= lo <= r["value"] <= hi <= 1.0
    assert screen.improvement(y, x, reps=300)["value"] == pytest.approx(1 - ref)
    assert screen.improvement(x, x, reps=300)["value"] == 0.5


# ---------------------------------------------------------------- the screen file


GOOD_ARMS = {"base": {"argv": []}, "explore": {"argv": ["--set", "train.explore_start_share=0.5"]}}
MATCHED = {  # an arm trained for as many iterations as the reused runs of `base`
    "base": {"argv": ["--minutes", "24"], "runs": {"0": "r/a", "1": "r/b"}},
    "m": {"argv": ["--set", "train.pipeline=true"], "iterations_of": "base"},
}


@pytest.mark.parametrize(
    "over, match",
    [
        ({"seed": [0]}, r"unknown key\(s\) \['seed'\]"),
        ({"arms": {"a/b": {}}}, r"'arms': 'a/b' is not a folder name"),
        ({"arms": {".x": {}}}, r"'arms': '.x' is not a folder name"),
        ({"arms": {"base": {"argv": [], "run": {}}}}, r"arms.base: unknown key\(s\) \['run'\]"),
        ({"arms": {"base": {"argv": "--x"}}}, r"arms.base: 'argv' must be a list of strings"),
        ({"arms": {"base": {"argv": ["--seed", "3"]}}}, "arms.base: 'argv' must not hold --seed"),
        ({"common_argv": ["--out", "x"]}, "'common_argv' must not hold --out"),
        ({"arms": {}}, "'arms' must be a non-empty object"),
        ({"baseline": "nosuch"}, "'baseline' must name an arm"),
        ({"seeds": [0, 0]}, "'seeds' must be a non-empty list of unique integers"),
        ({"seeds": [-1]}, "'seeds' must be"),
        ({"seeds": [True]}, "'seeds' must be"),
        ({"seeds": []}, "'seeds' must be"),
        ({"name": "a b"}, "'name' must be a folder name"),
        ({"trainer": "grbal"}, "'trainer' must be one of"),
        ({"evaluate": []}, "'evaluate' must be a non-empty list"),
        ({"evaluate": [["--split", "val", "--out", "x/y"]]}, r"'evaluate'\[0\] must give --out"),
        ({"evaluate": [["--split", "test", "--out", "{results}/e"]]}, "must be a --split val"),
        (
            {"arms": {"base": {"runs": {"0": "r/a"}}}},
            r"arms.base: 'runs': no run folder for seed\(s\) \[1\]",
        ),
        (
            {"arms": {"base": {"runs": {"0": "r/a", "1": "r/b", "2": "r/c"}}}},
            r"arms.base: 'runs': '2' is not one of the screen's seeds",
        ),
        ({"arms": {"base": {"runs": {"0": "r/a", "1": 3}}}}, "seed 1: the run folder must be"),
        (
            {"arms": {"base": {"argv": []}, "m": {"argv": [], "iterations_of": "base"}}},
            r"arms.m: 'iterations_of' must name an arm with 'runs' \(\[\]\), got 'base'",
        ),
        (
            {"arms": {**MATCHED, "m": {"argv": [], "iterations_of": "nosuch"}}},
            "arms.m: 'iterations_of' must name an arm with 'runs'",
        ),
        (
            {"arms": {**MATCHED, "m": {"argv": ["--iterations", "3"], "iterations_of": "base"}}},
            "arms.m: with 'iterations_of' its argv and common_argv must not hold --iterations",
        ),
        (
            {"arms": MATCHED, "common_argv": ["--minutes=24"]},
            "arms.m: with 'iterations_of' its argv and common_argv must not hold --minutes",
        ),
        (
            {"arms": {**MATCHED, "m": {"runs": {"0": "a", "1": "b"}, "iterations_of": "base"}}},
            "arms.m: 'iterations_of' is for a trained arm, not with 'runs'",
        ),
    ],
)
def test_bad_screen_files_name_the_file_and_field(tmp_path, over, match):
    over = dict(over)
    arms = over.pop("arms", GOOD_ARMS)
    path = write_screen(tmp_path / "s.json", arms, **{"baseline": "base", **over})
    with pytest.raises(ValueError, match=match) as e:
        screen.load_screen(path)
    assert "\n" not in str(e.value) and str(e.value).startswith(str(path))


def test_a_missing_or_unreadable_screen_file(tmp_path):
    with pytest.raises(ValueError, match="not a readable JSON screen"):
        screen.load_screen(tmp_path / "nosuch.json")
    path = write_screen(tmp_path / "s.json", GOOD_ARMS)
    raw = json.loads(path.read_text())
    del raw["baseline"]
    path.write_text(json.dumps(raw))
    with pytest.raises(ValueError, match=r"missing key\(s\) \['baseline'\]"):
        screen.load_screen(path)


def test_trained_arms_become_campaign_entries(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    path = write_screen(tmp_path / "s.json", {**GOOD_ARMS, "base": {"runs": {"0": "a", "1": "b"}}})
    s = screen.load_screen(path)
    runs = screen.campaign_runs(s)
    assert runs["base"] == []  # reused: nothing to train
    assert [r.name for r in runs["explore"]] == ["t-explore-s0", "t-explore-s1"]
    r = runs["explore"][1]
    assert r.argv == ("--set", "train.explore_start_share=0.5", "--no-progress", "--seed", "1")
    assert r.results == Path("res/screen/explore-s1") and r.trainer == "restaurant"
    (ev,) = r.evaluate  # the screen's flags as mpcpearl_jax.evaluate's keyword arguments
    assert ev.arguments == {
        "run": "res/screen/explore-s1",
        "split": "val",
        "task_seeds": "1-8",
        "figures": "none",
        "out": "res/screen/explore-s1/" + VAL,
    }
    assert s.folder("base", 1) == Path("b") and s.validation == VAL + "/results.json"


def test_an_arm_matched_to_reused_runs_trains_each_seed_for_their_iterations(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    make_run(tmp_path / "r/a", [0.0] * 7, 0.5)
    make_run(tmp_path / "r/b", [0.0] * 4, 0.5)
    s = screen.load_screen(write_screen(tmp_path / "s.json", MATCHED, baseline="base"))
    runs = screen.campaign_runs(s)
    assert runs["base"] == []
    assert [r.argv for r in runs["m"]] == [
        ("--set", "train.pipeline=true", "--no-progress", "--iterations", "7", "--seed", "0"),
        ("--set", "train.pipeline=true", "--no-progress", "--iterations", "4", "--seed", "1"),
    ]
    (tmp_path / "r/b/metrics.jsonl").write_text("")  # a reused run with no iteration: named
    with pytest.raises(ValueError, match=r"r/b/metrics.jsonl: no finished iteration to match"):
        screen.campaign_runs(s)
    (tmp_path / "r/b/metrics.jsonl").unlink()
    with pytest.raises(ValueError, match=r"r/b/metrics.jsonl: no finished iteration to match"):
        screen.campaign_runs(s)


# ---------------------------------------------------------------- the report


def _screen_folders(root: Path) -> Path:
    """A screen of two arms over seeds 0-3: `base` reuses runs/b<seed>; `new` trained three
    seeds so far (seed 3 is missing its validation record)."""
    base = {
        0: ([0, 0, 1, 0], 0.4, 0.5),
        1: ([0, 0, 0, 0], 0.0, 0.0),
        2: ([0, 1, 1, 1], 0.6, 0.25),
        3: ([0, 0, 0, 0.5], 0.2, 0.5),
    }
    for seed, (succ, val, test) in base.items():
        make_run(root / f"runs/b{seed}", succ, val, test)
    for seed, (succ, val) in enumerate([([1, 1, 1, 1], 0.7), ([0, 1, 1, 1], 0.5), ([0] * 4, 0.1)]):
        make_run(root / f"res/screen/new-s{seed}", succ, val, 0.5)
    make_run(root / "res/screen/new-s3", [0] * 4, 0.3, evaluated=False)
    arms = {"base": {"runs": {str(s): f"runs/b{s}" for s in base}}, "new": {"argv": ["--x"]}}
    return write_screen(root / "lab/screens/t.json", arms, seeds=range(4))


def test_the_report_is_made_from_the_finished_run_folders(tmp_path):
    s = screen.load_screen(_screen_folders(tmp_path))
    rep = screen.screen_report(s, tmp_path)
    base, new = rep["arms"]["base"], rep["arms"]["new"]
    assert base["finished"] == [0, 1, 2, 3] and base["missing"] == {}
    assert new["finished"] == [0, 1, 2]
    assert new["missing"] == {"3": {"run": "res/screen/new-s3", "lacks": [VAL + "/results.json"]}}
    # lift-off: base seed 0 at iteration 3 (30 gradient steps, 1.5 minutes); seed 1 never
    lifts = [r["liftoff"] for r in base["runs"]]
    assert lifts[0] == {"iteration": 3, "grad_steps": 30, "minutes": 1.5} and lifts[1] is None
    assert base["lifted"] == 3 and new["lifted"] == 2
    assert base["liftoff"]["grad_steps"]["curve"] == [[20, 0.25], [30, 0.5], [40, 0.75]]
    assert base["liftoff"]["grad_steps"]["median"] == 30
    assert base["liftoff"]["grad_steps"]["budget"] == 40
    assert new["liftoff"]["minutes"]["median"] == 1.0  # seeds 0 and 1 of 3 by minute 1
    # validation SR over seeds; passes need val SR and test SR >= 0.3
    vals = [0.4, 0.0, 0.6, 0.2]
    se = math.sqrt(np.var(vals, ddof=1) / 4)
    assert base["val"]["SR"] == pytest.approx({"mean": 0.3, "se": se, "worst": 0.0})
    assert base["val"]["TT"]["worst"] == 80.0  # the longest time is the worst
    assert base["passed"] == 1 and new["passed"] == 2
    assert base["iqm"]["SR"]["value"] == pytest.approx(trim_mean(vals, 0.25))
    assert base["improvement"]["SR"] is None  # the baseline against itself
    ref = np.mean([(a > b) + 0.5 * (a == b) for a in [0.7, 0.5, 0.1] for b in vals])
    assert new["improvement"]["SR"]["value"] == pytest.approx(ref)
    assert new["improvement"]["SPL"]["baseline_scores"] == [v / 2 for v in vals]
    assert rep["bootstrap"] == {"reps": 200, "seed": screen.BOOTSTRAP_SEED}


def test_a_report_reuses_an_earlier_bootstrap_only_for_the_same_scores(tmp_path, monkeypatch):
    s = screen.load_screen(_screen_folders(tmp_path))
    first = json.loads(json.dumps(screen.screen_report(s, tmp_path)))
    calls = []
    real = screen.iqm
    monkeypatch.setattr(screen, "iqm", lambda x: calls.append(x) or real(x))
    assert screen.screen_report(s, tmp_path, first) == first and calls == []
    make_run(tmp_path / "res/screen/new-s3", [0] * 4, 0.3)  # seed 3 of `new` finishes
    again = screen.screen_report(s, tmp_path, first)
    assert calls == [[0.7, 0.5, 0.1, 0.3], [0.35, 0.25, 0.05, 0.15]]  # SR, SPL of `new` only
    assert again["arms"]["base"] == first["arms"]["base"]
    monkeypatch.setattr(screen, "REPS", 300)  # other samples: nothing is reused
    screen.screen_report(s, tmp_path, first)
    assert len(calls) == 6


# ---------------------------------------------------------------- the command


def test_report_only_trains_nothing_and_names_the_missing_seeds(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    path = _screen_folders(tmp_path)
    assert screen.main([str(path), "--report-only"]) == 0
    out = capsys.readouterr().out
    assert "base: 4/4 seeds finished" in out
    assert f"new: 3/4 seeds finished; missing s3 (res/screen/new-s3: no {VAL}/results.json)" in out
    rep = json.loads((tmp_path / "res/screen/t.json").read_text())
    assert rep["arms"]["new"]["finished"] == [0, 1, 2]
    assert (tmp_path / "res/screen/t-liftoff.png").stat().st_size > 0
    assert not (tmp_path / campaign.WORK).exists()
    (tmp_path / "res/screen/new-s2/metrics.jsonl").unlink()  # no training record: not trained
    assert screen.main([str(path), "--report-only"]) == 0
    out = capsys.readouterr().out
    assert "new: 2/4 seeds finished; missing s3 (" in out and "; not trained: s2\n" in out


def test_dry_run_lists_the_campaign_entries_with_their_seeds(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    path = write_screen(tmp_path / "s.json", GOOD_ARMS, seeds=[3, 7], baseline="base")
    assert screen.main([str(path), "--dry-run", "--arms", "explore"]) == 0
    out = capsys.readouterr().out
    assert (
        "[screen] t-explore-s3: experiments.restaurant --set train.explore_start_share=0.5 "
        "--no-progress --seed 3 -> res/screen/explore-s3" in out
    )
    assert "t-explore-s7: new, 2 process(es)" in out and "t-base-" not in out
    assert "--seed 7 --out runs/campaign/t-explore-s7" in out
    assert not (tmp_path / "res").exists() and not (tmp_path / campaign.WORK).exists()
    assert screen.main([str(path), "--dry-run", "--arms", "nosuch"]) == 2
    assert "no arm named ['nosuch']" in capsys.readouterr().err


def test_a_retired_arm_is_reported_from_its_folders_and_never_trained(
    tmp_path, monkeypatch, capsys
):
    """An arm whose argv sets an option since removed (`config.REMOVED_OPTIONS`), marked
    `retired`: no campaign entry, no config rebuilt from its argv, its run folders reported."""
    monkeypatch.chdir(tmp_path)
    for seed in (0, 1):
        make_run(tmp_path / f"res/screen/old-s{seed}", [0, 1], 0.2 + seed / 10)
    arms = {
        **GOOD_ARMS,
        "old": {"argv": ["--set", "pearl.n_step=3"], "retired": "pearl.n_step"},
    }
    path = write_screen(tmp_path / "s.json", arms, baseline="base")
    s = screen.load_screen(path)
    assert s.arms["old"].retired == "pearl.n_step" and screen.campaign_runs(s)["old"] == []
    screen.check_reused(s, ["old"])  # nothing to rebuild (its argv no longer builds a config)
    assert screen.main([str(path), "--dry-run", "--arms", "old", "explore"]) == 0
    out = capsys.readouterr().out
    assert "old: retired (pearl.n_step); reported, not trained" in out
    assert "t-old-" not in out and "t-explore-s0" in out
    assert screen.screen_report(s, tmp_path)["arms"]["old"]["finished"] == [0, 1]
    bad = write_screen(tmp_path / "b.json", {"old": {"argv": [], "retired": ""}})
    with pytest.raises(ValueError, match="'retired' must name the removed options"):
        screen.load_screen(bad)


def test_the_queue_goes_seed_by_seed_and_takes_only_the_seeds_named(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    arms = {**GOOD_ARMS, "more": {"argv": ["--set", "train.crowd_delay_max=20"]}}
    path = write_screen(tmp_path / "s.json", arms, seeds=[3, 5, 7], baseline="base")
    argv = [str(path), "--dry-run", "--arms", "explore", "more", "--seeds", "7", "3"]
    assert screen.main(argv) == 0
    names = re.findall(r"\[screen\] (t-\S+):", capsys.readouterr().out)
    assert names == ["t-explore-s7", "t-more-s7", "t-explore-s3", "t-more-s3"]
    assert screen.main([str(path), "--dry-run", "--seeds", "4"]) == 2
    assert "--seeds: [4] not among" in capsys.readouterr().err


def test_training_runs_the_entries_one_at_a_time_and_continues_after_ctrl_c(
    tmp_path, monkeypatch, capsys
):
    """Each entry trains in its own process (here a stand-in writing the records), then is
    copied and evaluated; a run stopped with Ctrl-C (exit 130) stops the screen, and the same
    command continues with what is left, then writes the report."""
    monkeypatch.chdir(tmp_path)
    path = write_screen(tmp_path / "s.json", GOOD_ARMS, baseline="base")
    calls: list[list[str]] = []
    stop_at = [3]  # the third process is interrupted

    def child(cmd):
        calls.append(cmd)
        if len(calls) == stop_at[0]:
            return 130
        args = cmd[cmd.index("-m") + 1 :]
        if args[0] == "experiments.restaurant":
            seed = int(args[args.index("--seed") + 1])
            make_run(Path(args[args.index("--out") + 1]), [0, seed], 0.2 * seed, evaluated=False)
        else:  # lab.evaluation, its keyword arguments as one JSON object
            assert args[0] == "lab.evaluation"
            out = Path(json.loads(args[1])["out"])
            out.mkdir(parents=True)
            pooled = {k: {"mean": 0.5, "se": 0.0} for k in screen.METRICS}
            (out / "results.json").write_text(json.dumps({"pooled": pooled}))
        return 0

    monkeypatch.setattr(campaign, "run_child", child)
    assert screen.main([str(path)]) == 130
    assert not (tmp_path / "res/screen/t.json").exists()  # no report of a screen cut short
    assert screen.main([str(path)]) == 0
    trained = [c for c in calls if "experiments.restaurant" in c]
    # seed by seed: base-s0, explore-s0 (cut short, then afresh), base-s1, explore-s1
    assert [c[c.index("--seed") + 1] for c in trained] == ["0", "0", "0", "1", "1"]
    assert "--resume" not in trained[2]  # stopped before a checkpoint: started afresh
    assert all(c[0] == sys.executable for c in calls)
    rep = json.loads((tmp_path / "res/screen/t.json").read_text())
    arms = rep["arms"]
    assert arms["explore"]["finished"] == [0, 1] and arms["base"]["finished"] == [0, 1]
    assert rep["arms"]["explore"]["runs"][1]["liftoff"]["iteration"] == 2
    n = len(calls)
    assert screen.main([str(path)]) == 0 and len(calls) == n  # all done: nothing runs


def test_reused_runs_must_hold_the_config_their_arm_builds(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    run = campaign.CampaignRun("x", ("--no-progress", "--seed", "1"), tmp_path, (), "restaurant")
    cfg = campaign.built_config(run).to_dict()
    make_run(tmp_path / "r0", [0], 0.1)
    (tmp_path / "r0" / "config.json").write_text(json.dumps(cfg))
    arms = {"base": {"runs": {"0": "r0"}}}
    path = write_screen(tmp_path / "s.json", arms, seeds=[0], baseline="base")
    assert screen.main([str(path), "--dry-run"]) == 2  # trained with seed 1, said to be seed 0
    assert "differs from the trained run's r0/config.json in ['seed']" in capsys.readouterr().err
    arms["base"]["runs"] = {"1": "r0"}
    path = write_screen(tmp_path / "s.json", arms, seeds=[1], baseline="base")
    assert screen.main([str(path), "--dry-run"]) == 0
    # a run on a time budget records the iterations it did: those alone do not make it another
    cfg["train"]["iterations"] += 7
    (tmp_path / "r0" / "config.json").write_text(json.dumps(cfg))
    assert screen.main([str(path), "--dry-run"]) == 2
    assert "differs from the trained run's r0/config.json in ['train.iterations']" in (
        capsys.readouterr().err
    )
    arms["base"]["argv"] = ["--minutes", "24"]
    path = write_screen(tmp_path / "s.json", arms, seeds=[1], baseline="base")
    assert screen.main([str(path), "--dry-run"]) == 0


# ---------------------------------------------------------------- the table


def test_the_table_is_made_from_the_records_and_marks_unfinished_arms(tmp_path):
    _screen_folders(tmp_path)
    rec = Records(tmp_path / "results")
    text = screen.render_screen(rec, "lab/screens/t.json")
    rows = [line for line in text.splitlines() if line.startswith("| `")]
    base, new = rows[0].split(" | "), rows[1].split(" | ")
    assert base[:6] == ["| `base`", "4", "3/4", "30", "0.30 +- 0.13", "0.00"]
    assert base[7] == "(baseline)" and base[8] == "1 of 4"
    assert new[:4] == ["| `new`", "3/4 seeds", "2/3", "20"]
    assert new[4].startswith("0.43 +- ") and new[5] == "0.10"
    assert rows[2].startswith("| `base` | ") and rows[2].endswith("| (baseline) |")  # SPL table
    assert not rec.missing
    make_run(tmp_path / "res/screen/new-s3", [0] * 4, 0.3)  # a record changes: so does the table
    assert screen.render_screen(rec, "lab/screens/t.json") != text


def test_a_run_folder_with_broken_records_is_an_error_naming_it(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    path = _screen_folders(tmp_path)
    (tmp_path / "runs/b2/results.json").write_text(json.dumps({"test_online": {}}))
    with pytest.raises(ValueError, match=r"runs/b2: not a finished run's records \(KeyError"):
        screen.screen_report(screen.load_screen(path), tmp_path)
    assert screen.main([str(path), "--report-only"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "runs/b2: not a finished run's records" in err
