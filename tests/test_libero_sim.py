"""LIBERO-Gen against LIBERO itself (the `libero` extra, which `make test` installs): BDDL round trips on every
problem LIBERO ships, a generated Combination problem loads in the simulator with a goal its predicates check, and
bpp's reset and step of LIBERO's envs give what LIBERO's and robosuite's own give, bit for bit."""

from pathlib import Path

import numpy as np
import pytest

from bpp.benchmarks.libero.bddl import dumps, parse, section
from bpp.benchmarks.libero.rollouts import observe
from bpp.benchmarks.libero.sim import make_env, place_object, problems_folder, spatial_problem
from bpp.benchmarks.libero.suites import combination, combination_problem

pytestmark = pytest.mark.libero


def test_every_problem_libero_ships_survives_a_round_trip():
    files = sorted(problems_folder().rglob("*.bddl"))
    assert len(files) >= 130  # LIBERO's 130 tasks at least
    for path in files:
        problem = parse(path.read_text())
        assert parse(dumps(problem)) == problem, path


def test_every_combination_task_is_written_from_its_scene():
    for task in (*combination().train, *combination().test):
        problem = parse(combination_problem(task, spatial_problem(task.scene.base)))
        assert section(problem, ":goal")[1][1][1] == f"akita_black_bowl_{task.bowl}"


def n1_problem(folder) -> Path:
    """The BDDL file of Combination's scene-N1 task that puts bowl 1 into bowl 2 (on the plate), in `folder`."""
    task = next(t for t in combination().train if t.scene.name == "N1" and t.bowl == 1 and t.place == "bowl")
    path = folder / "task.bddl"
    path.write_text(combination_problem(task, spatial_problem(task.scene.base)))
    return path


def test_a_generated_problem_loads_and_its_goal_is_checked_by_libero(tmp_path):
    env = make_env(n1_problem(tmp_path))  # physics only
    try:
        env.seed(0)
        obs = env.reset()
        for _ in range(10):  # LIBERO's initial placements start objects in the air: let them settle
            obs, *_ = env.step(np.zeros(7))
        assert obs["akita_black_bowl_2_pos"][2] > obs["akita_black_bowl_1_pos"][2]  # bowl 2 starts on the plate
        assert not env.env._check_success()
        place_object(env, "akita_black_bowl_1", obs["akita_black_bowl_2_pos"] + np.array([0.0, 0.0, 0.04]))
        for _ in range(20):
            env.step(np.zeros(7))
        assert env.env._check_success()  # "in the black bowl on the plate", as LIBERO's predicates judge it
        env.env.timestep = 1000  # robosuite's default horizon: past it, it would refuse to step (Chain needs more)
        for _ in range(2):
            obs, *_ = env.step(np.zeros(7))
        # what the policy observes: the derived `eef` key is the gripper's pose and opening, as robosuite names them
        seen = observe(env, obs, (), 128)
        parts = ("robot0_eef_pos", "robot0_eef_quat", "robot0_gripper_qpos")
        np.testing.assert_allclose(seen["eef"], np.concatenate([obs[k] for k in parts]), rtol=1e-6)
    finally:
        env.close()


def test_an_env_that_renders_nothing_is_built_without_textures_and_steps_bit_for_bit_the_same(tmp_path):
    from bpp.benchmarks.libero.sim import render_now, reset_env

    path = n1_problem(tmp_path)
    drawn, bare = make_env(path, render=True), make_env(path)
    try:
        assert bare.env.sim.model._model.ntex == 0 < drawn.env.sim.model._model.ntex
        actions = np.random.default_rng(0).uniform(-1.0, 1.0, (40, 7))
        paths = []
        for env in (drawn, bare):
            reset_env(env, 3)
            paths.append(np.stack([env.step(a)[0]["robot0_eef_pos"] for a in actions]))
        np.testing.assert_array_equal(paths[0], paths[1])  # every step's gripper, then the final state entire
        np.testing.assert_array_equal(drawn.env.sim.get_state().flatten(), bare.env.sim.get_state().flatten())
        with pytest.raises(ValueError, match="renders nothing"):
            render_now(bare)
        bare.seed(0)
        bare.reset()  # LIBERO's own reset builds the model again: still without textures
        assert bare.env.sim.model._model.ntex == 0
    finally:
        drawn.close()
        bare.close()


