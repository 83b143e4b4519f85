"""Media codecs: videos as bytes through PyAV, single images as PNG through OpenCV.

- RGB video: H.264 (libx264, yuv420p) in MP4, lossy but reproducible (same frames, same
  bytes); odd sizes are padded by edge replication and cropped back on decode.
- Masks and depth: FFV1 in Matroska, lossless (``gray`` for uint8, ``gray16le`` for uint16).
- Depth in metres is quantised to uint16 steps of ``unit`` metres (0 = unknown depth).
- Single images: PNG, lossless.

Errors are :class:`MediaError` naming what could not be read.
"""

from __future__ import annotations

import heapq
import io
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path
from typing import Any

import av
import cv2
import numpy as np

DEFAULT_CRF = 18  # H.264 constant rate factor: lower is better quality, 18 is near-transparent
MIN_DEPTH_UNIT_M = 1e-4  # depth quantum in metres (0.1 mm), coarser only for far scenes


class MediaError(ValueError):
    """A video or image could not be encoded or decoded; the message names the input."""


def _pad(frames: np.ndarray, multiple: int) -> np.ndarray:
    """Pad ``(T, H, W, C)`` to multiples of ``multiple`` by repeating the last row/column."""
    pad_h, pad_w = -frames.shape[1] % multiple, -frames.shape[2] % multiple
    if pad_h == 0 and pad_w == 0:
        return frames
    return np.pad(frames, ((0, 0), (0, pad_h), (0, pad_w), (0, 0)), mode="edge")


def encode_rgb_video(frames: np.ndarray, fps: float, crf: int = DEFAULT_CRF) -> bytes:
    """Encode ``(T, H, W, 3)`` uint8 RGB frames as H.264 MP4 bytes (same frames, same bytes).

    Odd sizes are padded to even by edge replication; decode with the true size to crop.
    """
    if frames.ndim != 4 or frames.shape[-1] != 3 or frames.dtype != np.uint8:
        raise MediaError(f"RGB video must be (T, H, W, 3) uint8, got {frames.shape} {frames.dtype}")
    if len(frames) == 0:
        raise MediaError("cannot encode a video with no frames")
    padded = _pad(frames, 2)
    buffer = io.BytesIO()
    # bitexact: no creation time or muxer version in the header.
    with av.open(buffer, mode="w", format="mp4", options={"fflags": "+bitexact"}) as container:
        stream = container.add_stream("libx264", rate=Fraction(fps).limit_denominator(1001))
        stream.width, stream.height = padded.shape[2], padded.shape[1]
        stream.pix_fmt = "yuv420p"
        # cpu-independent: libx264 otherwise picks code paths by the CPU it detects, and the
        # same frames were measured to encode to different bytes from run to run here.
        stream.options = {
            "crf": str(crf),
            "preset": "medium",
            "x264-params": "threads=1:cpu-independent=1",
        }
        stream.codec_context.thread_count = 1
        for index, image in enumerate(padded):
            frame = av.VideoFrame.from_ndarray(image, format="rgb24")
            frame.pts = index
            for packet in stream.encode(frame):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)
    return buffer.getvalue()


def _decode(data: bytes | str | Path, fmt: str, what: str) -> list[np.ndarray]:
    try:
        source = io.BytesIO(data) if isinstance(data, bytes) else str(data)
        with av.open(source, mode="r") as container:
            stream = container.streams.video[0]
            stream.thread_type = "AUTO"
            return [frame.to_ndarray(format=fmt) for frame in container.decode(stream)]
    except (av.error.FFmpegError, IndexError, OSError) as exc:
        raise MediaError(f"cannot decode {what}: {exc}") from exc


def decode_rgb_video(
    data: bytes, height: int | None = None, width: int | None = None, what: str = "video"
) -> np.ndarray:
    """Decode H.264 bytes to ``(T, H, W, 3)`` uint8 RGB, cropped to ``height x width`` if given."""
    frames = _decode(data, "rgb24", what)
    if not frames:
        raise MediaError(f"{what} holds no frames")
    out = np.stack(frames)
    return out[:, : height or out.shape[1], : width or out.shape[2]]


