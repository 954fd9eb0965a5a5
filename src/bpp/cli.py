"""The ``bpp`` command line: ``bpp <group> <command> [flags]``; every command has ``--help``.

Commands are small dataclasses parsed by tyro, so every flag is typed, documented and validated.
"""

from __future__ import annotations

import contextlib
import sys
from collections.abc import Callable
from dataclasses import dataclass, field, make_dataclass
from pathlib import Path
from typing import Annotated, Any, Literal

import tyro

from bpp.envs.draw.dataset import PRESETS as DRAW_PRESETS
from bpp.envs.draw.dataset import DrawDataConfig
from bpp.policies.registry import get_method
from bpp.train import TrainConfig

# ----------------------------------------------------------------------------- bpp draw generate


@dataclass(frozen=True)
class DrawGenerate:
    """Generate a DrawAnything-Sim dataset (procedural training tasks, the unseen human set, or your drawings).

    Examples:
      bpp draw generate --preset paper --out data/draw/train.zarr
      bpp draw generate --preset human --out data/draw/human.zarr
      bpp draw generate --source files --drawings my.json house.svg --out data/draw/mine.zarr
    """

    out: Path
    """Store to write (a .zarr folder); written atomically."""
    preset: str = "paper"
    """Starting configuration: one of paper, cpu, debug, human, parts-1-3, parts-4-6 (flags below override it)."""
    workers: int = 0
    """Worker processes (0: one per core)."""
    overwrite: bool = False
    """Replace an existing store."""
    data: Annotated[DrawDataConfig, tyro.conf.OmitArgPrefixes] = field(default_factory=DrawDataConfig)


def draw_generate(args: DrawGenerate) -> None:
    import time

    from bpp.envs.draw.dataset import generate

    t0 = time.perf_counter()
    store = generate(args.data, args.out, workers=args.workers, overwrite=args.overwrite)
    seconds = time.perf_counter() - t0
    print(f"wrote {store}")
    print(f"  {seconds:.1f} s, {store.disk_bytes() / 1e6:.1f} MB on disk")


# ----------------------------------------------------------------------------- bpp draw sheet / video / info


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


def draw_sheet(args: DrawSheet) -> None:
    from bpp.envs.draw.sheets import write_contact_sheet

    print(f"wrote {write_contact_sheet(args.store, args.out, args.tasks, args.demos, args.size)}")


@dataclass(frozen=True)
class DrawVideo:
    """Animate one stored demonstration as a GIF (or MP4 if --out ends in .mp4)."""

    store: tyro.conf.Positional[Path]
    episode: int = 0
    out: Path = Path("demo.gif")
    size: int = 256


def draw_video(args: DrawVideo) -> None:
    from bpp.data.store import EpisodeStore
    from bpp.envs.draw.viz import episode_frames, save_animation

    store = EpisodeStore(args.store)
    ep = store.episode(args.episode, ("state", "action"))
    angle = float(store.column("board_angle")[args.episode])
    frames = episode_frames(ep["state"], ep["action"].astype("float64"), angle, args.size)
    print(f"wrote {save_animation(frames, args.out)} ({len(frames)} frames)")


@dataclass(frozen=True)
class StoreInfo:
    """Summarise a store: benchmark, tasks, episodes, steps, keys, episode lengths, size."""

    store: tyro.conf.Positional[Path]


def store_info(args: StoreInfo) -> None:
    import numpy as np

    from bpp.data.store import EpisodeStore

    s = EpisodeStore(args.store)
    lengths = np.diff(np.concatenate([[0], s.episode_ends]))
    print(s)
    print(f"  created {s.attrs.get('created')}, {s.disk_bytes() / 1e6:.1f} MB")
    print(f"  episode length: mean {lengths.mean():.1f}, min {lengths.min()}, max {lengths.max()}")
    for key in s.keys:
        arr = s[key]
        print(f"  {key:12s} {str(arr.dtype):8s} {arr.shape}")


# ----------------------------------------------------------------------------- bpp demo


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
    preset: str = "cpu-board"
    """BPP preset (cpu-board: state-only, board-frame actions; cpu: state-only, the paper's canvas actions)."""
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
    seed: int = 0


