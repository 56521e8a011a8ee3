"""The names the experiment commands share, from the command layer `mpcpearl_jax.cli`: the
training command (`main`, `cli.train`), building a config from a command line (`cli.args`),
the one error ladder (`cli.errors`) and the stop signals (`cli.stopping`)."""

from __future__ import annotations

from mpcpearl_jax.cli.args import (  # noqa: F401  (the commands' names for them)
    add_config_options,
    add_run_mode_options,
    add_task_source_options,
    build_config,
    config_help,
    env_family,
    field_comments,
    parse_args,
    parser,
)
from mpcpearl_jax.cli.errors import (  # noqa: F401
    Outcome,
    error_line,
    fail_line,
    one_line_errors,
    out_of_memory,
)
from mpcpearl_jax.cli.stopping import (  # noqa: F401
    exit_interrupted,
    stop_exit_code,
    stoppable,
    stops_with,
)
from mpcpearl_jax.cli.train import finished_line, main, trained_line  # noqa: F401
from mpcpearl_jax.config import ExperimentConfig  # noqa: F401
