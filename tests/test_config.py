"""Configs and presets (config.py): field checks name the field, `validate` owns the checks across
fields, the paper presets switch every extension off, `cpu-explore` and `recipe` build their
committed runs, and runs of removed options still load and evaluate."""

import dataclasses
import re
from pathlib import Path

import jax.numpy as jnp
import pytest

from mpcpearl_jax.config import ExperimentConfig, PearlConfig, TrainConfig, preset, validate
from mpcpearl_jax.errors import ConfigError
from mpcpearl_jax.mpc import MPCConfig


@pytest.mark.parametrize(
    "make, field",
    [
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


# the runs of the removed `cpu-paper` preset (the paper's algorithm on the CPU schedule)
CPU_PAPER_RUN = Path(__file__).resolve().parents[1] / "results/restaurant/mpc-pearl-eps0.2-paper"


def _cpu_paper() -> ExperimentConfig:
    """The removed `cpu-paper` preset, as its committed run recorded it (the iterations it
    finished aside)."""
    from mpcpearl_jax.config import read_config

    cfg = read_config(CPU_PAPER_RUN / "config.json")
    return cfg.replace(train=dataclasses.replace(cfg.train, iterations=3000))


@pytest.mark.parametrize("name", ["paper", "cpu-paper", "smoke"])
def test_paper_presets_have_every_extension_off(name):
    cfg = _cpu_paper() if name == "cpu-paper" else preset(name)
    if name == "paper":
        assert cfg.train == TrainConfig() and cfg.pearl == PearlConfig()
    assert not cfg.pearl.layer_norm
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
    """The presets are `paper`, `smoke`, `cpu-explore`, `recipe` and `default`; `cpu-explore`
    differs from the removed `cpu-paper` (as its committed run recorded it) exactly in the
    options docs/usage.md names, `recipe` from `cpu-explore` in automatic entropy tuning, and
    `default` from `cpu-explore` in its sizes, automatic entropy tuning and iterations. The
    removed preset's name says how to build it."""
    from mpcpearl_jax.config import PRESETS

    assert sorted(PRESETS) == ["cpu-explore", "default", "paper", "recipe", "smoke"]
    with pytest.raises(ConfigError, match=r"'cpu-paper' was removed .*--config results/"):
        preset("cpu-paper")
    explore, paper = preset("cpu-explore"), _cpu_paper()
    assert paper.env_overrides == {} and paper.seed == 0 and paper.train.eps == 0.2
    recipe = preset("recipe")
    assert recipe == explore.replace(pearl=explore.pearl.replace(auto_entropy=True))
    assert explore.pearl == paper.pearl.replace(layer_norm=True)
    changed = {k: v for k, v in explore.train.__dict__.items() if paper.train.__dict__[k] != v}
    assert changed == {"redraw_behaviours": True, "explore_start_share": 0.5}
    # the MPC: one worker per core (`config.RESULT_NEUTRAL`) and the expert chosen on the
    # convergence curve and the expert screen, 2 QPs with the unsafe-plan recovery (the committed
    # run's SQP settings: 2 QPs, step tolerance 0.05, 3 line-search steps)
    expert = dict(sqp_iters=2, sqp_step_tol=0.05, line_search_steps=3, unsafe_recovery=True)
    assert explore.mpc == paper.mpc.replace(n_workers=0, **expert)
    assert preset("smoke").mpc == MPCConfig()  # smoke: the paper's algorithm, small
    # the paper preset runs the SQP to convergence, as the paper's NLP solver
    assert preset("paper").mpc == MPCConfig()
    assert (MPCConfig().sqp_iters, MPCConfig().sqp_step_tol, MPCConfig().multi_start) == (
        100,
        1e-4,
        "off",
    )
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
    "name, sets, eps, algo, folder",
    [
        ("cpu-explore", (), "0.2", "pearl", "mpc-pearl-eps0.2"),
        ("cpu-explore", (), "0", "pearl", "pearl"),
        ("cpu-explore", (), "0.2", "sac", "mpc-sac"),
        # the five-seed comparison's recipe (the former `cpu-auto` preset), as the committed
        # campaign files spell it and as the preset named for it
        (
            "cpu-explore",
            ("pearl.auto_entropy=true",),
            "0.2",
            "pearl",
            "ablation/auto-entropy-24min",
        ),
        ("recipe", (), "0.2", "pearl", "ablation/auto-entropy-24min"),
        ("recipe", (), "0", "pearl", "ablation/pearl-auto-entropy-24min"),
        ("recipe", (), "0.2", "sac", "ablation/mpc-sac-auto-entropy-24min"),
    ],
)
def test_cpu_explore_and_recipe_build_the_committed_restaurant_runs(
    tmp_path, capsys, name, sets, eps, algo, folder
):
    """`--preset cpu-explore|recipe --eps E [--set ...]` builds exactly the committed run's
    config.json but for where it computes (`config.RESULT_NEUTRAL`; the run wrote the
    iterations it finished; options since removed are dropped at
    their inactive values; fields added since at the values that compute what the run did), so
    one short command reproduces it; the sidewalk, which cannot re-draw its crowds, is refused
    before anything is written."""
    import json

    from mpcpearl_jax.cli.args import build_config, parse_args
    from mpcpearl_jax.cli.train import main

    argv = ["--preset", name, "--eps", eps, "--algo", algo, "--minutes", "60"]
    args = parse_args("restaurant", [*argv, *(x for item in sets for x in ("--set", item))])
    cfg = build_config(args, "restaurant")
    head = Path(__file__).parents[1] / "results/restaurant" / folder / "config.json"
    raw = json.loads(head.read_text())
    from mpcpearl_jax.config import removed_options_on

    assert removed_options_on(raw) == []
    ref = ExperimentConfig.from_dict(raw)
    # everything but the iterations and the fields that never change results (the committed
    # runs had two MPC workers, the presets one per core: tests/test_worker_count.py)
    from mpcpearl_jax.config import RESULT_NEUTRAL
    from mpcpearl_jax.training.checkpoint import config_differences

    assert config_differences(ref, cfg, (*RESULT_NEUTRAL, "train.iterations")) == []
    assert set(RESULT_NEUTRAL) == {"devices", "mpc.n_workers"}
    argv = ["--env", "sidewalk", "--preset", name, "--eps", "0.2", "--minutes", "1"]
    out = tmp_path / "run"
    assert main("restaurant", [*argv, "--out", str(out)]) == 2
    assert "train.redraw_behaviours" in capsys.readouterr().err and not out.exists()


def test_default_preset_keeps_the_sidewalk_crowd():
    """The main command's preset re-draws crowds on the restaurant and leaves the sidewalk's
    recorded crowd alone (instead of refusing it, as an explicit preset is)."""
    from mpcpearl_jax.cli.args import build_config, parser

    for env, redraw in (("restaurant", True), ("sidewalk", False)):
        cfg = build_config(parser(env).parse_args([]), env)
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
        ("screen/mpcbuf-s0", "train.mpc_buffer_fraction"),
        ("screen/keep-s0", "train.keep_best"),
        ("screen/nstep-s0", "pearl.n_step"),
        ("screen/crossq-s0", "pearl.crossq"),
        ("screen/guide-s0", "train.guide_share"),
        ("screen/guide-window-s0", "train.guide_window"),
    ],
)
def test_runs_of_removed_options_evaluate_but_do_not_resume(tmp_path, folder, option):
    """docs/extensions.md, Removed options: a committed run that switched one on loads with the
    option dropped (its policy acts; a seed-screen run, which keeps no policy, says so in one
    line), resuming it is refused naming the option, and the option
    can no longer be set; a config.json with its removed options at their off value resumes as
    before."""
    import json

    from mpcpearl_jax import load_policy
    from mpcpearl_jax.config import REMOVED_OPTIONS, removed_options_on
    from mpcpearl_jax.errors import CheckpointError
    from mpcpearl_jax.runfolder import load_config

    run = Path(__file__).resolve().parents[1] / "results" / "restaurant" / folder
    raw = json.loads((run / "config.json").read_text())
    on = removed_options_on(raw)
    assert option in on
    cfg = load_config(run)
    section, field = option.split(".")
    part = getattr(cfg, section)
    assert field not in (part if isinstance(part, dict) else part.__dict__)
    if (run / "policy.msgpack").is_file():
        policy = load_policy(run)
        act = policy.act(jnp.zeros((policy.obs_dim,)), policy.prior_z())
        assert act.shape == (2,) and bool(jnp.all(jnp.isfinite(act)))
    else:
        # seed-screen runs keep their records, not their policies (results/README.md)
        assert folder.startswith("screen/"), f"{folder}: a headline run lost its policy"
        with pytest.raises(CheckpointError, match="policy.msgpack: missing"):
            load_policy(run)
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
        (
            {"pearl.bc_weight": 1.0, "train.mpc_buffer_fraction": 0.5},
            ["train.mpc_buffer_fraction", "pearl.bc_weight"],
        ),
        (
            {
                "pearl.bc_weight": 4.0,
                "pearl.bc_q_filter": False,
                "train.mpc_buffer_fraction": 0.5,
            },
            ["train.mpc_buffer_fraction", "pearl.bc_weight", "pearl.bc_q_filter"],
        ),
        ({"pearl.bc_q_filter": False}, []),  # the presets' inactive residue
        ({"pearl.init_alpha": 0.2, "pearl.reward_scale": 1.0}, ["pearl.init_alpha"]),
        # the MPC buffer held MPC transitions only; its capacity acted only with a fraction
        ({"train.mpc_buffer_fraction": 0.5}, ["train.mpc_buffer_fraction"]),
        ({"train.eps": 0.0, "train.mpc_buffer_fraction": 0.5}, []),  # PEARL: no MPC rows
        ({"train.mpc_buffer_capacity": 200}, []),
        # the kept policy's interval and task count acted only with keep_best
        (
            {"train.keep_best": True, "train.keep_tasks": 8},
            ["train.keep_best", "train.keep_tasks"],
        ),
        ({"train.keep_interval": 3}, []),
        ({"pearl.n_step": 3}, ["pearl.n_step"]),
        # the CrossQ momentum acted only with CrossQ
        (
            {"pearl.crossq": True, "pearl.crossq_momentum": 0.9, "pearl.layer_norm": False},
            ["pearl.crossq", "pearl.crossq_momentum"],
        ),
        ({"pearl.crossq_momentum": 0.9}, []),
        # the guide's roll-in steps, decrement, threshold and window acted only with a share
        (
            {"train.guide_share": 0.5, "train.guide_window": 32},
            ["train.guide_share", "train.guide_window"],
        ),
        ({"train.guide_steps": 40, "train.guide_window": 32}, []),
    ],
)
def test_removed_training_options_load_named_and_round_trip_off(tmp_path, changes, on):
    """A config.json of `default` with a retired option (the warm start, cloning, init_alpha,
    the MPC buffer, the kept policy, n-step returns, CrossQ, the guide) switched on loads for
    evaluation with the options dropped and names exactly those that acted (resume refused
    naming them); their inactive values, and their off values, load silently, resume, and
    round-trip through to_json without the removed fields."""
    import json

    from mpcpearl_jax.config import REMOVED_OPTIONS, removed_options_on
    from mpcpearl_jax.errors import CheckpointError
    from mpcpearl_jax.runfolder import load_config

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


