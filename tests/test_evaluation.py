"""The evaluation protocol and its prompt controls (another task's prompt, the prompt's chunks shuffled, its first
half, no prompt)."""

import json

import numpy as np
import pytest
import torch

import bpp.benchmarks.draw.rollouts as draw_rollouts
import bpp.core.prompting as prompting
import bpp.evaluation.evaluate as evaluation
from bpp.benchmarks.draw.benchmark import BENCHMARK
from bpp.core.contract import TaskSet
from bpp.data.contexts import CONTROL_CHUNK, prompt_steps, task_context
from bpp.errors import UserError
from bpp.evaluation.evaluate import Protocol, evaluate
from bpp.policies.agent import PolicyAgent
from bpp.policies.bpp.model import BPPModel
from bpp.policies.registry import get_method
from bpp.train import TrainConfig, train
from helpers import config, rollout_batch


def test_protocol_cycles_prompts_and_the_control_changes_only_the_prompt(debug_store):
    own, control = Protocol(rollouts=7), Protocol(rollouts=7, prompts="other-task")
    task_of = {int(e): t for t, eps in enumerate(debug_store.task_episodes()) for e in eps}
    for task in (0, 5, debug_store.num_tasks - 1):
        demos = list(debug_store.task_episodes()[task])
        mine, other = own.plan(debug_store, task, BENCHMARK), control.plan(debug_store, task, BENCHMARK)
        assert [p["prompt_episode"] for p in mine] == [demos[r % len(demos)] for r in range(7)]
        assert all(p["target_episode"] == p["prompt_episode"] for p in mine)
        prompted = [task_of[p["prompt_episode"]] for p in other]
        assert task not in prompted and len(set(prompted)) == 7  # another task every time, a different one per rollout
        for a, b in zip(mine, other, strict=True):  # the same rollouts otherwise: target, board angle and seed
            assert (a["target_episode"], a["board_angle"], a["seed"]) == (
                b["target_episode"],
                b["board_angle"],
                b["seed"],
            )
    again = Protocol(rollouts=7, prompts="other-task")
    assert control.plan(debug_store, 3, BENCHMARK) == again.plan(debug_store, 3, BENCHMARK)
    with pytest.raises(ValueError, match="prompts must be"):
        Protocol(prompts="backwards")


def test_rollouts_are_prompted_with_the_prompt_episodes_and_scored_on_their_own(debug_store, monkeypatch):
    torch.manual_seed(0)
    agent = PolicyAgent(BPPModel(config("bpp"), debug_store.stats).eval())
    targets, angles, seeds = [0, 4], [0.2, -0.3], [1, 2]
    plain = rollout_batch(agent, debug_store, targets, angles, seeds, max_steps=15)
    same = rollout_batch(agent, debug_store, targets, angles, seeds, max_steps=15, prompt_episodes=targets)
    assert [r.best_chamfer for r in plain] == [r.best_chamfer for r in same]
    prompted, scored = [], []
    task_context, prompt_target = prompting.task_context, draw_rollouts.prompt_target
    monkeypatch.setattr(
        prompting, "task_context", lambda st, ep, *a, **kw: prompted.append(ep) or task_context(st, ep, *a, **kw)
    )
    monkeypatch.setattr(draw_rollouts, "prompt_target", lambda st, ep: scored.append(ep) or prompt_target(st, ep))
    swapped = rollout_batch(agent, debug_store, targets, angles, seeds, max_steps=15, prompt_episodes=[9, 30])
    assert prompted == [9, 30] and scored == targets  # contexts from the prompt episodes, scores on the targets
    assert [r.best_chamfer for r in swapped] != [r.best_chamfer for r in plain]
    with pytest.raises(ValueError, match="1 prompt episodes for 2 rollouts"):
        rollout_batch(agent, debug_store, targets, angles, seeds, max_steps=5, prompt_episodes=[3])


