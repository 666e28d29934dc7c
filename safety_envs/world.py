"""MJCF assembly: floor, robot, task objects, light and cameras (docs/safety_envs.md).

The model is compiled once per env with every object of the task; :mod:`safety_envs.engine` moves the objects at
reset instead of recompiling: the goal, buttons, hazards and pillars are mocap bodies (fixed in the world, placed
through ``data.mocap_pos``), the box and vases are free bodies (placed through their joint's qpos), and each gremlin
is a free cube welded to a mocap body that the engine moves along the gremlin's circle.
"""

import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np

from safety_envs.tasks import RobotSpec, TaskSpec

ROBOTS_DIR = Path(__file__).parent / "robots"

# Geom groups, as Safety-Gym's: the vision camera renders groups 0-5.
GROUP_GOAL = 0
GROUP_BOX = 1
GROUP_BUTTON = 1
GROUP_PILLAR = 2
GROUP_HAZARD = 3
GROUP_VASE = 4
GROUP_GREMLIN = 5

GOAL_RGBA = "0 1 0 0.25"
HAZARD_RGBA = "0 0 1 0.25"
VASE_RGBA = "0 1 1 1"
BOX_RGBA = "1 1 0 1"
PILLAR_RGBA = "0.5 0.5 1 1"
GREMLIN_RGBA = "0.5 0 1 1"
GREMLIN_GHOST_RGBA = "0.05 0 0.1 0.1"  # Safety-Gym's ghost: the gremlin colour times 0.1
BUTTON_RGBA = np.array([1.0, 0.5, 0.0, 1.0])  # orange
GOAL_BUTTON_RGBA = np.array([0.0, 1.0, 0.0, 1.0])  # green: the goal button in the pixels (spec section 6.4)
GOAL_HEIGHT = 0.16  # centre height of the goal cylinder (m); half-height 0.15
HAZARD_HEIGHT = 0.02  # centre height of the hazard disc (m); half-height 0.01
GREMLIN_WELD_SOLREF = "0.02 1.5"


@dataclass(frozen=True)
class WorldIds:
    """Indices into the compiled model, cached once so that each step does no name lookups."""

    robot_body: int
    robot_qpos: np.ndarray  # qpos addresses of the robot's root joint(s)
    robot_geom_mask: np.ndarray  # (ngeom,) bool: geoms of the robot's body tree
    goal_body: int  # -1 in Button tasks (the goal is a button)
    goal_mocap: int  # index into data.mocap_pos; -1 without a goal body
    box_body: int  # -1 outside Push
    box_qpos: int  # qpos address of the box free joint; -1 outside Push
    button_bodies: np.ndarray  # (n_buttons,)
    button_mocaps: np.ndarray  # (n_buttons,)
    button_geoms: np.ndarray  # (n_buttons,) the sphere of each button
    button_of_geom: np.ndarray  # (ngeom,) int: button index of each geom, -1 for other geoms
    hazard_bodies: np.ndarray  # (n_hazards,)
    hazard_mocaps: np.ndarray  # (n_hazards,)
    vase_bodies: np.ndarray  # (n_vases,)
    vase_qpos: np.ndarray  # (n_vases,) qpos address of each vase free joint
    vase_dof: np.ndarray  # (n_vases,) dof address of each vase free joint
    vase_geom_mask: np.ndarray  # (ngeom,) bool
    pillar_bodies: np.ndarray  # (n_pillars,)
    pillar_mocaps: np.ndarray  # (n_pillars,)
    pillar_geom_mask: np.ndarray  # (ngeom,) bool
    gremlin_bodies: np.ndarray  # (n_gremlins,) the free cubes
    gremlin_qpos: np.ndarray  # (n_gremlins,) qpos address of each cube's free joint
    gremlin_mocaps: np.ndarray  # (n_gremlins,) the mocap body each cube is welded to
    gremlin_geom_mask: np.ndarray  # (ngeom,) bool: the colliding cubes (not the ghosts)
    vision_camera: int
    vision_back_camera: int  # the vision camera turned half a turn about the robot's vertical axis
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
    _add_back_camera(robot_body)
    # Third-person view for render(): 3 m behind (-y) and 4 m above the robot, world-aligned, following it.
    ET.SubElement(robot_body, "camera", name="track", mode="track", pos="0 -3 4", xyaxes="1 0 0 0 0.8 0.6", fovy="60")

    if task.has_goal_body:
        _add_mocap(world, "goal", "cylinder", (task.goal_size, 0.15), GOAL_HEIGHT, GOAL_RGBA, GROUP_GOAL, solid=False)
    if task.name == "Push":
        _add_box(world, task)
    for i in range(task.buttons_num):
        size = (task.buttons_size,)
        _add_mocap(world, f"button{i}", "sphere", size, task.buttons_size, _fmt(BUTTON_RGBA), GROUP_BUTTON)
    for i in range(task.hazards_num):
        size = (task.hazards_size, 0.01)
        _add_mocap(world, f"hazard{i}", "cylinder", size, HAZARD_HEIGHT, HAZARD_RGBA, GROUP_HAZARD, solid=False)
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
    for i in range(task.pillars_num):
        size = (task.pillars_size, task.pillars_height)
        _add_mocap(world, f"pillar{i}", "cylinder", size, task.pillars_height, PILLAR_RGBA, GROUP_PILLAR)
    if task.gremlins_num:
        _add_gremlins(root, world, task)
    return ET.tostring(root, encoding="unicode")


