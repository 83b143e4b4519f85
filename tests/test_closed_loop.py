"""The closed loop (``egosim simulate --continuous N``) on the synthetic world, oracle generator.

Segment 1 is seed 0's interaction clip (the box moves), segment 2 the camera coming back over
the table along another path (no hands). The loop starts from state 0 (the static video fused:
the world before the interaction) and must end with the box at its new place.
"""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import pytest
from typer.testing import CliRunner

from bench.bench_state_fusion import (
    SMALL,
    _instance_for,
    clip_rows,
    visible_object_points,
)
from egosim.pipeline.cli import app
from egosim.pipeline.clip_io import row_from_clip, write_clips
from egosim.pipeline.runner import IN_PROCESS, run_workflow
from egosim.pipeline.shards import ShardWriter, open_shard
from egosim.pipeline.stage import ConfigError
from egosim.pipeline.workflow import load_workflow
from egosim.schemas import CLIPS, STATE
from egosim.schemas.scene import SCENE_CLOUD, SCENE_RENDER
from egosim.schemas.state import state_for_clip
from egosim.stages.scene_cloud.stage import SceneCloudStage
from egosim.stages.state_fusion.closed_loop import ClosedLoopConfig, run_closed_loop
from egosim.stages.state_fusion.metrics import centroid_error
from egosim.stages.state_fusion.stage import StateFusionStage
from egosim.stages.state_fusion.state_io import state_from_row
from egosim.world import WorldConfig, render_clip
from egosim.world.state_truth import look_back_clip, moved_objects, scene_truth
from tests.conftest import translated

REPO = Path(__file__).resolve().parents[1]
CONFIG = WorldConfig(seed=0, **SMALL)  # 120x208, 17 frames


@pytest.fixture(scope="module")
def loop_inputs(tmp_path_factory) -> dict:
    """State 0 (a ``state`` shard) and the two segments (a ``clips`` shard)."""
    d = tmp_path_factory.mktemp("loop")
    clip = render_clip(CONFIG)
    seg2 = look_back_clip(CONFIG, clip)
    row0 = StateFusionStage().process(clip_rows(clip, static=True))
    with ShardWriter(d / "state0.parquet", STATE, stage="test") as writer:
        writer.write_row(row0)
    write_clips(d / "segments.parquet", [clip, seg2])
    return {"dir": d, "clip": clip, "seg2": seg2, "row0": row0}


def _simulate(out: Path, *args: str):
    return CliRunner().invoke(app, ["simulate", "--out", str(out), *args])


def test_two_segment_oracle_loop_from_the_cli(loop_inputs, tmp_path: Path) -> None:
    """The box stays at its new place after segment 2: measured 4.7 mm (bench segment_two);
    the no-update baseline (state 0) is 10+ cm off."""
    d, clip = loop_inputs["dir"], loop_inputs["clip"]
    result = _simulate(
        tmp_path,
        "--continuous",
        "2",
        "--state",
        str(d / "state0.parquet"),
        "--segments",
        str(d / "segments.parquet"),
    )
    assert result.exit_code == 0, result.output
    states = []
    for k in (1, 2):
        with open_shard(tmp_path / f"state_{k:02d}" / "shard-00000.parquet", STATE) as reader:
            states.append(next(reader.iter_rows()))
        for step, schema in (("clip", CLIPS), ("render", SCENE_RENDER)):
            with open_shard(tmp_path / f"{step}_{k:02d}" / "shard-00000.parquet", schema) as r:
                assert len(list(r.iter_rows())) == 1
    assert (tmp_path / "closed_loop.mp4").stat().st_size > 0
    assert (tmp_path / "initial" / "shard-00000.parquet").is_file()
    row1, row2 = states
    assert row1["previous_clip_id"] == loop_inputs["row0"]["state_clip_id"]
    assert row2["previous_clip_id"] == clip.clip_id
    assert row2["world_frame"] == loop_inputs["row0"]["world_frame"]
    s0, s1, s2 = (state_from_row(r) for r in (loop_inputs["row0"], row1, row2))
    truth = scene_truth(CONFIG, clip.object_poses[-1], clip.world_from_cam)
    (oid,) = moved_objects(clip.object_poses)
    inst, frame = _instance_for(s1, truth.object_points(int(oid)))
    target = visible_object_points(clip, max(frame, 0), int(oid))
    assert centroid_error(s2.instance_points(inst), target) < 0.01
    assert centroid_error(s0.instance_points(inst), target) > 0.08  # no-update baseline