def encode_lossless_video(frames: np.ndarray) -> bytes:
    """Encode ``(T, H, W)`` uint8 or uint16 frames losslessly (FFV1 in Matroska)."""
    if frames.ndim != 3 or frames.dtype not in (np.uint8, np.uint16) or len(frames) == 0:
        raise MediaError(
            f"lossless video must be non-empty (T, H, W) uint8/uint16, got "
            f"{frames.shape} {frames.dtype}"
        )
    pix_fmt = "gray" if frames.dtype == np.uint8 else "gray16le"
    buffer = io.BytesIO()
    with av.open(buffer, mode="w", format="matroska", options={"fflags": "+bitexact"}) as container:
        stream = container.add_stream("ffv1", rate=1)
        stream.width, stream.height = frames.shape[2], frames.shape[1]
        stream.pix_fmt = pix_fmt
        for image in frames:
            frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(image), format=pix_fmt)
            for packet in stream.encode(frame):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)
    return buffer.getvalue()


def decode_lossless_video(
    data: bytes, what: str = "lossless video", max_frames: int | None = None
) -> np.ndarray:
    """Decode FFV1 bytes to ``(T, H, W)`` uint8 or uint16, exactly as encoded.

    ``max_frames`` stops after that many frames (e.g. 1 for a clip's first-frame mask or depth).
    """
    frames: list[np.ndarray] = []
    try:
        with av.open(io.BytesIO(data), mode="r") as container:
            stream = container.streams.video[0]
            fmt = "gray16le" if stream.codec_context.pix_fmt == "gray16le" else "gray"
            for frame in container.decode(stream):
                frames.append(frame.to_ndarray(format=fmt))
                if max_frames is not None and len(frames) >= max_frames:
                    break
    except (av.error.FFmpegError, IndexError, OSError) as exc:
        raise MediaError(f"cannot decode {what}: {exc}") from exc
    if not frames:
        raise MediaError(f"{what} holds no frames")
    return np.stack(frames)


def encode_mask_video(mask: np.ndarray) -> bytes:
    """Encode a ``(T, H, W)`` mask or label video (uint8 values kept exactly)."""
    return encode_lossless_video(np.asarray(mask, dtype=np.uint8))


def depth_unit_for(depth: np.ndarray) -> float:
    """The depth quantum (metres per uint16 step) that fits ``depth``'s largest finite value."""
    finite = depth[np.isfinite(depth)]
    max_depth = float(finite.max()) if finite.size else 0.0
    return max(MIN_DEPTH_UNIT_M, max_depth / 65535.0)


def encode_depth_video(depth: np.ndarray, unit: float) -> bytes:
    """Quantise ``(T, H, W)`` metres to uint16 steps of ``unit`` and encode losslessly.

    Non-finite or non-positive depth becomes 0 (unknown). Raises if a value does not fit.
    """
    depth = np.asarray(depth, dtype=np.float64)
    steps = np.where(np.isfinite(depth) & (depth > 0), np.round(depth / unit), 0.0)
    if steps.max(initial=0.0) > 65535:
        raise MediaError(f"depth up to {depth[np.isfinite(depth)].max():.2f} m exceeds unit {unit}")
    return encode_lossless_video(steps.astype(np.uint16))


def decode_depth_video(
    data: bytes, unit: float, what: str = "depth video", max_frames: int | None = None
) -> np.ndarray:
    """Decode depth bytes to ``(T, H, W)`` float32 metres (0 = unknown)."""
    return (decode_lossless_video(data, what, max_frames).astype(np.float64) * unit).astype(
        np.float32
    )


