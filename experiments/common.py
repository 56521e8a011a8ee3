"""The names the experiment commands share, from the command layer `mpcpearl_jax.cli`: the
training command (`main`, `cli.train`), the task-source options (`cli.args`), the one error
ladder (`cli.errors`) and the stop signals (`cli.stopping`). Imports only: the code lives
in `mpcpearl_jax.cli`."""

from __future__ import annotations

from mpcpearl_jax.cli.args import add_task_source_options  # noqa: F401  (the commands' names)
from mpcpearl_jax.cli.errors import one_line_errors  # noqa: F401
from mpcpearl_jax.cli.stopping import stops_with  # noqa: F401
from mpcpearl_jax.cli.train import main  # noqa: F401