def test_bad_input_is_refused_before_anything_runs(loop_inputs, tmp_path: Path) -> None:
    d, clip = loop_inputs["dir"], loop_inputs["clip"]
    state0 = str(d / "state0.parquet")
    # No segments.
    result = _simulate(tmp_path / "a", "--continuous", "1", "--state", state0)
    assert result.exit_code == 2
    assert "no action segments given" in result.output
    # A count other than --continuous.
    segments = str(d / "segments.parquet")
    result = _simulate(
        tmp_path / "b", "--continuous", "3", "--state", state0, "--segments", segments
    )
    assert result.exit_code == 2
    assert "--continuous 3 but 2 segment(s) given" in result.output
    # A segment from another world frame (its cameras 10 m away from every camera of the state).
    far = dataclasses.replace(clip, world_from_cam=translated(clip.world_from_cam, [10.0, 0, 0]))
    write_clips(tmp_path / "far.parquet", [far])
    result = _simulate(
        tmp_path / "c",
        "--continuous",
        "1",
        "--state",
        state0,
        "--segments",
        str(tmp_path / "far.parquet"),
    )
    assert result.exit_code == 2
    assert "segment 1" in result.output and "another world frame" in result.output
    assert not (tmp_path / "c" / "state_01").exists()
    # A bad config value is quoted.
    result = _simulate(tmp_path / "d", "--continuous", "1", "--state", state0, "--generator", "x")
    assert result.exit_code == 2 and "got 'x'" in result.output
    # Flags of the pack-based simulate that the loop would ignore.
    result = _simulate(tmp_path / "e", "--continuous", "1", "--state", state0, "--data", state0)
    assert result.exit_code == 2 and "takes no ['--data']" in result.output
    with pytest.raises(ConfigError, match="num_segments must be >= 1, got 0"):
        ClosedLoopConfig(num_segments=0)


def test_one_segment_through_the_runner(loop_inputs, tmp_path: Path) -> None:
    """workflows/closed_loop.yaml: segment 1 rendered from state 0 and fused onto it."""
    clip = loop_inputs["clip"]
    write_clips(tmp_path / "segment.parquet", [clip])
    with ShardWriter(tmp_path / "state.parquet", STATE, stage="test") as writer:
        writer.write_row(state_for_clip(loop_inputs["row0"], clip.clip_id))
    workflow = load_workflow(REPO / "workflows" / "closed_loop.yaml")
    inputs = {"segment": [tmp_path / "segment.parquet"], "state": [tmp_path / "state.parquet"]}
    run_workflow(workflow, tmp_path / "run", scheduler=IN_PROCESS, inputs=inputs)
    with open_shard(tmp_path / "run" / "render" / "shard-00000.parquet", SCENE_RENDER) as r:
        assert [row["clip_id"] for row in r.iter_rows()] == [clip.clip_id]
    with open_shard(tmp_path / "run" / "fuse" / "shard-00000.parquet", STATE) as reader:
        (row1,) = list(reader.iter_rows())
    s1 = state_from_row(row1)
    truth = scene_truth(CONFIG, clip.object_poses[-1], clip.world_from_cam)
    (oid,) = moved_objects(clip.object_poses)
    inst, frame = _instance_for(s1, truth.object_points(int(oid)))
    target = visible_object_points(clip, max(frame, 0), int(oid))
    assert centroid_error(s1.instance_points(inst), target) < 0.01  # measured 4.7 mm


def test_loop_starts_from_a_scene_cloud(loop_inputs, tmp_path: Path) -> None:
    """A ``scene_cloud`` shard (the clip's hand-free first frame) as the initial state."""
    clip = loop_inputs["clip"]
    cloud = SceneCloudStage().process({"clips": row_from_clip(clip)})
    with ShardWriter(tmp_path / "cloud.parquet", SCENE_CLOUD, stage="test") as writer:
        writer.write_row(cloud)
    write_clips(tmp_path / "segment.parquet", [clip])
    config = ClosedLoopConfig(num_segments=1)
    result = run_closed_loop(
        tmp_path / "cloud.parquet", [tmp_path / "segment.parquet"], tmp_path / "out", config
    )
    with open_shard(result.states[0], STATE) as reader:
        (row,) = list(reader.iter_rows())
    assert row["world_frame"] == row["previous_clip_id"] == clip.clip_id  # its own cloud before
    with open_shard(tmp_path / "out" / "initial" / "shard-00000.parquet", SCENE_CLOUD) as reader:
        assert len(list(reader.iter_rows())) == 1


MODEL_SIZE = WorldConfig(seed=0, height=64, width=112, num_frames=9)  # tiny model at full pixels