# ------------------------------------------------------------------ resolve and --set
def test_resolve_gives_the_family_its_settings():
    """`config.resolve`: the default preset on the sidewalk validates (its recorded crowd kept,
    its MPC defaults, online adaptation as its headline), where the bare preset does not."""
    from mpcpearl_jax.config import PRESETS, resolve

    with pytest.raises(ConfigError, match="redraw_behaviours"):
        validate(preset("default").replace(env="sidewalk"))
    side = validate(resolve("default", env="sidewalk"))
    assert side.env == "sidewalk" and side.train.redraw_behaviours is False
    assert side.online_eval is True and side.mpc.v_max is None
    rest = validate(resolve("default"))
    assert rest.env == "restaurant" and rest.train.redraw_behaviours is True
    assert rest.online_eval is False and rest.mpc == preset("default").mpc
    # an explicit preset is not rewritten: the sidewalk refuses its re-drawn crowds
    redraws = [n for n, c in PRESETS.items() if c.train.redraw_behaviours and n != "default"]
    with pytest.raises(ConfigError, match="redraw_behaviours"):  # resolve checks across fields
        resolve(redraws[0], env="sidewalk")
    cfg = resolve(
        "smoke",
        "restaurant",
        changes={"train.eps": 0.0, "seed": 3, "mpc.v_max": 2.0},
        overrides=["seed=4", "env.observe_time=true"],
    )
    assert (cfg.train.eps, cfg.seed, cfg.mpc.v_max) == (0.0, 4, 2.0)  # --set comes last
    assert cfg.env_overrides == {"observe_time": True}
    with pytest.raises(ConfigError, match=r"TrainConfig has no field\(s\) \['nope'\]"):
        resolve("smoke", changes={"train.nope": 1})
    with pytest.raises(ConfigError, match="--data .*: no such file"):
        resolve("smoke", "sidewalk", data="/nonexistent/zara.txt")
    with pytest.raises(ConfigError, match="config is of 'restaurant'"):
        resolve(preset("smoke"), env="sidewalk")


