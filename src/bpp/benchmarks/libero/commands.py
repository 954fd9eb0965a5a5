"""LIBERO-Gen's own commands: ``bpp libero tasks|video|export|import`` (``bpp libero generate`` is generic)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import tyro

from bpp.benchmarks.libero.benchmark import BENCHMARK
from bpp.benchmarks.libero.export import export_store
from bpp.benchmarks.libero.importer import import_files
from bpp.benchmarks.libero.suites import SUITES_BY_NAME, parse_where, view
from bpp.benchmarks.libero.tasks import write_suite
from bpp.data.store import EpisodeStore
from bpp.errors import UserError
from bpp.media import save_animation
from bpp.utils import check_fields


@dataclass(frozen=True)
class LiberoTasks:
    """Print a LIBERO-Gen suite's split and, with --out, write its tasks as BDDL problems + tasks.json.

    Each held-out task is listed with the counts the paper's appendix lists (Combination: training tasks sharing its
    pick, its place; Chain: training chains sharing its first step and second-step object)."""

    suite: str = "combination"
    """combination or chain (LIBERO-Gen), chain_no_second_step (the ablation's view), chain_candidates (every chain
    the candidate rule generates, 218 + the 10 held out), or libero_spatial / libero_goal (LIBERO's own 10 tasks)."""
    where: str | None = None
    """Only the tasks in this view, e.g. ``pick=TD``, ``place!=ST;bowl=1``, ``view!=second_step`` (fields of each
    task's entry in tasks.json; the report then counts similar tasks within the view; default: every task, and an
    empty view is refused)."""
    out: Path | None = None
    """Folder to write (default: only print the report)."""
    overwrite: bool = False
    init_states: int = 0
    """With --out, also write this many initial states per task (LIBERO's placement sampler, seeds 0, 1, ...) as
    ``problems/<id>.init.npz``, for LIBERO's own evaluation tools (seconds per task on a CPU; LIBERO uses 50)."""

    def __post_init__(self):
        check_fields(
            self,
            ("suite", self.suite in SUITES_BY_NAME, f"one of {', '.join(SUITES_BY_NAME)}"),
            ("init_states", 0 <= self.init_states <= 1000, "in [0, 1000]"),
            ("init_states", not self.init_states or self.out is not None, "0 unless --out is given"),
        )
        if self.where is not None:
            parse_where(self.where)


def libero_tasks(args: LiberoTasks) -> None:
    suite = view(SUITES_BY_NAME[args.suite](), args.where)
    print(suite.report())
    if args.out is not None:
        print(f"wrote {write_suite(suite, args.out, args.overwrite, args.init_states)}")


@dataclass(frozen=True)
class LiberoVideo:
    """Animate one stored demonstration as a GIF (or MP4 if --out ends in .mp4).

    The frames are rendered from the episode's stored simulator states."""

    store: tyro.conf.Positional[Path]
    episode: int = 0
    out: Path = Path("demo.gif")
    size: int = 128
    camera: str = "agentview"
    """agentview or eye_in_hand."""

    def __post_init__(self):
        check_fields(
            self,
            ("episode", self.episode >= 0, ">= 0"),
            ("out", self.out.suffix.lower() in (".gif", ".mp4"), "a .gif or .mp4 file"),
            ("size", 16 <= self.size <= 512, "in [16, 512] px"),
        )


def libero_video(args: LiberoVideo) -> None:
    store = _libero_store(args.store)
    store.episode_slice(args.episode)  # an IndexError naming the store's episode count if out of range
    frames = BENCHMARK.frames(store, args.episode, args.camera, args.size)
    print(f"wrote {save_animation(list(frames), args.out)} ({len(frames)} frames)")


@dataclass(frozen=True)
class LiberoExport:
    """Export a store in the layout of LIBERO's released dataset files (robomimic-style HDF5 + BDDL, one pair per task),
    which LIBERO's and robomimic's loaders and LIBERO-to-LeRobot converters read unchanged.

    Each file holds the actions, simulator states, robot states, LIBERO's observation keys, any stored camera frames,
    and each demonstration's scene model, in which its actions replay its states bit for bit."""

    store: tyro.conf.Positional[Path]
    out: Path = Path("exports/libero")
    """Folder to write into."""
    overwrite: bool = False
    """Write into a folder that is not empty."""


def libero_export(args: LiberoExport) -> None:
    store = _libero_store(args.store)
    paths = export_store(store, args.out, args.overwrite)
    print(f"wrote {len(paths)} HDF5 files ({store.num_episodes} demonstrations) into {args.out}")


@dataclass(frozen=True)
class LiberoImport:
    """Import LIBERO dataset files (robomimic-style HDF5, e.g. LIBERO's own demonstrations of its four suites, or
    files `bpp libero export` wrote) into a store: one task per file.

    Each demonstration is replayed in the scene of its file's model (seconds each on a CPU), so its observations are
    what a rollout observes; LIBERO's own problems are evaluated from LIBERO's initial states."""

    files: tyro.conf.Positional[tuple[Path, ...]]
    out: Path = Path("data/libero/imported.zarr")
    overwrite: bool = False
    goal_size: int = 128
    """Size of the final agent-view frame kept per demonstration (the Goal-Image baseline's goal; 0: none)."""

    def __post_init__(self):
        check_fields(
            self,
            ("files", len(self.files) > 0, "at least one file"),
            ("goal_size", self.goal_size == 0 or 8 <= self.goal_size <= 512, "0 or in [8, 512] px"),
        )


def libero_import(args: LiberoImport) -> None:
    store = import_files(args.files, args.out, overwrite=args.overwrite, goal_size=args.goal_size)
    print(f"wrote {store}")


def _libero_store(path: Path):
    store = EpisodeStore(path)
    if store.benchmark != BENCHMARK.name:
        raise UserError(f"{store.path} is a {store.benchmark} store, not {BENCHMARK.name}")
    return store


COMMANDS = {
    "tasks": (LiberoTasks, libero_tasks),
    "video": (LiberoVideo, libero_video),
    "export": (LiberoExport, libero_export),
    "import": (LiberoImport, libero_import),
}
"""``bpp libero <name>``."""