def test_the_edit_controls_keep_whole_chunks_or_the_first_half():
    assert prompt_steps(37, None, 0) is None
    np.testing.assert_array_equal(prompt_steps(37, "first-half", 5), np.arange(19))
    shuffled = prompt_steps(37, "shuffled", 5)
    assert sorted(shuffled.tolist()) == list(range(37))  # every step once
    chunks = shuffled[:30].reshape(3, CONTROL_CHUNK)
    assert (np.diff(chunks, axis=1) == 1).all() and (chunks[:, 0] % CONTROL_CHUNK == 0).all()  # whole chunks
    np.testing.assert_array_equal(shuffled[30:], np.arange(30, 37))  # the shorter last chunk stays last
    orders = {tuple(prompt_steps(200, "shuffled", seed)[::CONTROL_CHUNK]) for seed in range(6)}
    assert len(orders) == 6 and tuple(range(0, 200, CONTROL_CHUNK)) not in orders
    np.testing.assert_array_equal(prompt_steps(200, "shuffled", 3), prompt_steps(200, "shuffled", 3))
    assert prompt_steps(37, "none", 5).shape == (0,)
    with pytest.raises(ValueError, match="unknown prompt edit"):
        prompt_steps(10, "reversed", 0)


@pytest.mark.parametrize("method", ["bpp", "goal_image", "language"])
def test_an_edited_prompt_is_made_of_the_demonstration_steps_it_names(debug_store, method):
    spec = get_method(method).model_cls(config(method), debug_store.stats).data_spec()
    episode = 8
    sl = debug_store.episode_slice(episode)
    steps = prompt_steps(sl.stop - sl.start, "shuffled", 11)
    edited = task_context(debug_store, episode, spec, BENCHMARK.frames, steps=steps)
    whole = task_context(debug_store, episode, spec, BENCHMARK.frames)
    if spec.context == "demo":
        np.testing.assert_array_equal(edited["action"], whole["action"][steps])
        for key in spec.lowdim_keys:
            np.testing.assert_array_equal(edited["obs"][key], whole["obs"][key][steps])
    elif spec.context == "goal_image":  # the frame of the edited prompt's latest step: shuffling keeps the goal
        np.testing.assert_array_equal(edited["image"], whole["image"])
        half = prompt_steps(sl.stop - sl.start, "first-half", 11)
        frame = BENCHMARK.frames(debug_store, episode, spec.context_image_key, spec.context_image_size, steps=half)
        first_half = task_context(debug_store, episode, spec, BENCHMARK.frames, steps=half)
        np.testing.assert_array_equal(first_half["image"], frame[-1])
        assert not np.array_equal(first_half["image"], whole["image"])
    else:
        assert edited == whole  # an instruction is not a demonstration: nothing to edit


@pytest.mark.parametrize("method", ["bpp", "icrt"])
def test_with_no_prompt_a_policy_acts_the_same_whatever_demonstration_it_was_given(debug_store, method):
    torch.manual_seed(0)
    model = get_method(method).model_cls(config(method), debug_store.stats).eval()
    agent = PolicyAgent(model)
    targets, angles, seeds = [0, 0, 4], [0.2, 0.2, -0.3], [1, 1, 2]

    def scores(prompts, edit=None):
        plan = [
            {"target_episode": t, "prompt_episode": p, "board_angle": a, "seed": s, "prompt_edit": edit}
            for t, p, a, s in zip(targets, prompts, angles, seeds, strict=True)
        ]
        results, _ = prompting.run_prompted(agent, BENCHMARK, debug_store, plan, 15, [False] * len(plan))
        return [r.score for r in results]

    none = scores([9, 30, 4], "none")
    assert none[0] == none[1]  # two demonstrations, neither attended to: one rollout
    own, other = scores([9, 30, 4]), scores([9, 30, 4], "first-half")
    assert own[0] != own[1] and own[:2] != none[:2] and other[:2] != none[:2]
    spec = model.data_spec()
    blank = task_context(debug_store, 9, spec, BENCHMARK.frames, steps=prompt_steps(50, "none", 0))
    assert blank["valid"].tolist() == [False] and len(blank["action"]) == 1
    assert model.validate_context(blank)["valid"].tolist() == [[False]]
    with pytest.raises(ValueError, match="may only mark all of its 1 steps False"):
        model.validate_context({**blank, "valid": np.ones(1, dtype=bool)})


