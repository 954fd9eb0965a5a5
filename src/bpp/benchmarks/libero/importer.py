"""Import LIBERO's own dataset files (robomimic-style HDF5, one per task) into a LIBERO-Gen store.

    bpp libero import ~/LIBERO/datasets/libero_object/*_demo.hdf5 --out data/libero/libero-object.zarr

This is how LIBERO's human demonstrations (its four suites: Spatial, Object, Goal and LIBERO-10, which the scripted
demonstrator does not cover) become prompts and training data, and how a store exported by ``bpp libero export``
comes back. Each file becomes one task: its problem is the file's ``bddl_file_content`` (or the LIBERO problem its
``bddl_file_name`` names), its instruction the ``problem_info`` language instruction. Each ``demo_<i>`` keeps its
actions and flattened simulator states.

The policy's observations (``proprio``, ``object_state``) are made again, whatever keys the file's ``obs`` group
has, the way a rollout receives them: in the demonstration's scene (its ``model_file``), started from its first state
as a replay starts (:func:`~bpp.benchmarks.libero.sim.seat`), each action is executed and the observation the env
returns kept. robosuite samples its observations inside the control step, so they lag the state at the end of the
step, and computing them from the stored states instead differed from a rollout's by up to 2.3e-2 in the joints'
velocities and 2.7e-3 in their angles. A step whose start is not the file's state (a file recorded in a scene or
with a simulator that does not reproduce its states, such as LIBERO's own files) starts from the file's state instead,
so the observations never drift from the demonstration.

The scene's fixtures (table, cabinet, stove) are kept per demonstration as the model placed them, so a replay from
the store rebuilds it. A file without ``model_file`` is rebuilt from the placement seed ``bpp_seed`` (0 if it has
none), which places the fixtures elsewhere than where the demonstration had them.
"""

from __future__ import annotations

import json
import re
import tempfile
import xml.etree.ElementTree as ET
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import NamedTuple

import numpy as np
from tqdm import tqdm

from bpp.benchmarks.libero.bddl import parse, section
from bpp.benchmarks.libero.dataset import ABSOLUTE_KEY, BENCHMARK, FIXTURE_KEY, GOAL_KEY, PROPRIO_LAYOUT
from bpp.benchmarks.libero.rollouts import observe
from bpp.benchmarks.libero.sim import (
    CAMERAS,
    absolute_actions,
    fixture_row,
    has_initial_states,
    libero_problem,
    make_env,
    problems_folder,
    render_now,
    reset_scene,
    seat,
)
from bpp.data.integrity import StoreError
from bpp.data.store import EpisodeStore, EpisodeWriter
from bpp.errors import UserError, require_extra


class Demo(NamedTuple):
    """One demonstration of a LIBERO dataset file, checked."""

    name: str
    seed: int
    """The placement seed of its reset (``bpp_seed``; 0 if the file has none)."""
    actions: np.ndarray
    """(T, 7) float64, as executed: they reproduce the states."""
    labels: np.ndarray
    """(T, 7) float64, the actions to learn: ``bpp_actions`` where the executed ones had noise added, else these."""
    states: np.ndarray
    """(T, S) float64, the flattened simulator state before each action."""
    model: str | None
    """Its scene's MJCF (``model_file``), if the file keeps it."""


def libero_problem_name(bddl_file_name: str) -> tuple[str, str] | None:
    """(suite folder, problem stem) if `bddl_file_name` (a path as LIBERO's files store it) is one of LIBERO's own
    problems, else None."""
    path = Path(str(bddl_file_name))
    if len(path.parts) < 2 or path.suffix != ".bddl":
        return None
    suite, stem = path.parts[-2], path.stem
    return (suite, stem) if (problems_folder() / suite / f"{stem}.bddl").is_file() else None


def read_task(f, path: Path) -> tuple[str, str, str, dict]:
    """(task id, problem text, instruction, task info) of an open LIBERO dataset file: the id and information an
    export of bpp keeps (``bpp_task``), else the file's name without ``_demo``."""
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
        instruction = " ".join(map(str, section(parse(problem), ":language")[1:]))
    if isinstance(instruction, list):  # LIBERO's collection scripts have stored it as its words
        instruction = " ".join(map(str, instruction))
    task_id, info = path.stem.removesuffix("_demo"), {}
    if "bpp_task" in attrs:
        try:
            task = json.loads(attrs["bpp_task"])
            task_id, info = str(task["id"]), dict(task["info"])
        except (KeyError, ValueError, TypeError) as err:
            raise UserError(f"{path}: data.attrs['bpp_task'] is not a task's id and information ({err})") from None
    info.update(problem=problem, source=str(path))
    if named is not None:
        info["suite"] = named[0]
        if has_initial_states(*named):  # rollouts start from LIBERO's own initial states of the task
            info["initial_states"] = "{}/{}.pruned_init".format(*named)
    return task_id, problem, str(instruction).strip(), info


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


