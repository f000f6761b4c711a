"""Trains a real policy for the closed-loop check: brax's own PPO on brax's ``inverted_pendulum``
(MJX backend), on this CPU, and lets brax write the checkpoint.

    python benchmarks/scripts/train_policy.py --out policies/inverted_pendulum [--timesteps 300000]
    python -m mjxdiff policy inverted_pendulum --policy policies/inverted_pendulum/<step>

Prints one JSON line: training seconds, timesteps, the last evaluation's episode reward, and the
checkpoint directory brax wrote (the last one: the trained policy).
"""

import argparse
import functools
import json
import time
from pathlib import Path

import jax


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", required=True, help="directory brax writes its checkpoints into")
    parser.add_argument("--timesteps", type=int, default=300_000)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    jax.config.update("jax_enable_x64", True)
    # brax 0.14.2's PPO calls jax.device_put_replicated, which jax 0.10 removed: the replicated
    # value is the value stacked once per device (pmap shards a leading axis of that size)
    jax.device_put_replicated = lambda value, devices: jax.tree.map(
        lambda x: jax.numpy.stack([jax.numpy.asarray(x)] * len(devices)), value)
    from brax import envs
    from brax.training.agents.ppo import train as ppo

    env = envs.get_environment("inverted_pendulum", backend="mjx")
    out = Path(args.out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    evals = []
    train = functools.partial(
        ppo.train, num_timesteps=args.timesteps, episode_length=200, num_envs=128, num_eval_envs=32,
        batch_size=128, num_minibatches=4, unroll_length=10, num_updates_per_batch=4, learning_rate=3e-4,
        entropy_cost=1e-2, discounting=0.97, normalize_observations=True, reward_scaling=1.0, num_evals=4,
        seed=args.seed, save_checkpoint_path=str(out), max_devices_per_host=1)
    t = time.perf_counter()
    train(environment=env, progress_fn=lambda step, metrics: evals.append(
        (int(step), float(metrics.get("eval/episode_reward", float("nan"))))))
    seconds = time.perf_counter() - t
    checkpoints = sorted(p for p in out.iterdir() if p.is_dir() and p.name.isdigit())
    print(json.dumps(dict(env="inverted_pendulum", backend="mjx", timesteps=args.timesteps,
                          train_seconds=round(seconds, 1), evals=evals,
                          checkpoint=str(checkpoints[-1]) if checkpoints else None)))


if __name__ == "__main__":
    main()