def test_one_typed_parser_for_every_set_option():
    """`config.parse_override` / `apply_overrides`: values read by the field's type, for the
    MPC-PEARL config, GrBAL's and a bare MPCConfig, errors one line naming the field."""
    from mpcpearl_jax.config import apply_overrides, override_sections, parse_override
    from mpcpearl_jax.grbal.config import GrbalExperimentConfig
    from mpcpearl_jax.mpc.config import MPCConfig

    sections = override_sections(ExperimentConfig)
    assert list(sections) == ["pearl", "train", "mpc", "env", ""]
    assert parse_override("pearl.hidden=[8,8]", sections) == ("pearl", "hidden", (8, 8))
    assert parse_override("mpc.r_safe=null", sections) == ("mpc", "r_safe", None)
    assert parse_override("train.redraw_behaviours=0", sections)[2] is False
    assert parse_override("train.eps=1", sections)[2] == 1
    for item, needle in [
        ("train.redraw_behaviours=2", "TrainConfig.redraw_behaviours must be true or false"),
        ("train.iterations=true", "TrainConfig.iterations must be an int, not a boolean"),
        ("train.eps=True", "TrainConfig.eps must be a number, not a boolean"),
        ("pearl.nope=1", "PearlConfig has no field(s) ['nope']"),
        ("kitchen.x=1", "unknown section 'kitchen'; use pearl, train, mpc, env or a top-level"),
        ("train.eps", "expected SECTION.FIELD=VALUE"),
    ]:
        with pytest.raises(ConfigError) as e:
            parse_override(item, sections)
        assert needle in str(e.value) and "\n" not in str(e.value), item
    g = apply_overrides(
        GrbalExperimentConfig(),
        ["grbal.hidden=[8,8]", "grbal.robot_model=known", "env.observe_time=true", "seed=2"],
    )
    assert g.grbal.hidden == (8, 8) and g.grbal.robot_model == "known" and g.seed == 2
    assert g.env_overrides == {"observe_time": True}
    with pytest.raises(ConfigError, match="GrbalConfig.iterations must be an int"):
        apply_overrides(g, ["grbal.iterations=true"])
    with pytest.raises(ConfigError, match=r"GrbalConfig has no field\(s\) \['nope'\]"):
        apply_overrides(g, ["grbal.nope=1"])
    with pytest.raises(ConfigError, match="GrbalConfig.past"):
        apply_overrides(g, ["grbal.past=0"])
    mpc = apply_overrides(MPCConfig(), ["unsafe_recovery=True", "v_max=3", "r_safe=None"])
    assert mpc.unsafe_recovery is True and mpc.v_max == 3 and mpc.r_safe is None
    with pytest.raises(ConfigError, match=r"MPCConfig has no field\(s\) \['nope'\]"):
        apply_overrides(mpc, ["nope=1"])


