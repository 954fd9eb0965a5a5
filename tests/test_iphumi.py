"""iPhUMI recordings on the workstation: synthetic app-format exports with known ground truth become stores whose
poses, widths and actions match the truth; every stage's failure names the recording and the reason; processing
resumes; bimanual and depth recordings keep their extra streams; and one recording becomes the live prompt of a
served policy."""

from __future__ import annotations

import errno
import json
import os
import re
import shutil
from collections import namedtuple
from pathlib import Path

import numpy as np
import pytest

from bpp.cli import main
from bpp.core.poses import (
    integrate_actions,
    interpolate_poses,
    invert,
    make_pose,
    matrix_from_rot6d,
    relative_actions,
    rot6d_from_matrix,
    rotation_angle,
    vector_to_pose,
)
from bpp.errors import UserError
from helpers import import_optional

pytestmark = pytest.mark.iphumi
import_optional("cv2", "iphumi")

from bpp.benchmarks.iphumi import pipeline  # noqa: E402
from bpp.benchmarks.iphumi.align import MOUNTS, Aligned, Limits, check_demonstration, load_mounts  # noqa: E402
from bpp.benchmarks.iphumi.process import ProcessSettings  # noqa: E402
from bpp.benchmarks.iphumi.recording import (  # noqa: E402
    Demonstration,
    RecordingError,
    find_recordings,
    group_demonstrations,
    read_recording,
    scan_export,
)
from bpp.benchmarks.iphumi.synthetic import SyntheticSettings, write_export  # noqa: E402
from bpp.data.store import EpisodeStore  # noqa: E402

imageio_ffmpeg = import_optional("imageio_ffmpeg", "iphumi")


@pytest.fixture(scope="module", autouse=True)
def calibration_cache(tmp_path_factory):
    """Gripper calibrations are cached on disk: here, in a folder of this module's own."""
    folder = tmp_path_factory.mktemp("cache")
    before = os.environ.get("BPP_CACHE")
    os.environ["BPP_CACHE"] = str(folder)
    yield folder / "iphumi"
    if before is None:
        del os.environ["BPP_CACHE"]
    else:
        os.environ["BPP_CACHE"] = before


@pytest.fixture(scope="module")
def export(tmp_path_factory):
    """Three single-gripper demonstrations of two labelled tasks each (two drawings in all), and the calibration."""
    out = tmp_path_factory.mktemp("iphumi") / "export"
    truths = write_export(out, SyntheticSettings(demonstrations=3, tasks=2, tasks_per_demonstration=2, seed=3))
    return out, truths


@pytest.fixture(scope="module")
def processed(export, tmp_path_factory):
    """The export processed by the command line, one episode per task of each demonstration held out."""
    out = tmp_path_factory.mktemp("iphumi-store") / "store.zarr"
    main(["iphumi", "process", str(export[0]), "--out", str(out), "--holdout-episodes", "1", "--workers", "1"])
    return EpisodeStore(out), EpisodeStore(out.with_name("store-heldout.zarr"))


def _truth_steps(truth, store: EpisodeStore, episode: int):
    """The ground-truth TCP poses and widths at an episode's steps, from the synthetic motion itself."""
    n = store.episode_slice(episode).stop - store.episode_slice(episode).start
    start = float(store.column("start_s")[episode])
    return truth.motion(truth.times[0] + start + np.arange(n) / store.config["fps"])


