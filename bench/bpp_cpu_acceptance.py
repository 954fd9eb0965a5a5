"""Does a short CPU training run of BPP learn to follow prompts? Rollouts of a checkpoint on two task sets.

    python bench/bpp_cpu_acceptance.py runs/bpp-cpu --train data/draw/cpu.zarr --unseen data/draw/human.zarr

For each set, `--tasks` tasks x `--rollouts` rollouts: the prompt is demo k of the task (cycling), the board angle
is drawn per rollout from a seeded generator, and the score is the best Chamfer distance (px at 512) to the
prompt's own ink. Two references put the number in context: *replay*, which executes the prompt's actions
verbatim on the new board (it ignores the rotation), and *empty*, which never inks (724.1 px by definition).
Writes a grid of prompt | rollout pictures next to the checkpoint.
"""

from __future__ import annotations

import argparse

import numpy as np

from bpp.benchmarks.contract import RolloutResult
from bpp.benchmarks.draw.benchmark import BENCHMARK
from bpp.benchmarks.draw.env import DrawEnv
from bpp.benchmarks.draw.geometry import MAX_BOARD_ANGLE
from bpp.benchmarks.draw.rollouts import prompt_target
from bpp.benchmarks.draw.viz import contact_sheet, group_strokes, render_strokes
from bpp.benchmarks.prompting import run_prompted
from bpp.checkpoint import resolve_checkpoint
from bpp.data.store import EpisodeStore
from bpp.policies.agent import PolicyAgent


def rollout(
    agent: PolicyAgent, store: EpisodeStore, episode: int, angle: float, seed: int, record_frames: bool = False
) -> RolloutResult:
    """One rollout prompted with demonstration `episode` and scored against its drawing (``score``: the best
    Chamfer distance), on a board at `angle`, seeded by `seed`: the evaluation protocol's runner."""
    plan = [{"target_episode": episode, "prompt_episode": episode, "board_angle": angle, "seed": seed}]
    results, _ = run_prompted(agent, BENCHMARK, store, plan, BENCHMARK.max_steps, [record_frames])
    return results[0]


def replay(store: EpisodeStore, episode: int, angle: float, seed: int) -> float:
    env = DrawEnv(image_size=None)
    env.reset(seed=seed, options={"board_angle": angle, "target": prompt_target(store, episode)})
    info = {"best_chamfer": env.best_chamfer}
    for action in store.episode(episode, ["action"])["action"]:
        *_, info = env.step(action)
    return info["best_chamfer"]


def evaluate(agent, store: EpisodeStore, tasks: int, rollouts: int, seed: int):
    by_task = store.task_episodes()
    chosen = np.unique(np.linspace(0, store.num_tasks - 1, min(tasks, store.num_tasks)).round().astype(int))
    rng = np.random.default_rng(seed)
    scores, replays, pictures = [], [], []
    for t in chosen:
        per_task, per_task_replay = [], []
        for k in range(rollouts):
            episode = int(by_task[t][k % len(by_task[t])])
            angle = float(rng.uniform(-MAX_BOARD_ANGLE, MAX_BOARD_ANGLE))
            r = rollout(agent, store, episode, angle, seed=int(rng.integers(2**31)), record_frames=k == 0)
            per_task.append(r.score)
            per_task_replay.append(replay(store, episode, angle, 0))
            if k == 0:
                ep = store.episode(episode, ("state", "action"))
                prompt_img = render_strokes(
                    group_strokes(ep["state"], ep["action"].astype(np.float64)),
                    float(store.column("board_angle")[episode]),
                    256,
                )
                pictures.append((prompt_img, r.frames[-1], store.tasks[t]["id"], r.score))
        scores.append(np.mean(per_task))
        replays.append(np.mean(per_task_replay))
    return np.array(scores), np.array(replays), pictures


def prompt_use(model, store_path: str, batches: int = 5) -> tuple[float, float]:
    """Mean px error of the executed actions on training windows: with the right prompt, and with a prompt of
    another task. A policy that uses its prompt does much better with the right one."""
    import torch

    from bpp.benchmarks.draw.geometry import BOARD_SIZE
    from bpp.data.prompt_dataset import PromptBatchDataset
    from bpp.utils import to_torch

    cfg = model.cfg
    ds = PromptBatchDataset(store_path, model.data_spec(), batch_size=64, seed=123)
    ta, start = cfg.horizons.n_action_steps, cfg.horizons.n_obs_steps - 1
    px = BOARD_SIZE if cfg.action_key == "action_on_board" else 1.0  # board-frame actions are in board units
    right, wrong = [], []
    for i in range(batches):
        batch, other = to_torch(ds[i], "cpu"), to_torch(ds[i + 1000], "cpu")
        for prompt, out in ((batch["context"], right), (other["context"], wrong)):
            pred = model.predict_action(
                batch["obs"], model.encode_prompt(prompt), generator=torch.Generator().manual_seed(0)
            )["action"]
            err = (pred[:, start : start + ta, :2] - batch["action"][:, start : start + ta, :2]).norm(dim=-1)
            out.append(px * err.mean().item())
    return float(np.mean(right)), float(np.mean(wrong))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("checkpoint")
    parser.add_argument("--train", default="data/draw/cpu.zarr")
    parser.add_argument("--unseen", default="data/draw/human.zarr")
    parser.add_argument("--tasks", type=int, default=10)
    parser.add_argument("--rollouts", type=int, default=2)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    ckpt = resolve_checkpoint(args.checkpoint)
    agent = PolicyAgent.from_checkpoint(ckpt)
    print(f"checkpoint {ckpt}")
    right, wrong = prompt_use(agent.model, args.train)
    print(f"training windows: action error {right:.1f} px with the right prompt, {wrong:.1f} px with another task's")
    for name, path in (("training tasks", args.train), ("unseen human-made", args.unseen)):
        store = EpisodeStore(path)
        scores, replays, pictures = evaluate(agent, store, args.tasks, args.rollouts, args.seed)
        print(
            f"{name:18s} BPP {scores.mean():6.2f} ± {scores.std():5.2f} px | prompt replay {replays.mean():6.2f} px"
            f" | empty 724.1 px   ({len(scores)} tasks x {args.rollouts} rollouts)"
        )
        images, titles = [], []
        for prompt_img, frame, task_id, score in pictures:
            images += [prompt_img, frame]
            titles += [f"prompt: {task_id}", f"rollout: {score:.1f} px"]
        out = ckpt.parent.parent / f"acceptance_{name.split()[0]}.png"
        print(f"  wrote {contact_sheet(images, titles, out, columns=4)}")


if __name__ == "__main__":
    main()
