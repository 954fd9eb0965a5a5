"""Probe the command line as a careful user and an attacker would, and tabulate the outcomes (issue 15).

Each probe runs one ``bpp`` command (or a short Python check) in a fresh process on a scratch workspace: bad files,
bad flags, damaged runs and stores, huge or hostile inputs. A probe either expects a refusal, which must exit
non-zero, without a traceback, naming the input it refuses, or expects success, with a check of the result (for
example that nothing was written outside ``--out``). Outcomes:

    clear error      refused, no traceback, the message names the input
    handled          accepted and the result checked out
    unclear message  refused without naming the input
    traceback        a Python traceback reached the user
    hang             ran past --timeout seconds
    accepted         a bad input was accepted silently
    wrong            accepted, but the check failed (data lost, a file outside --out, a stale result, ...)

    python bench/hardening_probes.py [--out runs/probes] [--timeout 120] [--only SUBSTRING]

Writes ``probes.md`` (the table and every probe's outcome) into --out and prints it. Takes about 5 minutes.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

CLASSES = {
    1: "writes outside the output folder, data loss",
    2: "stale or silent results, unchecked settings",
    3: "bounded work on any input",
    4: "recoverable runs",
    5: "messages for damaged or foreign inputs",
    6: "claims that must hold",
}
OUTCOMES = ("clear error", "handled", "unclear message", "traceback", "hang", "accepted", "wrong")


@dataclass
class Probe:
    group: int
    name: str
    argv: Callable[[], list[str]]
    """Prepares what the probe needs and returns the bpp arguments (or ["python", code])."""
    expect: str = "error"
    mention: str = ""
    """Text the refusal must contain (the input it names)."""
    check: Callable[[subprocess.CompletedProcess], str] | None = None
    """After the run: "" if fine, else what is wrong."""


@dataclass
class Workspace:
    root: Path
    store: Path = field(init=False)
    run: Path = field(init=False)

    def __post_init__(self):
        self.store = self.root / "debug.zarr"
        self.run = self.root / "run"

    def path(self, name: str) -> Path:
        return self.root / name

    def copy_run(self, name: str) -> Path:
        target = self.path(name)
        shutil.rmtree(target, ignore_errors=True)
        shutil.copytree(self.run, target)
        return target

    def copy_store(self, name: str) -> Path:
        target = self.path(name)
        shutil.rmtree(target, ignore_errors=True)
        shutil.copytree(self.store, target)
        return target

    def drawing(self, name: str, strokes, drawing_id: str = "d") -> Path:
        path = self.path(name)
        path.write_text(json.dumps({"drawings": [{"id": drawing_id, "strokes": strokes}]}))
        return path


V = [[[0.2, 0.2], [0.5, 0.8], [0.8, 0.2]]]
RUN = ["--preset", "debug", "--steps", "2", "--save-every", "1", "--workers", "0"]
"""The probes' trained run (resumed with the same flags)."""
QUICK = ["--rollouts", "1", "--max-steps", "8", "--workers", "1", "--videos", "1"]


def bpp(*args: str, timeout: float) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "bpp.cli", *args], capture_output=True, text=True, timeout=timeout, check=False
    )