def test_processed_poses_widths_and_actions_match_the_ground_truth(export, processed):
    _, truths = export
    store, held = processed
    position_mm, angle_deg, width_mm = [], [], []
    for part in (store, held):
        for episode in range(part.num_episodes):
            name = part.config["demonstrations"][episode] + "_right"
            truth = truths[name]
            tcp, width = _truth_steps(truth, part, episode)
            expected = invert(tcp[0]) @ tcp
            got = part.episode(episode, ["pose", "width", "action"])
            pose = vector_to_pose(got["pose"].astype(np.float64))
            position_mm.append(np.linalg.norm(pose[:, :3, 3] - expected[:, :3, 3], axis=1) * 1e3)
            angle_deg.append(np.rad2deg(rotation_angle(pose[:, :3, :3], expected[:, :3, :3])))
            width_mm.append(np.abs(got["width"][:, 0] - width) * 1e3)
            # the actions move each pose to the next one, in the gripper's own frame
            replayed = integrate_actions(pose[0], got["action"][:-1, :9].astype(np.float64))
            np.testing.assert_allclose(replayed[:, :3, 3], pose[:, :3, 3], atol=1e-5)
            np.testing.assert_allclose(got["action"][:-1, 9], got["width"][1:, 0], atol=1e-7)
    position_mm, angle_deg, width_mm = map(np.concatenate, (position_mm, angle_deg, width_mm))
    # what is left is the interpolation between logged samples at the path's corners
    assert position_mm.max() < 0.2, position_mm.max()
    assert angle_deg.max() < 0.05, angle_deg.max()
    assert np.median(width_mm) < 1.0 and np.percentile(width_mm, 95) < 3.0, np.percentile(width_mm, [50, 95, 100])


def test_task_labels_cut_one_episode_per_segment_and_hold_out_the_last(processed):
    store, held = processed
    assert sorted(t["instruction"] for t in store.tasks) == ["draw task 0", "draw task 1"]
    assert store.num_episodes + held.num_episodes == 6  # three demonstrations, two labelled segments each
    assert held.num_episodes == 2 and {t["instruction"] for t in held.tasks} == {"draw task 0", "draw task 1"}
    assert store.benchmark == "iphumi" and set(store.keys) == {"pose", "width", "rgb", "action"}
    assert store["rgb"].shape[1:] == (96, 96, 3)
    frame = store["rgb"][0]
    assert frame[:10].max() == 0 and frame[48].max() > 0  # 4:3 letterboxed: black bars above and below


def test_processing_resumes_without_redoing_finished_demonstrations(export, processed, tmp_path, monkeypatch):
    store, _ = processed
    parts = pipeline.parts_folder(Path(store.path), ProcessSettings())
    assert len(list(parts.glob("*.json"))) == 3

    def refuse(*args):
        raise AssertionError("a finished demonstration was processed again")

    monkeypatch.setattr(pipeline, "_process", refuse)
    again, held, rejected = pipeline.process_export(
        export[0], Path(store.path), workers=1, overwrite=True, holdout_episodes=1, progress=False
    )
    assert rejected == [] and again.num_episodes == store.num_episodes
    np.testing.assert_array_equal(again["pose"][:], store["pose"][:])


def test_a_calibration_is_measured_once_and_read_back_from_the_cache(export, processed, calibration_cache, monkeypatch):
    from bpp.benchmarks.iphumi import gripper, process

    assert len(list(calibration_cache.glob("*.json"))) == 1  # three demonstrations, one calibration recording

    def refuse(*args):
        raise AssertionError("the calibration was measured again")

    monkeypatch.setattr(gripper, "calibrate", refuse)
    recording = next(f for f in find_recordings(export[0]) if "demonstration" in f.name)
    episode = pipeline.process_one(recording, ProcessSettings())  # a new process would find it the same way
    assert len(episode["steps"]["width"]) > 10
    assert process.calibration_cache() == calibration_cache


def _copy(export: Path, tmp_path: Path) -> Path:
    copy = tmp_path / "export"
    shutil.copytree(export, copy)
    return copy


def _edit(folder: Path, **changes) -> None:
    path = folder / f"{folder.name}.json"
    meta = json.loads(path.read_text())
    meta.update(changes)
    path.write_text(json.dumps(meta))


