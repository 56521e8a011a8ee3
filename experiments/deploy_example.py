"""The committed MPC-PEARL policy in a control loop fed raw arrays, adapting online (run from the
repository root: python -m experiments.deploy_example; docs/deploy.md explains each call)."""

import time

import jax

from mpcpearl_jax import Adapter, Frame, Scene, load_exported, make_env, make_tasks

start = time.perf_counter()
policy = load_exported("results/restaurant/mpc-pearl-eps0.2/policy.export")  # or load_policy(run)
adapter = Adapter(policy)  # the run's observation options; z re-inferred every 5 transitions

# Stand-in for a robot, its sensors and a crowd: the 24 unseen restaurant test tasks.
world, tasks = make_env("restaurant"), make_tasks("restaurant", "test")
drive = jax.jit(world.step)
successes = 0
for i in range(tasks.num_tasks):
    task = jax.tree_util.tree_map(lambda x, i=i: x[i], tasks)
    key = jax.random.PRNGKey(i)
    scene = Scene.from_task(task)  # goal and static obstacles; or Scene.circles(goal, centres, r)
    state = adapter.init(scene, key)  # a new task: empty context, z drawn from the prior
    _, robot = world.reset(key, task)
    frame = Frame.start(robot.pose, task.human_pos[0], task.human_mask[0])
    reached = touched = False
    for t in range(world.config.horizon):
        action = adapter.act(state, frame)  # [-1, 1]^2; adapter.command: (v m/s, delta rad)
        _, robot, _, _, info = drive(key, robot, action, task)  # the robot moves
        # sense again: pose, the people (rows = identities) and who of them is there
        nxt = frame.advance(robot.pose, task.human_pos[t + 1], task.human_mask[t + 1])
        state = adapter.add(state, frame, action, nxt)  # reward of eq. (2), context row, z
        frame = nxt
        reached, touched = reached or bool(info.in_goal), touched or bool(info.collision)
    successes += reached and not touched
print(f"SR {successes / tasks.num_tasks:.2f} on {tasks.num_tasks} unseen tasks, online adaptation")
print(f"({time.perf_counter() - start:.0f} s)")
