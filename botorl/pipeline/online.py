"""The online loop's resumable state: everything besides the agents that decides what comes next.

``OnlineState`` (the members' envs mid-episode, observations, counters, the replay buffer with
a member axis, each member's batch generator, the step) is built from explicit inputs. Its
``state_dict()`` is the whole state for a checkpoint and ``load_state_dict()`` restores it, so a
resumed loop repeats an uninterrupted one exactly (docs/CONTRACTS.md "Runs"). What a method needs
of it is in its ``Method`` (``finished_episodes_only``: Cal-QL's batches of finished episodes, MC
returns filled when one ends; ``batch_layout``; botorl/configs/methods.py).
"""

from __future__ import annotations

from typing import Callable

import jax
import numpy as np

from botorl.agents import population
from botorl.data.dataset import Dataset, RewardTransform
from botorl.data.replay import ReplayBuffer
from botorl.envs.metric import episode_success
from botorl.envs.state import get_env_state, set_env_state
from botorl.errors import warn
from botorl.pipeline.checkpoint import CheckpointCorrupt


class OnlineState:
    """The online loop's state beside the agents (the module docstring), with the MC-return rule
    ``mc_returns``, the ``success_mode`` and the ``offline`` data batches mix in at
    ``cfg.offline_ratio``. With ``learning`` off (the warm-up) it only acts and stores; while
    ``ended`` is a list (the warm-up's, never saved: it is not resumed mid-way) each member's
    episode ends go into it as buffer rows, for D_warmup."""

    def __init__(self, envs: list, buffer: ReplayBuffer, rngs: list[np.random.Generator], cfg, method,
                 reward: RewardTransform, *, mc_returns: Callable[[Dataset], np.ndarray], success_mode: str,
                 offline: Dataset | None = None):
        n = len(envs)
        self.envs, self.buffer, self.rngs, self.cfg, self.method, self.reward = envs, buffer, rngs, cfg, method, reward
        self.mc_returns, self.success_mode = mc_returns, success_mode
        self.offline = offline if cfg.offline_ratio > 0 else None
        self.step, self.episodes, self.resumes = 0, [0] * n, 0
        self.learning, self.ended = True, None
        self.obs, self.ep_succ = np.zeros((n, buffer.obs_dim), np.float32), np.zeros(n)
        # each member's running episode's buffer rows; the successes of the episodes since the last log
        self.ep_rows, self.recent_success = [[] for _ in range(n)], [[] for _ in range(n)]
        self.finished_only = method.finished_episodes_only
        self.drawn = None  # (actions, next rng) at self.obs from the last update call, not yet taken

    def reset(self, seeds) -> None:
        self.obs = np.stack([np.asarray(e.reset(seed=s)[0], np.float32) for e, s in zip(self.envs, seeds)])
        self.seeds = list(seeds)

    def state_dict(self) -> dict:
        """This whole state as a checkpoint holds it: ``np_rng`` (each member's generator),
        ``extra`` (the step, counters), ``arrays`` (npz groups) and ``documents`` (JSON)."""
        arrays = {"buffer": self.buffer.state_dict(), "online": {"obs": self.obs, "ep_succ": self.ep_succ}}
        if self.drawn is not None:  # the next step's action, drawn by the fused call: resumed as drawn
            actions, rng = jax.device_get(self.drawn)
            arrays["online"].update(drawn_actions=np.asarray(actions), drawn_rng=np.asarray(rng))
        return {"np_rng": [r.bit_generator.state for r in self.rngs], "arrays": arrays,
                "extra": {"step": self.step, "episodes": self.episodes, "resumes": self.resumes},
                # what of the running episodes is not in arrays: each member's env state, the buffer rows
                # of its running episode (their MC returns are filled when it ends), the recent successes
                "documents": {"envs": {"envs": [get_env_state(e) for e in self.envs],
                                       "ep_rows": [[int(r) for r in rows] for rows in self.ep_rows],
                                       "recent_success": [[float(x) for x in xs] for xs in self.recent_success]}}}

    def load_state_dict(self, state: dict) -> None:
        """The state ``state_dict()`` gave (read back from checkpoint ``state["name"]``), each env
        set to its saved state mid-episode. A checkpoint of an older botorl, without env states:
        each member starts a new episode, with seeds not used before (the run is then not exact)."""
        n, extra, arrays = len(self.envs), state.get("extra", {}), state["arrays"]
        if "buffer" not in arrays:  # the warm-up's end as an older botorl saved it (D_warmup alone)
            raise CheckpointCorrupt(
                f"checkpoint {state.get('name')} holds no online loop (an older botorl's warm-up end); resume "
                f"from the pre-training's end, which runs the warm-up again: `botorl resume RUN_DIR --from pretrain-final`.")
        self.buffer = ReplayBuffer.from_state_dict(arrays["buffer"])
        self.step = int(extra.get("step", state["step"]))  # a stage end's state.json has no step
        rng_states = state.get("np_rng")
        for rng, st in zip(self.rngs, rng_states if isinstance(rng_states, list) else [rng_states] * n):
            rng.bit_generator.state = st
        episodes = extra.get("episodes", 0)
        self.episodes = list(episodes) if isinstance(episodes, list) else [int(episodes)] * n
        self.resumes = int(extra.get("resumes", 0)) + 1
        doc, online = state["documents"].get("envs"), arrays.get("online")
        if doc is None or online is None:
            warn("this checkpoint has no env state (written by an older botorl); fine-tuning "
                 "continues with new episodes, so the run will not repeat an uninterrupted one exactly.")
            return self.reset([s + 100_003 * self.resumes for s in self.seeds])
        try:
            if len(doc["envs"]) != n or online["obs"].shape[0] != n:
                raise ValueError(f"it holds {len(doc['envs'])} envs, the run has {n} members")
            for env, st in zip(self.envs, doc["envs"]):
                # the env steps so far, as the run's budget bounds them (state.json is data too)
                set_env_state(env, st, min(self.step, self.cfg.steps))
            self.obs = np.array(online["obs"], np.float32)
            self.ep_succ = np.array(online["ep_succ"], np.float64)
            if "drawn_actions" in online:  # an accelerator may compute the fused call's draw in other bits
                self.drawn = (np.asarray(online["drawn_actions"], np.float32), np.asarray(online["drawn_rng"]))
            self.ep_rows = [[int(r) for r in rows] for rows in doc["ep_rows"]]
            self.recent_success = [[float(x) for x in xs] for xs in doc["recent_success"]]
        except (KeyError, TypeError, ValueError, IndexError) as err:
            raise CheckpointCorrupt(
                f"checkpoint {state.get('name')}: its env state (envs.json, online.npz) does not fit this run "
                f"({type(err).__name__}: {err}). Resume from another checkpoint: `botorl resume RUN_DIR --from NAME`."
            ) from None

    def __enter__(self) -> "OnlineState":
        return self

    def __exit__(self, *exc) -> None:
        for env in self.envs:
            env.close()
        self.envs = []  # closed once: the runner closes a loop a failed stage left open

    # ------------------------------------------------------------------ one env step, one update
    def advance(self, agents, window):
        """One online step of every member (one policy call for all), then one UTD update (with
        ``learning`` on, from ``online.random_steps`` on): the body of the online loop. When every member learns,
        the update and the next step's policy call are one jitted call (one dispatch per step)."""
        if self.drawn is None:
            actions, agents = population.sample(agents, self.obs)
        else:  # drawn at this observation by the last step's update call, with the updated actor
            (actions, rng), self.drawn = self.drawn, None
            agents = agents.replace(rng=jax.device_put(rng, agents.rng.sharding))  # a no-op unless resumed
        self.act(np.asarray(jax.device_get(actions), dtype=np.float32))  # explicit: no implicit transfer
        if self.learning and self.step >= self.cfg.random_steps:
            agents = self.learn(agents, window)
        self.step += 1
        return agents

    def act(self, actions: np.ndarray) -> None:
        """Every member's env steps with its action; the transitions go into the buffer; ended
        episodes close (with their Monte-Carlo returns where the method needs them) and reset."""
        n = len(self.envs)
        next_obs, rewards, dones = np.zeros_like(self.obs), np.zeros(n, np.float32), np.zeros(n, np.float32)
        ended = []
        for i, env in enumerate(self.envs):
            next_obs[i], r, terminated, truncated, info = env.step(actions[i])
            rewards[i] = self.reward(float(r))
            dones[i] = float(terminated)
            self.ep_succ[i] = episode_success(self.ep_succ[i], info.get("success", 0.0), self.success_mode)
            if terminated or truncated:
                ended.append(i)
        for rows in self.ep_rows:
            rows.append(self.buffer.insert_index)
        self.buffer.insert(self.obs, actions, rewards, next_obs, dones)
        self.obs[:] = next_obs
        for i in ended:
            if self.finished_only:
                self.buffer.set_mc_returns(self.ep_rows[i], self.mc_returns, member=i)
            self.buffer.end_episode(i)
            if self.ended is not None:
                self.ended[i].append(self.ep_rows[i][-1])
            self.ep_rows[i] = []
            self.episodes[i] += 1
            self.recent_success[i].append(self.ep_succ[i])
            self.obs[i] = self.envs[i].reset()[0]
            self.ep_succ[i] = 0.0

    def learn(self, agents, window):
        """One UTD update of every member that has rows to learn from (a Cal-QL member waits for
        its first finished episode; the others keep their agents exactly)."""
        oc, n = self.cfg, len(self.envs)
        rows = [self.buffer.finished_len(i) if self.finished_only else len(self.buffer) for i in range(n)]
        active = [r > 0 or (self.offline is not None and not self.finished_only) for r in rows]
        if not any(active):
            return agents
        # (N, u, B, ...), u = the UTD, each minibatch with the offline/online mix: one update of u
        # critic minibatches (SAC's train_step), or u updates of B rows ("per_update": IQL's)
        b = self.buffer.sample_members(self.rngs, oc.batch_size, oc.utd, active=active, finished=self.finished_only,
                                       offline=self.offline, offline_ratio=oc.offline_ratio)
        many = self.method.batch_layout == "per_update"
        if all(active):
            # one dispatch for the update and the next step's action; the agents keep the rng they
            # had before the draw until that step takes it, so a checkpoint now is the separate calls'
            agents, metrics, actions, rng = population.update_then_sample(agents, b, self.obs, many=many)
            self.drawn = (actions, rng)
        else:
            agents, metrics = population.update_masked(agents, b, np.asarray(active), many=many)
        window.add(metrics, np.asarray(active))
        return agents

    def log_rows(self, ms: list[dict], env_steps_per_s: float) -> list[dict]:
        """Each member's fine-tuning log row at a log point (the episode successes since the last)."""
        rows = [{**m, "episodes": self.episodes[i], "env_steps_per_s": env_steps_per_s,
                 "train_success": float(np.mean(self.recent_success[i])) if self.recent_success[i] else float("nan"),
                 "buffer_size": len(self.buffer)} for i, m in enumerate(ms)]
        self.recent_success = [[] for _ in ms]
        return rows
