"""Configs and presets (config.py): field checks name the field, `validate` owns the checks across
fields, the paper presets switch every extension off, `cpu-explore` builds its committed runs,
and runs of removed options still load and evaluate."""

import dataclasses
import re
from pathlib import Path

import jax.numpy as jnp
import pytest

from mpcpearl_jax.config import ExperimentConfig, PearlConfig, TrainConfig, preset
from mpcpearl_jax.envs.types import ConfigError


@pytest.mark.parametrize(
    "make, field",
    [
        (lambda: TrainConfig(mpc_buffer_fraction=1.0), "mpc_buffer_fraction"),
        (lambda: TrainConfig(mpc_buffer_fraction=-0.1), "mpc_buffer_fraction"),
        (lambda: PearlConfig(layer_norm="False"), "layer_norm"),
        (lambda: TrainConfig(explore_start_share=1.0), "explore_start_share"),
        (lambda: TrainConfig(explore_start_share=-0.1), "explore_start_share"),
        (lambda: TrainConfig(explore_start_share=True), "explore_start_share"),
        (
            lambda: TrainConfig(explore_start_share=0.5, posterior_episodes=0),
            "explore_start_share",
        ),
    ],
)
def test_invalid_extension_settings_name_the_field(make, field):
    with pytest.raises(ConfigError, match=field):
        make()


@pytest.mark.parametrize("name", ["paper", "cpu-paper", "smoke"])
def test_paper_presets_have_every_extension_off(name):
    cfg = preset(name)
    if name == "paper":
        assert cfg.train == TrainConfig() and cfg.pearl == PearlConfig()
    assert cfg.train.mpc_buffer_fraction == 0 and not cfg.pearl.layer_norm
    assert not cfg.pearl.auto_entropy and cfg.pearl.target_entropy is None
    assert not cfg.mpc.unsafe_recovery and cfg.train.explore_start_share == 0
    assert cfg.train.crowd_delay_max == 0
    for field in (
        "observe_velocity",
        "observe_relative",
        "sensing_radius",
        "observe_time",
        "observe_sorted",
    ):
        assert not cfg.env_overrides.get(field), field
    from mpcpearl_jax.envs import make_env

    assert not make_env(cfg.env, **cfg.env_overrides).config.observe_sorted


def test_five_presets_and_cpu_explore_is_cpu_paper_with_the_documented_extensions():
    """The presets are `paper`, `smoke`, `cpu-paper`, `cpu-explore` and `default`; `cpu-explore`
    differs from `cpu-paper` exactly in the options docs/usage.md names, and `default` from
    `cpu-explore` in its sizes, automatic entropy tuning and iterations."""
    from mpcpearl_jax.config import PRESETS

    assert sorted(PRESETS) == ["cpu-explore", "cpu-paper", "default", "paper", "smoke"]
    explore, paper = preset("cpu-explore"), preset("cpu-paper")
    assert explore.pearl == paper.pearl.replace(layer_norm=True)
    changed = {k: v for k, v in explore.train.__dict__.items() if paper.train.__dict__[k] != v}
    assert changed == {"redraw_behaviours": True, "explore_start_share": 0.5}
    assert explore.mpc == paper.mpc.replace(unsafe_recovery=True, n_workers=2)
    assert explore.env_overrides == {
        "observe_velocity": True,
        "sensing_radius": 3.0,
        "observe_time": True,
        "observe_relative": True,
        "observe_sorted": True,
    }
    default = preset("default")
    assert default.pearl == explore.pearl.replace(
        hidden=(64, 64), encoder_hidden=(64, 64), meta_batch=4, auto_entropy=True
    )
    assert default.train == dataclasses.replace(explore.train, iterations=75)
    assert default.mpc == explore.mpc and default.env_overrides == explore.env_overrides


