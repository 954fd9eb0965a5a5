"""One training loop for every method, on one CPU, one GPU or many processes under ``torchrun`` (DDP).

Read it top to bottom: set up (distributed, data, model, optimiser, resume), then a plain loop of
``loss = model(batch); backward; clip; step; EMA``, with logging and atomic checkpoints.
"""

from __future__ import annotations

import contextlib
import copy
import math
import os
import signal
import time
from pathlib import Path

import torch
import torch.distributed as dist
from torch.utils.tensorboard import SummaryWriter
from tqdm import tqdm

from bpp.checkpoint import load_training_state, resolve_checkpoint, save_checkpoint
from bpp.core.contract import device_frames
from bpp.core.registry import get_benchmark, open_store
from bpp.data.frame_refs import render_batch
from bpp.data.prompt_dataset import PromptBatchDataset, finite_statistics, stored_keys, trainable_tasks
from bpp.errors import UserError
from bpp.policies.model import count_parameters, keep_eager
from bpp.policies.registry import PolicyModelContract, get_method
from bpp.train_config import TrainConfig
from bpp.utils import from_dict, read_json, resolve_device, to_dict, to_torch, usable_cores, write_json_atomic


def lr_at(step: int, cfg: TrainConfig) -> float:
    """Warm-up + cosine schedule: a pure function of the step, so resuming needs no scheduler state."""
    if step < cfg.warmup_steps:
        return cfg.lr * (step + 1) / cfg.warmup_steps
    progress = (step - cfg.warmup_steps) / max(1, cfg.steps - cfg.warmup_steps)
    return cfg.lr * 0.5 * (1.0 + math.cos(math.pi * min(progress, 1.0)))


def _setup_distributed(requested: str) -> tuple[int, int, torch.device]:
    world = int(os.environ.get("WORLD_SIZE", "1"))
    rank = int(os.environ.get("RANK", "0"))
    local = int(os.environ.get("LOCAL_RANK", "0"))
    device = resolve_device(requested)
    if device.type == "cuda" and world > 1:
        device = torch.device("cuda", local)
        torch.cuda.set_device(device)
    if world > 1 and not dist.is_initialized():
        dist.init_process_group(backend="nccl" if device.type == "cuda" else "gloo")
    return rank, world, device


def cpu_plan(cfg: TrainConfig, device: torch.device) -> tuple[int, int]:
    """(loader workers, torch threads; 0: torch's default) for `cfg`'s auto settings on `device`."""
    cores = usable_cores() // int(os.environ.get("LOCAL_WORLD_SIZE", "1"))  # shared by torchrun's processes
    gpu_workers = min(2, cores - 2) if cfg.frames_on == "device" else cores - 2  # references take little building
    workers = cfg.workers if cfg.workers >= 0 else (0 if device.type == "cpu" else max(1, gpu_workers))
    threads = max(cfg.threads, 0)
    if cfg.threads <= 0 and device.type == "cpu" and not os.environ.get("OMP_NUM_THREADS"):  # the user's choice stands
        threads = max(1, cores - workers) if cfg.threads == -1 else max(1, cores - 1 - workers)
    return workers, threads


@torch.no_grad()
def _ema_update(ema: torch.nn.Module, model: torch.nn.Module, decay: float) -> None:
    # One multi-tensor kernel per list on a GPU instead of one launch per tensor (the same arithmetic as lerp_).
    torch._foreach_lerp_(list(ema.parameters()), [p.detach() for p in model.parameters()], 1.0 - decay)
    for e, b in zip(ema.buffers(), model.buffers(), strict=True):
        e.copy_(b)


def batch_loader(dataset, steps: range, workers: int, pin_memory: bool) -> torch.utils.data.DataLoader:
    """`dataset`'s whole batches for `steps`, built by `workers` processes (0: this one), each up to 4 batches ahead;
    page-locked when `pin_memory` (for a GPU), so that they copy to it while it computes."""
    return torch.utils.data.DataLoader(
        dataset,
        batch_size=None,
        sampler=steps,
        num_workers=workers,
        persistent_workers=False,
        prefetch_factor=4 if workers else None,
        pin_memory=pin_memory,
        worker_init_fn=_end_quietly_on_sigterm if workers else None,
    )


def _end_quietly_on_sigterm(worker_id: int) -> None:
    """In a loader process: SIGTERM (sent to every process of an interrupted command) ends it as Ctrl-C does, through
    the KeyboardInterrupt torch's loader loop ends on quietly. torch's own handler dies of the signal, which the
    training process then reports as a failed loader, traceback and all."""
    signal.signal(signal.SIGTERM, signal.default_int_handler)