def test_a_suite_is_written_as_problems_and_an_index(tmp_path, capsys):
    import json

    import pytest

    from bpp.cli import main

    out = tmp_path / "combination"
    main(["libero", "tasks", "--suite", "combination", "--out", str(out)])
    report = capsys.readouterr().out
    assert "164 training tasks, 10 held out" in report and "[7 tasks]" in report  # the top-drawer pick: 7 places
    index = json.loads((out / "tasks.json").read_text())
    assert len(index["train"]) == 164 and len(index["test"]) == 10
    assert len(list((out / "problems").glob("*.bddl"))) == 174
    assert index["test"][0]["similar"] == {"same_pick": 9, "same_place": 8}
    with pytest.raises(SystemExit, match="exists; pass --overwrite"):
        main(["libero", "tasks", "--out", str(out)])

    chain = tmp_path / "chain"  # BDDL has no order: each step's operator and goal, in order, stand in the index
    main(["libero", "tasks", "--suite", "chain", "--out", str(chain)])
    assert "311 training tasks, 10 held out" in capsys.readouterr().out
    index = json.loads((chain / "tasks.json").read_text())
    assert len(list((chain / "problems").glob("*.bddl"))) == 321
    assert [s["operator"] for s in index["test"][2]["steps"]] == ["push", "place"]
    assert {t["start"] for t in index["train"] if t["view"] == "second_step"} >= {"open the top drawer"}


def test_the_scripted_demonstrator_passes_libero_predicates_for_each_kind_of_place_and_the_drawer(tmp_path):
    from bpp.benchmarks.libero.demonstrator import demonstrate

    suite = combination()
    first = next(t for t in suite.train if t.scene.name == "S1" and t.bowl == 1 and t.place == "PL")
    kinds = [first]  # onto an object (the plate)
    kinds.append(next(t for t in suite.train if t.scene.name == "S1" and t.bowl == 1 and t.place == "TC"))  # region
    kinds.append(next(t for t in suite.train if t.scene.name == "S1" and t.bowl == 1 and t.place == "bowl"))
    kinds.append(next(t for t in suite.train if t.pick == "TD" and t.place == "bowl"))  # out of the open drawer
    # The bowl next to the cookie box is at the arm's reach: taken on its side rim, the lifted arm locked straight
    # and never came back (0 of 4 seeds to the table centre); on its near rim seeds 2 and 3 pass (0 and 1 still lock).
    kinds.append(next(t for t in suite.train if t.scene.name == "S4" and t.pick == "NB" and t.place == "TC"))
    for task in kinds:
        path = tmp_path / f"{task.name}.bddl"
        path.write_text(combination_problem(task, spatial_problem(task.scene.base)))
        env = make_env(path)
        try:
            demo = demonstrate(env, task, seed=2 if task.pick == "NB" else 0)
        finally:
            env.close()
        assert demo.success, task.instruction
        assert demo.actions.shape[1] == 7 and np.abs(demo.actions).max() <= 1.0
        assert len(demo.states) == len(demo.actions) == len(demo.observations["robot0_eef_pos"])


CHEESE, BOWL_1, WINE, CABINET_TOP = "cream_cheese_1", "akita_black_bowl_1", "wine_bottle_1", "wooden_cabinet_1_top_side"


@pytest.mark.parametrize(
    ("operator", "problem", "objects", "state"),
    [
        ("turn_on", "turn_on_the_stove", {}, None),
        ("push", "push_the_plate_to_the_front_of_the_stove", {}, None),
        ("open", "open_the_top_drawer_and_put_the_bowl_inside", {}, "wooden_cabinet_1_top_region"),
        ("open", "open_the_middle_drawer_of_the_cabinet", {"drawer": "middle"}, None),
        ("place", "put_the_cream_cheese_in_the_bowl", {"obj": CHEESE, "target": BOWL_1}, None),
        ("place", "put_the_bowl_on_the_stove", {"obj": BOWL_1, "target": "flat_stove_1_cook_region"}, None),
        ("place", "put_the_wine_bottle_on_top_of_the_cabinet", {"obj": WINE, "target": CABINET_TOP}, None),
    ],
)
def test_each_operator_passes_libero_predicate_on_a_libero_goal_task(operator, problem, objects, state):
    """LIBERO-Goal's own problems, judged by LIBERO: the problem's goal (the stove's knob turned on, the plate pushed
    in front of it), or, for the first of two steps, LIBERO's predicate on the object's state (the drawer open)."""
    from bpp.benchmarks.libero.demonstrator import demonstrate_operator

    env = make_env(problems_folder() / "libero_goal" / f"{problem}.bddl")
    try:
        demo = demonstrate_operator(env, operator, seed=0, **objects)
        if state is None:
            assert demo.success, problem
        else:
            assert env.env.object_states_dict[state].is_open() and not demo.success  # its second step is not done
    finally:
        env.close()
    assert demo.actions.shape[1] == 7 and np.abs(demo.actions).max() <= 1.0
    assert len(demo.states) == len(demo.actions)
    with pytest.raises(ValueError, match="no operator 'fly'; known: turn_on, push, open, close, place"):
        demonstrate_operator(None, "fly", seed=0)


