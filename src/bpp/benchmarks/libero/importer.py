"""Import LIBERO's own dataset files (robomimic-style HDF5, one per task) into a LIBERO-Gen store.

    bpp libero import ~/LIBERO/datasets/libero_object/*_demo.hdf5 --out data/libero/libero-object.zarr

This is how LIBERO's human demonstrations (its four suites: Spatial, Object, Goal and LIBERO-10, which the scripted
demonstrator does not cover) become prompts and training data, and how a store exported by ``bpp libero export``
comes back. Each file becomes one task: its problem is the file's ``bddl_file_content`` (or the LIBERO problem its
``bddl_file_name`` names), its instruction the ``problem_info`` language instruction. Each ``demo_<i>`` keeps its
actions and flattened simulator states; the policy's observations (``proprio``, ``object_state``) are recomputed
from each stored state in a LIBERO env, so they are exactly what a rollout observes, whatever keys the file's
``obs`` group has. A task that is one of LIBERO's own problems is evaluated from LIBERO's initial states of it, as
the generated ``libero-spatial`` task set is.

Files from LIBERO itself hold no placement seed, so their demonstrations are stored with seed 0: frames rendered
from their states show the fixtures where that seed puts them (LIBERO's own files keep each demonstration's scene
model, which this import does not read).
"""

from __future__ import annotations

import json
import re
import tempfile
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from tqdm import tqdm

from bpp.benchmarks.libero.dataset import BENCHMARK, GOAL_KEY
from bpp.data.store import EpisodeStore, EpisodeWriter, StoreError
from bpp.errors import UserError


def libero_problem_name(bddl_file_name: str) -> tuple[str, str] | None:
    """(suite folder, problem stem) if `bddl_file_name` (a path as LIBERO's files store it) is one of LIBERO's own
    problems, else None."""
    from bpp.benchmarks.libero.sim import problems_folder

    path = Path(str(bddl_file_name))
    if len(path.parts) < 2 or path.suffix != ".bddl":
        return None
    suite, stem = path.parts[-2], path.stem
    return (suite, stem) if (problems_folder() / suite / f"{stem}.bddl").is_file() else None


def read_task(f, path: Path) -> tuple[str, str, dict]:
    """(problem text, instruction, task info) of an open LIBERO dataset file."""
    from bpp.benchmarks.libero.sim import has_initial_states, libero_problem

    if "data" not in f or not hasattr(f["data"], "keys"):
        raise UserError(f"{path}: not a LIBERO dataset file (no 'data' group)")
    attrs = f["data"].attrs
    named = libero_problem_name(attrs.get("bddl_file_name", ""))
    problem = attrs.get("bddl_file_content")
    if problem is None and named is not None:
        problem = libero_problem(*named)
    if problem is None:
        raise UserError(
            f"{path}: no BDDL problem (data.attrs has neither bddl_file_content nor a LIBERO bddl_file_name)"
        )
    problem = problem.decode() if isinstance(problem, bytes) else str(problem)
    try:
        instruction = json.loads(attrs["problem_info"])["language_instruction"]
    except (KeyError, ValueError, TypeError):
        from bpp.benchmarks.libero.bddl import parse, section

        instruction = " ".join(map(str, section(parse(problem), ":language")[1:]))
    info = {"problem": problem, "source": str(path)}
    if named is not None:
        info["suite"] = named[0]
        if has_initial_states(*named):  # rollouts start from LIBERO's own initial states of the task
            info["initial_states"] = "{}/{}.pruned_init".format(*named)
    return problem, str(instruction).strip(), info


def open_dataset_file(h5py, path: Path):
    """`path` opened read-only with `h5py`, or a UserError naming it: not an HDF5 file at all, or one h5py cannot
    read (truncated, damaged)."""
    try:
        return h5py.File(path, "r")
    except OSError as err:
        try:
            hdf5 = h5py.is_hdf5(path)
        except OSError:
            hdf5 = True  # unreadable: say what h5py said
        if not hdf5:
            raise UserError(f"{path}: not an HDF5 file (LIBERO dataset files are HDF5, e.g. *_demo.hdf5)") from None
        raise UserError(f"{path}: cannot read this HDF5 file ({err})") from None


def _demo_names(f, path: Path) -> list[str]:
    """The file's demonstrations, data/demo_<i>, by i."""
    names = [k for k in f["data"] if k.startswith("demo_")]
    odd = [k for k in names if not re.fullmatch(r"demo_\d+", k)]
    if odd:
        raise UserError(f"{path}: data/{odd[0]} is not a demonstration name (expected data/demo_<i>, i a number)")
    if not names:
        raise UserError(f"{path}: no demonstrations (no data/demo_<i> groups)")
    return sorted(names, key=lambda k: int(k.split("_")[1]))


