"""Real videos in the shapes researchers have them: does each come out as clips or a clear reject?

``python -m bench.real_variants [--data ../shared/data] [--out runs/variants] [--only A,B]
[--full] [--workers 1]`` writes variants of the real videos in ``../shared/data`` into
``OUT/inputs`` (re-encoded with PyAV from the real files: other frame rates, sizes, a portrait
frame, an MP4 with a phone's display rotation, an iPhone-like HEVC 10-bit .mov, variable frame
timing, other containers, an audio stream, a greyscale view, a too-short cut, a hand-free cut,
HOT3D and fixed-camera cuts at other offsets, the EPIC-KITCHENS frame folder as it is) and runs
``egosim run`` on each with default settings, in a subprocess (a crash there is reported as a
crash, not taken down with the bench): ``workflows/dataset.yaml`` on the variants whose pictures
differ, ``workflows/ingest.yaml`` alone on those that only change the file (container, codec,
display rotation, audio, frame rate or size of the same pictures), which keeps the bench near
15 minutes; ``--full`` runs the dataset workflow on every variant. A variant holding the same
pictures as another (``same_as``) must ingest to frames within :data:`SAME_MIN_PSNR_DB` of
that one's (as ingest makes them in this process).

It prints per variant: the workflow, exit code, clips ingested -> packed, frames posed by
estimation / all frames and the camera model (dataset runs), the share of frames where the
hands step kept the left / right hand (dataset runs), the first clip's frame count, fps,
size and policy, the PSNR against ``same_as``, seconds and a verdict; then the source region
ingest's crop kept (``source_crop`` of the first clip) and every reject with its step and
reason; ``OUT/real_variants.json`` holds the rows.

Each variant states what a researcher should get (``expect``): ``clips`` (at least one packed
clip, or ingested clip for ingest-only runs, exit 0) or ``reject`` (no clip, exit 3, and a
reject whose reason contains ``reason``). The bench exits 1 when a variant gets something else:
a crash (exit 1, 2 or a signal), a silent nothing (no clip and no reject saying why), or the
wrong one. The variants are cut short (2.2 s: one 33-frame clip at 16 fps).
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path
from typing import Any

import av
import cv2
import numpy as np

from bench.real_video import read_step
from egosim.pipeline import media
from egosim.pipeline.shards import open_shard
from egosim.stages.common.frame_plan import plan_resize

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_DATA = ROOT.parent / "shared" / "data"
WORKFLOW = ROOT / "workflows" / "dataset.yaml"
INGEST_WORKFLOW = ROOT / "workflows" / "ingest.yaml"
# Variants that hold the same pictures as another (other container, codec, rotation metadata)
# must ingest to frames within this PSNR of that one's (two lossy encodes apart).
SAME_MIN_PSNR_DB = 30.0
EGODEX = "egodex_sample/sample.mp4"
DWM = "dwm_realworld/realworld_dynamic/videos/00013.mp4"
POUR = "dwm_realworld/realworld_fixed/pour_coke.mp4"
LIFT = "dwm_realworld/realworld_fixed/lift_tumbler.mp4"
HOT3D = "hot3d_video/ego_centric_aria.mp4"
EPIC = "epic_kitchens_frames"
HOT3D_RGB_X = (427, 853)  # HOT3D's side-by-side recording: the RGB (middle) view, pixels
HOT3D_LEFT_X = (0, 427)  # ... and the left greyscale view
CRF = 18  # H.264 quality of the written variants
FORMATS = {"mkv": "matroska", "mov": "mov", "webm": "webm", "avi": "avi", "mts": "mpegts"}


@dataclass(frozen=True)
class Spec:
    """How to write one variant video from a real one (all optional: a plain re-encode)."""

    start_s: float = 0.0  # first source second kept
    duration_s: float = 0.0  # seconds kept; 0 = to the end
    fps: float = 0.0  # output rate (frames picked nearest in time, repeated when faster); 0 = same
    crop_x: tuple[int, int] = ()  # keep source columns [x0, x1) (one view of a side-by-side file)
    crop_y: tuple[int, int] = ()  # keep source rows [y0, y1)
    aspect: float = 0.0  # centre-crop to this width/height before resizing; 0 = keep
    size: tuple[int, int] = ()  # output (width, height); () = the (cropped) source size
    rotation: int = 0  # display rotation written to the stream (degrees, counterclockwise);
    # the pixels are stored turned the other way, so a player that honours it shows them upright
    vfr: bool = False  # irregular frame times (jitter up to 35% of a frame, some frames dropped)
    container: str = "mp4"  # mp4, mov, mkv, webm (VP9), avi (H.264 with B-frames) or mts (TS)
    audio: bool = False  # add an AAC (Opus in webm) audio stream
    grey: bool = False  # encode as greyscale (pix_fmt gray)
    hevc: bool = False  # encode H.265 Main 10 (yuv420p10le), as phones record, not H.264
    frames: int = 0  # keep only the first N frames after the time cut; 0 = all

    def __post_init__(self) -> None:
        problems = []
        if self.container != "mp4" and self.container not in FORMATS:
            problems.append(
                f"container must be mp4 or one of {sorted(FORMATS)}, got {self.container!r}"
            )
        if self.rotation % 90:
            problems.append(f"rotation must be a multiple of 90 degrees, got {self.rotation}")
        if min(self.start_s, self.duration_s, self.fps, self.aspect, self.frames) < 0:
            problems.append(
                "start_s, duration_s, fps, aspect and frames must be >= 0, got "
                f"{self.start_s}, {self.duration_s}, {self.fps}, {self.aspect}, {self.frames}"
            )
        if problems:
            raise ValueError("Spec: " + "; ".join(problems))


@dataclass(frozen=True)
class Variant:
    """One input a researcher might feed in, and what should come out."""

    name: str  # row label and file stem
    source: str  # path under the data folder
    spec: Spec | None  # how to write the variant; None = use the source as it is
    expect: str  # "clips" (packed clips, exit 0) or "reject" (no clip, exit 3, a reason)
    reason: str = ""  # for "reject": a fragment the reject reason must contain
    note: str = ""  # what the variant checks
    full: bool = True  # run the whole dataset workflow; False: ingest only (unless --full)
    same_as: str = ""  # a variant whose ingested frames these must equal (same pictures)

    def __post_init__(self) -> None:
        problems = []
        if self.expect not in ("clips", "reject"):
            problems.append(f"expect must be 'clips' or 'reject', got {self.expect!r}")
        if self.expect == "reject" and not self.reason:
            problems.append("a 'reject' variant needs the reason fragment its reject must name")
        if problems:
            raise ValueError(f"Variant {self.name!r}: " + "; ".join(problems))


SHORT_S = 2.2  # seconds of most variants: 35 target frames at 16 fps, one 33-frame clip
DWM_S = 4.2  # the DWM clip is 8 fps: 4.2 s hold 34 frames, one 33-frame clip


def _variants() -> tuple[Variant, ...]:
    short = SHORT_S
    fmt = "the same pictures as {} in another file format: ingest only, frames compared"
    return (
        Variant("egodex_ref", EGODEX, Spec(duration_s=short), "clips", note="plain re-encode"),
        Variant(
            "dwm_ref",
            DWM,
            Spec(duration_s=DWM_S),
            "clips",
            note="plain re-encode, 8 fps (ingest only: dwm_24fps runs these pictures through)",
            full=False,
        ),
        *(
            Variant(
                f"egodex_{fps:g}fps",
                EGODEX,
                Spec(duration_s=short, fps=fps),
                "clips",
                note="EgoDex sample re-sampled to another rate (ingest only)",
                full=False,
            )
            for fps in (24.0, 25.0, 60.0)
        ),
        Variant(
            "dwm_24fps",
            DWM,
            Spec(duration_s=short, fps=24.0),
            "clips",
            note="DWM Aria clip (8 fps) re-encoded at 24 fps: each picture repeated 3 times",
        ),
        *(
            Variant(
                f"dwm_{fps:g}fps",
                DWM,
                Spec(duration_s=short, fps=fps),
                "clips",
                note="DWM Aria clip re-encoded at a faster rate, pictures repeated (ingest only)",
                full=False,
            )
            for fps in (25.0, 60.0)
        ),
        Variant(
            "egodex_1280x720",
            EGODEX,
            Spec(duration_s=short, size=(1280, 720)),
            "clips",
            note="720p (ingest only)",
            full=False,
        ),
        Variant(
            "egodex_640x480",
            EGODEX,
            Spec(duration_s=short, aspect=4 / 3, size=(640, 480)),
            "clips",
            note="4:3 frame (ingest only)",
            full=False,
        ),
        Variant(
            "egodex_portrait",
            EGODEX,
            Spec(duration_s=short, aspect=9 / 16, size=(1080, 1920)),
            "clips",
            note="portrait 1080x1920 (a phone held upright)",
        ),
        Variant(
            "egodex_rotated",
            EGODEX,
            Spec(duration_s=short, aspect=9 / 16, size=(1080, 1920), rotation=-90),
            "clips",
            note="portrait stored landscape with a -90 degree display matrix, as phones write",
            full=False,
            same_as="egodex_portrait",
        ),
        Variant(
            "egodex_phone",
            EGODEX,
            Spec(
                duration_s=short,
                aspect=9 / 16,
                size=(1080, 1920),
                rotation=-90,
                container="mov",
                hevc=True,
                audio=True,
            ),
            "clips",
            note="as an iPhone writes: HEVC 10-bit .mov, -90 degree display matrix, AAC audio",
            full=False,
            same_as="egodex_portrait",
        ),
        Variant(
            "egodex_vfr",
            EGODEX,
            Spec(duration_s=short, vfr=True),
            "clips",
            note="variable frame rate: frame times jittered by up to 35%, some frames dropped "
            "(ingest only: after ingest the clip is an ordinary one)",
            full=False,
        ),
        *(
            Variant(
                f"egodex_{c}",
                EGODEX,
                Spec(duration_s=short, container=c),
                "clips",
                note=fmt.format("egodex_ref"),
                full=False,
                same_as="egodex_ref",
            )
            for c in ("mov", "webm", "avi", "mts")
        ),
        Variant(
            "egodex_audio",
            EGODEX,
            Spec(duration_s=short, audio=True),
            "clips",
            note=fmt.format("egodex_ref") + " (an AAC audio stream added)",
            full=False,
            same_as="egodex_ref",
        ),
        Variant(
            "dwm_mkv",
            DWM,
            Spec(duration_s=DWM_S, container="mkv"),
            "clips",
            note=fmt.format("dwm_ref"),
            full=False,
            same_as="dwm_ref",
        ),
        Variant(
            "hot3d_grey",
            HOT3D,
            Spec(start_s=1.0, duration_s=short, crop_x=HOT3D_LEFT_X, grey=True),
            "clips",
            note="HOT3D's left greyscale view, encoded gray",
        ),
        Variant(
            "egodex_20frames",
            EGODEX,
            Spec(frames=20),
            "reject",
            reason="shorter than one clip",
            note="20 frames at 30 fps: below the 33-frame minimum",
        ),
        Variant(
            "pour_coke_no_hands",
            POUR,
            Spec(duration_s=short, crop_x=(0, 860)),
            "reject",
            reason="hand_valid_fraction",
            note="fixed camera, the left part of the table before the hand comes in: no hand, "
            "so pack's quality gate must name the missing hands",
        ),
        Variant(
            "epic_frames",
            EPIC,
            None,
            "reject",
            reason="holds 8 frame(s); the minimum is 33",
            note="8 frames, no frame rate given: must name the frame count and the minimum",
        ),
        Variant(
            "hot3d_rgb_8s",
            HOT3D,
            Spec(start_s=8.0, duration_s=short, crop_x=HOT3D_RGB_X),
            "clips",
            note="HOT3D's RGB view from 8 s",
        ),
        Variant("pour_coke_3s", POUR, Spec(start_s=3.0, duration_s=short), "clips"),
        Variant("lift_tumbler_5s", LIFT, Spec(start_s=5.0, duration_s=short), "clips"),
    )


VARIANTS = _variants()


def _pick_times(times: np.ndarray, spec: Spec) -> tuple[np.ndarray, np.ndarray]:
    """Source frame indices ``(N,)`` of the variant and their output times ``(N,)`` seconds."""
    times = times - times[0]
    end = spec.start_s + spec.duration_s if spec.duration_s else np.inf
    inside = np.flatnonzero((times >= spec.start_s - 1e-6) & (times < end - 1e-6))
    if spec.frames:
        inside = inside[: spec.frames]
    if not spec.fps:
        return inside, times[inside] - times[inside[0]]
    t0, t1 = times[inside[0]], times[inside[-1]]
    out_times = np.arange(0.0, t1 - t0 + 1e-9, 1.0 / spec.fps)  # (N,) output frame times
    nearest = np.abs(times[inside][None, :] - (t0 + out_times)[:, None]).argmin(axis=1)
    return inside[nearest], out_times


def _shape(frame: np.ndarray, spec: Spec) -> np.ndarray:
    """One source ``(H, W, 3)`` frame cropped, centre-cropped to the aspect and resized."""
    if spec.crop_x:
        frame = frame[:, spec.crop_x[0] : spec.crop_x[1]]
    if spec.crop_y:
        frame = frame[spec.crop_y[0] : spec.crop_y[1]]
    if spec.aspect:
        h, w = frame.shape[:2]
        if w / h > spec.aspect:
            cw = round(h * spec.aspect)
            frame = frame[:, (w - cw) // 2 : (w - cw) // 2 + cw]
        else:
            ch = round(w / spec.aspect)
            frame = frame[(h - ch) // 2 : (h - ch) // 2 + ch]
    if spec.size:
        frame = cv2.resize(frame, spec.size, interpolation=cv2.INTER_AREA)
    if frame.shape[0] % 2 or frame.shape[1] % 2:  # yuv420p needs even sizes
        frame = frame[: frame.shape[0] // 2 * 2, : frame.shape[1] // 2 * 2]
    return np.ascontiguousarray(frame)


def _vfr_times(n: int, fps: float, seed: int = 0) -> np.ndarray:
    """``(n,)`` irregular frame times at about ``fps``: jitter and every 7th-ish frame dropped."""
    rng = np.random.default_rng(seed)
    steps = (1.0 + rng.uniform(-0.35, 0.35, n)) / fps
    steps[rng.random(n) < 0.12] *= 2.0  # a dropped frame: a double gap
    steps[0] = 0.0
    return np.cumsum(steps)


def write_variant(src: Path, dst: Path, spec: Spec) -> None:
    """Write the variant of video ``src`` described by ``spec`` to ``dst`` (PyAV)."""
    frames, times = media.read_video_file(src)  # (T, H, W, 3), (T,) seconds
    picks, out_times = _pick_times(times, spec)
    source_fps = (len(times) - 1) / float(times[-1] - times[0])
    fps = spec.fps or source_fps
    if spec.vfr:
        out_times = _vfr_times(len(picks), fps)
    images = [_shape(frames[i], spec) for i in picks]
    turns = round(spec.rotation / 90) % 4
    if turns:  # stored turned back, so that the display rotation makes it upright
        images = [np.ascontiguousarray(np.rot90(im, k=-turns)) for im in images]
    codec = "libx265" if spec.hevc else {"webm": "libvpx-vp9"}.get(spec.container, "libx264")
    fmt = FORMATS.get(spec.container, "mp4")
    rate = Fraction(fps).limit_denominator(1001)
    time_base = Fraction(1, 90000)
    dst.parent.mkdir(parents=True, exist_ok=True)
    # bitexact and one encoder thread: the same variant file on every run (a threaded x264 and
    # the header's creation time changed its bytes, and cameras decided one clip differently)
    with av.open(str(dst), mode="w", format=fmt, options={"fflags": "+bitexact"}) as container:
        stream = container.add_stream(codec, rate=rate)
        stream.codec_context.thread_count = 1
        stream.width, stream.height = images[0].shape[1], images[0].shape[0]
        stream.pix_fmt = "gray" if spec.grey else "yuv420p10le" if spec.hevc else "yuv420p"
        stream.time_base = time_base
        stream.codec_context.time_base = time_base
        if codec == "libx264":
            x264 = "threads=1:cpu-independent=1"
            stream.options = {"crf": str(CRF), "preset": "veryfast", "x264-params": x264}
        elif codec == "libx265":
            stream.options = {
                "crf": str(CRF + 4),
                "preset": "ultrafast",
                "x265-params": "log-level=1:pools=1:frame-threads=1",
            }
        else:
            stream.options = {
                "crf": "32",
                "b": "0",
                "deadline": "realtime",
                "cpu-used": "8",
                "threads": "1",
            }
        if turns:
            stream.set_display_rotation(float(spec.rotation))
        audio = None
        if spec.audio:
            audio = container.add_stream("libopus" if fmt == "webm" else "aac", rate=48000)
        for t, image in zip(out_times, images, strict=True):
            if spec.grey:
                grey = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
                frame = av.VideoFrame.from_ndarray(grey, format="gray")
            else:
                frame = av.VideoFrame.from_ndarray(image, format="rgb24")
            frame.pts = round(t / time_base)
            frame.time_base = time_base
            container.mux(stream.encode(frame))
        container.mux(stream.encode())
        if audio is not None:
            _write_tone(container, audio, float(out_times[-1]) + 1.0 / fps)


def _write_tone(container: Any, audio: Any, seconds: float) -> None:
    """A 440 Hz tone of ``seconds`` on ``audio`` (what a phone's microphone track stands for)."""
    rate, chunk = 48000, 960
    total = int(seconds * rate)
    for start in range(0, total, chunk):
        t = (start + np.arange(chunk)) / rate
        samples = (0.1 * np.sin(2 * np.pi * 440 * t)).astype(np.float32)[None, :]
        frame = av.AudioFrame.from_ndarray(samples, format="fltp", layout="mono")
        frame.sample_rate = rate
        frame.pts = start
        container.mux(audio.encode(frame))
    container.mux(audio.encode())


def variant_input(variant: Variant, data: Path, out: Path) -> Path:
    """The path ``egosim run`` gets for ``variant``: the source itself, or its variant written
    once into ``OUT/inputs/``."""
    if variant.spec is None:
        return data / variant.source
    ext = f".{variant.spec.container}"
    path = out / "inputs" / f"{variant.name}{ext}"
    if not path.is_file():
        tmp = path.with_name(f"tmp-{path.name}")
        write_variant(data / variant.source, tmp, variant.spec)
        tmp.rename(path)
    return path


TIMED_OUT = 124  # exit code recorded for a run stopped at its time limit (as timeout(1) says)


def run_variant(
    source: Path, run: Path, workers: int, full: bool, limit_s: float = 1800.0
) -> tuple[int, float]:
    """``egosim run`` on ``source`` into ``run``, the dataset workflow (``full``, on ``workers``
    local Dask workers) or ingest's alone (in the subprocess, no cluster), with default
    settings: (exit code, seconds). A run still going after ``limit_s`` seconds is stopped with
    its whole process group (its Dask workers too) and gets :data:`TIMED_OUT`, so one hung
    variant does not hang the bench."""
    workflow = WORKFLOW if full else INGEST_WORKFLOW
    cmd = [sys.executable, "-m", "egosim.pipeline.cli", "run", str(workflow)]
    cmd += ["--out", str(run), "--input", str(source)]
    # One ingest task needs no Dask cluster (its start was half of an ingest-only run)
    cmd += ["--workers", str(workers)] if full else ["--scheduler", "here"]
    run.mkdir(parents=True, exist_ok=True)
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    start = time.perf_counter()
    with open(run / "bench.log", "w") as log:
        proc = subprocess.Popen(
            cmd, stdout=log, stderr=subprocess.STDOUT, env=env, cwd=ROOT, start_new_session=True
        )
        try:
            code = proc.wait(timeout=limit_s)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
            code = TIMED_OUT
    return code, time.perf_counter() - start


def _rows(run: Path, step: str, columns: list[str]) -> list[dict[str, Any]]:
    """Rows of every shard of ``step`` in shard order ([] when the step wrote nothing)."""
    return list(read_step(run, step, columns).values())


def ingested_frames(run: Path) -> list[np.ndarray]:
    """The frames ``(T, H, W, 3)`` of every clip the run's ingest step wrote, in shard order."""
    rows = _rows(run, "ingest", ["clip_id", "video", "height", "width"])
    return [
        media.decode_rgb_video(r["video"], int(r["height"]), int(r["width"]), r["clip_id"])
        for r in rows
    ]


def reference_frames(variant: Variant, data: Path, out: Path) -> list[np.ndarray]:
    """The frames ingest makes of ``variant``'s input with default settings (in this process)."""
    from egosim.stages.ingest.stage import IngestConfig, IngestStage

    stage = IngestStage(IngestConfig())
    frames = []
    for unit in stage.list_units(str(variant_input(variant, data, out))):
        for row in stage.process_unit(unit):
            video = row["video"]
            frames.append(media.decode_rgb_video(video, int(row["height"]), int(row["width"])))
    return frames


def psnr_db(a: np.ndarray, b: np.ndarray) -> float:
    """PSNR in dB of two same-shaped uint8 arrays."""
    err = np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)
    return float(10 * np.log10(255.0**2 / max(err, 1e-10)))