@pytest.mark.parametrize(
    ("cfg", "item", "message"),
    [
        (
            "pearl",
            "pearl.hidden=64,64",
            "PearlConfig.hidden: must be a non-empty tuple of positive "
            "ints, got '64,64' (write it as [64,64])",
        ),
        ("pearl", "pearl.encoder_hidden=(200, 200)", "got '(200, 200)' (write it as [200,200])"),
        ("pearl", "pearl.hidden=64", "got 64 (write it as [64])"),
        ("pearl", "pearl.hidden=wide", "got 'wide' (write it as a list, e.g. [64,64])"),
        (
            "grbal",
            "grbal.hidden=64,64",
            "GrbalConfig.hidden: must be a non-empty tuple of "
            "positive ints, got '64,64' (write it as [64,64])",
        ),
    ],
)
def test_layer_sizes_without_brackets_name_the_form_they_take(cfg, item, message):
    """`--set pearl.hidden=64,64` (and GrBAL's `grbal.hidden`) is text, not a list: the message
    says how the field is written; a bracketed list is taken, a wrong list has no hint."""
    from mpcpearl_jax.config import apply_overrides
    from mpcpearl_jax.grbal.config import GrbalExperimentConfig

    base = ExperimentConfig() if cfg == "pearl" else GrbalExperimentConfig()
    with pytest.raises(ConfigError) as e:
        apply_overrides(base, [item])
    assert message in str(e.value) and "\n" not in str(e.value)
    key = item.partition("=")[0]
    taken = apply_overrides(base, [f"{key}=[64,64]"])
    assert getattr(getattr(taken, cfg), key.partition(".")[2]) == (64, 64)
    with pytest.raises(ConfigError) as e:
        PearlConfig(hidden=(0, 64))
    assert str(e.value).endswith("got (0, 64)")


