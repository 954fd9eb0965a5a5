"""The ``bpp`` command line: ``bpp <group> <command> [flags]``; every command has ``--help``.

One path for every benchmark: ``bpp <benchmark> generate`` writes a store, ``bpp train --data STORE`` reads the
benchmark from the store, ``bpp eval RUN`` reads it from the checkpoint. A benchmark adds its own commands under its
group (``bpp draw sheet ...``). Commands are small dataclasses parsed by tyro, so every flag is typed, documented
and validated.
"""

from __future__ import annotations

import signal
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field, make_dataclass
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
import tyro

from bpp.core.registry import (
    DEFAULT_BENCHMARK,
    benchmark_commands,
    benchmark_for_command,
    benchmark_names,
    get_benchmark,
    open_store,
)
from bpp.data.merge import merge_stores
from bpp.data.store import EpisodeStore
from bpp.errors import UserError, raise_interrupted
from bpp.evaluation.protocol import PromptChoice
from bpp.evaluation.report import markdown_table
from bpp.executor import check_executor_flags, make_executor
from bpp.policies.registry import get_method
from bpp.runs import RUNS, SUMMARIES, WholeRun, whole_run
from bpp.serve.command import Serve, serve
from bpp.serve.robot import RobotClient, robot_client
from bpp.train_config import TrainConfig
from bpp.utils import check_fields, write_json_atomic, write_text_atomic

# ----------------------------------------------------------------------------- bpp <benchmark> generate


@dataclass(frozen=True)
class Generate:
    """Generate a benchmark's tasks and demonstrations into a store (atomically)."""

    out: Path
    """Store to write (a .zarr folder)."""
    preset: str = ""
    """Starting data configuration, one of the benchmark's data presets (default: its first; flags below override
    it)."""
    workers: int = 0
    """Worker processes (0: one per core)."""
    executor: Literal["local", "ray"] = "local"
    """Where the tasks are demonstrated: local processes, or a Ray cluster (pip install -e '.[ray]' in bpp's clone):
    the same store."""
    ray_address: str = ""
    """The Ray cluster's head (host:port, or auto); default: RAY_ADDRESS, else a cluster on this machine."""
    overwrite: bool = False
    """Replace an existing store."""
    data: Any = None

    def __post_init__(self):
        check_executor_flags(self.executor, self.workers, self.ray_address)  # a cluster is reached when it runs


def _generate_class(benchmark) -> type:
    """`Generate` with `data` typed as the benchmark's data config, so that tyro offers its fields as flags."""
    cls = make_dataclass(
        "Generate",
        [("data", Annotated[benchmark.data_config, tyro.conf.OmitArgPrefixes], field(default=None))],
        bases=(Generate,),
        frozen=True,
    )
    presets = ", ".join(benchmark.data_presets)
    cls.__doc__ = (
        f"Generate {benchmark.name} tasks and demonstrations into a store (atomically); data presets: {presets}.\n\n"
        f"{benchmark.description}.\n\nExample:\n  bpp {benchmark.command} generate --preset "
        f"{next(iter(benchmark.data_presets))} --out data/{benchmark.command}/train.zarr"
    )
    return cls


def generate_cmd(args: Generate, benchmark) -> None:
    t0 = time.perf_counter()
    executor = make_executor(args.executor, args.workers, args.ray_address)
    store = benchmark.generate(args.data, args.out, workers=executor, overwrite=args.overwrite)
    print(f"wrote {store}")
    print(f"  {time.perf_counter() - t0:.1f} s, {store.disk_bytes() / 1e6:.1f} MB on disk")


# ----------------------------------------------------------------------------- bpp store info


@dataclass(frozen=True)
class StoreInfo:
    """Summarise a store: benchmark, tasks, episodes, steps, keys, episode lengths, size.

    Opening a store checks its header and every array's metadata against their digests; every chunk is checked
    (present, matching its checksum, the chunk the header records under its key) when it is read. --verify reads
    them all now.

    Example:
      bpp store info data/draw/train.zarr --verify
    """

    store: tyro.conf.Positional[Path]
    verify: bool = False
    """Read every chunk of the store and check it."""


def store_info(args: StoreInfo) -> None:
    s = open_store(args.store)
    lengths = np.diff(np.concatenate([[0], s.episode_ends]))
    print(s)
    print(f"  created {s.attrs.get('created')}, {s.disk_bytes() / 1e6:.1f} MB")
    print(f"  episode length: mean {lengths.mean():.1f}, min {lengths.min()}, max {lengths.max()}")
    for key in s.keys:
        arr = s[key]
        print(f"  {key:16s} {str(arr.dtype):8s} {arr.shape}")
    if args.verify:
        t0 = time.perf_counter()
        chunks = s.verify()
        seconds = time.perf_counter() - t0
        print(f"  verified: all {chunks} chunks present and matching their checksums ({seconds:.1f} s)")
        if not s.chunks_recorded:
            print(
                f"  note: a version {s.attrs['version']} store records no checksum per chunk key, so a chunk of "
                "another store in one's place goes unseen; generate it again to have them"
            )


