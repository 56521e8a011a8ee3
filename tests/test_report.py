"""report.py is the one home of labels, tables and the paper's numbers; the family's MPC
defaults come with its registration."""

import argparse

from experiments.common import add_config_options, build_config
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