def _add_mocap(
    world: ET.Element, name: str, geom_type: str, size: tuple, height: float, rgba: str, group: int, solid: bool = True
) -> None:
    """
    A static object moved at reset through its mocap body: body and geom ``name``, centre ``height`` m above the floor,
    ``size`` (m) as MuJoCo reads it for ``geom_type``; ``solid=False`` makes it a marker that nothing collides with.
    """
    body = ET.SubElement(world, "body", name=name, mocap="true", pos=_fmt((0, 0, height)))
    contacts = {} if solid else {"contype": "0", "conaffinity": "0"}
    ET.SubElement(body, "geom", name=name, type=geom_type, size=_fmt(size), rgba=rgba, **contacts, group=str(group))


def _add_box(world: ET.Element, task: TaskSpec) -> None:
    """The push box: a free cube of half-size ``box_size`` with four half-width corner posts (spec section 6.3)."""
    size, half = task.box_size, task.box_size / 2
    box = ET.SubElement(world, "body", name="box", pos=_fmt((0, 0, size)))
    ET.SubElement(box, "freejoint", name="box")
    common = {"type": "box", "density": str(task.box_density), "rgba": BOX_RGBA, "group": str(GROUP_BOX)}
    ET.SubElement(box, "geom", name="box", size=_fmt((size, size, size)), **common)
    for k, (sx, sy) in enumerate(((1, 1), (-1, 1), (1, -1), (-1, -1))):
        ET.SubElement(
            box, "geom", name=f"box_corner{k}", pos=_fmt((sx * size, sy * size, 0)), size=_fmt((half, half, size)), **common
        )


def _add_gremlins(root: ET.Element, world: ET.Element, task: TaskSpec) -> None:
    """Gremlins: free cubes ``gremlin{i}obj`` welded (solref 0.02 1.5) to mocap bodies ``gremlin{i}mocap``.

    The weld's relative pose is the identity, so each cube follows its mocap body, which carries a non-colliding
    ghost of the cube; the engine moves the mocap bodies along their circles before every physics substep.
    """
    size = _fmt([task.gremlins_size] * 3)
    equality = ET.SubElement(root, "equality")
    for i in range(task.gremlins_num):
        cube = ET.SubElement(world, "body", name=f"gremlin{i}obj", pos=_fmt((0, 0, task.gremlins_size)))
        ET.SubElement(cube, "freejoint", name=f"gremlin{i}obj")
        ET.SubElement(
            cube,
            "geom",
            name=f"gremlin{i}obj",
            type="box",
            size=size,
            density=str(task.gremlins_density),
            rgba=GREMLIN_RGBA,
            group=str(GROUP_GREMLIN),
        )
        mocap = ET.SubElement(world, "body", name=f"gremlin{i}mocap", mocap="true", pos=_fmt((0, 0, task.gremlins_size)))
        ET.SubElement(
            mocap,
            "geom",
            name=f"gremlin{i}mocap",
            type="box",
            size=size,
            rgba=GREMLIN_GHOST_RGBA,
            contype="0",
            conaffinity="0",
            group=str(GROUP_GREMLIN),
        )
        ET.SubElement(
            equality,
            "weld",
            name=f"gremlin{i}",
            body1=f"gremlin{i}mocap",
            body2=f"gremlin{i}obj",
            relpose="0 0 0 1 0 0 0",
            solref=GREMLIN_WELD_SOLREF,
        )