# ----------------------------------------------------------------------------- bpp store merge


@dataclass(frozen=True)
class StoreMerge:
    """Merge stores of one benchmark into one (atomically): pieces generated on several machines, or demonstrations
    of a few tasks added later. A task in several stores keeps one entry with all its episodes. Refused, naming the
    field: stores of different benchmarks, keys, columns, per-task arrays, shapes or dtypes, or of different cameras or
    rates in their configs, and a task id that names different tasks (procedural pieces need different --seed
    values); a demonstration that two of the stores hold (a store given twice, a copy, a merge that includes
    another); and a store to write (--out) that is an input, lies inside one or holds one.

    Example:
      bpp store merge data/libero/chain-train.zarr data/libero/chain-extra.zarr --out data/libero/chain-all.zarr
    """

    stores: tyro.conf.Positional[tuple[Path, ...]]
    out: Path
    """Store to write (a .zarr folder)."""
    overwrite: bool = False
    """Replace an existing store."""


def store_merge(args: StoreMerge) -> None:
    store = merge_stores(args.stores, args.out, overwrite=args.overwrite)
    print(f"wrote {store}")


# ----------------------------------------------------------------------------- bpp train


@dataclass(frozen=True)
class Train:
    """Train a policy on a store (CPU, GPU, or many GPUs under torchrun); the benchmark is the store's.

    The model is a method's size preset (--preset debug|cpu|paper) observing one of the benchmark's observation
    presets (--obs; default: the benchmark's for that size); --model.* flags override any field.

    Examples:
      bpp train --data data/draw/train.zarr --out runs/bpp-cpu --preset cpu --obs board
      bpp train --method icrt --data data/draw/train.zarr --out runs/icrt-cpu --preset cpu --obs board
      bpp train --data data/draw/train.zarr --out runs/bpp-cpu --resume        (continue a killed run)
      torchrun --nproc-per-node 4 -m bpp.cli train --data ... --preset paper --out runs/paper
    """

    train: Annotated[TrainConfig, tyro.conf.OmitArgPrefixes]
    preset: str = "cpu"
    """Size preset of the chosen --method (debug, cpu, paper)."""
    obs: str = ""
    """Observation preset of the store's benchmark ("": the benchmark's default for --preset)."""
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


def _train_default(argv: list[str]) -> tuple[type, Train]:
    """The `Train` class and defaults for argv: the method, size and observation presets decide the defaults of
    every --model.* flag, and the store decides the benchmark (the default benchmark's presets for --help alone)."""
    method = get_method(_flag(argv, "--method", "bpp"))
    data = _flag(argv, "--data", "")
    benchmark = get_benchmark(EpisodeStore(data).benchmark if data else DEFAULT_BENCHMARK)
    preset, obs = _flag(argv, "--preset", "cpu"), _flag(argv, "--obs", "")
    model = method.config(preset, obs or None, benchmark)
    cls = _train_class(method)
    return cls, cls(train=TrainConfig(data=tyro.MISSING, method=method.name), model=model, preset=preset, obs=obs)


def train_cmd(args: Train) -> None:
    # torch: imported when the command runs, not when the command line starts
    from bpp.train import train

    ckpt = train(args.train, args.model)
    print(f"[train] final checkpoint: {ckpt}")


# ----------------------------------------------------------------------------- bpp eval


