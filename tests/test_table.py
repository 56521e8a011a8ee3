"""lab.table and lab.tables: the READMEs' results tables are the committed
records, rebuilt; seed groups, paired differences, missing records and the results/ paths the
READMEs name."""

import json
import math
from pathlib import Path

import pytest

from lab import table
from lab.tables import catalogue, render
from lab.tables import statistics as stats
from lab.tables.catalogue import Entry
from lab.tables.statistics import Records, Stat

ROOT = Path(__file__).resolve().parents[1]


def test_committed_tables_are_the_records():
    files, missing = table.generate(ROOT / "results")
    assert not missing, "records missing:\n" + "\n".join(missing)
    for path, (committed, generated) in files.items():
        assert committed == generated, f"{path}: run python -m lab.table"


def test_table_check_passes_on_the_committed_results(capsys):
    """`python -m lab.table --check` exits 0: tables current, no record or path missing."""
    assert table.main([str(ROOT / "results"), "--check"]) == 0, capsys.readouterr()


def test_every_results_path_the_readmes_name_exists():
    assert table.missing_references(ROOT) == []


def _run(results, name, sr, tt, val, scen=True, steps=1000):
    """A synthetic run folder: results.json, curve.json, the pooled validation record (one task
    set with the given per-task SR) and, if asked, the scenario records."""
    run = results / "restaurant" / name
    m = {"SR": sr, "TT": tt, "CFR": 1.0, "SPL": sr / 2, "MGD": tt / 2}
    (run / "eval").mkdir(parents=True)
    res = {"test_adapt": m, "test_online": m, "ood_adapt": m}
    (run / "results.json").write_text(json.dumps(res))
    point = {"val_SR": sr, "val_CFR": 1.0}
    curve = {"budget_minutes": 60.0, "grad_steps": steps, "points": [point]}
    (run / "curve.json").write_text(json.dumps(curve))
    n = len(val)
    mean = sum(val) / n
    se = math.sqrt(sum((v - mean) ** 2 for v in val) / (n - 1) / n)
    pooled = {k: {"mean": v, "se": 0.0} for k, v in m.items()}
    pooled["SR"] = {"mean": mean, "se": se}
    rec = {"task_seed": 1, "tasks": list(range(n)), "per_task": {"SR": [val]}}
    val8 = run / stats.VAL8
    val8.parent.mkdir(parents=True)
    val8.write_text(json.dumps({"pooled": pooled, "records": [rec]}))
    for rel in stats.SCENARIOS.values():
        if scen:
            (run / rel).parent.mkdir(parents=True)
            (run / rel).write_text(json.dumps({"metrics": m}))
    return f"restaurant/{name}"


def test_a_seed_group_is_mean_standard_error_over_seeds_and_worst_seed(tmp_path):
    results = tmp_path / "results"
    srs, tts = [0.5, 0.75, 1.0], [60.0, 50.0, 40.0]
    runs = tuple(
        _run(results, f"s{i}", sr, tt, [sr, sr], steps=1000 + 500 * i)
        for i, (sr, tt) in enumerate(zip(srs, tts, strict=True))
    )
    rec = Records(results)
    group = Entry("group", runs)
    sr = stats.entry_values(rec, group, "test", "SR")
    assert [s.value for s in sr] == srs
    se = math.sqrt(sum((v - 0.75) ** 2 for v in srs) / 2 / 3)  # ddof 1, over 3 seeds
    assert stats.seed_stats(srs, "SR") == pytest.approx((0.75, se, 0.5))
    assert stats.seed_stats(tts, "TT") == pytest.approx((50.0, se * 40, 60.0))  # worst = longest
    assert render.fmt_metric(sr, "SR") == f"0.75 +- {se:.2f} (worst 0.50)"
    tt = stats.entry_values(rec, group, "test", "TT")
    assert render.fmt_metric(tt, "TT") == f"50.00 +- {se * 40:.2f} (worst 60.00)"
    # the validation cell of a group is over the seeds' pooled means, not over tasks
    assert render.val8_cell(rec, group, cfr=True) == f"0.75 +- {se:.2f} (worst 0.50) (CFR 1.00)"
    cfr = "1.00 +- 0.00 (worst 1.00)"
    assert render.pair_cell(rec, group, "scen_test") == f"0.75 +- {se:.2f} (worst 0.50) / {cfr}"
    # counts: the range over the seeds' records
    steps = stats.entry_values(rec, group, "grad_steps", "")
    assert render.fmt_count(steps, render._steps) == "1000-2000"
    assert render.fmt_count(stats.entry_values(rec, group, "budget", ""), render._minutes) == "60"
    one = Entry("one", runs[:1])
    assert render.val8_cell(rec, one, cfr=False) == "0.50 +- 0.00"
    assert render.fmt_metric([Stat(0.875)], "SR") == "0.88"  # the records' rounding
    with pytest.raises(ValueError):
        stats.seed_stats([0.5], "SR")
    assert not rec.missing