def demo(args: Demo) -> None:
    import json
    import time

    from bpp.checkpoint import read_state, resolve_checkpoint
    from bpp.data.store import EpisodeStore, StoreError
    from bpp.envs.draw.dataset import generate
    from bpp.evaluation.evaluate import Protocol, evaluate, resolve_task_set
    from bpp.train import train
    from bpp.utils import to_dict

    t0 = time.perf_counter()

    def stage(text: str) -> None:
        print(f"[demo {time.perf_counter() - t0:6.0f} s] {text}", flush=True)

    def ensure(name: str, cfg: DrawDataConfig) -> EpisodeStore:
        path = args.data_dir / f"{name}.zarr"
        try:
            store = EpisodeStore(path)
            if json.loads(json.dumps(store.config)) == json.loads(json.dumps(to_dict(cfg))):
                stage(f"reusing {store}")
                return store
        except StoreError:
            pass
        stage(f"generating {path}")
        return generate(cfg, path, workers=args.workers, overwrite=True)

    train_cfg = DrawDataConfig(num_tasks=args.num_tasks, seed=args.seed)
    store = ensure(f"train-{args.num_tasks}", train_cfg)
    ensure("human", DRAW_PRESETS["human"])

    method = get_method("bpp")
    model_cfg = method.preset(args.preset)
    run = args.run_dir
    finished = False
    with contextlib.suppress(OSError, ValueError):  # no checkpoint yet
        finished = read_state(resolve_checkpoint(run))["step"] >= args.steps
    if finished:
        stage(f"reusing the trained policy in {run}")
    else:
        resume = (run / "checkpoints" / "last").is_file()
        stage(f"{'resuming' if resume else 'training'} BPP ({args.preset} preset, {args.steps} steps) in {run}")
        tc = TrainConfig(
            data=store.path,
            out=run,
            steps=args.steps,
            tasks_per_batch=args.tasks_per_batch,
            seed=args.seed,
            resume=resume,
            save_every=500,
        )
        train(tc, model_cfg)

    stage(f"evaluating on the unseen human-made drawings ({args.rollouts} rollouts each)")
    human, tasks, label = resolve_task_set("human", run, data_dir=args.data_dir, num_tasks=args.eval_tasks)
    protocol = Protocol(rollouts=args.rollouts, seed=args.seed, max_steps=args.max_steps)
    result = evaluate(run, human, tasks, label, args.out_dir / "eval-human", protocol, args.workers)
    write_demo_report(args, result, time.perf_counter() - t0)
    stage(f"done. Report: {args.out_dir / 'report.md'}")


