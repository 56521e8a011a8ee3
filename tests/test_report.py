"""report.py is the one home of labels, tables and the paper's numbers; the family's MPC
defaults come with its registration."""

import argparse

from mpcpearl_jax.cli.args import add_config_options, build_config
from mpcpearl_jax.config import preset
from mpcpearl_jax.envs import mpc_defaults
from mpcpearl_jax.evaluation.report import PAPER, comparison_table, results_table, run_label


def test_run_label_of_configs_and_saved_dicts():
    cfg = preset("smoke")
    cases = [(0.2, True, "MPC-PEARL 0.2"), (0.0, True, "PEARL"), (0.2, False, "MPC-SAC 0.2")]
    cases.append((0.0, False, "SAC"))
    for eps, context, want in cases:
        c = cfg.replace(
            train=cfg.train.__class__(**{**cfg.train.__dict__, "eps": eps}),
            pearl=cfg.pearl.replace(use_context=context),
        )
        assert run_label(c) == run_label(c.to_dict()) == want
    assert run_label({"method": "grbal"}) == "GrBAL"


def test_tables_put_the_paper_beside_the_run():
    m = {"SR": 0.5, "TT": 40.0, "CFR": 0.9, "SPL": 0.4, "MGD": 20.0}
    res = {"label": "PEARL", "test_adapt": m, "test_online": m, "paper": PAPER["restaurant"]}
    one = results_table(res)
    assert "| PEARL | PEARL (online) | paper PEARL |" in one.splitlines()[0]
    assert "| SR | 0.50 | 0.50 | 0.36 |" in one
    assert one.splitlines()[-1] == "paper columns: the paper's published table"
    # the restaurant's: how long the paper's agents trained (method §9), under the table
    note = results_table({**res, "env": "restaurant"}).splitlines()[-1]
    assert note.startswith("paper columns: the paper's published table (3000 iterations x 750")
    assert "about 27 h on the authors' GPU machine, mean over 7 seeds" in note
    many = comparison_table([("PEARL", res)], PAPER["sidewalk"])
    assert "PEARL (2 adapt. eps.)" in many and "| CFR | 0.90 | 0.90 | - |" in many


def test_sidewalk_mpc_speed_default_comes_from_its_registration():
    assert mpc_defaults("sidewalk") == {"v_max": None} and mpc_defaults("restaurant") == {}
    p = argparse.ArgumentParser()
    add_config_options(p, "sidewalk")
    cfg = build_config(p.parse_args(["--preset", "smoke"]), "sidewalk")
    assert cfg.mpc.v_max is None
    cfg = build_config(p.parse_args(["--preset", "smoke", "--set", "mpc.v_max=3"]), "sidewalk")
    assert cfg.mpc.v_max == 3


def test_the_results_table_spells_out_each_metric_and_column_once():
    """Under the table: each metric's name, meaning and better direction, once; what "(online)"
    and "(OOD)" mean; the paper's note stays last."""
    m = {"SR": 0.5, "TT": 40.0, "CFR": 0.9, "SPL": 0.4, "MGD": 20.0}
    res = {
        "label": "MPC-PEARL 0.2",
        "env": "restaurant",
        "test_adapt": m,
        "test_online": m,
        "ood_adapt": m,
        "paper": PAPER["restaurant"],
        "config": {"train": {"eval_adapt_episodes": 2}},
    }
    text = results_table(res)
    lines = text.splitlines()
    for name, words, better in (
        ("SR", "success rate", "higher"),
        ("TT", "time to goal", "lower"),
        ("CFR", "collision-free rate", "higher"),
        ("SPL", "success weighted by path length", "higher"),
        ("MGD", "mean goal distance", "lower"),
    ):
        defs = [x for x in lines if x.startswith(f"{name} ") and words in x]
        assert len(defs) == 1 and f"({better} is better)" in defs[0], (name, lines)
    cols = [x for x in lines if x.startswith("columns: ")]
    assert len(cols) == 1 and "2 adaptation episodes" in cols[0]
    assert "(online): adapting within the one scored episode" in cols[0]
    assert "(OOD): out-of-distribution tasks" in cols[0]
    assert lines[-1].startswith("paper columns: the paper's published table")
    no_ood = results_table({**res, "ood_adapt": {"skipped": "none"}})
    assert "(OOD)" not in no_ood


def test_the_learning_curve_figure_marks_the_saved_policy(tmp_path, monkeypatch):
    import matplotlib.figure

    from mpcpearl_jax.evaluation.report import plot_learning_curves

    titles = []
    real = matplotlib.figure.Figure.suptitle
    monkeypatch.setattr(
        matplotlib.figure.Figure,
        "suptitle",
        lambda self, t, **kw: titles.append(t) or real(self, t, **kw),
    )
    rows = [
        {"iteration": i, "train_return": -i, "test_return": -i, "test_SR": s, "test_CFR": 1.0}
        for i, s in ((25, 0.1), (50, 0.29), (75, 0.12))
    ]
    assert plot_learning_curves([("x", rows)], tmp_path / "a.png", saved_last=True).is_file()
    assert titles[-1].startswith("dashed line: the saved policy, the last iteration's (75)")
