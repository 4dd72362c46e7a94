"""User-facing errors: one line, exit code 2, no traceback (see cli.main)."""


class UserError(Exception):
    """A problem with the user's input (file, prompt, folder), not a bug in t2bs.

    The CLI prints ``error: <message>`` on one line and exits with code 2.
    """


class MissingCheckpointError(UserError):
    """A real generative backend was asked for, but its local weights are not there."""

    def __init__(self, what: str, where: str, how: str):
        super().__init__(f"{what} not found at {where}: {how}")


def run_command(fn) -> None:
    """``typer.run(fn)`` for a standalone script (benchmarks/): a UserError becomes one line and exit code 2."""
    import sys

    import typer

    try:
        typer.run(fn)
    except UserError as exc:
        print(f"error: {exc}", file=sys.stderr)
        sys.exit(2)
