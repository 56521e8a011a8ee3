"""Meta-training: the trainer (Algorithm 1, `trainer`; its episodes come from
`mpcpearl_jax.collection`), the run session that opens, trains and closes a run folder (`run`:
checks, lock, restore, log, the MPC bridge's pool; the iterations mode), the one training loop
(`loop`), training on a time budget with its learning curve (`budget`: the minutes mode), the
end of a training and the one entry to it, for Python and the commands (`final`: `train`,
`TrainOptions`, `finish`, the final evaluation), the stop flag of stop signals (`stopping`),
and what a run keeps beside its files (`mpcpearl_jax.runfolder`): orbax checkpoints
(`checkpoint`), the folder's lock (`runlock`), TensorBoard (`livelog`), memory checks
(`resources`) and the machine's record (`machine`)."""