def uses_amp(cfg: TrainConfig, device: torch.device) -> bool:
    """Whether training on `device` runs under bf16 autocast (CUDA devices that support it well)."""
    return cfg.amp and device.type == "cuda" and torch.cuda.is_bf16_supported()


def build_training(cfg: TrainConfig, model: torch.nn.Module, device: torch.device):
    """`model` on `device` in training form, its EMA copy and the optimiser: (model, ema, optimizer)."""
    assert isinstance(model, PolicyModelContract), f"{cfg.method}'s model does not satisfy the model contract"
    model = model.to(device)
    cuda = device.type == "cuda"
    if cuda:
        # cuDNN's own choice of algorithms, not timed ones (cudnn.benchmark): a prompt's length, and with it the
        # number of frames its encoder sees, changes from batch to batch, and each new shape would be timed anew.
        torch.backends.cuda.matmul.allow_tf32 = True  # what autocast leaves in fp32
        if cfg.channels_last:
            model = model.to(memory_format=torch.channels_last)
    ema = copy.deepcopy(model).requires_grad_(False).eval()
    # Fused: one operation for every tensor (on a GPU one launch instead of hundreds; on a CPU a shorter optimiser
    # step, measured in BENCHMARKS.md's git history). A run checkpointed unfused resumes unfused: the flag is in its
    # saved optimiser state.
    optimizer = torch.optim.AdamW(
        model.parameters(),
        lr=cfg.lr,
        betas=(0.95, 0.999),
        weight_decay=cfg.weight_decay,
        fused=device.type in ("cpu", "cuda") or None,
    )
    return model, ema, optimizer


def compiled(cfg: TrainConfig, net: torch.nn.Module) -> torch.nn.Module:
    """`net` (the model or its DDP wrapper) compiled as `cfg.compile` says, or itself when that is off. The model's
    weights stay `net`'s: checkpoints and the EMA are unaffected."""
    if cfg.compile == "off":
        return net
    keep_eager(net)
    if cfg.compile == "cudagraphs":
        return torch.compile(net, backend="cudagraphs")
    return torch.compile(net, mode=None if cfg.compile == "default" else cfg.compile)


def train_step(cfg: TrainConfig, net, model, ema, optimizer, batch, step: int, amp: bool, world: int = 1, rank=0):
    """One optimisation step on a batch already on the device: (loss, gradient norm), both tensors (reading them
    waits for the device). `net` is `model`, its DDP wrapper, or either compiled (:func:`compiled`)."""
    for group in optimizer.param_groups:
        group["lr"] = lr_at(step, cfg)
    # Every random draw of a step (diffusion noise and time steps, dropout) depends only on
    # (seed, step, rank): a resumed run continues exactly as an uninterrupted one.
    step_seed = (cfg.seed * 1_000_003 + step) * max(world, 1) + rank
    torch.manual_seed(step_seed)
    device = next(model.parameters()).device
    generator = torch.Generator(device).manual_seed(step_seed)
    noise = model.draw_noise(batch, generator)  # outside the loss, which is then one graph when compiled
    with torch.autocast(device.type, dtype=torch.bfloat16, enabled=amp):
        loss = net(batch, noise=noise)
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    grad_norm = torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.grad_clip)
    optimizer.step()
    _ema_update(ema, model, min(cfg.ema_decay, (1 + step) / (10 + step)))
    return loss, grad_norm


