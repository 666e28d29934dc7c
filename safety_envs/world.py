"""MJCF assembly: floor, robot, goal, hazards, vases, light and cameras (SAFETY_GYM_SPEC.md sections 1.1, 6.2, 6.3).

The model is compiled once per env with every object of the task; :mod:`safety_envs.engine` moves the objects at
reset instead of recompiling: the goal and hazards are mocap bodies (fixed in the world, placed through
``data.mocap_pos``) and the vases are free bodies (placed through their joint's qpos).
"""

import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np

from safety_envs.tasks import RobotSpec, TaskSpec

ROBOTS_DIR = Path(__file__).parent / "robots"

# Geom groups (SAFETY_GYM_SPEC.md section 6.2): the vision camera renders groups 0-5.
GROUP_GOAL = 0
GROUP_HAZARD = 3
GROUP_VASE = 4

GOAL_RGBA = "0 1 0 0.25"
HAZARD_RGBA = "0 0 1 0.25"
VASE_RGBA = "0 1 1 1"
GOAL_HEIGHT = 0.16  # centre height of the goal cylinder (m); half-height 0.15
HAZARD_HEIGHT = 0.02  # centre height of the hazard disc (m); half-height 0.01


@dataclass(frozen=True)
class WorldIds:
    """Indices into the compiled model, cached once so that each step does no name lookups."""

    robot_body: int
    robot_qpos: np.ndarray  # qpos addresses of the robot's root joint(s)
    robot_geom_mask: np.ndarray  # (ngeom,) bool: geoms of the robot's body tree
    goal_body: int
    goal_mocap: int  # index into data.mocap_pos
    hazard_bodies: np.ndarray  # (n_hazards,)
    hazard_mocaps: np.ndarray  # (n_hazards,)
    vase_bodies: np.ndarray  # (n_vases,)
    vase_qpos: np.ndarray  # (n_vases,) qpos address of each vase free joint
    vase_dof: np.ndarray  # (n_vases,) dof address of each vase free joint
    vase_geom_mask: np.ndarray  # (ngeom,) bool
    vision_camera: int
    track_camera: int


def _fmt(values) -> str:
    return " ".join(f"{v:.6g}" for v in values)