def read_demos(f, path: Path) -> Iterator[Demo]:
    """Each demonstration of an open LIBERO dataset file, in order; a UserError naming the file and the
    demonstration if one lacks its actions or states, has them in other shapes, or holds a number that is not
    finite (float32's range for actions)."""
    for name in _demo_names(f, path):
        where = f"{path}:{name}"
        demo = f["data"][name]
        missing = [key for key in ("actions", "states") if not hasattr(demo, "keys") or key not in demo]
        if missing:
            raise UserError(f"{where}: no {' and no '.join(missing)} (expected datasets data/{name}/actions, states)")
        try:
            actions = np.asarray(demo["actions"], dtype=np.float64)
            labels = np.asarray(demo["bpp_actions"], dtype=np.float64) if "bpp_actions" in demo else actions
            states = np.asarray(demo["states"], dtype=np.float64)
            seed = int(demo.attrs.get("bpp_seed", demo.attrs.get("seed", 0)))  # "seed": older exports of bpp
        except (TypeError, ValueError, OverflowError) as err:
            raise UserError(f"{where}: expected numeric actions, states and seed ({err})") from None
        if (
            actions.ndim != 2
            or actions.shape[1] != 7
            or labels.shape != actions.shape
            or states.ndim != 2
            or len(actions) != len(states)
            or not len(states)
        ):
            raise UserError(
                f"{where}: expected (T, 7) actions and (T, S) states, T > 0, got {actions.shape} and {states.shape}"
                + (f" (and bpp_actions {labels.shape})" if labels.shape != actions.shape else "")
            )
        if not 0 <= seed < 2**32:
            raise UserError(f"{where}: seed {seed} is not in [0, 2**32)")
        float32 = np.finfo(np.float32).max
        for key, values, limit in (
            ("actions", actions, float32),
            ("bpp_actions", labels, float32),
            ("states", states, np.inf),
        ):
            bad = np.argwhere(~(np.abs(values) <= limit))
            if len(bad):
                step, column = bad[0]
                raise UserError(
                    f"{where}: {key}[{step}, {column}] = {values[step, column]} is not a finite "
                    f"{'number' if key == 'states' else 'float32'}"
                )
        model = demo.attrs.get("model_file")
        model = model.decode() if isinstance(model, bytes) else None if model is None else str(model)
        yield Demo(name, seed, actions, labels, states, model)


def import_files(
    paths: Sequence[Path], out: Path, *, overwrite: bool = False, goal_size: int = 128, progress: bool = True
) -> EpisodeStore:
    """One task per file of `paths`; every demonstration's observations made again as a rollout receives them; the
    agent-view frame after its last action rendered at `goal_size` (0: none) as the Goal-Image baseline's goal."""
    h5py = require_extra("h5py", "libero")

    if not paths:
        raise UserError("no files to import")
    missing = [str(p) for p in paths if not Path(p).is_file()]
    if missing:
        raise UserError(f"no such file: {', '.join(missing)}")
    noisy = False  # whether any demonstration has actions to learn apart from the executed ones (bpp_actions)
    for path in map(Path, paths):  # every file is checked before anything is written
        with open_dataset_file(h5py, path) as f:
            read_task(f, path)
            noisy |= any(demo.labels is not demo.actions for demo in read_demos(f, path))
    with EpisodeWriter(
        out,
        benchmark=BENCHMARK,
        config={"imported": [str(p) for p in paths], "goal_size": goal_size},
        overwrite=overwrite,
        stats_keys=("action", ABSOLUTE_KEY, "proprio", "object_state"),
    ) as writer:
        bar = tqdm(paths, desc=f"importing into {Path(out).name}", unit="file", disable=not progress)
        for path in bar:
            path = Path(path)
            with open_dataset_file(h5py, path) as f, tempfile.TemporaryDirectory(prefix="libero-import-") as folder:
                task_id, problem, instruction, info = read_task(f, path)
                problem_path = Path(folder) / "task.bddl"
                problem_path.write_text(problem)
                env = make_env(problem_path, render=bool(goal_size))
                try:
                    info["fixtures"] = sorted(env.env.fixtures_dict)  # the rows of each episode's fixture_pose
                    task_index = writer.add_task(task_id, info, instruction=instruction)
                    for demo in read_demos(f, path):
                        where = f"{path}:{demo.name}"
                        rebuild_scene(env, demo, where)
                        poses = fixture_row(env)[1]
                        proprio, object_state = observe_demo(env, demo.states, demo.actions, where)
                        columns = {"seed": demo.seed, FIXTURE_KEY: poses}
                        if goal_size:  # after the last action, as generation renders it
                            columns[GOAL_KEY] = render_now(env, CAMERAS["agentview"], goal_size)
                        steps = {
                            "action": demo.labels,
                            ABSOLUTE_KEY: absolute_actions(demo.labels, proprio[:, PROPRIO_LAYOUT["eef_pos"]]),
                            "proprio": proprio,
                            "object_state": object_state,
                            "sim_state": demo.states,
                        }
                        if noisy:
                            steps["executed_action"] = demo.actions
                        writer.add_episode(steps, task_index, **columns)
                finally:
                    env.close()
    return EpisodeStore(out)


