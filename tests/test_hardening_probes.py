"""The command line given bad inputs, as a careful user or an attacker would give them.

Each case in the tables below runs one ``bpp`` command in this process on a small store and a 2-step debug run,
with inputs it prepares in its own folder. A refused command must exit non-zero with one line (no traceback) that
names the input it refuses, and must leave every file it was given as it was and write nothing. The tests after the
tables are inputs that must be handled, each with a check of its result. What a library function refuses is tested
in test_hardening.py; here, that the command line turns it into a clean refusal.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from bpp.cli import main

V = [[[0.2, 0.2], [0.5, 0.8], [0.8, 0.2]]]
"""A drawing's strokes: one V."""
RUN = ["--preset", "debug", "--steps", "2", "--save-every", "1", "--workers", "0"]
"""How the shared run is trained (a resume repeats these flags)."""
QUICK = ["--rollouts", "1", "--max-steps", "8", "--workers", "1", "--videos", "1"]
"""The shortest evaluation that still writes a video."""


@dataclass(frozen=True)
class Inputs:
    """What a case prepares its command from: the shared store and run (never changed) and its own folder."""

    store: Path
    run: Path
    tmp: Path

    def copy_run(self, name: str = "run") -> Path:
        target = self.tmp / name
        shutil.copytree(self.run, target)
        return target

    def copy_store(self, name: str = "store.zarr") -> Path:
        target = self.tmp / name
        shutil.copytree(self.store, target)
        return target

    def text(self, name: str, text: str | bytes) -> Path:
        path = self.tmp / name
        path.parent.mkdir(parents=True, exist_ok=True)
        if isinstance(text, bytes):
            path.write_bytes(text)
        else:
            path.write_text(text)
        return path

    def drawing(self, name: str, strokes, drawing_id: str = "d") -> Path:
        return self.text(name, json.dumps({"drawings": [{"id": drawing_id, "strokes": strokes}]}))


@pytest.fixture(scope="module")
def shared(debug_store, tmp_path_factory) -> tuple[Path, Path]:
    """The debug store and a 2-step debug run trained on it, with checkpoints at steps 1 and 2."""
    run = tmp_path_factory.mktemp("probes") / "run"
    main(["train", "--data", str(debug_store.path), "--out", str(run), *RUN])
    return debug_store.path, run


@pytest.fixture
def inputs(shared, tmp_path) -> Inputs:
    return Inputs(*shared, tmp_path / "case")


def refused(argv: list[str], capsys) -> str:
    """Runs ``bpp argv``, which must refuse; returns its message after checking that it is a clean refusal."""
    capsys.readouterr()
    with pytest.raises(SystemExit) as stop:
        main(argv)
    err = capsys.readouterr().err
    code = stop.value.code
    assert code not in (0, None), f"exit status 0 for a bad input; stderr: {err[-1000:]}"
    message = code if isinstance(code, str) else err  # the CLI's own errors exit with their line; tyro's print first
    assert "Traceback" not in message + err, message + err
    if isinstance(code, str):
        assert message.startswith("bpp ") and "\n" not in message.strip(), message
    return message


def snapshot(folder: Path) -> dict[str, tuple[int, int]]:
    """Every path under `folder` with its size and modification time."""
    return {str(p.relative_to(folder)): (p.stat().st_size, p.stat().st_mtime_ns) for p in sorted(folder.rglob("*"))}


def _newest(run: Path) -> Path:
    return run / "checkpoints" / (run / "checkpoints" / "last").read_text().strip()


def _truncate(path: Path) -> None:
    path.write_bytes(path.read_bytes()[:1000])


def _svg(body: str) -> str:
    return f'<svg xmlns="http://www.w3.org/2000/svg" viewBox="0 0 200 200">{body}</svg>'


def _laughs() -> str:
    """An SVG whose entities expand to 10**9 characters."""
    entities = '<!ENTITY l0 "ha">' + "".join(f'<!ENTITY l{i} "{("&l" + str(i - 1) + ";") * 10}">' for i in range(1, 10))
    return f'<?xml version="1.0"?><!DOCTYPE svg [{entities}]><svg xmlns="http://www.w3.org/2000/svg"><text>&l9;</text></svg>'