def probes(ws: Workspace) -> list[Probe]:
    p = ws.path
    out: list[Probe] = []

    def add(group, name, argv, expect="error", mention="", check=None):
        out.append(Probe(group, name, argv, expect, mention, check))

    def nothing_outside(_) -> str:
        stray = [*ws.root.rglob("pwn*"), *Path("/tmp").glob("pwn-bpp*")]
        return f"wrote {stray}" if stray else ""

    def evil_id(drawing_id):
        def argv():
            f = ws.drawing("evil.json", V, drawing_id)
            return [
                "eval",
                str(ws.run),
                "--files",
                str(f),
                *QUICK,
                "--out",
                str(p("e/evil")),
                "--data-dir",
                str(p("d")),
            ]

        return argv

    # 1. writes outside the output folder, data loss --------------------------------------------------------
    add(1, "drawing id x/../../../pwn", evil_id("x/../../../pwn"), "ok", check=nothing_outside)
    add(1, "drawing id /tmp/pwn-bpp", evil_id("/tmp/pwn-bpp"), "ok", check=nothing_outside)
    add(1, "drawing id with newline and NUL", evil_id("pwn\n\x00x"), "ok", check=nothing_outside)
    add(1, "drawing id '..'", evil_id(".."), "ok", check=nothing_outside)

    def precious(name):
        folder = p(name)
        folder.mkdir(exist_ok=True)
        (folder / "thesis.tex").write_text("years of work")
        return folder

    def intact(name):
        return lambda _: "" if (p(name) / "thesis.tex").exists() else f"{name}/thesis.tex deleted"

    add(
        1,
        "generate --overwrite onto a folder that is not a store",
        lambda: ["draw", "generate", "--preset", "debug", "--out", str(precious("thesis")), "--overwrite"],
        mention="not an episode store",
        check=intact("thesis"),
    )

    def a_file():
        (p("notes.txt")).write_text("keep me")
        return ["draw", "generate", "--preset", "debug", "--out", str(p("notes.txt")), "--overwrite"]

    add(
        1,
        "generate --overwrite onto a file",
        a_file,
        mention="notes.txt",
        check=lambda _: "" if p("notes.txt").read_text() == "keep me" else "notes.txt changed",
    )

    def nothing_written(*names):
        return lambda _: ", ".join(f"{n} written" for n in names if p(n).exists())

    add(
        1,
        "eval of a missing checkpoint writes nothing",
        lambda: ["eval", str(p("typo")), "--data-dir", str(p("d-typo")), "--out", str(p("e-typo"))],
        mention="typo",
        check=nothing_written("d-typo", "e-typo"),
    )
    add(
        1,
        "eval --tasks with an unknown name writes nothing",
        lambda: ["eval", str(ws.run), "--tasks", "hman", "--data-dir", str(p("d-hman")), "--out", str(p("e-hman"))],
        mention="hman",
        check=nothing_written("d-hman", "e-hman"),
    )
    add(
        1,
        "train --data missing creates no run",
        lambda: ["train", "--data", str(p("nope.zarr")), "--out", str(p("r-nope")), "--preset", "debug"],
        mention="nope.zarr",
        check=nothing_written("r-nope"),
    )

    def killed_generate():
        proc = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "bpp.cli",
                "draw",
                "generate",
                "--preset",
                "debug",
                "--num-tasks",
                "5000",
                "--workers",
                "1",
                "--out",
                str(p("killed.zarr")),
            ],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        time.sleep(6)
        proc.kill()
        proc.wait()
        if p("killed.zarr").exists():
            raise RuntimeError("a killed generation left a store at its --out")
        return ["draw", "generate", "--preset", "debug", "--workers", "1", "--out", str(p("killed.zarr"))]

    add(
        1,
        "store generation killed with -9, then run again",
        killed_generate,
        "ok",
        check=lambda _: ", ".join(q.name for q in ws.root.glob(".killed.zarr.partial-*")),
    )

    # 2. stale or silent results, unchecked settings -----------------------------------------------------------
    def eval_twice_after(change: Callable[[], None], name: str):
        def argv():
            f = ws.drawing(f"{name}.json", V)
            run = ws.copy_run(f"run-{name}")
            command = [
                "eval",
                str(run),
                "--files",
                str(f),
                *QUICK,
                "--out",
                str(p(f"e-{name}")),
                "--data-dir",
                str(p("d")),
            ]
            first = bpp(*command, timeout=300)
            if first.returncode:
                raise RuntimeError(first.stderr[-500:])
            change()
            return command

        return argv

    def not_reused(result):
        return "reused stale results" if "reusing" in result.stdout else ""

    add(
        2,
        "eval after the drawing file was edited",
        eval_twice_after(lambda: ws.drawing("edited.json", [[[0.2, 0.2], [0.5, 0.6], [0.8, 0.2]]]), "edited"),
        "ok",
        check=not_reused,
    )

    def retrain():
        run = p("run-retrained")
        shutil.rmtree(run)
        r = bpp(
            "train",
            "--data",
            str(ws.store),
            "--out",
            str(run),
            "--preset",
            "debug",
            "--steps",
            "2",
            "--seed",
            "7",
            timeout=300,
        )
        if r.returncode:
            raise RuntimeError(r.stderr[-500:])

    add(2, "eval after the run was trained again", eval_twice_after(retrain, "retrained"), "ok", check=not_reused)
    for flag, value, field_name in (("--steps", "9", "steps"), ("--seed", "3", "seed"), ("--model.dim", "64", "dim")):
        add(
            2,
            f"--resume with another {flag}",
            lambda flag=flag, value=value: [
                "train",
                "--data",
                str(ws.store),
                "--out",
                str(ws.copy_run("run-resume")),
                *RUN,
                "--resume",
                flag,
                value,
            ],
            mention=field_name,
        )
    for flag, value in (
        ("--grad-clip", "-1"),
        ("--ema-decay", "1"),
        ("--save-every", "0"),
        ("--log-every", "0"),
        ("--lr", "nan"),
        ("--batch-size", "0"),
        ("--model.heads", "3"),
        ("--model.dropout", "1.5"),
        ("--model.diffusion.num-inference-steps", "0"),
        ("--model.horizons.horizon", "15"),
        ("--model.obs.image-widths", "50"),
    ):
        add(
            2,
            f"train {flag} {value}",
            lambda flag=flag, value=value: [
                "train",
                "--data",
                str(ws.store),
                "--out",
                str(p("r-bad")),
                "--preset",
                "debug",
                flag,
                value,
            ],
            mention=flag.split(".")[-1].lstrip("-").replace("-", "_"),
        )
    for flag, value in (
        ("--max-steps", "-1"),
        ("--rollouts", "0"),
        ("--seed", "-1"),
        ("--num-tasks", "-2"),
        ("--videos", "-1"),
        ("--workers", "-3"),
    ):
        add(
            2,
            f"eval {flag} {value}",
            lambda flag=flag, value=value: ["eval", str(ws.run), flag, value, "--out", str(p("e-bad"))],
            mention=flag.lstrip("-").replace("-", "_"),
        )
    for flag, value in (
        ("--num-tasks", "0"),
        ("--demos-per-task", "0"),
        ("--noise-std", "-1"),
        ("--min-parts", "7"),
        ("--min-new-point-px", "1000"),
        ("--speed-range", "0 0"),
        ("--max-steps", "0"),
        ("--connect-prob", "1.5"),
    ):
        add(
            2,
            f"generate {flag} {value}",
            lambda flag=flag, value=value: [
                "draw",
                "generate",
                "--preset",
                "debug",
                flag,
                *value.split(),
                "--out",
                str(p("g-bad.zarr")),
            ],
            mention=flag.lstrip("-").replace("-", "_") if flag != "--min-parts" else "max_parts",
        )
    for value, shown in (('"0.5"', "'0.5'"), ("true", "True"), ("null", "None")):
        add(
            2,
            f"drawing coordinate {value}",
            lambda value=value: [
                "draw",
                "generate",
                "--source",
                "files",
                "--out",
                str(p("g-json.zarr")),
                "--drawings",
                str(
                    _text(
                        p("coord.json"), f'{{"drawings": [{{"id": "a", "strokes": [[[0.1, 0.1], [{value}, 0.2]]]}}]}}'
                    )
                ),
            ],
            mention=shown,
        )

    def svg_check(_):
        from bpp.benchmarks.draw.files import load_drawings

        a = load_drawings(p("t.svg"))[0]
        b = load_drawings(p("plain.svg"))[0]
        same = len(a.strokes) == len(b.strokes) and all(
            np.allclose(x, y, atol=1e-9) for x, y in zip(a.strokes, b.strokes, strict=True)
        )
        return "" if same else "transform not applied"

    def svg_argv():
        _text(
            p("t.svg"),
            _svg(
                '<g transform="translate(100,20) rotate(90)"><path d="M 0 0 L 10 0" '
                'transform="scale(2)"/></g><line x1="10" y1="10" x2="40" y2="10"/>'
            ),
        )
        _text(p("plain.svg"), _svg('<path d="M 100 20 L 100 40"/><line x1="10" y1="10" x2="40" y2="10"/>'))
        return [
            "draw",
            "generate",
            "--source",
            "files",
            "--drawings",
            str(p("t.svg")),
            "--out",
            str(p("g-svg.zarr")),
            "--overwrite",
        ]

    add(2, "SVG with transforms", svg_argv, "ok", check=svg_check)

    # 3. bounded work on any input --------------------------------------------------------------------------
    def generate_from(path_fn):
        return lambda: [
            "draw",
            "generate",
            "--source",
            "files",
            "--out",
            str(p("g-big.zarr")),
            "--overwrite",
            "--drawings",
            str(path_fn()),
        ]

    t = np.linspace(0, 2 * np.pi, 200_000)
    add(
        3,
        "JSON stroke of 200k points (a circle)",
        generate_from(
            lambda: ws.drawing("circle.json", [np.stack([0.5 + 0.4 * np.cos(t), 0.5 + 0.4 * np.sin(t)], 1).tolist()])
        ),
        "ok",
    )
    rng = np.random.default_rng(0)
    add(
        3,
        "JSON stroke of 200k points (a random walk)",
        generate_from(
            lambda: ws.drawing(
                "walk.json", [np.clip(0.5 + np.cumsum(rng.normal(0, 0.01, (200_000, 2)), 0), 0, 1).tolist()]
            )
        ),
        mention="walk.json",
    )
    add(
        3,
        "JSON drawing of 20k strokes",
        generate_from(lambda: ws.drawing("many.json", [[[0.1, 0.1], [0.2, 0.2]]] * 20_000)),
        mention="many.json",
    )
    add(
        3,
        "SVG zigzag polyline of 20k vertices (about 200 KB)",
        generate_from(
            lambda: _text(
                p("zigzag.svg"),
                _svg('<polyline points="' + " ".join(f"{i * 0.05:.2f},{(i % 2) * 100}" for i in range(20_000)) + '"/>'),
            )
        ),
        mention="zigzag.svg",
    )
    add(
        3,
        "SVG of 20k tiny curves",
        generate_from(
            lambda: _text(
                p("curves.svg"),
                _svg("".join(f'<path d="M {i % 100} {i // 100} q 0.5 0.5 1 0"/>' for i in range(20_000))),
            )
        ),
        mention="curves.svg",
    )
    add(
        3,
        "JSON nested 100k deep",
        generate_from(lambda: _text(p("deep.json"), "[" * 100_000 + "]" * 100_000)),
        mention="deep.json",
    )
    add(
        3,
        "SVG nested 100k groups deep",
        generate_from(
            lambda: _text(p("deep.svg"), _svg("<g>" * 100_000 + '<path d="M 0 0 L 1 1"/>' + "</g>" * 100_000))
        ),
        expect="ok",
    )
    add(
        3,
        "SVG entity expansion (billion laughs)",
        generate_from(lambda: _text(p("laughs.svg"), _laughs())),
        mention="laughs.svg",
    )
    add(
        3,
        "JSON file of 20 MB",
        generate_from(lambda: _text(p("huge.json"), " " * (20 << 20) + "{}")),
        mention="huge.json",
    )
    add(
        3,
        "drawing too long to demonstrate (100 zigzag strokes)",
        generate_from(
            lambda: ws.drawing(
                "long.json", [[[float(j % 2), 0.1 + 0.8 * k / 99] for j in range(49)] for k in range(100)]
            )
        ),
        mention="long",
    )
    add(
        3,
        "draw sheet --size 100000",
        lambda: ["draw", "sheet", str(ws.store), "--size", "100000", "--out", str(p("s.png"))],
        mention="size",
    )
    add(
        3,
        "generate --max-parts 1000000000",
        lambda: ["draw", "generate", "--preset", "debug", "--max-parts", "1000000000", "--out", str(p("g-parts.zarr"))],
        mention="max_parts",
    )

    # 4. recoverable runs ------------------------------------------------------------------------------------
    def newest(run: Path) -> Path:
        return run / "checkpoints" / (run / "checkpoints" / "last").read_text().strip()

    def damaged(name: str, damage: Callable[[Path], None], command="eval"):
        def argv():
            run = ws.copy_run(name)
            damage(run)
            if command == "eval":
                return [
                    "eval",
                    str(run),
                    "--tasks",
                    str(ws.store),
                    "--num-tasks",
                    "1",
                    *QUICK,
                    "--out",
                    str(p(f"e-{name}")),
                ]
            return ["train", "--data", str(ws.store), "--out", str(run), *RUN, "--resume"]

        return argv

    def truncate(file: str):
        return lambda run: (newest(run) / file).write_bytes((newest(run) / file).read_bytes()[:1000])

    add(
        4, "eval with truncated EMA weights", damaged("r-trunc", truncate("ema.safetensors")), mention="ema.safetensors"
    )
    add(
        4,
        "resume with truncated optimizer state",
        damaged("r-trunc-opt", truncate("optimizer.safetensors"), "train"),
        "ok",
        check=lambda r: "" if "resuming from step_00000001" in r.stderr else "did not fall back",
    )
    add(
        4,
        "eval with 'last' naming a missing folder",
        damaged("r-last", lambda run: (run / "checkpoints" / "last").write_text("step_00000099")),
        "ok",
    )
    add(
        4,
        "eval with 'last' naming ../../..",
        damaged("r-last2", lambda run: (run / "checkpoints" / "last").write_text("../../../etc")),
        "ok",
    )
    add(4, "eval with truncated state.json", damaged("r-state", truncate("state.json")), mention="state.json")
    add(
        4,
        "resume with a damaged config.json",
        damaged("r-config", lambda run: (run / "config.json").write_text("{"), "train"),
        mention="config.json",
    )
    add(
        4,
        "eval of a run with no checkpoints",
        damaged("r-empty", lambda run: shutil.rmtree(run / "checkpoints")),
        mention="r-empty",
    )

    def killed_training():
        run = p("r-killed")
        shutil.rmtree(run, ignore_errors=True)
        command = [
            "train",
            "--data",
            str(ws.store),
            "--out",
            str(run),
            "--preset",
            "debug",
            "--steps",
            "300",
            "--save-every",
            "5",
            "--workers",
            "0",
        ]
        proc = subprocess.Popen(
            [sys.executable, "-m", "bpp.cli", *command], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
        )
        deadline = time.time() + 120
        while time.time() < deadline and not (run / "checkpoints" / "last").exists():
            time.sleep(0.2)
        proc.kill()
        proc.wait()
        return [*command, "--resume"]

    add(
        4,
        "training killed with -9, then resumed",
        killed_training,
        "ok",
        check=lambda _: "" if newest(p("r-killed")).name == "step_00000300" else "did not finish",
    )

    # 5. messages for damaged or foreign inputs ----------------------------------------------------------------
    def store_damage(name: str, damage: Callable[[Path], None], command: str):
        def argv():
            store = ws.copy_store(name)
            damage(store)
            if command == "info":
                return ["store", "info", str(store)]
            if command == "eval":
                return ["eval", str(ws.run), "--tasks", str(store), *QUICK, "--out", str(p(f"e-{name}"))]
            return ["train", "--data", str(store), "--out", str(p(f"r-{name}")), "--preset", "debug", "--steps", "1"]

        return argv

    def chunk(store: Path) -> None:
        part = next(q for q in sorted((store / "data" / "action" / "c").rglob("*")) if q.is_file())
        part.write_bytes(part.read_bytes()[:20])

    def header(store: Path) -> None:
        (store / "zarr.json").write_text('{"zarr_format": 3, "node_type": "group", "attributes": {')

    for command in ("info", "train", "eval"):
        add(
            5,
            f"{command}: store with a truncated data chunk",
            store_damage(f"s-chunk-{command}", chunk, command),
            "error" if command != "info" else "ok",
            mention=f"s-chunk-{command}",
        )
        add(
            5,
            f"{command}: store with a broken header",
            store_damage(f"s-head-{command}", header, command),
            mention=f"s-head-{command}",
        )
    add(
        5,
        "train: store missing meta/episode_ends",
        store_damage("s-ends", lambda s: shutil.rmtree(s / "meta" / "episode_ends"), "train"),
        mention="s-ends",
    )
    add(
        5,
        "train: store with a deleted data array",
        store_damage("s-array", lambda s: shutil.rmtree(s / "data" / "action"), "train"),
        mention="s-array",
    )
    add(
        5,
        "train --data a drawing file",
        lambda: ["train", "--data", str(ws.drawing("x.json", V)), "--out", str(p("r-x"))],
        mention="x.json",
    )
    add(5, "train --method unknown", lambda: ["train", "--data", str(ws.store), "--method", "bppp"], mention="bppp")
    add(5, "train --preset unknown", lambda: ["train", "--data", str(ws.store), "--preset", "huge"], mention="huge")
    add(5, "train --obs unknown", lambda: ["train", "--data", str(ws.store), "--obs", "pixels"], mention="pixels")
    for name, text in (
        ("empty.json", ""),
        ("latin1.json", None),
        ("list.json", "[1, 2]"),
        ("id.json", '{"drawings": [{"id": 5, "strokes": [[[0.1, 0.1]]]}]}'),
        ("bad.svg", "<svg><path d='M 0 0 L'"),
        ("badpath.svg", _svg('<path d="M 0 0 L 1 Q"/>')),
        ("nopaths.svg", _svg("<text>hi</text>")),
        ("notes.txt", "hello"),
    ):

        def argv(name=name, text=text):
            file = p(name)
            if text is None:
                file.write_bytes(b'{"drawings": "\xe9"}')
            else:
                file.write_text(text)
            return ["draw", "generate", "--source", "files", "--drawings", str(file), "--out", str(p("g-f.zarr"))]

        add(5, f"drawing file {name}", argv, mention=name)
    add(
        5,
        "eval --files a folder",
        lambda: ["eval", str(ws.run), "--files", str(ws.root), "--out", str(p("e-f"))],
        mention=str(ws.root),
    )
    add(
        5,
        "draw video --episode 99999",
        lambda: ["draw", "video", str(ws.store), "--episode", "99999", "--out", str(p("v.gif"))],
        mention="99999",
    )
    add(5, "draw video --out x.txt", lambda: ["draw", "video", str(ws.store), "--out", str(p("v.txt"))], mention="out")
    add(
        5,
        "eval a checkpoint of another format",
        damaged("r-format", lambda run: (newest(run) / "state.json").write_text('{"format": "other"}')),
        mention="r-format",
    )

    # 6. claims that must hold ------------------------------------------------------------------------------
    add(
        6,
        "identical integer drawings score exactly 0 at 0.3 rad",
        lambda: [
            "python",
            (
                "import numpy as np\n"
                "from bpp.benchmarks.draw.geometry import canvas_to_upright, rotation\n"
                "from bpp.benchmarks.draw.metric import chamfer_distance, ink_mask\n"
                "line = np.array([[x, 256] for x in range(156, 357, 10)], float)\n"
                "moved = canvas_to_upright((line - 256) @ rotation(0.3).T + 256, 0.3)\n"
                "assert chamfer_distance(ink_mask([line]), ink_mask([moved])) == 0.0"
            ),
        ],
        "ok",
    )
    add(
        6,
        "circle parity value as the README states (9.684)",
        lambda: [
            "python",
            (
                "import numpy as np\n"
                "from bpp.benchmarks.draw.metric import chamfer_distance, ink_mask\n"
                "th = np.deg2rad(np.arange(360))\n"
                "c = lambda r: np.round(np.stack([256 + r * np.cos(th), 256 + r * np.sin(th)], 1))\n"
                "assert round(chamfer_distance(ink_mask([c(100)]), ink_mask([c(110)])), 3) == 9.684"
            ),
        ],
        "ok",
    )
    return out