def test_the_close_operator_shuts_both_drawers_by_libero_goal_check(tmp_path):
    """Closing, judged by LIBERO's ``Close`` (which holds only at the drawer's stop): a LIBERO-Goal problem whose
    ``:init`` opens the top drawer and whose goal is both drawers closed. The demonstrator closes the top drawer,
    then opens the middle one and closes it again, with the fingers leading (a hand pointing down met the top
    drawer's handle 6 mm short of the stop). LIBERO's scene cannot start with the middle drawer open: it opens
    around the bowl, which then keeps it from closing."""
    from bpp.benchmarks.libero.bddl import set_section
    from bpp.benchmarks.libero.chain import parse_step
    from bpp.benchmarks.libero.demonstrator import demonstrate_steps
    from bpp.benchmarks.libero.sim import GOAL_BASE, libero_problem

    top, middle = parse_step("close the top drawer"), parse_step("close the middle drawer of the cabinet")
    assert (top.operator, top.goal) == ("close", "(Close wooden_cabinet_1_top_region)")
    problem = parse(libero_problem("libero_goal", GOAL_BASE))
    set_section(problem, ":init", [*section(problem, ":init")[1:], ["Open", "wooden_cabinet_1_top_region"]])
    set_section(problem, ":goal", [["And", *(s.goal.strip("()").split() for s in (top, middle))]])
    path = tmp_path / "close.bddl"
    path.write_text(dumps(problem))
    env = make_env(path)
    try:
        steps = [("close", top.kwargs), ("open", middle.kwargs), ("close", middle.kwargs)]
        demo = demonstrate_steps(env, steps, seed=0)
    finally:
        env.close()
    assert demo.success and len(demo.actions) > 300


def test_libero_goal_own_two_step_task_the_bowl_into_the_opened_drawer():
    """LIBERO-Goal's "open the top drawer and put the bowl inside", both steps in one episode, judged by LIBERO's
    goal. The opened drawer overhangs the bowl: taken on the near rim and lifted straight up, the bowl met the
    drawer's floor (0 of 2 seeds before the demonstrator slid it out first and took it across the drawer's width)."""
    from bpp.benchmarks.libero.demonstrator import DemoConfig, demonstrate_steps

    steps = [("open", {}), ("place", {"obj": BOWL_1, "target": "wooden_cabinet_1_top_region"})]
    env = make_env(problems_folder() / "libero_goal" / "open_the_top_drawer_and_put_the_bowl_inside.bddl")
    try:
        demo = demonstrate_steps(env, steps, seed=0, cfg=DemoConfig(max_steps=1200))
    finally:
        env.close()
    assert demo.success


def test_chain_start_states_written_into_init_hold_in_libero_once_settled(tmp_path):
    """Second-step tasks start from a first step's end state written into the problem's ``:init``. Four such effects
    at once (the plate pushed, the drawer open, the stove on, the bowl on the cream cheese) hold by LIBERO's own
    predicates after the demonstrator's settling steps; a demonstration whose start state does not hold is refused."""
    from bpp.benchmarks.libero.chain import ChainTask, parse_step
    from bpp.benchmarks.libero.demonstrator import demonstrate_steps
    from bpp.benchmarks.libero.sim import GOAL_BASE, holds, libero_problem

    starts = [
        "push the plate to the front of the stove",
        "open the top drawer",
        "turn on the stove",
        "put the bowl on the cream cheese",
    ]
    text = libero_problem("libero_goal", GOAL_BASE)
    for start in starts:
        text = ChainTask(start, "first_step", start).problem(text)
    path = tmp_path / "starts.bddl"
    path.write_text(text)
    env = make_env(path)
    try:
        demo = demonstrate_steps(env, [("turn_on", {})], seed=0, requires="(On wine_bottle_1 plate_1)")
        assert [holds(env, parse_step(s).goal) for s in starts] == [True] * 4
        assert not holds(env, "(On wine_bottle_1 plate_1)")
    finally:
        env.close()
    assert not demo.success and len(demo.actions) == 0  # refused before any step


