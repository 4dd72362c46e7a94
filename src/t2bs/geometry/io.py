"""Load and save meshes: .glb/.gltf/.vrm with named morph targets (pygltflib), .obj/.ply (trimesh).

trimesh drops glTF morph targets, so glTF is read here: every mesh primitive reachable from the
default scene is transformed by its node's world matrix and merged, one part label per primitive
(the node or mesh name). Saving writes one primitive with POSITION, NORMAL, COLOR_0 or
TEXCOORD_0 + an embedded PNG, named morph targets (mesh.extras.targetNames, the convention
three.js and Blender read) with POSITION and NORMAL deltas and, optionally, a morph-weight animation.

Colour spaces: ``Mesh.vertex_colors`` hold display (sRGB) values, like the texture's pixels, because
that is what the renders and the videos compare against. glTF defines COLOR_0 as *linear* RGB
(three.js and Blender apply the sRGB curve on output), so COLOR_0 is written linear and converted
back to sRGB on reading; writing the sRGB values raw made every consumer show a washed-out character.
"""

from __future__ import annotations

import base64
import io
import os
from pathlib import Path

import numpy as np
import pygltflib
from PIL import Image

from t2bs.errors import UserError
from t2bs.geometry.mesh import Mesh, merge_meshes

GLTF_SUFFIXES = {".glb", ".gltf", ".vrm"}
TRIMESH_SUFFIXES = {".obj", ".ply", ".off", ".stl"}

_COMPONENT_DTYPES = {5120: np.int8, 5121: np.uint8, 5122: np.int16, 5123: np.uint16, 5125: np.uint32, 5126: np.float32}
_TYPE_SIZES = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}
MAX_ACCESSOR_COUNT = 1 << 25  # a count past this cannot be a real buffer; refuse before allocating it


def load_mesh(path: str | os.PathLike) -> Mesh:
    """Read a mesh file into a validated Mesh (UserError with one line on any bad input)."""
    path = Path(path)
    if not path.exists():
        raise UserError(f"{path}: no such file")
    if path.is_dir():
        raise UserError(f"{path}: is a folder, expected a mesh file")
    if path.stat().st_size == 0:
        raise UserError(f"{path}: file is empty")
    suffix = path.suffix.lower()
    if suffix not in GLTF_SUFFIXES | TRIMESH_SUFFIXES:
        raise UserError(f"{path}: unsupported mesh format {suffix!r} (use .glb .gltf .vrm .obj .ply)")
    try:
        mesh = _load_gltf(path) if suffix in GLTF_SUFFIXES else _load_trimesh(path)
    except MemoryError:
        raise UserError(f"{path}: mesh too large to load in memory") from None
    check_mesh_size(mesh.num_vertices, len(mesh.faces), str(path))
    return mesh.validate(str(path))


def srgb_to_linear(c: np.ndarray) -> np.ndarray:
    """Display (sRGB, 0..1) colours -> linear RGB (the IEC 61966-2-1 curve), float32."""
    c = np.clip(np.asarray(c, np.float32), 0.0, 1.0)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4).astype(np.float32)


def linear_to_srgb(c: np.ndarray) -> np.ndarray:
    """Linear RGB (0..1) -> display (sRGB) colours, float32; the inverse of ``srgb_to_linear``."""
    c = np.clip(np.asarray(c, np.float64), 0.0, 1.0)
    return np.where(c <= 0.0031308, c * 12.92, 1.055 * c ** (1 / 2.4) - 0.055).astype(np.float32)


# A character mesh past these sizes makes every stage slow and memory-bound (measured: a
# 2-million-vertex mesh took 77 s and 1.6 GB to render and grew past 10 GB in reconstruct), far
# beyond the detail a 512 px video shows. Raise them with T2BS_MAX_VERTICES / T2BS_MAX_FACES.
MAX_VERTICES = 300_000
MAX_FACES = 600_000


