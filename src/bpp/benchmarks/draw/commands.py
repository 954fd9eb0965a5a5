"""DrawAnything's own commands: ``bpp draw sheet|video|rollout|demo`` (``bpp draw generate`` is generic).

``demo`` is the main job (``bpp demo``): it drives the generic training loop and evaluator, so unlike the rest of
this folder it uses them. They, the checkpoints and the policies load torch, so they are imported when a command
runs: ``bpp --help`` lists this table without loading torch.
"""

from __future__ import annotations

import contextlib
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import tyro

from bpp.benchmarks.draw.benchmark import BENCHMARK
from bpp.benchmarks.draw.dataset import PRESETS, DrawDataConfig, generate
from bpp.benchmarks.draw.sheets import write_contact_sheet
from bpp.benchmarks.draw.studio.command import StudioCommand, studio
from bpp.benchmarks.draw.viz import episode_frames
from bpp.core.prompting import run_prompted
from bpp.data.store import EpisodeStore, stored_with
from bpp.errors import UserError
from bpp.media import contact_sheet, save_animation
from bpp.policies.registry import get_method
from bpp.utils import check_fields, write_text_atomic


@dataclass(frozen=True)
class DrawSheet:
    """Write a contact sheet PNG of a store's tasks (upright, strokes coloured by order) and demonstrations."""

    store: tyro.conf.Positional[Path]
    out: Path = Path("sheet.png")
    tasks: int = 8
    """How many tasks (rows) to show, evenly spread over the store."""
    demos: int = 5
    """Demonstrations per task to show beside the task."""
    size: int = 160

    def __post_init__(self):
        check_fields(
            self,
            ("tasks", 1 <= self.tasks <= 200, "in [1, 200]"),
            ("demos", 1 <= self.demos <= 50, "in [1, 50]"),
            ("size", 16 <= self.size <= 1024, "in [16, 1024] px"),
        )


def draw_sheet(args: DrawSheet) -> None:
    print(f"wrote {write_contact_sheet(args.store, args.out, args.tasks, args.demos, args.size)}")


@dataclass(frozen=True)
class DrawVideo:
    """Animate one stored demonstration as a GIF (or MP4 if --out ends in .mp4)."""

    store: tyro.conf.Positional[Path]
    episode: int = 0
    out: Path = Path("demo.gif")
    size: int = 256

    def __post_init__(self):
        check_fields(
            self,
            ("episode", self.episode >= 0, ">= 0"),
            ("out", self.out.suffix.lower() in (".gif", ".mp4"), "a .gif or .mp4 file"),
            ("size", 16 <= self.size <= 1024, "in [16, 1024] px"),
        )


def draw_video(args: DrawVideo) -> None:
    store = EpisodeStore(args.store)
    ep = store.episode(args.episode, ("state", "action"))
    angle = float(store.column("board_angle")[args.episode])
    frames = episode_frames(ep["state"], ep["action"].astype("float64"), angle, args.size)
    print(f"wrote {save_animation(frames, args.out)} ({len(frames)} frames)")


@dataclass(frozen=True)
class DrawRollout:
    """Prompt a trained policy with one stored demonstration and let it draw at another board angle.

    Writes a picture (prompt | rollout with the target overlaid) and an animation, and prints the Chamfer score.
    """

    checkpoint: tyro.conf.Positional[Path]
    """A run directory or checkpoint folder."""
    store: Path = Path("data/draw/human.zarr")
    """Where the prompt demonstration comes from."""
    episode: int = 0
    """The prompt: an episode of the store."""
    board_angle_deg: float = 20.0
    seed: int = 0
    out: Path = Path("outputs/rollout")

    def __post_init__(self):
        check_fields(
            self,
            ("episode", self.episode >= 0, ">= 0"),
            ("board_angle_deg", -180.0 <= self.board_angle_deg <= 180.0, "in [-180, 180]"),
            ("seed", self.seed >= 0, ">= 0"),
        )


def draw_rollout(args: DrawRollout) -> None:
    # torch: imported when the command runs, not when the command line starts
    from bpp.checkpoint import Checkpoint
    from bpp.policies.agent import PolicyAgent

    store = EpisodeStore(args.store)
    store.episode_slice(args.episode)  # an IndexError naming the store's episode count if out of range
    checkpoint = Checkpoint.load(args.checkpoint, use_ema=True)
    if checkpoint.benchmark != BENCHMARK.name:
        raise UserError(f"{checkpoint.path} was trained on {checkpoint.benchmark}, not {BENCHMARK.name}")
    agent = PolicyAgent(checkpoint.build_model(), record_attention=True)
    plan = [
        {
            "target_episode": args.episode,
            "prompt_episode": args.episode,
            "board_angle": float(np.radians(args.board_angle_deg)),
            "seed": args.seed,
        }
    ]
    (result,), _ = run_prompted(agent, BENCHMARK, store, plan, BENCHMARK.max_steps, [True])
    args.out.mkdir(parents=True, exist_ok=True)
    sheet = contact_sheet(
        [BENCHMARK.prompt_picture(store, args.episode), result.frames[-1]],
        ["prompt", f"rollout: Chamfer {result.score:.2f}"],
        args.out / "rollout.png",
        columns=2,
    )
    gif = save_animation(result.frames, args.out / "rollout.gif")
    final = result.extra["final_chamfer"]
    print(f"best Chamfer {result.score:.2f} px (final {final:.2f}) in {result.steps} steps")
    print(f"wrote {sheet} and {gif}")


