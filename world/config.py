"""Configuration of the procedural synthetic world."""

from __future__ import annotations

from dataclasses import dataclass

MODES = ("tabletop", "wild")
VARIANTS = ("default", "alt")  # differently made worlds; see WorldConfig.variant


class WorldConfigError(ValueError):
    """A :class:`WorldConfig` field holds an invalid value; the message quotes every bad value."""


@dataclass(frozen=True)
class WorldConfig:
    """What to render: one seed gives one scene, one camera path and one scripted interaction."""

    seed: int = 0  # seeds every random choice (scene, textures, camera path, interaction)
    mode: str = "tabletop"  # "tabletop": head ~0.6 m above the table, a few cm of motion;
    # "wild": standing head, tens of cm of motion and large yaw sweeps
    height: int = 480  # image height in pixels
    width: int = 832  # image width in pixels
    num_frames: int = 61  # number of frames T
    fps: float = 16.0  # frames per second
    horizontal_fov_deg: float = 75.0  # horizontal FOV of the pinhole camera, degrees ("alt"
    # adds a per-seed offset in [-15, 15] and clips the result to [10, 150])
    articulated: bool = False  # True: the right hand opens a hinged lid instead of moving an object
    variant: str = "default"  # "default": the world the stages were tuned on; "alt": held-out
    # world (ellipsoid hands, sleeved arms with elbows, per-seed FOV, higher steeper head, round
    # table, other objects, colours and textures), for checking stages off their tuning world

    def __post_init__(self) -> None:
        problems: list[str] = []
        if not isinstance(self.seed, int) or isinstance(self.seed, bool) or self.seed < 0:
            problems.append(f"seed must be a non-negative int, got {self.seed!r}")
        if self.mode not in MODES:
            problems.append(f"mode must be one of {MODES}, got {self.mode!r}")
        for name in ("height", "width"):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool) or value < 8:
                problems.append(f"{name} must be an int >= 8, got {value!r}")
        if (
            not isinstance(self.num_frames, int)
            or isinstance(self.num_frames, bool)
            or self.num_frames < 1
        ):
            problems.append(f"num_frames must be >= 1, got {self.num_frames!r}")
        if not isinstance(self.fps, (int, float)) or not (0.0 < float(self.fps) < 1e4):
            problems.append(f"fps must be a positive number, got {self.fps!r}")
        fov = self.horizontal_fov_deg
        if not isinstance(fov, (int, float)) or not (10.0 <= float(fov) <= 150.0):
            problems.append(f"horizontal_fov_deg must be in [10, 150], got {fov!r}")
        if not isinstance(self.articulated, bool):
            problems.append(f"articulated must be a bool, got {self.articulated!r}")
        if self.variant not in VARIANTS:
            problems.append(f"variant must be one of {VARIANTS}, got {self.variant!r}")
        if problems:
            raise WorldConfigError("invalid WorldConfig: " + "; ".join(problems))