def check_mesh_size(vertices: int, faces: int, source: str) -> None:
    """UserError naming the counts and how to decimate when a mesh is over the size limit."""
    limits = {}
    for name, default in (("VERTICES", MAX_VERTICES), ("FACES", MAX_FACES)):
        raw = os.environ.get(f"T2BS_MAX_{name}", "")
        try:
            limits[name] = int(raw) if raw else default
        except ValueError:
            raise UserError(f"T2BS_MAX_{name}={raw!r} is not a whole number") from None
    if vertices > limits["VERTICES"] or faces > limits["FACES"]:
        raise UserError(
            f"{source}: mesh has {vertices:,} vertices and {faces:,} faces, over the limit of "
            f"{limits['VERTICES']:,} vertices / {limits['FACES']:,} faces; decimate it first (Blender: "
            f"Decimate modifier; Python: `pip install fast-simplification` then trimesh's "
            f"mesh.simplify_quadric_decimation(face_count={limits['FACES'] // 2})) or raise "
            f"T2BS_MAX_VERTICES / T2BS_MAX_FACES"
        )


# ---------------------------------------------------------------------------------- glTF read


def _load_gltf(path: Path) -> Mesh:
    import warnings

    if path.suffix.lower() in (".glb", ".vrm"):
        with open(path, "rb") as fh:
            magic = fh.read(4)
        if magic != b"glTF":
            raise UserError(f"{path}: not a readable glTF/GLB file (it does not start with the GLB header)")
    try:
        # pygltflib picks binary vs JSON by the suffix; a .vrm is a binary glTF under another name.
        with open(path, "rb") as f:
            binary = f.read(4) == b"glTF"
        with warnings.catch_warnings():  # pygltflib warns in several lines about odd files; the error says it in one
            warnings.simplefilter("ignore")
            gltf = pygltflib.GLTF2().load_binary(str(path)) if binary else pygltflib.GLTF2().load_json(str(path))
    except Exception as exc:  # pygltflib raises many types on garbage input
        raise UserError(f"{path}: not a readable glTF/GLB file ({type(exc).__name__})") from None
    if gltf is None or not gltf.meshes:
        raise UserError(f"{path}: glTF file contains no meshes")
    try:
        return _parse_gltf(gltf, path)
    except _MalformedGltf as exc:
        raise UserError(f"{path}: malformed glTF: {exc}") from None
    except (IndexError, KeyError, TypeError, ValueError, AttributeError, OverflowError) as exc:
        # The file is untrusted input: any index or field the checks below do not name still ends
        # as one line (exc names what numpy/pygltflib tripped over), never a traceback.
        raise UserError(
            f"{path}: malformed glTF ({type(exc).__name__}: {str(exc).splitlines()[0][:160] if str(exc) else 'bad field'})"
        ) from None


class _MalformedGltf(Exception):
    """A glTF structure that breaks the spec (message without the path; _load_gltf adds it)."""


def _index(items, i, what: str):
    """``items[i]`` for a glTF index ``i`` (None-safe; negative or past the end = malformed)."""
    if not isinstance(i, int) or items is None or not 0 <= i < len(items):
        raise _MalformedGltf(f"{what} index {i!r} out of range (file has {0 if items is None else len(items)})")
    return items[i]


def _parse_gltf(gltf: pygltflib.GLTF2, path: Path) -> Mesh:
    buffers = [_buffer_bytes(gltf, b, path) for b in gltf.buffers]
    parts: list[tuple[str, Mesh]] = []
    scene = _index(gltf.scenes, gltf.scene or 0, "scene") if gltf.scenes else None
    roots = (scene.nodes or []) if scene is not None else range(len(gltf.nodes))
    for node_index, world, node_name in _walk_nodes(gltf, roots):
        node = gltf.nodes[node_index]
        if node.mesh is None:
            continue
        gmesh = _index(gltf.meshes, node.mesh, "mesh")
        names = (gmesh.extras or {}).get("targetNames", []) if isinstance(gmesh.extras, dict) else []
        for p_index, prim in enumerate(gmesh.primitives):
            if prim.mode not in (None, 4):  # only triangle lists are surfaces
                continue
            label = node_name or gmesh.name or f"mesh{node.mesh}"
            if len(gmesh.primitives) > 1:
                label = f"{label}.{p_index}"
            part = _read_primitive(gltf, buffers, prim, names, world, path)
            part_names = gmesh.extras.get("partNames") if isinstance(gmesh.extras, dict) else None
            part_index = getattr(prim.attributes, "_PART_ID", None)
            if part_names and part_index is not None:
                part.part_ids = _read_accessor(gltf, buffers, part_index)[:, 0].astype(np.int32)
                part.part_names = list(part_names)
            parts.append((label, part))
    if not parts:
        raise UserError(f"{path}: glTF file has no triangle meshes in its scene")
    if len(parts) == 1 and parts[0][1].part_ids is not None:
        return parts[0][1]  # a file written by save_mesh keeps its own part labels
    return merge_meshes(parts)


