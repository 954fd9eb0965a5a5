"""Named whole runs: one method on one benchmark end to end (data, training, evaluation, a report), each stage reused
once it is done, so a killed or repeated run picks up where it stopped.

``bpp run NAME`` runs the preset NAME of :data:`RUNS`; every field is a flag that overrides it (named configs, as
openpi's are overridden on its command line). ``bpp demo`` is ``bpp run demo``: the main job. A preset is data, not
code: adding one is an entry in :data:`RUNS` naming a benchmark, its data preset and task set, a method and its sizes.
Training and evaluation are the generic ones (:func:`bpp.train.train`, :func:`bpp.evaluation.evaluate.evaluate`);
torch is imported when a run starts, not when the command line starts.
"""

from __future__ import annotations

import contextlib
import dataclasses
import time
from dataclasses import dataclass
from pathlib import Path

from bpp.core.registry import DEFAULT_BENCHMARK, get_benchmark
from bpp.data.store import EpisodeStore, stored_with
from bpp.errors import UserError
from bpp.policies.registry import get_method
from bpp.utils import check_fields, write_text_atomic


@dataclass(frozen=True)
class WholeRun:
    """One method on one benchmark end to end, on the preset's defaults (every field a flag):

    1. generate the benchmark's training data (`data` preset, `num_tasks` tasks) and the evaluation task set into
       data_dir;
    2. train the method (`preset` size, `obs` observations) into run_dir (a killed run resumes);
    3. evaluate it on the task set with the paper's protocol (fewer rollouts per task by default);
    4. write a report folder (table, prompt | rollout grid, prompt attention, rollout videos) and print its path.

    Re-running reuses every finished stage.
    """

    out_dir: Path | None = None
    """The report folder (default: outputs/NAME)."""
    data_dir: Path | None = None
    """Where the data is generated (default: the benchmark's data folder)."""
    run_dir: Path | None = None
    """The training run (default: runs/NAME-METHOD)."""
    benchmark: str = DEFAULT_BENCHMARK
    data: str = "cpu"
    """The benchmark's data preset to train on (its store: data_dir/train-N.zarr, or train-PRESET-N.zarr for others
    than cpu)."""
    num_tasks: int = 500
    """Training tasks (the data preset's demonstrations each)."""
    tasks: str = "human"
    """The benchmark's task set to evaluate on (generated into data_dir on first use)."""
    method: str = "bpp"
    preset: str = "cpu"
    """The method's size preset (debug, cpu, paper)."""
    obs: str = "board"
    """The benchmark's observation preset (bpp train --help lists them)."""
    steps: int = 12000
    """Training steps."""
    batch_size: int = 64
    """Samples per training step (windows of a demonstration; ICRT's samples are whole demonstrations)."""
    tasks_per_batch: int = 8
    """Tasks per training step, each with its own prompt (the paper: 1; more learn faster on a CPU)."""
    rollouts: int = 8
    """Rollouts per evaluation task (the paper uses 32: bpp eval --rollouts 32)."""
    eval_tasks: int = 0
    """Evaluation tasks (0: all of the task set)."""
    max_steps: int = 400
    """Rollout length limit."""
    noise_scale: float = -1.0
    """A diffusion decoder's initial noise times this when it acts, in [0, 2], saved with the policy (-1: the
    method's own, 1); below 1 acts nearer the most likely action chunk (see docs/training.md)."""
    workers: int = 0
    """Processes for data generation and evaluation (0: one per core)."""
    threads: int = 0
    """torch threads for training (0: auto, one fewer than the cores; -1: every core unless OMP_NUM_THREADS is set,
    for a run that has the machine to itself: faster on an idle machine, slower beside another busy program; see
    docs/training.md, "CPU threads")."""
    loader_workers: int = -1
    """Data-loader processes for training (-1: auto, none on a CPU)."""
    seed: int = 0
    paper: str = ""
    """The paper's score in its own setting, set beside this run's in the report."""

    def __post_init__(self):
        check_fields(
            self,
            ("num_tasks", self.num_tasks >= 1, ">= 1"),
            ("steps", self.steps >= 1, ">= 1"),
            ("batch_size", self.batch_size >= self.tasks_per_batch, ">= tasks_per_batch"),
            ("tasks_per_batch", self.tasks_per_batch >= 1, ">= 1"),
            ("rollouts", self.rollouts >= 1, ">= 1"),
            ("eval_tasks", self.eval_tasks >= 0, ">= 0 (0: all)"),
            ("max_steps", self.max_steps >= 1, ">= 1"),
            ("noise_scale", self.noise_scale == -1 or 0 <= self.noise_scale <= 2, "in [0, 2], or -1 (the method's)"),
            ("workers", self.workers >= 0, ">= 0 (0: one per core)"),
            ("threads", self.threads >= -1, ">= -1 (0: auto, -1: every core)"),
            ("loader_workers", self.loader_workers >= -1, ">= -1 (-1: auto)"),
            ("seed", self.seed >= 0, ">= 0"),
        )

    @property
    def sampling_noise(self) -> float | None:
        """The decoder's noise scale this run asks for; None: the method's own."""
        return None if self.noise_scale == -1 else self.noise_scale