def test_stored_states_render_the_same_frames_every_time(tmp_path):
    from bpp.benchmarks.libero.sim import render_states

    task = combination().train[0]
    path = tmp_path / "task.bddl"
    path.write_text(combination_problem(task, spatial_problem(task.scene.base)))
    env = make_env(path, cameras=("agentview",), image_size=64)
    try:
        env.seed(0)
        obs = env.reset()
        states = [env.env.sim.get_state().flatten()]
        for _ in range(3):
            env.step(np.r_[0.4, 0.0, -0.3, 0.0, 0.0, 0.0, -1.0])
            states.append(env.env.sim.get_state().flatten())
        first, again = render_states(env, states, size=64), render_states(env, states[::-1], size=64)[::-1]
        assert first.shape == (4, 64, 64, 3) and np.array_equal(first, again)
        assert np.array_equal(first[0], obs["agentview_image"][::-1, ::-1])  # the reset image, upright, bit for bit
        assert np.abs(first[3].astype(int) - first[0]).max() > 20  # the arm moved: frames are not all the same
        np.testing.assert_array_equal(env.env.sim.get_state().flatten(), states[-1])  # the env's state is restored
    finally:
        env.close()


def test_envs_of_one_scene_share_a_renderer_that_draws_what_robosuite_draws(tmp_path):
    """Two tasks of one scene (their models differ in where the fixtures stand) render through one shared renderer,
    and every frame is bit for bit what robosuite's own renderer (an env made with the camera) draws of the same state.
    robosuite's renderer draws the simulator's data as it is: after a step, poses computed 2 ms before the state
    (MuJoCo integrates after computing them), so that env's data is computed for its state first. The shared renderer
    draws the state itself without changing the env: both envs step on to the same states."""
    from bpp.benchmarks.libero.sim import SharedRenderer, render_now, reset_env

    tasks = combination().train
    first, second = tasks[0], next(t for t in tasks[1:] if t.scene.base == tasks[0].scene.base)
    renderers = []
    for i, task in enumerate((first, second)):
        path = tmp_path / f"task{i}.bddl"
        path.write_text(combination_problem(task, spatial_problem(task.scene.base)))
        shared, own = make_env(path, render=True), make_env(path, cameras=("agentview", "robot0_eye_in_hand"))
        try:
            assert shared.env.sim._render_context_offscreen is None  # no renderer of its own
            renderers.append(SharedRenderer.of(shared.env.sim))
            for env in (shared, own):
                reset_env(env, seed=i)
            for step in range(3):
                own.env.sim.forward()
                for camera in ("agentview", "robot0_eye_in_hand"):
                    for size in (32, 128):
                        a, b = render_now(shared, camera, size), render_now(own, camera, size)
                        assert a.shape == (size, size, 3) and np.array_equal(a, b), (i, step, camera, size)
                for env in (shared, own):
                    env.step(np.r_[0.3, 0.1, -0.2, 0.0, 0.0, 0.0, -1.0])
                np.testing.assert_array_equal(shared.env.sim.get_state().flatten(), own.env.sim.get_state().flatten())
        finally:
            shared.close()
            own.close()
    assert renderers[0] is renderers[1]


def test_a_closed_env_frees_its_model_and_renderer_without_a_garbage_collection(tmp_path):
    """Closing an env (per task in generation, per rollout in evaluation) runs no full collection of the process's
    heap: its model, data and renderer go by reference counting alone."""
    import gc
    import weakref

    task = combination().train[0]
    path = tmp_path / "task.bddl"
    path.write_text(combination_problem(task, spatial_problem(task.scene.base)))
    env = make_env(path, cameras=("agentview",), image_size=32)
    sim = env.env.sim
    gone = [weakref.ref(sim.model), weakref.ref(sim.data), weakref.ref(sim._render_context_offscreen)]
    collections = gc.get_stats()[2]["collections"]
    gc.disable()
    try:
        env.close()
        del sim
        assert [ref() for ref in gone] == [None, None, None]
        assert gc.get_stats()[2]["collections"] == collections  # no full collection ran
    finally:
        gc.enable()


