"""``calstation reconstruct``: a recording + H → a PLY point cloud in the platter frame D."""

from __future__ import annotations

from pathlib import Path

import typer


def register(app: typer.Typer) -> None:
    """Add the ``reconstruct`` command."""

    @app.command("reconstruct")
    def reconstruct_cmd(
        recording: Path = typer.Argument(
            ..., help="An MCAP recording (a spin scan).", metavar="RECORDING", show_default=False
        ),
        calibration: Path | None = typer.Option(
            None,
            "--calibration",
            "-c",
            help="Calibration result (YAML/JSON) with a mapping H: {tx, ty, tz, rx, ry, rz}.",
            show_default=False,
        ),
        truth: Path | None = typer.Option(
            None,
            "--truth",
            help="A simulator truth.json (tx..rz at top level): reconstruct with the true H.",
            show_default=False,
        ),
        out: Path = typer.Option(..., "--out", "-o", help="Output PLY file.", show_default=False),
    ) -> None:
        """Reconstruct RECORDING into a point cloud in frame D (metres) and write it as PLY.

        Each point's platter angle is interpolated from the encoder at the point's own time.
        Give exactly one of --calibration or --truth.
        """
        from rich.console import Console

        from ..errors import RecordingError
        from ..quiet import stdout_to_stderr
        from ..reconstruct import load_extrinsics, reconstruct, write_ply
        from ..recording import read_recording

        if (calibration is None) == (truth is None):
            raise typer.BadParameter("give exactly one of --calibration FILE or --truth FILE")
        source = "calibration" if calibration is not None else "truth"
        h_path = calibration if calibration is not None else truth
        assert h_path is not None
        H = load_extrinsics(h_path, source=source)
        console = Console(stderr=True)
        with console.status(f"reading {recording}"):
            rec = read_recording(recording)
        with console.status(f"reconstructing {rec.n_points:,} points"), stdout_to_stderr():
            points = reconstruct(rec, H)
        if len(points) == 0:
            raise RecordingError(
                f"{recording}: none of its {rec.n_lines:,} lines holds a valid return: nothing "
                f"to reconstruct, {out} not written"
            )
        with console.status(f"writing {out}"), stdout_to_stderr():
            write_ply(out, points)
        note = " (recording truncated: read up to its last complete chunk)" if rec.truncated else ""
        typer.echo(
            f"wrote {len(points):,} points (frame D, metres) from {rec.n_lines:,} lines "
            f"to {out}{note}"
        )