def test_a_missing_record_is_named_and_never_filled_in(tmp_path, monkeypatch, capsys):
    results = tmp_path / "results"
    ok = _run(results, "ok", 0.5, 60.0, [0.0, 1.0])
    gap = _run(results, "gap", 0.5, 60.0, [0.0, 1.0], scen=False)
    entries = (
        Entry("ok", (ok,)),
        Entry("gap", (gap,)),
        Entry("none", (gap,), absent=catalogue._NO_SCEN),
    )
    (tmp_path / "README.md").write_text("text\n<!-- table:t -->\nold\n<!-- /table:t -->\nend\n")
    (results / "README.md").write_text("no block here\n")
    blocks = [("README.md", "t", lambda rec: render.render_restaurant(rec, entries))]
    files, missing = table.generate(results, blocks)
    new = files[tmp_path / "README.md"][1]
    assert new.startswith("text\n<!-- table:t -->\n| run |") and new.endswith("\nend\n")
    rows = {line.split(" [")[0].strip("| "): line for line in new.splitlines() if "[`" in line}
    assert rows["ok"].endswith("| 0.50 / 1.00 | 0.50 / 1.00 |")
    assert rows["gap"].endswith(
        f"| {stats.MISSING} / {stats.MISSING} | {stats.MISSING} / MISSING |"
    )
    assert rows["none"].endswith("| - / - | - / - |")
    assert missing == [
        "results/restaurant/gap/eval/policy-scenarios-test/results.json",
        "results/restaurant/gap/eval/policy-scenarios-ood/results.json",
    ]
    monkeypatch.setattr(table, "BLOCKS", tuple(blocks))
    monkeypatch.setattr(table, "missing_references", lambda root: [])
    assert table.main([str(results), "--check"]) == 1
    out = capsys.readouterr()
    assert "missing record: results/restaurant/gap/eval/policy-scenarios-test" in out.err
    assert "(committed)" in out.out and "+| run |" in out.out  # the diff
    assert (tmp_path / "README.md").read_text().count("old") == 1  # --check writes nothing


def test_check_passes_once_the_tables_are_written(tmp_path, monkeypatch, capsys):
    results = tmp_path / "results"
    entries = (Entry("ok", (_run(results, "ok", 0.5, 60.0, [0.0, 1.0]),)),)
    (tmp_path / "README.md").write_text("<!-- table:t -->\n<!-- /table:t -->\n")
    (results / "README.md").write_text("")
    monkeypatch.setattr(
        table, "BLOCKS", (("README.md", "t", lambda r: render.render_restaurant(r, entries)),)
    )
    monkeypatch.setattr(table, "missing_references", lambda root: [])
    assert table.main([str(results), "--check"]) == 1
    assert table.main([str(results)]) == 0
    assert table.main([str(results), "--check"]) == 0
    assert "0.50 +- 0.50 (CFR 1.00)" in (tmp_path / "README.md").read_text()
    capsys.readouterr()


def test_block_markers_must_be_there_once():
    assert table.replace_block("a\n<!-- table:x -->\nb\n<!-- /table:x -->\n", "x", "c") == (
        "a\n<!-- table:x -->\nc\n<!-- /table:x -->\n"
    )
    for text in ("none", "<!-- /table:x --><!-- table:x -->", "<!-- table:x -->" * 2):
        with pytest.raises(ValueError, match="table:x"):
            table.replace_block(text, "x", "c")


