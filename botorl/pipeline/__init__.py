"""The offline-to-online pipeline: what ``botorl run`` / ``resume`` / ``eval`` / ``export`` do.

    botorl run                                   # BOTO on pointmaze-umaze, quick profile, data made here
    botorl run --task door-binary-v0 --method boto --profile full --data.path ~/calql-data
    botorl run --task door-binary-local --profile quick        # demos shipped in botorl/data/assets
    botorl run --task pointmaze-large --method wsrl --seed 1 --online.steps 50000
    botorl resume runs/pointmaze-large-boto-s0-20260101-120000
    botorl eval runs/pointmaze-large-boto-s0-20260101-120000 --episodes 50

Modules: ``stages`` (pretrain, warmup, boto, finetune), ``online`` (fine-tuning's resumable
state), ``runner`` (order, checkpoints, resume, summary, curve), ``evaluation`` (lockstep
episodes, Q statistics), ``population`` (a population's memory), ``rundir`` / ``checkpoint``
(the files of a run directory: CONTRACTS.md "Runs"), ``policy`` / ``export`` (a run's policy
outside botorl), ``cli`` (the commands). The configs, presets, the method table and the
population's members are in ``botorl.configs``; a population's mapped calls in
``botorl.agents.population``.
"""
