"""The ``bpp`` command line: ``bpp <group> <command> [flags]``; every command has ``--help``.

Commands are small dataclasses parsed by tyro, so every flag is typed, documented and validated.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from dataclasses import dataclass, field, make_dataclass
from pathlib import Path
from typing import Annotated, Any

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
    """The main job, end to end on built-in defaults (re-running reuses what is already built).

    For now: generate a small DrawAnything-Sim training set and the unseen human-made evaluation set, and write
    contact sheets and an animation of them.
    """

    out_dir: Path = Path("outputs/demo")
    data_dir: Path = Path("data/draw")
    num_tasks: int = 64
    workers: int = 0


def demo(args: Demo) -> None:
    from bpp.data.store import EpisodeStore, StoreError
    from bpp.envs.draw.dataset import generate
    from bpp.envs.draw.sheets import write_contact_sheet
    from bpp.envs.draw.viz import episode_frames, save_animation

    def ensure(name: str, cfg: DrawDataConfig) -> EpisodeStore:
        path = args.data_dir / f"{name}.zarr"
        try:
            store = EpisodeStore(path)
            if store.config.get("num_tasks") == cfg.num_tasks or cfg.source != "procedural":
                print(f"[demo] reusing {store}")
                return store
        except StoreError:
            pass
        print(f"[demo] generating {path}")
        return generate(cfg, path, workers=args.workers, overwrite=True)

    train = ensure("train-demo", DrawDataConfig(num_tasks=args.num_tasks))
    human = ensure("human", DRAW_PRESETS["human"])
    args.out_dir.mkdir(parents=True, exist_ok=True)
    sheets = [
        write_contact_sheet(train.path, args.out_dir / "train_sheet.png", tasks=8, demos=5),
        write_contact_sheet(human.path, args.out_dir / "human_sheet.png", tasks=10, demos=5),
    ]
    ep = human.episode(0, ("state", "action"))
    frames = episode_frames(ep["state"], ep["action"].astype("float64"), float(human.column("board_angle")[0]))
    gif = save_animation(frames, args.out_dir / "human_demo_0.gif")
    print("[demo] done. Results:")
    for path in [*sheets, gif]:
        print(f"  {path}")


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


# ----------------------------------------------------------------------------- dispatch

COMMANDS: dict[tuple[str, ...], tuple[type, Callable]] = {
    ("draw", "generate"): (DrawGenerate, draw_generate),
    ("draw", "sheet"): (DrawSheet, draw_sheet),
    ("draw", "video"): (DrawVideo, draw_video),
    ("store", "info"): (StoreInfo, store_info),
    ("train",): (Train, train_cmd),
    ("draw", "rollout"): (DrawRollout, draw_rollout),
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
