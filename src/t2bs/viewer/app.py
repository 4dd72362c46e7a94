"""The web viewer (issue 10): a viser server that shows a project's character and what was made from it.

What a user opens first after a run: the character (vertex colours; Gaussian splats as an option),
one slider per blendshape (PCA components and named semantic shapes of ``blendshapes/model.npz``;
the character's own rig morph targets when no model was built yet), a reset button, a capture
picker that plays a reconstructed expression (``recon/<video_id>/vertices.npy``) next to its input
frames (the canonical view of ``videos/<video_id>/``), and playback of a retargeting result
(``retarget/<name>/weights.csv``). The camera starts at the frontal view of the pipeline's renders.

Why the mesh is re-sent as a small GLB on every change: viser's simple mesh node has one colour per
mesh, and vertex colours (the character's texture sampled per vertex) only reach three.js through a
glTF ``COLOR_0`` attribute. Changes are coalesced by one worker thread (latest state wins), so a
dragged slider never queues more frames than the client can draw.

Python API (used by the tests and scripts)::

    app = ViewerApp("fox/", port=0)          # port 0: any free port; app.url says which
    app.set_weights({"pc000": 0.3})          # waits until the new mesh was queued to the clients
    app.show_capture("smile-s0", frame=5)
    app.show_retarget("face", frame=10)
    app.stop()
"""

from __future__ import annotations

import csv
import math
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from t2bs.errors import UserError
from t2bs.geometry.camera import ORBIT_FOV_Y, frontal_camera
from t2bs.geometry.mesh import Mesh, incident_edge_lengths, vertex_normals
from t2bs.geometry.io import glb_bytes

TIME_COLUMNS = ("time", "t", "time_s", "seconds", "timestamp")  # weights.csv: seconds per row
FRAME_COLUMNS = ("frame", "index", "frame_index")  # weights.csv: row index, ignored for timing
DEFAULT_CAPTURE_FPS = 8.0  # when a capture's grid is missing (the quick pipeline's videos run at 8 fps)
DEFAULT_RETARGET_FPS = 30.0  # when weights.csv has no time column
CAPTURE_CACHE = 4  # reconstructed captures kept in memory
MESH_NODE = "/character/mesh"
SPLAT_NODE = "/character/splats"


# ----------------------------------------------------------------------------------- project data


@dataclass
class Shape:
    """One slider: vertex offsets at value 1, and the slider's range."""

    name: str  # unique key used by set_weights (PCA "pc000", semantic "jaw_open", rig "rig:smile")
    group: str  # "arkit/<eyes|brows|jaw|mouth|cheeks|nose|tongue>" | "semantic" | "pca" | "rig": its GUI folder
    offsets: np.ndarray  # [N, 3] float32 displacement per unit of the slider
    lo: float  # slider minimum
    hi: float  # slider maximum


@dataclass
class Capture:
    video_id: str
    vertices: np.ndarray  # [T, N, 3] float32 reconstructed vertices (canonical view frame)
    frames: np.ndarray | None  # [T', H, W, 3] uint8 canonical-view input frames, None if no grid
    times: np.ndarray  # [T] float seconds of each reconstructed frame
    note: str = ""  # why frames are missing or do not line up, shown under the image


@dataclass
class Retarget:
    name: str
    times: np.ndarray  # [T] float seconds
    weights: np.ndarray  # [T, M] slider values per frame, columns = shape_idx
    shape_idx: np.ndarray  # [M] int index into the viewer's shapes for each weight column
    ignored: list[str] = field(default_factory=list)  # csv columns that name no shape

    @property
    def note(self) -> str:
        """Shown under the retargeting panel's slider."""
        return f"ignored columns: {', '.join(self.ignored)}" if self.ignored else ""


def load_character(root: Path) -> Mesh:
    """The mesh to show: character/mesh.glb, else the blendshape model's glb (same topology)."""
    from t2bs.geometry.io import load_mesh

    for rel in (("character", "mesh.glb"), ("blendshapes", "model.glb")):
        path = root.joinpath(*rel)
        if path.exists():
            return load_mesh(path)
    raise UserError(
        f"{root}: nothing to view (no character/mesh.glb or blendshapes/model.glb); run `t2bs create` or `t2bs render` first"
    )


def _pca_range(basis_k: np.ndarray, capture_w: np.ndarray | None, diag: float) -> float:
    """Half-range of a PCA slider: 1.25x the largest weight seen in the captures, else the weight
    that moves some vertex by 10 % of the bounding-box diagonal (rows are unit-norm over 3N)."""
    if capture_w is not None and capture_w.size and np.isfinite(capture_w).all() and np.abs(capture_w).max() > 0:
        return float(1.25 * np.abs(capture_w).max())
    peak = float(np.linalg.norm(basis_k, axis=1).max())
    return float(0.1 * diag / peak) if peak > 0 else 1.0