def test_bad_recordings_are_left_out_with_their_reasons_and_nothing_half_written(export, tmp_path):
    copy = _copy(export[0], tmp_path)
    demos = [f for f in find_recordings(copy) if "demonstration" in f.name]
    rgb = demos[0] / f"{demos[0].name}_rgb.mp4"
    rgb.write_bytes(rgb.read_bytes()[:2000])  # a truncated video
    meta = json.loads((demos[1] / f"{demos[1].name}.json").read_text())
    times = meta["poseTimes"]
    _edit(demos[1], poseTimes=times[:5] + [times[3]] + times[6:])  # a clock that went back
    _edit(demos[2], poseTransforms=[m[:3] for m in meta["poseTransforms"]])  # 3x4 matrices
    out = tmp_path / "store.zarr"
    with pytest.raises(UserError, match="every demonstration was rejected") as err:
        pipeline.process_export(copy, out, workers=2, progress=False)  # workers spawned after OpenCV ran here
    text = str(err.value)
    assert "cannot decode the video" in text or "truncated" in text
    assert "poseTimes is not strictly increasing" in text and "poseTransforms must be" in text
    assert not out.exists() and not list(tmp_path.glob("*.partial*"))


@pytest.mark.parametrize(
    "damage, reason",
    [
        (lambda f, m: _edit(f, poseTimes=m["poseTimes"][:-1]), "poseTransforms must be"),
        (lambda f, m: _edit(f, rgbTimes=["yesterday"] + m["rgbTimes"][1:]), "rgbTimes\\[0\\] = 'yesterday'"),
        (lambda f, m: _edit(f, mainCameraIntrinsics=[[1, 0, 0], [0, 1, 0]]), "mainCameraIntrinsics must be"),
        (lambda f, m: _edit(f, taskNames=["a"], taskStartTimestamps=[], taskEndTimestamps=[]), "one entry per label"),
        (lambda f, m: (f / f"{f.name}_ultrawidergb.mp4").unlink(), "missing .*_ultrawidergb.mp4"),
        (lambda f, m: _edit(f, side="left"), "contradicts the folder name"),
    ],
)
def test_each_kind_of_damaged_recording_is_named_with_its_problem(export, tmp_path, damage, reason):
    copy = _copy(export[0], tmp_path)
    folder = next(f for f in find_recordings(copy) if "demonstration" in f.name)
    damage(folder, json.loads((folder / f"{folder.name}.json").read_text()))
    with pytest.raises(RecordingError, match=reason) as err:
        read_recording(folder)
    assert folder.name in str(err.value)


def test_missing_sides_and_calibration_runs_are_reasons_too(export, tmp_path):
    copy = _copy(export[0], tmp_path)
    demos = [f for f in find_recordings(copy) if "demonstration" in f.name]
    _edit(demos[0], sidesPresent=["right", "left"])
    for calibration in [f for f in find_recordings(copy) if "grippercalibration" in f.name]:
        shutil.rmtree(calibration)
    valid, invalid = group_demonstrations([read_recording(f) for f in find_recordings(copy)])
    assert invalid == [(demos[0].name.rsplit("_", 1)[0], "the side(s) left listed in sidesPresent have no recording")]
    with pytest.raises(UserError, match="calibration run .* is not among the recordings"):
        pipeline.process_export(copy, tmp_path / "store.zarr", workers=1, progress=False)
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(UserError, match="no iPhUMI recordings"):
        pipeline.process_export(empty, tmp_path / "x.zarr", progress=False)
    with pytest.raises(RecordingError, match="not an iPhUMI recording folder name"):
        read_recording(empty)


def _rename(folder: Path, name: str) -> Path:
    """A recording folder renamed, its files with it (as the app would have named them)."""
    target = folder.rename(folder.with_name(name))
    for path in target.iterdir():
        path.rename(target / path.name.replace(folder.name, name))
    return target


def _keep(export: Path, count: int) -> list[Path]:
    """The first `count` demonstration recordings of a copied export, the others deleted (for speed)."""
    demos = [f for f in find_recordings(export) if "demonstration" in f.name]
    for folder in demos[count:]:
        shutil.rmtree(folder)
    return demos[:count]


def _matches_truth(store: EpisodeStore, truths: dict, names: dict[str, str]) -> None:
    """Every episode's poses are those of its own demonstration's ground truth (`names`: group -> truth's name)."""
    for episode in range(store.num_episodes):
        tcp, _ = _truth_steps(truths[names[store.config["demonstrations"][episode]]], store, episode)
        pose = vector_to_pose(store.episode(episode, ["pose"])["pose"].astype(np.float64))
        np.testing.assert_allclose(pose[:, :3, 3], (invert(tcp[0]) @ tcp)[:, :3, 3], atol=1e-3)