@pytest.mark.parametrize(
    "sets, eps, algo, folder",
    [
        ((), "0.2", "pearl", "mpc-pearl-eps0.2"),
        ((), "0", "pearl", "pearl"),
        ((), "0.2", "sac", "mpc-sac"),
        # the five-seed comparison's recipe (the former `cpu-auto` preset)
        (("pearl.auto_entropy=true",), "0.2", "pearl", "ablation/auto-entropy-24min"),
        (("pearl.auto_entropy=true",), "0", "pearl", "ablation/pearl-auto-entropy-24min"),
        (("pearl.auto_entropy=true",), "0.2", "sac", "ablation/mpc-sac-auto-entropy-24min"),
    ],
)
def test_cpu_explore_builds_the_committed_restaurant_runs(
    tmp_path, capsys, sets, eps, algo, folder
):
    """`--preset cpu-explore --eps E [--set ...]` builds exactly the committed run's config.json
    (the run wrote the iterations it finished; options since removed are dropped at their
    inactive values), so one short command reproduces it; the sidewalk, which cannot re-draw its
    crowds, is refused before anything is written."""
    import json

    from experiments import learning
    from experiments.common import ENV_EXTRAS, build_config

    argv = ["--preset", "cpu-explore", "--eps", eps, "--algo", algo, "--minutes", "60"]
    args = learning.parse_args([*argv, *(x for item in sets for x in ("--set", item))])
    cfg = build_config(args, "restaurant", **ENV_EXTRAS["restaurant"])
    head = Path(__file__).parents[1] / "results/restaurant" / folder / "config.json"
    raw = json.loads(head.read_text())
    from mpcpearl_jax.config import removed_options_on

    assert removed_options_on(raw) == []
    ref = ExperimentConfig.from_dict(raw)
    assert cfg == ref.replace(train=dataclasses.replace(ref.train, iterations=cfg.train.iterations))
    argv = ["--env", "sidewalk", "--preset", "cpu-explore", "--eps", "0.2", "--minutes", "1"]
    out = tmp_path / "run"
    assert learning.main([*argv, "--out", str(out)]) == 2
    assert "train.redraw_behaviours" in capsys.readouterr().err and not out.exists()


def test_default_preset_keeps_the_sidewalk_crowd():
    """The main command's preset re-draws crowds on the restaurant and leaves the sidewalk's
    recorded crowd alone (instead of refusing it, as an explicit preset is)."""
    from experiments.common import ENV_EXTRAS, build_config, parser

    for env, redraw in (("restaurant", True), ("sidewalk", False)):
        cfg = build_config(parser(env).parse_args([]), env, **ENV_EXTRAS[env])
        assert cfg.train.redraw_behaviours is redraw and cfg.train.explore_start_share == 0.5


@pytest.mark.parametrize(
    "folder, option",
    [
        ("ablation/dagger-labels-60min", "train.mpc_dagger_labels"),
        ("ablation/policy-ema-60min", "pearl.policy_ema"),
        ("ablation/collision-penalty-60min", "env_overrides.w_collision"),
        ("main-seeds/alpha-lr1e-3-s2", "pearl.alpha_lr"),
        ("main-seeds/warmstart20-s0", "train.mpc_demo_share"),
        ("ablation/extended-60min", "pearl.bc_weight"),
        ("main-seeds/rs1-alpha02-s0", "pearl.init_alpha"),
    ],
)
def test_runs_of_removed_options_evaluate_but_do_not_resume(tmp_path, folder, option):
    """docs/extensions.md, Removed options: a committed run that switched one on loads with the
    option dropped (its policy acts), resuming it is refused naming the option, and the option
    can no longer be set; a config.json with its removed options at their off value resumes as
    before."""
    import json

    from mpcpearl_jax import load_policy
    from mpcpearl_jax.config import REMOVED_OPTIONS, removed_options_on
    from mpcpearl_jax.errors import CheckpointError
    from mpcpearl_jax.training.checkpoint import load_config

    run = Path(__file__).resolve().parents[1] / "results" / "restaurant" / folder
    raw = json.loads((run / "config.json").read_text())
    on = removed_options_on(raw)
    assert option in on
    cfg = load_config(run)
    section, field = option.split(".")
    part = getattr(cfg, section)
    assert field not in (part if isinstance(part, dict) else part.__dict__)
    policy = load_policy(run)
    act = policy.act(jnp.zeros((policy.obs_dim,)), policy.prior_z())
    assert act.shape == (2,) and bool(jnp.all(jnp.isfinite(act)))
    with pytest.raises(CheckpointError, match=option):
        load_config(run, resume=True)
    off = json.loads(json.dumps(raw))
    for name in on:
        sec, fld = name.split(".")
        off[sec][fld] = REMOVED_OPTIONS[sec][fld]
    (tmp_path / "config.json").write_text(json.dumps(off))
    assert load_config(tmp_path, resume=True) == cfg
    from mpcpearl_jax.envs import make_env

    build = {"train": TrainConfig, "pearl": PearlConfig}.get(section)
    build = build or (lambda **kw: make_env("restaurant", **kw))
    with pytest.raises((TypeError, ValueError)):
        build(**{field: 1})


