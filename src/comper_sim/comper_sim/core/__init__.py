"""Pure core of the simulation bridge (no ROS imports): config, environments, lock-step bridge."""
from .bridge import EnvInfo, EpisodeRecord, SimBridge, SimError, StepManyResult, StepResult
from .config import EPISODE_END_RULES, SimConfig, episode_over
from .envs import AreaResize, AtariEnv, EnvError, SimEnv, VectorEnv, area_resize_matrix, make_env

__all__ = ["SimConfig", "EPISODE_END_RULES", "episode_over", "SimBridge", "SimError", "StepResult", "StepManyResult",
           "EpisodeRecord", "EnvInfo", "make_env", "EnvError", "SimEnv", "VectorEnv", "AtariEnv",
           "area_resize_matrix", "AreaResize"]