def _pooled(per_task: list[list[float]], seeds=(1, 2)) -> dict:
    return {
        "records": [
            {"task_seed": s, "tasks": list(range(len(t))), "per_task": {"SR": [t]}}
            for s, t in zip(seeds, per_task, strict=True)
        ]
    }


def test_paired_difference_is_over_the_same_tasks():
    a = _pooled([[1, 1, 0, 0], [1, 1, 1, 0]])
    b = _pooled([[1, 0, 0, 1], [0, 1, 1, 0]])
    p = stats.paired_difference(a, b)
    d = [0, 1, 0, -1, 1, 0, 0, 0]
    se = math.sqrt(sum((x - 0.125) ** 2 for x in d) / 7 / 8)
    assert (p.mean, p.tasks, p.both, p.only_a, p.only_b) == (0.125, 8, 3, 2, 1)
    assert p.se == pytest.approx(se)
    assert str(p).startswith(f"+0.12 +- {se:.2f} over 8 tasks")
    with pytest.raises(ValueError, match="same tasks"):
        stats.paired_difference(a, _pooled([[1, 1, 0, 0], [1, 1, 1, 0]], seeds=(1, 3)))


def test_referenced_paths_reads_code_brackets_and_links_but_not_outputs():
    text = (
        "see `results/restaurant/pearl` and [`ablation/x`, `restaurant/y`] or [a](earlier/z.png);"
        " `python -m lab.diagnostics.imitation --out results/new/folder`"
        " `runs/<run>` `docs/a.md`\n"
        "```bash\npython -m x results/in/code\n```\n"
    )
    assert table.referenced_paths(text) == [
        "results/restaurant/pearl",
        "ablation/x",
        "restaurant/y",
        "earlier/z.png",
    ]


def test_seed_table_gives_seed_statistics_and_the_papers_ordering_with_seeds_as_the_unit(tmp_path):
    results = tmp_path / "results"

    def group(name, srs):
        return name, tuple(
            _run(results, f"{name}{i}", sr, 50.0, [sr, sr]) for i, sr in enumerate(srs)
        )

    groups = (
        group("MPC-PEARL 0.2", [0.9, 0.8, 1.0]),
        group("PEARL", [0.5, 0.4, 0.6]),  # 0.4 below MPC-PEARL on every seed
        group("MPC-SAC 0.2", [0.6, 0.3, 0.5]),  # PEARL - MPC-SAC: -0.1, +0.1, +0.1
    )
    rec = Records(results)
    text = render.render_seeds(rec, groups)
    rows = [line for line in text.splitlines() if line.startswith("| ")]
    first = rows[1].split(" | ")
    assert first[:5] == ["| MPC-PEARL 0.2", "3", "60", "1000", "24 test tasks"]
    se = math.sqrt(sum((v - 0.9) ** 2 for v in (0.9, 0.8, 1.0)) / 2 / 3)
    assert first[5] == f"0.90 +- {se:.2f} (worst 0.80)"
    claims = {tuple(r.split(" | ")[:2]): r for r in rows if "(SR)" in r}
    holds = claims[("| MPC-PEARL 0.2 > PEARL (SR)", "192 validation tasks")]
    assert "+0.40 +- 0.00" in holds and holds.endswith("| 3 | holds |")
    mixed = claims[("| PEARL > MPC-SAC 0.2 (SR)", "paper's 25 test scenarios")]
    assert "+0.03 +- 0.07" in mixed and mixed.endswith("cannot be told apart |")
    # B ahead on every seed: the claim does not hold
    d = stats.seed_difference([Stat(0.1), Stat(0.2), Stat(0.3)], [Stat(0.5), Stat(0.62), Stat(0.7)])
    assert d[:2] == pytest.approx((-0.4066667, 0.0066667), abs=1e-6) and d[2] == 3
    assert stats.verdict(d).startswith("does not hold")
    assert stats.verdict(stats.seed_difference([Stat(0.5)], [Stat(0.1)])) == (
        "fewer than 3 seeds each: no verdict"
    )
    # two seeds that differ by the same amount (se 0) get no verdict, not 'holds'
    two = stats.seed_difference([Stat(0.9), Stat(0.8)], [Stat(0.7), Stat(0.6)])
    assert two == pytest.approx((0.2, 0.0, 2))
    assert stats.verdict(two) == "fewer than 3 seeds each: no verdict"
    # one seed is shown as such, never as a spread
    one = render.render_seeds(rec, (group("solo", [0.7]),))
    assert "0.70 (1 seed)" in one
    assert not rec.missing


