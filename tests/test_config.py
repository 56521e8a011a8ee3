"""Configs and presets (config.py): field checks name the field, `validate` owns the checks across
fields, the paper presets switch every extension off, each preset builds its committed runs, and
runs of removed options still load and evaluate."""

import dataclasses
from pathlib import Path

import jax.numpy as jnp
import pytest

from mpcpearl_jax.config import ExperimentConfig, PearlConfig, TrainConfig, preset, validate
from mpcpearl_jax.envs.types import ConfigError


def test_demo_share_schedule():
    tc = TrainConfig(mpc_demo_share=0.8, mpc_demo_iterations=10)
    assert tc.demo_share(0) == pytest.approx(0.8)
    assert tc.demo_share(5) == pytest.approx(0.4)
    assert tc.demo_share(10) == 0.0 and tc.demo_share(50) == 0.0
    assert TrainConfig().demo_share(0) == 0.0
    # eps = 0 is PEARL: no MPC, so no warm start either
    pearl = TrainConfig(eps=0.0, mpc_demo_share=0.5, mpc_demo_iterations=3)
    assert not pearl.uses_mpc and pearl.demo_share(0) == 0.0


@pytest.mark.parametrize(
    "make, field",
    [
        (lambda: TrainConfig(mpc_demo_share=1.5), "mpc_demo_share"),
        (lambda: TrainConfig(mpc_buffer_fraction=1.0), "mpc_buffer_fraction"),
        (lambda: TrainConfig(mpc_demo_iterations=-1), "mpc_demo_iterations"),
        (lambda: PearlConfig(bc_weight=-1.0), "bc_weight"),
        (lambda: PearlConfig(layer_norm="False"), "layer_norm"),
        (
            lambda: validate(ExperimentConfig(pearl=PearlConfig(bc_weight=1.0))),
            "bc_weight",
        ),
        (lambda: TrainConfig(mpc_demo_step_prob=-0.1), "mpc_demo_step_prob"),
        (lambda: TrainConfig(explore_start_share=1.0), "explore_start_share"),
        (lambda: TrainConfig(explore_start_share=-0.1), "explore_start_share"),
        (lambda: TrainConfig(explore_start_share=True), "explore_start_share"),
        (
            lambda: TrainConfig(explore_start_share=0.5, posterior_episodes=0),
            "explore_start_share",
        ),
        (lambda: PearlConfig(bc_q_filter=1), "bc_q_filter"),
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
    assert cfg.train.mpc_demo_share == 0 and cfg.train.mpc_buffer_fraction == 0
    assert cfg.train.mpc_demo_step_prob == 1.0
    assert cfg.pearl.bc_weight == 0 and not cfg.pearl.layer_norm
    assert not cfg.pearl.auto_entropy and cfg.pearl.target_entropy is None
    assert cfg.pearl.init_alpha == 1.0
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


def test_cpu_presets_differ_only_in_the_extensions():
    ext, paper = preset("cpu"), preset("cpu-paper")
    assert ext.train.mpc_demo_share > 0 and ext.pearl.bc_weight > 0 and ext.pearl.layer_norm
    assert ext.mpc.unsafe_recovery
    same = dataclasses.replace(
        ext.train,
        mpc_demo_share=0.0,
        mpc_demo_iterations=0,
        mpc_demo_step_prob=1.0,
        mpc_buffer_fraction=0.0,
    )
    assert same == paper.train
    assert ext.pearl.replace(bc_weight=0.0, bc_q_filter=True, layer_norm=False) == paper.pearl


@pytest.mark.parametrize(
    "name, eps, algo, folder",
    [
        ("cpu-explore", "0.2", "pearl", "mpc-pearl-eps0.2"),
        ("cpu-explore", "0", "pearl", "pearl"),
        ("cpu-explore", "0.2", "sac", "mpc-sac"),
        ("cpu-robust", "0.2", "pearl", "ablation/crowd-delay20-30min"),
        ("cpu-auto", "0.2", "pearl", "ablation/auto-entropy-24min"),
        ("cpu-auto", "0", "pearl", "ablation/pearl-auto-entropy-24min"),
        ("cpu-auto", "0.2", "sac", "ablation/mpc-sac-auto-entropy-24min"),
        ("cpu-tuned", "0.2", "pearl", "ablation/extended-60min"),
        ("cpu-tuned", "0", "pearl", "ablation/pearl-tuned-60min"),
        ("cpu-tuned", "0.2", "sac", "ablation/mpc-sac-tuned-60min"),
    ],
)
def test_presets_build_the_committed_restaurant_runs(tmp_path, capsys, name, eps, algo, folder):
    """`--preset P --eps E` builds exactly the committed run's config.json (the run wrote the
    iterations it finished), so one short command reproduces it; the sidewalk, which cannot
    re-draw its crowds, is refused before anything is written."""
    import json
    from pathlib import Path

    from experiments import learning
    from experiments.common import ENV_EXTRAS, build_config

    args = learning.parse_args(["--preset", name, "--eps", eps, "--algo", algo, "--minutes", "60"])
    cfg = build_config(args, "restaurant", **ENV_EXTRAS["restaurant"])
    head = Path(__file__).parents[1] / "results/restaurant" / folder / "config.json"
    ref = ExperimentConfig.from_dict(json.loads(head.read_text()))
    assert cfg == ref.replace(train=dataclasses.replace(ref.train, iterations=cfg.train.iterations))
    argv = ["--env", "sidewalk", "--preset", name, "--eps", "0.2", "--minutes", "1"]
    out = tmp_path / "run"
    assert learning.main([*argv, "--out", str(out)]) == 2
    assert "train.redraw_behaviours" in capsys.readouterr().err and not out.exists()


def test_tuned_presets_differ_from_cpu_only_where_documented():
    tuned, cpu, explore = preset("cpu-tuned"), preset("cpu"), preset("cpu-explore")
    assert tuned.mpc == cpu.mpc and tuned.pearl.replace(bc_weight=cpu.pearl.bc_weight) == cpu.pearl
    assert explore.pearl == tuned.pearl.replace(bc_weight=0.0)
    assert explore.env_overrides == tuned.env_overrides and explore.mpc == tuned.mpc
    changed = {
        k: v for k, v in explore.train.__dict__.items() if tuned.train.__dict__[k] != v
    }  # the MPC-based extensions off, exploring starts on
    assert changed == {
        "mpc_demo_share": 0.0,
        "mpc_demo_iterations": 0,
        "mpc_buffer_fraction": 0.0,
        "explore_start_share": 0.5,
    }
    default = preset("default")
    assert default.train.explore_start_share == 0.5 and default.train.mpc_demo_share == 0
    assert default.pearl.hidden == (64, 64) and default.pearl.meta_batch == 4
    assert default.pearl == explore.pearl.replace(
        hidden=(64, 64), encoder_hidden=(64, 64), meta_batch=4, auto_entropy=True
    )
    assert default.env_overrides == tuned.env_overrides


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
    ],
)
def test_runs_of_removed_options_evaluate_but_do_not_resume(tmp_path, folder, option):
    """docs/extensions.md, Removed options: a committed run that switched one on loads with the
    option dropped (its policy acts), resuming it is refused naming the option, and the option
    can no longer be set; a config.json with the option at its off value resumes as before."""
    import json

    from mpcpearl_jax import load_policy
    from mpcpearl_jax.config import REMOVED_OPTIONS, removed_options_on
    from mpcpearl_jax.errors import CheckpointError
    from mpcpearl_jax.training.checkpoint import load_config

    run = Path(__file__).resolve().parents[1] / "results" / "restaurant" / folder
    raw = json.loads((run / "config.json").read_text())
    assert removed_options_on(raw) == [option]
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
    off[section][field] = REMOVED_OPTIONS[section][field]
    (tmp_path / "config.json").write_text(json.dumps(off))
    assert load_config(tmp_path, resume=True) == cfg
    from mpcpearl_jax.envs import make_env

    build = {"train": TrainConfig, "pearl": PearlConfig}.get(section)
    build = build or (lambda **kw: make_env("restaurant", **kw))
    with pytest.raises((TypeError, ValueError)):
        build(**{field: 1})