def _eval(i: Inputs, *flags: str) -> list[str]:
    return ["eval", str(i.run), *flags, "--out", str(i.tmp / "eval")]


def _eval_of(run: Path, i: Inputs) -> list[str]:
    """A quick evaluation of `run` on one task of the store."""
    return ["eval", str(run), "--tasks", str(i.store), "--num-tasks", "1", *QUICK, "--out", str(i.tmp / "eval")]


def _train(i: Inputs, *flags: str, data: Path | None = None) -> list[str]:
    return ["train", "--data", str(data or i.store), "--out", str(i.tmp / "new-run"), "--preset", "debug", *flags]


def _resume(i: Inputs, *flags: str) -> list[str]:
    return ["train", "--data", str(i.store), "--out", str(i.copy_run()), *RUN, "--resume", *flags]


def _generate(i: Inputs, *flags: str) -> list[str]:
    return ["draw", "generate", "--preset", "debug", *flags, "--out", str(i.tmp / "new.zarr")]


def _generate_from(path: Path) -> list[str]:
    """Generates a store from the drawing file `path`."""
    return ["draw", "generate", "--source", "files", "--drawings", str(path), "--out", str(path.parent / "new.zarr")]


def _damaged_store(damage: Callable[[Path], None], command: str) -> Callable[[Inputs], list[str]]:
    def argv(i: Inputs) -> list[str]:
        store = i.copy_store("damaged.zarr")
        damage(store)
        if command == "eval":
            return _eval(i, "--tasks", str(store), *QUICK)
        if command == "sheet":
            return ["draw", "sheet", str(store), "--out", str(i.tmp / "sheet.png")]
        return _train(i, "--steps", "1", data=store)

    return argv


def _truncated_chunk(store: Path) -> None:
    part = next(p for p in sorted((store / "data" / "action" / "c").rglob("*")) if p.is_file())
    part.write_bytes(part.read_bytes()[:20])


def _copy_chunk(source: Path, array: Path) -> None:
    """Put chunk (0, 0) of array `source` in the place of `array`'s."""
    shutil.copyfile(source / "c" / "0" / "0", array / "c" / "0" / "0")


def _broken_header(store: Path) -> None:
    (store / "zarr.json").write_text('{"zarr_format": 3, "node_type": "group", "attributes": {')


