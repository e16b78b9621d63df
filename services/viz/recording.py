"""Rerun recordings on their sinks: the native viewer (spawned), the web viewer (served), an .rrd file.

The only module of :mod:`services.viz` that starts servers, processes or writes files.
"""

from __future__ import annotations

import logging
import os
import shutil
import sys
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable
from urllib.parse import quote

import rerun as rr
import rerun.blueprint as rrb

from services.viz.scene import Record, time_arguments

log = logging.getLogger("fleetslam.viz")

APPLICATION_ID = "fleetslam"


@dataclass
class Outputs:
    """Where a recording goes; ``serve`` is the web viewer's HTTP port."""

    save: str | None = None
    spawn: bool = False
    serve: int | None = None
    grpc_port: int = 9876
    grpc_bind: str = "127.0.0.1"


def web_viewer_url(web_port: int, grpc_port: int) -> str:
    """The address to open in a browser: the served web viewer, told where its data is."""
    return f"http://127.0.0.1:{web_port}/?url={quote(f'rerun+http://127.0.0.1:{grpc_port}/proxy', safe='')}"


def open_recording(outputs: Outputs, blueprint: rrb.Blueprint, name: str) -> tuple[rr.RecordingStream, list[str]]:
    """A recording stream sending to every output; returns it and lines telling the user where to look.

    Raises ValueError (one line) when an output cannot be opened: an unwritable file, no viewer executable.
    """
    recording = rr.RecordingStream(APPLICATION_ID, recording_id=str(uuid.uuid4()))
    recording.send_recording_name(name)
    sinks: list = []
    notes: list[str] = []
    if outputs.save:
        path = Path(outputs.save)
        if path.suffix != ".rrd":
            raise ValueError(f"--save {outputs.save}: a Rerun recording file must end in .rrd")
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            path.touch()
        except OSError as exc:
            raise ValueError(f"cannot write the recording {path}: {exc.strerror}") from None
        sinks.append(rr.FileSink(str(path)))
        notes.append(f"recording to {path} (replay: rerun {path})")
    if outputs.serve is not None:
        server = rr.GrpcServerSink(bind_ip=outputs.grpc_bind, port=outputs.grpc_port)
        sinks.append(server)
        rr.serve_web_viewer(web_port=outputs.serve, open_browser=False, connect_to=server.uri)
        notes.append(f"web viewer: {web_viewer_url(outputs.serve, outputs.grpc_port)}")
    if outputs.spawn:
        if not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
            log.warning("--spawn: no DISPLAY or WAYLAND_DISPLAY: the native viewer may not open (try --serve PORT)")
        beside_python = Path(sys.executable).with_name("rerun")
        viewer = str(beside_python) if beside_python.exists() else shutil.which("rerun")
        if viewer is None:
            raise ValueError("--spawn: the `rerun` viewer executable is not installed (pip install rerun-sdk)")
        port = outputs.grpc_port + 1 if outputs.serve is not None else outputs.grpc_port
        rr.spawn(port=port, connect=False, executable_path=viewer, recording=recording)
        sinks.append(rr.GrpcSink(f"rerun+http://127.0.0.1:{port}/proxy"))
        notes.append(f"native viewer on port {port}")
    recording.set_sinks(*sinks, default_blueprint=blueprint)
    return recording, notes


def log_records(recording: rr.RecordingStream, records: Iterable[Record]) -> int:
    """Log records, each at its own times; returns how many."""
    count = 0
    for record in records:
        if record.static:
            recording.log(record.path, record.archetype, static=True)
        else:
            recording.reset_time()
            for timeline, when in time_arguments(record):
                recording.set_time(timeline, **when)
            recording.log(record.path, record.archetype)
        count += 1
    return count


def close_recording(recording: rr.RecordingStream, timeout_s: float = 10.0) -> None:
    """Flush and close every sink (the .rrd file gets its footer); a viewer that cannot be reached is one line."""
    try:
        recording.flush(timeout_sec=timeout_s)
    except RuntimeError as error:
        log.error("Rerun: not every sink took the data: %s", str(error).splitlines()[0])
    recording.disconnect()


def save_records(path: str, records: Iterable[Record], blueprint: rrb.Blueprint, name: str) -> int:
    """Write records to an .rrd file; returns how many were logged."""
    recording, _ = open_recording(Outputs(save=path), blueprint, name)
    try:
        return log_records(recording, records)
    finally:
        close_recording(recording)


def save_offline_run(path: str, dataset, run, truth: dict, estimator: str, period_s: float) -> None:
    """Write an offline run (``fleetslam run --rerun``) to ``path``; the outcome goes to ``run.extra`` (``rerun``, or
    ``rerun_error``: the run's figures are kept either way)."""
    from services.viz.scene import blueprint, clip_trajectory, offline_records

    infos = {rid: dataset.robots[rid].info for rid in truth.keys() | run.trajectories.keys()}
    ends = [trajectory.stamps[-1] for trajectory in run.trajectories.values() if len(trajectory)]
    if ends:  # the truth of the data the run covered (--duration, or an interrupted run), not of the whole data set
        truth = {rid: clip_trajectory(trajectory, max(ends)) for rid, trajectory in truth.items()}
    records = offline_records(run, truth, infos, estimator, dataset.landmarks, dataset.landmark_ids, period_s)
    try:
        count = save_records(path, records, blueprint(with_stats=False), f"{estimator} on {dataset.name}")
    except (ValueError, OSError) as error:
        log.error("Rerun recording not written: %s", error)
        run.extra["rerun_error"] = str(error)
        return
    log.info("Rerun recording of %d records written to %s (open: rerun %s)", count, path, path)
    run.extra["rerun"] = {"path": path, "records": count}
