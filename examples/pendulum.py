"""A task without success in botorl: Gymnasium's own Pendulum-v1, from logged data to a report.

    python examples/pendulum.py                    # BOTO and WSRL, quick profile, and their report
    python examples/pendulum.py --profile smoke    # every stage for a few steps (the tests)
    python examples/pendulum.py --score            # in the normalised score instead of the return

Pendulum-v1 has actions in [-2, 2] (botorl rescales them) and no ``success`` in its info, so
botorl reports the episode return: summary.json's ``return_*``, curve.png, the printed summary
and ``botorl report`` (Table 1, Figure 5, the dip) are about the return. With ``--score`` the
task gets reference scores, the returns of a random policy and of the noise-free controller
(both measured here), and everything is in D4RL's normalised score
``100 * (R - ref_min) / (ref_max - ref_min)`` instead.

1. the env: ``gymnasium.make("Pendulum-v1")`` (episodes of 200 steps, truncated, never terminated);
2. logged data from a noisy swing-up controller (``logged_data``), as a dict of arrays;
3. ``botorl.register_task`` and ``botorl.run`` for BOTO and WSRL, then ``botorl report``;
4. ``botorl.load_policy`` driving the env in a plain Gymnasium loop.
"""

from __future__ import annotations

import argparse

import gymnasium as gym
import numpy as np

MAX_STEPS = 200  # Pendulum-v1's own TimeLimit
MAX_TORQUE = 2.0


def make_env(seed: int = 0) -> gym.Env:
    """botorl's entry point: a fresh Pendulum-v1 (botorl seeds its first reset with ``seed``)."""
    return gym.make("Pendulum-v1")


def controller(obs: np.ndarray) -> float:
    """A swing-up controller: pump energy (torque along the velocity) until the pendulum comes
    near the top, then hold it there with a PD law. Pendulum-v1's dynamics are
    theta'' = 15 sin(theta) + 3 u (theta = 0 upright), so E = theta'^2 / 2 + 15 (cos(theta) - 1)
    is 0 at rest upright and dE/dt = 3 u theta'."""
    cos, sin, thdot = (float(x) for x in obs)
    theta = np.arctan2(sin, cos)
    if cos > 0.85:
        return float(np.clip(-12.0 * theta - 2.5 * thdot, -MAX_TORQUE, MAX_TORQUE))
    energy = 0.5 * thdot**2 + 15.0 * (cos - 1.0)
    return float(MAX_TORQUE * np.sign(thdot if thdot != 0 else 1.0)) if energy < 0 else 0.0


def logged_data(episodes: int = 100, noise: float = 0.6, seed: int = 0) -> dict:
    """Transitions of the controller with Gaussian noise on its torque (clipped to [-2, 2]), in
    the env's own units."""
    rng = np.random.default_rng(seed)
    env = make_env()
    rows: dict[str, list] = {k: [] for k in ("observations", "actions", "rewards", "next_observations", "terminals",
                                             "timeouts")}
    for ep in range(episodes):
        obs, _ = env.reset(seed=seed * 100_000 + ep)
        for t in range(MAX_STEPS):
            a = np.clip([controller(obs) + rng.normal(0.0, noise)], -MAX_TORQUE, MAX_TORQUE).astype(np.float32)
            nxt, r, terminated, truncated, _ = env.step(a)
            rows["observations"].append(obs)
            rows["actions"].append(a)
            rows["rewards"].append(r)
            rows["next_observations"].append(nxt)
            rows["terminals"].append(terminated)
            rows["timeouts"].append(truncated and not terminated)
            obs = nxt
            if terminated or truncated:
                break
    return {k: np.asarray(v, dtype=np.float32 if k not in ("terminals", "timeouts") else bool)
            for k, v in rows.items()}


def mean_return(policy, episodes: int = 10, seed: int = 50_000) -> float:
    """The mean undiscounted return of ``policy(obs) -> action`` over ``episodes`` episodes."""
    env = make_env()
    total = 0.0
    for ep in range(episodes):
        obs, _ = env.reset(seed=seed + ep)
        for _ in range(MAX_STEPS):
            obs, r, terminated, truncated, _ = env.step(policy(obs))
            total += float(r)
            if terminated or truncated:
                break
    return total / episodes


def reference_scores() -> tuple[float, float]:
    """(ref_min_score, ref_max_score): a uniformly random policy's mean return and the noise-free
    controller's, as D4RL takes a random and an expert policy's."""
    rng = np.random.default_rng(1)
    low = mean_return(lambda o: rng.uniform(-MAX_TORQUE, MAX_TORQUE, 1).astype(np.float32))
    high = mean_return(lambda o: np.array([controller(o)], np.float32))
    return low, high


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--profile", default="quick", choices=["smoke", "quick", "full"])
    p.add_argument("--out", default="runs/pendulum", help="folder for the run directories and the report")
    p.add_argument("--score", action="store_true", help="report the normalised score (reference scores measured here)")
    args = p.parse_args()

    import botorl
    from botorl.cli import main as botorl_cli

    refs = {}
    if args.score:
        low, high = reference_scores()
        refs = {"ref_min_score": round(low, 1), "ref_max_score": round(high, 1)}
        print(f"reference scores: random {refs['ref_min_score']}, controller {refs['ref_max_score']}")
    # Pendulum's reward lies in [-16.3, 0]; scaled by 0.1 the critic's targets stay within a few
    # tens (as with antmaze's and the door's transforms), which the quick profile's small networks fit.
    botorl.register_task("pendulum", make_env, logged_data(), max_episode_steps=MAX_STEPS, reward_scale=0.1, **refs)
    runs = {}
    for method in ("boto", "wsrl"):
        summary = botorl.run(task="pendulum", method=method, profile=args.profile, out=f"{args.out}/{method}",
                             progress=False)
        name = "score" if args.score else "return"
        print(f"{method}: status {summary['status']}, {name} {summary[name + '_initial']:.1f} -> "
              f"{summary[name + '_final']:.1f}")
        runs[method] = summary["run_dir"]
    # Table 1, Figure 5 and the dip, in the return (or the normalised score)
    botorl_cli(["report", f"{args.out}/boto", f"{args.out}/wsrl", "--out", f"{args.out}/report"])

    # the policy outside botorl: Pendulum's observations in, torques in [-2, 2] out
    policy = botorl.load_policy(runs["boto"])
    env = make_env()
    obs, _ = env.reset(seed=1_000)
    for _ in range(MAX_STEPS):
        action = policy(obs)
        assert env.action_space.contains(action)
        obs, reward, terminated, truncated, _ = env.step(action)
        if terminated or truncated:
            break
    print(f"boto's policy in a plain Gymnasium loop: return {mean_return(policy, episodes=5):.1f} over 5 episodes")


if __name__ == "__main__":
    main()