@pytest.fixture(scope="module")
def model_inputs(tmp_path_factory) -> dict:
    """State 0 and one segment at the tiny model's CPU size."""
    d = tmp_path_factory.mktemp("model")
    clip = render_clip(MODEL_SIZE)
    row0 = StateFusionStage().process(clip_rows(clip, static=True))
    with ShardWriter(d / "state0.parquet", STATE, stage="test") as writer:
        writer.write_row(row0)
    write_clips(d / "segment.parquet", [clip])
    return {"dir": d, "clip": clip, "row0": row0}


def test_model_generator_makes_the_segments_clip(model_inputs) -> None:
    """An untrained tiny model: the clip has the segment's frames and size, its action, none of
    the world's ground truth, and a hand mask from the generated frames and the joints."""
    import numpy as np

    from egosim.pipeline import media
    from egosim.pipeline.stage import get_stage
    from egosim.stages.state_fusion.closed_loop import GROUND_TRUTH_COLUMNS, build_generator

    clip = model_inputs["clip"]
    seg = row_from_clip(clip)
    before = state_for_clip(model_inputs["row0"], clip.clip_id)
    render = get_stage("scene_render")().process({"clips": seg, "state": before})
    config = ClosedLoopConfig(generator="model", steps=2, device="cpu")
    out = build_generator(config)(seg, render)
    t, h, w = clip.num_frames, clip.height, clip.width
    video = media.decode_rgb_video(out["video"], h, w)
    assert video.shape == (t, h, w, 3)
    assert not np.array_equal(video, clip.frames)  # generated, not the segment's own video
    assert all(out[c] is None for c in GROUND_TRUTH_COLUMNS if c != "hand_mask")
    assert out["world_from_cam"] == seg["world_from_cam"]  # the action is kept
    mask = media.decode_lossless_video(out["hand_mask"])
    assert mask.shape == (t, h, w) and mask.any()


def test_model_generator_errors_are_clear(model_inputs, tmp_path: Path) -> None:
    """A missing checkpoint names the path; an untrained model's noise gives no depth, so the
    loop stops naming the segment and the reason, never with an unchanged state."""
    from egosim.stages.state_fusion.closed_loop import ClosedLoopError

    d = model_inputs["dir"]
    paths = (d / "state0.parquet", [d / "segment.parquet"])
    missing = tmp_path / "no-such-run"
    config = ClosedLoopConfig(generator="model", checkpoint=str(missing), device="cpu")
    with pytest.raises(ClosedLoopError, match=r"cannot load checkpoint .*no-such-run"):
        run_closed_loop(*paths, tmp_path / "a", config)
    config = ClosedLoopConfig(generator="model", steps=2, device="cpu")
    with pytest.raises(ClosedLoopError, match=r"segment 1 of 1 rejected: .*empty observation"):
        run_closed_loop(*paths, tmp_path / "b", config)
    assert not (tmp_path / "b" / "state_01").exists()


def _run(*args: str):
    return CliRunner().invoke(app, ["run", str(REPO / "workflows" / "closed_loop.yaml"), *args])


def _chain_args(loop_inputs, tmp_path: Path, seg1) -> list[str]:
    """Write segment 1 (``seg1``), the test's segment 2 and state 0 (keyed by the clip); the
    `egosim run` arguments of the two-link chain over them into ``tmp_path / "run"``."""
    write_clips(tmp_path / "seg1.parquet", [seg1])
    write_clips(tmp_path / "seg2.parquet", [loop_inputs["seg2"]])
    with ShardWriter(tmp_path / "state.parquet", STATE, stage="test") as writer:
        writer.write_row(state_for_clip(loop_inputs["row0"], loop_inputs["clip"].clip_id))
    args = ["--out", str(tmp_path / "run"), "--scheduler", "here", "--chain", "segment"]
    args += ["--feed", "state=fuse", "--input-shard", f"state={tmp_path / 'state.parquet'}"]
    for seg in ("seg1", "seg2"):
        args += ["--input-shard", f"segment={tmp_path / f'{seg}.parquet'}"]
    return args


