"""Trust boundaries and data integrity (issue 11): what data may never do to the machine."""

from __future__ import annotations

import pickle
from pathlib import Path

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from egosim.model.checkpoint import UnsafeCheckpointError, load_tree, save_tree
from egosim.pipeline.cli import app


class _Payload:
    """Unpickling this object creates ``marker`` (stands for any code a pickle can run)."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self) -> tuple:
        return (open, (str(self.marker), "w"))


def _evil_checkpoint(path: Path, marker: Path, zip_format: bool = True) -> Path:
    """A file as torch.save (zip) or plain pickle would write it, carrying the payload."""
    path.parent.mkdir(parents=True, exist_ok=True)
    payload = {"config": {"preset": "tiny"}, "model": {}, "evil": _Payload(marker)}
    if zip_format:
        torch.save(payload, path)
    else:
        path.write_bytes(pickle.dumps(payload, protocol=4))
    assert not marker.exists()
    return path


# --- 1. checkpoints are tensors, never pickles -------------------------------------------------


@pytest.mark.parametrize("zip_format", [True, False])
def test_pickled_checkpoint_is_refused_and_never_run(tmp_path: Path, zip_format: bool) -> None:
    from egosim.model.inference import load_trained

    marker = tmp_path / "PWNED"
    evil = _evil_checkpoint(tmp_path / "evil.pt", marker, zip_format)
    with pytest.raises(UnsafeCheckpointError, match=r"evil\.pt.*pickle"):
        load_trained(evil)
    # Renamed like a real checkpoint inside a run directory: still refused.
    run = tmp_path / "run"
    _evil_checkpoint(run / "checkpoints" / "step_00000001.safetensors", marker, zip_format)
    with pytest.raises(UnsafeCheckpointError, match=r"step_00000001\.safetensors.*pickle"):
        load_trained(run)
    assert not marker.exists()


def test_simulate_cli_refuses_a_pickled_checkpoint(tmp_path: Path) -> None:
    marker = tmp_path / "PWNED"
    evil = _evil_checkpoint(tmp_path / "evil.pt", marker)
    result = CliRunner().invoke(
        app,
        [
            "simulate",
            "--data",
            str(tmp_path),
            "--out",
            str(tmp_path / "o"),
            "--checkpoint",
            str(evil),
        ],
    )
    assert result.exit_code == 2, result.output
    assert "evil.pt" in result.output and "pickle" in result.output
    assert not marker.exists()


def test_run_directory_with_only_legacy_pickles_is_refused(tmp_path: Path) -> None:
    from egosim.model.train import latest_checkpoint

    marker = tmp_path / "PWNED"
    _evil_checkpoint(tmp_path / "checkpoints" / "step_00000002.pt", marker)
    with pytest.raises(UnsafeCheckpointError, match=r"step_00000002\.pt.*--fresh"):
        latest_checkpoint(tmp_path)
    assert not marker.exists()


def test_checkpoint_tree_round_trips_without_pickle(tmp_path: Path) -> None:
    import random

    tree = {
        "step": 3,
        "lr": 1e-4,
        "none": None,
        "flag": True,
        "name": "tiny",
        "betas": (0.9, 0.999),
        "optimizer": {"state": {0: {"step": torch.tensor(2.0), "m": torch.ones(2, 3)}}},
        "numpy_rng": np.random.get_state(),
        "python_rng": random.getstate(),
        "shared": [torch.arange(4)[1:], torch.arange(4)],  # a view and a tensor
    }
    path = tmp_path / "c.safetensors"
    save_tree(path, tree, format_version=7)
    assert path.read_bytes()[:2] not in (b"PK", b"\x80\x04")
    got, version = load_tree(path)
    assert version == 7
    assert got["betas"] == (0.9, 0.999) and got["none"] is None and got["flag"] is True
    assert torch.equal(got["optimizer"]["state"][0]["m"], torch.ones(2, 3))
    assert got["optimizer"]["state"][0]["step"].shape == ()
    assert got["python_rng"] == tree["python_rng"]
    assert got["numpy_rng"][0] == "MT19937"
    assert np.array_equal(got["numpy_rng"][1], tree["numpy_rng"][1])
    assert torch.equal(got["shared"][0], torch.tensor([1, 2, 3]))
    with pytest.raises(TypeError, match="unsupported type"):
        save_tree(tmp_path / "bad.safetensors", {"x": object()})
    (tmp_path / "junk.safetensors").write_bytes(b"\x08\x00\x00\x00\x00\x00\x00\x00{}garbage")
    with pytest.raises(UnsafeCheckpointError, match="junk"):
        load_tree(tmp_path / "junk.safetensors")


# --- 2. identifiers that become paths ----------------------------------------------------------

TRAVERSAL_IDS = ["../../ESCAPED_0", "..", ".hidden", "a/b", "a\\b", "/abs", "-flag", "x" * 129, ""]


@pytest.mark.parametrize("bad", TRAVERSAL_IDS)
def test_identifier_rule_refuses_path_like_ids(bad: str) -> None:
    from egosim.schemas.ids import InvalidIdError, validate_id

    with pytest.raises(InvalidIdError):
        validate_id(bad)


def test_sanitized_ids_are_always_valid() -> None:
    from egosim.schemas.ids import id_problems, sanitize_id

    rng = np.random.default_rng(0)
    alphabet = [*"ab./\\-_ :é\x00", "..", "%2F"]
    texts = [*TRAVERSAL_IDS, "café kitchen", "x.", "_"]
    texts += ["".join(rng.choice(alphabet, size=rng.integers(0, 300))) for _ in range(200)]
    for text in texts:
        for suffix in ("", "-w000", "-w001-3fa9c1e2"):
            out = sanitize_id(text, suffix)
            assert id_problems(out) == [], (text, out)
            assert out.endswith(suffix)
    assert sanitize_id("kitchen_01", "-w000") == "kitchen_01-w000"  # valid names are kept


def test_path_under_refuses_escapes(tmp_path: Path) -> None:
    from egosim.schemas.ids import PathEscapeError, path_under

    assert path_under(tmp_path, "videos", "a.mp4") == tmp_path / "videos" / "a.mp4"
    for parts in (("..", "x"), ("videos", "../../x"), ("/etc/passwd",), ("",)):
        with pytest.raises(PathEscapeError):
            path_under(tmp_path, *parts)
    (tmp_path / "link").symlink_to(tmp_path.parent)
    with pytest.raises(PathEscapeError):
        path_under(tmp_path, "link", "x")


def test_every_schema_refuses_a_traversal_clip_id(tmp_path: Path) -> None:
    from egosim.pipeline.shards import ShardWriter
    from egosim.schemas import CLIPS, SCHEMAS, RowValidationError

    for schema in SCHEMAS.values():
        if "clip_id" in schema.column_names and schema.name != "rejects":
            row = {c: None for c in schema.column_names} | {"clip_id": "../../ESCAPED_0"}
            assert any("clip id" in p for p in schema.row_problems(row)), schema.name
    # The writer every stage uses (ingest included) refuses the row; nothing is written.
    row = {c: None for c in CLIPS.column_names} | {"clip_id": "../x"}
    writer = ShardWriter(tmp_path / "c.parquet", CLIPS, stage="test")
    with pytest.raises(RowValidationError, match="clip id"), writer:
        writer.write_row(row)
    assert list(tmp_path.iterdir()) == []


def test_ingest_makes_valid_ids_unique_across_a_run(tmp_path: Path) -> None:
    from egosim.pipeline.media import write_video_file
    from egosim.schemas import CLIPS
    from egosim.stages.ingest.stage import IngestConfig, IngestStage
    from tests.conftest import smooth_frames

    frames = smooth_frames(8, 32, 48)
    for rel in ("a/x.mp4", "b/x.mp4", "b/X.mp4", "c/..evil name:.mp4", "c/solo.mp4"):
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        write_video_file(tmp_path / rel, frames, fps=8.0)
    stage = IngestStage(IngestConfig(height=32, width=48, num_frames=8, fps=8.0, min_frames=5))
    units = stage.list_units(str(tmp_path))
    ids = []
    for unit in units:
        for row in stage.process_unit(unit):
            CLIPS.validate_row(row)
            ids.append(row["clip_id"])
    assert len(ids) == 5 and len(set(ids)) == 5 and len({i.lower() for i in ids}) == 5, ids
    assert "solo-w000" in ids  # a unique, valid name is kept as it was
    assert any(i.startswith("_evil_name_-w000") for i in ids), ids
    # The tags depend only on the path: listing again gives the same units (same fingerprints).
    assert stage.list_units(str(tmp_path)) == units


def test_workflow_loader_refuses_a_traversal_step_name(tmp_path: Path) -> None:
    from egosim.pipeline.runner import shard_path
    from egosim.pipeline.workflow import WorkflowError, load_workflow
    from egosim.schemas.ids import InvalidIdError

    wf = tmp_path / "wf.yaml"
    wf.write_text("steps:\n  ../../escape_step:\n    stage: ingest\n")
    with pytest.raises(WorkflowError, match=r"step '\.\./\.\./escape_step'.*step name"):
        load_workflow(wf)
    with pytest.raises(InvalidIdError):
        shard_path(tmp_path / "out", "../../escape_step", 0)
    result = CliRunner().invoke(app, ["run", str(wf), "--out", str(tmp_path / "out")])
    assert result.exit_code == 2 and "step name" in result.output
    assert sorted(p.name for p in tmp_path.iterdir()) == ["wf.yaml"]


def _pack_row(clip_id: str) -> dict:
    from egosim.pipeline import media

    t, h, w = 5, 16, 16
    video = np.full((t, h, w, 3), 120, np.uint8)
    return {
        "clip_id": clip_id,
        "num_frames": t,
        "width": w,
        "height": h,
        "fps": 8.0,
        "frame_indices": list(range(t)),
        "intrinsics": [16.0, 16.0, 8.0, 8.0],
        "world_from_cam": None,
        "target_video": media.encode_rgb_video(video, 8.0),
        "scene_video": media.encode_rgb_video(video, 8.0),
        "visible": media.encode_mask_video(np.ones((t, h, w), np.uint8)),
        "skeleton_video": media.encode_rgb_video(video, 8.0),
        "first_frame": media.encode_png(video[0]),
        "first_frame_source": "frame0",
        "hand_mask": None,
        "depth0": None,
        "depth_unit_m": None,
        "prompt": "move",
        "visible_fraction": 1.0,
        "registered_fraction": 1.0,
        "hand_valid_fraction": 1.0,
    }


def _write_unchecked(path: Path, schema, rows: list[dict], stage: str = "pack") -> None:
    """Write a shard as a hostile producer would: egosim metadata, no row validation."""
    import json

    import pyarrow as pa
    import pyarrow.parquet as pq

    from egosim.pipeline.shards import SHARD_META_KEY

    meta = {"schema": schema.name, "schema_version": schema.version, "stage": stage}
    arrow = schema.arrow.with_metadata({**schema.arrow.metadata, SHARD_META_KEY: json.dumps(meta)})
    path.parent.mkdir(parents=True, exist_ok=True)
    pq.write_table(pa.Table.from_pylist(rows, schema=arrow), path)


def test_simulate_and_check_refuse_a_traversal_clip_id(tmp_path: Path) -> None:
    from egosim.schemas import PACK

    data = tmp_path / "data" / "shard-00000.parquet"
    _write_unchecked(data, PACK, [_pack_row("../../ESCAPED_0"), _pack_row("fine-w000")])
    out = tmp_path / "a" / "b" / "out"
    result = CliRunner().invoke(
        app,
        ["simulate", "--data", str(data), "--out", str(out), "--param", "steps=1"],
    )
    assert result.exit_code == 0, result.output
    assert "1 clips, 1 rejected" in result.output
    assert (out / "videos" / "fine-w000.mp4").is_file()
    escaped = [p for p in tmp_path.rglob("*ESCAPED*")]
    assert escaped == []
    result = CliRunner().invoke(app, ["check", str(data)])
    assert result.exit_code == 1 and "clip id '../../ESCAPED_0'" in result.output


# --- 3. integrity: checksums, content hashes, check ---------------------------------------------


def _clips_shard(path: Path, ids: tuple[str, ...] = ("a", "b")) -> Path:
    from egosim.pipeline.clip_io import write_clips
    from tests.conftest import make_clip

    write_clips(path, [make_clip(i, seed=k) for k, i in enumerate(ids)], stage="test")
    return path


def test_shards_carry_page_checksums_and_row_hashes(tmp_path: Path) -> None:
    import pyarrow.parquet as pq

    from egosim.pipeline.shards import CONTENT_KEY, ShardReader

    path = _clips_shard(tmp_path / "s.parquet")
    footer = pq.ParquetFile(path).metadata
    assert CONTENT_KEY in footer.metadata
    with ShardReader(path) as reader:
        assert reader.hashed and len(reader.row_hashes) == 2
        assert len({*reader.row_hashes}) == 2
    # pyarrow finds a page checksum mismatch only when the file has checksums: flip one byte
    # inside the first data page and reading fails even with every hash check turned off.
    first = footer.row_group(0).column(0)
    data = bytearray(path.read_bytes())
    data[first.data_page_offset + first.total_compressed_size - 2] ^= 0xFF
    path.write_bytes(bytes(data))
    with pytest.raises(OSError):
        pq.ParquetFile(path, page_checksum_verification=True).read_row_group(0)


def test_a_changed_value_with_intact_pages_is_caught_on_read(tmp_path: Path) -> None:
    import pyarrow as pa
    import pyarrow.parquet as pq

    from egosim.pipeline.check import check_shard
    from egosim.pipeline.clip_io import read_clips
    from egosim.pipeline.shards import CONTENT_KEY, ContentMismatchError

    path = _clips_shard(tmp_path / "s.parquet")
    table = pq.read_table(path)
    content = pq.ParquetFile(path).metadata.metadata[CONTENT_KEY]
    fps = table.column("fps").to_pylist()
    table = table.set_column(table.schema.get_field_index("fps"), "fps", pa.array([fps[0], 99.0]))
    table = table.replace_schema_metadata({**table.schema.metadata, CONTENT_KEY: content})
    pq.write_table(table, path, row_group_size=1, write_page_checksum=True)
    with pytest.raises(ContentMismatchError, match=r"row 1 \(clip 'b'\)"):
        list(read_clips(path))
    problems = check_shard(path)
    assert len(problems) == 1 and "row 1 (clip 'b') differs" in problems[0]


def test_check_reports_every_problem_of_every_file_without_traceback(tmp_path: Path) -> None:
    import json

    import pyarrow as pa
    import pyarrow.parquet as pq

    from egosim.pipeline.check import check_paths
    from egosim.pipeline.shards import SHARD_META_KEY
    from egosim.schemas import CLIPS

    run = tmp_path / "run" / "ingest"
    _clips_shard(run / "shard-00000.parquet", ("a", "b"))
    _clips_shard(run / "shard-00001.parquet", ("b", "c"))  # 'b' again, in another shard
    (run / "shard-00002.parquet").write_bytes(b"PAR1" + bytes(100) + b"PAR1")
    for raw in (b"\xff\xfe not utf8", b"{not json", b"[1, 2]", json.dumps({"x": 1}).encode()):
        arrow = CLIPS.arrow.with_metadata({**CLIPS.arrow.metadata, SHARD_META_KEY: raw})
        pq.write_table(pa.Table.from_pylist([], schema=arrow), run / f"meta-{len(raw)}.parquet")
    count, problems = check_paths([tmp_path / "run"])
    text = "\n".join(problems)
    assert count == 7
    assert "shard-00001.parquet clip 'b': clip id also in shard-00000.parquet" in text
    assert "shard-00002.parquet: not a readable Parquet shard" in text
    assert sum("provenance metadata" in p for p in problems) == 4, text
    result = CliRunner().invoke(app, ["check", str(tmp_path / "run")])
    assert result.exit_code == 1 and "Traceback" not in result.output
    assert f"checked 7 shard(s): {len(problems)} violation(s)" in result.output


def test_fuzzed_shards_never_crash_check_nor_pass_it_changed(tmp_path: Path) -> None:
    from bench.fuzz_check import fuzz

    result = fuzz(cases=40, seed=3, seconds=4.0, folder=tmp_path)
    assert result.cases >= 5, result.line()
    assert result.crashes == 0 and result.false_accepts == 0, result.examples
    assert result.clean_rejects >= result.cases // 2, result.line()


# --- 4. one run per folder, stale temporaries, damaged outputs recomputed ----------------------


def test_run_lock_stale_temporaries_and_damaged_shards(tmp_path: Path) -> None:
    import yaml

    from egosim.pipeline.check import check_paths
    from egosim.pipeline.execute import run_shard_task
    from egosim.pipeline.media import write_video_file
    from egosim.pipeline.runner import RunLockedError, plan_tasks, run_lock, run_workflow
    from egosim.pipeline.workflow import load_workflow
    from tests.conftest import smooth_frames

    videos = tmp_path / "videos"
    videos.mkdir()
    for i in range(2):
        write_video_file(videos / f"v{i}.mp4", smooth_frames(8, 32, 48, seed=i), fps=8.0)
    params = {"height": 32, "width": 48, "num_frames": 8, "fps": 8.0, "units_per_shard": 1}
    wf_path = tmp_path / "wf.yaml"
    wf_path.write_text(yaml.safe_dump({"steps": {"ingest": {"params": params}}}))
    wf, out = load_workflow(wf_path), tmp_path / "out"
    for task in plan_tasks(wf, str(videos), out):  # the first run, in this process
        run_shard_task(task)
    # A second run on the same folder while one holds it: refused at once, clearly.
    with run_lock(out):
        with pytest.raises(RunLockedError, match=rf"pid {__import__('os').getpid()}"):
            run_workflow(wf, out, source=str(videos), n_workers=1, gpu_workers=0)
        result = CliRunner().invoke(
            app, ["run", str(wf_path), "--out", str(out), "--input", str(videos)]
        )
        assert result.exit_code == 2 and "another egosim run is writing" in result.output
    # A stale temporary and a shard whose video bytes rotted (metadata intact).
    stale = out / "ingest" / "shard-00000.parquet.tmp-deadbeef"
    stale.write_bytes(b"half a shard")
    damaged = out / "ingest" / "shard-00001.parquet"
    video = _column_chunk(damaged, 0, "video")  # its bytes sit in the dictionary page
    data = bytearray(damaged.read_bytes())
    data[(video.dictionary_page_offset + video.data_page_offset) // 2] ^= 0x10
    damaged.write_bytes(bytes(data))
    assert check_paths([damaged])[1]
    summary = run_workflow(wf, out, source=str(videos), n_workers=1, gpu_workers=0)
    skipped = {r.shard_index: r.skipped for r in summary.results}
    assert skipped == {0: True, 1: False}
    assert not stale.exists()
    assert check_paths([out / "ingest"]) == (4, [])


def _column_chunk(path: Path, group: int, name: str):
    """Footer metadata of column ``name`` in row group ``group``."""
    import pyarrow.parquet as pq

    meta = pq.ParquetFile(path).metadata.row_group(group)
    return next(
        meta.column(i) for i in range(meta.num_columns) if meta.column(i).path_in_schema == name
    )


# --- 5. resource bounds of the workflow loader --------------------------------------------------


def test_workflow_loader_bounds_size_and_alias_expansion(tmp_path: Path) -> None:
    import time

    from egosim.pipeline.workflow import MAX_WORKFLOW_BYTES, WorkflowError, load_workflow

    lines = ['a0: &a0 "lol"']
    lines += [f"a{i}: &a{i} [{', '.join([f'*a{i - 1}'] * 9)}]" for i in range(1, 10)]
    lines += ["steps:", "  ingest:", "    params:", "      source: *a9"]
    bomb = tmp_path / "bomb.yaml"
    bomb.write_text("\n".join(lines) + "\n")
    assert bomb.stat().st_size < 1000
    start = time.perf_counter()
    with pytest.raises(WorkflowError, match="nested YAML aliases"):
        load_workflow(bomb)
    assert time.perf_counter() - start < 2.0
    big = tmp_path / "big.yaml"
    big.write_text("steps: {}\n#" + "x" * MAX_WORKFLOW_BYTES)
    with pytest.raises(WorkflowError, match="larger than"):
        load_workflow(big)
    loop = tmp_path / "loop.yaml"
    loop.write_text("steps:\n  ingest:\n    params: &p {source: *p}\n")
    with pytest.raises(WorkflowError):
        load_workflow(loop)


# --- 6. ingest: truncated, rotated, tiny and audio-only files -----------------------------------

INGEST_SMALL = {"height": 32, "width": 48, "num_frames": 8, "fps": 8.0, "min_frames": 5}


def test_truncated_video_is_flagged_after_its_decoded_clips(tmp_path: Path) -> None:
    import av

    from egosim.pipeline.stage import ClipRejected
    from egosim.stages.ingest.stage import IngestConfig
    from egosim.stages.ingest.video_source import read_video_clips
    from tests.conftest import smooth_frames

    path = tmp_path / "long.mp4"
    # The index (moov) first, as streaming-friendly files have it: a cut keeps it whole.
    with av.open(str(path), "w", format="mp4", options={"movflags": "faststart"}) as out:
        stream = out.add_stream("libx264", rate=8)
        stream.width, stream.height, stream.pix_fmt = 48, 32, "yuv420p"
        for frame in smooth_frames(96, 32, 48):
            for packet in stream.encode(av.VideoFrame.from_ndarray(frame, format="rgb24")):
                out.mux(packet)
        for packet in stream.encode():
            out.mux(packet)
    assert len(list(read_video_clips(path, IngestConfig(**INGEST_SMALL)))) == 12
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])  # truncated at 50%
    clips = []
    with pytest.raises(ClipRejected, match=r"truncated: decoded \d+ of the 96 frames"):
        for clip in read_video_clips(path, IngestConfig(**INGEST_SMALL)):
            clips.append(clip)
    assert 0 < len(clips) < 12


def test_rotated_video_comes_out_upright(tmp_path: Path) -> None:
    import struct

    from egosim.pipeline.media import probe_video_file, write_video_file
    from egosim.stages.ingest.stage import IngestConfig
    from egosim.stages.ingest.video_source import read_video_clips

    frames = np.zeros((8, 48, 32, 3), np.uint8)  # upright: portrait, white block at the top
    frames[:, :12] = 255
    stored = np.ascontiguousarray(np.rot90(frames, k=1, axes=(1, 2)))  # as a phone stores it
    path = tmp_path / "phone.mp4"
    write_video_file(path, stored, fps=8.0)
    data = bytearray(path.read_bytes())
    at = data.index(b"tkhd") + 4 + 40  # the track header's display matrix: 90 deg clockwise
    data[at : at + 36] = struct.pack(">9i", 0, 1 << 16, 0, -(1 << 16), 0, 0, 0, 0, 1 << 30)
    path.write_bytes(bytes(data))
    info = probe_video_file(path)
    assert (info.width, info.height, info.rotation) == (32, 48, -90)
    cfg = IngestConfig(**{**INGEST_SMALL, "height": 48, "width": 32})
    (clip,) = read_video_clips(path, cfg)
    top, bottom = clip.frames[0, :10].mean(), clip.frames[0, -20:].mean()
    assert top > 200 and bottom < 50, (top, bottom)


def test_tiny_and_audio_only_files_are_rejected_with_the_reason(tmp_path: Path) -> None:
    import av

    from egosim.pipeline.media import write_video_file
    from egosim.pipeline.stage import ClipRejected
    from egosim.stages.ingest.stage import IngestConfig
    from egosim.stages.ingest.video_source import MIN_SOURCE_SIDE, read_video_clips

    tiny = tmp_path / "tiny.mp4"
    write_video_file(tiny, np.zeros((8, 16, 16, 3), np.uint8), fps=8.0)
    with pytest.raises(ClipRejected, match=f"16x16, smaller than the minimum {MIN_SOURCE_SIDE}"):
        list(read_video_clips(tiny, IngestConfig(**INGEST_SMALL)))
    audio = tmp_path / "voice.m4a"
    with av.open(str(audio), "w") as container:
        stream = container.add_stream("aac", rate=8000)
        frame = av.AudioFrame.from_ndarray(
            np.zeros((1, 1024), np.float32), format="fltp", layout="mono"
        )
        frame.sample_rate = 8000
        for packet in [*stream.encode(frame), *stream.encode()]:
            container.mux(packet)
    with pytest.raises(ClipRejected, match=r"voice\.m4a: no video stream \(streams: audio\)"):
        list(read_video_clips(audio, IngestConfig(**INGEST_SMALL)))