def test_demonstrations_starting_in_the_same_second_are_both_kept(export, tmp_path):
    copy = _copy(export[0], tmp_path)
    first, second = _keep(copy, 2)
    start = first.name.split("_")[0]  # e.g. 2026-01-15T09-00-25.000Z
    renamed = _rename(second, f"{start.split('.')[0]}.500Z_" + second.name.split("_", 1)[1])
    store, _, rejected = pipeline.process_export(copy, tmp_path / "store.zarr", workers=1, progress=False)
    groups = {first.name.rsplit("_", 1)[0]: first.name, renamed.name.rsplit("_", 1)[0]: second.name}
    assert rejected == [] and store.num_episodes == 4 and set(store.config["demonstrations"]) == set(groups)
    _matches_truth(store, export[1], groups)  # each episode is its own demonstration's, none the other's


def test_two_recordings_of_one_name_are_refused_naming_both(export, tmp_path):
    copy = _copy(export[0], tmp_path)
    demo = _keep(copy, 1)[0]
    twin = copy / "2026-01-16" / demo.name
    shutil.copytree(demo, twin)
    _edit(twin, taskNames=["another task", "and another"])
    with pytest.raises(UserError, match=f"two recordings are named {demo.name}") as err:
        pipeline.process_export(copy, tmp_path / "store.zarr", workers=1, progress=False)
    assert str(demo) in str(err.value) and str(twin) in str(err.value)
    assert not (tmp_path / ".store.zarr.parts").exists()
    with pytest.raises(RecordingError, match="two recordings are named"):
        pipeline.process_one(demo, ProcessSettings(), export=copy)


def test_folders_left_out_are_named_with_the_reason_and_counted(export, tmp_path, capsys):
    copy = _copy(export[0], tmp_path)
    no_json, misnamed, kept = _keep(copy, 3)
    (no_json / f"{no_json.name}.json").unlink()
    misnamed = misnamed.rename(misnamed.with_name("my demo"))
    found, left_out = scan_export(copy)
    assert kept in found and no_json not in found
    assert [f for f, _ in left_out] == [no_json, misnamed]
    out = tmp_path / "store.zarr"
    main(["iphumi", "process", str(copy), "--out", str(out), "--workers", "1"])
    printed = capsys.readouterr()
    for folder, reason in [(no_json, f"missing {no_json.name}.json"), (misnamed, "not an iPhUMI recording folder")]:
        name = folder.relative_to(copy).as_posix()
        assert f"warning: leaving out {name}: {reason}" in printed.err
        assert f"  {name}: {reason}" in printed.out
    assert "left out 2 recording(s) or demonstration(s)" in printed.out
    assert len(EpisodeStore(out).config["rejected"]) == 2


def test_demonstrations_the_settings_leave_out_are_named_before_any_work(export, tmp_path, capsys):
    copy = _copy(export[0], tmp_path)
    demos = [f for f in find_recordings(copy) if "demonstration" in f.name]
    _edit(demos[0], isErrorCorrection=True)
    kept, _, rejected = pipeline.gather(copy, ProcessSettings(include_error_correction=False))
    group = demos[0].name.rsplit("_", 1)[0]
    assert len(kept) == 2 and rejected == [
        (group, "marked as an error correction (left out by --no-include-error-correction)")
    ]
    assert f"warning: leaving out {group}: marked as an error correction" in capsys.readouterr().err
    with pytest.raises(
        UserError, match="no usable demonstration.*asks for depth, which its right phone did not record"
    ):
        pipeline.gather(copy, ProcessSettings(cameras=("rgb", "depth")))


