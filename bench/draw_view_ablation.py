"""Does a `board-image` policy read the board's view? The unseen drawings scored twice, paired drawing by drawing: with
the view as the env renders it, and with the view frozen at each rollout's first frame (the board before any ink, the
cursor at its start), so that the policy still sees a board but nothing of what it has drawn.

    python bench/draw_view_ablation.py runs/long-image/bpp-s2/checkpoints/step_00017600 --out outputs/view/bpp-s2

If the score barely moves, the policy draws from its state and prompt and leaves the view unread. The frozen
evaluation is never reused (its results would not say that the view was frozen); the other is, as ``bpp eval``
reuses its results.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from bpp.benchmarks.draw.env import DrawEnv
from bpp.checkpoint import Checkpoint
from bpp.evaluation.evaluate import Protocol, evaluate, resolve_tasks
from common import paired, task_means

VIEW = "board_image"


def freeze_the_view() -> None:
    """Every DrawEnv from now on shows its board's view as it was at its last reset."""
    observe, reset = DrawEnv._observation, DrawEnv.reset

    def first_view(env: DrawEnv) -> dict:
        obs = observe(env)
        if VIEW in obs:
            obs[VIEW] = env.__dict__.setdefault("_frozen_view", obs[VIEW])
        return obs

    def new_rollout(env: DrawEnv, **kwargs):
        env.__dict__.pop("_frozen_view", None)
        return reset(env, **kwargs)

    DrawEnv._observation, DrawEnv.reset = first_view, new_rollout


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("checkpoint", type=Path, help="a checkpoint trained with --obs board-image")
    parser.add_argument("--num-tasks", type=int, default=50, help="unseen drawings (0: all 50)")
    parser.add_argument("--rollouts", type=int, default=2, help="rollouts per drawing")
    parser.add_argument("--data-dir", type=Path, default=Path("data/draw"))
    parser.add_argument("--out", type=Path, default=Path("outputs/view"))
    args = parser.parse_args()
    checkpoint = Checkpoint.load(args.checkpoint, use_ema=True)
    if VIEW not in checkpoint.model_config().obs.image_keys:
        parser.error(f"{args.checkpoint} was not trained on the board's view ({VIEW}); train it with --obs board-image")
    _, task_set, tasks = resolve_tasks("human", checkpoint, data_dir=args.data_dir, num_tasks=args.num_tasks)
    protocol = Protocol(rollouts=args.rollouts)
    view = evaluate(checkpoint, task_set, tasks, args.out / "view", protocol, workers=1, videos=0)
    freeze_the_view()
    frozen = evaluate(checkpoint, task_set, tasks, args.out / "frozen", protocol, workers=1, videos=0, reuse=False)
    result = paired(task_means(view), task_means(frozen))
    medians = [results["summary"]["score_median_rollout"] for results in (view, frozen)]
    print(
        f"{args.checkpoint}: the view as rendered {result.mean_a:.2f} px (median rollout {medians[0]:.2f}), frozen "
        f"{result.mean_b:.2f} ({medians[1]:.2f}); frozen minus rendered {result} px, worse on "
        f"{result.tasks - result.b_better} of {result.tasks}"
    )


if __name__ == "__main__":
    main()