def summarise(
    variant: Variant, run: Path, code: int, seconds: float, full: bool, same_db: float | None
) -> dict[str, Any]:
    """The bench row of one variant from what its run left on disk."""
    clips = _rows(
        run,
        "ingest",
        ["clip_id", "num_frames", "fps", "width", "height", "clip_policy", "source_crop"],
    )
    cams = _rows(run, "cameras", ["clip_id", "camera_model", "registered", "num_frames"])
    packed = _rows(run, "pack", ["clip_id"])
    hands = _rows(run, "hands", ["clip_id", "hand_valid"])
    valid = [np.asarray(h["hand_valid"], dtype=bool).reshape(-1, 2) for h in hands]
    kept = np.concatenate(valid) if valid else np.zeros((0, 2), bool)  # (frames, 2) left, right
    rejects: list[str] = []
    if (run / "rejects.parquet").is_file():
        with open_shard(run / "rejects.parquet") as reader:
            rejects = [f"{r['step']}: {r['reason']}" for r in reader.iter_rows()]
    log_tail = ""
    if (run / "bench.log").is_file():
        log_tail = "\n".join((run / "bench.log").read_text(errors="replace").splitlines()[-8:])
    row: dict[str, Any] = {
        "variant": variant.name,
        "note": variant.note,
        "expect": variant.expect,
        "workflow": "dataset" if full else "ingest",
        "exit_code": code,
        "clips_ingested": len(clips),
        "clips_packed": len(packed),
        "clips": [
            f"{c['num_frames']}f@{c['fps']:g} {c['width']}x{c['height']} {c['clip_policy']}"
            for c in clips
        ],
        # the source region (x0, y0, x1, y1 pixels) ingest's crop kept, first clip (None: centre)
        "source_crop": _crop(clips[0].get("source_crop")) if clips else None,
        "camera_models": [c.get("camera_model") or "?" for c in cams],
        "frames_posed": int(sum(int(np.sum(c["registered"])) for c in cams)),
        "frames_total": int(sum(int(c["num_frames"]) for c in cams)),
        "hands_left": float(kept[:, 0].mean()) if len(kept) else None,
        "hands_right": float(kept[:, 1].mean()) if len(kept) else None,
        "same_as": variant.same_as,
        "same_psnr_db": same_db,
        "rejects": rejects,
        "seconds": seconds,
    }
    row["verdict"] = verdict(variant, row)
    if row["verdict"] != "ok":
        row["log_tail"] = log_tail
    return row