def test_torch_can_load_its_compiler_after_a_camera_env(tmp_path):
    """Mesa's renderer and triton each bring an LLVM; in the wrong order the process used to crash (SIGSEGV)."""
    import subprocess
    import sys

    task = combination().train[0]
    path = tmp_path / "task.bddl"
    path.write_text(combination_problem(task, spatial_problem(task.scene.base)))
    code = (
        "from bpp.benchmarks.libero.sim import make_env\n"
        f"env = make_env({str(path)!r}, cameras=('agentview',), image_size=32)\n"
        "env.reset()\n"
        "import torch._dynamo  # loads triton\n"
        "print('alive')\n"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0 and "alive" in result.stdout, result.stderr[-2000:]


def test_a_missing_renderer_is_named_with_its_package(monkeypatch):
    import pytest

    from bpp.benchmarks.libero import sim

    monkeypatch.setenv("MUJOCO_GL", "egl")
    sim._check_renderer()  # Debian's Mesa provides EGL here
    monkeypatch.setitem(sim.RENDERER_LIBRARIES, "egl", ("NoSuchRendererLibrary", "libegl1 and libgl1-mesa-dri"))
    with pytest.raises(sim.LiberoUnavailable, match="apt-get install libegl1 and libgl1-mesa-dri"):
        sim._check_renderer()
    monkeypatch.setenv("MUJOCO_GL", "vulkan")
    with pytest.raises(sim.LiberoUnavailable, match="not a renderer; use one of egl, osmesa, glfw"):
        sim._check_renderer()


def test_libero_goal_is_libero_own_ten_problems_with_their_initial_states():
    from bpp.benchmarks.libero.dataset import problem_text
    from bpp.benchmarks.libero.sim import initial_states
    from bpp.benchmarks.libero.suites import SUITES_BY_NAME

    suite = SUITES_BY_NAME["libero_goal"]()
    assert suite.original and len(suite.train) == 10 and not suite.test
    for task in suite.train:
        folder, name = task.libero_source
        assert problem_text(task, original=True) == (problems_folder() / folder / f"{name}.bddl").read_text()
        assert initial_states(f"{folder}/{name}.pruned_init").shape[0] == 50
        assert task.steps  # each reads as the demonstrator's operators


def test_written_initial_states_are_what_libero_sampler_gives_and_load_back(tmp_path, capsys):
    """``bpp libero tasks --init-states N`` writes, per task, the states LIBERO's placement sampler gives for seeds
    0 .. N-1; LIBERO's ``set_init_state`` puts the scene back into each of them."""
    import json

    from bpp.benchmarks.libero.suites import Suite
    from bpp.benchmarks.libero.tasks import write_suite
    from bpp.cli import main

    task = combination().test[0]
    index = json.loads(write_suite(Suite("mini", (), (task,)), tmp_path / "mini", init_states=2).read_text())
    entry = index["test"][0]
    path = tmp_path / "mini" / entry["problem"]
    states = np.load(tmp_path / "mini" / entry["init_states"])["states"]
    assert states.shape == (2, 92) and not np.array_equal(states[0], states[1])
    env = make_env(path)
    try:
        env.seed(1)
        env.reset()
        assert np.array_equal(env.env.sim.get_state().flatten(), states[1])
        env.set_init_state(states[0])
        assert np.allclose(env.env.sim.get_state().flatten(), states[0])
    finally:
        env.close()
    with pytest.raises(SystemExit):
        main(["libero", "tasks", "--init-states", "5"])
    err = " ".join(capsys.readouterr().err.replace("│", " ").split())  # tyro wraps its message in a box
    assert "init_states must be 0 unless --out is given" in err


def _env_of_task(folder, task, name: str = "task"):
    path = folder / f"{name}.bddl"
    path.write_text(combination_problem(task, spatial_problem(task.scene.base)))
    return make_env(path)


STAT = ("meaninertia", "meanmass", "meansize", "extent", "center")
"""The model's statistics, which MuJoCo also derives when it compiles a scene."""


def _assert_same_scene(a, b) -> None:
    """The same simulator state, fixture poses, changeable parts of the model (bodies' poses, sites' colours, the
    constants derived from the poses) and gripper command, bit for bit."""
    from bpp.benchmarks.libero.sim import COMPILED_CONSTANTS, fixture_poses

    np.testing.assert_array_equal(a.env.sim.get_state().flatten(), b.env.sim.get_state().flatten())
    np.testing.assert_array_equal(fixture_poses(a)[1], fixture_poses(b)[1])
    for name in ("body_pos", "body_quat", "site_rgba"):
        np.testing.assert_array_equal(getattr(a.env.sim.model, name), getattr(b.env.sim.model, name), err_msg=name)
    for name in COMPILED_CONSTANTS:
        np.testing.assert_array_equal(getattr(a.env.sim.model._model, name), getattr(b.env.sim.model._model, name))
    for name in STAT:
        np.testing.assert_array_equal(
            getattr(a.env.sim.model._model.stat, name), getattr(b.env.sim.model._model.stat, name)
        )
    np.testing.assert_array_equal(a.env.robots[0].gripper.current_action, b.env.robots[0].gripper.current_action)


def _assert_same_observation(a: dict, b: dict) -> None:
    assert a.keys() == b.keys()
    for key in a:
        np.testing.assert_array_equal(a[key], b[key], err_msg=key)


def test_a_soft_reset_gives_what_libero_hard_reset_gives_after_the_same_episodes(tmp_path):
    """reset_env resets the compiled model in place; LIBERO's own reset rebuilds and recompiles it. In the scene whose
    bowl starts in the open top drawer (placed from the drawer's site; the drawer opened by a joint initializer, which
    LIBERO adds once more at every rebuild), after episodes that closed the gripper and turned the stove on (its
    burner's site shows), every seed gives the same scene and observation bit for bit, and so does every step."""
    from bpp.benchmarks.libero.sim import reset_env

    task = next(t for t in combination().train if t.pick == "TD")
    hard, soft = _env_of_task(tmp_path, task), _env_of_task(tmp_path, task)
    try:
        for seed in (0, 1, 2):
            hard.seed(seed)
            _assert_same_observation(hard.reset(), reset_env(soft, seed))
            _assert_same_scene(hard, soft)
            for t in range(12):
                if t == 6:
                    for env in (hard, soft):
                        env.env.sim.data.set_joint_qpos("flat_stove_1_button", 1.0)  # the stove on
                action = np.r_[0.3, 0.0, -0.6, 0.0, 0.0, 0.2, 1.0]  # down and turning, closing the gripper
                _assert_same_observation(hard.step(action)[0], soft.step(action)[0])
            _assert_same_scene(hard, soft)
            assert hard.env.sim.model.site_rgba[hard.env.sim.model.site_name2id("flat_stove_1_burner"), 3] > 0
    finally:
        hard.close()
        soft.close()


def test_a_soft_reset_after_an_episode_gives_the_scene_of_a_new_env(tmp_path):
    """Where the problem sets no joint at the start (no initializer draws from the seed before the placements), a
    seed's scene does not depend on the env's history: reset_env in an env whose episode left the gripper closed,
    its fixtures' constants derived where they stood, gives LIBERO's reset of a new env, and the same steps after it."""
    from bpp.benchmarks.libero.sim import fixture_poses, place_fixtures, reset_env

    task = combination().train[0]
    used, new = _env_of_task(tmp_path, task), _env_of_task(tmp_path, task)
    try:
        reset_env(used, 3)
        place_fixtures(used, *fixture_poses(used))  # as a replay of a demonstration starts
        for _ in range(10):
            used.step(np.r_[0.0, 0.2, -0.5, 0.0, 0.0, 0.0, 1.0])
        new.seed(5)
        _assert_same_observation(new.reset(), reset_env(used, 5))
        _assert_same_scene(new, used)
        for _ in range(8):  # opening: from rest in a new gripper
            action = np.r_[0.2, 0.0, -0.4, 0.0, 0.0, 0.0, -1.0]
            _assert_same_observation(new.step(action)[0], used.step(action)[0])
        _assert_same_scene(new, used)
    finally:
        used.close()
        new.close()


def test_the_fast_step_gives_robosuite_own_step_bit_for_bit(tmp_path):
    """make_env's envs step with one forward dynamics per physics substep (mj_step1, the controller, mj_step2) where
    robosuite's step runs it three times, and control the arm between policy steps without robosuite's lookups: a
    scripted demonstration (down to the bowl, grasp, carry, release: contacts all along) made with it replays through
    robosuite's own step to its states and observations bit for bit, and to the same force-torque record of the hand
    (read at each action's first substep)."""
    import mujoco
    from robosuite.environments.base import MujocoEnv

    from bpp.benchmarks.libero import sim
    from bpp.benchmarks.libero.demonstrator import demonstrate
    from bpp.benchmarks.libero.substeps import ArmSubstep

    task = combination().train[0]
    env = _env_of_task(tmp_path, task)
    try:
        assert MujocoEnv.step is not sim._ROBOSUITE_STEP  # the fast step is installed, and LIBERO integrates by Euler:
        assert env.env.sim.model.opt.integrator == mujoco.mjtIntegrator.mjINT_EULER  # it is in use
        demo = demonstrate(env, task, seed=0)
        assert demo.success
        robot, inner = env.env.robots[0], env.env
        assert ArmSubstep.of(robot) is not None  # its substeps ran bpp's control, not robosuite's
        end, force = inner.sim.get_state().flatten(), robot.recent_ee_forcetorques.current.copy()
        sim.reset_scene(env, 0)
        sim.seat(env, demo.states[0])
        for t, action in enumerate(demo.actions):
            np.testing.assert_array_equal(inner.sim.get_state().flatten(), demo.states[t])
            obs, *_ = sim._ROBOSUITE_STEP(inner, action)
            if t + 1 < len(demo.actions):
                seen = {k: np.asarray(obs[k], dtype=np.float32) for k in demo.observations}
                _assert_same_observation(seen, {k: v[t + 1] for k, v in demo.observations.items()})
        np.testing.assert_array_equal(inner.sim.get_state().flatten(), end)
        np.testing.assert_array_equal(robot.recent_ee_forcetorques.current, force)
        assert np.abs(force).max() > 0
    finally:
        env.close()


def test_a_drawer_demonstration_replays_in_the_scene_its_file_compiles(tmp_path):
    """A demonstration whose hand reaches into the open top drawer, replayed in the scene its exported ``model_file``
    compiles (the fixtures where it had them), passes through every state it recorded, bit for bit, and reaches its
    goal or not, as it did. LIBERO compiles a scene with its fixtures at the origin and then moves them: what MuJoCo
    derives from the bodies' poses at compile time (the drawer joints' inverse weights, the cameras' offsets) must be
    the file's, or the replay leaves the demonstration where the hand pushes the drawer."""
    from bpp.benchmarks.libero.demonstrator import demonstrate
    from bpp.benchmarks.libero.export import scene_xml
    from bpp.benchmarks.libero.sim import COMPILED_CONSTANTS, fixture_poses, seat

    task = next(t for t in combination().train if t.pick == "TD" and t.place == "NP")
    env = _env_of_task(tmp_path, task)
    try:
        demo = demonstrate(env, task, seed=0)  # it fails, pushing the drawer (step 190)
        built = {name: getattr(env.env.sim.model._model, name).copy() for name in COMPILED_CONSTANTS}
        built_stat = [np.asarray(getattr(env.env.sim.model._model.stat, name)).tolist() for name in STAT]
        sim_end = env.env.sim.get_state().flatten()
        xml = scene_xml(env, 0, fixture_poses(env))
        env.env.reset_from_xml_string(xml)
        compiled = env.env.sim.model._model
        for name in COMPILED_CONSTANTS:
            np.testing.assert_array_equal(built[name], getattr(compiled, name), err_msg=name)
        assert built_stat == [np.asarray(getattr(compiled.stat, name)).tolist() for name in STAT]
        seat(env, demo.states[0])
        actions = demo.actions if demo.executed is None else demo.executed
        for t, action in enumerate(actions):
            np.testing.assert_array_equal(env.env.sim.get_state().flatten(), demo.states[t], err_msg=f"step {t}")
            env.step(action)
        np.testing.assert_array_equal(env.env.sim.get_state().flatten(), sim_end)
        assert env.env._check_success() == demo.success
    finally:
        env.close()