def _add_back_camera(robot_body: ET.Element) -> None:
    """
    Add ``vision_back`` beside the robot's ``vision`` camera: the same camera turned half a turn about its body's z axis
    (the robot's vertical), so it looks behind the robot from the mirrored mount with the same field of view.
    """
    for parent in robot_body.iter("body"):
        vision = parent.find("camera[@name='vision']")
        if vision is not None:
            break
    else:
        raise ValueError("the robot has no camera named 'vision'")
    half_turn = np.array([-1.0, -1.0, 1.0])  # rotation by pi about z: (x, y, z) -> (-x, -y, z)
    back = ET.SubElement(parent, "camera", name="vision_back")
    back.set("pos", _fmt(np.array(vision.get("pos", "0 0 0").split(), dtype=float) * half_turn))
    xyaxes = np.array(vision.get("xyaxes").split(), dtype=float).reshape(2, 3) * half_turn
    back.set("xyaxes", _fmt(xyaxes.ravel()))
    if vision.get("fovy") is not None:
        back.set("fovy", vision.get("fovy"))


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

    def bodies(fmt: str, num: int) -> np.ndarray:
        return np.array([body(fmt.format(i)) for i in range(num)], dtype=np.int64)

    def qpos(bodies: np.ndarray) -> np.ndarray:
        return model.jnt_qposadr[model.body_jntadr[bodies]].copy()

    robot_body = body("robot")
    robot_geom_mask = np.isin(model.geom_bodyid, _subtree_bodies(model, robot_body))
    root_joints = np.flatnonzero(model.jnt_bodyid == robot_body)
    goal_body = body("goal") if task.has_goal_body else -1
    box_body = body("box") if task.name == "Push" else -1
    button_bodies = bodies("button{}", task.buttons_num)
    button_geoms = model.body_geomadr[button_bodies].copy()
    button_of_geom = np.full(model.ngeom, -1, dtype=np.int64)
    button_of_geom[button_geoms] = np.arange(task.buttons_num)
    hazard_bodies = bodies("hazard{}", task.hazards_num)
    vase_bodies = bodies("vase{}", task.vases_num)
    pillar_bodies = bodies("pillar{}", task.pillars_num)
    gremlin_bodies = bodies("gremlin{}obj", task.gremlins_num)
    ids = WorldIds(
        robot_body=robot_body,
        robot_qpos=model.jnt_qposadr[root_joints].copy(),
        robot_geom_mask=robot_geom_mask,
        goal_body=goal_body,
        goal_mocap=int(model.body_mocapid[goal_body]) if goal_body >= 0 else -1,
        box_body=box_body,
        box_qpos=int(model.jnt_qposadr[model.body_jntadr[box_body]]) if box_body >= 0 else -1,
        button_bodies=button_bodies,
        button_mocaps=model.body_mocapid[button_bodies].copy(),
        button_geoms=button_geoms,
        button_of_geom=button_of_geom,
        hazard_bodies=hazard_bodies,
        hazard_mocaps=model.body_mocapid[hazard_bodies].copy(),
        vase_bodies=vase_bodies,
        vase_qpos=qpos(vase_bodies),
        vase_dof=model.jnt_dofadr[model.body_jntadr[vase_bodies]].copy(),
        vase_geom_mask=np.isin(model.geom_bodyid, vase_bodies),
        pillar_bodies=pillar_bodies,
        pillar_mocaps=model.body_mocapid[pillar_bodies].copy(),
        pillar_geom_mask=np.isin(model.geom_bodyid, pillar_bodies),
        gremlin_bodies=gremlin_bodies,
        gremlin_qpos=qpos(gremlin_bodies),
        gremlin_mocaps=model.body_mocapid[bodies("gremlin{}mocap", task.gremlins_num)].copy(),
        gremlin_geom_mask=np.isin(model.geom_bodyid, gremlin_bodies),
        vision_camera=camera("vision"),
        vision_back_camera=camera("vision_back"),
        track_camera=camera("track"),
    )
    return model, ids