def run_differences(run: Path, cfg: TrainConfig, model_cfg) -> list[str]:
    """How the settings `run` was started with differ from `cfg` and `model_cfg`: one "path: old in the run, new now"
    line per field (where the run lives, and whether a call resumes it, are not settings)."""
    recorded = read_json(run / "config.json", "run configuration")
    if not isinstance(recorded, dict):
        raise UserError(f"{run / 'config.json'}: expected a JSON object (the run's configuration)")
    now = {"method": cfg.method, "train_config": to_dict(cfg), "model_config": to_dict(model_cfg)}
    # A field added to bpp after the run started is absent from its record: read the record as bpp reads a saved
    # config (absent fields at their defaults), so that only values that differ are named.
    for key, cls in (("train_config", TrainConfig), ("model_config", type(model_cfg))):
        if isinstance(recorded.get(key), dict):
            with contextlib.suppress(TypeError, ValueError, AttributeError):  # unreadable (UserError too): compared raw
                recorded[key] = to_dict(from_dict(cls, recorded[key]))
    differences = []
    absent = object()  # a key the run's record lacks

    def compare(path: str, old, new) -> None:
        if isinstance(old, dict) and isinstance(new, dict):
            for key in sorted(set(old) | set(new)):
                compare(f"{path}.{key}" if path else key, old.get(key, absent), new.get(key, absent))
        elif path in ("train_config.out", "train_config.resume", "train_config.threads"):
            return  # where the run is now (it may have been moved), whether this call resumes, and the cores it has
        elif path == "model_config.diffusion.noise_scale":
            return  # how the decoder samples at inference, not what is trained
        elif path == "train_config.data" and old and new and old is not absent:
            if Path(old).resolve() != Path(new).resolve():
                differences.append(f"{path}: {old!r} in the run, {new!r} now")
        elif old != new:
            said = lambda value: "absent" if value is absent else repr(value)  # noqa: E731
            differences.append(f"{path}: {said(old)} in the run, {said(new)} now")

    compare("", {k: recorded.get(k, absent) for k in now}, now)
    return differences


def check_resume(run: Path, cfg: TrainConfig, model_cfg) -> None:
    """Refuse to resume `run` with settings other than those it was started with (a resumed run must continue
    exactly as it would have): a UserError naming each differing field with both values."""
    differences = run_differences(run, cfg, model_cfg)
    if differences:
        raise UserError(
            f"{run} was started with other settings, and --resume continues a run exactly as it began; drop the "
            "differing flags or train into another --out: " + "; ".join(differences)
        )


def _recorded_model_config(run: Path) -> dict | None:
    """The model config (JSON) that `run` recorded when it began, if it is readable (:func:`check_resume` reports
    a record that is not)."""
    try:
        recorded = read_json(run / "config.json", "run configuration")
    except (UserError, OSError):
        return None
    config = recorded.get("model_config") if isinstance(recorded, dict) else None
    return config if isinstance(config, dict) else None