@dataclass(frozen=True)
class Eval:
    """Evaluate checkpoints with the paper's protocol on their benchmark (JSON, Markdown, grid, attention, videos).

    Examples:
      bpp eval runs/bpp-cpu                                   (the benchmark's first named task set, e.g. human)
      bpp eval runs/bpp-cpu --tasks train --num-tasks 20      (training tasks)
      bpp eval runs/bpp-cpu --tasks data/draw/val.zarr        (any store of the same benchmark)
      bpp eval runs/bpp-cpu --files mine.json logo.svg        (your own tasks, in the benchmark's file format)
      bpp eval runs/seed0 runs/seed1 runs/seed2               (mean ± std over checkpoints)
      bpp eval runs/bpp-cpu --prompts other-task              (control: prompted with another task's demo;
                                                               also shuffled, first-half, none)
    """

    checkpoints: tyro.conf.Positional[tuple[Path, ...]]
    """Run directories or checkpoint folders (several: e.g. one per seed)."""
    tasks: str = ""
    """train (the checkpoint's training store), a named task set of the benchmark (see README), or a store path
    ("": the benchmark's first named set, else train)."""
    files: tuple[Path, ...] = ()
    """Files of your own tasks to evaluate on instead, in the benchmark's format (see README), demonstrated by its
    built-in demonstrator."""
    num_tasks: int = 0
    """Tasks to evaluate, spread evenly (0: all; train: 50)."""
    rollouts: int = 32
    """Rollouts per task; prompts cycle through each task's demonstrations."""
    seed: int = 0
    max_steps: int = 0
    """Rollout length limit (0: the benchmark's, e.g. 400)."""
    prompts: PromptChoice = "own"
    """own: the paper's protocol. Controls, each scored against the rollout's own task (a policy that follows its
    prompt must score worse): other-task, prompted with another task's demonstration; shuffled, with its own
    demonstration's 10-step chunks in a random order; first-half, with the first half of its own demonstration;
    none, with no prompt (not for a goal-image method, which needs its goal)."""
    n_action_steps: int = 0
    """Actions executed per inference (0: the checkpoint's Ta; fewer replans more often)."""
    inference_steps: int = 0
    """Denoising steps per inference for diffusion decoders (0: the checkpoint's own)."""
    noise_scale: float = -1.0
    """A diffusion decoder's initial noise times this, in [0, 2]: below 1 samples nearer the most likely chunk
    (-1: the checkpoint's own, 1 unless trained with --model.diffusion.noise-scale)."""
    tasks_per_batch: int = 1
    """Tasks whose rollouts step together through the policy, in the order evaluated: faster on a CPU (e.g. 8); each
    task's scores then depend in their last bits on the tasks batched with it. A benchmark that keeps a simulator per
    rollout keeps that many more in memory."""
    workers: int = 0
    """Processes (0: one per core), for the rollouts and for generating a named task set or --files the first time."""
    executor: Literal["local", "ray"] = "local"
    """Where the tasks' rollouts run: local processes, or a Ray cluster (pip install -e '.[ray]' in bpp's clone): the
    same results."""
    ray_address: str = ""
    """The Ray cluster's head (host:port, or auto); default: RAY_ADDRESS, else a cluster on this machine."""
    videos: int = 2
    """Tasks whose first rollout is saved as a video."""
    out: Path = Path("outputs/eval")
    data_dir: Path | None = None
    """Where named task sets and stores made from --files are generated (default: the benchmark's own folder)."""

    def __post_init__(self):
        check_fields(
            self,
            ("checkpoints", len(self.checkpoints) >= 1, "at least one run directory or checkpoint folder"),
            ("num_tasks", self.num_tasks >= 0, ">= 0 (0: all)"),
            ("workers", self.workers >= 0, ">= 0 (0: one per core)"),
            ("videos", self.videos >= 0, ">= 0"),
        )
        check_executor_flags(self.executor, self.workers, self.ray_address)  # a cluster is reached when it runs