def _walk_nodes(gltf: pygltflib.GLTF2, roots, parent=np.eye(4), parent_name=None, path=()):
    """Yield (node index, world matrix, name of the node or of its nearest named ancestor).

    ``path``: the node indices above, so a node that is its own ancestor (a cycle the spec forbids)
    is an error instead of endless recursion."""
    for i in roots:
        node = _index(gltf.nodes, i, "node")
        if i in path:
            raise _MalformedGltf(f"node {i} is its own ancestor (a cycle in the node hierarchy)")
        if len(path) > 256:
            raise _MalformedGltf("node hierarchy deeper than 256 levels")
        world = parent @ _node_matrix(node)
        if not np.isfinite(world).all():
            raise _MalformedGltf(f"node {i} has a non-finite transform")
        name = node.name or parent_name
        yield i, world, name
        yield from _walk_nodes(gltf, node.children or [], world, name, path + (i,))


def _node_matrix(node: pygltflib.Node) -> np.ndarray:
    if node.matrix:
        return np.asarray(node.matrix, dtype=np.float64).reshape(4, 4).T  # glTF is column-major
    t = np.asarray(node.translation or [0, 0, 0], dtype=np.float64)
    x, y, z, w = node.rotation or [0, 0, 0, 1]
    r = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )
    s = np.asarray(node.scale or [1, 1, 1], dtype=np.float64)
    m = np.eye(4)
    m[:3, :3] = r * s[None, :]
    m[:3, 3] = t
    return m


def _buffer_bytes(gltf: pygltflib.GLTF2, buffer: pygltflib.Buffer, path: Path) -> bytes:
    if buffer.uri is None:
        blob = gltf.binary_blob()
        if blob is None:
            raise UserError(f"{path}: GLB has no binary chunk")
        return blob
    if buffer.uri.startswith("data:"):
        return _data_uri(buffer.uri, path)
    return _read_beside(path, buffer.uri, "external buffer")


def _data_uri(uri: str, path: Path) -> bytes:
    try:
        return base64.b64decode(uri.split(",", 1)[1], validate=False)
    except (IndexError, ValueError):
        raise UserError(f"{path}: malformed data: uri in a buffer or image") from None


def _read_beside(path: Path, uri: str, what: str) -> bytes:
    """The file a relative glTF uri names, only inside the glTF file's own folder.

    A file someone sends you must not make t2bs read elsewhere on disk (``../../etc/passwd``, an
    absolute path, a link pointing out): the resolved path must stay under the folder."""
    from urllib.parse import unquote, urlparse

    if urlparse(uri).scheme not in ("", "file") or uri.startswith("file:"):
        raise UserError(f"{path}: {what} uri {uri!r} is not a relative file name (only files beside the glTF are read)")
    folder = path.parent.resolve()
    target = (folder / unquote(uri)).resolve()
    if not target.is_relative_to(folder):
        raise UserError(f"{path}: {what} uri {uri!r} points outside the glTF file's folder; refused")
    if target.is_dir():
        raise UserError(f"{path}: {what} uri {uri!r} names a folder, not a file")
    if not target.is_file():
        raise UserError(f"{path}: {what} {uri!r} not found next to it")
    try:
        return target.read_bytes()
    except OSError as exc:
        raise UserError(f"{path}: cannot read {what} {target}: {exc.strerror or exc}") from None