def _flip_a_bit(file: Path) -> None:
    data = bytearray(file.read_bytes())
    data[len(data) // 2] ^= 0x10
    file.write_bytes(bytes(data))


def _header(store: Path, **changes) -> None:
    """Sets entries of the store's zarr.json (an entry of attributes if its name is not zarr.json's own)."""
    doc = json.loads((store / "zarr.json").read_text())
    for key, value in changes.items():
        (doc if key in doc else doc["attributes"])[key] = value
    (store / "zarr.json").write_text(json.dumps(doc))


def _merge(i: Inputs, *stores: Path, out: Path | None = None) -> list[str]:
    return ["store", "merge", *map(str, stores), "--out", str(out or i.tmp / "merged.zarr")]


def _damaged_run(damage: Callable[[Path], None], command: str = "eval") -> Callable[[Inputs], list[str]]:
    def argv(i: Inputs) -> list[str]:
        run = i.copy_run("damaged-run")
        damage(run)
        if command == "eval":
            return _eval_of(run, i)
        return ["train", "--data", str(i.store), "--out", str(run), *RUN, "--resume"]

    return argv


def _case(argv: Callable[[Inputs], list[str]], mention: str, name: str, leaves: str = ""):
    """A refused command `argv`, whose message must contain `mention` ("{tmp}" stands for the case's folder, "{store}"
    for the shared store).
    `leaves`: a folder the refusal is known to leave behind (with no checkpoint in it); "": it writes nothing."""
    return pytest.param(argv, mention, leaves, id=name)


FLAGS = [
    # Settings out of range, refused naming the setting.
    *(
        _case(lambda i, f=flag, v=value: _train(i, f, v), f"{field} must be", f"train {flag} {value}")
        for flag, value, field in [
            ("--grad-clip", "-1", "grad_clip"),
            ("--ema-decay", "1", "ema_decay"),
            ("--save-every", "0", "save_every"),
            ("--log-every", "0", "log_every"),
            ("--lr", "nan", "lr"),
            ("--batch-size", "0", "batch_size"),
            ("--model.heads", "3", "heads"),
            ("--model.dropout", "1.5", "dropout"),
            ("--model.diffusion.num-inference-steps", "0", "num_inference_steps"),
            ("--model.horizons.horizon", "15", "horizons.horizon 15"),
            ("--model.obs.image-widths", "50", "image_widths"),
        ]
    ),
    *(
        _case(lambda i, f=flag, v=value: _eval(i, f, v), f"{field} must be", f"eval {flag} {value}")
        for flag, value, field in [
            ("--max-steps", "-1", "max_steps"),
            ("--rollouts", "0", "rollouts"),
            ("--seed", "-1", "seed"),
            ("--num-tasks", "-2", "num_tasks"),
            ("--videos", "-1", "videos"),
            ("--workers", "-3", "workers"),
        ]
    ),
    *(
        _case(lambda i, f=flag, v=value: _generate(i, f, *v.split()), f"{field} must be", f"generate {flag} {value}")
        for flag, value, field in [
            ("--num-tasks", "0", "num_tasks"),
            ("--demos-per-task", "0", "demos_per_task"),
            ("--noise-std", "-1", "noise_std"),
            ("--min-parts", "7", "max_parts"),  # above the preset's max_parts: the pair is refused at max_parts
            ("--min-new-point-px", "1000", "min_new_point_px"),
            ("--speed-range", "0 0", "speed_range"),
            ("--max-steps", "0", "max_steps"),
            ("--connect-prob", "1.5", "connect_prob"),
            ("--max-parts", "1000000000", "max_parts"),  # bounded work: not a billion parts per drawing
        ]
    ),
    # Names that do not exist, refused naming the name.
    _case(lambda i: _train(i, "--method", "bppp"), "unknown method 'bppp'", "train --method unknown"),
    _case(lambda i: _train(i, "--preset", "huge"), "unknown bpp preset 'huge'", "train --preset unknown"),
    _case(lambda i: _train(i, "--obs", "pixels"), "no observation preset 'pixels'", "train --obs unknown"),
    _case(lambda i: _generate(i, "--preset", "huge"), "unknown preset 'huge'", "generate --preset unknown"),
    _case(lambda i: _eval(i, "--tasks", "hman"), "--tasks 'hman'", "eval --tasks unknown"),
    # A resumed run keeps its own settings.
    _case(lambda i: _resume(i, "--steps", "9"), "train_config.steps: 2 in the run, 9 now", "resume --steps other"),
    _case(lambda i: _resume(i, "--seed", "3"), "train_config.seed: 0 in the run, 3 now", "resume --seed other"),
    _case(
        lambda i: _resume(i, "--model.dim", "64"), "model_config.dim: 32 in the run, 64 now", "resume --model.dim other"
    ),
    # Other commands' flags.
    _case(
        lambda i: ["draw", "sheet", str(i.store), "--size", "100000", "--out", str(i.tmp / "s.png")],
        "size must be",
        "draw sheet --size 100000",
    ),
    _case(
        lambda i: ["draw", "video", str(i.store), "--episode", "99999", "--out", str(i.tmp / "v.gif")],
        "episode 99999 out of range",
        "draw video --episode 99999",
    ),
    _case(
        lambda i: ["draw", "video", str(i.store), "--out", str(i.tmp / "v.txt")],
        "out must be a .gif or .mp4 file",
        "draw video --out x.txt",
    ),
]

PATHS = [
    # Paths that are missing or of the wrong kind, refused naming the path; a file or folder that is not a store is
    # never replaced.
    _case(
        lambda i: ["eval", str(i.tmp / "typo"), "--data-dir", str(i.tmp / "data"), "--out", str(i.tmp / "eval")],
        "typo: no such checkpoint",
        "eval of a missing checkpoint",
    ),
    _case(lambda i: _train(i, data=i.tmp / "nope.zarr"), "nope.zarr: no such store", "train --data missing"),
    _case(
        lambda i: _train(i, data=i.drawing("x.json", V)), "x.json: not an episode store", "train --data a drawing file"
    ),
    _case(lambda i: _eval(i, "--files", str(i.tmp)), "{tmp}: is a directory", "eval --files a folder"),
    _case(
        lambda i: ["draw", "generate", "--preset", "debug", "--overwrite", "--out", str(i.text("thesis/ch1.tex", ""))],
        "ch1.tex",
        "generate --overwrite onto a file",
    ),
    _case(
        lambda i: [
            "draw",
            "generate",
            "--preset",
            "debug",
            "--overwrite",
            "--out",
            str(i.text("thesis/1.tex", "").parent),
        ],
        "thesis exists and is not an episode store",
        "generate --overwrite onto a folder that is not a store",
    ),
]

DRAWINGS = [
    # Drawing files that are damaged, foreign or too big, refused naming the file.
    *(
        _case(lambda i, n=name, t=text: _generate_from(i.text(n, t)), name, f"drawing file {name}")
        for name, text in [
            ("empty.json", ""),
            ("list.json", "[1, 2]"),
            ("id.json", '{"drawings": [{"id": 5, "strokes": [[[0.1, 0.1]]]}]}'),
            ("bad.svg", "<svg><path d='M 0 0 L'"),
            ("badpath.svg", _svg('<path d="M 0 0 L 1 Q"/>')),
            ("nopaths.svg", _svg("<text>hi</text>")),
            ("notes.txt", "hello"),
            ("deep.json", "[" * 100_000 + "]" * 100_000),
            ("laughs.svg", _laughs()),
            ("curves.svg", _svg("".join(f'<path d="M {i % 100} {i // 100} q 0.5 0.5 1 0"/>' for i in range(20_000)))),
            (
                "zigzag.svg",
                _svg('<polyline points="' + " ".join(f"{i * 0.05:.2f},{(i % 2) * 100}" for i in range(20_000)) + '"/>'),
            ),
        ]
    ),
    _case(
        lambda i: _generate_from(i.text("latin1.json", b'{"drawings": "\xe9"}')),
        "latin1.json",
        "drawing file not UTF-8",
    ),
    _case(lambda i: _generate_from(i.text("huge.json", " " * (20 << 20) + "{}")), "huge.json", "drawing file of 20 MB"),
    *(
        _case(
            lambda i, v=value: _generate_from(
                i.text("coord.json", f'{{"drawings": [{{"id": "a", "strokes": [[[0.1, 0.1], [{v}, 0.2]]]}}]}}')
            ),
            f"coord.json: drawing 'a', stroke 0, point 1: expected [x, y] with two numbers, got [{shown}, 0.2]",
            f"drawing coordinate {value}",
        )
        for value, shown in [('"0.5"', "'0.5'"), ("true", "True"), ("null", "None")]
    ),
    _case(
        lambda i: _generate_from(i.drawing("many.json", [[[0.1, 0.1], [0.2, 0.2]]] * 20_000)),
        "many.json",
        "drawing of 20k strokes",
    ),
    _case(
        lambda i: _generate_from(
            i.drawing(
                "walk.json",
                [np.clip(0.5 + np.cumsum(np.random.default_rng(0).normal(0, 0.01, (200_000, 2)), 0), 0, 1).tolist()],
            )
        ),
        "walk.json",
        "stroke of 200k points (a random walk)",
    ),
    _case(
        lambda i: _generate_from(
            i.drawing("long.json", [[[float(j % 2), 0.1 + 0.8 * k / 99] for j in range(49)] for k in range(100)], "zz")
        ),
        "long.json: drawing 'zz': drawing it takes more than 1200 steps",
        "drawing too long to demonstrate",
    ),
]

DAMAGED = [
    # Damaged stores, refused naming the store.
    # A chunk is read when the first batch is loaded, after the run folder exists: this refusal leaves a run without
    # checkpoints, and a new `bpp train` into that folder starts it afresh.
    _case(
        _damaged_store(_truncated_chunk, "train"),
        "damaged.zarr: damaged store",
        "train on a truncated chunk",
        leaves="new-run",
    ),
    _case(_damaged_store(_truncated_chunk, "eval"), "damaged.zarr: damaged store", "eval on a truncated chunk"),
    _case(_damaged_store(_broken_header, "train"), "damaged.zarr: damaged store header", "train on a broken header"),
    _case(_damaged_store(_broken_header, "eval"), "damaged.zarr: damaged store header", "eval on a broken header"),
    _case(
        _damaged_store(lambda s: shutil.rmtree(s / "meta" / "episode_ends"), "train"),
        "damaged.zarr: damaged store (no meta/episode_ends)",
        "train on a store without episode_ends",
    ),
    _case(
        _damaged_store(lambda s: shutil.rmtree(s / "data" / "action"), "train"),
        "damaged.zarr: damaged store (no data/action)",
        "train on a store without actions",
    ),
    # Every read is verified: a chunk that is missing or changed is refused naming the array and the chunk, where
    # zarr alone reads zeros or decodes the changed bytes.
    _case(
        _damaged_store(lambda s: (s / "data" / "action" / "c" / "0" / "0").unlink(), "train"),
        "damaged.zarr: damaged store, cannot read data/action: its chunk (0, 0) (data/action/c/0/0) is missing",
        "train on a store with a deleted chunk",
        leaves="new-run",
    ),
    _case(
        _damaged_store(lambda s: _flip_a_bit(s / "data" / "state" / "c" / "0" / "0"), "eval"),
        "damaged.zarr: damaged store, cannot read data/state: its chunk (0, 0) (data/state/c/0/0) fails its checksum",
        "eval on a store with a flipped bit",
    ),
    _case(
        _damaged_store(lambda s: _copy_chunk(s / "data" / "action_on_board", s / "data" / "action"), "train"),
        "damaged.zarr: damaged store, cannot read data/action: its chunk (0, 0) (data/action/c/0/0) is not the chunk "
        "the store recorded there",
        "train on a store whose actions' chunk is another array's, whole and of the same shape",
        leaves="new-run",
    ),
    _case(
        _damaged_store(lambda s: (s / "tasks" / "strokes" / "c" / "0" / "0").unlink(), "sheet"),
        "damaged.zarr: damaged store, cannot read tasks/strokes: its chunk (0, 0) (tasks/strokes/c/0/0) is missing",
        "sheet of a store whose drawings' chunk was deleted",
    ),
    _case(
        _damaged_store(lambda s: _header(s, stats={}), "train"),
        "damaged.zarr: damaged store header (it does not match its digest)",
        "train on a store whose statistics were changed",
    ),
    # Stores of another format or version, refused by it.
    _case(
        _damaged_store(lambda s: _header(s, version=1), "train"),
        "damaged.zarr: store version 1, written by an older bpp; this bpp reads versions 2 and 3",
        "train on a store of version 1",
    ),
    _case(
        _damaged_store(lambda s: _header(s, zarr_format=2), "eval"),
        "damaged.zarr: not an episode store (zarr format 2",
        "eval on a header of zarr format 2",
    ),
    # Damaged runs, refused naming the damaged file.
    _case(
        _damaged_run(lambda run: _truncate(_newest(run) / "ema.safetensors")),
        "ema.safetensors: unreadable weights",
        "eval of truncated weights",
    ),
    _case(
        _damaged_run(lambda run: _truncate(_newest(run) / "state.json")),
        "state.json: the checkpoint state is not valid JSON",
        "eval of a truncated state.json",
    ),
    _case(
        _damaged_run(lambda run: (_newest(run) / "state.json").write_text("[" * 100_000 + "]" * 100_000)),
        "state.json: the checkpoint state is nested too deeply",
        "eval of a state.json nested 100k deep",
    ),
    _case(
        _damaged_run(lambda run: (_newest(run) / "state.json").write_text('{"step": ' + "9" * 5000 + "}")),
        "state.json: the checkpoint state holds an integer of 5000 digits",
        "eval of a state.json with a 5000-digit step",
    ),
    _case(
        _damaged_run(lambda run: (_newest(run) / "state.json").write_text('{"step": 1e999}')),
        "state.json: the checkpoint state holds the number 1e999, which overflows a float",
        "eval of a state.json with a number past float's range",
    ),
    _case(
        _damaged_run(lambda run: (_newest(run) / "state.json").write_text('{"format": "other"}')),
        "damaged-run/checkpoints/step_00000002: not a bpp checkpoint",
        "eval of a checkpoint of another format",
    ),
    _case(
        _damaged_run(lambda run: shutil.rmtree(run / "checkpoints")),
        "damaged-run: no checkpoint found",
        "eval of a run without checkpoints",
    ),
    _case(
        _damaged_run(lambda run: (run / "config.json").write_text("{"), "train"),
        "config.json: the run configuration is not valid JSON",
        "resume with a damaged config.json",
    ),
]

MERGES = [
    # Merges that would double demonstrations or change an input.
    _case(lambda i: _merge(i, i.store, i.store), "debug.zarr is {store} given again", "merge a store with itself"),
    _case(
        lambda i: _merge(i, i.store, i.copy_store("copy.zarr")),
        "episode 0 of {tmp}/copy.zarr is episode 0 of {store} again",
        "merge a store with its copy",
    ),
    _case(
        lambda i: _merge(i, i.copy_store("a.zarr"), i.store, out=i.tmp / "a.zarr" / "data" / "m.zarr"),
        "the merge would be written inside its input {tmp}/a.zarr",
        "merge into an input store",
    ),
    _case(
        lambda i: _merge(i, i.copy_store("a.zarr"), i.store, out=i.tmp / "a.zarr") + ["--overwrite"],
        "the merge would be written over its input {tmp}/a.zarr",
        "merge over an input store",
    ),
]


@pytest.mark.parametrize(("argv", "mention", "leaves"), [*FLAGS, *PATHS, *DRAWINGS, *DAMAGED, *MERGES])
def test_bad_inputs_are_refused_in_one_line_naming_the_input_and_change_nothing(argv, mention, leaves, inputs, capsys):
    inputs.tmp.mkdir()
    command = argv(inputs)
    before = snapshot(inputs.tmp)
    message = refused(command, capsys)
    mention = mention.format(tmp=inputs.tmp, store=inputs.store)
    assert mention in " ".join(message.replace("│", " ").split()), message
    after = snapshot(inputs.tmp)
    assert {p: after.get(p) for p in before} == before  # every file given is as it was
    written = sorted(set(after) - set(before))
    if leaves:
        assert all(p == leaves or p.startswith(leaves + "/") for p in written), written
        assert not any("checkpoints" in p for p in written), written
    else:
        assert not written


# ----------------------------------------------------------------------------- inputs that must be handled


@pytest.mark.filterwarnings("ignore:Glyph 0")  # the NUL in an id has no glyph in the report's font
@pytest.mark.parametrize("drawing_id", ["x/../../../pwn", "/tmp/pwn-bpp", "pwn\n\x00x", ".."])
def test_drawing_ids_never_become_paths_outside_the_output_folder(drawing_id, inputs):
    inputs.tmp.mkdir()
    drawing = inputs.drawing("evil.json", V, drawing_id)
    out, data = inputs.tmp / "a" / "b" / "eval", inputs.tmp / "d"

    main(["eval", str(inputs.run), "--files", str(drawing), *QUICK, "--out", str(out), "--data-dir", str(data)])
    assert len(list(out.glob("rollout_*"))) == 1
    written = [p for p in inputs.tmp.rglob("*") if p.is_file() and p != drawing]
    assert written and all(out in p.parents or data in p.parents for p in written), written
    assert not list(Path("/tmp").glob("pwn-bpp*"))


@pytest.mark.parametrize("pointer", ["step_00000099", "../../../etc"])
def test_eval_of_a_run_whose_last_pointer_is_wrong_uses_its_newest_checkpoint(pointer, inputs, capsys):
    inputs.tmp.mkdir()
    run = inputs.copy_run()
    (run / "checkpoints" / "last").write_text(pointer)
    main(_eval_of(run, inputs))
    assert f"{run}/checkpoints/last names" in capsys.readouterr().err  # a warning names the bad pointer
    results = json.loads((inputs.tmp / "eval" / "results.json").read_text())
    assert Path(results["checkpoint"]) == run / "checkpoints" / "step_00000002"


def test_resume_with_damaged_optimizer_state_falls_back_to_the_checkpoint_before(inputs, capsys):
    inputs.tmp.mkdir()
    run = inputs.copy_run()
    _truncate(run / "checkpoints" / "step_00000002" / "optimizer.safetensors")
    main(["train", "--data", str(inputs.store), "--out", str(run), *RUN, "--resume"])
    err = capsys.readouterr().err
    assert "skipping step_00000002" in err and "resuming from step_00000001" in err
    assert _newest(run).name == "step_00000002"
    main(_eval_of(run, inputs))  # the step saved again is whole


def test_an_svg_nested_100k_groups_deep_is_read(tmp_path):
    from bpp.drawing.files import load_drawings

    svg = tmp_path / "deep.svg"
    svg.write_text(_svg("<g>" * 100_000 + '<path d="M 0 0 L 100 100"/>' + "</g>" * 100_000))
    (drawing,) = load_drawings(svg)
    assert len(drawing.strokes) == 1


def _bpp_process(*args: str) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "bpp.cli", *args], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
    )


