"""User-facing errors: one line, exit code 2, no traceback (the CLI prints them: t2bs.cli.exits)."""


class UserError(Exception):
    """A problem with the user's input (file, prompt, folder), not a bug in t2bs.

    The CLI prints ``error: <message>`` on one line and exits with code 2.
    """


class MissingCheckpointError(UserError):
    """A real generative backend was asked for, but its local weights are not there."""

    def __init__(self, what: str, where: str, how: str):
        super().__init__(f"{what} not found at {where}: {how}")


INTERRUPTED = "interrupted; finished jobs are kept, re-run to resume"


def os_error_line(exc: OSError) -> str:
    """One line for an OSError: the path(s) and what the system said (read-only, no space, ...)."""

    def short(name) -> str:
        name = str(name)
        return name if len(name) <= 200 else name[:200] + f"... ({len(name)} characters)"

    where = short(exc.filename) if exc.filename is not None else None
    what = exc.strerror or str(exc) or type(exc).__name__
    if where is not None and exc.filename2 is not None:
        return f"{where} -> {short(exc.filename2)}: {what}"
    return f"{where}: {what}" if where is not None else what