def read_demos(f, path: Path):
    """(name, seed, actions (T, 7) float32, states (T, S) float64) of each demonstration of an open LIBERO dataset
    file, in order; a UserError naming the file and the demonstration if one lacks its actions or states, has them
    in other shapes, or holds a number that is not finite (float32's range for actions)."""
    for name in _demo_names(f, path):
        where = f"{path}:{name}"
        demo = f["data"][name]
        missing = [key for key in ("actions", "states") if not hasattr(demo, "keys") or key not in demo]
        if missing:
            raise UserError(f"{where}: no {' and no '.join(missing)} (expected datasets data/{name}/actions, states)")
        try:
            actions = np.asarray(demo["actions"], dtype=np.float64)
            states = np.asarray(demo["states"], dtype=np.float64)
            seed = int(demo.attrs.get("seed", 0))
        except (TypeError, ValueError, OverflowError) as err:
            raise UserError(f"{where}: expected numeric actions, states and seed ({err})") from None
        if (
            actions.ndim != 2
            or actions.shape[1] != 7
            or states.ndim != 2
            or len(actions) != len(states)
            or not len(states)
        ):
            raise UserError(
                f"{where}: expected (T, 7) actions and (T, S) states, T > 0, got {actions.shape} and {states.shape}"
            )
        if not 0 <= seed < 2**32:
            raise UserError(f"{where}: seed {seed} is not in [0, 2**32)")
        for key, values, limit in (("actions", actions, np.finfo(np.float32).max), ("states", states, np.inf)):
            bad = np.argwhere(~(np.abs(values) <= limit))
            if len(bad):
                step, column = bad[0]
                raise UserError(
                    f"{where}: {key}[{step}, {column}] = {values[step, column]} is not a finite "
                    f"{'float32' if key == 'actions' else 'number'}"
                )
        yield name, seed, actions.astype(np.float32), states


def import_files(
    paths: Sequence[Path], out: Path, *, overwrite: bool = False, goal_size: int = 128, progress: bool = True
) -> EpisodeStore:
    """One task per file of `paths`; every demonstration's observations recomputed from its states; the final
    agent-view frame rendered at `goal_size` (0: none) as the Goal-Image baseline's goal."""
    from bpp.errors import require_extra

    h5py = require_extra("h5py", "libero")

    from bpp.benchmarks.libero.sim import CAMERAS, make_env, render_now

    if not paths:
        raise UserError("no files to import")
    missing = [str(p) for p in paths if not Path(p).is_file()]
    if missing:
        raise UserError(f"no such file: {', '.join(missing)}")
    for path in map(Path, paths):  # every file is checked before anything is written
        with open_dataset_file(h5py, path) as f:
            read_task(f, path)
            for _ in read_demos(f, path):
                pass
    with EpisodeWriter(
        out,
        benchmark=BENCHMARK,
        config={"imported": [str(p) for p in paths], "goal_size": goal_size},
        overwrite=overwrite,
        stats_keys=("action", "proprio", "object_state"),
    ) as writer:
        bar = tqdm(paths, desc=f"importing into {Path(out).name}", unit="file", disable=not progress)
        for path in bar:
            path = Path(path)
            with open_dataset_file(h5py, path) as f, tempfile.TemporaryDirectory(prefix="libero-import-") as folder:
                problem, instruction, info = read_task(f, path)
                task_id = path.stem.removesuffix("_demo")
                task_index = writer.add_task(task_id, info, instruction=instruction)
                problem_path = Path(folder) / "task.bddl"
                problem_path.write_text(problem)
                env = make_env(problem_path, render=bool(goal_size))
                try:
                    for name, seed, actions, states in read_demos(f, path):
                        env.seed(seed)
                        env.reset()
                        proprio, object_state = observe_states(env, states, f"{path}:{name}")
                        columns = {"seed": seed}
                        if goal_size:
                            columns[GOAL_KEY] = render_now(env, CAMERAS["agentview"], goal_size)  # the last state
                        steps = {
                            "action": actions,
                            "proprio": proprio,
                            "object_state": object_state,
                            "sim_state": states,
                        }
                        writer.add_episode(steps, task_index, **columns)
                finally:
                    env.close()
    return EpisodeStore(out)


def observe_states(env, states: np.ndarray, where: str) -> tuple[np.ndarray, np.ndarray]:
    """(proprio, object_state), float32, as a rollout observes them (:func:`~bpp.benchmarks.libero.rollouts.observe`) in
    each flattened simulator state; the env is left in the last state."""
    from bpp.benchmarks.libero.rollouts import observe

    sim = env.env.sim
    size = len(sim.get_state().flatten())
    if states.shape[1] != size:
        raise StoreError(
            f"{where}: states have {states.shape[1]} values, this task's LIBERO scene has {size}: the file was not "
            "recorded in this problem's scene"
        )
    proprio, object_state = [], []
    for state in states:
        sim.set_state_from_flattened(state)
        sim.forward()
        obs = observe(env, env.env._get_observations(force_update=True), (), 0)
        proprio.append(obs["proprio"])
        object_state.append(obs["object_state"])
    return np.stack(proprio), np.stack(object_state)