def test_no_prompt_gives_an_instruction_policy_no_instruction_and_a_goal_image_policy_an_error(debug_store):
    language = get_method("language").model_cls(config("language"), debug_store.stats).data_spec()
    assert task_context(debug_store, 3, language, BENCHMARK.frames, steps=prompt_steps(9, "none", 0)) == {"text": ""}
    goal = get_method("goal_image").model_cls(config("goal_image"), debug_store.stats).data_spec()
    with pytest.raises(ValueError, match="cannot run without its goal"):
        task_context(debug_store, 3, goal, BENCHMARK.frames, steps=prompt_steps(9, "none", 0))


def test_evaluate_refuses_no_prompt_for_a_goal_image_policy_before_any_rollout(debug_store, tmp_path):
    run = tmp_path / "run"
    cfg = TrainConfig(data=debug_store.path, out=run, method="goal_image", steps=1, batch_size=4, workers=0)
    train(cfg, config("goal_image"), progress=False)
    protocol = Protocol(rollouts=1, max_steps=5, prompts="none")
    with pytest.raises(UserError, match="--prompts none does not apply"):
        evaluate(run, TaskSet(debug_store, "debug"), [0], tmp_path / "eval", protocol, videos=0, progress=False)
    assert not (tmp_path / "eval").exists()


@pytest.mark.parametrize("control", ["shuffled", "first-half"])
def test_evaluate_with_an_edit_control_prompts_with_the_edited_demonstration(
    debug_store, tmp_path, control, monkeypatch
):
    run = tmp_path / "run"
    cfg = TrainConfig(data=debug_store.path, out=run, method="bpp", steps=1, batch_size=4, workers=0, warmup_steps=1)
    train(cfg, config("bpp"), progress=False)
    seen = []
    real = prompting.task_context
    monkeypatch.setattr(prompting, "task_context", lambda *a, **kw: seen.append(kw["steps"]) or real(*a, **kw))
    protocol = Protocol(rollouts=2, max_steps=10, prompts=control)
    evaluate(run, TaskSet(debug_store, "debug"), [1], tmp_path / "eval", protocol, workers=0, videos=0, progress=False)
    data = json.loads((tmp_path / "eval" / "results.json").read_text())
    assert data["protocol"]["prompts"] == control
    rows = data["rollouts"]
    assert all(r["prompt_edit"] == control and r["prompt_episode"] == r["target_episode"] for r in rows)
    for row, steps in zip(rows, seen, strict=True):
        sl = debug_store.episode_slice(row["prompt_episode"])
        np.testing.assert_array_equal(steps, prompt_steps(sl.stop - sl.start, control, row["seed"]))


def test_evaluate_with_the_control_records_both_episodes(debug_store, tmp_path):
    run = tmp_path / "run"
    cfg = TrainConfig(data=debug_store.path, out=run, method="bpp", steps=1, batch_size=4, workers=0, warmup_steps=1)
    train(cfg, config("bpp"), progress=False)
    protocol = Protocol(rollouts=2, max_steps=12, prompts="other-task")
    evaluate(
        run, TaskSet(debug_store, "debug"), [0, 1], tmp_path / "eval", protocol, workers=1, videos=0, progress=False
    )
    data = json.loads((tmp_path / "eval" / "results.json").read_text())
    assert data["protocol"]["prompts"] == "other-task"
    episodes = debug_store.task_episodes()
    for row in data["rollouts"]:
        assert row["target_episode"] in episodes[row["task"]] and row["prompt_episode"] not in episodes[row["task"]]
    assert np.isfinite(data["summary"]["score_mean"])


