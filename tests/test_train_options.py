"""`TrainOptions` checks each option's type when it is built: a TypeError naming the option and
what it expects, not a bare comparison error inside `mpcpearl_jax.train`."""

from __future__ import annotations

import pytest

from mpcpearl_jax.training.final import TrainOptions


@pytest.mark.parametrize(
    "option, value",
    [
        ("eval_minutes", "5"),
        ("eval_minutes", True),
        ("resume", "yes"),
        ("overwrite", 1),
        ("policy_only", None),
        ("tensorboard", "false"),
        ("record", ["preset"]),
        ("clock", 5.0),
        ("on_start", "print"),
        ("on_row", 3),
        ("on_point", object()),
        ("on_trained", True),
    ],
)
def test_a_wrong_type_names_the_option(option, value):
    with pytest.raises(TypeError, match=rf"^TrainOptions: {option} must be .*, not "):
        TrainOptions(**{option: value})


def test_the_right_types_are_taken():
    opts = TrainOptions(
        resume=True, eval_minutes=5, record={"preset": "default"}, on_row=print, clock=lambda: 0.0
    )
    assert opts.eval_minutes == 5 and opts.resume
    assert TrainOptions(eval_minutes=2.5, on_trained=None).eval_minutes == 2.5
