"""A LIBERO scene is rebuilt exactly from what an episode stores: LIBERO places its fixtures (cabinet, stove, rack)
anew at every reset, and a fixture's pose is not in the simulator state, so each episode keeps it. Needs the
`libero` extra, which `make test` installs."""

from __future__ import annotations

import numpy as np
import pytest

from bpp.benchmarks.libero import dataset
from bpp.cli import main
from bpp.data.store import EpisodeStore

pytestmark = pytest.mark.libero


@pytest.mark.slow
def test_a_drawer_scene_is_rebuilt_from_its_episode(tmp_path):
    """LIBERO places the cabinet, stove and rack anew at every reset, and their pose is not in the simulator state:
    each episode keeps it, so a replay from another reset, and a re-rendered frame, are those of the demonstration."""
    from bpp.benchmarks.libero.benchmark import _render
    from bpp.benchmarks.libero.rollouts import task_problem
    from bpp.benchmarks.libero.sim import make_env, replay

    out = tmp_path / "drawer.zarr"
    flags = ["--suite", "chain", "--task-indices", "1", "--demos-per-task", "1", "--goal-size", "16"]  # the top drawer
    main(["libero", "generate", "--out", str(out), "--workers", "1", *flags])
    store = EpisodeStore(out)
    assert store.tasks[0]["instruction"] == "open the top drawer"
    names, poses = dataset.episode_fixtures(store, 0)
    assert "wooden_cabinet_1" in names and np.isfinite(poses).all()
    steps = store.episode(0, ["sim_state", "action"])
    other_seed = int(store.column("seed")[0]) + 1  # another reset: the fixtures elsewhere, until put back
    problem = tmp_path / "drawer.bddl"
    problem.write_text(task_problem(store, 0))
    env = make_env(problem)
    try:
        states, success = replay(env, other_seed, steps["sim_state"], steps["action"], (names, poses))
        np.testing.assert_array_equal(states[:-1], steps["sim_state"])
        assert success
        elsewhere, _ = replay(env, other_seed, steps["sim_state"], steps["action"])  # without them: another scene
        assert np.abs(elsewhere[:-1] - steps["sim_state"]).max() > 1e-3
    finally:
        env.close()
    frame = _render(store, 0, states[-1:], "agentview", 16)  # the end, as the generating env drew its goal frame
    np.testing.assert_array_equal(frame[0], store.column(dataset.GOAL_KEY)[0])