def test_lift_off_reads_first_success_last_ten_and_lowest_alpha():
    rows = [
        {"iteration": i + 1, "train_success": s, "alpha": a}
        for i, (s, a) in enumerate([(0, 1.0), (0, 0.3), (0.5, 0.05), (0, 0.2)] + [(1.0, 0.9)] * 9)
    ]
    assert render._lift_off(rows) == ("3", "0.90", "0.05 (it 3)")
    fixed = [{k: v for k, v in r.items() if k != "alpha"} for r in rows[:2]]
    assert render._lift_off(fixed) == ("never", "0.00", "fixed")


def _curve(results: Path, name: str, points, first_success) -> str:
    run = results / name
    run.mkdir(parents=True)
    pts = [{"minutes": m, "val_SR": v, "val_CFR": c, "test_SR": t} for m, v, c, t in points]
    hit = None if first_success is None else {"minutes": first_success}
    curve = {"eval_every_minutes": 6.0, "points": pts, "time_to": {"train": {"first_success": hit}}}
    (run / "curve.json").write_text(json.dumps(curve))
    return name


def test_seed_curves_read_each_evaluation_point_and_pair_seeds_at_each_minute(tmp_path):
    results = tmp_path / "results"

    def pts(v12, v24):  # points at 0, 6.1, 12.05, 18.2, 24.01 minutes
        return [(0.0, 0, 0.5, 0), (6.1, 0, 0.5, 0), (12.05, v12, 0.8, v12), (18.2, 0.5, 0.9, 0.5),
                (24.01, v24, 1.0, v24)]  # fmt: skip

    groups = (
        ("MPC-PEARL 0.2", tuple(_curve(results, f"m{i}", pts(v, 0.9), 7.0 + i)
                                for i, v in enumerate((0.1, 0.2, 0.3)))),
        ("PEARL", tuple(_curve(results, f"p{i}", pts(v, 0.9), f)
                        for i, (v, f) in enumerate([(0.5, 4.0), (0.6, 5.0), (0.7, None)]))),
    )  # fmt: skip
    rec = Records(results)
    text = render.render_seed_curves(rec, groups)
    rows = {tuple(r.split(" | ")[:3]): r for r in text.splitlines() if r.startswith("| ")}
    m = rows[("| MPC-PEARL 0.2", "3", "SR, 24 validation tasks")].split(" | ")
    se = math.sqrt(2 * 0.1**2 / 2 / 3)
    assert m[3:7] == ["0.00 +- 0.00 (worst 0.00)", f"0.20 +- {se:.2f} (worst 0.10)",
                      "0.50 +- 0.00 (worst 0.50)", "0.90 +- 0.00 (worst 0.90)"]  # fmt: skip
    assert m[7] == "8.00 +- 0.58 (worst 9.00) |"  # the slowest seed is the worst
    p = rows[("| PEARL", "3", "SR, 24 validation tasks")]
    assert p.endswith("4.50 over 2 seed(s) (worst: never, on 1) |")  # no spread, never as worst
    (claim,) = [r for r in text.splitlines() if r.startswith("| MPC-PEARL 0.2 > PEARL | SR, 24 v")]
    assert claim.split(" | ")[2:4] == [
        "+0.00 +- 0.00, cannot be told apart",
        "-0.40 +- 0.00, B ahead",
    ]
    assert not rec.missing
    # a run without a point near a minute is named, never filled in
    _curve(results, "short", [(0.0, 0, 0, 0), (6.0, 0.1, 0.5, 0.1)], 3.0)
    text = render.render_seed_curves(rec, (("X", ("short", "m0")),))
    assert "MISSING" in text and any("no point at 12 minutes" in m for m in rec.missing)