def _kill_when(proc: subprocess.Popen, ready: Callable[[], bool], timeout: float = 120.0) -> None:
    deadline = time.monotonic() + timeout
    while not ready() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)
    proc.kill()
    proc.wait()
    assert ready(), "the process ended or timed out before the moment to kill it"


@pytest.mark.slow
def test_a_generation_killed_midway_leaves_no_store_and_its_rerun_cleans_up(tmp_path):
    out = tmp_path / "killed.zarr"
    proc = _bpp_process(
        "draw", "generate", "--preset", "debug", "--num-tasks", "5000", "--workers", "1", "--out", str(out)
    )
    _kill_when(proc, lambda: any(tmp_path.glob(".killed.zarr.partial-*/**/c/*")))  # killed while writing data
    assert not out.exists()
    main(["draw", "generate", "--preset", "debug", "--workers", "1", "--out", str(out)])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["killed.zarr"]


@pytest.mark.slow
def test_a_training_killed_midway_resumes_to_its_last_step(debug_store, tmp_path):
    run = tmp_path / "run"
    command = ["train", "--data", str(debug_store.path), "--out", str(run), "--preset", "debug", "--steps", "40"]
    proc = _bpp_process(*command, "--save-every", "5", "--workers", "0")
    _kill_when(proc, lambda: (run / "checkpoints" / "last").exists())
    assert _newest(run).name != "step_00000040"
    main([*command, "--save-every", "5", "--workers", "0", "--resume"])
    assert _newest(run).name == "step_00000040"


