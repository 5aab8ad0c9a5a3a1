"""gaitscope's task as Gymnasium wrappers, written in Python from the spec (docs/world.md).

Ant-v4 plus a goal at (5, 5), the goal reward, contact-force fatigue with a permanent torque
scale past a threshold, and the 16-step context window folded into the observation. Used by the
fixture generator (tests/fixtures/) and the peer benchmarks (bench/peers/); no gaitscope code is
imported, so these are an independent implementation of the same task.
"""

import warnings
from collections import deque

import gymnasium as gym
import mujoco
import numpy as np

# Ant-v4 is deprecated in favour of v5; v4 is the model and reward gaitscope matches.
warnings.filterwarnings("ignore", message=".*Ant-v4 is out of date.*")

# The task, as GaitConfig's defaults.
GOAL = np.array([5.0, 5.0])
SUCCESS_RADIUS = 1.0
NATIVE_WEIGHT, PROGRESS_WEIGHT, SUCCESS_BONUS = 0.5, 50.0, 200.0
# The fatigue model: f_i += ALPHA*|a_i| + BETA*||cfrc_ext[body_i]||, trigger at THRESHOLD.
ALPHA, BETA, THRESHOLD = 1.0, 0.1, 30.0
SCALES = {"healthy": 1.0, "mild": 0.5, "severe": 0.1}
CONTEXT_LEN = 16


def torso_xy(env):
    """Gymnasium's get_body_com("torso")[:2]: the torso body's xpos."""
    return env.unwrapped.get_body_com("torso")[:2].copy()


class GoalTask(gym.Wrapper):
    """Walk to GOAL: obs gains goal - torso_xy; r = 0.5 r_native + 50 progress + 200 [d < 1]."""

    def __init__(self, env):
        super().__init__(env)
        low = np.concatenate([env.observation_space.low, [-np.inf, -np.inf]])
        self.observation_space = gym.spaces.Box(low, -low, dtype=np.float64)

    def reset(self, **kwargs):
        obs, info = self.env.reset(**kwargs)
        self.distance = np.linalg.norm(GOAL - torso_xy(self.env))
        return self.observe(obs), info

    def observe(self, obs):
        return np.concatenate([obs, GOAL - torso_xy(self.env)])

    def step(self, action):
        obs, native, terminated, truncated, info = self.env.step(action)
        distance = np.linalg.norm(GOAL - torso_xy(self.env))
        success = distance < SUCCESS_RADIUS
        reward = (
            NATIVE_WEIGHT * native
            + PROGRESS_WEIGHT * (self.distance - distance)
            + SUCCESS_BONUS * float(success)
        )
        self.distance = distance
        info["is_success"] = bool(success)
        return self.observe(obs), reward, terminated or success, truncated, info


class Fatigue(gym.Wrapper):
    """The paper's DamageWrapper: fatigue from effort and contact force, a permanent torque
    scale from the step after an actuator's fatigue first reaches the threshold. `condition` is
    one of SCALES, or "random" for a uniform draw at every reset."""

    def __init__(self, env, condition="random"):
        super().__init__(env)
        model = env.unwrapped.model
        # The body each actuator's joint moves: its cfrc_ext is the contact load on that joint.
        self.bodies = [model.jnt_bodyid[model.actuator_trnid[i, 0]] for i in range(model.nu)]
        self.condition = condition

    def reset(self, **kwargs):
        obs, info = self.env.reset(**kwargs)
        n = len(self.bodies)
        self.fatigue = np.zeros(n)
        self.triggered = np.zeros(n, dtype=bool)
        self.scale = np.ones(n)
        condition = self.condition
        if condition == "random":
            condition = list(SCALES)[self.np_random.integers(len(SCALES))]
        self.scale_when_triggered = SCALES[condition]
        return obs, info

    def step(self, action):
        commanded = np.asarray(action, dtype=np.float64)
        applied = self.scale * commanded
        obs, reward, terminated, truncated, info = self.env.step(applied)
        model, data = self.env.unwrapped.model, self.env.unwrapped.data
        # cfrc_ext is only filled on request (Gymnasium 1.x asks already; a second call is a no-op).
        mujoco.mj_rnePostConstraint(model, data)
        contact = np.linalg.norm(data.cfrc_ext[self.bodies], axis=1)
        self.fatigue += ALPHA * np.abs(commanded) + BETA * contact
        newly = ~self.triggered & (self.fatigue >= THRESHOLD)
        self.triggered |= newly
        self.scale[newly] = self.scale_when_triggered
        info["applied_action"] = applied
        return obs, reward, terminated, truncated, info


class FoldedWindow(gym.Wrapper):
    """The paper's ContextHistoryWrapper, folded into the observation: the last CONTEXT_LEN
    (obs, action) pairs, oldest first, zero-padded at the front, then the current observation
    (16 * 37 + 29 = 621 values for the Ant: gaitscope's encoder input layout)."""

    def __init__(self, env, k=CONTEXT_LEN):
        super().__init__(env)
        self.obs_dim = env.observation_space.shape[0]
        self.act_dim = env.action_space.shape[0]
        self.k = k
        n = k * (self.obs_dim + self.act_dim) + self.obs_dim
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (n,), dtype=np.float64)

    def reset(self, **kwargs):
        obs, info = self.env.reset(**kwargs)
        width = self.obs_dim + self.act_dim
        self.history = deque([np.zeros(width)] * self.k, maxlen=self.k)
        self.obs = obs
        return self.fold(), info

    def fold(self):
        return np.concatenate([*self.history, self.obs])

    def step(self, action):
        self.history.append(np.concatenate([self.obs, np.asarray(action, dtype=np.float64)]))
        self.obs, reward, terminated, truncated, info = self.env.step(action)
        return self.fold(), reward, terminated, truncated, info


def make_env(condition="random", window=False, max_episode_steps=1000):
    """The damaged Ant as gaitscope trains on it: ClipAction(Fatigue(GoalTask(Ant-v4))), with the
    folded window outermost for encoder policies."""
    # ClipAction first: gaitscope clips commands to [-1, 1] before damage and fatigue see them.
    env = gym.make("Ant-v4", max_episode_steps=max_episode_steps)
    env = gym.wrappers.ClipAction(Fatigue(GoalTask(env), condition))
    # ClipAction widens the space to (-inf, inf); agents need the Ant's [-1, 1] to squash into.
    env.action_space = env.env.action_space
    return FoldedWindow(env) if window else env
