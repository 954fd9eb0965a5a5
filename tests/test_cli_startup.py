"""The command line answers at once: ``bpp --help`` and every command's ``--help`` import no torch (nor Ray), and
parsing a command's flags contacts no Ray cluster. torch is imported when a command that builds a model runs."""

import subprocess
import sys
import textwrap

HEAVY = ("torch", "ray")
"""Modules that take seconds to import and that no command's flags need."""


def _python(code: str) -> subprocess.CompletedProcess:
    """`code` in a fresh interpreter (nothing imported yet, whatever this test process has loaded)."""
    return subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True, timeout=300)


def test_help_of_every_command_imports_no_torch():
    result = _python(
        f"""
        import contextlib, io, sys

        from bpp import cli
        from bpp.policies.registry import METHODS

        commands = [list(words) for words, _ in cli._command_classes()]
        runs = [
            ["--help"],
            *([*words, "--help"] for words in commands),
            *([group] for group in sorted(cli._groups())),
            *(["train", "--method", method, "--preset", preset, "--help"] for method in METHODS
              for preset in ("debug", "cpu", "paper")),
        ]
        for argv in runs:
            with contextlib.redirect_stdout(io.StringIO()):
                try:
                    cli.main(argv)
                except SystemExit as exit:
                    assert exit.code in (0, None), (argv, exit.code)
            loaded = [name for name in {HEAVY!r} if name in sys.modules]
            assert not loaded, f"bpp {{' '.join(argv)}} imported {{loaded}}"
        print(len(commands))
        """
    )
    assert result.returncode == 0, result.stderr[-3000:]
    assert int(result.stdout) >= 20  # every benchmark's commands were asked, not an empty list


def test_the_bpp_program_starts_without_torch():
    """``python -m bpp --help`` as a shell runs it (through bpp.launch): torch is not among the modules it imports."""
    result = subprocess.run(
        [sys.executable, "-X", "importtime", "-m", "bpp", "--help"], capture_output=True, text=True, timeout=300
    )
    assert result.returncode == 0, result.stderr[-3000:]
    lines = [line for line in result.stderr.splitlines() if line.startswith("import time:")]
    imported = {line.rsplit("|", 1)[-1].strip() for line in lines}
    assert "bpp.cli" in imported  # the listing is the program's imports
    assert not imported & set(HEAVY), sorted(imported & set(HEAVY))


def test_parsing_executor_flags_contacts_no_cluster():
    """A Ray cluster's address is reached when the command runs, not while its flags are parsed (nor for --help)."""
    result = _python(
        """
        import contextlib, io, socket, sys

        from bpp import cli
        from bpp.errors import UserError
        from bpp.executor import RAY_MISSING

        def contact(*args, **kwargs):
            raise AssertionError(f"contacted {args}")

        socket.create_connection = contact
        address = "127.0.0.1:1"
        for make in (
            lambda: cli.Generate(out="x.zarr", executor="ray", ray_address=address),
            lambda: cli.Eval(checkpoints=("runs/x",), executor="ray", ray_address=address),
        ):
            try:
                make()
            except UserError as err:  # Ray is not installed: said without importing it
                assert str(err) == RAY_MISSING, err
        with contextlib.redirect_stdout(io.StringIO()):
            try:
                cli.main(["draw", "generate", "--executor", "ray", "--ray-address", address, "--help"])
            except SystemExit as exit:
                assert exit.code in (0, None), exit.code
        assert "ray" not in sys.modules, "ray was imported"
        print("ok")
        """
    )
    assert result.returncode == 0, result.stderr[-3000:]
    assert result.stdout.strip() == "ok"