# ----------------------------------------------------------------------------- the main job


@dataclass(frozen=True)
class Demo:
    """The main job, end to end on built-in defaults: data -> train BPP -> evaluate on unseen drawings -> report.

    1. generate a procedural DrawAnything-Sim training set and the 50 unseen human-made drawings (data_dir);
    2. train BPP with a CPU preset (run_dir; a killed run resumes);
    3. evaluate it on the unseen drawings with the paper's protocol (fewer rollouts per task by default);
    4. write a report folder (table, prompt | rollout grid, prompt attention, rollout videos) and print its path.

    Re-running reuses every finished stage.
    """

    out_dir: Path = Path("outputs/demo")
    data_dir: Path = Path("data/draw")
    run_dir: Path = Path("runs/demo-bpp")
    num_tasks: int = 500
    """Procedural training tasks (5 demonstrations each)."""
    preset: str = "cpu"
    """BPP size preset (debug, cpu, paper)."""
    obs: str = "board"
    """Observation preset (board: state-only, board-frame actions; canvas: state-only, the paper's canvas actions;
    canvas-ink: canvas and the ink drawn so far)."""
    steps: int = 6000
    """Training steps (batch 64)."""
    tasks_per_batch: int = 8
    """Tasks per training step, each with its own prompt (the paper: 1; more learn faster on a CPU)."""
    rollouts: int = 8
    """Rollouts per unseen drawing (the paper uses 32: bpp eval --rollouts 32)."""
    eval_tasks: int = 0
    """Unseen drawings to evaluate (0: all 50)."""
    max_steps: int = 400
    """Rollout length limit (the paper's 400)."""
    workers: int = 0
    """Processes for data generation and evaluation (0: one per core)."""
    threads: int = 0
    """torch threads for training (0: auto, one fewer than the cores; see docs/training.md, "CPU threads")."""
    loader_workers: int = -1
    """Data-loader processes for training (-1: auto, none on a CPU)."""
    seed: int = 0

    def __post_init__(self):
        check_fields(
            self,
            ("num_tasks", self.num_tasks >= 1, ">= 1"),
            ("steps", self.steps >= 1, ">= 1"),
            ("tasks_per_batch", self.tasks_per_batch >= 1, ">= 1"),
            ("rollouts", self.rollouts >= 1, ">= 1"),
            ("eval_tasks", self.eval_tasks >= 0, ">= 0 (0: all)"),
            ("max_steps", self.max_steps >= 1, ">= 1"),
            ("workers", self.workers >= 0, ">= 0 (0: one per core)"),
            ("threads", self.threads >= 0, ">= 0 (0: auto)"),
            ("loader_workers", self.loader_workers >= -1, ">= -1 (-1: auto)"),
            ("seed", self.seed >= 0, ">= 0"),
        )