CONFIG_RUNS = [
    "restaurant/main-default",
    "restaurant/mpc-sac",
    "restaurant/paper-scenarios/cpu-explore-eps0.2",
    "sidewalk/pearl",
    "sidewalk/seeds/mpc-pearl-s0",
]


@pytest.mark.parametrize("run", CONFIG_RUNS)
def test_config_option_builds_the_recorded_run(run):
    """--config RUN/config.json (the training commands, and `experiments.learning`, which takes
    the family from the file): exactly the run's config, the other options on top (--seed
    changes the seed only)."""
    import json

    from mpcpearl_jax.cli.args import build_config, parse_args, parser

    old = {"command": "learning", "from_config": True}  # experiments/learning.py

    path = Path(__file__).resolve().parents[1] / "results" / run / "config.json"
    ref = ExperimentConfig.from_dict(json.loads(path.read_text()))
    env = ref.env
    for extra in ([], ["--seed", "3"]):
        want = ref.replace(seed=3) if extra else ref
        args = parser(env).parse_args(["--config", str(path), *extra])
        assert args.preset == path.parent.name  # the run's name where a preset's would go
        assert build_config(args, env).to_dict() == want.to_dict()
        args = parse_args("restaurant", ["--config", str(path), "--minutes", "1", *extra], **old)
        assert args.env == env  # the old name's command takes the family from the file
        assert build_config(args, args.env).to_dict() == want.to_dict()


def test_config_option_refuses_what_it_cannot_repeat(tmp_path, capsys):
    from mpcpearl_jax.cli.args import build_config, parser
    from mpcpearl_jax.cli.train import main

    root = Path(__file__).resolve().parents[1] / "results"
    removed = root / "restaurant/ablation/policy-ema-60min/config.json"
    with pytest.raises(ConfigError, match=r"switched on .*pearl\.policy_ema.*since removed"):
        build_config(parser("restaurant").parse_args(["--config", str(removed)]), "restaurant")
    side = root / "sidewalk/pearl/config.json"
    with pytest.raises(ConfigError, match="a sidewalk run, not restaurant"):
        build_config(parser("restaurant").parse_args(["--config", str(side)]), "restaurant")
    grbal = root / "restaurant/grbal/config.json"
    for bad, needle in [(grbal, "a grbal run's config"), (tmp_path / "none.json", "none.json")]:
        out = tmp_path / "run"
        assert main("restaurant", ["--config", str(bad), "--out", str(out)]) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("error: --config") and needle in err and "\n" not in err
        assert not out.exists()
    with pytest.raises(SystemExit):  # a preset or a run's config, not both
        parser("restaurant").parse_args(["--preset", "smoke", "--config", str(side)])