def build_xml(robot: RobotSpec, task: TaskSpec, offscreen_size: tuple[int, int]) -> str:
    """The MJCF text of ``robot`` inside the world of ``task``.

    :param offscreen_size: (width, height) in pixels of the offscreen buffer: the largest image rendered.
    Objects start at the origin; the engine places them at reset.
    """
    root = ET.parse(ROBOTS_DIR / robot.xml).getroot()
    width, height = offscreen_size

    visual = ET.SubElement(root, "visual")
    # Offscreen buffer sized to the largest image, no shadow map: rendering cost scales with both.
    ET.SubElement(visual, "global", offwidth=str(width), offheight=str(height))
    ET.SubElement(visual, "quality", shadowsize="0")

    asset = ET.SubElement(root, "asset")
    ET.SubElement(
        asset,
        "texture",
        name="texplane",
        type="2d",
        builtin="checker",
        width="100",
        height="100",
        rgb1="0.7 0.7 0.7",
        rgb2="0.8 0.8 0.8",
    )
    ET.SubElement(
        asset,
        "material",
        name="MatPlane",
        texture="texplane",
        texrepeat="10 10",
        reflectance="0.1",
        shininess="0.1",
        specular="0.1",
    )

    world = root.find("worldbody")
    assert world is not None, f"{robot.xml} has no worldbody"
    statics = [
        ET.Element("geom", name="floor", type="plane", size="3.5 3.5 0.1", rgba="1 1 1 1", material="MatPlane"),
        ET.Element(
            "light",
            name="light",
            type="directional",
            pos="0 0 0.5",
            dir="0 0 -1",
            diffuse="1 1 1",
            specular="0 0 0",
            castshadow="false",
            cutoff="100",
            exponent="1",
        ),
        ET.Element("camera", name="fixednear", pos="0 -2 2", zaxis="0 -1 1"),
        ET.Element("camera", name="fixedfar", pos="0 -5 5", zaxis="0 -1 1"),
    ]
    for i, element in enumerate(statics):
        world.insert(i, element)

    robot_body = world.find("body[@name='robot']")
    assert robot_body is not None, f"{robot.xml} has no body named 'robot'"
    # Third-person view for render(): 3 m behind (-y) and 4 m above the robot, world-aligned, following it.
    ET.SubElement(robot_body, "camera", name="track", mode="track", pos="0 -3 4", xyaxes="1 0 0 0 0.8 0.6", fovy="60")

    goal = ET.SubElement(world, "body", name="goal", mocap="true", pos=_fmt((0, 0, GOAL_HEIGHT)))
    ET.SubElement(
        goal,
        "geom",
        name="goal",
        type="cylinder",
        size=_fmt((task.goal_size, 0.15)),
        rgba=GOAL_RGBA,
        contype="0",
        conaffinity="0",
        group=str(GROUP_GOAL),
    )
    for i in range(task.hazards_num):
        hazard = ET.SubElement(world, "body", name=f"hazard{i}", mocap="true", pos=_fmt((0, 0, HAZARD_HEIGHT)))
        ET.SubElement(
            hazard,
            "geom",
            name=f"hazard{i}",
            type="cylinder",
            size=_fmt((task.hazards_size, 0.01)),
            rgba=HAZARD_RGBA,
            contype="0",
            conaffinity="0",
            group=str(GROUP_HAZARD),
        )
    for i in range(task.vases_num):
        vase = ET.SubElement(world, "body", name=f"vase{i}", pos=_fmt((0, 0, task.vases_size - task.vases_sink)))
        ET.SubElement(vase, "freejoint", name=f"vase{i}")
        ET.SubElement(
            vase,
            "geom",
            name=f"vase{i}",
            type="box",
            size=_fmt([task.vases_size] * 3),
            density=str(task.vases_density),
            rgba=VASE_RGBA,
            group=str(GROUP_VASE),
        )
    return ET.tostring(root, encoding="unicode")


def _subtree_bodies(model: mujoco.MjModel, root: int) -> np.ndarray:
    """Ids of ``root`` and all its descendants."""
    inside = np.zeros(model.nbody, dtype=bool)
    inside[root] = True
    for body in range(root + 1, model.nbody):  # parents always precede children
        inside[body] = inside[model.body_parentid[body]]
    return np.flatnonzero(inside)


def build_world(robot: RobotSpec, task: TaskSpec, offscreen_size: tuple[int, int]) -> tuple[mujoco.MjModel, WorldIds]:
    """Compile the world of ``task`` with ``robot`` and cache the ids the engine needs."""
    model = mujoco.MjModel.from_xml_string(build_xml(robot, task, offscreen_size))

    def body(name: str) -> int:
        return mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, name)

    def camera(name: str) -> int:
        return mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, name)

    robot_body = body("robot")
    robot_geom_mask = np.isin(model.geom_bodyid, _subtree_bodies(model, robot_body))
    root_joints = np.flatnonzero(model.jnt_bodyid == robot_body)
    hazard_bodies = np.array([body(f"hazard{i}") for i in range(task.hazards_num)], dtype=np.int64)
    vase_bodies = np.array([body(f"vase{i}") for i in range(task.vases_num)], dtype=np.int64)
    vase_joints = model.body_jntadr[vase_bodies] if task.vases_num else np.zeros(0, dtype=np.int64)
    ids = WorldIds(
        robot_body=robot_body,
        robot_qpos=model.jnt_qposadr[root_joints].copy(),
        robot_geom_mask=robot_geom_mask,
        goal_body=body("goal"),
        goal_mocap=int(model.body_mocapid[body("goal")]),
        hazard_bodies=hazard_bodies,
        hazard_mocaps=model.body_mocapid[hazard_bodies].copy(),
        vase_bodies=vase_bodies,
        vase_qpos=model.jnt_qposadr[vase_joints].copy(),
        vase_dof=model.jnt_dofadr[vase_joints].copy(),
        vase_geom_mask=np.isin(model.geom_bodyid, vase_bodies),
        vision_camera=camera("vision"),
        track_camera=camera("track"),
    )
    return model, ids