def load_shapes(root: Path, mesh: Mesh) -> tuple[np.ndarray, list[Shape], str]:
    """(neutral [N, 3], sliders, description) from blendshapes/model.npz, else the mesh's rig."""
    n = mesh.num_vertices
    diag = max(mesh.bbox_diagonal(), 1e-6)
    path = root / "blendshapes" / "model.npz"
    if not path.exists():
        shapes = [Shape(f"rig:{k}", "rig", np.asarray(d, np.float32), 0.0, 1.0) for k, d in mesh.morph_targets.items()]
        what = f"no blendshape model yet; {len(shapes)} rig morph targets of the character"
        return mesh.vertices.astype(np.float32), shapes, what
    from t2bs.blendshapes.model import load_model

    model = load_model(path)
    if model.num_vertices != n:
        raise UserError(f"{path}: model has {model.num_vertices} vertices but the character mesh has {n}")
    shapes: list[Shape] = []
    # ARKit shapes first (the names capture apps and engines speak), grouped like Apple's list.
    from t2bs.face.arkit import ARKIT_GROUP_OF, load_arkit_shapes

    arkit = load_arkit_shapes(root / "blendshapes" / "arkit.json", model.num_components)
    if arkit is not None and arkit.names:
        for name, off in zip(arkit.names, model.offsets(arkit.weights)):
            shapes.append(Shape(name, f"arkit/{ARKIT_GROUP_OF[name]}", off.astype(np.float32), 0.0, 1.0))
    # Then the prompt-named shapes, read defensively: older files may carry only the offsets, or nothing.
    sem_names = list(model.semantic_names)
    sem_off = model.semantic_offsets() if model.semantic_weights is not None else None
    if sem_names and (sem_off is None or sem_off.shape[0] != len(sem_names)):
        with np.load(path, allow_pickle=False) as z:
            raw = z["semantic_offsets"] if "semantic_offsets" in z.files else None
        sem_off = raw if raw is not None and raw.shape == (len(sem_names), n, 3) else None
    if sem_names and sem_off is not None:
        for name, off in zip(sem_names, sem_off):
            shapes.append(Shape(str(name), "semantic", np.asarray(off, np.float32), 0.0, 1.0))
    allw = np.concatenate(list(model.capture_weights.values())) if model.capture_weights else None  # [M, K]
    for k in model.visible_components():  # the components that move something visible (model.py)
        name = model.names[k]
        r = _pca_range(
            model.basis[k], None if allw is None or allw.shape[1] != model.num_components else allw[:, k], diag
        )
        shapes.append(Shape(str(name), "pca", model.basis[k].astype(np.float32), -r, r))
    names = [s.name for s in shapes]
    if len(set(names)) != len(names):
        dup = sorted({x for x in names if names.count(x) > 1})
        raise UserError(f"{path}: blendshape names are not unique ({', '.join(dup)})")
    what = (
        f"{len([s for s in shapes if s.group.startswith('arkit/')])} ARKit shapes, "
        f"{len([s for s in shapes if s.group == 'semantic'])} named shapes, "
        f"{len(model.visible_components())} of {model.num_components} PCA components (the visible ones)"
    )
    return model.neutral.astype(np.float32), shapes, what


NONE = "(none)"  # a timeline dropdown's entry for "nothing chosen"


@dataclass
class Timeline:
    """The GUI of one timeline panel, captures or retargeting results (viser handles)."""

    kind: str  # "capture" | "retarget": the mode tag (``ViewerApp.mode``) and ``set_playing``'s name
    title: str  # its word in the status line ("capture", "retargeting")
    dropdown: object  # which capture / result; NONE when nothing is chosen
    frame: object  # frame slider
    play: object  # play checkbox
    note: object  # markdown under the slider: load errors and what does not line up
    image: object | None = None  # the input's canonical view at the shown frame (captures only)


def list_captures(root: Path) -> list[str]:
    d = root / "recon"
    return sorted(p.parent.name for p in d.glob("*/vertices.npy")) if d.is_dir() else []


def list_retargets(root: Path) -> list[str]:
    d = root / "retarget"
    return sorted(p.parent.name for p in d.glob("*/weights.csv")) if d.is_dir() else []


