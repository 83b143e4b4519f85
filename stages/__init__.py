"""Built-in stages. Importing this package registers every stage (one line per stage)."""

from egosim.pipeline.stage import register_stage
from egosim.stages.ingest.stage import IngestStage

register_stage(IngestStage)
