"""The offline-to-online pipeline: what ``botorl run`` / ``resume`` / ``eval`` / ``export`` do
(docs/running.md).

Modules: ``stages`` (pretrain, warmup, boto, finetune), ``online`` (fine-tuning's resumable
state), ``runner`` (order, checkpoints, resume, summary, curve), ``evaluation`` (lockstep
episodes, Q statistics), ``population`` (a population's memory), ``rundir`` / ``checkpoint``
(the files of a run directory: CONTRACTS.md "Runs"), ``policy`` / ``export`` (a run's policy
outside botorl), ``cli`` (the commands). The configs, presets, the method table and the
population's members are in ``botorl.configs``; a population's mapped calls in
``botorl.agents.population``.
"""
