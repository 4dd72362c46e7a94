"""Serve a project's web viewer until Ctrl-C (SIGINT), SIGTERM or a stop event (`t2bs view DIR`)."""

from __future__ import annotations

import ipaddress
import os
import signal
import sys
import threading
from dataclasses import dataclass

from t2bs.errors import UserError
from t2bs.project import Project


@dataclass
class ViewConfig:
    port: int = 8080  # port to serve on (0 = any free port; a busy port moves to the next free one)
    host: str = "127.0.0.1"  # address to bind: loopback serves this machine only; 0.0.0.0 exposes it (no auth)
    splats: bool = False  # start with the character drawn as Gaussian splats instead of the mesh


def exposure_warning(host: str) -> str | None:
    """The warning printed when --host makes the viewer reachable from other machines (None: loopback)."""
    if host.strip().lower() == "localhost":
        return None
    try:
        if ipaddress.ip_address(host.strip().strip("[]")).is_loopback:
            return None
    except ValueError:  # a host name: it resolves to whatever the network says
        pass
    return (
        f"warning: serving on {host}: anyone who can reach this machine on that address can open the viewer "
        "and read the project (no authentication)"
    )


def check_bindable(host: str) -> None:
    """UserError unless this machine can listen on ``host`` (tried on a free port, closed at once).

    viser binds in a background thread: an address that is not this machine's only logged a
    warning there while the command waited forever (issue 39), so the address is tried here first."""
    import socket

    name = host.strip().strip("[]")
    try:
        infos = socket.getaddrinfo(name, 0, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except (socket.gaierror, UnicodeError) as exc:
        why = getattr(exc, "strerror", None) or exc
        raise UserError(f"--host {host}: cannot resolve the address ({why})") from None
    errors = []
    for family, kind, proto, _, addr in infos:
        try:
            with socket.socket(family, kind, proto) as sock:
                sock.bind(addr)
                return
        except OSError as exc:
            errors.append(exc.strerror or str(exc))
    raise UserError(
        f"--host {host}: this machine cannot listen on that address "
        f"({errors[0] if errors else 'no address'}); "
        "use 127.0.0.1, 0.0.0.0 or one of this machine's own addresses"
    )


def serve(
    project: Project | str | os.PathLike, config: ViewConfig = ViewConfig(), stop: threading.Event | None = None
) -> None:
    """Web page with the character, one slider per blendshape, captures and retargeting playback; blocks.

    Reads the project folder (character/mesh.glb, blendshapes/model.npz, videos/, recon/, retarget/, whatever
    exists) and serves it with viser on ``config.host``:``config.port`` until SIGINT or SIGTERM arrives (called
    from the main thread, the handlers are installed for the call and the previous ones restored) or ``stop``
    is set. Prints a warning on stderr when the address is reachable from other machines or the port was busy,
    the URL on stdout (``t2bs viewer: http://...``), and ``t2bs viewer: stopped`` at the end.

    Writes nothing itself (the page's captures and landmark picks write into the project). Takes no project
    lock: the viewer only reads the stages' outputs, and a stage may run while it is open.

    Raises UserError for an empty or unbindable host and for a project the viewer cannot show (no character,
    a broken mesh), before anything is served.
    """
    from t2bs.viewer.app import ViewerApp

    root = project.root if isinstance(project, Project) else project
    host, port = config.host, config.port
    if not host.strip():
        raise UserError("--host must not be empty")
    check_bindable(host)
    warning = exposure_warning(host)
    if warning:
        print(warning, file=sys.stderr, flush=True)
    stop = stop if stop is not None else threading.Event()

    def _on_signal(signum, _frame) -> None:
        stop.set()

    # Installed before the server starts, so a signal during start-up still shuts it down cleanly. Python
    # takes signal handlers in the main thread only: a serve() in another thread stops through ``stop``.
    in_main = threading.current_thread() is threading.main_thread()
    previous = {sig: signal.signal(sig, _on_signal) for sig in (signal.SIGINT, signal.SIGTERM)} if in_main else {}
    app = None
    try:
        app = ViewerApp(root, host=host, port=port, splats=config.splats)
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
