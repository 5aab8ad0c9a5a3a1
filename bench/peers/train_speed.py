"""Training speed of one peer on gaitscope's task: env steps/s with one SAC update per step.

Same algorithm and hyperparameters as `gaitscope train` (SB3's SAC defaults with batch 256,
replay 300k, one gradient step per env step, separate actor/critic feature extractors), on the
task of python/gaitscope_gym.py. Times `--steps` learning steps after `--warmup` random ones (and
`--untimed` learning steps, so JAX's compilation is not counted) and prints one JSON line. One
thread: run it pinned (`taskset -c 1`), as scripts/bench-peers.sh does.
"""

import argparse
import json
import os
import sys
import time
from pathlib import Path

# One CPU thread for JAX/XLA, set before it loads.
os.environ["XLA_FLAGS"] = "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"
os.environ.setdefault("JAX_PLATFORMS", "cpu")
sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "python"))
from gaitscope_gym import make_env  # noqa: E402
from gaitscope_sb3 import lstm_extractor  # noqa: E402


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--lib", choices=["sb3", "sbx"], required=True)
    parser.add_argument("--model", choices=["none", "lstm", "folded-mlp"], required=True,
                        help="none: 29-d obs; lstm: SB3 LSTM extractor; folded-mlp: MLP over 621-d")
    parser.add_argument("--warmup", type=int, default=1000)
    parser.add_argument("--steps", type=int, default=1000)
    parser.add_argument("--untimed", type=int, default=50,
                        help="learning steps before the clock starts (JAX compiles on the first)")
    args = parser.parse_args()

    env = make_env(window=args.model != "none")
    kwargs = dict(
        learning_starts=args.warmup, batch_size=256, buffer_size=300_000, learning_rate=3e-4,
        train_freq=1, gradient_steps=1, seed=0, verbose=0,
    )
    policy_kwargs = dict(net_arch=[256, 256])
    if args.lib == "sb3":
        import torch
        from stable_baselines3 import SAC
        from stable_baselines3.common.callbacks import BaseCallback

        torch.set_num_threads(1)
        torch.set_num_interop_threads(1)
        kwargs["device"] = "cpu"
        if args.model == "lstm":
            policy_kwargs.update(features_extractor_class=lstm_extractor(),
                                 share_features_extractor=False)
        version = f"stable-baselines3 {__import__('stable_baselines3').__version__}, torch {torch.__version__}"
    else:
        if args.model == "lstm":
            sys.exit("sbx has no custom features extractors")
        import jax
        from sbx import SAC
        from stable_baselines3.common.callbacks import BaseCallback

        version = f"sbx {__import__('sbx').__version__}, jax {jax.__version__}"

    class Clock(BaseCallback):
        """Wall time once learning has run `--untimed` steps, and at the end."""

        def _on_step(self):
            if self.num_timesteps == args.warmup + args.untimed:
                self.start = time.perf_counter()
            return True

    clock = Clock()
    model = SAC("MlpPolicy", env, policy_kwargs=policy_kwargs, **kwargs)
    model.learn(total_timesteps=args.warmup + args.untimed + args.steps, callback=clock)
    elapsed = time.perf_counter() - clock.start
    print(json.dumps({
        "peer": f"{'SB3' if args.lib == 'sb3' else 'SBX'} {args.model}",
        "version": version,
        "steps": args.steps,
        "train_steps_per_s": args.steps / elapsed,
    }))


if __name__ == "__main__":
    main()