def _read_accessor(gltf: pygltflib.GLTF2, buffers: list[bytes], index: int) -> np.ndarray:
    acc = _index(gltf.accessors, index, "accessor")
    if acc.componentType not in _COMPONENT_DTYPES:
        raise _MalformedGltf(
            f"accessor {index} has componentType {acc.componentType!r} (valid: {sorted(_COMPONENT_DTYPES)})"
        )
    if acc.type not in _TYPE_SIZES:
        raise _MalformedGltf(f"accessor {index} has type {acc.type!r} (valid: {', '.join(_TYPE_SIZES)})")
    if not isinstance(acc.count, int) or acc.count < 0 or acc.count > MAX_ACCESSOR_COUNT:
        raise _MalformedGltf(f"accessor {index} has count {acc.count!r}")
    dtype = _COMPONENT_DTYPES[acc.componentType]
    width = _TYPE_SIZES[acc.type]
    if acc.bufferView is None:
        out = np.zeros((acc.count, width), dtype=dtype)  # all zeros unless sparse (spec 3.6.2.3)
    else:
        view = _index(gltf.bufferViews, acc.bufferView, "bufferView")
        data = _index(buffers, view.buffer, "buffer")
        start = (view.byteOffset or 0) + (acc.byteOffset or 0)
        item = np.dtype(dtype).itemsize * width
        stride = view.byteStride or item
        end = start + (stride * (acc.count - 1) + item if acc.count else 0)
        view_end = (view.byteOffset or 0) + (view.byteLength or 0)
        if start < 0 or stride < item or end > min(len(data), view_end):
            raise _MalformedGltf(
                f"accessor {index} reads bytes {start}..{end} but its buffer view / buffer ends at "
                f"{min(len(data), view_end)} (truncated buffer?)"
            )
        if stride == item:
            out = np.frombuffer(data, dtype=dtype, count=acc.count * width, offset=start).reshape(acc.count, width)
        else:
            raw = np.frombuffer(data, dtype=np.uint8, count=stride * (acc.count - 1) + item, offset=start)
            rows = np.lib.stride_tricks.as_strided(raw, (acc.count, item), (stride, 1))
            out = rows.copy().view(dtype).reshape(acc.count, width)
    if acc.sparse is not None:  # morph targets are often sparse
        out = out.copy()
        sp = acc.sparse
        iv = gltf.bufferViews[sp.indices.bufferView]
        idx = np.frombuffer(
            buffers[iv.buffer],
            dtype=_COMPONENT_DTYPES[sp.indices.componentType],
            count=sp.count,
            offset=(iv.byteOffset or 0) + (sp.indices.byteOffset or 0),
        )
        vv = gltf.bufferViews[sp.values.bufferView]
        vals = np.frombuffer(
            buffers[vv.buffer],
            dtype=dtype,
            count=sp.count * width,
            offset=(vv.byteOffset or 0) + (sp.values.byteOffset or 0),
        ).reshape(sp.count, width)
        out[idx.astype(np.int64)] = vals
    if acc.normalized and np.issubdtype(dtype, np.integer):
        out = out.astype(np.float32) / np.iinfo(dtype).max
    return out


def _read_primitive(gltf, buffers, prim, target_names, world: np.ndarray, path: Path) -> Mesh:
    attrs = prim.attributes
    if attrs.POSITION is None:
        raise UserError(f"{path}: a primitive has no POSITION attribute")
    pos = _read_accessor(gltf, buffers, attrs.POSITION).astype(np.float64)
    if prim.indices is not None:
        idx = _read_accessor(gltf, buffers, prim.indices)
        if idx.shape[1] != 1 or not np.issubdtype(idx.dtype, np.integer) or len(idx) % 3:
            raise _MalformedGltf(
                f"triangle indices must be an integer SCALAR accessor with a multiple of 3 entries, "
                f"got {len(idx)} x {idx.shape[1]} {idx.dtype}"
            )
        faces = idx.reshape(-1, 3).astype(np.int64)
    else:
        if len(pos) % 3:
            raise _MalformedGltf(f"a non-indexed triangle list has {len(pos)} vertices, not a multiple of 3")
        faces = np.arange(len(pos)).reshape(-1, 3)
    linear = world[:3, :3]
    vertices = pos @ linear.T + world[:3, 3]
    if np.linalg.det(linear) < 0:  # mirrored node: keep outward winding
        faces = faces[:, ::-1]
    morphs = {}
    for t_index, target in enumerate(prim.targets or []):
        name = target_names[t_index] if t_index < len(target_names) else f"target_{t_index}"
        if "POSITION" in target and target["POSITION"] is not None:
            morphs[name] = (_read_accessor(gltf, buffers, target["POSITION"]).astype(np.float64) @ linear.T).astype(
                np.float32
            )
    colors = uv = texture = None
    factor = np.ones(3)
    if prim.material is not None:
        pbr = _index(gltf.materials, prim.material, "material").pbrMetallicRoughness
        if pbr is not None:
            factor = np.asarray((pbr.baseColorFactor or [1, 1, 1, 1])[:3], dtype=np.float64)
            tex_info = pbr.baseColorTexture
            if tex_info is not None and attrs.TEXCOORD_0 is not None:
                texture = _read_texture(gltf, buffers, tex_info.index, path)
                uv = _read_accessor(gltf, buffers, attrs.TEXCOORD_0).astype(np.float32)
                if not np.allclose(factor, 1):
                    texture = np.clip(texture * factor, 0, 255).astype(np.uint8)
    if texture is None:
        if attrs.COLOR_0 is not None:
            colors = linear_to_srgb(_read_accessor(gltf, buffers, attrs.COLOR_0)[:, :3])
        else:  # baseColorFactor is linear too
            colors = np.tile(linear_to_srgb(factor), (len(vertices), 1))
    return Mesh(vertices.astype(np.float32), faces.astype(np.int32), colors, uv, texture, morphs)