def load_capture(root: Path, video_id: str, n: int) -> Capture:
    """Reconstructed vertices of one capture and the canonical view of its input grid."""
    vpath = root / "recon" / video_id / "vertices.npy"
    from t2bs.project import read_array

    verts = read_array(vpath, "reconstructed vertices", finite=False)  # empty, torn or pickled: one error line
    if verts.ndim != 3 or verts.shape[1:] != (n, 3) or verts.shape[0] == 0:
        raise UserError(f"{vpath}: vertices {verts.shape} do not match the character [T, {n}, 3]")
    if not np.isfinite(verts).all():
        raise UserError(f"{vpath}: vertices contain NaN or infinite values")
    t = verts.shape[0]
    frames, note = None, ""
    times = np.arange(t) / DEFAULT_CAPTURE_FPS
    gdir = root / "videos" / video_id
    if (gdir / "grid.json").exists():
        from t2bs.video.grid import load_grid, read_rgb, read_video

        grid = load_grid(gdir, load_frames=False)  # cameras and times only; one view is read below
        fdir = gdir / "frames"
        cv = grid.canonical_view
        if (fdir / f"view{cv:02d}.mp4").exists():
            frames = read_video(fdir / f"view{cv:02d}.mp4")
        else:
            frames = np.stack([read_rgb(fdir / f"view{cv:02d}" / f"{i:04d}.png") for i in range(grid.num_frames)])
        if grid.num_frames == t:
            times = np.asarray(grid.times, np.float64)
        else:
            note = f"the grid has {grid.num_frames} frames, the reconstruction {t}: frames shown by index"
    else:
        note = f"no input grid at videos/{video_id}/"
    return Capture(video_id, verts.astype(np.float32), frames, times, note)


def load_retarget(root: Path, name: str, shapes: list[Shape]) -> Retarget:
    """weights.csv: a header row naming shapes (PCA names, semantic names, or rig names with or
    without the ``rig:`` prefix), an optional time column in seconds, one row per frame."""
    path = root / "retarget" / name / "weights.csv"
    try:
        with open(path, newline="") as f:
            rows = [r for r in csv.reader(f) if r and any(c.strip() for c in r)]
    except (OSError, UnicodeDecodeError) as exc:
        raise UserError(f"{path}: unreadable ({exc})") from None
    if len(rows) < 2:
        raise UserError(f"{path}: needs a header row and at least one frame")
    header = [h.strip() for h in rows[0]]
    try:
        data = np.array([[float(c) for c in r] for r in rows[1:]], dtype=np.float64)
    except ValueError as exc:
        raise UserError(f"{path}: non-numeric value ({exc})") from None
    if data.ndim != 2 or data.shape[1] != len(header):
        raise UserError(f"{path}: rows do not all have {len(header)} columns like the header")
    if not np.isfinite(data).all():
        raise UserError(f"{path}: NaN or infinite weights")
    index = {s.name: i for i, s in enumerate(shapes)}
    index.update({s.name[4:]: i for i, s in enumerate(shapes) if s.name.startswith("rig:") and s.name[4:] not in index})
    times = None
    cols, idx, ignored = [], [], []
    for j, h in enumerate(header):
        key = h.lower()
        if key in TIME_COLUMNS and times is None:
            times = data[:, j]
        elif key in FRAME_COLUMNS:
            continue
        elif h in index:
            cols.append(j)
            idx.append(index[h])
        else:
            ignored.append(h)
    if not cols:
        raise UserError(f"{path}: no column names a blendshape of this viewer (have {', '.join(header[:6])}...)")
    if times is None:
        times = np.arange(data.shape[0]) / DEFAULT_RETARGET_FPS
    if data.shape[0] > 1 and np.any(np.diff(times) <= 0):
        raise UserError(f"{path}: times must increase")
    return Retarget(name, times, data[:, cols], np.asarray(idx), ignored)


# ------------------------------------------------------------------------------------ geometry