def write_demo_report(args: Demo, result: dict, seconds: float) -> None:
    s = result["summary"]
    eval_dir = "eval-human"
    videos = sorted(p.name for p in (args.out_dir / eval_dir).glob("rollout_*"))
    lines = [
        "# bpp main job: BPP on DrawAnything-Sim, unseen human-made drawings",
        "",
        f"Trained `{args.preset}` BPP for {result['train_step']} steps on {args.num_tasks} procedural tasks x 5 "
        f"demonstrations ({args.run_dir}); evaluated on {s['tasks']} unseen drawings x {args.rollouts} rollouts, each "
        "prompted with one demonstration and drawing on a board at a new angle. Score: best Chamfer distance per "
        "rollout (px at 512, lower is better), averaged per drawing then over drawings.",
        "",
        "| quantity | value |",
        "| --- | --- |",
        f"| Chamfer, mean over drawings | **{s['chamfer_mean']:.2f} px** |",
        f"| std / s.e.m. over drawings | {s['chamfer_std_over_tasks']:.2f} / {s['chamfer_sem_over_tasks']:.2f} px |",
        f"| median rollout | {s['chamfer_median_rollout']:.2f} px |",
        f"| rollouts under 5 px | {100 * s['rollouts_under_5px']:.0f}% |",
        "| paper (BPP, 224 px images, 27+ GPU-hours) | 3.41 ± 0.13 px |",
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
    if args.preset == "cpu-board":
        lines.append(
            "Note: the `cpu-board` preset observes the cursor, the pen and the length of ink drawn so far and acts "
            "in the board's own frame (state only), which removes the need to learn rotations from data; the "
            "paper's setting is images and canvas actions "
            "(`--preset cpu` is state-only with canvas actions). See BENCHMARKS.md."
        )
    (args.out_dir / "report.md").write_text("\n".join(lines) + "\n")


# ----------------------------------------------------------------------------- bpp train


@dataclass(frozen=True)
class Train:
    """Train a policy on a store (CPU, GPU, or many GPUs under torchrun).

    Examples:
      bpp train --data data/draw/train.zarr --out runs/bpp-cpu --preset cpu
      bpp train --method icrt --data data/draw/train.zarr --out runs/icrt-cpu --preset cpu
      bpp train --data data/draw/train.zarr --out runs/bpp-cpu --resume        (continue a killed run)
      torchrun --nproc-per-node 4 -m bpp.cli train --data ... --preset paper --out runs/paper
    """

    train: Annotated[TrainConfig, tyro.conf.OmitArgPrefixes]
    preset: str = "cpu"
    """Model preset of the chosen --method (e.g. debug, cpu, paper; --model.* flags override it)."""
    model: Any = None


def _train_class(method) -> type:
    """`Train` with `model` typed as the method's config, so that tyro offers that method's --model.* flags."""
    cls = make_dataclass(
        "Train",
        [("model", method.config_cls, field(default_factory=method.config_cls))],
        bases=(Train,),
        frozen=True,
    )
    cls.__doc__ = Train.__doc__
    return cls


def train_cmd(args: Train) -> None:
    from bpp.train import train

    ckpt = train(args.train, args.model)
    print(f"[train] final checkpoint: {ckpt}")


# ----------------------------------------------------------------------------- bpp draw rollout


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


def draw_rollout(args: DrawRollout) -> None:
    import numpy as np

    from bpp.data.store import EpisodeStore
    from bpp.envs.draw.viz import contact_sheet, group_strokes, render_strokes, save_animation
    from bpp.evaluation.draw import rollout
    from bpp.policies.agent import PolicyAgent

    store = EpisodeStore(args.store)
    agent = PolicyAgent.from_checkpoint(args.checkpoint, record_attention=True)
    result = rollout(agent, store, args.episode, np.radians(args.board_angle_deg), args.seed, record_frames=True)
    ep = store.episode(args.episode, ("state", "action"))
    prompt_img = render_strokes(
        group_strokes(ep["state"], ep["action"].astype(np.float64)),
        float(store.column("board_angle")[args.episode]),
        256,
    )
    args.out.mkdir(parents=True, exist_ok=True)
    sheet = contact_sheet(
        [prompt_img, result.frames[-1]],
        ["prompt", f"rollout: Chamfer {result.best_chamfer:.2f}"],
        args.out / "rollout.png",
        columns=2,
    )
    gif = save_animation(result.frames, args.out / "rollout.gif")
    print(f"best Chamfer {result.best_chamfer:.2f} px (final {result.final_chamfer:.2f}) in {result.steps} steps")
    print(f"wrote {sheet} and {gif}")


# ----------------------------------------------------------------------------- bpp eval


@dataclass(frozen=True)
class Eval:
    """Evaluate checkpoints on DrawAnything-Sim with the paper's protocol (JSON, Markdown, grid, attention, video).

    Examples:
      bpp eval runs/bpp-cpu                                   (the 50 unseen human-made drawings, 32 rollouts each)
      bpp eval runs/bpp-cpu --tasks train --num-tasks 20      (training drawings)
      bpp eval runs/bpp-cpu --drawings house.svg star.json    (your own drawings)
      bpp eval runs/seed0 runs/seed1 runs/seed2               (mean ± std over checkpoints)
      bpp eval runs/bpp-cpu --prompts other-task              (control: prompted with another task's demo)
    """

    checkpoints: tyro.conf.Positional[tuple[Path, ...]]
    """Run directories or checkpoint folders (several: e.g. one per seed)."""
    tasks: str = "human"
    """human (the built-in unseen drawings), train (the checkpoint's training store) or a store path."""
    drawings: tuple[Path, ...] = ()
    """JSON stroke files or SVGs to evaluate on instead (demonstrated by the built-in demonstrator)."""
    num_tasks: int = 0
    """Tasks to evaluate, spread evenly (0: all; train: 50)."""
    rollouts: int = 32
    """Rollouts per task; prompts cycle through each task's demonstrations."""
    seed: int = 0
    max_steps: int = 400
    prompts: Literal["own", "other-task"] = "own"
    """own: the paper's protocol. other-task: a control, each rollout prompted with another task's demonstration
    and scored against its own task's drawing (a policy that follows its prompt must score far worse)."""
    n_action_steps: int = 0
    """Actions executed per inference (0: the checkpoint's Ta; fewer replans more often)."""
    inference_steps: int = 0
    """Denoising steps per inference for diffusion decoders (0: the checkpoint's own)."""
    workers: int = 0
    """Processes (0: one per core)."""
    videos: int = 2
    """Tasks whose first rollout is saved as a video."""
    out: Path = Path("outputs/eval")
    data_dir: Path = Path("data/draw")
    """Where the human set (and stores made from --drawings) are generated."""


def eval_cmd(args: Eval) -> None:
    from bpp.evaluation.evaluate import Protocol, combine, evaluate, resolve_task_set
    from bpp.evaluation.report import markdown_table
    from bpp.utils import write_json_atomic

    protocol = Protocol(
        rollouts=args.rollouts,
        seed=args.seed,
        max_steps=args.max_steps,
        prompts=args.prompts,
        n_action_steps=args.n_action_steps,
        inference_steps=args.inference_steps,
    )
    runs = []
    for i, ckpt in enumerate(args.checkpoints):
        store, tasks, label = resolve_task_set(args.tasks, ckpt, args.drawings, args.data_dir, args.num_tasks)
        out = args.out if len(args.checkpoints) == 1 else args.out / f"{i}-{Path(ckpt).name}"
        data = evaluate(ckpt, store, tasks, label, out, protocol, args.workers, args.videos)
        s = data["summary"]
        spread = s["chamfer_std_over_tasks"]
        print(f"[eval] {ckpt}: {label}: Chamfer {s['chamfer_mean']:.2f} px (std over tasks {spread:.2f})")
        print(f"[eval] wrote {out}/results.json, results.md, grid.png, attention.png")
        runs.append(data)
    if len(runs) > 1:
        summary = combine(runs)
        write_json_atomic(args.out / "summary.json", summary)
        rows = [(run["checkpoint"], run["summary"]["chamfer_mean"]) for run in runs]
        text = markdown_table(["checkpoint", "Chamfer (px)"], rows)
        text += f"\n**{summary['chamfer_mean']:.2f} ± {summary['chamfer_std']:.2f} px** (mean ± std over checkpoints)\n"
        (args.out / "summary.md").write_text(text)
        print(f"[eval] {len(runs)} checkpoints: {summary['chamfer_mean']:.2f} ± {summary['chamfer_std']:.2f} px")


# ----------------------------------------------------------------------------- dispatch

COMMANDS: dict[tuple[str, ...], tuple[type, Callable]] = {
    ("draw", "generate"): (DrawGenerate, draw_generate),
    ("draw", "sheet"): (DrawSheet, draw_sheet),
    ("draw", "video"): (DrawVideo, draw_video),
    ("store", "info"): (StoreInfo, store_info),
    ("train",): (Train, train_cmd),
    ("draw", "rollout"): (DrawRollout, draw_rollout),
    ("eval",): (Eval, eval_cmd),
    ("demo",): (Demo, demo),
}


def _usage() -> str:
    lines = ["usage: bpp <command> [--help]", "", "commands:"]
    for words, (cls, _) in COMMANDS.items():
        summary = (cls.__doc__ or "").strip().splitlines()[0]
        lines.append(f"  bpp {' '.join(words):16s} {summary}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    argv = list(sys.argv[1:] if argv is None else argv)
    for n in (2, 1):
        words = tuple(argv[:n])
        if words in COMMANDS:
            cls, run = COMMANDS[words]
            rest = argv[n:]
            default = None
            if cls is DrawGenerate:
                default = DrawGenerate(out=tyro.MISSING, data=_draw_preset(rest))
            elif cls is Train:
                try:
                    method = get_method(_flag(rest, "--method", "bpp"))
                    preset = _flag(rest, "--preset", "cpu")
                    model = method.preset(preset)
                except ValueError as err:
                    sys.exit(f"bpp train: {err}")
                cls = _train_class(method)
                default = cls(train=TrainConfig(data=tyro.MISSING, method=method.name), model=model, preset=preset)
            args = tyro.cli(cls, args=rest, prog=f"bpp {' '.join(words)}", default=default)
            try:
                run(args)
            except (ValueError, OSError, RuntimeError, KeyError) as err:
                sys.exit(f"bpp {' '.join(words)}: error: {err}")
            return
    print(_usage(), file=sys.stderr if argv and argv[0] not in ("-h", "--help") else sys.stdout)
    if argv and argv[0] not in ("-h", "--help"):
        sys.exit(2)


def _flag(argv: list[str], flag: str, default: str) -> str:
    """The value of `flag` in argv (before tyro parses it: presets decide the other flags' defaults)."""
    value = default
    for i, a in enumerate(argv):
        if a == flag and i + 1 < len(argv):
            value = argv[i + 1]
        elif a.startswith(flag + "="):
            value = a.split("=", 1)[1]
    return value


def _draw_preset(argv: list[str]) -> DrawDataConfig:
    name = _flag(argv, "--preset", "paper")
    if name not in DRAW_PRESETS:
        sys.exit(f"bpp draw generate: unknown preset {name!r}; choose from {', '.join(DRAW_PRESETS)}")
    return DRAW_PRESETS[name]


if __name__ == "__main__":
    main()