# ----------------------------------------------------------------------------- numbers and shapes from user files


def _coordinate(i: Inputs, name: str, value: str) -> Path:
    """A JSON drawing file whose second point has x = `value`, as written."""
    return i.text(name, f'{{"drawings": [{{"id": "a", "strokes": [[[0.1, 0.1], [{value}, 0.2]]]}}]}}')


NUMBERS = [
    # Numbers that overflow, or that the format does not allow, refused naming the file, the element and the number.
    _case(
        lambda i: _generate_from(_coordinate(i, "far.json", "1e309")),
        "far.json: drawing 'a', stroke 0, point 1: coordinate 1e309 is not a finite number",
        "drawing coordinate 1e309",
    ),
    _case(
        lambda i: _generate_from(_coordinate(i, "digits.json", "9" * 5000)),
        "digits.json: drawing 'a', stroke 0, point 1: coordinate 9999999999999999...9999 (5000 characters) is not",
        "drawing coordinate of 5000 digits",
    ),
    _case(
        lambda i: _eval(i, "--files", str(_coordinate(i, "far.json", "-Infinity")), *QUICK),
        "far.json: drawing 'a', stroke 0, point 1: coordinate -Infinity is not a finite number",
        "eval --files with a coordinate -Infinity",
    ),
    *(
        _case(
            lambda i, n=name, b=body: _generate_from(i.text(n, _svg(b))), f"{name}: {mention}", f"drawing file {name}"
        )
        for name, body, mention in [
            ("far.svg", '<path d="M 0 0 L 1e309 10"/>', "<path> #1, attribute 'd': 1e309 is not a finite number"),
            (
                "scaled.svg",
                '<g transform="scale(1e10)"><path transform="scale(1e10)" d="M 0 0 L 1 1"/></g>',
                "<path> #1, attribute 'transform': with the transforms of its groups it scales or moves coordinates",
            ),
            (
                "transform.svg",
                '<g transform="translate(5) foo(1)"><path d="M 0 0 L 1 1"/></g><path d="M 0 0 L 9 9"/>',
                "<g> #1, attribute 'transform': cannot read 'translate(5) foo(1)'",
            ),
            (
                "arc.svg",
                '<path d="M 0 0 L 9 9"/><path id="tiny" d="M 5 5 A 1e-320 1e-320 0 0 1 20 20"/>',
                "<path id='tiny'>: the length of its segment 0 (Arc) is not a finite number",
            ),
            (
                "points.svg",
                '<polyline points="0,0 inf,1 2,2"/>',
                "<polyline> #1, attribute 'points': 'inf' is not a number",
            ),
        ]
    ),
    # LIBERO views: an empty or malformed --where is refused quoting it.
    *(
        _case(lambda i, w=where: ["libero", "tasks", "--where", w], mention, f"libero tasks --where {where!r}")
        for where, mention in [
            ("", "where '' is empty"),
            ("pick=TD;", "where 'pick=TD;': clause 2 is empty"),
            ("pick==TD", "where 'pick==TD': 'pick==TD' is not field=value"),
        ]
    ),
    _case(
        lambda i: ["libero", "generate", "--preset", "debug", "--where", "pick=TD", "--out", str(i.tmp / "l.zarr")],
        "task_indices [0] are not in the view 'pick=TD' (task_indices come from --task-indices or the preset",
        "libero generate --where outside the preset's task_indices",
    ),
    pytest.param(
        lambda i: ["libero", "import", str(i.text("notes_demo.hdf5", "hello")), "--out", str(i.tmp / "l.zarr")],
        "{tmp}/notes_demo.hdf5: not an HDF5 file",
        "",
        id="libero import of a text file",
        marks=pytest.mark.libero,
    ),
]