def _text(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def _svg(body: str) -> str:
    return f'<svg xmlns="http://www.w3.org/2000/svg" viewBox="0 0 200 200">{body}</svg>'


def _laughs() -> str:
    entities = '<!ENTITY l0 "ha">' + "".join(f'<!ENTITY l{i} "{("&l" + str(i - 1) + ";") * 10}">' for i in range(1, 10))
    return f'<?xml version="1.0"?><!DOCTYPE svg [{entities}]><svg xmlns="http://www.w3.org/2000/svg"><text>&l9;</text></svg>'


def classify(probe: Probe, result: subprocess.CompletedProcess | None, error: str) -> tuple[str, str]:
    if error:
        return "wrong", error
    if result is None:
        return "hang", ""
    text = result.stdout + result.stderr
    lines = result.stderr.strip().splitlines() or [""]
    last = next((line for line in lines if probe.mention and probe.mention in line), lines[-1]).strip("│ ")[:200]
    if "Traceback (most recent call last)" in text:
        return "traceback", last
    problem = probe.check(result) if probe.check else ""
    if probe.expect == "error":
        if result.returncode == 0:
            return "accepted", "exit 0"
        if problem:
            return "wrong", problem
        return ("clear error" if probe.mention in text else "unclear message"), last
    if result.returncode != 0:
        return "wrong", f"refused: {last}"
    return ("wrong", problem) if problem else ("handled", "")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=Path("runs/probes"))
    parser.add_argument("--timeout", type=float, default=120.0, help="seconds before a probe counts as a hang")
    parser.add_argument("--only", default="", help="run only probes whose name contains this")
    args = parser.parse_args()
    shutil.rmtree(args.out, ignore_errors=True)
    ws = Workspace(args.out.resolve() / "ws")
    ws.root.mkdir(parents=True)
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    print("setting up: a debug store and a 2-step debug run")
    for setup in (
        ["draw", "generate", "--preset", "debug", "--workers", "1", "--out", str(ws.store)],
        ["train", "--data", str(ws.store), "--out", str(ws.run), *RUN],
    ):
        done = bpp(*setup, timeout=600)
        if done.returncode:
            sys.exit(done.stderr[-2000:])
    rows = []
    for probe in probes(ws):
        if args.only and args.only not in probe.name:
            continue
        start = time.perf_counter()
        result, error = None, ""
        try:
            argv = probe.argv()
            if argv[0] == "python":
                result = subprocess.run(
                    [sys.executable, "-c", argv[1]], capture_output=True, text=True, timeout=args.timeout, check=False
                )
            else:
                result = bpp(*argv, timeout=args.timeout)
        except subprocess.TimeoutExpired:
            result = None
        except Exception as err:  # noqa: BLE001 - a probe's own preparation failed: report it, go on
            error = f"probe setup failed: {type(err).__name__}: {err}"
        outcome, detail = classify(probe, result, error)
        seconds = time.perf_counter() - start
        rows.append((probe, outcome, detail, seconds))
        print(f"[{probe.group}] {outcome:15s} {seconds:5.1f}s  {probe.name}" + (f"  ({detail})" if detail else ""))
    report = _report(rows, args.timeout)
    (args.out / "probes.md").write_text(report)
    print(report)
    shutil.rmtree(ws.root, ignore_errors=True)


def _report(rows, timeout: float) -> str:
    lines = ["| class | probes | " + " | ".join(OUTCOMES) + " |", "|---|---:|" + "---:|" * len(OUTCOMES)]
    for group, title in CLASSES.items():
        mine = [r for r in rows if r[0].group == group]
        if mine:
            count = Counter(r[1] for r in mine)
            lines.append(f"| {group}. {title} | {len(mine)} | " + " | ".join(str(count[o]) for o in OUTCOMES) + " |")
    total = Counter(r[1] for r in rows)
    lines.append(f"| all | {len(rows)} | " + " | ".join(str(total[o]) for o in OUTCOMES) + " |")
    lines += [
        "",
        f"Hang: over {timeout:.0f} s.",
        "",
        "| class | probe | outcome | seconds | detail |",
        "|---|---|---|---:|---|",
    ]
    for probe, outcome, detail, seconds in rows:
        detail = detail.replace("|", "/").replace("\n", " ")[:160]
        lines.append(f"| {probe.group} | {probe.name} | {outcome} | {seconds:.1f} | {detail} |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