def test_sidewalk_seed_table_reads_the_windows_and_lists_a_method_without_seeds(tmp_path):
    results = tmp_path / "results"
    mpc = tuple(
        _run(results, f"m{i}", sr, 200.0, [sr, sr]) for i, sr in enumerate([0.5, 0.67, 0.83])
    )
    pearl = tuple(
        _run(results, f"p{i}", sr, 250.0, [sr, sr]) for i, sr in enumerate([0.0, 0.17, 0.0])
    )
    rec = Records(results)
    text = render.render_sidewalk_seeds(rec, (("MPC-PEARL 0.2", mpc), ("PEARL", pearl)))
    rows = [line for line in text.splitlines() if line.startswith("| ")]
    online = rows[1].split(" | ")
    assert online[4] == "6 test windows, online" and online[5].startswith(
        "0.67 +- 0.10 (worst 0.50)"
    )
    assert not any("192 validation" in r for r in rows)  # the restaurant's sets are not read
    claim = next(
        r for r in rows if r.startswith("| MPC-PEARL 0.2 > PEARL (SR) | 6 test windows, online")
    )
    assert "+0.61 +- 0.11" in claim and claim.endswith("| 3 | holds |")
    empty = render.render_sidewalk_seeds(rec, (("MPC-PEARL 0.2", mpc[:1]), ("PEARL", ())))
    assert "| PEARL | 0 | no seed finished yet |" in empty and "PEARL: none yet" in empty
    assert "0.50 (1 seed)" in empty
    assert "| MPC-PEARL 0.2 > PEARL | every set | - | 0 | no seed of PEARL finished yet |" in empty
    assert "(SR)" not in empty  # no per-set pair rows against a method without seeds
    assert not rec.missing


def test_grbal_is_in_the_seed_table_but_not_in_the_curve_table():
    assert "GrBAL" in dict(catalogue.SEED_GROUPS)
    assert "GrBAL" in dict(catalogue.CAMPAIGN_SEED_GROUPS)
    assert "GrBAL" not in dict(catalogue.CURVE_SEED_GROUPS)
    assert ("MPC-SAC 0.2", "GrBAL") in catalogue.PAPER_ORDER


def test_the_seed_tables_name_their_own_runs_and_sets():
    """The five-seed table reads the current version's recipe seeds on the six sets, the paper's
    25 OOD scenarios among them; the earlier campaign's table keeps its own runs."""
    from lab.tables import render

    rec = Records(ROOT / "results")
    now, earlier = render.render_seeds(rec), render.render_campaign_seeds(rec)
    assert "methods-recipe-screen/pearl-s4" in now and "seeds/pearl-s4" not in now
    for rendered in (now, earlier):
        assert all(label in rendered for _, label in catalogue.SEED_SETS)
    assert "seeds/mpc-pearl-s4" in earlier and "student-recipe-screen" not in earlier
    assert not rec.missing


def test_a_difference_that_rounds_to_zero_has_no_minus_sign():
    assert stats.signed(-1e-17) == "+0.00" and stats.signed(-0.004) == "+0.00"
    assert stats.signed(-0.17) == "-0.17" and stats.signed(0.2) == "+0.20"


def test_main_seed_summary_pairs_recipes_with_default_and_counts_seeds_clearing_both(tmp_path):
    """A seed passes when its test SR and its validation SR both reach 0.3 (0.3 itself passes);
    each recipe is paired with `default` seed by seed."""
    results = tmp_path / "results"
    default = tuple(
        _run(results, f"d{i}", t, 50.0, [v, v])
        for i, (t, v) in enumerate([(0.5, 0.2), (0.3, 0.3), (0.29, 0.9)])
    )
    better = tuple(
        _run(results, f"b{i}", t, 50.0, [v, v])
        for i, (t, v) in enumerate([(0.6, 0.6), (0.7, 0.7), (0.8, 0.95)])
    )
    groups = (("`default`", default), ("better", better))
    text = render.render_main_seed_summary(Records(results), groups)
    assert "| `default` | 1 of 3 |" in text and "| better | 3 of 3 |" in text
    claim = next(r for r in text.splitlines() if r.startswith("| better > `default` (SR) | 192"))
    assert "+0.28 +- 0.12" in claim and claim.endswith("cannot be told apart |")
    assert "| A > B | evaluated on |" in text


