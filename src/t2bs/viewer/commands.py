"""`t2bs view DIR`: serve the project's web viewer until Ctrl-C (SIGINT) or SIGTERM."""

from __future__ import annotations

import ipaddress
import signal
import sys
import threading
from pathlib import Path

import typer

from t2bs.cli.exits import exit_on_user_error
from t2bs.errors import UserError


def exposure_warning(host: str) -> str | None:
    """The warning printed when --host makes the viewer reachable from other machines (None: loopback)."""
    if host.strip().lower() == "localhost":
        return None
    try:
        if ipaddress.ip_address(host.strip().strip("[]")).is_loopback:
            return None
    except ValueError:  # a host name: it resolves to whatever the network says
        pass
    return (f"warning: serving on {host}: anyone who can reach this machine on that address can open the viewer "
            "and read the project (no authentication)")


def check_bindable(host: str) -> None:
    """UserError unless this machine can listen on ``host`` (tried on a free port, closed at once).

    viser binds in a background thread: an address that is not this machine's only logged a
    warning there while the command waited forever (issue 39), so the address is tried here first."""
    import socket

    name = host.strip().strip("[]")
    try:
        infos = socket.getaddrinfo(name, 0, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except (socket.gaierror, UnicodeError) as exc:
        raise UserError(f"--host {host}: cannot resolve the address ({getattr(exc, 'strerror', None) or exc})") from None
    errors = []
    for family, kind, proto, _, addr in infos:
        try:
            with socket.socket(family, kind, proto) as sock:
                sock.bind(addr)
                return
        except OSError as exc:
            errors.append(exc.strerror or str(exc))
    raise UserError(f"--host {host}: this machine cannot listen on that address ({errors[0] if errors else 'no address'}); "
                    "use 127.0.0.1, 0.0.0.0 or one of this machine's own addresses")


def view_command(
    project_dir: Path = typer.Argument(..., help="Project folder (made by `t2bs create` or the stage commands)."),
    port: int = typer.Option(8080, "--port", help="Port to serve on (0 = any free port; a busy port moves to the next free one)."),
    host: str = typer.Option("127.0.0.1", "--host", help="Address to bind. The default serves this machine only; "
                             "0.0.0.0 exposes the viewer (no authentication) to the network."),
    splats: bool = typer.Option(False, "--splats", help="Start with the character drawn as Gaussian splats instead of the mesh."),
) -> None:
    """Web page with the character, one slider per blendshape, captures and retargeting playback."""
    from t2bs.viewer.app import ViewerApp

    if not host.strip():
        raise UserError("--host must not be empty")
    check_bindable(host)
    warning = exposure_warning(host)
    if warning:
        print(warning, file=sys.stderr, flush=True)
    stop = threading.Event()

    def _on_signal(signum, _frame) -> None:
        stop.set()

    # Installed before the server starts, so a signal during start-up still shuts it down cleanly.
    previous = {sig: signal.signal(sig, _on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}
    app = None
    try:
        app = ViewerApp(project_dir, host=host, port=port, splats=splats)
        if port and app.port != port:
            print(f"warning: port {port} is busy, using {app.port}", file=sys.stderr, flush=True)
        print(f"t2bs viewer: {app.url}  (Ctrl-C to stop)", flush=True)
        while not stop.wait(0.25):  # a timed wait lets the signal handler run promptly
            pass
    finally:
        if app is not None:
            app.stop()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    print("t2bs viewer: stopped", flush=True)


def main() -> None:
    """Entry point of `python -m t2bs.viewer` (same as `t2bs view`)."""
    app = typer.Typer(add_completion=False, pretty_exceptions_enable=False)
    app.command()(view_command)
    exit_on_user_error(app)
