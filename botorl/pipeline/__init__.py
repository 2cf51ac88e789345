"""The offline-to-online pipeline: what ``botorl run`` / ``resume`` / ``eval`` do.

    botorl run                                   # BOTO on pointmaze-umaze, quick profile, data made here
    botorl run --task door-binary-v0 --method boto --profile full --data.path ~/calql-data
    botorl run --task door-binary-local --profile quick        # demos shipped in botorl/data/assets
    botorl run --task pointmaze-large --method wsrl --seed 1 --online.steps 50000
    botorl resume runs/pointmaze-large-boto-s0-20260101-120000
    botorl eval runs/pointmaze-large-boto-s0-20260101-120000 --episodes 50

Modules: ``stages`` (pretrain, warmup, boto, finetune), ``online`` (fine-tuning's resumable
state), ``runner`` (order, checkpoints, resume, summary, curve), ``evaluation`` (lockstep
episodes, Q statistics), ``population`` (a population's memory), ``rundir`` / ``checkpoint``
(the files), ``cli`` / ``population_cli``. The configs, presets, the method table and the
population's members are in ``botorl.configs``; a population's mapped calls in
``botorl.agents.population``.

Run directory (CONTRACTS.md "Runs"):

    config.json                 resolved RunConfig (top level: task, method, seed, alpha, pretrain, profile)
    eval.csv                    stage, env_step, success, return, q_data, q_uniform (env_step 0 = start of fine-tuning)
    metrics/<stage>.csv/.jsonl  training metrics per stage (pretrain, warmup, boto, finetune)
    metrics/q_probe.csv         q_data / q_uniform at the end of pretrain and boto
    tb/                         TensorBoard events (if tensorboardX is installed)
    checkpoints/latest.json     the newest complete checkpoint
    checkpoints/<stage>-final/  agent.ckpt (+ warmup.npz = D_warmup), state.json
    checkpoints/<stage>-stepNNNNNNNNN/   the newest mid-stage checkpoint (agent, buffer.npz, rng, step)
    curve.png                   success vs online env steps, warm-up shaded, fine-tuning start marked
    summary.json                success_initial / _10k / _final, stage_seconds, status, ...
    eval-<checkpoint>.json      written by `botorl eval`
"""
