"""The NAO + ball scene: model loading, joint tables, the stance, and the ball's rolling law."""

from __future__ import annotations

import copy
import dataclasses
import functools
from pathlib import Path

import mujoco
import numpy as np

ASSETS = Path(__file__).resolve().parents[3] / "assets" / "nao_mjcf"
SCENE_XML = ASSETS / "scene.xml"

# SimSpark's perceptor names, in SimSpark's order: also the order of the 22 actions.
JOINTS = (
    "hj1", "hj2",
    "laj1", "laj2", "laj3", "laj4",
    "raj1", "raj2", "raj3", "raj4",
    "llj1", "llj2", "llj3", "llj4", "llj5", "llj6",
    "rlj1", "rlj2", "rlj3", "rlj4", "rlj5", "rlj6",
)  # fmt: skip
N_JOINTS = len(JOINTS)

# SimSpark's motor limits (rcssserver3d, hingejoint.rsg / naosoccersim.rb).
MAX_TORQUE = 10.0  # N m
MAX_JOINT_SPEED = 6.1395  # rad/s (351.77 deg/s)

BALL_RADIUS = 0.042
BALL_MASS = 0.026
# A ball counts as resting below this speed (m/s).
BALL_REST_SPEED = 0.05


def _stance_degrees() -> dict[str, float]:
    """A slightly crouched stance: knees bent 40 deg, arms hanging, feet flat."""
    crouch = 20.0
    stance = {name: 0.0 for name in JOINTS}
    for side in "lr":
        stance[f"{side}lj3"] = crouch  # hip pitch, thigh forward
        stance[f"{side}lj4"] = -2.0 * crouch  # knee
        stance[f"{side}lj5"] = crouch  # ankle pitch, keeps the sole flat
        stance[f"{side}aj1"] = -90.0  # arms down
    stance["laj2"] = 8.0  # arms slightly away from the body
    stance["raj2"] = -8.0
    stance["laj4"] = -20.0
    stance["raj4"] = 20.0
    return stance


STANCE = np.deg2rad(np.array([_stance_degrees()[n] for n in JOINTS]))


@dataclasses.dataclass(frozen=True)
class SceneIds:
    """Names resolved once into indices of the compiled model."""

    joint_qpos: np.ndarray  # (22,) qpos addresses of the 22 hinges, SimSpark order
    joint_qvel: np.ndarray  # (22,) qvel addresses
    joint_range: np.ndarray  # (22, 2) radians
    ball_body: int
    ball_qpos: int  # start of the ball's 7 free-joint qpos
    ball_qvel: int  # start of its 6 qvel
    torso_body: int
    l_foot_geom: int
    floor_geom: int
    ball_geom: int
    ball_floor_pair: int


def load_model(path: Path | str = SCENE_XML) -> mujoco.MjModel:
    """The compiled scene (C MuJoCo model); pass it to `mjx.put_model` for MJX."""
    return mujoco.MjModel.from_xml_path(str(path))


@functools.lru_cache(maxsize=1)
def default_timestep() -> float:
    """The scene's own physics step (s), as its MJCF sets it."""
    return float(load_model().opt.timestep)


def scene_ids(model: mujoco.MjModel) -> SceneIds:
    def jid(name: str) -> int:
        i = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, name)
        if i < 0:
            raise ValueError(f"joint {name!r} is missing from the model")
        return i

    jids = [jid(n) for n in JOINTS]
    actuated = [int(model.actuator_trnid[a, 0]) for a in range(model.nu)]
    if actuated != jids:
        raise ValueError("actuators must drive the 22 joints one each, in SimSpark order")
    ball_joint = jid("ball")

    def body(name: str) -> int:
        return mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, name)

    def geom(name: str) -> int:
        return mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, name)

    return SceneIds(
        joint_qpos=np.array([model.jnt_qposadr[j] for j in jids]),
        joint_qvel=np.array([model.jnt_dofadr[j] for j in jids]),
        joint_range=np.array([model.jnt_range[j] for j in jids]),
        ball_body=body("ball"),
        ball_qpos=int(model.jnt_qposadr[ball_joint]),
        ball_qvel=int(model.jnt_dofadr[ball_joint]),
        torso_body=body("torso"),
        l_foot_geom=geom("l_foot"),
        floor_geom=geom("floor"),
        ball_geom=geom("ball"),
        ball_floor_pair=mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_PAIR, "ball_floor"),
    )


