"""Text -> character backends: procedural (offline default), diffusers Shap-E, a user command, a file.

Every backend returns a ``GenerationResult`` whose mesh is validated and in the canonical frame
(centred, facing +Z, bounding-box diagonal 1.2), plus an info dict naming the backend.
"""

from __future__ import annotations

import contextlib
import os
import shlex
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np

from t2bs.character.procedural import GenerationResult, generate_procedural
from t2bs.errors import MissingCheckpointError, UserError
from t2bs.geometry.mesh import Mesh, detect_facing, normalize

BACKENDS = ("procedural", "diffusers", "command", "file")
MESH_SUFFIXES = (".glb", ".gltf", ".vrm", ".obj", ".ply")
SHAP_E_REPO = "openai/shap-e"


def default_checkpoint_dir() -> Path:
    """Where the Shap-E folder is looked for when --checkpoint is not given."""
    root = os.environ.get("T2BS_CHECKPOINTS", str(Path.home() / ".cache" / "t2bs" / "checkpoints"))
    return Path(root) / "shap-e"


def generate(
    prompt: str,
    backend: str = "procedural",
    seed: int = 0,
    checkpoint: Path | None = None,
    command: str | None = None,
    mesh_path: Path | None = None,
    steps: int = 64,
    device: str | None = None,
    facing: str = "auto",
    grid_size: int = 128,
    command_timeout: float | None = None,
) -> GenerationResult:
    """Run one backend; UserError for unknown backends or missing arguments."""
    if backend not in BACKENDS:
        raise UserError(f"unknown --backend {backend!r}; use one of {', '.join(BACKENDS)}")
    if backend == "procedural":
        if not prompt.strip():
            raise UserError('the prompt is empty; describe the character, e.g. "a cartoon fox with big ears"')
        return generate_procedural(prompt, seed)
    if backend == "diffusers":
        return generate_shap_e(
            prompt, checkpoint or default_checkpoint_dir(), seed, steps=steps, device=device, grid_size=grid_size
        )
    if backend == "command":
        if not command:
            raise UserError(
                '--backend command needs --command, e.g. --command "python run_trellis.py --prompt {prompt} --out {out}"'
            )
        return generate_with_command(
            prompt,
            command,
            seed,
            facing=facing,
            timeout=COMMAND_TIMEOUT_S if command_timeout is None else command_timeout,
        )
    if mesh_path is None:
        raise UserError("--backend file needs --mesh PATH")
    return generate_from_file(mesh_path, prompt, facing=facing)


# ---------------------------------------------------------------- diffusers (Shap-E)


def load_shap_e(checkpoint: Path, device: str | None = None):
    """ShapEPipeline from a local folder (model_index.json + prior, text_encoder, tokenizer, ...)."""
    checkpoint = Path(checkpoint)
    if not (checkpoint / "model_index.json").is_file():
        raise MissingCheckpointError(
            f"Shap-E text-to-3D weights ({SHAP_E_REPO})",
            str(checkpoint),
            f"download them where there is internet (`huggingface-cli download {SHAP_E_REPO} --local-dir shap-e`), "
            f"copy the folder to {checkpoint} or pass --checkpoint FOLDER",
        )
    try:
        import torch
        from diffusers import ShapEPipeline
    except ImportError as exc:
        raise UserError(f"the diffusers backend needs `pip install -e .[diffusers]` ({exc})") from None
    device = device or ("cuda" if torch.cuda.is_available() else "cpu")
    dtype = torch.float16 if device.startswith("cuda") else torch.float32
    try:
        pipe = ShapEPipeline.from_pretrained(str(checkpoint), torch_dtype=dtype, local_files_only=True)
    except (OSError, ValueError) as exc:
        raise UserError(f"{checkpoint}: not a loadable Shap-E pipeline folder: {str(exc).splitlines()[0]}") from None
    pipe.set_progress_bar_config(disable=True)
    return pipe.to(device)