def test_evaluate_reuses_results_only_under_the_same_protocol(debug_store, tmp_path, capsys):
    run = tmp_path / "run"
    cfg = TrainConfig(data=debug_store.path, out=run, method="bpp", steps=1, batch_size=4, workers=0, warmup_steps=1)
    train(cfg, config("bpp"), progress=False)
    protocol, out = Protocol(rollouts=1, max_steps=8), tmp_path / "eval"
    evaluate(run, TaskSet(debug_store, "debug"), [2], out, protocol, workers=1, videos=0, progress=False)
    capsys.readouterr()
    evaluate(run, TaskSet(debug_store, "debug"), [2], out, protocol, workers=1, videos=0, progress=False)
    assert "reusing" in capsys.readouterr().out
    results = out / "results.json"
    data = json.loads(results.read_text())
    del data["protocol"]["prompts"]  # a record that does not state the whole protocol is run again
    results.write_text(json.dumps(data))
    evaluate(run, TaskSet(debug_store, "debug"), [2], out, protocol, workers=1, videos=0, progress=False)
    assert "reusing" not in capsys.readouterr().out
    control = Protocol(rollouts=1, max_steps=8, prompts="other-task")
    evaluate(run, TaskSet(debug_store, "debug"), [2], out, control, workers=1, videos=0, progress=False)
    assert "reusing" not in capsys.readouterr().out
    data = json.loads(results.read_text())
    del data["protocol"]["tasks_per_batch"]  # a record without the field: one task a batch
    results.write_text(json.dumps(data))
    evaluate(run, TaskSet(debug_store, "debug"), [2], out, control, workers=1, videos=0, progress=False)
    assert "reusing" in capsys.readouterr().out
    batched = Protocol(rollouts=1, max_steps=8, prompts="other-task", tasks_per_batch=2)
    evaluate(run, TaskSet(debug_store, "debug"), [2], out, batched, workers=1, videos=0, progress=False)
    assert "reusing" not in capsys.readouterr().out


def test_tasks_batched_together_give_the_same_results_on_any_number_of_workers(debug_store, tmp_path, monkeypatch):
    """With tasks_per_batch, consecutive tasks of the list step together (batches fixed by the list, not by the
    workers): one worker or two give the same results file, and they are the rollouts of one task at a time to the
    last bits of the policy's arithmetic."""
    run = tmp_path / "run"
    cfg = TrainConfig(data=debug_store.path, out=run, method="bpp", steps=2, batch_size=4, workers=0, warmup_steps=1)
    train(cfg, config("bpp"), progress=False)
    tasks, batches = TaskSet(debug_store, "debug"), []
    real = evaluation._run_tasks
    monkeypatch.setattr(evaluation, "_run_tasks", lambda job: batches.append([t for t, _ in job]) or real(job))
    results = {}
    for name, size, workers in (("alone", 1, 1), ("one", 3, 1), ("two", 3, 2)):
        if workers == 2:
            monkeypatch.undo()  # the pool's processes pickle the function they run
        protocol = Protocol(rollouts=2, max_steps=12, tasks_per_batch=size)
        results[name] = evaluate(run, tasks, [0, 3, 5, 7], tmp_path / name, protocol, workers, 1, progress=False)
    assert batches == [[0], [3], [5], [7], [0, 3, 5], [7]]
    assert results["one"]["rollouts"] == results["two"]["rollouts"]
    assert results["one"]["summary"] == results["two"]["summary"]
    for got, want in zip(results["one"]["rollouts"], results["alone"]["rollouts"], strict=True):
        assert got["steps"] == want["steps"] and got["score"] == pytest.approx(want["score"], abs=1e-3)