def _crop(crop: Any) -> list[float] | None:
    """A clip row's ``source_crop`` rounded to 0.1 px (None for rows without one)."""
    return None if crop is None else [round(float(v), 1) for v in crop]


def verdict(variant: Variant, row: dict[str, Any]) -> str:
    """``ok`` when the variant came out as expected, else what went wrong (see module doc)."""
    code = row["exit_code"]
    if code == TIMED_OUT:
        return "timed out"
    if code not in (0, 3, 4):
        return f"crash (exit {code})"
    made = row["clips_packed"] if row["workflow"] == "dataset" else row["clips_ingested"]
    if variant.expect == "clips":
        if not (made and code == 0):
            if not row["rejects"]:
                return f"silent nothing (exit {code}, no reject)"
            return f"rejected (exit {code})"
        same = row["same_psnr_db"]
        if variant.same_as and (same is None or same < SAME_MIN_PSNR_DB):
            return f"frames differ from {variant.same_as} ({same} dB)"
        return "ok"
    if made:
        return "clips where a reject was expected"
    if code != 3:
        return f"no clip but exit {code} (3 expected)"
    if not any(variant.reason in r for r in row["rejects"]):
        return f"reject does not name {variant.reason!r}"
    return "ok"


def print_table(rows: list[dict[str, Any]]) -> None:
    """One line per variant, then every reject and every unexpected outcome."""
    head = (
        f"{'variant':<19} {'run':<7} {'exit':>4} {'clips':>6} {'posed':>7} {'model':<8} "
        f"{'hands L/R':<9} {'clip':<32} {'same dB':>7} {'s':>4}  verdict"
    )
    print(head)
    print("-" * len(head))
    for r in rows:
        posed = f"{r['frames_posed']}/{r['frames_total']}" if r["frames_total"] else "-"
        models = ",".join(sorted(set(r["camera_models"]))) or "-"
        clip = r["clips"][0] if r["clips"] else "-"
        if len(r["clips"]) > 1:
            clip += f" +{len(r['clips']) - 1}"
        clips = (
            f"{r['clips_ingested']}->{r['clips_packed']}"
            if r["workflow"] == "dataset"
            else (f"{r['clips_ingested']}")
        )
        same = f"{r['same_psnr_db']:.1f}" if r["same_psnr_db"] is not None else "-"
        hands = "-"
        if r.get("hands_left") is not None:
            hands = f"{r['hands_left']:.2f}/{r['hands_right']:.2f}"
        print(
            f"{r['variant']:<19} {r['workflow']:<7} {r['exit_code']:>4} {clips:>6} {posed:>7} "
            f"{models:<8} {hands:<9} {clip:<32} {same:>7} {r['seconds']:>4.0f}  {r['verdict']}"
        )
    crops = [r for r in rows if r.get("source_crop") is not None]
    if crops:  # where each variant's band sits (a changed crop rule shows here first)
        print("source region kept by ingest's crop (x0, y0, x1, y1 source pixels), first clip:")
        for r in crops:
            print(f"  {r['variant']:<19} {tuple(r['source_crop'])}")
    for r in rows:
        for reason in r["rejects"]:
            print(f"{r['variant']}: rejected at {reason[:300]}")
        if r["verdict"] != "ok" and r.get("log_tail"):
            print(f"{r['variant']}: log tail:\n{r['log_tail']}")