@pytest.mark.parametrize(
    "changes, on",
    [
        # the MPC warm start acted with a share and an iteration count, and with the MPC
        (
            {"train.mpc_demo_share": 1.0, "train.mpc_demo_iterations": 20},
            ["train.mpc_demo_share", "train.mpc_demo_iterations"],
        ),
        (
            {
                "train.mpc_demo_share": 1.0,
                "train.mpc_demo_iterations": 400,
                "train.mpc_demo_step_prob": 0.5,
            },
            ["train.mpc_demo_share", "train.mpc_demo_iterations", "train.mpc_demo_step_prob"],
        ),
        ({"train.mpc_demo_share": 1.0}, []),
        ({"train.mpc_demo_step_prob": 0.5}, []),  # the presets' inactive residue
        (
            {"train.eps": 0.0, "train.mpc_demo_share": 1.0, "train.mpc_demo_iterations": 20},
            [],
        ),
        # behaviour cloning read the MPC buffer's rows
        ({"pearl.bc_weight": 1.0, "train.mpc_buffer_fraction": 0.5}, ["pearl.bc_weight"]),
        (
            {
                "pearl.bc_weight": 4.0,
                "pearl.bc_q_filter": False,
                "train.mpc_buffer_fraction": 0.5,
            },
            ["pearl.bc_weight", "pearl.bc_q_filter"],
        ),
        ({"pearl.bc_q_filter": False}, []),  # the presets' inactive residue
        ({"pearl.init_alpha": 0.2, "pearl.reward_scale": 1.0}, ["pearl.init_alpha"]),
    ],
)
def test_removed_training_options_load_named_and_round_trip_off(tmp_path, changes, on):
    """A config.json of `default` with the retired warm start, cloning or init_alpha switched on
    loads for evaluation with the options dropped and names exactly those that acted (resume
    refused naming them); their inactive values, and their off values, load silently, resume,
    and round-trip through to_json without the removed fields."""
    import json

    from mpcpearl_jax.config import REMOVED_OPTIONS, removed_options_on
    from mpcpearl_jax.errors import CheckpointError
    from mpcpearl_jax.training.checkpoint import load_config

    base = preset("default")
    raw = json.loads(base.to_json())
    for name, value in changes.items():
        section, field = name.split(".")
        raw[section][field] = value
    removed = {f"{sec}.{f}" for sec, fields in REMOVED_OPTIONS.items() for f in fields}
    live = {tuple(k.split(".")): v for k, v in changes.items() if k not in removed}
    pearl = {f: v for (sec, f), v in live.items() if sec == "pearl"}
    train = {f: v for (sec, f), v in live.items() if sec == "train"}
    want = base.replace(
        pearl=base.pearl.replace(**pearl), train=dataclasses.replace(base.train, **train)
    )
    assert removed_options_on(raw) == on
    (tmp_path / "config.json").write_text(json.dumps(raw))
    assert load_config(tmp_path) == want
    if on:
        with pytest.raises(CheckpointError, match=re.escape(", ".join(on))):
            load_config(tmp_path, resume=True)
    else:
        assert load_config(tmp_path, resume=True) == want
    for name in changes.keys() & removed:  # every removed option at its off value
        section, field = name.split(".")
        raw[section][field] = REMOVED_OPTIONS[section][field]
    assert removed_options_on(raw) == []
    (tmp_path / "config.json").write_text(json.dumps(raw))
    cfg = load_config(tmp_path, resume=True)
    assert cfg == want and ExperimentConfig.from_json(cfg.to_json()) == want
    assert not {f for part in REMOVED_OPTIONS.values() for f in part} & {
        *json.loads(cfg.to_json())["train"],
        *json.loads(cfg.to_json())["pearl"],
    }