@pytest.mark.parametrize(("argv", "mention", "leaves"), NUMBERS)
def test_numbers_and_views_the_format_does_not_allow_are_refused_in_one_line_naming_them(
    argv, mention, leaves, inputs, capsys
):
    test_bad_inputs_are_refused_in_one_line_naming_the_input_and_change_nothing(argv, mention, leaves, inputs, capsys)


# ----------------------------------------------------------------------------- outputs: folders and task ids

OUTPUTS = [
    # An output folder that cannot be made, refused naming it before any work (an evaluation before its rollouts).
    _case(
        lambda i: _eval_of(i.run, i)[:-1] + [str(i.text("notes.txt", "mine") / "eval")],
        "--out {tmp}/notes.txt/eval: {tmp}/notes.txt is not a folder",
        "eval --out under a file",
    ),
    _case(
        lambda i: _generate(i)[:-1] + [str(i.text("notes.txt", "mine") / "new.zarr")],
        "{tmp}/notes.txt",
        "generate --out under a file",
    ),
    _case(
        lambda i: _train(i, "--out", str(i.text("notes.txt", "mine") / "run"), "--steps", "1"),
        "{tmp}/notes.txt/run",
        "train --out under a file",
    ),
]


@pytest.mark.parametrize(("argv", "mention", "leaves"), OUTPUTS)
def test_output_folders_that_cannot_be_made_are_refused_in_one_line_naming_them(argv, mention, leaves, inputs, capsys):
    test_bad_inputs_are_refused_in_one_line_naming_the_input_and_change_nothing(argv, mention, leaves, inputs, capsys)


def test_task_ids_that_one_file_name_would_merge_get_a_video_each(inputs):
    """'a/b' and 'a_b' once shared one video, as did 'star.v1' and 'star.v2' (the suffix taken for the file's)."""
    inputs.tmp.mkdir()
    ids = ["a/b", "a_b", "star.v1", "star.v2"]
    drawings = inputs.text("ids.json", json.dumps({"drawings": [{"id": d, "strokes": V} for d in ids]}))
    out = inputs.tmp / "eval"
    main(["eval", str(inputs.run), "--files", str(drawings), *QUICK[:-1], "4", "--out", str(out)])
    results = json.loads((out / "results.json").read_text())
    assert len({task["video"] for task in results["tasks"]}) == 4 == len(list(out.glob("rollout_*")))