def test_the_removed_mpc_solver_option_loads_old_configs_and_is_a_one_line_error(tmp_path):
    """`mpc.solver` and `mpc.device_qp_iters` (the device solver, removed): a config.json that
    has them loads with them dropped, resumable at the host solver ("osqp") or where the MPC
    never acted (eps 0); a run that trained with the device solver loads for evaluation and is
    refused for resuming; setting either is a one-line error naming the removal."""
    import json

    from mpcpearl_jax.config import removed_options_on, resolve
    from mpcpearl_jax.errors import CheckpointError
    from mpcpearl_jax.runfolder import load_config

    base = preset("default")
    old = json.loads(base.to_json())  # a config.json written with the option
    old["mpc"].update(solver="osqp", device_qp_iters=30)
    assert removed_options_on(old) == [] and ExperimentConfig.from_dict(old) == base
    old["mpc"]["device_qp_iters"] = 10  # acted only with the device solver
    assert removed_options_on(old) == []
    old["mpc"]["solver"] = "device"
    assert removed_options_on(old) == ["mpc.solver", "mpc.device_qp_iters"]
    assert ExperimentConfig.from_dict(old) == base
    (tmp_path / "config.json").write_text(json.dumps(old))
    assert load_config(tmp_path) == base
    with pytest.raises(CheckpointError, match="mpc.solver, mpc.device_qp_iters"):
        load_config(tmp_path, resume=True)
    old["train"]["eps"] = 0.0  # PEARL: the MPC never acted
    assert removed_options_on(old) == []
    for item in ("mpc.solver=device", "mpc.solver=osqp", "mpc.device_qp_iters=30"):
        with pytest.raises(ConfigError) as e:
            resolve("default", overrides=[item])
        msg = str(e.value)
        assert "removed" in msg and "Removed options" in msg and "\n" not in msg
    with pytest.raises(TypeError):
        MPCConfig(solver="device")  # type: ignore[call-arg]


def test_a_seed_beyond_64_bits_or_negative_is_one_line_before_anything_runs(capsys):
    """--seed 1180591620717411303424 ended in an OverflowError traceback when the seeds' PRNG keys
    were made (--print-config accepted it); a negative seed failed later in the host streams of
    re-drawn crowds. Now both are refused where the config is resolved, --print-config too."""
    from mpcpearl_jax.cli.train import main

    top = 2**63 - 2
    cases = [
        (["--seed", "1180591620717411303424"], "seed: must be at most"),
        (["--seed", str(top + 1), "--seeds", "2"], f"seed: must be at most {top}"),
        (["--seed=-1"], "seed: must be a non-negative int"),
        (["--set", "task_seed=-3"], "task_seed: must be a non-negative int"),
    ]
    for extra, msg in cases:
        for mode in ([], ["--print-config"]):
            assert main("restaurant", ["--preset", "smoke", *extra, *mode]) == 2, extra
            err = capsys.readouterr().err.strip()
            assert err.startswith("error: ") and msg in err and "\n" not in err, err
    assert ExperimentConfig(seed=2**63 - 1).seed == 2**63 - 1


def test_an_unknown_field_in_a_config_file_is_named_as_set_names_it(tmp_path):
    """A --config file (or a run's config.json) with a field no section has: the words of --set
    ('TrainConfig has no field(s) ['foo']'), not Python's raw __init__() message."""
    base = ExperimentConfig().to_dict()
    cases = [
        ({**base, "train": {**base["train"], "foo": 1}}, "TrainConfig has no field(s) ['foo']"),
        ({**base, "pearl": {**base["pearl"], "foo": 1}}, "PearlConfig has no field(s) ['foo']"),
        ({**base, "bar": 2}, "ExperimentConfig has no field(s) ['bar']"),
    ]
    for bad, msg in cases:
        with pytest.raises(ConfigError, match=re.escape(msg)):
            ExperimentConfig.from_dict(bad)