def test_two_segments_chained_through_the_runner(loop_inputs, tmp_path: Path) -> None:
    """`egosim run closed_loop.yaml --chain segment --feed state=fuse`: one run per segment,
    each fed the previous run's state; the box stays at its new place after segment 2 (the
    same figure as the in-process loop, under 1 cm; no update: 10+ cm)."""
    clip, seg2 = loop_inputs["clip"], loop_inputs["seg2"]
    out = tmp_path / "run"
    args = _chain_args(loop_inputs, tmp_path, clip)
    result = _run(*args)
    assert result.exit_code == 0, result.output
    assert len(re.findall(r"link \d: .*: 4 shard tasks \(0 skipped\)", result.output)) == 2
    rows = []
    for k in (1, 2):
        with open_shard(out / f"link-{k:02d}" / "fuse" / "shard-00000.parquet", STATE) as r:
            rows += list(r.iter_rows())
    with open_shard(out / "link-02" / "given" / "state.parquet", STATE) as r:
        (fed,) = list(r.iter_rows())
    assert fed["clip_id"] == seg2.clip_id and fed["state_clip_id"] == clip.clip_id
    row1, row2 = rows
    assert row1["previous_clip_id"] == loop_inputs["row0"]["state_clip_id"]
    assert row2["previous_clip_id"] == clip.clip_id
    s0, s1, s2 = (state_from_row(r) for r in (loop_inputs["row0"], row1, row2))
    truth = scene_truth(CONFIG, clip.object_poses[-1], clip.world_from_cam)
    (oid,) = moved_objects(clip.object_poses)
    inst, frame = _instance_for(s1, truth.object_points(int(oid)))
    target = visible_object_points(clip, max(frame, 0), int(oid))
    assert centroid_error(s2.instance_points(inst), target) < 0.01
    assert centroid_error(s0.instance_points(inst), target) > 0.08  # no-update baseline
    # a second run skips every finished shard of both links
    again = _run(*args)
    assert again.exit_code == 0, again.output
    assert len(re.findall(r"link \d: .*: 4 shard tasks \(4 skipped\)", again.output)) == 2


def test_chained_run_refuses_bad_flags_before_running(loop_inputs, tmp_path: Path) -> None:
    d = loop_inputs["dir"]
    out = ["--out", str(tmp_path / "run"), "--scheduler", "here"]
    state = ["--input-shard", f"state={d / 'state0.parquet'}"]
    segs = ["--input-shard", f"segment={d / 'segments.parquet'}"]
    result = _run(*out, *state, *segs, "--chain", "segment")
    assert result.exit_code == 2 and "--chain and --feed go together" in result.output
    result = _run(*out, *state, *segs, "--chain", "segments", "--feed", "state=render")
    assert result.exit_code == 2
    assert "--chain 'segments' is not an input" in result.output
    assert "step 'render' writes 'scene_render' shards, input 'state' takes 'state'" in (
        result.output
    )
    result = _run(*out, "--input-shard", "state", "--input-shard", f"pack={d}")
    assert result.exit_code == 2
    assert "--input-shard takes NAME=PATH, got 'state'" in result.output
    assert "--input-shard 'pack': the workflow's inputs are ['segment', 'state']" in result.output
    assert not (tmp_path / "run").exists()


def test_a_rejected_link_stops_the_chain_with_the_reason(loop_inputs, tmp_path: Path) -> None:
    """Segment 1 from another world frame (cameras 10 m away): its fuse step rejects it, so
    link 2 has no state; the chain stops naming the link and the reason (never the old state
    passed on)."""
    clip = loop_inputs["clip"]
    far = dataclasses.replace(clip, world_from_cam=translated(clip.world_from_cam, [10.0, 0, 0]))
    out = tmp_path / "run"
    result = _run(*_chain_args(loop_inputs, tmp_path, far))
    assert result.exit_code == 2, result.output
    assert "link 1" in result.output and "wrote no row to feed link 2" in result.output
    assert "no overlap in camera poses" in result.output
    assert not (out / "link-02").exists()


def test_oracle_video_generator_returns_only_the_video(loop_inputs) -> None:
    """The perfect-model generator: the segment's frames, no ground-truth column, and a hand
    mask made from its frames and joints that covers the true hand mask's pixels mostly."""
    from egosim.pipeline import media
    from egosim.stages.state_fusion.closed_loop import (
        GROUND_TRUTH_COLUMNS,
        oracle_video_generator,
    )

    clip = loop_inputs["clip"]
    segment = row_from_clip(clip)
    out = oracle_video_generator(segment, {})
    assert out["video"] == segment["video"] and out["clip_id"] == clip.clip_id
    assert all(out[c] is None for c in GROUND_TRUTH_COLUMNS if c != "hand_mask")
    t, h, w = clip.num_frames, clip.height, clip.width
    mask = media.decode_lossless_video(out["hand_mask"]) > 0  # (T, H, W)
    truth = clip.hand_mask > 0
    assert mask.shape == (t, h, w)
    assert (mask & truth).sum() > 0.5 * truth.sum()