def eval_cmd(args: Eval) -> None:
    # torch: imported when the command runs, not when the command line starts
    from bpp.checkpoint import Checkpoint
    from bpp.evaluation.evaluate import Protocol, combine, evaluate, resolve_tasks
    from bpp.policies.agent import PolicyAgent

    protocol = Protocol(
        rollouts=args.rollouts,
        seed=args.seed,
        max_steps=args.max_steps,
        prompts=args.prompts,
        n_action_steps=args.n_action_steps,
        inference_steps=args.inference_steps,
        noise_scale=None if args.noise_scale == -1 else args.noise_scale,
        tasks_per_batch=args.tasks_per_batch,
    )
    # Every argument is checked (checkpoints read, agent options tried, task sets resolved) before anything is
    # evaluated or written.
    checkpoints = [Checkpoint.load(path, use_ema=True) for path in args.checkpoints]
    benchmarks = {ckpt.benchmark for ckpt in checkpoints}
    if len(benchmarks) > 1:
        raise UserError(f"the checkpoints were trained on different benchmarks ({', '.join(sorted(benchmarks))})")
    for ckpt in checkpoints:
        PolicyAgent(ckpt.build_model(), **protocol.agent_options())
    executor = make_executor(args.executor, args.workers, args.ray_address)
    tasks = args.tasks or _default_tasks(checkpoints[0])
    jobs = []
    for ckpt in checkpoints:  # one task set for all (a store from --files is built once), but each its own `train`
        own = tasks == "train" and not args.files
        if own or not jobs:
            jobs.append(resolve_tasks(tasks, ckpt, args.files, args.data_dir, args.num_tasks, executor))
        else:
            jobs.append(jobs[0])
    runs = []
    for i, (ckpt, (benchmark, task_set, indices)) in enumerate(zip(checkpoints, jobs, strict=True)):
        out = args.out if len(checkpoints) == 1 else args.out / f"{i}-{Path(args.checkpoints[i]).name}"
        data = evaluate(ckpt, task_set, indices, out, protocol, executor, args.videos)
        s, metric = data["summary"], benchmark.metric
        score, spread = metric.format(s["score_mean"]), s["score_std_over_tasks"]
        print(f"[eval] {ckpt.path}: {task_set.label}: {metric.name} {score} (std over tasks {spread:.2f})")
        print(f"[eval] wrote {out}/results.json, results.md, grid.png, attention.png")
        runs.append(data)
    if len(runs) > 1:
        summary = combine(runs)
        write_json_atomic(args.out / "summary.json", summary)
        metric = jobs[0][0].metric
        rows = [(run["checkpoint"], run["summary"]["score_mean"]) for run in runs]
        text = markdown_table(["checkpoint", f"{metric.name} ({metric.unit or 'score'})"], rows)
        spread = f"{metric.format(summary['score_mean'])} ± {summary['score_std']:.2f}"
        text += f"\n**{spread}** (mean ± std over checkpoints)\n"
        write_text_atomic(args.out / "summary.md", text)
        print(f"[eval] {len(runs)} checkpoints: {metric.name} {spread}")


def _default_tasks(ckpt) -> str:
    """The task set `bpp eval` uses without --tasks: the benchmark's first named one, else the training tasks."""
    return next(iter(get_benchmark(ckpt.benchmark).task_sets), "train")


# ----------------------------------------------------------------------------- dispatch

COMMANDS: dict[tuple[str, ...], tuple[type, Callable]] = {
    ("store", "info"): (StoreInfo, store_info),
    ("store", "merge"): (StoreMerge, store_merge),
    ("train",): (Train, train_cmd),
    ("eval",): (Eval, eval_cmd),
    ("serve",): (Serve, serve),
    ("robot-client",): (RobotClient, robot_client),
}
"""Generic commands; each benchmark adds ``bpp <its command> generate`` and its own commands."""


def _resolve(argv: list[str]) -> tuple[tuple[str, ...], type, Callable, Any] | None:
    """(words, command class, function, tyro default) for the command argv starts with, or None."""
    if argv[:1] == ["demo"]:  # the main job: the named whole run "demo"
        return ("demo",), WholeRun, lambda args: whole_run(args, "demo"), RUNS["demo"]
    if argv[:1] == ["run"] and len(argv) > 1 and argv[1] in RUNS:
        name = argv[1]
        return ("run", name), WholeRun, lambda args: whole_run(args, name), RUNS[name]
    if argv[:1] == ["studio"]:  # the studio: the default benchmark's
        cls, run = benchmark_commands(get_benchmark(DEFAULT_BENCHMARK))["studio"]
        return ("studio",), cls, run, None
    for n in (2, 1):
        words = tuple(argv[:n])
        if words in COMMANDS:
            cls, run = COMMANDS[words]
            return words, cls, run, None
    benchmark = benchmark_for_command(argv[0]) if argv else None
    if benchmark is None or len(argv) < 2:
        return None
    name = argv[1]
    if name == "generate":
        preset = _flag(argv[2:], "--preset", next(iter(benchmark.data_presets)))
        if preset not in benchmark.data_presets:
            raise UserError(
                f"unknown preset {preset!r} for {benchmark.name} data; choose from {', '.join(benchmark.data_presets)}"
            )
        cls = _generate_class(benchmark)
        default = cls(out=tyro.MISSING, preset=preset, data=benchmark.data_presets[preset])
        return (argv[0], name), cls, lambda args: generate_cmd(args, benchmark), default
    commands = benchmark_commands(benchmark)
    if name in commands:
        cls, run = commands[name]
        return (argv[0], name), cls, run, None
    return None


def _command_classes() -> list[tuple[tuple[str, ...], type]]:
    """Every command's words and class, in the order ``bpp --help`` lists them."""
    found = [(words, cls) for words, (cls, _) in COMMANDS.items()]
    found.append((("demo",), _described(SUMMARIES["demo"])))
    found += [(("run", name), _described(SUMMARIES.get(name, f"The whole run {name}."))) for name in RUNS]
    found.append((("studio",), benchmark_commands(get_benchmark(DEFAULT_BENCHMARK))["studio"][0]))
    for name in benchmark_names():
        benchmark = get_benchmark(name)
        found.append(((benchmark.command, "generate"), _generate_class(benchmark)))
        found += [((benchmark.command, command), cls) for command, (cls, _) in benchmark_commands(benchmark).items()]
    return found


