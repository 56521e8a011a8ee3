"""The training commands' memory check names the fields that made the state too large: the
observation's (env.observe_forecast) when the replay buffers are what grew, the network's
(pearl.crowd_dim) when the networks are, not only train.rl_capacity, the tasks or the seeds."""

from __future__ import annotations

import pytest

from mpcpearl_jax.cli.train import main
from mpcpearl_jax.training.resources import dataclass_defaults, grown_fields

RELATIVE = ["--set", "env.observe_relative=true"]
ENCODER = [
    *RELATIVE,
    "--set",
    "env.observe_presence=true",
    "--set",
    "pearl.crowd_encoder=attention",
]


@pytest.mark.parametrize(
    "extra, first, part",
    [
        (
            [*RELATIVE, "--set", "env.observe_forecast=100000"],
            "env.observe_forecast=100000",
            "replay",
        ),
        ([*ENCODER, "--set", "pearl.crowd_dim=400000"], "pearl.crowd_dim=400000", "networks"),
    ],
)
def test_the_memory_check_names_the_field_that_grew(tmp_path, capsys, extra, first, part):
    out = tmp_path / "run"
    assert main("restaurant", ["--no-progress", "--out", str(out), *extra]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"error: {first}"), err
    assert "train.rl_capacity" in err[0] and "lower them" in err[0]  # still named, after it
    assert f"{part}" in err[0] and not out.exists()


def test_grown_fields_compares_with_the_defaults():
    from mpcpearl_jax.pearl.config import PearlConfig

    defaults = dataclass_defaults(PearlConfig)
    got = {"crowd_dim": 128, "hidden": (300, 300, 300, 300), "latent_dim": 5, "lr": 1.0}
    got["crowd_encoder"] = "attention"
    assert grown_fields(got, defaults, "pearl") == [
        "pearl.crowd_dim=128",
        "pearl.hidden=300,300,300,300",
    ]


def test_grbal_memory_check_names_the_model_width_that_grew(tmp_path, capsys, monkeypatch):
    """GrBAL's check blamed the planner and the buffers (grbal.plan_horizon, num_samples,
    buffer_episodes, the seeds) for a model made too wide by grbal.hidden: the model's width is
    now named first when the model and its optimizer are the larger part."""
    from experiments import grbal
    from mpcpearl_jax.training import resources

    monkeypatch.setattr(resources, "free_bytes", lambda: 2**30)
    out = tmp_path / "run"
    argv = ["--preset", "smoke", "--no-progress", "--out", str(out)]
    assert grbal.main([*argv, "--set", "grbal.hidden=[20000,20000]"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: grbal.hidden=20000,20000, or "), err
    assert "grbal.num_samples" in err[0] and "model and optimizer" in err[0]
    assert grbal.main([*argv, "--set", "grbal.buffer_episodes=1000000"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: grbal.plan_horizon, "), err
    assert "grbal.hidden" not in err[0] and not out.exists()
