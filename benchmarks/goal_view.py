"""
What a Safety-Gym frame shows, one definition for the benchmarks and the diagnostics: the goal, hazard and vase pixels
of the robot's first-person RGB frames, whether the goal is "in view" (its pixels cover at least ``IN_VIEW_SHARE`` of
the frame), and, from the simulator state, whether the goal's centre lies inside the camera's field of view.

The colour rules were checked against MuJoCo's segmentation rendering of the same scenes (random-policy frames of
PointGoal1, PointGoal2, CarGoal1 and CarGoal2 at 32x32 and 64x64): no pixel of another object or of the floor has its
green channel above both others, so the goal rule has no false positive, and it finds 97-100% of the goal's pixels (it
misses the goal drawn over a hazard, which is blue there). The translucent goal's lit top is bright green, its sides
only faintly (green 5-10 levels above red and blue): a margin of 0.15 (38 levels), used before, found 22-23% of the
goal's pixels on the Point tasks at 32x32 and 61% on CarGoal1. Hazards are blue (at least 10 levels above red and green,
or more: the goal drawn over a hazard is blue-green), vases cyan (green = blue, red at most 16).

The in-view share, 10/4096 of the frame (10 pixels at 64x64, 2.5 at 32x32), is the same solid angle at every frame size:
straight ahead of the Point (fovy 90) the translucent 0.3 m goal covers it out to about 5 m at 32x32 (4 pixels at 5 m,
2 at 6 m) and 4-5 m at 64x64 (16 pixels at 4 m, 8 at 5 m), so inside the 3x3 m (Goal1) and 4x4 m (Goal2) placement
regions it counts the goal wherever it is in front of the camera and not cut by the frame's edge or a vase, and a one-
or two-pixel sliver at 32x32 does not count. ``goal_in_fov`` says how often that agrees with the
geometry (``benchmarks/results/ceiling.md``).
"""

import numpy as np

GOAL_MARGIN = 8  # uint8 levels: green above both red and blue
HAZARD_MARGIN = 8  # uint8 levels: blue above both red and green
VASE_MIN_CYAN = 20  # uint8 levels: green (= blue within 2) above red
IN_VIEW_SHARE = 10 / 4096  # share of the frame's pixels an object covers to be "in view"


def _channels(frames: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(..., 3) uint8 -> its red, green and blue channels as int16 (differences do not wrap)."""
    frames = np.asarray(frames, dtype=np.int16)
    return frames[..., 0], frames[..., 1], frames[..., 2]


def goal_mask(frames: np.ndarray) -> np.ndarray:
    """(..., H, W, 3) uint8 frames -> (..., H, W) bool: the goal's green pixels."""
    red, green, blue = _channels(frames)
    return green >= np.maximum(red, blue) + GOAL_MARGIN


def hazard_mask(frames: np.ndarray) -> np.ndarray:
    """(..., H, W, 3) uint8 frames -> (..., H, W) bool: the hazards' blue pixels."""
    red, green, blue = _channels(frames)
    return blue >= np.maximum(red, green) + HAZARD_MARGIN


def vase_mask(frames: np.ndarray) -> np.ndarray:
    """(..., H, W, 3) uint8 frames -> (..., H, W) bool: the vases' cyan pixels."""
    red, green, blue = _channels(frames)
    return (np.abs(green - blue) <= 2) & (green >= red + VASE_MIN_CYAN)


def object_masks(frames: np.ndarray) -> dict[str, np.ndarray]:
    """(..., H, W, 3) uint8 frames -> boolean (..., H, W) masks of the goal (green) and hazard (blue) pixels."""
    return {"goal": goal_mask(frames), "hazard": hazard_mask(frames)}


def min_pixels(height: int, width: int, min_share: float = IN_VIEW_SHARE) -> float:
    """The pixel count (may be fractional) that ``min_share`` of a ``height`` x ``width`` frame is."""
    return min_share * height * width


def in_view(mask: np.ndarray, min_share: float = IN_VIEW_SHARE) -> np.ndarray:
    """(..., H, W) bool masks -> (...) bool: the mask covers at least ``min_share`` of its frame's pixels."""
    return mask.sum(axis=(-2, -1)) >= min_pixels(*mask.shape[-2:], min_share)


def goal_in_view(frames: np.ndarray, min_share: float = IN_VIEW_SHARE) -> np.ndarray:
    """(..., H, W, 3) uint8 frames -> (...) bool: the goal's pixels cover at least ``min_share`` of the frame."""
    return in_view(goal_mask(frames), min_share)


def goal_in_fov(env) -> bool:
    """
    Whether the goal's centre is inside the horizontal field of view of the robot's ``vision`` camera (or, for an env
    made with ``back_camera=True``, of its ``vision_back`` camera too), from the simulator state: the goal in the
    camera's frame (which looks along its -z) in front of it, at a bearing within half the horizontal field of view
    (fovy times the aspect ratio: Point 90 degrees, Car MuJoCo's default 45). Vertically the goal is always inside the
    frame once it is in front (the camera is pitched down about 22 degrees and the goal is reached before it could leave
    the bottom of the frame), so only the bearing is checked.

    :param env: a ``safety_envs`` Goal env (``SafetyGymEnv``, or a wrapper of one)
    """
    sim = env.unwrapped
    data = sim.data
    cameras = (sim.ids.vision_camera, sim.ids.vision_back_camera) if sim.back_camera else (sim.ids.vision_camera,)
    for camera in cameras:
        offset = data.xpos[sim.ids.goal_body] - data.cam_xpos[camera]
        x, _, z = data.cam_xmat[camera].reshape(3, 3).T @ offset  # world -> camera frame
        half_width = np.tan(np.radians(sim.model.cam_fovy[camera]) / 2) * sim.width / sim.height
        if z < 0 and abs(x) <= -z * half_width:
            return True
    return False