def _described(summary: str) -> type:
    """:class:`WholeRun` with `summary` as its help's first line (each named run's line in ``bpp --help``)."""
    return type("WholeRun", (WholeRun,), {"__doc__": f"{summary}\n\n{WholeRun.__doc__}"})


def _groups() -> set[str]:
    """The first words of the commands that take a second (``store``, each benchmark's group)."""
    return {words[0] for words, _ in _command_classes() if len(words) > 1}


def _usage(group: str = "") -> str:
    """The list of commands: all of them, or those of `group` (``bpp store``, a benchmark's group)."""
    lines = [f"usage: bpp {group + ' ' if group else ''}<command> [--help]", "", "commands:"]
    for words, cls in _command_classes():
        if not group or words[0] == group:
            summary = (cls.__doc__ or "").strip().splitlines()[0]
            lines.append(f"  bpp {' '.join(words):16s} {summary}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    """Run the command argv names. A :class:`~bpp.errors.UserError` or an OSError (a file that is missing, not
    readable or not writable, a full disk: its message names the path) ends the program with one line naming the
    command; any other exception is a bug and keeps its traceback. tyro reports bad flags itself. Ctrl-C (SIGINT) and
    SIGTERM end it with one line and the status 130 or 143, once every writer has removed what it left half-written
    and every worker process is stopped."""
    argv = list(sys.argv[1:] if argv is None else argv)
    prog = f"bpp {' '.join(argv[:2])}"
    restore = _stop_on_signals()
    try:
        found = _resolve(argv)
        if found is None:
            # A group alone or asked for help (`bpp`, `bpp --help`, `bpp store`, `bpp store --help`) lists its
            # commands; anything else is unknown: the list, to stderr, and the status 2.
            group = argv[0] if argv and argv[0] in _groups() else ""
            asked = (argv[1:] if group else argv) in ([], ["-h"], ["--help"])
            print(_usage(group), file=sys.stdout if asked else sys.stderr)
            if not asked:
                sys.exit(2)
            return
        words, cls, run, default = found
        rest = argv[len(words) :]
        prog = f"bpp {' '.join(words)}"
        if cls is Train:
            cls, default = _train_default(rest)
        described = {"description": _described(SUMMARIES[words[-1]]).__doc__} if cls is WholeRun else {}
        args = tyro.cli(cls, args=rest, prog=prog, default=default, **described)
        run(args)
    except (UserError, OSError) as err:
        sys.exit(f"{prog}: error: {_message(err)}")
    except KeyboardInterrupt as err:
        signum = getattr(err, "signum", signal.SIGINT)
        print(f"{prog}: interrupted by {signal.Signals(signum).name}", file=sys.stderr)
        sys.exit(128 + signum)
    finally:
        restore()


def _stop_on_signals() -> Callable[[], None]:
    """Make SIGINT and SIGTERM raise :class:`~bpp.errors.Interrupted` where the program is, so that both run the
    clean-up Ctrl-C runs (a signal the process was started ignoring stays ignored); returns what restores the
    handlers. Signal handlers live in the main thread only: elsewhere this does nothing."""
    if threading.current_thread() is not threading.main_thread():
        return lambda: None
    previous = {}
    for signum, default in ((signal.SIGINT, signal.default_int_handler), (signal.SIGTERM, signal.SIG_DFL)):
        if signal.getsignal(signum) in (default, raise_interrupted):  # the latter: installed by `bpp.launch`
            previous[signum] = signal.signal(signum, raise_interrupted)

    def restore() -> None:
        for signum, handler in previous.items():
            signal.signal(signum, handler)

    return restore


def _message(err: Exception) -> str:
    """What went wrong, in one line: an OSError raised by the system as "path: reason" (no errno number)."""
    if isinstance(err, OSError) and err.strerror:
        paths = [str(p) for p in (err.filename, err.filename2) if p is not None]
        return ": ".join([" -> ".join(paths), err.strerror] if paths else [err.strerror])
    return str(err)


def _flag(argv: list[str], flag: str, default: str) -> str:
    """The value of `flag` in argv (before tyro parses it: presets decide the other flags' defaults)."""
    value = default
    for i, a in enumerate(argv):
        if a == flag and i + 1 < len(argv):
            value = argv[i + 1]
        elif a.startswith(flag + "="):
            value = a.split("=", 1)[1]
    return value


if __name__ == "__main__":
    main()