def _read_texture(gltf, buffers, texture_index: int, path: Path) -> np.ndarray:
    image = _index(gltf.images, _index(gltf.textures, texture_index, "texture").source, "image")
    if image.bufferView is not None:
        view = _index(gltf.bufferViews, image.bufferView, "bufferView")
        data = _index(buffers, view.buffer, "buffer")[(view.byteOffset or 0) : (view.byteOffset or 0) + view.byteLength]
    elif image.uri and image.uri.startswith("data:"):
        data = _data_uri(image.uri, path)
    elif image.uri:
        data = _read_beside(path, image.uri, "texture image")
    else:
        raise UserError(f"{path}: texture image has no data")
    try:
        return np.asarray(Image.open(io.BytesIO(data)).convert("RGB"))
    except Exception:
        raise UserError(f"{path}: texture image cannot be decoded") from None


# ---------------------------------------------------------------------------- other formats


def _load_trimesh(path: Path) -> Mesh:
    import trimesh

    try:
        loaded = trimesh.load(str(path), force="mesh", process=False)
    except Exception as exc:
        raise UserError(f"{path}: not a readable mesh file ({type(exc).__name__})") from None
    # trimesh drops vertices that no face uses, so a points-only file arrives empty.
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise UserError(f"{path}: mesh has no faces (a point cloud is not a character mesh)")
    vertices = np.asarray(loaded.vertices, dtype=np.float32)
    faces = np.asarray(loaded.faces, dtype=np.int32).reshape(-1, 3)
    colors = uv = texture = None
    visual = loaded.visual
    if getattr(visual, "kind", None) == "texture" and getattr(visual, "uv", None) is not None:
        img = getattr(visual.material, "baseColorTexture", None) or getattr(visual.material, "image", None)
        if img is not None:
            texture = np.asarray(img.convert("RGB"))
            uv = np.asarray(visual.uv, dtype=np.float32).copy()
            uv[:, 1] = 1.0 - uv[:, 1]  # OBJ/trimesh UVs have v = 0 at the bottom
    if texture is None and getattr(visual, "kind", None) == "vertex":
        colors = np.asarray(visual.vertex_colors, dtype=np.float32)[:, :3] / 255.0
    return Mesh(vertices, faces, colors, uv, texture)


# --------------------------------------------------------------------------------------- save


def save_mesh(mesh: Mesh, path: str | os.PathLike, animation: dict | None = None) -> Path:
    """Write ``mesh`` to .glb (morph targets, texture, optional animation) or .ply, atomically.

    ``animation``: {"times": [T] seconds, "weights": [T, M] morph weights in target order,
    "name": str} adds a glTF animation driving the morph weights; optional "rotation": [T, 4]
    unit quaternions (x, y, z, w) and "translation": [T, 3] animate the node rigidly (a head turn).
    """
    from t2bs.fileio import atomic_path

    path = Path(path)
    suffix = path.suffix.lower()
    with atomic_path(path) as tmp:
        if suffix == ".glb":
            Path(tmp).write_bytes(glb_bytes(mesh, animation))
        elif suffix == ".ply":
            _save_ply(mesh, tmp)
        else:
            raise UserError(f"{path}: can only save .glb or .ply")
    return path