def generate_shap_e(
    prompt: str,
    checkpoint: Path,
    seed: int = 0,
    steps: int = 64,
    guidance_scale: float = 15.0,
    device: str | None = None,
    pipe=None,
    grid_size: int = 128,
) -> GenerationResult:
    """Text -> mesh with Shap-E; colours from its per-vertex RGB channels.

    Same as ``pipe(prompt, output_type="mesh")`` (the prior's latents decoded by the pipeline's
    own ``shap_e_renderer.decode_to_mesh``), with the marching-cubes ``grid_size`` exposed
    (128 in the pipeline; smaller is faster and coarser).
    """
    import torch

    start = time.perf_counter()
    pipe = pipe or load_shap_e(checkpoint, device)
    dev = pipe.device
    generator = torch.Generator(device="cpu").manual_seed(int(seed))
    with torch.no_grad():
        latents = pipe(
            prompt,
            num_inference_steps=int(steps),
            guidance_scale=guidance_scale,
            generator=generator,
            output_type="latent",
        ).images  # [1, num_embeddings, embedding_dim]
        try:
            decoded = pipe.shap_e_renderer.decode_to_mesh(latents[0][None], dev, grid_size=int(grid_size))
        except (ValueError, RuntimeError) as exc:  # marching cubes found no surface
            raise UserError(
                f"Shap-E produced no surface ({str(exc).splitlines()[0]}); try another seed or prompt"
            ) from None
    mesh = shap_e_to_mesh(decoded)
    info = {
        "backend": "diffusers",
        "model": "ShapEPipeline",
        "checkpoint": str(checkpoint),
        "prompt": prompt,
        "seed": int(seed),
        "steps": int(steps),
        "guidance_scale": guidance_scale,
        "grid_size": int(grid_size),
        "device": str(dev),
        "vertices": mesh.num_vertices,
        "faces": int(len(mesh.faces)),
        "seconds": round(time.perf_counter() - start, 3),
    }
    return GenerationResult(mesh, info, [])


def shap_e_to_mesh(decoded) -> Mesh:
    """Shap-E's MeshDecoderOutput (Z up) -> canonical Mesh (Y up, facing +Z) with vertex colours."""
    verts = decoded.verts.detach().float().cpu().numpy().astype(np.float64)  # [N, 3]
    faces = decoded.faces.detach().cpu().numpy().astype(np.int32)  # [F, 3]
    if len(verts) == 0 or len(faces) == 0:
        raise UserError("Shap-E produced an empty mesh (no surface in its SDF); try another seed or prompt")
    channels = decoded.vertex_channels
    rgb = np.stack([channels[k].detach().float().cpu().numpy() for k in ("R", "G", "B")], 1)
    # Shap-E's world is Z up with objects facing -Y: rotate to Y up, facing +Z.
    verts = np.stack([verts[:, 0], verts[:, 2], -verts[:, 1]], 1)
    mesh = Mesh(verts.astype(np.float32), faces, np.clip(rgb, 0, 1).astype(np.float32))
    mesh, _ = normalize(mesh.validate("Shap-E output"), facing="+z")
    return mesh


# ---------------------------------------------------------------- external command


COMMAND_TIMEOUT_S = 3600.0  # default limit of a --command run (a 3D generator on a GPU takes minutes)
_PLACEHOLDERS = ("prompt", "out", "seed")
_SHELLS = {"sh", "bash", "dash", "zsh", "ksh", "fish", "csh", "tcsh", "cmd", "cmd.exe", "powershell", "pwsh"}
_INTERPRETERS = ("python", "perl", "ruby", "node", "php", "lua", "rscript")  # their -c / -e run inline code


def command_argv(template: str, prompt: str, out: Path, seed: int) -> list[str]:
    """The argument list of a --command template: parsed once with shlex, placeholders filled per argument.

    No shell ever sees the prompt: ``{prompt}`` (bare, ``'{prompt}'`` or ``"{prompt}"``) becomes
    part of one argv entry, so ``$(...)``, backticks and ``;`` in a prompt stay text. A template that
    runs a shell itself (``sh -c '... {prompt} ...'``) is refused: the script would re-parse the
    prompt; such a script reads ``"$T2BS_PROMPT"`` (set for every command) instead.
    """
    import string

    try:
        args = shlex.split(template)
    except ValueError as exc:
        raise UserError(f"--command template cannot be parsed ({exc}): {template}") from None
    if not args:
        raise UserError("--command template is empty")
    values = {"prompt": prompt, "out": str(out), "seed": str(int(seed))}
    argv = []
    for i, arg in enumerate(args):
        try:
            fields = [f for f in string.Formatter().parse(arg) if f[1] is not None]
        except ValueError as exc:
            raise UserError(
                f"--command template: malformed placeholder in {arg!r} ({exc}); use {{prompt}} {{out}} {{seed}}"
            ) from None
        for _, name, spec, conv in fields:
            if name not in _PLACEHOLDERS or spec or conv:
                bad = "{" + name + (f"!{conv}" if conv else "") + (f":{spec}" if spec else "") + "}"
                raise UserError(
                    f"--command template: unknown placeholder {bad}; use {{prompt}} {{out}} {{seed}} as they are"
                )
        if i == 0 and fields:
            raise UserError("--command template: the program name cannot be a placeholder")
        if any(name == "prompt" for _, name, _, _ in fields) and _runs_shell_script(args, i):
            raise UserError(
                "--command template passes {prompt} into a shell script or inline code (-c/-e), which would "
                'run what the prompt contains; pass it as its own argument, or read "$T2BS_PROMPT" '
                "in the script"
            )
        argv.append(arg.format(**values))  # also turns {{ }} into literal braces
    return argv


