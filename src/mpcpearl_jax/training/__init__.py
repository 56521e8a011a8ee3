"""Meta-training: the trainer (Algorithm 1, `trainer`, with its collection phases in `collect`),
the run session that opens, trains and closes a run folder (`run`: checks, lock, restore, log,
Ctrl-C, the MPC bridge's pool), the one training loop (`loop`), and the run folder's files
(`checkpoint`, `runlock`, `livelog`, `resources`, `machine`)."""
