"""Collection without the MPC (eps = 0) never waits on the host: no MPC guard or host callback in
its program, even with a bridge at hand, and no transfer between host and device once compiled,
neither in `make_collector`'s program nor in the trainer's collection phases."""

import contextlib
from collections import Counter

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mpcpearl_jax import collection as collect_lib

# primitives that stop the device for the host: a callback, or (on a GPU) a branch whose
# predicate the host reads
HOST_WAITS = ("cond", "pure_callback", "debug_callback", "io_callback")


def _primitives(jaxpr, acc: Counter | None = None) -> Counter:
    """Every primitive of a jaxpr, the bodies of its scans, branches and calls included."""
    from jax.extend.core import jaxprs_in_params

    acc = Counter() if acc is None else acc
    for eqn in jaxpr.eqns:
        acc[eqn.primitive.name] += 1
        for sub in jaxprs_in_params(eqn.params):
            _primitives(sub, acc)
    return acc


@contextlib.contextmanager
def no_transfers():
    """`jax.transfer_guard("disallow")`, which on an accelerator refuses every implicit transfer
    and on a CPU the host-to-device ones (reading a CPU array copies nothing, so the guard lets
    it pass); reads of a device array's value (`np.asarray`, `np.array`, `int`, `float`,
    `device_get`, ...) are refused here on every backend."""
    array_type = type(jnp.zeros(()))

    def refuse(*_):
        raise AssertionError("a device array was read on the host during collection")

    def guarded(fn):
        def call(a, *args, **kw):
            if isinstance(a, jax.Array) and not isinstance(a, jax.core.Tracer):
                refuse()
            return fn(a, *args, **kw)

        return call

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(array_type, "_value", property(refuse))
        for name in ("asarray", "array", "asanyarray"):
            mp.setattr(np, name, guarded(getattr(np, name)))
        with jax.transfer_guard("disallow"):
            yield


@pytest.fixture(scope="module")
def trainer():
    from mpcpearl_jax.training.trainer import Trainer
    from tests.test_training import TINY

    return Trainer(TINY)


def _inputs(trainer, rows: int = 3):
    """(key, policy params [S], z [S, R, L], tasks [S, R]) on the device."""
    state = trainer.init_state()
    s = trainer.cfg.seeds
    ids = jnp.arange(s * rows).reshape(s, rows) % trainer.num_train
    z = jax.random.normal(jax.random.PRNGKey(1), (s, rows, trainer.cfg.pearl.latent_dim))
    tasks = jax.vmap(collect_lib.rows_of)(state.tasks, ids)
    args = (jax.random.PRNGKey(0), state.learner.params["policy"], z, tasks)
    return jax.device_put(args)


def test_the_guard_sees_reads_of_device_arrays():
    x = jax.jit(lambda a: a * 2)(jax.device_put(np.arange(3.0)))
    reads = (
        lambda a: np.asarray(a),  # looked up when called: the guard patches np.asarray
        lambda a: np.array(a),
        lambda a: float(a.sum()),
        jax.device_get,
        lambda a: a.tolist(),
    )
    for read in reads:
        with pytest.raises(Exception), no_transfers():  # noqa: B017 (the backend's error or ours)
            read(x)
    with pytest.raises(Exception), no_transfers():  # noqa: B017
        jax.jit(lambda a: a * 2)(np.arange(3.0))  # host-to-device


def test_eps0_collection_holds_no_mpc_guard_or_callback(trainer):
    """With a bridge but eps = 0 the program is that of no bridge: no MPC guard, no callback."""
    from mpcpearl_jax.mpc import make_mpc_bridge

    env, nets = trainer.env, trainer.nets
    bridge = make_mpc_bridge(env, trainer.cfg.mpc)
    args = _inputs(trainer)
    trace = lambda b, eps: _primitives(  # noqa: E731
        jax.make_jaxpr(collect_lib.make_collector(env, nets, b, eps))(*args).jaxpr
    )
    with_bridge, without = trace(bridge, 0.0), trace(None, 0.0)
    assert not any(with_bridge[p] for p in HOST_WAITS), with_bridge
    assert with_bridge == without
    mpc = trace(bridge, 0.2)  # the MPC's own guard and callback are seen where eps > 0
    assert mpc["cond"] > 0 and mpc["pure_callback"] == 1


def test_eps0_collection_runs_without_host_transfers(trainer):
    from mpcpearl_jax.mpc import make_mpc_bridge

    bridge = make_mpc_bridge(trainer.env, trainer.cfg.mpc)
    collect = jax.jit(collect_lib.make_collector(trainer.env, trainer.nets, bridge, 0.0))
    args = _inputs(trainer)
    jax.block_until_ready(collect(*args))  # compiles
    with no_transfers():
        ep = jax.block_until_ready(collect(*args))
    assert ep.position.shape[:2] == args[2].shape[:2]
    assert not np.any(np.asarray(ep.used_mpc)) and bridge.stats()["calls"] == 0


def test_trainer_collection_phases_run_without_host_transfers(trainer):
    """The trainer's collection phases (initial, prior, posterior; eps = 0) after a first,
    compiling call of each: no transfer between host and device inside them."""
    state = trainer.init_state()
    state, ids = trainer._choose_tasks(state, trainer.cfg.train.tasks_per_iteration)
    state, ids = jax.device_put((state, ids))

    def phases(state):
        state, _ = trainer.initial_collection(state)
        state, prior = trainer.prior_collection(state, ids)
        state, post = trainer.posterior_collection(state, ids)
        return jax.block_until_ready((state, prior, post))

    state, _, _ = phases(state)  # compiles
    with no_transfers():
        state, prior, post = phases(state)
    tc = trainer.cfg.train
    assert tc.eps == 0.0 and trainer.bridge is None
    assert int(post["steps"]) == tc.tasks_per_iteration * tc.posterior_episodes * trainer.horizon
    assert np.all(np.isfinite(np.asarray(prior["return"])))