def glb_bytes(mesh: Mesh, animation: dict | None = None, roughness: float = 1.0) -> bytes:
    """``mesh`` as a binary glTF (.glb) in memory: the bytes ``save_mesh`` writes to a .glb file.

    One primitive: POSITION, NORMAL, COLOR_0 (linear RGBA) or TEXCOORD_0 + an embedded PNG, the
    morph targets in ``mesh.morph_targets`` order (names in mesh.extras.targetNames), part labels,
    and ``animation`` as in ``save_mesh``. ``roughness``: the material's roughnessFactor (not metallic,
    double-sided). The viewer sends these bytes to the browser (three.js GLTFLoader) on every pose.
    """
    return b"".join(_to_gltf(mesh, animation, roughness).save_to_bytes())


def _save_ply(mesh: Mesh, path: Path) -> None:
    import trimesh

    colors = (np.clip(mesh.vertex_rgb(), 0, 1) * 255).astype(np.uint8)
    tm = trimesh.Trimesh(mesh.vertices, mesh.faces, vertex_colors=colors, process=False)
    data = tm.export(file_type="ply")
    Path(path).write_bytes(data)


class _BinaryBuilder:
    """Appends aligned buffer views and accessors to a GLTF2 under construction."""

    def __init__(self, gltf: pygltflib.GLTF2):
        self.gltf = gltf
        self.blob = bytearray()

    def view(self, data: bytes, target: int | None = None) -> int:
        while len(self.blob) % 4:
            self.blob.append(0)
        self.gltf.bufferViews.append(
            pygltflib.BufferView(buffer=0, byteOffset=len(self.blob), byteLength=len(data), target=target)
        )
        self.blob.extend(data)
        return len(self.gltf.bufferViews) - 1

    def accessor(self, array: np.ndarray, kind: str, target: int | None = None, bounds: bool = False) -> int:
        array = np.ascontiguousarray(array)
        component = {np.float32: pygltflib.FLOAT, np.uint32: pygltflib.UNSIGNED_INT}[array.dtype.type]
        view = self.view(array.tobytes(), target)
        flat = array.reshape(len(array), -1)
        acc = pygltflib.Accessor(bufferView=view, componentType=component, count=len(array), type=kind)
        if bounds:
            acc.min = flat.min(0).astype(float).tolist()
            acc.max = flat.max(0).astype(float).tolist()
        self.gltf.accessors.append(acc)
        return len(self.gltf.accessors) - 1