def test_a_changed_recording_is_processed_again_not_taken_from_the_kept_parts(export, tmp_path):
    copy = _copy(export[0], tmp_path)
    demo = _keep(copy, 1)[0]
    out = tmp_path / "store.zarr"
    before, _, _ = pipeline.process_export(copy, out, workers=1, progress=False)
    poses = before["pose"][:]
    meta = json.loads((demo / f"{demo.name}.json").read_text())
    moved = np.asarray(meta["poseTransforms"]).reshape(-1, 4, 4)
    moved[:, 0, 3] += np.linspace(0.0, 0.26, len(moved))  # a slow drift, 0.26 m in all
    _edit(demo, taskNames=["corrected label", *meta["taskNames"][1:]], poseTransforms=moved.tolist())
    after, _, _ = pipeline.process_export(copy, out, workers=1, overwrite=True, progress=False)
    assert "corrected label" in {t["instruction"] for t in after.tasks}
    assert np.abs(after["pose"][:] - poses).max() > 0.05
    # a new calibration recording changes the key too; the same files keep it
    demonstration = group_demonstrations([read_recording(demo)])[0][0]
    index = {f.name: f for f in find_recordings(copy)}
    key = pipeline.part_key(demonstration, index, ProcessSettings())
    assert pipeline.part_key(demonstration, index, ProcessSettings()) == key
    calibration = index[demonstration.phones["right"].calibration_name]
    _edit(calibration, gripperID="another gripper")
    assert pipeline.part_key(demonstration, index, ProcessSettings()) != key


def _pair(demo: Path, side: str) -> Path:
    """A second phone for a recorded demonstration: its recording copied as `side`, both listing both sides."""
    phone = demo.with_name(demo.name.rsplit("_", 1)[0] + f"_{side}")
    shutil.copytree(demo, phone)
    for path in phone.iterdir():
        path.rename(phone / path.name.replace(demo.name, phone.name))
    _edit(phone, side=side, sidesPresent=["right", side])
    _edit(demo, sidesPresent=["right", side])
    return phone


@pytest.mark.parametrize(
    "side, kinds", [("left", "bimanual and single-arm"), ("head", "single-arm and single-arm with")]
)
def test_an_export_mixing_kinds_of_demonstration_is_refused_before_any_work(export, tmp_path, monkeypatch, side, kinds):
    copy = _copy(export[0], tmp_path)
    demos = _keep(copy, 2)
    _pair(demos[0], side)

    def refuse(*args):
        raise AssertionError("a demonstration was processed before the refusal")

    monkeypatch.setattr(pipeline, "_process", refuse)
    with pytest.raises(UserError, match=f"mix {kinds}") as err:
        pipeline.process_export(copy, tmp_path / "store.zarr", workers=1, progress=False)
    mixed, single = (d.name.rsplit("_", 1)[0] for d in demos)
    assert f"(1): {mixed}" in str(err.value) and f"single-arm (1): {single}" in str(err.value)
    assert not (tmp_path / ".store.zarr.parts").exists()


def test_an_existing_held_out_store_is_refused_before_any_work(export, tmp_path, monkeypatch):
    monkeypatch.setattr(pipeline, "_process", lambda *args: pytest.fail("processed before the refusal"))
    (tmp_path / "store-heldout.zarr").mkdir()
    with pytest.raises(UserError, match="store-heldout.zarr exists; pass --overwrite"):
        pipeline.process_export(export[0], tmp_path / "store.zarr", workers=1, holdout_episodes=1, progress=False)


@pytest.mark.parametrize(
    "settings, message",
    [
        (dict(main_size=(0, 0)), "main_size must be a width and a height, even numbers of pixels in \\[16, 4096\\]"),
        (dict(main_size=(-4, 120)), "main_size must be"),
        (dict(main_size=(161, 121)), "main_size must be"),
        (dict(main_size=(8192, 8192)), "main_size must be"),
        (dict(seed=-1), "seed must be >= 0"),
        (dict(session="lab/one"), "session must be a name of letters"),
        (dict(demonstrations=0), "demonstrations must be >= 1"),
    ],
)
def test_synthetic_settings_it_cannot_write_are_refused(settings, message):
    with pytest.raises(UserError, match=message):
        SyntheticSettings(**settings)


