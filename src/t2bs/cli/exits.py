"""How the CLI ends: a user's mistake is one ``error:`` line and exit 2, Ctrl-C exit 130, a bug a traceback."""

from __future__ import annotations

import sys

import typer

from t2bs.errors import INTERRUPTED, UserError, os_error_line


def exit_on_user_error(app) -> None:
    """Run a typer/click ``app`` so that every failure the user can act on is one line and exit 2.

    A UserError, a bad command line (click's usage errors: typer would draw a multi-line box), an
    OSError (read-only folder, full disk, no permission: named with its path) and an exhausted
    memory each print ``error: ...`` on one line on stderr. Ctrl-C prints INTERRUPTED and exits
    130. Anything else is a bug and keeps its traceback. The app runs with click's
    ``standalone_mode=False``, so these reach this function instead of click's own handlers."""
    try:  # typer >= 0.26 vendors click as typer._click; older ones use click itself
        from typer._click.exceptions import ClickException, NoArgsIsHelpError
    except ImportError:
        from click.exceptions import ClickException, NoArgsIsHelpError
    try:
        rc = app(standalone_mode=False)
    except UserError as exc:
        _fail(str(exc))
    except typer.Abort as exc:  # typer turns EOFError (reading an empty file) into Abort
        cause = exc.__cause__ or exc.__context__
        _fail("unexpected end of input" + (f" ({cause})" if cause and str(cause) else " (an empty or truncated file?)"))
    except NoArgsIsHelpError as exc:  # `t2bs` alone: the help, as before
        exc.show()
        sys.exit(exc.exit_code)
    except ClickException as exc:
        _fail(exc.format_message())
    except OSError as exc:
        _fail(os_error_line(exc))
    except MemoryError:
        _fail("out of memory (the input is too large for this machine; see docs/HOSTILE_INPUTS.md for the size limits)")
    if rc == 130:  # typer's answer to KeyboardInterrupt in non-standalone mode
        print(INTERRUPTED, file=sys.stderr, flush=True)
    sys.exit(rc if isinstance(rc, int) else 0)


def _fail(message: str) -> None:
    line = " ".join(str(message).split())  # one line whatever the message held
    print(f"error: {line}", file=sys.stderr, flush=True)
    sys.exit(2)


def run_command(fn) -> None:
    """``typer.run(fn)`` for a standalone script (benchmarks/), with ``exit_on_user_error``."""
    app = typer.Typer(add_completion=False, pretty_exceptions_enable=False)
    app.command()(fn)
    exit_on_user_error(app)