def rebuild_scene(env, demo: Demo, where: str) -> None:
    """Make `env` (made from the demonstration's problem) hold the demonstration's scene: its ``model_file``, with
    the asset files it names found in this installation, else the reset with its seed. The env is reset first, as
    LIBERO's own replay does: loading a model keeps the robot's gripper as the last episode left it (robosuite's
    gripper integrates its commands), and the first demonstration's grip then changed the next one's steps."""
    reset_scene(env, demo.seed)
    if demo.model is None:
        return
    try:
        env.env.reset_from_xml_string(local_assets(demo.model))
    except (ValueError, SyntaxError) as err:  # MuJoCo's errors in a model, and XML that does not parse
        raise UserError(f"{where}: LIBERO cannot build the scene of its model_file ({err})") from None


def local_assets(xml: str) -> str:
    """A scene's MJCF `xml` with each asset file that is not where it names found in this installation, as LIBERO's
    own replay does for robosuite's files (``postprocess_model_xml``), and for LIBERO's (files recorded elsewhere
    name the recording machine's folders): a path through a ``robosuite`` folder in robosuite's package, else one
    through an ``assets`` folder in LIBERO's assets. Files found neither way are left for MuJoCo to name."""

    # robosuite: the libero extra
    import robosuite
    from libero.libero import get_libero_path

    folders = {"robosuite": Path(robosuite.__file__).parent, "assets": Path(get_libero_path("assets"))}
    root = ET.fromstring(xml)
    for element in root.iter():
        file = element.get("file")
        if file is None or Path(file).is_file():
            continue
        parts = Path(file).parts
        for anchor, folder in folders.items():
            if anchor in parts:
                local = folder.joinpath(*parts[len(parts) - parts[::-1].index(anchor) :])
                if local.is_file():
                    element.set("file", str(local))
                break
    return ET.tostring(root, encoding="unicode")


def observe_demo(env, states: np.ndarray, actions: np.ndarray, where: str) -> tuple[np.ndarray, np.ndarray]:
    """(proprio, object_state), float32, as a rollout receives them (:func:`~bpp.benchmarks.libero.rollouts.observe`)
    along a demonstration in `env`, which holds its scene: the first from its first state, seated as a replay starts;
    each next one returned by the step that executes the action before it, from the stored state before that action.
    The env is left after the last action."""
    size = len(env.env.sim.get_state().flatten())
    if states.shape[1] != size:
        raise StoreError(
            f"{where}: states have {states.shape[1]} values, this task's LIBERO scene has {size}: the file was not "
            "recorded in this problem's scene"
        )
    observed = [observe(env, seat(env, states[0]), (), 0)]
    for t, (state, action) in enumerate(zip(states, actions, strict=True)):
        sim = env.env.sim
        if not np.array_equal(sim.get_state().flatten(), state):  # the replay does not reproduce the file's state
            sim.set_state_from_flattened(state)
            sim.forward()
        raw, *_ = env.step(action)
        if t + 1 < len(states):
            observed.append(observe(env, raw, (), 0))
    return np.stack([o["proprio"] for o in observed]), np.stack([o["object_state"] for o in observed])