def test_an_interrupted_evaluation_resumes_with_the_tasks_it_had_finished(debug_store, tmp_path, monkeypatch):
    run = tmp_path / "run"
    cfg = TrainConfig(data=debug_store.path, out=run, method="bpp", steps=1, batch_size=4, workers=0, warmup_steps=1)
    train(cfg, config("bpp"), progress=False)
    protocol, tasks = Protocol(rollouts=2, max_steps=10), TaskSet(debug_store, "debug")
    evaluate(run, tasks, [0, 3, 5], tmp_path / "whole", protocol, workers=1, videos=1, progress=False)
    real, ran = evaluation._run_tasks, []

    def killed_on_the_third(job):
        ran.append(job[0][0])
        if len(ran) == 3:
            raise KeyboardInterrupt
        return real(job)

    monkeypatch.setattr(evaluation, "_run_tasks", killed_on_the_third)
    out = tmp_path / "eval"
    with pytest.raises(KeyboardInterrupt):
        evaluate(run, tasks, [0, 3, 5], out, protocol, workers=1, videos=1, progress=False)
    assert not out.exists() and len(list((tmp_path / ".eval.journal").glob("task-*.npz"))) == 2
    ran.clear()
    evaluate(run, tasks, [0, 3, 5], out, protocol, workers=1, videos=1, progress=False)
    assert ran == [5]  # tasks 0 and 3 (with its video frames) came from the journal
    whole, resumed = (json.loads((tmp_path / name / "results.json").read_text()) for name in ("whole", "eval"))
    for key in ("summary", "tasks", "rollouts"):
        assert resumed[key] == whole[key]
    assert (out / "grid.png").read_bytes() == (tmp_path / "whole" / "grid.png").read_bytes()
    assert sorted(p.name for p in out.iterdir()) == sorted(p.name for p in (tmp_path / "whole").iterdir())
    assert not (tmp_path / ".eval.journal").exists()  # gone with the results written


