"""The `t2bs` command: one subcommand per pipeline stage, all reading/writing a project folder.

User mistakes (UserError) print one line and exit with code 2; anything else is a bug and keeps
its traceback.
"""

from __future__ import annotations

import sys

import typer

from t2bs.cli.exits import exit_on_user_error
from t2bs.errors import INTERRUPTED

app = typer.Typer(add_completion=False, no_args_is_help=True, pretty_exceptions_enable=False,
                  help="Text or any character mesh -> animatable blendshape rig (T2Bs).")

# `t2bs bench ...`: benchmarks that reproduce the paper's evaluation (JSON + Markdown).
bench_app = typer.Typer(no_args_is_help=True, help="Benchmarks against ground truth (print JSON).")
app.add_typer(bench_app, name="bench")

# Stage commands. Each module defines a plain function with typer-annotated parameters.
from t2bs.commands_render import render_command  # noqa: E402

app.command("render")(render_command)
# -- more stage commands are registered below, one line each --
from t2bs.recon.commands import reconstruct_command  # noqa: E402

app.command("reconstruct")(reconstruct_command)
from t2bs.blendshapes import commands as _blendshapes  # noqa: E402

app.command("blendshapes")(_blendshapes.blendshapes_command)
from t2bs.retarget import commands as _retarget  # noqa: E402

app.command("landmarks")(_retarget.landmarks_command)
app.command("retarget")(_retarget.retarget_command)
from t2bs.viewer.commands import view_command  # noqa: E402

app.command("view")(view_command)
from t2bs.video.commands import videos_command  # noqa: E402

app.command("videos")(videos_command)
from t2bs.character import commands as _character  # noqa: E402

app.command("character")(_character.character_command)
app.command("gallery")(_character.gallery_command)
from t2bs.pipeline import create_command  # noqa: E402

app.command("create")(create_command)
from t2bs.blendshapes.export_cli import export_command  # noqa: E402

app.command("export")(export_command)

from t2bs.rig.commands import autorig_command  # noqa: E402

app.command("autorig")(autorig_command)
# -- bench subcommands are registered below (bench_app.command("NAME")(fn)), one line each --
from t2bs.eval.bench_raster import bench_raster_command  # noqa: E402

bench_app.command("raster")(bench_raster_command)
from t2bs.eval.bench_vcdgs import bench_vcdgs_command  # noqa: E402

bench_app.command("vcdgs")(bench_vcdgs_command)
from t2bs.eval.bench_blendshapes import bench_blendshapes_command  # noqa: E402
from t2bs.eval.bench_retarget import bench_retarget  # noqa: E402

bench_app.command("blendshapes")(bench_blendshapes_command)
bench_app.command("retarget")(bench_retarget)


def main() -> None:
    try:
        exit_on_user_error(app)  # also prints the interrupted message (typer turns Ctrl-C into exit 130)
    except KeyboardInterrupt:  # Ctrl-C outside typer's call (while importing, while exiting)
        print(INTERRUPTED, file=sys.stderr)
        sys.exit(130)


if __name__ == "__main__":
    main()
