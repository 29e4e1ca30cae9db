"""SimConfig: every parameter of the simulation bridge, with its default and thesis value.

Pure (no ROS imports). The node declares these as ROS parameters with
``comper_msgs_py.ros_params.declare_config(node, SimConfig)``; tests and benchmarks build it with
``comper_msgs_py.params.config_from_dict(SimConfig, {...})`` or ``SimConfig(...)``.
"""
from __future__ import annotations

from dataclasses import dataclass

from comper_msgs_py.params import param

__all__ = ["SimConfig", "EPISODE_END_RULES", "episode_over"]

EPISODE_END_RULES = ("standard", "truncation_only", "termination_only")


def episode_over(rule: str, terminated: bool, truncated: bool) -> bool:
    """Whether a step ends the episode under an episode end rule (only terminated masks the
    bootstrap, whatever the rule; ALE's game over ends it in any case: SimBridge)."""
    if rule == "truncation_only":
        return bool(truncated)
    if rule == "termination_only":
        return bool(terminated)
    return bool(terminated or truncated)


@dataclass(frozen=True)
class SimConfig:
    env_id: str = param(
        "Hopper-v4",
        "gymnasium environment id: MuJoCo (Hopper-v4, Walker2d-v4, ...), classic control "
        "(Pendulum-v1, MountainCarContinuous-v0) or an ALE game (ALE/Freeway-v5, ...)",
        thesis="chapter 6 MuJoCo -v4 tasks, Pendulum-v1, MountainCarContinuous-v0; chapter 5 Atari games")
    seed: int = param(
        0, "seed of the first reset (a Reset request with seed >= 0 reseeds); -1: unseeded (not reproducible)",
        minimum=-1)
    episode_end: str = param(
        "standard",
        "which signal ends an episode: standard (terminated or truncated), truncation_only (a terminal "
        "state does not end it, the time limit does), termination_only (the time limit does not end it). "
        "terminated and truncated are always reported as the environment gives them. An ALE game over "
        "always ends the episode (the emulator cannot continue)",
        thesis="two series, ending on truncation only and on termination only (method.md 6.3)",
        choices=EPISODE_END_RULES,
        deviation="standard is the default; the thesis's two series are the other two values")
    max_episode_steps: int = param(
        0, "time limit in agent steps: 0 keeps the environment's registered limit (Hopper-v4: 1000; ALE: "
        "none, see max_episode_frames), > 0 overrides it, -1 removes it", minimum=-1)
    action_out_of_range: str = param(
        "error", "what to do with a continuous action outside the Box bounds: error (refuse the request) "
        "or clip (clip to the bounds)", choices=("error", "clip"))
    run_id: str = param("", "run id written into TransitionBatch.run_id and EpisodeSummary.run_id")
    # --- ALE protocol (Machado et al. 2018; method.md section 5) ---------------------------------
    preprocessing: str = param(
        "standard",
        "ALE observation pipeline: standard (average of the last two frames of the skip, luminance, "
        "obs_size x obs_size area resize, uint8) or none (luminance of the last frame, 210x160, uint8). "
        "Vector tasks always give the raw observation as float32",
        thesis="colour averaging, luminance, 84x84 (section 5.1; Machado et al. 2018)",
        choices=("standard", "none"))
    frame_pooling: str = param(
        "average", "ALE, preprocessing standard: how the last two frames of the skip combine before the resize: "
        "average (colour averaging; luminance is linear in RGB) or max (per-pixel maximum of the two luminance "
        "frames, the 'frame pooling' of Mnih et al. 2015)",
        thesis="colour averaging for COMPER (Table 34), frame pooling (max) for DQN (Table 35)",
        choices=("average", "max"))
    frame_stack: int = param(
        1, "ALE: frames per observation; 1 gives [84, 84], 4 gives [4, 84, 84] (oldest first)",
        thesis="a single frame by default; a stack of 4 for the DQN-style agents", minimum=1, maximum=16)
    frame_skip: int = param(
        5, "ALE: emulator frames per agent step (the action repeats; rewards are summed)",
        thesis="5 (Machado et al. 2018)", minimum=1)
    repeat_action_probability: float = param(
        0.25, "ALE: sticky actions, the probability that the emulator repeats the previous action at each frame",
        thesis="0.25 (Machado et al. 2018)", minimum=0.0, maximum=1.0)
    full_action_space: bool = param(
        True, "ALE: the full action set of 18 for every game (false: the game's minimal set)",
        thesis="full action set of 18 (Machado et al. 2018)")
    obs_size: int = param(84, "ALE: side of the square resized frame (preprocessing standard)",
                          thesis="84", minimum=8, maximum=210)
    max_episode_frames: int = param(
        108_000, "ALE: frame cap of one episode, counting skipped frames (ale-py v5 default, 30 min of play); "
        "reaching it reports truncated; 0: no cap", minimum=0)

    @property
    def is_atari(self) -> bool:
        return self.env_id.startswith("ALE/")