@pytest.mark.slow
def test_agent_overrides_set_denoising_steps_and_replanning(debug_store, tmp_path, capsys):
    from bpp.policies.icrt.model import ICRTModel

    model = BPPModel(config("bpp"), debug_store.stats).eval()
    calls = []
    model.head.net.register_forward_hook(lambda *_: calls.append(1))
    for steps, executed in ((None, None), (2, 3)):
        agent = PolicyAgent(model, n_action_steps=executed, num_inference_steps=steps)
        calls.clear()
        rollout_batch(agent, debug_store, [0], [0.1], [1], max_steps=9)
        per_call = steps or config("bpp").diffusion.num_inference_steps
        inferences = -(-9 // (executed or config("bpp").horizons.n_action_steps))
        assert len(calls) == per_call * inferences
    with pytest.raises(ValueError, match="no diffusion decoder"):
        PolicyAgent(ICRTModel(config("icrt"), debug_store.stats), num_inference_steps=4)
    with pytest.raises(ValueError, match="inference steps must be in"):
        PolicyAgent(model, num_inference_steps=10_000)

    run, out = tmp_path / "run", tmp_path / "eval"
    cfg = TrainConfig(data=debug_store.path, out=run, method="bpp", steps=1, batch_size=4, workers=0, warmup_steps=1)
    train(cfg, config("bpp"), progress=False)
    tuned = Protocol(rollouts=1, max_steps=8, n_action_steps=2, inference_steps=3)
    evaluate(run, TaskSet(debug_store, "debug"), [2], out, tuned, workers=1, videos=0, progress=False)
    assert json.loads((out / "results.json").read_text())["protocol"]["inference_steps"] == 3
    assert "2 actions per inference, 3 denoising steps" in (out / "results.md").read_text()
    capsys.readouterr()
    plain = Protocol(rollouts=1, max_steps=8)
    evaluate(run, TaskSet(debug_store, "debug"), [2], out, plain, workers=1, videos=0, progress=False)
    assert "reusing" not in capsys.readouterr().out


def test_bpp_eval_reads_each_checkpoint_once(debug_store, tmp_path, monkeypatch):
    import bpp.checkpoint as checkpoint
    from bpp.cli import main

    run = tmp_path / "run"
    cfg = TrainConfig(data=debug_store.path, out=run, method="bpp", steps=1, batch_size=4, workers=0, warmup_steps=1)
    train(cfg, config("bpp"), progress=False)
    reads = []
    load_tensors, read_state = checkpoint._load_tensors, checkpoint.read_state
    monkeypatch.setattr(checkpoint, "_load_tensors", lambda path, *a: reads.append(path.name) or load_tensors(path, *a))
    monkeypatch.setattr(checkpoint, "read_state", lambda path: reads.append("state.json") or read_state(path))
    args = ["eval", str(run), "--tasks", str(debug_store.path), "--num-tasks", "2", "--rollouts", "1"]
    main([*args, "--max-steps", "5", "--workers", "1", "--videos", "0", "--out", str(tmp_path / "eval")])
    assert sorted(reads) == ["ema.safetensors", "state.json"]


@pytest.mark.slow
def test_bad_agent_options_are_refused_before_any_worker_starts(debug_store, tmp_path):
    """A worker that fails to start would be restarted forever by a process pool: the parent checks first."""
    import subprocess
    import sys

    run = tmp_path / "icrt"
    cfg = TrainConfig(data=debug_store.path, out=run, method="icrt", steps=1, batch_size=2, workers=0, warmup_steps=1)
    train(cfg, config("icrt"), progress=False)
    args = ["eval", str(run), "--tasks", str(debug_store.path), "--num-tasks", "2", "--workers", "2"]
    out = subprocess.run(
        [sys.executable, "-m", "bpp.cli", *args, "--n-action-steps", "4", "--out", str(tmp_path / "eval")],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode != 0 and "executes all N=10 actions" in out.stderr and "Traceback" not in out.stderr
    assert not (tmp_path / "eval").exists()


def test_evaluate_renders_only_the_frames_it_writes(debug_store, tmp_path, monkeypatch):
    """Without videos an evaluation renders one frame per task (the grid's), not the whole first rollout; with a
    video, that task's first rollout is rendered at every step."""
    from bpp.benchmarks.draw.env import DrawEnv

    run = tmp_path / "run"
    cfg = TrainConfig(data=debug_store.path, out=run, method="bpp", steps=1, batch_size=4, workers=0, warmup_steps=1)
    train(cfg, config("bpp"), progress=False)
    rendered = []
    render = DrawEnv.render
    monkeypatch.setattr(DrawEnv, "render", lambda env: rendered.append(env) or render(env))
    protocol = Protocol(rollouts=2, max_steps=12)
    for videos, expected in ((0, 2), (1, 1 + 12 + 1)):
        rendered.clear()
        out = tmp_path / f"eval-{videos}"
        evaluate(run, TaskSet(debug_store, "debug"), [0, 1], out, protocol, workers=1, videos=videos, progress=False)
        assert len(rendered) == expected
        assert (out / "grid.png").stat().st_size > 0


@pytest.mark.parametrize("workers", [1, 3])
def test_a_task_set_made_for_an_evaluation_uses_its_workers(debug_store, tmp_path, monkeypatch, workers):
    import bpp.benchmarks.draw.dataset as draw_dataset
    from bpp.checkpoint import Checkpoint
    from bpp.evaluation.evaluate import resolve_tasks

    run = tmp_path / "run"
    cfg = TrainConfig(data=debug_store.path, out=run, method="bpp", steps=1, batch_size=4, workers=0, warmup_steps=1)
    train(cfg, config("bpp"), progress=False)
    asked = []
    generate = draw_dataset.generate
    monkeypatch.setattr(draw_dataset, "generate", lambda *a, **k: asked.append(a[2]) or generate(*a, **k))
    resolve_tasks("human", Checkpoint.load(run), data_dir=tmp_path / "data", workers=workers)
    assert asked == [workers]


@pytest.mark.parametrize("rows", [1, 17])
def test_a_grid_s_title_clears_its_first_row_of_captions(rows, tmp_path, monkeypatch):
    import bpp.media as media

    kept = {}
    monkeypatch.setattr(media, "save_figure", lambda fig, path, dpi: kept.setdefault("fig", fig) and path)
    image = np.full((32, 32, 3), 200, np.uint8)
    captions = [f"drawing {i}\nboard +12°: 18.84 px" for i in range(6 * rows)]
    media.contact_sheet([image] * len(captions), captions, tmp_path / "grid.png", columns=6, title="a report's title")
    fig = kept["fig"]
    renderer = fig.canvas.get_renderer()
    title = fig._suptitle.get_window_extent(renderer)
    first_row = [ax.title.get_window_extent(renderer) for ax in fig.axes[:6]]
    assert all(title.y0 > caption.y1 for caption in first_row)  # display coordinates: y grows upwards
    assert title.y1 <= fig.bbox.y1  # and it is on the page