RUNS: dict[str, WholeRun] = {
    # The main job: BPP on the default benchmark, state observations, training on every core (it runs alone).
    # Its decoder samples from zero noise: the most likely chunk, the most precise drawings on the validation split.
    "demo": WholeRun(threads=-1, noise_scale=0.0, paper="BPP, 224 px images, 27-42 hours on 4 GPUs: 3.41 ± 0.13 px"),
    # The same on ICRT, the paper's strongest baseline, at its own batch (whole demonstrations) and a similar time.
    "demo-icrt": WholeRun(
        run_dir=Path("runs/demo-icrt"),
        out_dir=Path("outputs/demo-icrt"),
        method="icrt",
        steps=3000,
        batch_size=16,
        paper="ICRT, 224 px images: about 5.1 px",
    ),
    # A minute's check that everything runs (a debug-size model; its score means nothing).
    "smoke": WholeRun(
        data_dir=Path("data/smoke"),
        preset="debug",
        num_tasks=12,
        steps=200,
        eval_tasks=5,
        rollouts=2,
        max_steps=100,
    ),  # fmt: skip
}
"""Named whole runs (``bpp run NAME``)."""
SUMMARIES = {
    "demo": "The main job: BPP on the default benchmark's unseen tasks, end to end on built-in defaults.",
    "demo-icrt": "The main job's data and evaluation, on ICRT (the paper's strongest baseline).",
    "smoke": "A minute's check that data, training, evaluation and the report all run (a debug-size model).",
}
"""What each named run is, as ``bpp run --help`` lists them."""


def whole_run(args: WholeRun, name: str = "") -> None:
    """Run `args` (the preset `name`, as the flags changed it)."""
    # torch: imported when a run starts, not when the command line starts
    from bpp.checkpoint import Checkpoint, read_state, resolve_checkpoint
    from bpp.evaluation.evaluate import Protocol, evaluate, resolve_tasks
    from bpp.train import TrainConfig, run_differences, train

    t0 = time.perf_counter()
    label = f"run {name}" if name else "run"

    def stage(text: str) -> None:
        print(f"[{label} {time.perf_counter() - t0:6.0f} s] {text}", flush=True)

    benchmark = get_benchmark(args.benchmark)
    args = dataclasses.replace(
        args,
        out_dir=args.out_dir or Path("outputs") / (name or "run"),
        data_dir=args.data_dir or benchmark.default_data_dir,
        run_dir=args.run_dir or Path("runs") / f"{name or 'run'}-{args.method}",
    )
    if args.tasks not in benchmark.task_sets:
        raise UserError(f"--tasks {args.tasks!r}: {benchmark.name}'s task sets are {', '.join(benchmark.task_sets)}")
    method = get_method(args.method)
    model_cfg = method.config(args.preset, args.obs, benchmark)  # flags refused before any data is made
    noise_scale = args.sampling_noise
    if noise_scale is not None:
        if not hasattr(model_cfg, "diffusion"):
            raise UserError(f"--noise-scale: {args.method} has no diffusion decoder, so no noise to scale")
        decoder = dataclasses.replace(model_cfg.diffusion, noise_scale=noise_scale)
        model_cfg = dataclasses.replace(model_cfg, diffusion=decoder)
    store = _training_data(args, benchmark, stage)
    stage(f"the evaluation set: {benchmark.task_set(args.tasks, args.data_dir, args.workers).store.path}")
    run = args.run_dir
    finished = False
    with contextlib.suppress(OSError, ValueError):  # no checkpoint yet
        finished = read_state(resolve_checkpoint(run))["step"] >= args.steps
    resume = (run / "checkpoints" / "last").is_file()
    tc = TrainConfig(
        data=store.path,
        out=run,
        method=args.method,
        steps=args.steps,
        batch_size=args.batch_size,
        tasks_per_batch=args.tasks_per_batch,
        seed=args.seed,
        resume=resume,
        save_every=500,
        threads=args.threads,
        workers=args.loader_workers,
    )
    if resume and not finished:
        steps = [d for d in run_differences(run, tc, model_cfg) if d.startswith("train_config.steps:")]
        if steps:  # e.g. a run of an earlier, shorter main job
            raise UserError(
                f"{run} holds a run of other length ({steps[0]}); pass --steps with its length to reuse it, or "
                "another --run-dir to train anew"
            )
    if finished:
        # Its model must be this one (how long or how it trained may differ: a finished run is reused as it is).
        differences = [d for d in run_differences(run, tc, model_cfg) if not d.startswith("train_config.")]
        if differences:
            raise UserError(
                f"{run} holds a policy trained with another model than --method {args.method} --preset {args.preset} "
                f"--obs {args.obs}; pass another --run-dir, or the flags it was trained with: " + "; ".join(differences)
            )
        stage(f"reusing the trained policy in {run}")
    else:
        what = f"{args.preset} preset, {args.obs} observations, {args.steps} steps"
        stage(f"{'resuming' if resume else 'training'} {args.method} ({what}) in {run}")
        train(tc, model_cfg)

    ckpt = Checkpoint.load(run, use_ema=True)
    _, task_set, tasks = resolve_tasks(args.tasks, ckpt, data_dir=args.data_dir, num_tasks=args.eval_tasks)
    stage(f"evaluating on the {task_set.label} ({args.rollouts} rollouts each)")
    protocol = Protocol(rollouts=args.rollouts, seed=args.seed, max_steps=args.max_steps, noise_scale=noise_scale)
    result = evaluate(ckpt, task_set, tasks, args.out_dir / f"eval-{args.tasks}", protocol, args.workers)
    write_report(args, name, benchmark, task_set.label, result, time.perf_counter() - t0)
    stage(f"done. Report: {args.out_dir / 'report.md'}")
    if benchmark.name == DEFAULT_BENCHMARK:
        studio = f"bpp studio --runs {args.run_dir.parent}"
        print(f"[{label}] prompt it yourself: `{studio}` opens a page where you draw a prompt")