def _to_gltf(mesh: Mesh, animation: dict | None, roughness: float = 1.0) -> pygltflib.GLTF2:
    from t2bs.geometry.mesh import vertex_normals

    gltf = pygltflib.GLTF2(asset=pygltflib.Asset(generator="t2bs", version="2.0"))
    gltf.bufferViews, gltf.accessors = [], []
    b = _BinaryBuilder(gltf)
    n0 = vertex_normals(mesh.vertices, mesh.faces)
    attrs = pygltflib.Attributes(
        POSITION=b.accessor(mesh.vertices.astype(np.float32), "VEC3", pygltflib.ARRAY_BUFFER, bounds=True),
        NORMAL=b.accessor(n0.astype(np.float32), "VEC3", pygltflib.ARRAY_BUFFER),
    )
    # Double-sided: generated characters often have open boundaries (mouth interior, eyelids).
    material = pygltflib.Material(
        name="character",
        doubleSided=True,
        pbrMetallicRoughness=pygltflib.PbrMetallicRoughness(metallicFactor=0.0, roughnessFactor=float(roughness)),
    )
    if mesh.texture is not None and mesh.uv is not None:
        attrs.TEXCOORD_0 = b.accessor(mesh.uv.astype(np.float32), "VEC2", pygltflib.ARRAY_BUFFER)
        png = io.BytesIO()
        Image.fromarray(mesh.texture).save(png, format="PNG")
        gltf.images = [pygltflib.Image(bufferView=b.view(png.getvalue()), mimeType="image/png")]
        gltf.samplers = [pygltflib.Sampler(magFilter=9729, minFilter=9729, wrapS=33071, wrapT=33071)]
        gltf.textures = [pygltflib.Texture(source=0, sampler=0)]
        material.pbrMetallicRoughness.baseColorTexture = pygltflib.TextureInfo(index=0)
    else:
        rgba = np.concatenate([srgb_to_linear(mesh.vertex_rgb()), np.ones((mesh.num_vertices, 1), np.float32)], 1)
        attrs.COLOR_0 = b.accessor(rgba.astype(np.float32), "VEC4", pygltflib.ARRAY_BUFFER)
    # Normal deltas: without them a consumer lights every pose with the neutral's normals (an open
    # jaw or a closed lid keeps the neutral shading). Delta = normals of the fully applied target
    # minus the neutral's; consumers renormalise after blending.
    targets = [
        {
            "POSITION": b.accessor(d.astype(np.float32), "VEC3", pygltflib.ARRAY_BUFFER, bounds=True),
            "NORMAL": b.accessor(
                (vertex_normals(mesh.vertices + d, mesh.faces) - n0).astype(np.float32), "VEC3", pygltflib.ARRAY_BUFFER
            ),
        }
        for d in mesh.morph_targets.values()
    ]
    prim = pygltflib.Primitive(
        attributes=attrs,
        indices=b.accessor(mesh.faces.astype(np.uint32).reshape(-1), "SCALAR", pygltflib.ELEMENT_ARRAY_BUFFER),
        material=0,
        targets=targets or None,
    )
    extras = {"targetNames": mesh.morph_names} if targets else {}
    if mesh.part_ids is not None:
        extras["partNames"] = mesh.part_names
        prim.attributes._PART_ID = b.accessor(mesh.part_ids.astype(np.float32), "SCALAR", pygltflib.ARRAY_BUFFER)
    gmesh = pygltflib.Mesh(
        name="character", primitives=[prim], extras=extras, weights=[0.0] * len(targets) if targets else None
    )
    gltf.meshes = [gmesh]
    gltf.materials = [material]
    gltf.nodes = [pygltflib.Node(name="character", mesh=0)]
    gltf.scenes = [pygltflib.Scene(nodes=[0])]
    gltf.scene = 0
    if animation is not None and targets:
        times = np.asarray(animation["times"], dtype=np.float32)
        weights = np.asarray(animation["weights"], dtype=np.float32)
        if weights.shape != (len(times), len(targets)):
            raise ValueError(f"animation weights must be [T={len(times)}, M={len(targets)}], got {weights.shape}")
        t_acc = b.accessor(times, "SCALAR", bounds=True)
        w_acc = b.accessor(weights.reshape(-1), "SCALAR")
        samplers = [pygltflib.AnimationSampler(input=t_acc, output=w_acc, interpolation="LINEAR")]
        channels = [
            pygltflib.AnimationChannel(sampler=0, target=pygltflib.AnimationChannelTarget(node=0, path="weights"))
        ]
        for key, kind in (("rotation", "VEC4"), ("translation", "VEC3")):
            if animation.get(key) is None:
                continue
            values = np.asarray(animation[key], dtype=np.float32)
            if values.shape != (len(times), 4 if kind == "VEC4" else 3):
                raise ValueError(
                    f"animation {key} must be [T={len(times)}, {4 if kind == 'VEC4' else 3}], got {values.shape}"
                )
            samplers.append(
                pygltflib.AnimationSampler(input=t_acc, output=b.accessor(values, kind), interpolation="LINEAR")
            )
            channels.append(
                pygltflib.AnimationChannel(
                    sampler=len(samplers) - 1, target=pygltflib.AnimationChannelTarget(node=0, path=key)
                )
            )
        gltf.animations = [
            pygltflib.Animation(name=animation.get("name", "capture"), samplers=samplers, channels=channels)
        ]
    gltf.buffers = [pygltflib.Buffer(byteLength=len(b.blob))]
    gltf.set_binary_blob(bytes(b.blob))
    return gltf