def crop_recall(name: str, path: Path, step: int = 2) -> str:
    """How many of the hands of video ``path`` the clip's crop keeps: MediaPipe (per image, at
    the size ingest's crop search uses) on every ``step``-th frame of the whole source frame;
    a hand counts as kept when 11 of its 21 landmarks lie inside the crop's source region. For
    the centre crop and for the crop ingest's default config picks (``crop=hands``), which
    looks at 8 of these frames itself."""
    from egosim.stages.common.hand_landmarks import detect_hand_landmarks
    from egosim.stages.ingest import crop_anchor
    from egosim.stages.ingest.stage import IngestConfig

    cfg = IngestConfig()
    info = media.probe_video_file(path)
    frames, _ = media.read_video_file(path)  # (T, H, W, 3)
    sample = crop_anchor.sample_video(path, info)
    anchor = crop_anchor.choose_anchor(cfg, info.width, info.height, sample, name)
    small = np.stack([crop_anchor.shrink(f) for f in frames[::step]])  # (N, h, w, 3)
    raw = detect_hand_landmarks(small, crop_anchor.DETECT_PARAMS)
    size = np.array([info.width, info.height]) / small.shape[2:0:-1]  # source px per small px
    uv = raw.uv[raw.present] * size  # (K, 21, 2) source pixels
    parts = [f"{name}: {len(uv)} hands on {len(small)} frames"]
    for label, a in (("centre", (0.5, 0.5)), ("ingest", anchor)):
        x0, y0, x1, y1 = plan_resize(info.width, info.height, cfg.width, cfg.height, a).source_crop
        inside = (uv[..., 0] >= x0) & (uv[..., 0] <= x1) & (uv[..., 1] >= y0) & (uv[..., 1] <= y1)
        kept = float((inside.sum(axis=1) >= 11).mean()) if len(uv) else float("nan")
        parts.append(f"{label} anchor ({a[0]:.3f}, {a[1]:.3f}) keeps {kept:.2f}")
    return "; ".join(parts)