def test_lifetime_wall_time_adds_the_segments_of_a_resumed_run():
    """A record whose resumed process restarted wall_s at 0 (written before resumed runs
    carried their clocks on) counts both segments; evaluation rows without wall_s are skipped."""
    rows = [{"wall_s": 10.0}, {"wall_s": 20.0}, {"eval_SR": 0.5}, {"wall_s": 5.0}, {"wall_s": 8.0}]
    assert stats.lifetime_wall_s(rows) == 28.0
    assert stats.lifetime_wall_s([{"wall_s": 3.0}, {"wall_s": 7.5}]) == 7.5


def test_a_deleted_end_marker_is_one_line_naming_the_file(tmp_path, monkeypatch, capsys):
    """A README whose block lost its end marker used to end in a ValueError traceback."""
    results = tmp_path / "results"
    results.mkdir()
    (tmp_path / "README.md").write_text("<!-- table:t -->\nold rows\n")  # no end marker
    monkeypatch.setattr(table, "BLOCKS", (("README.md", "t", lambda r: "new"),))
    monkeypatch.setattr(table, "missing_references", lambda root: [])
    assert table.main([str(results), "--check"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["error: README.md: expected one <!-- table:t --> ... <!-- /table:t --> block"]


def test_check_finds_a_figure_typed_into_readme_prose(tmp_path, monkeypatch, capsys):
    """A README sentence quoting 0.83 from a generated table used to pass `--check` after being
    edited to 0.93; a two-decimal figure in README.md's prose must be one a generated table (or
    the paper's table) holds. Code, Python versions and the blocks themselves are not prose."""
    results = tmp_path / "results"
    results.mkdir()
    block = "<!-- table:t -->\n| SR | 0.83 |\n<!-- /table:t -->\n"
    (results / "README.md").write_text("")
    monkeypatch.setattr(table, "BLOCKS", (("README.md", "t", lambda r: "| SR | 0.83 |"),))
    monkeypatch.setattr(table, "missing_references", lambda root: [])
    prose = "With Python 3.11 the method reaches SR 0.83 (`0.55` in code).\n"
    (tmp_path / "README.md").write_text(prose + block)
    assert table.main([str(results), "--check"]) == 0
    (tmp_path / "README.md").write_text(prose.replace("0.83", "0.93") + block)
    assert table.main([str(results), "--check"]) == 1
    assert "README.md:1: 0.93" in capsys.readouterr().err
    from mpcpearl_jax.evaluation.report import PAPER

    paper = f"The paper reports SR {PAPER['restaurant']['MPC-PEARL 0.2']['SR']:.2f}.\n"
    (tmp_path / "README.md").write_text(paper + block)
    assert table.main([str(results), "--check"]) == 0


def test_summary_tables_set_the_paper_beside_the_recipe_with_budgets():
    """README's summary: the paper's row with its training (method §9), the recipe over its five
    seeds with the worst seed and its budget from the records, GP-MPC; the speed table reads both
    machines' benchmark records."""
    from lab.tables import summary

    rec = Records(ROOT / "results")
    text = summary.render_summary(rec)
    rows = {r.split(" | ")[0].strip("| "): r for r in text.splitlines() if r.startswith("| ")}
    paper = rows["MPC-PEARL 0.2, the paper"]
    assert "| 0.92 | 0.99 |" in paper and "about 27 h on the authors' GPU machine" in paper
    recipe = rows["MPC-PEARL 0.2, this project's recipe"]
    assert "(worst " in recipe and "min each on a 2-core CPU" in recipe and "5 seeds" in recipe
    # the recipe's seeds on the current version, their cores read from results.json (no curve)
    assert "student-recipe-screen/recipe-s4" in text and "cores not recorded" not in recipe
    assert "GP-MPC, this project, the SQP to convergence (the `paper` preset's expert)" in rows
    expert = (
        "GP-MPC, this project, the learned presets' expert (2 QPs with the unsafe-plan recovery)"
    )
    assert "| 0.92 | 1.00 |" in rows[expert] and "seeds 0-9" in text
    assert "the learned presets' SQP" not in text  # the 2-QP row without the recovery is not it
    speed = summary.render_speed(rec)
    assert "MISSING" not in speed and "2.88 ms" in speed  # the H100's PEARL step
    assert summary._duration(0.274101) == "0.274 s" and summary._duration(1.5996e-2) == "16.0 ms"
    assert summary._rate(926533055.98) == "927M" and summary._rate(332409.97) == "332k"
    assert not rec.missing