def stance_qpos(model: mujoco.MjModel, joints: np.ndarray = STANCE) -> np.ndarray:
    """qpos with the robot standing in `joints` (22,), soles on the floor, ball 0.2 m ahead.

    The torso height is found by forward kinematics so that the lower sole touches z = 0;
    the ball's centre sits 0.2 m ahead of the kicking (left) foot's centre, on the floor.
    """
    ids = scene_ids(model)
    data = mujoco.MjData(model)
    qpos = model.qpos0.copy()
    qpos[ids.joint_qpos] = joints
    qpos[2] = 1.0
    data.qpos[:] = qpos
    mujoco.mj_kinematics(model, data)
    sole_z = []
    for side in ("l_sole", "r_sole"):
        sole_z.append(data.site_xpos[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, side)][2])
    qpos[2] -= min(sole_z)
    data.qpos[:] = qpos
    mujoco.mj_kinematics(model, data)
    foot = data.geom_xpos[ids.l_foot_geom]
    qpos[ids.ball_qpos : ids.ball_qpos + 3] = [foot[0] + 0.2, foot[1], BALL_RADIUS]
    qpos[ids.ball_qpos + 3 : ids.ball_qpos + 7] = [1.0, 0.0, 0.0, 0.0]
    return qpos


def damping_decel_rate(model: mujoco.MjModel) -> float:
    """The design value of c in the ball's rolling law dv/dt = -c v (1/s).

    The ball's free joint has one damping value d on all six dofs. Rolling without slip
    (omega = v / r) the damping force is d v and the damping torque d v / r, which the
    floor's friction turns into d v / r^2 at the contact; both decelerate the ball's rolling
    mass m + I / r^2. So c = d (1 + 1 / r^2) / (m + I / r^2).
    """
    ids = scene_ids(model)
    d = float(model.dof_damping[ids.ball_qvel])
    m = float(model.body_mass[ids.ball_body])
    inertia = float(model.body_inertia[ids.ball_body][0])
    r = float(model.geom_size[ids.ball_geom][0])
    return d * (1.0 + 1.0 / r**2) / (m + inertia / r**2)


@functools.lru_cache(maxsize=8)
def rolling_decel_rate(path: str = str(SCENE_XML), timestep: float | None = None) -> float:
    """c in dv/dt = -c v as the simulator realises it, measured on the ball-only model
    (at `timestep` s, default: the scene's own).

    The soft contact lets the ball sink ~0.15 mm, which shortens its rolling radius and
    makes c about 0.2 % larger than `damping_decel_rate`: over a 16 m roll that is 3 cm,
    too much for a resting point that must be right to a few cm. So we measure it: a ball
    rolling from 2 m/s, the log-speed slope over 10 s.
    """
    model = ball_only_model(path)
    if timestep is not None:
        model = copy.deepcopy(model)  # the cached model is shared
        model.opt.timestep = timestep
    data = mujoco.MjData(model)
    data.qpos[:7] = [0.0, 0.0, BALL_RADIUS, 1.0, 0.0, 0.0, 0.0]
    data.qvel[[0, 4]] = [2.0, 2.0 / BALL_RADIUS]
    steps = int(round(1.0 / model.opt.timestep))
    for _ in range(steps):  # settle into the contact
        mujoco.mj_step(model, data)
    v_start = data.qvel[0]
    for _ in range(10 * steps):
        mujoco.mj_step(model, data)
    return float(np.log(v_start / data.qvel[0]) / 10.0)


@functools.lru_cache(maxsize=4)
def ball_only_model(path: str = str(SCENE_XML)) -> mujoco.MjModel:
    """The scene without the robot: the same ball, floor and ball-floor contact.

    Used to finish a kick: after the kick phase only the ball moves, and this one-body model
    simulates it at a fraction of the cost of the full scene.
    """
    spec = mujoco.MjSpec.from_file(path)
    spec.delete(spec.body("torso"))
    for pair in list(spec.pairs):
        if pair.name != "ball_floor":
            spec.delete(pair)
    return spec.compile()


def stance_command() -> np.ndarray:
    """The 22 joint targets that hold the stance (an action that stands still)."""
    return STANCE.copy()


def mj_data_for(model: mujoco.MjModel) -> mujoco.MjData:
    """A C MuJoCo MjData in the stance, for the viewer, tests and rendering."""
    data = mujoco.MjData(model)
    data.qpos[:] = stance_qpos(model)
    data.ctrl[:] = STANCE
    mujoco.mj_forward(model, data)
    return data