def _runs_shell_script(args: list[str], i: int) -> bool:
    """True when argument ``i`` is code for an interpreter (``sh -c SCRIPT``, ``bash -lc``, ``python -c``,
    ``perl -e``, ``node --eval``, ``cmd /c``): there the prompt would be parsed as code, not passed as text."""
    for j in range(i):
        name = Path(args[j]).name.lower()
        if name in _SHELLS or name.startswith(_INTERPRETERS):
            if name.startswith(("cmd", "pwsh", "powershell")):
                return True
            for k in range(j + 1, i):  # the interpreter's own options, up to its script or code
                flag = args[k]
                if not flag.startswith("-"):
                    return False  # a script file: the prompt is one of its arguments
                if flag in ("--eval", "--print", "--command") or (
                    not flag.startswith("--") and set(flag[1:]) & set("cep")
                ):
                    return i == k + 1  # the argument after -c / -e is code
            return False
    return False


def run_argv(argv: list[str], timeout: float | None, env: dict | None = None) -> subprocess.CompletedProcess:
    """Run ``argv`` without a shell; past ``timeout`` seconds its whole process group is killed (UserError)."""
    import signal

    try:
        proc = subprocess.Popen(
            argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, start_new_session=True
        )  # own group: a timeout kills what it started too
    except (FileNotFoundError, PermissionError, OSError) as exc:
        raise UserError(f"--command cannot start {argv[0]!r}: {exc.strerror or exc}") from None
    try:
        stdout, stderr = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
        proc.communicate()
        raise UserError(
            f"--command did not finish within {timeout:g} s (raise it with --command-timeout): {shlex.join(argv)}"
        ) from None
    except BaseException:  # Ctrl-C: do not leave the generator running
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
        raise
    return subprocess.CompletedProcess(argv, proc.returncode, stdout, stderr)


def generate_with_command(
    prompt: str, template: str, seed: int = 0, timeout: float | None = COMMAND_TIMEOUT_S, facing: str = "auto"
) -> GenerationResult:
    """Run a user command template (placeholders {prompt} {out} {seed}) that writes a mesh into {out}.

    {out} is an empty folder; the command may write any mesh file there (glb/gltf/vrm/obj/ply).
    The template runs without a shell (``command_argv``); the values are also in the environment
    as T2BS_PROMPT, T2BS_OUT and T2BS_SEED. ``timeout``: seconds (None or 0 = no limit).
    """
    if "{out}" not in template:
        raise UserError("--command must contain {out} (the folder the command writes its mesh into)")
    if timeout is not None and not (timeout >= 0 and np.isfinite(timeout)):
        raise UserError(f"--command-timeout must be a number of seconds >= 0, got {timeout}")
    start = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="t2bs-command-") as tmp:
        out = Path(tmp) / "out"
        out.mkdir()
        argv = command_argv(template, prompt, out, seed)
        env = {**os.environ, "T2BS_PROMPT": prompt, "T2BS_OUT": str(out), "T2BS_SEED": str(int(seed))}
        proc = run_argv(argv, timeout or None, env)
        line = shlex.join(argv)
        if proc.returncode != 0:
            tail = (proc.stderr.strip() or proc.stdout.strip() or "no output").splitlines()[-1]
            raise UserError(f"--command failed with exit code {proc.returncode}: {tail}")
        found = sorted(
            (p for p in out.rglob("*") if p.suffix.lower() in MESH_SUFFIXES),
            key=lambda p: (MESH_SUFFIXES.index(p.suffix.lower()), str(p)),
        )
        if not found:
            raise UserError(f"--command finished but wrote no mesh ({', '.join(MESH_SUFFIXES)}) into {{out}}: {line}")
        result = generate_from_file(found[0], prompt, facing=facing)
    result.info.update(
        {
            "backend": "command",
            "command": template,
            "seed": int(seed),
            "output_file": found[0].name,
            "seconds": round(time.perf_counter() - start, 3),
        }
    )
    return result


# ---------------------------------------------------------------- file


def generate_from_file(path: Path, prompt: str = "", facing: str = "auto") -> GenerationResult:
    """Any mesh the foundation loader reads, moved to the canonical frame."""
    from t2bs.geometry.io import load_mesh

    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: no such mesh file")
    start = time.perf_counter()
    mesh = load_mesh(path)
    if facing == "auto":
        facing = "-z" if path.suffix.lower() == ".vrm" else detect_facing(mesh)
    mesh, transform = normalize(mesh, facing)
    info = {
        "backend": "file",
        "source": str(path),
        "prompt": prompt,
        "facing": facing,
        "transform": transform,
        "vertices": mesh.num_vertices,
        "faces": int(len(mesh.faces)),
        "seconds": round(time.perf_counter() - start, 3),
    }
    return GenerationResult(mesh, info, [])
