"""``calstation reconstruct``: a recording + H → a PLY point cloud in the platter frame D."""

from __future__ import annotations

from pathlib import Path

import typer


def register(app: typer.Typer) -> None:
    """Add the ``reconstruct`` command."""

    @app.command("reconstruct")
    def reconstruct_cmd(
        recordings: list[Path] = typer.Argument(
            ..., help="MCAP recordings (spin scans) of one object: their clouds are merged.",
            metavar="RECORDING...", show_default=False,
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
        """Reconstruct RECORDINGs into one point cloud in frame D (metres) and write it as PLY.

        Each point's platter angle is interpolated from the encoder at the point's own time.
        Give exactly one of --calibration or --truth. A calibration that estimated the
        lidar–encoder time offset (encoder_latency_s) replaces the recordings' configured encoder
        latency, so that scans taken at other speeds, or turning the other way, fit together.
        """
        import numpy as np
        from rich.console import Console

        from calstation.atomic import check_output
        from calstation.engine.reconstruct import reconstruct
        from calstation.errors import RecordingError
        from calstation.quiet import stdout_to_stderr
        from calstation.recordings.files import (
            load_calibration_file,
            load_range_model,
            write_ply,
        )
        from calstation.recordings.reader import read_recording

        if (calibration is None) == (truth is None):
            raise typer.BadParameter("give exactly one of --calibration FILE or --truth FILE")
        check_output(out, "PLY file")  # refused before the recordings are read
        source = "calibration" if calibration is not None else "truth"
        h_path = calibration if calibration is not None else truth
        assert h_path is not None
        H, latency = load_calibration_file(h_path, source=source)
        ranges = load_range_model(h_path, source=source)
        console = Console(stderr=True)
        clouds, lines, truncated = [], 0, []
        for path in recordings:
            with console.status(f"reading {path}"):
                rec = read_recording(path)
            if latency is not None and latency != rec.encoder_latency_s:
                console.print(
                    f"{path}: encoder latency {latency * 1e3:.3f} ms from {h_path} "
                    f"(the recording says {rec.encoder_latency_s * 1e3:.3f} ms)"
                )
            with console.status(f"reconstructing {rec.n_points:,} points"), stdout_to_stderr():
                clouds.append(reconstruct(rec, H, latency, ranges))
            lines += rec.n_lines
            if rec.truncated:
                truncated.append(str(path))
        points = np.concatenate(clouds)
        if len(points) == 0:
            whose = "its" if len(recordings) == 1 else "their"
            raise RecordingError(
                f"{', '.join(map(str, recordings))}: none of {whose} {lines:,} lines holds a "
                f"valid return: nothing to reconstruct, {out} not written"
            )
        with console.status(f"writing {out}"), stdout_to_stderr():
            write_ply(out, points)
        note = (f" ({', '.join(truncated)} truncated: read up to the last complete chunk)"
                if truncated else "")
        typer.echo(
            f"wrote {len(points):,} points (frame D, metres) from {lines:,} lines "
            f"to {out}{note}"
        )
