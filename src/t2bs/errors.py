"""User-facing errors: one line, exit code 2, no traceback (see cli.main)."""


class UserError(Exception):
    """A problem with the user's input (file, prompt, folder), not a bug in t2bs.

    The CLI prints ``error: <message>`` on one line and exits with code 2.
    """


class MissingCheckpointError(UserError):
    """A real generative backend was asked for, but its local weights are not there."""

    def __init__(self, what: str, where: str, how: str):
        super().__init__(f"{what} not found at {where}: {how}")


def exit_on_user_error(call) -> None:
    """Run ``call()``; a UserError (a user mistake, not a bug) becomes one line on stderr and exit code 2."""
    import sys

    try:
        call()
    except UserError as exc:
        print(f"error: {exc}", file=sys.stderr)
        sys.exit(2)


def run_command(fn) -> None:
    """``typer.run(fn)`` for a standalone script (benchmarks/), with ``exit_on_user_error``."""
    import typer

    exit_on_user_error(lambda: typer.run(fn))