def train(cfg: TrainConfig, model_cfg, progress: bool = True) -> Path:
    """Train `cfg.method` with `model_cfg` on `cfg.data`; returns the final checkpoint folder."""
    rank, world, device = _setup_distributed(cfg.device)
    workers, threads = cpu_plan(cfg, device)
    if threads:
        torch.set_num_threads(threads)
    main = rank == 0
    run = Path(cfg.out)
    has_ckpt = (run / "checkpoints" / "last").is_file()
    if has_ckpt and not cfg.resume:
        raise FileExistsError(f"{run} already holds a run; pass --resume to continue it, or choose another --out")
    if cfg.resume and not has_ckpt:
        raise FileNotFoundError(f"{run}: nothing to resume (no checkpoints/last)")
    # Files of the user's that the model reads (Language's pretrained text encoder): checked, and their digests
    # recorded in the config, before any data is read; a resumed run checks the digests it recorded.
    model_cfg = model_cfg.pinned(_recorded_model_config(run) if cfg.resume else None)
    if cfg.resume:
        check_resume(run, cfg, model_cfg)

    store = open_store(cfg.data)
    benchmark = get_benchmark(store.benchmark)
    trainable_tasks(store)  # refused now, not after the model is built (or loaded, or compiled)
    obs = getattr(model_cfg, "obs", None)  # a method of another shape: its data loader checks what it reads
    if obs is not None:
        stored_keys(store, [*obs.proprio_keys, *obs.lowdim_keys, model_cfg.action_key])
    finite_statistics(store)
    method = get_method(cfg.method)
    torch.manual_seed(cfg.seed)
    model, ema, optimizer = build_training(cfg, method.model_cls(model_cfg, store.stats), device)
    cuda = device.type == "cuda"
    start = load_training_state(run, model, ema, optimizer) if cfg.resume else 0
    meta = {
        "method": cfg.method,
        "model_config": to_dict(model_cfg),
        "train_config": to_dict(cfg),
        "stats": store.stats,
        "dataset": {"path": str(cfg.data), "benchmark": store.benchmark, "tasks": store.num_tasks},
        "world_size": world,
    }
    spec = model.data_spec()
    if main:
        print(f"[train] {cfg.method}: {count_parameters(model) / 1e6:.2f}M parameters; {store}")
        print(
            f"[train] run dir {run}; steps {start} -> {cfg.steps}; world size {world}; device {device}; "
            f"{threads or torch.get_num_threads()} torch threads, {workers} loader workers"
        )
        lengths = store.episode_ends - store.episode_starts
        if spec.context == "demo" and lengths.max() > spec.max_prompt_steps:
            print(
                f"[train] warning: {(lengths > spec.max_prompt_steps).sum()} of the store's {len(lengths)} "
                f"demonstrations are longer than this model's prompts ({spec.max_prompt_steps} steps; the longest has "
                f"{lengths.max()}): training cuts them, and evaluation refuses them as prompts. Raise the model's "
                f"limit (BPP: --model.prompt.max-steps)."
            )
    net = compiled(cfg, torch.nn.parallel.DistributedDataParallel(model) if world > 1 else model)
    padding = cfg.padding(spec)
    if main and cfg.compile != "off":
        print(
            f"[train] compiling the loss and its backward (torch.compile, mode {cfg.compile}): the first step, and "
            f"each new batch shape, take a while; prompts padded to a multiple of {padding} steps"
        )

    renderer = None  # with frames_on device: the benchmark's renderer of the store's frames on the device
    if cfg.frames_on == "device" and (spec.image_keys or spec.context == "goal_image"):
        renderer = device_frames(benchmark, store, device)
        if main:
            print(f"[train] camera frames rendered on {device} from references the loader sends (--frames-on device)")
    dataset = PromptBatchDataset(
        store,
        spec,
        batch_size=cfg.batch_size,
        num_batches=cfg.steps,
        seed=cfg.seed,
        rank=rank,
        tasks_per_batch=cfg.tasks_per_batch,
        frames=benchmark.frames,
        frame_cache_bytes=cfg.frame_cache_share(workers),
        pad_to_multiple=padding,
        frame_refs=renderer is not None,
    )
    loader = batch_loader(dataset, range(start, cfg.steps), workers, pin_memory=cuda)
    writer = None
    if main:  # only now, once the store has given what the model needs: a refused run leaves no folder behind
        run.mkdir(parents=True, exist_ok=True)
        if not cfg.resume:  # a resumed run keeps the record of how it began (check_resume made sure it matches)
            write_json_atomic(run / "config.json", {k: v for k, v in meta.items() if k != "stats"})

        writer = SummaryWriter(str(run / "tb"), purge_step=start)
    amp = uses_amp(cfg, device)
    bar = tqdm(total=cfg.steps, initial=start, desc=f"train {cfg.method}", disable=not (main and progress))
    t_last, n_last = time.perf_counter(), start
    loss_sum, loss_n = torch.zeros((), device=device), 0  # summed on the device: no wait for the GPU per step
    step = start
    model.train()
    batches = iter(loader)
    try:  # an error or an interrupt still closes the progress bar and the log (it keeps what it logged)
        for step, batch in zip(range(start, cfg.steps), batches, strict=False):
            lr = lr_at(step, cfg)
            if renderer is not None:
                batch = render_batch(batch, spec, renderer)
            loss, grad_norm = train_step(
                cfg, net, model, ema, optimizer, to_torch(batch, device), step, amp, world, rank
            )
            loss_sum += loss.detach().float()
            loss_n += 1
            bar.update(1)
            if main and ((step + 1) % cfg.log_every == 0 or step + 1 == cfg.steps):
                now = time.perf_counter()
                rate = (step + 1 - n_last) * cfg.batch_size * world / max(now - t_last, 1e-9)
                t_last, n_last = now, step + 1
                mean_loss = loss_sum.item() / loss_n
                loss_sum, loss_n = torch.zeros((), device=device), 0
                bar.set_postfix(loss=f"{mean_loss:.4f}", lr=f"{lr:.2e}", samples_s=f"{rate:.0f}")
                writer.add_scalar("train/loss", mean_loss, step + 1)
                writer.add_scalar("train/lr", lr, step + 1)
                writer.add_scalar("train/grad_norm", float(grad_norm), step + 1)
                writer.add_scalar("train/samples_per_s", rate, step + 1)
            if (step + 1) % cfg.save_every == 0 or step + 1 == cfg.steps:
                if main:
                    save_checkpoint(run, step + 1, model, ema, optimizer, meta, keep=cfg.keep_checkpoints)
                if world > 1:
                    dist.barrier()
    finally:
        bar.close()
        if writer is not None:
            writer.close()
        del batches  # the loader's processes stop now, not at exit: an interrupted run reports once they are gone
    if world > 1:
        dist.barrier()
        dist.destroy_process_group()
    return resolve_checkpoint(run)