def demo(args: Demo) -> None:
    # torch: imported when the command runs, not when the command line starts
    from bpp.checkpoint import Checkpoint, read_state, resolve_checkpoint
    from bpp.evaluation.evaluate import Protocol, evaluate, resolve_tasks
    from bpp.train import TrainConfig, run_differences, train

    t0 = time.perf_counter()

    def stage(text: str) -> None:
        print(f"[demo {time.perf_counter() - t0:6.0f} s] {text}", flush=True)

    def ensure(name: str, cfg: DrawDataConfig) -> EpisodeStore:
        path = args.data_dir / f"{name}.zarr"
        store = stored_with(path, cfg)
        if store is not None:
            stage(f"reusing {store}")
            return store
        stage(f"generating {path}")
        return generate(cfg, path, workers=args.workers, overwrite=True)

    store = ensure(f"train-{args.num_tasks}", DrawDataConfig(num_tasks=args.num_tasks, seed=args.seed))
    ensure("human", PRESETS["human"])

    model_cfg = get_method("bpp").config(args.preset, args.obs, BENCHMARK)
    run = args.run_dir
    finished = False
    with contextlib.suppress(OSError, ValueError):  # no checkpoint yet
        finished = read_state(resolve_checkpoint(run))["step"] >= args.steps
    resume = (run / "checkpoints" / "last").is_file()
    tc = TrainConfig(
        data=store.path,
        out=run,
        steps=args.steps,
        tasks_per_batch=args.tasks_per_batch,
        seed=args.seed,
        resume=resume,
        save_every=500,
        threads=args.threads,
        workers=args.loader_workers,
    )
    if finished:
        # Its model must be this one (how long or how it trained may differ: a finished run is reused as it is).
        differences = [d for d in run_differences(run, tc, model_cfg) if not d.startswith("train_config.")]
        if differences:
            raise UserError(
                f"{run} holds a policy trained with another model than --preset {args.preset} --obs {args.obs}; "
                "pass another --run-dir, or the flags it was trained with: " + "; ".join(differences)
            )
        stage(f"reusing the trained policy in {run}")
    else:
        what = f"{args.preset} preset, {args.obs} observations, {args.steps} steps"
        stage(f"{'resuming' if resume else 'training'} BPP ({what}) in {run}")
        train(tc, model_cfg)

    stage(f"evaluating on the unseen human-made drawings ({args.rollouts} rollouts each)")
    ckpt = Checkpoint.load(run, use_ema=True)
    _, human, tasks = resolve_tasks("human", ckpt, data_dir=args.data_dir, num_tasks=args.eval_tasks)
    protocol = Protocol(rollouts=args.rollouts, seed=args.seed, max_steps=args.max_steps)
    result = evaluate(ckpt, human, tasks, args.out_dir / "eval-human", protocol, args.workers)
    write_demo_report(args, result, time.perf_counter() - t0)
    stage(f"done. Report: {args.out_dir / 'report.md'}")
    print(f"[demo] prompt it yourself: `bpp studio --runs {args.run_dir.parent}` opens a page where you draw a prompt")


def write_demo_report(args: Demo, result: dict, seconds: float) -> None:
    s = result["summary"]
    eval_dir = "eval-human"
    videos = [task["video"] for task in result["tasks"] if task.get("video")]  # this evaluation's, not older ones
    lines = [
        "# bpp main job: BPP on DrawAnything-Sim, unseen human-made drawings",
        "",
        f"Trained `{args.preset}` BPP with `{args.obs}` observations for {result['train_step']} steps on "
        f"{args.num_tasks} procedural tasks x 5 demonstrations ({args.run_dir}); evaluated on {s['tasks']} unseen "
        f"drawings x {args.rollouts} rollouts, each prompted with one demonstration and drawing on a board at a new "
        "angle. Score: best Chamfer distance per rollout (px at 512, lower is better), averaged per drawing then "
        "over drawings.",
        "",
        "| quantity | value |",
        "| --- | --- |",
        f"| Chamfer, mean over drawings | **{s['score_mean']:.2f} px** |",
        f"| std / s.e.m. over drawings | {s['score_std_over_tasks']:.2f} / {s['score_sem_over_tasks']:.2f} px |",
        f"| median rollout | {s['score_median_rollout']:.2f} px |",
        f"| rollouts under 5 px | {100 * s['good_rollouts']:.0f}% |",
        "| paper (BPP, 224 px images, 27-42 hours on 4 GPUs) | 3.41 ± 0.13 px |",
        f"| wall time of this run (this call) | {seconds / 60:.1f} min |",
        "",
        f"Per drawing: [{eval_dir}/results.md]({eval_dir}/results.md); raw numbers: "
        f"[{eval_dir}/results.json]({eval_dir}/results.json).",
        "",
        f"![prompt | rollout]({eval_dir}/grid.png)",
        "",
        f"![prompt attention]({eval_dir}/attention.png)",
        "",
        "Rollout videos: " + ", ".join(f"[{v}]({eval_dir}/{v})" for v in videos),
        "",
    ]
    if args.obs == "board":
        lines.append(
            "Note: the `board` observations are the cursor, the pen and the length of ink drawn so far, and actions "
            "in the board's own frame (state only), which removes the need to learn rotations from data; the "
            "paper's setting is images and canvas actions (`--obs canvas-ink` is state-only with canvas actions). "
            "See BENCHMARKS.md."
        )
    write_text_atomic(args.out_dir / "report.md", "\n".join(lines) + "\n")


COMMANDS = {
    "sheet": (DrawSheet, draw_sheet),
    "video": (DrawVideo, draw_video),
    "rollout": (DrawRollout, draw_rollout),
    "demo": (Demo, demo),
    "studio": (StudioCommand, studio),
}
"""``bpp draw <name>``; ``demo`` is also ``bpp demo`` (the main job) and ``studio`` ``bpp studio``."""