def encode_png(image: np.ndarray) -> bytes:
    """Encode an RGB ``(H, W, 3)`` or grey ``(H, W)`` uint8/uint16 image as PNG bytes."""
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
    ok, buf = cv2.imencode(".png", image)
    if not ok:
        raise MediaError(f"cannot encode image of shape {image.shape} as PNG")
    return buf.tobytes()


def decode_png(data: bytes, what: str = "image") -> np.ndarray:
    """Decode PNG bytes to RGB ``(H, W, 3)`` or grey ``(H, W)``, keeping the bit depth."""
    image = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise MediaError(f"cannot decode {what} as an image")
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
    return image


@dataclass(frozen=True)
class VideoFileInfo:
    """What a video file says about itself before decoding."""

    path: Path  # the file
    fps: float  # average frame rate the container declares
    num_frames: int  # frame count the container declares (0 if unknown)
    width: int  # displayed frame width in pixels (after the display rotation)
    height: int  # displayed frame height in pixels (after the display rotation)
    rotation: int = 0  # display rotation, degrees counterclockwise (0, 90, 180 or -90)
    start_s: float = 0.0  # the stream's first timestamp, seconds (0 when it declares none)
    duration_s: float = 0.0  # the stream's declared duration, else the container's, seconds
    # (0 when neither is declared)


def _quarter_turns(rotation: float) -> int:
    """``rotation`` degrees (counterclockwise, from the display matrix) as quarter turns."""
    return round(rotation / 90.0) % 4


def _seconds(value: int | None, time_base: Fraction | None) -> float:
    """``value`` ticks of ``time_base`` in seconds; 0 when either is unknown."""
    return float(value * time_base) if value is not None and time_base else 0.0


def probe_video_file(path: Path) -> VideoFileInfo:
    """Read a video file's frame rate, displayed size, rotation, declared frame count, and the
    video stream's declared start and duration.

    Decodes the first frame only (the display rotation travels with decoded frames). Raises
    :class:`MediaError` naming the real reason: no video stream (and what streams there are),
    no frame rate, no decodable frame, or an unreadable file.
    """
    try:
        with av.open(str(path), mode="r") as container:
            if not container.streams.video:
                kinds = sorted({s.type for s in container.streams}) or ["none"]
                raise MediaError(f"{path}: no video stream (streams: {', '.join(kinds)})")
            stream = container.streams.video[0]
            rate = stream.average_rate or stream.guessed_rate
            if not rate:
                raise MediaError(f"{path}: video declares no frame rate")
            first = next(iter(container.decode(stream)), None)
            if first is None:
                raise MediaError(f"{path}: video stream holds no decodable frame")
            turns = _quarter_turns(getattr(first, "rotation", 0) or 0)
            width, height = first.width, first.height
            if turns % 2:
                width, height = height, width
            return VideoFileInfo(
                path=Path(path),
                fps=float(rate),
                num_frames=int(stream.frames or 0),
                width=width,
                height=height,
                rotation=[0, 90, 180, -90][turns],
                start_s=_seconds(stream.start_time, stream.time_base),
                duration_s=_seconds(stream.duration, stream.time_base)
                or (container.duration or 0) / av.time_base,
            )
    except (av.error.FFmpegError, OSError) as exc:
        raise MediaError(f"cannot read video file {path}: {exc}") from exc


# Decoded frames whose container timestamps may come in decode order, not presentation order
# (AVI stores no presentation times: with B-frames its decoded frames carry shuffled stamps).
# The stamps of this many consecutive frames are sorted back onto them (H.264 reorders at most
# 16 frames; x264's B-pyramid 4).
REORDER_DEPTH = 16