def test_synth_refuses_sizes_on_the_command_line_and_folders_that_hold_recordings(tmp_path, capsys):
    with pytest.raises(SystemExit):
        main(["iphumi", "synth", str(tmp_path / "a"), "--main-size", "0", "0"])
    assert "main_size must be" in capsys.readouterr().err and not (tmp_path / "a").exists()
    earlier = tmp_path / "b" / "2026-01-15T09-00-25.000Z_12345_lab_demonstration_right"
    earlier.mkdir(parents=True)
    (earlier / f"{earlier.name}.json").write_text("{}")
    with pytest.raises(UserError, match="already holds 1 iPhUMI recording"):
        write_export(tmp_path / "b", SyntheticSettings(demonstrations=1))
    assert (earlier / f"{earlier.name}.json").read_text() == "{}" and len(list((tmp_path / "b").iterdir())) == 1


def test_synth_and_process_on_a_full_disk_name_what_they_wrote_and_leave_nothing_half_written(
    export, tmp_path, monkeypatch, capsys
):
    real_writer = imageio_ffmpeg.write_frames

    def writer_that_breaks(*args, **kwargs):
        frames = real_writer(*args, **kwargs)
        frames.send(None)
        for _ in range(3):
            yield
            raise BrokenPipeError(errno.EPIPE, "Broken pipe")  # FFmpeg died on the full disk
        yield

    usage = namedtuple("usage", "total used free")
    monkeypatch.setattr(imageio_ffmpeg, "write_frames", writer_that_breaks)
    monkeypatch.setattr(shutil, "disk_usage", lambda path: usage(10**9, 10**9, 4096))
    with pytest.raises(SystemExit) as stop:
        main(["iphumi", "synth", str(tmp_path / "synth"), "--demonstrations", "1"])
    assert re.fullmatch(r"bpp iphumi synth: error: .*synth/2026-01-15: No space left on device", stop.value.code)
    assert list((tmp_path / "synth").iterdir()) == []  # no half-written day folder
    monkeypatch.undo()

    def no_space(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")  # as zipfile reports it: no file named

    monkeypatch.setattr(pipeline.np, "savez", no_space)
    out = tmp_path / "store.zarr"
    with pytest.raises(SystemExit) as stop:
        main(["iphumi", "process", str(export[0]), "--out", str(out), "--workers", "1"])
    assert re.fullmatch(r"bpp iphumi process: error: .*\.npz: No space left on device", stop.value.code)
    assert not out.exists() and not [p for p in tmp_path.rglob("*") if "partial" in p.name or ".tmp-" in p.name]


@pytest.mark.parametrize(
    "limits, message",
    [
        (Limits(max_speed=float("nan")), "limits.max_speed must be > 0"),
        (Limits(max_speed=-1.0), "limits.max_speed must be > 0"),
        (Limits(max_gripper_offset=(1.0, 0.0, 0.5)), "limits.max_gripper_offset must be three distances"),
        (Limits(max_relative_rotation_deg=0.0), "limits.max_relative_rotation_deg must be in"),
        (Limits(max_head_distance=float("nan")), "limits.max_head_distance must be > 0"),
    ],
)
def test_processing_limits_that_would_reject_everything_or_nothing_are_refused(limits, message):
    with pytest.raises(UserError, match=message):
        ProcessSettings(limits=limits)


def test_dropped_frames_read_the_last_frame_and_a_truncated_video_is_refused(tmp_path):
    from bpp.benchmarks.iphumi.video import read_frames, write_video

    frames = [np.full((24, 32, 3), 10 * i, np.uint8) for i in range(20)]
    path = tmp_path / "v.mp4"
    write_video(path, frames, 10, (32, 24))
    got, beyond = read_frames(path, [0, 19, 20], logged=21)  # one logged time whose frame the encoder dropped
    assert beyond == 1 and got.shape == (3, 24, 32, 3)
    np.testing.assert_allclose(got[2].astype(float), got[1].astype(float))  # the last decoded frame stands in
    assert abs(float(got[1].mean()) - 190) < 3 and abs(float(got[0].mean()) - 0) < 3
    with pytest.raises(RecordingError, match="20 frames decoded for 40 logged frame times; the video is truncated"):
        read_frames(path, [39], logged=40)
    small, _ = read_frames(path, [5], logged=20, fit=16)
    assert small.shape == (1, 12, 16, 3)  # scaled to fit 16x16, the aspect kept


def test_implausible_motion_and_flipped_sides_are_rejected_with_the_reason():
    n = 30
    times = np.arange(n) / 60.0
    poses = np.repeat(np.eye(4)[None], n, axis=0)
    jumped = poses.copy()
    jumped[15:, 0, 3] += 0.2  # 20 cm in one frame: 12 m/s
    single = Aligned(Demonstration("d", {}), times, tcp={"right": jumped}, camera={"right": jumped})
    assert any("moves at 12.0 m/s" in r for r in check_demonstration(single))
    right = poses.copy()
    right[:, 0, 3] = -0.3  # the right phone to the left of the left one
    flipped = Aligned(
        Demonstration("d", {}), times, tcp={"right": right, "left": poses}, camera={"right": right, "left": poses}
    )
    assert any("sides flipped" in r for r in check_demonstration(flipped))
    right[:, 0, 3] = 0.3
    assert check_demonstration(flipped) == []


def test_rotations_are_interpolated_on_the_rotation_group():
    from scipy.spatial.transform import Rotation

    times = np.array([0.0, 1.0])
    rotations = Rotation.from_rotvec([[0, 0, 0], [0, 0, 2.5]]).as_matrix()  # 143 degrees about z
    poses = make_pose(rotations, np.zeros((2, 3)))
    middle = interpolate_poses(times, poses, np.array([0.5]))[0, :3, :3]
    np.testing.assert_allclose(middle, Rotation.from_rotvec([0, 0, 1.25]).as_matrix(), atol=1e-12)
    componentwise = (rotations[0] + rotations[1]) / 2
    assert abs(np.linalg.det(componentwise) - 1) > 0.3  # what per-entry interpolation would give: not a rotation


def test_pose_vectors_and_relative_actions_round_trip():
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(0)
    poses = make_pose(Rotation.random(20, random_state=1).as_matrix(), rng.normal(size=(20, 3)))
    np.testing.assert_allclose(matrix_from_rot6d(rot6d_from_matrix(poses[:, :3, :3])), poses[:, :3, :3], atol=1e-12)
    actions = relative_actions(poses)
    np.testing.assert_allclose(integrate_actions(poses[0], actions[:-1]), poses, atol=1e-9)
    moved = make_pose(Rotation.random(random_state=2).as_matrix(), [1.0, 2.0, 3.0]) @ poses
    np.testing.assert_allclose(relative_actions(moved), actions, atol=1e-9)  # whatever the world frame


def test_the_iphone_15_pro_mount_and_mount_files(tmp_path):
    mount = MOUNTS["iPhone16,1"]
    expected = [[1, 0, 0], [0, -0.9659258, 0.25881904], [0, -0.25881904, -0.9659258]]
    np.testing.assert_allclose(mount[:3, :3], expected, atol=1e-7)
    np.testing.assert_allclose(mount[:3, 3], [0.0, -0.06441, -0.211397])
    path = tmp_path / "mounts.json"
    path.write_text(json.dumps({"iPhone17,1": {"rotation": np.eye(3).tolist(), "translation": [0, 0, -0.2]}}))
    assert set(load_mounts(path)) == {"iPhone16,1", "iPhone17,1"}
    path.write_text(json.dumps({"iPhone17,1": {"rotation": (2 * np.eye(3)).tolist(), "translation": [0, 0, 0]}}))
    with pytest.raises(RecordingError, match="not a proper rotation"):
        load_mounts(path)
    path.write_text(json.dumps({"iPhone17,1": {"rotation": np.eye(3).tolist()}}))
    with pytest.raises(RecordingError, match="needs 'rotation'"):
        load_mounts(path)


@pytest.mark.slow
def test_bimanual_head_and_depth_recordings_keep_every_stream(tmp_path):
    export = tmp_path / "export"
    write_export(export, SyntheticSettings(demonstrations=1, bimanual=True, head=True, depth=True, seed=5))
    settings = ProcessSettings(cameras=("rgb", "depth"), image_size=32)
    store, _, rejected = pipeline.process_export(export, tmp_path / "s.zarr", settings, workers=1, progress=False)
    assert rejected == []
    assert set(store.keys) == {
        "pose", "width", "rgb", "depth", "arm1_pose", "arm1_width", "arm1_rgb", "arm1_depth", "head_rgb", "action"
    }  # fmt: skip
    assert store["action"].shape[1] == 20 and store["depth"].shape[1:] == (32, 32, 1)
    # the left gripper traced the same path 35 cm to the left: its pose in the right one's starting frame says so
    np.testing.assert_allclose(store["arm1_pose"][0][:3], [-0.35, 0.0, 0.0], atol=1e-3)
    left_width = store["arm1_width"][:, 0]
    np.testing.assert_allclose(left_width, store["width"][:, 0], atol=2e-3)  # tags 6/7 read like tags 0/1


@pytest.mark.serve
@pytest.mark.slow
def test_one_recording_becomes_the_prompt_of_a_served_policy(export, processed, tmp_path):
    import_optional("websockets", "serve")
    from bpp.benchmarks.iphumi.prompt import hand_off
    from bpp.serve.client import PolicyClient
    from bpp.serve.command import build_server
    from bpp.serve.server import ServerLimits, ServerThread

    store, _ = processed
    run = tmp_path / "run"
    main(["train", "--method", "bpp", "--preset", "debug", "--obs", "state", "--data", str(store.path)]
         + ["--out", str(run), "--steps", "2", "--batch-size", "4", "--workers", "0"])  # fmt: skip
    recording = next(f for f in find_recordings(export[0]) if "demonstration" in f.name)
    with ServerThread(build_server(run, str(store.path))) as url:
        result = hand_off(recording, url)
        assert result.handle.startswith("upload:") and result.first_action.shape == (10,)
        assert result.task == recording.name.split("_")[2]  # two labels: the whole demonstration, named by session
        robot = PolicyClient(url)
        first = {"pose": np.zeros(9, np.float32), "width": np.zeros(1, np.float32)}
        first["pose"][3], first["pose"][7] = 1.0, 1.0
        reply = robot.infer({**first, "prompt": "upload:latest"})
        assert reply["prompt"] == result.handle
        again = hand_off(recording, url, check=False)
        assert again.handle == result.handle  # the same demonstration, the same prompt
        robot.close()
    # open-loop evaluation on the processed store, as for any recorded dataset
    evaluation = tmp_path / "eval"
    main(["eval", str(run), "--tasks", str(store.path), "--rollouts", "1", "--workers", "1", "--out", str(evaluation)])
    results = json.loads((evaluation / "results.json").read_text())
    assert results["metric"]["name"] == "action error" and results["summary"]["tasks"] == 2
    with ServerThread(build_server(run, str(store.path), token="secret")) as url:
        with pytest.raises(UserError, match="refused the connection"):
            hand_off(recording, url, check=False)
        assert hand_off(recording, url, token="secret", check=False).handle == result.handle
    small = ServerLimits(max_message_bytes=4096)
    with ServerThread(build_server(run, str(store.path), limits=small)) as url, pytest.raises(UserError) as err:
        hand_off(recording, url)
    assert "KiB, over the 4 KiB a message to this server may have" in str(err.value)


def test_a_demonstration_whose_phone_never_sees_the_canvas_is_refused_naming_what_to_do(export):
    folder = next(f for f in find_recordings(export[0]) if "demonstration" in f.name)
    with pytest.raises(RecordingError, match="shows the canvas's four red markers.*hold the phone still above"):
        pipeline.process_one(folder, ProcessSettings(canvas=True))
    with pytest.raises(UserError, match="canvas.*without --bimanual"):
        SyntheticSettings(canvas=True, bimanual=True, main_size=(320, 240))
    with pytest.raises(UserError, match="at least 320x240"):
        SyntheticSettings(canvas=True)