def main(argv: list[str] | None = None) -> int:
    """Write and run every variant (or ``--only``); exit 1 when one came out unexpectedly."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA, help="the shared data folder")
    parser.add_argument("--out", type=Path, default=ROOT / "runs" / "variants", help="outputs")
    parser.add_argument(
        "--only", default="", help="variants whose name contains one of these (comma-separated)"
    )
    parser.add_argument("--full", action="store_true", help="dataset workflow on every variant")
    parser.add_argument("--workers", type=int, default=1, help="local Dask workers per run")
    parser.add_argument(
        "--timeout", type=float, default=1800.0, help="seconds before a variant's run is stopped"
    )
    parser.add_argument("--no-run", action="store_true", help="only read existing run folders")
    parser.add_argument("--list", action="store_true", help="list the variants and stop")
    parser.add_argument(
        "--crop-recall",
        action="store_true",
        help="print the share of hands the centre crop and ingest's crop keep per variant, stop",
    )
    args = parser.parse_args(argv)
    wanted = [s for s in args.only.split(",") if s]
    chosen = [v for v in VARIANTS if not wanted or any(s in v.name for s in wanted)]
    by_name = {v.name: v for v in VARIANTS}
    if args.crop_recall:
        for v in chosen:
            if v.spec is not None and (args.data / v.source).exists():
                print(crop_recall(v.name, variant_input(v, args.data, args.out)), flush=True)
        return 0
    if args.list:
        for v in chosen:
            run = "dataset" if v.full else "ingest"
            print(f"{v.name:<19} {run:<7} {v.expect:<7} {v.source}  {v.note}")
        return 0
    rows = []
    refs: dict[str, list[np.ndarray]] = {}  # ingested frames of each same_as variant, made once
    for variant in chosen:
        if not (args.data / variant.source).exists():
            print(f"{variant.name}: {args.data / variant.source} not found, skipped")
            continue
        run = args.out / variant.name
        full = variant.full or args.full
        code, seconds = 0, 0.0
        if args.no_run:
            saved = run / "bench_exit_code"
            code = int(saved.read_text()) if saved.is_file() else 0
        else:
            source = variant_input(variant, args.data, args.out)
            code, seconds = run_variant(source, run, args.workers, full, args.timeout)
            (run / "bench_exit_code").write_text(str(code))
        same_db = None
        if variant.same_as:
            mine = ingested_frames(run)
            if variant.same_as not in refs:
                refs[variant.same_as] = reference_frames(
                    by_name[variant.same_as], args.data, args.out
                )
            ref = refs[variant.same_as]
            if mine and [f.shape for f in mine] == [f.shape for f in ref]:
                same_db = min(psnr_db(a, b) for a, b in zip(mine, ref, strict=True))
        rows.append(summarise(variant, run, code, seconds, full, same_db))
        print(f"{variant.name}: exit {code}, {rows[-1]['verdict']} ({seconds:.0f} s)", flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "real_variants.json").write_text(json.dumps(rows, indent=1))
    print_table(rows)
    return 0 if rows and all(r["verdict"] == "ok" for r in rows) else 1


if __name__ == "__main__":
    raise SystemExit(main())