def _training_data(args: WholeRun, benchmark, stage) -> EpisodeStore:
    """The run's training store: generated from the benchmark's data preset with the run's task count and seed, or
    reused if it is already there from exactly that configuration."""
    if args.data not in benchmark.data_presets:
        raise UserError(
            f"--data {args.data!r}: {benchmark.name}'s data presets are {', '.join(benchmark.data_presets)}"
        )
    base = benchmark.data_presets[args.data]
    try:
        cfg = dataclasses.replace(base, num_tasks=args.num_tasks, seed=args.seed)
    except TypeError:
        raise UserError(
            f"{benchmark.name}'s data presets take no task count and seed: a whole run needs both"
        ) from None
    name = f"train-{args.num_tasks}" if args.data == "cpu" else f"train-{args.data}-{args.num_tasks}"
    path = args.data_dir / f"{name}.zarr"
    store = stored_with(path, cfg)
    if store is not None:
        stage(f"reusing {store}")
        return store
    stage(f"generating {path}")
    return benchmark.generate(cfg, path, workers=args.workers, overwrite=True)


def _sampling(args: WholeRun) -> str:
    """How the policy's decoder sampled, as a phrase for the report ("" for the method's own way)."""
    if args.sampling_noise is None:
        return ""
    return f", its decoder sampling from noise x {args.sampling_noise:g} (1: as trained)"


def write_report(args: WholeRun, name: str, benchmark, label: str, result: dict, seconds: float) -> None:
    """``report.md`` in the run's out_dir: the score, the pictures and videos of the evaluation, how it was made."""
    s, metric = result["summary"], benchmark.metric
    unit = f" {metric.unit}" if metric.unit else ""
    eval_dir = f"eval-{args.tasks}"
    videos = [task["video"] for task in result["tasks"] if task.get("video")]  # this evaluation's, not older ones
    observation = benchmark.observations[args.obs].description
    lines = [
        f"# bpp {name or 'run'}: {args.method} on {benchmark.name}, {label}",
        "",
        f"Trained `{args.preset}` {args.method} with `{args.obs}` observations for {result['train_step']} steps on "
        f"{args.num_tasks} training tasks ({args.run_dir}); evaluated on {s['tasks']} tasks x {args.rollouts} "
        f"rollouts, each prompted with one demonstration{_sampling(args)}. Score: {metric.description}, averaged per "
        "task then over tasks.",
        "",
        "| quantity | value |",
        "| --- | --- |",
        f"| {metric.name}, mean over tasks | **{metric.format(s['score_mean'])}** |",
        f"| std / s.e.m. over tasks | {s['score_std_over_tasks']:.2f} / {s['score_sem_over_tasks']:.2f}{unit} |",
        f"| median rollout | {metric.format(s['score_median_rollout'])} |",
        *([f"| {metric.good_label} | {100 * s['good_rollouts']:.0f}% |"] if metric.good_label else []),
        *([f"| paper | {args.paper} |"] if args.paper else []),
        f"| wall time of this run (this call) | {seconds / 60:.1f} min |",
        "",
        f"Per task: [{eval_dir}/results.md]({eval_dir}/results.md); raw numbers: "
        f"[{eval_dir}/results.json]({eval_dir}/results.json).",
        "",
        f"![prompt | rollout]({eval_dir}/grid.png)",
        "",
        f"![prompt attention]({eval_dir}/attention.png)",
        "",
        "Rollout videos: " + ", ".join(f"[{v}]({eval_dir}/{v})" for v in videos),
        "",
        f"Observations `{args.obs}`: {observation}.",
    ]
    write_text_atomic(args.out_dir / "report.md", "\n".join(lines) + "\n")
