"""The `t2bs` command: one subcommand per stage, each mapping its flags onto the stage's config and calling
its library function (docs/ARCHITECTURE.md). The only package that imports typer.

User mistakes (UserError) print one line and exit with code 2; anything else is a bug and keeps
its traceback (t2bs.cli.exits).
"""

from __future__ import annotations

import sys

import typer

from t2bs.cli import bench
from t2bs.cli.autorig import autorig_command
from t2bs.cli.blendshapes import blendshapes_command, export_command
from t2bs.cli.character import character_command, gallery_command
from t2bs.cli.create import create_command
from t2bs.cli.exits import exit_on_user_error
from t2bs.cli.reconstruct import reconstruct_command
from t2bs.cli.render import render_command
from t2bs.cli.retarget import landmarks_command, retarget_command
from t2bs.cli.videos import videos_command
from t2bs.cli.view import view_command
from t2bs.errors import INTERRUPTED

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    help="Text or any character mesh -> animatable blendshape rig (T2Bs).",
)

# `t2bs bench ...`: benchmarks that reproduce the paper's evaluation (JSON + Markdown).
bench_app = typer.Typer(no_args_is_help=True, help="Benchmarks against ground truth (print JSON).")
app.add_typer(bench_app, name="bench")

# The order of `t2bs --help`.
for name, command in (
    ("render", render_command),
    ("reconstruct", reconstruct_command),
    ("blendshapes", blendshapes_command),
    ("landmarks", landmarks_command),
    ("retarget", retarget_command),
    ("view", view_command),
    ("videos", videos_command),
    ("character", character_command),
    ("gallery", gallery_command),
    ("create", create_command),
    ("export", export_command),
    ("autorig", autorig_command),
):
    app.command(name)(command)
for name, command in (
    ("raster", bench.bench_raster_command),
    ("vcdgs", bench.bench_vcdgs_command),
    ("blendshapes", bench.bench_blendshapes_command),
    ("retarget", bench.bench_retarget_command),
):
    bench_app.command(name)(command)


def main() -> None:
    try:
        exit_on_user_error(app)  # also prints the interrupted message (typer turns Ctrl-C into exit 130)
    except KeyboardInterrupt:  # Ctrl-C outside typer's call (while importing, while exiting)
        print(INTERRUPTED, file=sys.stderr)
        sys.exit(130)


if __name__ == "__main__":
    main()