def vertex_splat_sigma(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """[N] tangential std-dev of one Gaussian per vertex: half the mean incident edge length, so
    neighbouring splats overlap into a closed surface."""
    mean, count, _ = incident_edge_lengths(vertices, faces)
    fallback = np.median(mean[count > 0]) if (count > 0).any() else 0.01
    return np.where(count > 0, 0.5 * mean, 0.5 * fallback)


def splat_covariances(vertices: np.ndarray, faces: np.ndarray, sigma_t: np.ndarray) -> np.ndarray:
    """[N, 3, 3] flat disc Gaussians in the tangent plane: s_t^2 (I - n n^T) + s_n^2 n n^T, s_n = s_t / 10."""
    n = vertex_normals(vertices, faces).astype(np.float64)  # [N, 3]
    nn = n[:, :, None] * n[:, None, :]  # [N, 3, 3]
    st2 = (sigma_t**2)[:, None, None]
    return (st2 * (np.eye(3)[None] - nn) + 0.01 * st2 * nn).astype(np.float32)


# ------------------------------------------------------------------------------------------ app


class ViewerApp:
    """A running viewer for one project folder (state: the server, its GUI and the shown pose)."""

    def __init__(
        self,
        project_dir: str | Path,
        host: str = "127.0.0.1",
        port: int = 8080,
        splats: bool = False,
        verbose: bool = False,
    ):
        try:
            import viser
        except ImportError:
            raise UserError("the viewer needs viser: pip install 't2bs[viewer]' (or pip install viser)") from None
        self.root = Path(project_dir)
        if not self.root.is_dir():
            raise UserError(f"{self.root}: no such project folder")
        if not 0 <= int(port) <= 65535:
            raise UserError(f"--port must be 0..65535, got {port}")
        self.mesh = load_character(self.root)
        self.neutral, self.shapes, self.shapes_info = load_shapes(self.root, self.mesh)
        n = self.mesh.num_vertices
        self.faces = self.mesh.faces.astype(np.int64)
        self.colors = self.mesh.vertex_rgb().astype(np.float32)  # [N, 3] display colours
        # What the browser gets on every change: this mesh with the shown vertices (vertex colours, no morph targets).
        self._display = Mesh(self.neutral, self.faces, vertex_colors=self.colors)
        self._stack = (
            np.stack([s.offsets for s in self.shapes]).reshape(len(self.shapes), -1)
            if self.shapes
            else np.zeros((0, n * 3), np.float32)
        )  # [M, 3N]
        self._sigma = vertex_splat_sigma(self.neutral, self.faces)
        self.capture_ids = list_captures(self.root)
        self.retarget_names = list_retargets(self.root)
        self._captures: dict[str, Capture] = {}
        self._retargets: dict[str, Retarget] = {}

        self._lock = threading.RLock()
        self._values = np.zeros(len(self.shapes), np.float64)  # [M] slider values
        self._mode: tuple = ("shapes",)  # ("shapes",) | ("capture", id, t) | ("retarget", name, t)
        self._open_at = 0  # frame at which a capture / retargeting chosen in its dropdown opens (_open sets it)
        self._requested = 0  # version of the newest state
        self._pushed = 0  # version of the newest state queued to the clients
        self._pushed_cv = threading.Condition()
        self._dirty = threading.Event()
        self._stopping = threading.Event()
        self._shown_vertices = self.neutral.copy()
        self._bulk = False  # set while set_weights/reset move many sliders: one redraw at the end
        self._play_start: dict[str, tuple[float, float]] = {}  # kind -> (wall clock, media time) at play

        self.server = viser.ViserServer(host=host, port=int(port), label="t2bs", verbose=verbose)
        try:
            self._build_scene(splats)
            self._build_gui(splats)
        except BaseException:
            self.server.stop()
            raise
        self._worker = threading.Thread(target=self._redraw_loop, name="t2bs-viewer-redraw", daemon=True)
        self._player = threading.Thread(target=self._play_loop, name="t2bs-viewer-play", daemon=True)
        self._worker.start()
        self._player.start()
        self._schedule()
        self.wait_idle()

    # ------------------------------------------------------------------------- public API

    @property
    def host(self) -> str:
        return self.server.get_host()

    @property
    def port(self) -> int:
        return int(self.server.get_port())

    @property
    def url(self) -> str:
        host = self.host
        host = "127.0.0.1" if host in ("0.0.0.0", "") else (f"[{host}]" if ":" in host else host)
        return f"http://{host}:{self.port}"

    @property
    def shape_names(self) -> list[str]:
        return [s.name for s in self.shapes]

    @property
    def weights(self) -> dict[str, float]:
        with self._lock:
            return {s.name: float(v) for s, v in zip(self.shapes, self._values)}

    @property
    def mode(self) -> tuple:
        with self._lock:
            return self._mode

    def set_weights(self, weights: dict[str, float], wait: bool = True) -> None:
        """Move sliders by name (values clamped to each slider's range); shows the blendshapes."""
        index = {s.name: i for i, s in enumerate(self.shapes)}
        unknown = [k for k in weights if k not in index]
        if unknown:
            raise UserError(f"unknown blendshape {unknown[0]!r}; have {', '.join(index) or 'none'}")
        with self._lock:
            self._bulk = True
            try:
                for k, v in weights.items():
                    s = self.shapes[index[k]]
                    self._sliders[index[k]].value = float(min(max(float(v), s.lo), s.hi))
            finally:
                self._bulk = False
            self._show_shapes()
        if wait:
            self.wait_idle()

    def reset(self, wait: bool = True) -> None:
        """All sliders to 0 (the neutral character), playback stopped."""
        self.set_weights({s.name: 0.0 for s in self.shapes}, wait=wait)

    def show_capture(self, video_id: str, frame: int = 0, wait: bool = True) -> None:
        if video_id not in self.capture_ids:
            raise UserError(f"no reconstructed capture {video_id!r}; have {', '.join(self.capture_ids) or 'none'}")
        self._open("capture", video_id, frame, wait)

    def show_retarget(self, name: str, frame: int = 0, wait: bool = True) -> None:
        if name not in self.retarget_names:
            raise UserError(f"no retargeting result {name!r}; have {', '.join(self.retarget_names) or 'none'}")
        self._open("retarget", name, frame, wait)

    def set_playing(self, kind: str, playing: bool) -> None:
        """Start/stop playback of the selected capture ("capture") or retargeting ("retarget")."""
        if kind not in self._timelines:
            raise UserError(f"playback kind must be capture or retarget, got {kind!r}")
        self._timelines[kind].play.value = bool(playing)

    def current_vertices(self) -> np.ndarray:
        """[N, 3] the vertices the viewer shows (after wait_idle: what the clients were sent)."""
        with self._lock:
            return self._vertices_for(self._mode).copy()

    def wait_idle(self, timeout: float = 10.0) -> None:
        """Block until the newest state was queued to the clients."""
        deadline = time.monotonic() + timeout
        with self._pushed_cv:
            while self._pushed < self._requested and not self._stopping.is_set():
                left = deadline - time.monotonic()
                if left <= 0:
                    raise TimeoutError("viewer: redraw did not finish in time")
                self._pushed_cv.wait(left)

    def focus_frontal(self) -> None:
        """Move every connected browser's camera to the frontal view."""
        cam = frontal_camera()
        for client in self.server.get_clients().values():
            client.camera.up_direction = (0.0, 1.0, 0.0)
            client.camera.position = tuple(cam.position)
            client.camera.look_at = (0.0, 0.0, 0.0)
            client.camera.fov = math.radians(ORBIT_FOV_Y)

    def stop(self) -> None:
        if self._stopping.is_set():
            return
        self._stopping.set()
        self._dirty.set()
        with self._pushed_cv:
            self._pushed_cv.notify_all()
        for t in (getattr(self, "_worker", None), getattr(self, "_player", None)):
            if t is not None and t.is_alive() and t is not threading.current_thread():
                t.join(timeout=5.0)
        self.server.stop()

    def __enter__(self) -> "ViewerApp":
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

    # ------------------------------------------------------------------------- scene / GUI

    def _build_scene(self, splats: bool) -> None:
        s = self.server
        s.scene.set_up_direction("+y")  # the project's world is Y up
        cam = frontal_camera()  # position (0, 0.39, 2.22) looking at the origin, fov 30
        s.initial_camera.up = (0.0, 1.0, 0.0)
        s.initial_camera.position = tuple(float(x) for x in cam.position)
        s.initial_camera.look_at = (0.0, 0.0, 0.0)
        s.initial_camera.fov = math.radians(ORBIT_FOV_Y)
        s.initial_camera.near = 0.01
        # Lights instead of viser's image-based environment: its prefiltering takes 15-20 s on a
        # software WebGL (a headless browser, a remote desktop) before the first frame shows.
        # A hemisphere fill plus a key light from the camera's upper left, fixed in the world.
        s.scene.configure_environment_map(None)
        s.scene.configure_default_lights(False)
        s.scene.add_light_hemisphere(
            "/lights/fill", sky_color=(255, 255, 255), ground_color=(110, 100, 95), intensity=1.2
        )
        s.scene.add_light_point("/lights/key", intensity=2.0, position=(0.9, 1.3, 2.4), decay=0.0)
        self._mesh_handle = None
        self._splat_handle = None
        self._show_mesh = not splats
        self._show_splats = splats

    def _build_gui(self, splats: bool) -> None:
        gui = self.server.gui
        gui.add_markdown(f"**{self.root.name or self.root}** · {self.mesh.num_vertices} vertices · {self.shapes_info}")
        self._status = gui.add_markdown("Showing: blendshapes")

        with gui.add_folder("View"):
            frontal = gui.add_button("Frontal view")
            frontal.on_click(lambda _: self.focus_frontal())
            mesh_box = gui.add_checkbox("Mesh", initial_value=not splats)
            splat_box = gui.add_checkbox("Gaussian splats", initial_value=splats)
            env_box = gui.add_checkbox(
                "Environment light", initial_value=False, hint="image-based lighting; slow to start without a GPU"
            )

            @env_box.on_update
            def _(_event) -> None:
                self.server.scene.configure_environment_map("studio" if env_box.value else None)

            @mesh_box.on_update
            def _(_event) -> None:
                with self._lock:
                    self._show_mesh = bool(mesh_box.value)
                self._schedule()

            @splat_box.on_update
            def _(_event) -> None:
                with self._lock:
                    self._show_splats = bool(splat_box.value)
                self._schedule()

        self._timelines = {
            "capture": self._add_timeline(
                "capture",
                "capture",
                "Captures",
                ("Capture", "Capture frame", "Play capture"),
                self.capture_ids,
                "No reconstructed captures (`recon/VIDEO_ID/vertices.npy`).",
                image=True,
            ),
            "retarget": self._add_timeline(
                "retarget",
                "retargeting",
                "Retargeting",
                ("Result", "Retarget frame", "Play retargeting"),
                self.retarget_names,
                "No retargeting results (`retarget/NAME/weights.csv`).",
            ),
        }

        with gui.add_folder("Blendshapes"):
            reset = gui.add_button("Reset")
            reset.on_click(lambda _: self.reset(wait=False))
            if not self.shapes:
                gui.add_markdown("No blendshapes (run `t2bs blendshapes DIR`).")
            self._sliders: list = [None] * len(self.shapes)  # slider i drives shape i
            from t2bs.face.arkit import ARKIT_GROUPS

            arkit = [(i, s) for i, s in enumerate(self.shapes) if s.group.startswith("arkit/")]
            if arkit:
                with gui.add_folder(f"ARKit ({len(arkit)} of 52)"):
                    for sub in ARKIT_GROUPS:
                        members = [(i, s) for i, s in arkit if s.group == f"arkit/{sub}"]
                        if members:
                            with gui.add_folder(sub, expand_by_default=sub in ("eyes", "jaw")):
                                self._add_sliders(members)
            titles = {"semantic": "Named shapes", "pca": "PCA components", "rig": "Character rig"}
            for group in ("semantic", "pca", "rig"):
                members = [(i, s) for i, s in enumerate(self.shapes) if s.group == group]
                if not members:
                    continue
                with gui.add_folder(titles[group], expand_by_default=group != "pca" or len(members) <= 12):
                    self._add_sliders(members, strip="rig:" if group == "rig" else "")
        self._build_landmark_picker()

    def _add_sliders(self, members: list, strip: str = "") -> None:
        """One slider per (index, Shape) in the current GUI folder."""
        for i, s in members:
            label = s.name[len(strip) :] if strip and s.name.startswith(strip) else s.name
            step = float(f"{(s.hi - s.lo) / 200:.2g}") or 1e-3
            h = self.server.gui.add_slider(label, min=s.lo, max=s.hi, step=step, initial_value=0.0)
            h.on_update(self._slider_callback(i))
            self._sliders[i] = h

    def _build_landmark_picker(self) -> None:
        """Landmarks for the auto rig (issue 34): pick a point, click it on the character, save."""
        from t2bs.rig.pick import PICKED, SLOTS, LandmarkPicks

        gui = self.server.gui
        self.landmarks_path = self.root / "landmarks" / PICKED
        self.picks = LandmarkPicks.for_project(self.root, self.mesh.num_vertices)
        with gui.add_folder("Landmarks (auto rig)", expand_by_default=False):
            gui.add_markdown(
                "Click the 20 points (68-point numbers; right / left are the character's own) for "
                "`t2bs autorig --landmarks` and the video stage's auto rig."
            )
            labels = [f"{k}: {d}" for k, d in SLOTS]
            self._pick_slot = gui.add_dropdown(
                "Point",
                labels,
                initial_value=labels[SLOTS.index(next(x for x in SLOTS if x[0] == self.picks.next_slot()))],
            )
            self._pick_on = gui.add_checkbox("Pick by clicking", initial_value=False)
            save = gui.add_button("Save landmarks")
            self._pick_note = gui.add_markdown(self._picks_note())

        @self._pick_on.on_update
        def _(_event) -> None:
            if self._pick_on.value:
                self.server.scene.on_click()(lambda ev: self.pick_ray(ev.ray_origin, ev.ray_direction))
            else:
                self.server.scene.remove_click_callback("all")

        @save.on_click
        def _(_event) -> None:
            try:
                self._pick_note.content = f"Saved {self.save_landmarks()}"
            except UserError as e:
                self._pick_note.content = f"Not saved: {e}"

    def _picks_note(self) -> str:
        missing = self.picks.missing()
        return f"{20 - len(missing)} of 20 picked" + (f"; missing {', '.join(missing)}" if missing else "")

    def pick_ray(self, origin, direction) -> int | None:
        """Set the chosen landmark to the vertex a click ray (world frame) hits; moves to the next point."""
        from t2bs.rig.pick import SLOTS, ray_vertex

        with self._lock:
            verts = self._shown_vertices.copy()
        vid = ray_vertex(verts, self.faces, origin, direction)
        if vid is None:
            return None
        slot = self._pick_slot.value.split(":")[0]
        self.picks.set(slot, vid)
        nxt = self.picks.next_slot(slot)
        self._pick_slot.value = next(f"{k}: {d}" for k, d in SLOTS if k == nxt)
        self._pick_note.content = self._picks_note()
        picked = np.asarray(list(self.picks.ids.values()), np.int64)
        self.server.scene.add_point_cloud(
            "/landmarks", points=verts[picked].astype(np.float32), colors=(255, 220, 0), point_size=0.012
        )
        return vid

    def save_landmarks(self) -> Path:
        """Write the picks to DIR/landmarks/picked.json (UserError naming the points still missing)."""
        return self.picks.save(self.landmarks_path)

    def _add_timeline(
        self,
        kind: str,
        title: str,
        folder: str,
        labels: tuple[str, str, str],
        names: list[str],
        empty: str,
        image: bool = False,
    ) -> Timeline:
        """One timeline panel: a dropdown of ``names``, a frame slider and a play box (``labels``)."""
        gui = self.server.gui
        with gui.add_folder(folder):
            if not names:
                gui.add_markdown(empty)
            tl = Timeline(
                kind,
                title,
                dropdown=gui.add_dropdown(labels[0], (NONE, *names), initial_value=NONE, disabled=not names),
                frame=gui.add_slider(labels[1], min=0, max=1, step=1, initial_value=0, disabled=True),
                play=gui.add_checkbox(labels[2], initial_value=False, disabled=True),
                note=gui.add_markdown(""),
                image=gui.add_image(np.full((8, 8, 3), 255, np.uint8), label="input (canonical view)", visible=False)
                if image
                else None,
            )

        @tl.dropdown.on_update
        def _(_event) -> None:
            if tl.dropdown.value == NONE:
                tl.play.value = False
                tl.frame.disabled = tl.play.disabled = True
                if tl.image is not None:
                    tl.image.visible = False
                with self._lock:
                    if self._mode[0] == kind:
                        self._show_shapes()
                return
            self._set_frame(kind, tl.dropdown.value, self._open_at)

        @tl.frame.on_update
        def _(_event) -> None:
            if tl.dropdown.value != NONE:
                self._set_frame(kind, tl.dropdown.value, int(tl.frame.value))

        @tl.play.on_update
        def _(_event) -> None:
            self._start_play(kind, tl.play.value)

        return tl

    def _slider_callback(self, i: int):
        def cb(_event) -> None:
            with self._lock:
                self._values[i] = float(self._sliders[i].value)
                if not self._bulk:
                    self._show_shapes()

        return cb

    # ------------------------------------------------------------------------- state changes

    def _show_shapes(self) -> None:
        with self._lock:
            if self._mode[0] != "shapes":
                self._mode = ("shapes",)
                for tl in self._timelines.values():
                    tl.play.value = False
            self._status.content = "Showing: blendshapes"
        self._schedule()

    def _capture(self, vid: str) -> Capture:
        with self._lock:
            if vid in self._captures:
                self._captures[vid] = self._captures.pop(vid)  # most recently used last
                return self._captures[vid]
        cap = load_capture(self.root, vid, self.mesh.num_vertices)  # slow (PNG decoding): outside the lock
        with self._lock:
            self._captures[vid] = cap
            # A character has ~60 captures of [49, N, 3]; keep a few, never the one on screen.
            shown = self._mode[1] if self._mode[0] == "capture" else None
            for old in [k for k in self._captures if k not in (vid, shown)][
                : max(len(self._captures) - CAPTURE_CACHE, 0)
            ]:
                del self._captures[old]
        return cap

    def _retarget(self, name: str) -> Retarget:
        if name not in self._retargets:
            self._retargets[name] = load_retarget(self.root, name, self.shapes)
        return self._retargets[name]

    def _loaded(self, kind: str) -> dict:
        """Captures or retargeting results loaded so far, by name."""
        return self._captures if kind == "capture" else self._retargets

    def _open(self, kind: str, name: str, frame: int, wait: bool) -> None:
        # The dropdown's callback (viser runs it synchronously) opens a newly chosen capture at
        # the requested frame rather than at 0: pushing frame 0 first let a slow browser draw
        # and hold it. Unchanged dropdown: no callback, so set the frame here.
        self._open_at = int(frame)
        try:
            self._timelines[kind].dropdown.value = name
        finally:
            self._open_at = 0
        self._set_frame(kind, name, int(frame))
        if wait:
            self.wait_idle()

    def _set_frame(self, kind: str, name: str, t: int) -> None:
        """Show frame t of capture / retargeting result ``name`` (loading it on first use)."""
        tl = self._timelines[kind]
        try:
            item = self._capture(name) if kind == "capture" else self._retarget(name)
        except UserError as exc:
            tl.note.content = f"error: {exc}"
            return
        nt = len(item.times)
        t = int(min(max(t, 0), nt - 1))
        with self._lock:
            tl.frame.max = max(nt - 1, 1)
            tl.frame.disabled = tl.play.disabled = nt < 2
            if tl.frame.value != t:
                tl.frame.value = t  # re-enters here once with the same t
            if tl.image is not None:
                if item.frames is not None:
                    tl.image.image = item.frames[min(t, len(item.frames) - 1)]
                tl.image.visible = item.frames is not None
            tl.note.content = item.note
            if self._mode[0] not in ("shapes", kind):
                self._timelines[self._mode[0]].play.value = False
            self._mode = (kind, name, t)
            self._status.content = f"Showing: {tl.title} {name}, frame {t + 1}/{nt} ({item.times[t]:.2f} s)"
        self._schedule()

    def _vertices_for(self, mode: tuple) -> np.ndarray:
        if mode[0] == "capture":
            return self._captures[mode[1]].vertices[mode[2]]
        if mode[0] == "retarget":
            rt = self._retargets[mode[1]]
            values = np.zeros(len(self.shapes), np.float64)
            np.add.at(values, rt.shape_idx, rt.weights[mode[2]])
        else:
            values = self._values
        if not len(values):
            return self.neutral
        return (self.neutral.astype(np.float64) + (values @ self._stack).reshape(-1, 3)).astype(np.float32)

    # ------------------------------------------------------------------------- threads

    def _schedule(self) -> None:
        with self._pushed_cv:
            self._requested += 1
        self._dirty.set()

    def _redraw_loop(self) -> None:
        """Send the newest state; states requested while one is being sent collapse into one."""
        while not self._stopping.is_set():
            if not self._dirty.wait(timeout=0.2):
                continue
            self._dirty.clear()
            with self._pushed_cv:
                version = self._requested
            with self._lock:
                verts = self._vertices_for(self._mode).copy()
                show_mesh, show_splats = self._show_mesh, self._show_splats
            try:
                self._push(verts, show_mesh, show_splats)
            except Exception as exc:  # a closed server during shutdown; anything else is printed
                if not self._stopping.is_set():
                    print(f"t2bs viewer: redraw failed: {type(exc).__name__}: {exc}", file=sys.stderr)
            with self._pushed_cv:
                self._pushed = max(self._pushed, version)
                self._pushed_cv.notify_all()

    def _push(self, verts: np.ndarray, show_mesh: bool, show_splats: bool) -> None:
        scene = self.server.scene
        self._shown_vertices = verts
        if show_mesh:
            # Not metallic, fairly rough (0.75): a painted character, not chrome.
            glb = glb_bytes(self._display.with_vertices(verts), roughness=0.75)
            if self._mesh_handle is None:
                self._mesh_handle = scene.add_glb(MESH_NODE, glb, cast_shadow=False, receive_shadow=False)
            else:
                self._mesh_handle.glb_data = glb
                self._mesh_handle.visible = True
        elif self._mesh_handle is not None:
            self._mesh_handle.visible = False
        if show_splats:
            # viser's splat node takes the whole buffer at once: re-adding replaces it.
            cov = splat_covariances(verts, self.faces, self._sigma)
            self._splat_handle = scene.add_gaussian_splats(
                SPLAT_NODE,
                centers=verts.astype(np.float32),
                covariances=cov,
                rgbs=self.colors,
                opacities=np.ones((len(verts), 1), np.float32),
            )
        elif self._splat_handle is not None:
            self._splat_handle.remove()
            self._splat_handle = None

    def _start_play(self, kind: str, playing: bool) -> None:
        with self._lock:
            if not playing:
                self._play_start.pop(kind, None)
                return
            tl = self._timelines[kind]
            item = self._loaded(kind).get(tl.dropdown.value)
            if item is None:
                return
            times, t = item.times, int(tl.frame.value)
            self._play_start[kind] = (time.monotonic(), float(times[min(t, len(times) - 1)] - times[0]))

    def _play_loop(self) -> None:
        """Advance the playing timeline at real time (looping), ~30 updates per second."""
        while not self._stopping.wait(1 / 30):
            for kind, tl in self._timelines.items():
                with self._lock:
                    start = self._play_start.get(kind)
                    item = self._loaded(kind).get(tl.dropdown.value)
                    if start is None or item is None or len(item.times) < 2:
                        continue
                    times, slider = item.times, tl.frame
                    # One frame period past the last frame before looping, so the last frame shows.
                    period = float(times[-1] - times[0]) + float(np.median(np.diff(times)))
                    media = (start[1] + time.monotonic() - start[0]) % period
                    t = int(np.searchsorted(times - times[0], media, side="right") - 1)
                    if t != slider.value:
                        slider.value = max(t, 0)
