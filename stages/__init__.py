"""Built-in stages. Importing this package registers every stage (one line per stage)."""

from egosim.pipeline.stage import register_stage
from egosim.stages.caption.stage import CaptionStage
from egosim.stages.depth_camera.stage import DepthCameraStage
from egosim.stages.encode.stage import EncodeStage
from egosim.stages.evaluate.stage import EvaluateStage
from egosim.stages.hand_mask.stage import HandMaskStage
from egosim.stages.hands.stage import HandsStage
from egosim.stages.ingest.stage import IngestStage
from egosim.stages.inpaint.stage import InpaintStage
from egosim.stages.keypoint_render.stage import KeypointRenderStage
from egosim.stages.pack.stage import PackStage
from egosim.stages.pose_clean.stage import PoseCleanStage
from egosim.stages.scene_cloud.stage import SceneCloudStage
from egosim.stages.scene_render.stage import SceneRenderStage
from egosim.stages.simulate.stage import SimulateStage
from egosim.stages.state_fusion.stage import StateFusionStage

register_stage(IngestStage)
register_stage(CaptionStage)
register_stage(PoseCleanStage)
register_stage(SceneCloudStage)
register_stage(SceneRenderStage)
register_stage(HandsStage)
register_stage(KeypointRenderStage)
register_stage(HandMaskStage)
register_stage(InpaintStage)
register_stage(DepthCameraStage)
register_stage(PackStage)
register_stage(EncodeStage)
register_stage(SimulateStage)
register_stage(EvaluateStage)
register_stage(StateFusionStage)
