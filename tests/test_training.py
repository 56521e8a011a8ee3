"""Meta-training end to end at tiny scale: tracing, resume, checkpoints, load_policy, CLI."""

import json

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from faults_helpers import train_only

from mpcpearl_jax.config import ExperimentConfig, PearlConfig, TrainConfig, preset
from mpcpearl_jax.deploy.policy import load_policy
from mpcpearl_jax.errors import ConfigError
from mpcpearl_jax.training.checkpoint import CheckpointError
from mpcpearl_jax.training.trainer import Trainer

TINY = ExperimentConfig(
    seeds=2,
    pearl=PearlConfig(
        hidden=(16, 16),
        encoder_hidden=(16,),
        latent_dim=3,
        meta_batch=3,
        batch_size=16,
        context_size=8,
    ),
    train=TrainConfig(
        iterations=3,
        initial_episodes=1,
        tasks_per_iteration=2,
        prior_episodes=1,
        posterior_episodes=1,
        updates_per_iteration=3,
        rl_capacity=400,
        eps=0.0,
        eval_interval=0,
        checkpoint_interval=1,
        keep_checkpoints=2,
    ),
)


@pytest.fixture(scope="module")
def trainer():
    return Trainer(TINY)


def _leaves_equal(a, b):
    la, lb = jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)
    assert len(la) == len(lb)
    for x, y in zip(la, lb, strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_collection_and_update_trace_once(trainer):
    state = trainer.init_state()
    state, _ = trainer.initial_collection(state)
    steps = jax.jit(chex.assert_max_traces(trainer._update_steps, n=1), donate_argnums=0)
    chunks, trainer._update_steps_jit = trainer._update_steps_jit, steps
    try:
        for _ in range(2):
            state, m = trainer.update_phase(state)
    finally:
        trainer._update_steps_jit = chunks
    assert np.all(np.isfinite(np.asarray(m["q_loss"])))
    coll = jax.jit(chex.assert_max_traces(trainer._collector, n=1))
    rows = jnp.array([[0, 1], [2, 3]])
    tasks = jax.tree_util.tree_map(lambda x: x[rows], trainer.train_tasks)
    for i in range(2):
        z = jax.random.normal(jax.random.PRNGKey(i), (2, 2, 3))
        ep = coll(jax.random.PRNGKey(i), state.learner.params["policy"], z, tasks)
    assert ep.transitions.obs.shape == (2, 2, trainer.horizon, trainer.obs_dim)
    assert ep.position.shape == (2, 2, trainer.horizon + 1, 2)
    chex.clear_trace_counter()


def test_buffers_fill_and_encoder_buffer_resets(trainer):
    state = trainer.init_state()
    state, log = trainer.iteration(state)
    T = trainer.horizon
    rl_size = np.asarray(state.rl.size)
    enc_size = np.asarray(state.enc.size)
    # iteration 1: all tasks got 1 initial episode; 2 tasks got 1 prior + 1 posterior more
    assert rl_size.shape == (2, trainer.num_train)
    assert np.all(np.isin(rl_size, [T, 3 * T]))
    assert np.all((rl_size == 3 * T).sum(1) == 2)
    # encoder buffer: only the most recent prior collection (cleared on the visit)
    assert np.all(enc_size == T)
    assert log["iteration"] == 1 and np.isfinite(log["q_loss"])


@pytest.mark.slow  # (~70 s); exact resume in the fast set: test_faults_resume
def test_resume_equals_uninterrupted(tmp_path):
    cfg = TINY
    _, full = train_only(cfg, tmp_path / "full")
    short = cfg.replace(train=TrainConfig(**{**cfg.train.__dict__, "iterations": 2}))
    train_only(short, tmp_path / "cut")
    # the clocks of the kept rows, pushed 1000 s on: a resumed run's train_s and wall_s go on
    # from its last kept row (they are over the run's lifetime), they do not start again at 0
    path = tmp_path / "cut" / "metrics.jsonl"
    kept = [json.loads(x) for x in path.read_text().splitlines()]
    for r in kept:
        r.update(train_s=r["train_s"] + 1000.0, wall_s=r["wall_s"] + 1000.0)
    path.write_text("".join(json.dumps(r) + "\n" for r in kept))
    _, resumed = train_only(cfg, tmp_path / "cut", resume=True)
    _leaves_equal(full, resumed)
    log = [json.loads(x) for x in path.read_text().splitlines()]
    assert [r["iteration"] for r in log] == [1, 2, 3]
    for key in ("train_s", "wall_s"):
        assert log[2][key] > log[1][key] > 1000.0, [r[key] for r in log]


@pytest.mark.slow  # exact resume: test_resume_equals_uninterrupted runs in the fast set (~75 s)
def test_learned_entropy_weight_resumes_exactly(tmp_path):
    """Extension `pearl.auto_entropy`: log alpha and its optimizer state are part of the
    checkpointed learner state (resume is exact), each seed has its own, and the log has it."""
    cfg = TINY.replace(pearl=TINY.pearl.replace(auto_entropy=True, target_entropy=5.0))
    _, full = train_only(cfg, tmp_path / "full")
    short = cfg.replace(train=TrainConfig(**{**cfg.train.__dict__, "iterations": 2}))
    train_only(short, tmp_path / "cut")
    _, resumed = train_only(cfg, tmp_path / "cut", resume=True)
    _leaves_equal(full, resumed)
    alpha = np.exp(np.asarray(full.learner.log_alpha))
    assert alpha.shape == (cfg.seeds,) and np.all(alpha > 1.0)  # entropy below the target 5
    log = [json.loads(x) for x in (tmp_path / "full" / "metrics.jsonl").read_text().splitlines()]
    assert all(r["alpha"] >= 1.0 for r in log) and log[-1]["alpha"] > log[0]["alpha"]


def test_resume_with_other_config_is_a_clear_error(tmp_path):
    train_only(TINY, tmp_path / "run")
    other = TINY.replace(pearl=TINY.pearl.replace(lr=1e-3))
    with pytest.raises(CheckpointError, match="pearl.lr"):
        train_only(other, tmp_path / "run", resume=True)
    with pytest.raises(CheckpointError, match="--resume"):
        train_only(TINY, tmp_path / "run")


def _garble(ckpt_dir):
    for p in ckpt_dir.rglob("*"):
        if p.is_file() and p.stat().st_size > 0 and "metadata" not in p.name:
            p.write_bytes(b"garbage")


@pytest.mark.slow  # (~14 s); checkpoint errors: test_faults_cli
def test_corrupt_checkpoint_is_a_clear_error(tmp_path, capsys):
    run = tmp_path / "run"
    train_only(TINY, run)
    ckpts = sorted((run / "checkpoints").iterdir(), key=lambda p: int(p.name))
    assert len(ckpts) == TINY.train.keep_checkpoints  # keeps only the last few
    longer = TINY.replace(train=TrainConfig(**{**TINY.train.__dict__, "iterations": 5}))
    for c in ckpts:
        _garble(c)
    with pytest.raises(CheckpointError, match="no intact checkpoint"):
        train_only(longer, run, resume=True)
    assert "cannot restore" in capsys.readouterr().err  # each one reported
    (run / "policy.msgpack").write_bytes(b"junk")
    with pytest.raises(CheckpointError, match="policy.msgpack"):
        load_policy(run)


def test_load_policy_acts_like_training_policy(tmp_path):
    trainer, state = train_only(TINY, tmp_path / "run")
    pol = load_policy(tmp_path / "run", seed_index=1)
    obs = jax.random.uniform(jax.random.PRNGKey(0), (5, trainer.obs_dim), minval=-1, maxval=1)
    z = jax.random.normal(jax.random.PRNGKey(1), (5, 3))
    params1 = jax.tree_util.tree_map(lambda x: x[1], state.learner.params["policy"])
    ref = trainer.nets.act(params1, obs, z, None)
    act, infer = pol.jit()
    np.testing.assert_allclose(act(obs, z), ref, rtol=1e-6)
    ctx = jax.random.normal(jax.random.PRNGKey(2), (8, trainer.nets.context_dim))
    zc = infer(ctx)
    assert zc.shape == (3,)
    a = jax.jit(pol.__call__)(obs, ctx)
    assert a.shape == (5, 2) and bool(jnp.all(jnp.abs(a) <= 1))
    with pytest.raises(ValueError, match="seed_index"):
        load_policy(tmp_path / "run", seed_index=2)
    # the network dims are saved beside the parameters; without them (runs saved before
    # network.json existed) they come from the parameter shapes
    spec = json.loads((tmp_path / "run" / "network.json").read_text())
    assert spec == trainer.nets.spec()
    (tmp_path / "run" / "network.json").unlink()
    old = load_policy(tmp_path / "run", seed_index=1)
    assert old.nets.spec() == spec
    np.testing.assert_array_equal(np.asarray(old.jit()[0](obs, z)), np.asarray(act(obs, z)))


@pytest.mark.parametrize(
    "make",
    [
        lambda: TrainConfig(eps=1.5),
        lambda: TrainConfig(updates_per_iteration=0),
        lambda: TrainConfig(iterations=-3),
        lambda: ExperimentConfig(seeds=0),
    ],
)
def test_invalid_train_config_is_rejected(make):
    with pytest.raises(ConfigError, match=r"\.(eps|updates_per_iteration|iterations|seeds)"):
        make()


def test_experiment_config_is_typed_all_the_way_down():
    from mpcpearl_jax.mpc import MPCConfig
    from mpcpearl_jax.pearl.config import PearlConfig as PC

    cfg = ExperimentConfig(mpc={"r_safe": 0.3})  # a dict of MPCConfig fields is converted
    assert isinstance(cfg.mpc, MPCConfig) and cfg.mpc == MPCConfig(r_safe=0.3)
    back = ExperimentConfig.from_json(cfg.to_json())
    assert back == cfg and isinstance(back.mpc, MPCConfig)
    # an older config.json holds only the MPC fields that were changed
    old = ExperimentConfig.from_dict({"mpc": {"unsafe_recovery": True}})
    assert old.mpc == MPCConfig(unsafe_recovery=True)
    with pytest.raises(ConfigError, match=r"MPCConfig has no field\(s\) \['speed'\]"):
        ExperimentConfig(mpc={"speed": 1.0})
    with pytest.raises(ConfigError, match=r"ExperimentConfig.env_overrides: .*\['speed'\]"):
        ExperimentConfig(env_overrides={"speed": 1.0})
    # one validation helper: every class names the field, booleans are not numbers
    for make, field in [
        (lambda: PC(latent_dim=True), "PearlConfig.latent_dim"),
        (lambda: PC(max_grad_norm=0.0), "PearlConfig.max_grad_norm"),
        (lambda: MPCConfig(osqp_polish=1), "MPCConfig.osqp_polish"),
        (lambda: TrainConfig(redraw_behaviours="yes"), "TrainConfig.redraw_behaviours"),
        (lambda: ExperimentConfig(online_eval="no"), "ExperimentConfig.online_eval"),
        (lambda: ExperimentConfig(seed=1.5), "ExperimentConfig.seed"),
    ]:
        with pytest.raises(ConfigError, match=field.replace(".", r"\.")):
            make()


def test_cli_rejects_bad_values(capsys):
    from mpcpearl_jax.cli.train import main

    assert main("restaurant", ["--preset", "smoke", "--eps", "2"]) == 2
    assert "TrainConfig.eps" in capsys.readouterr().err
    assert main("restaurant", ["--preset", "smoke", "--set", "pearl.nope=1"]) == 2
    assert "nope" in capsys.readouterr().err
    assert main("restaurant", ["--preset", "nosuch"]) == 2
    assert "unknown preset 'nosuch'" in capsys.readouterr().err


def test_restaurant_cli_smoke(tmp_path):
    """The README's main command at the smoke preset, PEARL and MPC-SAC variants (eps = 0)."""
    from mpcpearl_jax.cli.train import main

    out = tmp_path / "r"
    assert (
        main(
            "restaurant",
            [
                "--preset",
                "smoke",
                "--eps",
                "0",
                "--iterations",
                "2",
                "--out",
                str(out),
                "--no-progress",
            ],
        )
        == 0
    )
    res = json.loads((out / "results.json").read_text())
    for m in ("SR", "TT", "CFR", "SPL", "MGD"):
        assert m in res["test_adapt"] and m in res["test_online"]
    assert (out / "learning_curves.png").stat().st_size > 1000
    assert len((out / "metrics.jsonl").read_text().splitlines()) == 2
    # and the comparison command on the finished run
    from lab import compare

    assert compare.main([str(out), "--out", str(tmp_path / "cmp")]) == 0
    assert (tmp_path / "cmp" / "curves.png").stat().st_size > 1000
    assert "| SR |" in (tmp_path / "cmp" / "table.md").read_text()


def test_presets_are_valid():
    for name in ("smoke", "default", "cpu-explore", "recipe", "paper"):
        cfg = preset(name)
        assert cfg.train.iterations > 0
    assert preset("paper").pearl == PearlConfig()
    assert preset("paper").train == TrainConfig()


@pytest.mark.slow
def test_short_run_improves_training_return(tmp_path):
    """A few minutes of PEARL training raise the return on the training tasks."""
    cfg = preset("default").replace(
        train=TrainConfig(
            **{**preset("default").train.__dict__, "eps": 0.0, "iterations": 16, "eval_interval": 0}
        )
    )
    train_only(cfg, tmp_path / "run")
    rows = [json.loads(x) for x in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    first = np.mean([r["train_return"] for r in rows[:5]])
    last = np.mean([r["train_return"] for r in rows[-5:]])
    assert last > first + 50, (first, last)