def _presentation_times(frames: Iterator[av.VideoFrame]) -> Iterator[tuple[float | None, Any]]:
    """``(time in seconds or None, frame)`` of decoded ``frames`` (presentation order), each
    given the smallest timestamp still unused among the next :data:`REORDER_DEPTH` frames.

    Where a container's timestamps increase (MP4, MOV, MKV, WebM, TS) this is each frame's own;
    where they come in decode order (AVI with B-frames: 0.05, 0.2, 0.15, 0.25, 0.1, ...) the
    sorted stamps belong to the frames in the order they are shown. Frames without a timestamp
    get None (the caller falls back to the rate).
    """
    pending: deque[av.VideoFrame] = deque()  # frames decoded, not yet given out
    stamps: list[float] = []  # heap of the pending frames' timestamps
    for frame in frames:
        pending.append(frame)
        if frame.time is not None:
            heapq.heappush(stamps, float(frame.time))
        if len(pending) > REORDER_DEPTH:
            out = pending.popleft()
            yield (heapq.heappop(stamps) if out.time is not None else None), out
    while pending:
        out = pending.popleft()
        yield (heapq.heappop(stamps) if out.time is not None else None), out


def iter_video_file(path: Path, start: float = 0.0) -> Iterator[tuple[float, np.ndarray]]:
    """Stream ``(time in seconds, (H, W, 3) uint8 RGB)`` from a video file, one frame at a time.

    Times are the frames' presentation timestamps (put back in increasing order where the
    container gives them in decode order, see :func:`_presentation_times`); frames without a
    usable timestamp get ``index / fps``. The display rotation of the file (its display matrix)
    is applied, so frames come out upright. ``start`` > 0 seeks to the keyframe at or before
    ``start`` seconds and decodes from there (frames before ``start`` minus half a frame are
    skipped), so reading the end of a long file does not decode all of it; after a seek every
    frame must carry a timestamp. Raises :class:`MediaError` naming the file when it cannot be
    opened or decoding fails part way (frames already yielded stand). Up to
    ``REORDER_DEPTH + 1`` decoded frames are held at a time, for the reordering of their stamps.
    """
    info = probe_video_file(path)
    last = -np.inf
    try:
        with av.open(str(path), mode="r") as container:
            stream = container.streams.video[0]
            stream.thread_type = "AUTO"
            if start > 0 and stream.time_base is not None:
                # backward=True (default): land on the keyframe at or before the target
                container.seek(int(start / stream.time_base), stream=stream)
            decoded = _presentation_times(container.decode(stream))
            for index, (stamp, frame) in enumerate(decoded):
                if start > 0:
                    if stamp is None:
                        raise MediaError(f"cannot seek in video file {path}: no frame timestamps")
                    if stamp < start - 0.5 / info.fps:
                        continue
                time = stamp if stamp is not None else index / info.fps
                if not time > last:  # broken or repeated timestamps: fall back to the rate
                    time = last + 1.0 / info.fps
                last = time
                image = frame.to_ndarray(format="rgb24")
                turns = _quarter_turns(getattr(frame, "rotation", 0) or 0)
                if turns:  # np.rot90 turns counterclockwise, like the display matrix angle
                    image = np.ascontiguousarray(np.rot90(image, k=turns))
                yield time, image
    except (av.error.FFmpegError, OSError) as exc:
        raise MediaError(f"cannot decode video file {path}: {exc}") from exc


def read_video_file(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Decode a whole video file: ``(frames (T, H, W, 3) uint8 RGB, timestamps (T,) seconds)``.

    Timestamps start at 0. Raises :class:`MediaError` for unreadable, truncated or empty files.
    """
    pairs = list(iter_video_file(path))
    if not pairs:
        raise MediaError(f"video file {path} holds no decodable frames")
    stamps = np.array([t for t, _ in pairs], dtype=np.float64)
    return np.stack([f for _, f in pairs]), stamps - stamps[0]


def write_video_file(path: Path, frames: np.ndarray, fps: float, crf: int = DEFAULT_CRF) -> None:
    """Write ``(T, H, W, 3)`` uint8 RGB frames to an H.264 MP4 file."""
    Path(path).write_bytes(encode_rgb_video(frames, fps, crf))
